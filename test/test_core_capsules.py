"""Capsules enclosing the URDF collision geometry (cdmp_ros.core.kinematics.capsules), checked
against the meshes' own vertices, closed forms, and pybullet's closest points."""
import math
import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from cdmp_ros.core.coupling.obstacle import CouplingConfig, ObstacleCoupling
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
from cdmp_ros.core.kinematics.capsules import (Capsule, collision_balls, collision_capsules,
                                               fit_capsule)
from cdmp_ros.core.kinematics.closest import Sphere
from cdmp_ros.ros.robot_model import default_urdf_path

PANDA_LINKS = [f'panda_link{i}' for i in range(1, 8)] + ['panda_hand', 'panda_leftfinger']


def _segment_distance(p, a, b):
    a, b, p = np.asarray(a), np.asarray(b), np.asarray(p)
    u = b - a
    t = 0.0 if u @ u == 0 else np.clip((p - a) @ u / (u @ u), 0.0, 1.0)
    return float(np.linalg.norm(p - a - t * u))


def test_fit_encloses_balls_and_recovers_a_capsule(rng):
    # balls sampled inside a known capsule, some on its surface: the fit encloses all, and
    # is no larger than the capsule they came from (within the radius grid)
    a, b, R = np.array([0.1, -0.2, 0.3]), np.array([0.4, 0.1, 0.1]), 0.07
    t = rng.uniform(0, 1, 400)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rho = rng.uniform(0.0, 0.02, 400)
    reach = (R - rho) * np.where(np.arange(400) < 50, 1.0, rng.uniform(0.5, 1, 400))
    centres = a + t[:, None] * (b - a) + d * reach[:, None]   # the first 50 touch the surface
    s, e, r = fit_capsule(centres, rho)
    cap = Capsule('x', tuple(s), tuple(e), r)
    assert (cap.distance(centres) + rho <= 1e-9).all()
    volume = math.pi * r * r * np.linalg.norm(e - s) + 4 / 3 * math.pi * r ** 3
    known = math.pi * R * R * np.linalg.norm(b - a) + 4 / 3 * math.pi * R ** 3
    assert volume <= 1.02 * known
    # one point: a ball of its radius
    s, e, r = fit_capsule(np.array([[1.0, 2.0, 3.0]]), np.array([0.5]))
    assert r == pytest.approx(0.5) and np.allclose(s, [1, 2, 3]) and np.allclose(e, s)


@pytest.mark.parametrize('bad', [np.zeros((0, 3)), np.zeros((3, 2)), np.array([[np.nan, 0, 0]])])
def test_fit_rejects_bad_points(bad):
    with pytest.raises(ValidationError, match='centres'):
        fit_capsule(bad)


def test_panda_capsules_enclose_every_collision_vertex():
    path = default_urdf_path()
    root = ET.parse(path).getroot()
    links = {el.get('name'): el for el in root.findall('link')}
    for cap in collision_capsules(path, PANDA_LINKS):
        centres, rho = collision_balls(links[cap.link], os.path.dirname(path), cap.link)
        assert len(centres) > 50, cap.link
        excess = cap.distance(centres) + rho
        assert excess.max() <= 1e-9, (cap.link, excess.max())
        # and reasonably tight: some vertex is within 5 mm of the surface
        assert excess.max() > -5e-3, (cap.link, excess.max())


def test_panda_capsule_distance_is_a_lower_bound_of_pybullet(rng):
    """Independent check: pybullet's closest points between a link (its collision mesh, as
    the simulator loads it) and a sphere are never closer than the capsule model says."""
    from cdmp_ros.sim import World, panda_spec
    chain = panda_chain(default_urdf_path())
    links = [f'panda_link{i}' for i in range(3, 8)] + ['panda_hand']
    caps = collision_capsules(default_urdf_path(), links)
    gaps = []
    with World() as world:
        robot = world.add_robot(panda_spec())
        for trial in range(6):
            q = rng.uniform(chain.lower * 0.8, chain.upper * 0.8)
            robot.reset(q)
            for cap in caps:
                A, B = chain.forward(q, [PointOfInterest(cap.link, cap.start),
                                         PointOfInterest(cap.link, cap.end)])
                for _ in range(4):
                    d = rng.normal(size=3)
                    centre = 0.5 * (A + B) + d / np.linalg.norm(d) * rng.uniform(0.1, 0.25)
                    radius = 0.03
                    model = _segment_distance(centre, A, B) - cap.radius - radius
                    world.obstacles.add_sphere('s', centre, radius, replace=True)
                    rep = world.obstacles.distances(robot, max_distance=2.0)
                    true = rep.distance[rep.link_names.index(cap.link), 0]
                    # pybullet pads a convex mesh with its collision margin: the capsule
                    # encloses every vertex (test above), pybullet's shape by 0.9 mm less
                    # at most (600 samples, 2026-11-26)
                    assert true >= model - 1.5e-3, (cap.link, q, centre, true, model)
                    gaps.append(true - model)
    # the model is a bound, not a wild over-estimate: it comes within 3 cm of the truth
    assert min(gaps) < 0.03, min(gaps)


def test_urdf_primitives_and_errors(tmp_path):
    urdf = tmp_path / 'r.urdf'
    urdf.write_text('''<robot name="r">
      <link name="box"><collision><origin xyz="0 0 0.5" rpy="0 0 0"/>
        <geometry><box size="0.2 0.1 1.0"/></geometry></collision></link>
      <link name="cyl"><collision><origin xyz="1 0 0" rpy="0 1.5707963 0"/>
        <geometry><cylinder radius="0.05" length="0.4"/></geometry></collision></link>
      <link name="ball"><collision><geometry><sphere radius="0.1"/></geometry></collision>
        </link>
      <link name="cap"><collision><origin xyz="0.5 0 0" rpy="0 1.57079632679 0"/>
        <geometry><capsule radius="0.05" length="1"/></geometry></collision></link>
      <link name="none"/>
      <link name="stl"><collision><geometry><mesh filename="package://x/m.stl"/></geometry>
        </collision></link>
      <link name="missing"><collision><geometry><mesh filename="package://x/m.obj"/>
        </geometry></collision></link>
    </robot>''')
    box, cyl, ball = collision_capsules(str(urdf), ['box', 'cyl', 'ball'])
    corners = np.array([[x, y, z] for x in (-.1, .1) for y in (-.05, .05) for z in (0, 1)])
    assert (box.distance(corners) <= 1e-9).all()
    ang = np.linspace(0, 2 * np.pi, 500)
    # the cylinder's axis is along x after the 90 degree pitch: its rims at x = 1 +- 0.2
    rims = np.concatenate([np.stack([np.full_like(ang, 1 + s), 0.05 * np.cos(ang),
                                     0.05 * np.sin(ang)], 1) for s in (-0.2, 0.2)])
    assert (cyl.distance(rims) <= 1e-9).all()
    assert cyl.radius == pytest.approx(0.05, abs=2e-3)
    assert ball.radius == pytest.approx(0.1) and np.allclose(ball.start, 0)
    # a capsule is its own capsule: the axis from x = 0 to x = 1 (pitched 90 degrees), radius
    # 0.05 up to the ends' rounding
    cap, = collision_capsules(str(urdf), ['cap'])
    assert sorted([cap.start[0], cap.end[0]]) == pytest.approx([0.0, 1.0], abs=1e-8)
    assert np.allclose([cap.start[1:], cap.end[1:]], 0.0, atol=1e-8)
    assert cap.radius == pytest.approx(0.05, abs=1e-8)
    surface = np.array([[0.3, 0.05, 0.0], [0.7, 0.0, -0.05], [-0.05, 0.0, 0.0], [1.05, 0, 0]])
    assert np.abs(cap.distance(surface)).max() <= 1e-7
    with pytest.raises(ValidationError, match="'none': no <collision>"):
        collision_capsules(str(urdf), ['none'])
    with pytest.raises(ValidationError, match=r'only Wavefront \.obj'):
        (tmp_path / 'm.stl').write_text('solid')
        collision_capsules(str(urdf), ['stl'])
    with pytest.raises(ValidationError, match="mesh 'package://x/m.obj' not found"):
        collision_capsules(str(urdf), ['missing'])
    with pytest.raises(ValidationError, match="no link 'nope'"):
        collision_capsules(str(urdf), ['nope'])
    bad = tmp_path / 'bad.urdf'
    bad.write_text('<robot name="r"><link name="b"><collision><geometry>'
                   '<box size="1 nan 1"/></geometry></collision></link></robot>')
    with pytest.raises(ValidationError, match='size: expected 3 numbers'):
        collision_capsules(str(bad), ['b'])


def test_coupling_uses_each_capsule_radius():
    chain = panda_chain(default_urdf_path())
    (seg,) = [s for s in chain.link_segments() if s[0] == 'panda_link4']
    q = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
    A, B = chain.forward(q, [PointOfInterest(seg[0], seg[1]), PointOfInterest(seg[0], seg[2])])
    centre = 0.5 * (A + B) + [0.0, 0.0, 0.3]
    obstacle = Sphere(tuple(centre), 0.05)
    axis = _segment_distance(centre, A, B)
    for radius in (0.0, 0.06, 0.12):
        c = ObstacleCoupling(chain, [Capsule('panda_link4', seg[1], seg[2], radius)],
                             config=CouplingConfig(link_radius=0.01))
        c.joint_acceleration(q, None, [obstacle])
        assert c.last_distances[1] == pytest.approx(axis - radius - 0.05, abs=1e-9)
    # by name: config.link_radius
    c = ObstacleCoupling(chain, ['panda_link4'], config=CouplingConfig(link_radius=0.01))
    c.joint_acceleration(q, None, [obstacle])
    assert c.last_distances[1] == pytest.approx(axis - 0.01 - 0.05, abs=1e-9)
    with pytest.raises(ValidationError, match=r'links\[0\]: radius'):
        ObstacleCoupling(chain, [Capsule('panda_link4', seg[1], seg[2], float('nan'))])


def test_streamer_parameter_errors_name_the_parameter(tmp_path):
    from cdmp_ros.ros.robot_model import load_collision_capsules
    assert load_collision_capsules('', []) == []
    (cap,) = load_collision_capsules('', ['panda_hand'])
    assert cap.link == 'panda_hand' and 0.03 < cap.radius < 0.07
    with pytest.raises(ValidationError,
                       match=r"coupling_capsule_links: links\[1\]: no link 'panda_link9'"):
        load_collision_capsules('', ['panda_hand', 'panda_link9'])
    # a robot_description whose meshes are neither here nor beside urdf_path: named
    text = open(default_urdf_path()).read()
    missing = r"mesh 'package://meshes/collision/link5.obj' not found"
    with pytest.raises(ValidationError,
                       match=r"coupling_capsule_links: link 'panda_link5'.*" + missing):
        load_collision_capsules(str(tmp_path / 'robot.urdf'), ['panda_link5'],
                                robot_description=text)


def test_more_bad_inputs_are_named(tmp_path):
    from cdmp_ros.ros.robot_model import load_collision_capsules
    chain = panda_chain(default_urdf_path())
    bad = r"coupling_capsule_links\[1\]: 'panda_leftfinger' is not a link of the chain"
    with pytest.raises(ValidationError, match=bad):
        load_collision_capsules('', ['panda_hand', 'panda_leftfinger'], chain=chain)
    with pytest.raises(ValidationError, match=r"links\[1\]: 'panda_hand' is listed twice"):
        load_collision_capsules('', ['panda_hand', 'panda_hand'])
    urdf = tmp_path / 'r.urdf'
    urdf.write_text('<robot name="r"><link name="m"><collision><geometry>'
                    '<mesh filename="m.obj"/></geometry></collision></link></robot>')
    (tmp_path / 'm.obj').write_text('v 0 0 0\nv 1 2\nv 1 1 1\n')
    with pytest.raises(ValidationError, match="line 2: bad vertex 'v 1 2'"):
        collision_capsules(str(urdf), ['m'])
    (tmp_path / 'm.obj').write_text('# no vertices\n')
    with pytest.raises(ValidationError, match='no usable vertices'):
        collision_capsules(str(urdf), ['m'])


def test_arm_capsules_sphere_clearance_against_the_link_frames(rng):
    """ArmCapsules.sphere_clearance = min over capsules of |c - segment| - R - r, with each
    segment's ends put in the base frame through the link frames of Chain.forward, and the
    tool capsule = the chain's last link segment."""
    from cdmp_ros.core.kinematics.capsules import ArmCapsules
    chain = panda_chain(default_urdf_path())
    caps = collision_capsules(default_urdf_path(), PANDA_LINKS[:8])
    arm = ArmCapsules(chain, caps, tool_radius=0.06)
    tool_link, tool_a, tool_b = chain.link_segments()[-1]
    assert arm.capsules[-1] == Capsule(tool_link, tuple(tool_a), tuple(tool_b), 0.06)
    for _ in range(20):
        q = rng.uniform(chain.lower, chain.upper)
        c, r = rng.uniform([-0.6, -0.6, 0.0], [0.6, 0.6, 1.0]), rng.uniform(0.0, 0.1)
        want = np.inf
        for cap in arm.capsules:
            a, b = chain.forward(q, [PointOfInterest(cap.link, cap.start),
                                     PointOfInterest(cap.link, cap.end)])
            want = min(want, _segment_distance(c, a, b) - cap.radius - r)
        assert arm.sphere_clearance(q, c, r) == pytest.approx(want, abs=1e-12)


def test_fitted_capsules_are_cached_checked_on_reading_and_refitted_when_wrong(
        tmp_path, monkeypatch):
    """A fit (0.1-0.3 s per link, and scipy.optimize's import) is done once per set of balls:
    the second process reads it from the capsule cache. A cached capsule is used only if it
    encloses every ball: one shrunk, malformed or not finite in the file is fitted again."""
    import json

    from cdmp_ros.core import cache
    from cdmp_ros.core.kinematics import capsules
    monkeypatch.setenv(cache.CACHE_ENV, str(tmp_path))
    path = default_urdf_path()
    fits = []
    real_fit = capsules.fit_capsule
    monkeypatch.setattr(capsules, 'fit_capsule', lambda *a: fits.append(1) or real_fit(*a))
    first = collision_capsules(path, PANDA_LINKS[:3])
    assert len(fits) == 3
    files = sorted((tmp_path / 'capsules').glob('capsule_*.json'))
    assert len(files) == 3
    assert os.stat(tmp_path / 'capsules').st_mode & 0o777 == 0o700
    again = collision_capsules(path, PANDA_LINKS[:3])
    assert len(fits) == 3 and again == first  # read back, bit for bit
    root = ET.parse(path).getroot()
    links = {el.get('name'): el for el in root.findall('link')}
    for cap in again:
        centres, rho = collision_balls(links[cap.link], os.path.dirname(path), cap.link)
        assert capsules.encloses(cap.start, cap.end, cap.radius, centres, rho)
    # a wrong file: shrunk by 1 mm, malformed, not finite, an end of 2 numbers, enclosing
    # but 1e300 wide, a number too large for a float: each is fitted again
    good = files[0].read_text()
    for bad in (lambda d: dict(d, radius=d['radius'] - 1e-3), lambda d: {'start': 1},
                lambda d: dict(d, radius=float('nan')), lambda d: dict(d, end=[0, 0]),
                lambda d: dict(d, radius=1e300), lambda d: '{"radius": 1' + '0' * 400 + '}'):
        d = bad(json.loads(good))
        files[0].write_text(d if isinstance(d, str) else json.dumps(d))
        n = len(fits)
        assert collision_capsules(path, PANDA_LINKS[:3]) == first
        assert len(fits) == n + 1
    files[0].write_text('x' * 5000)  # longer than any capsule file: not read
    n = len(fits)
    assert collision_capsules(path, PANDA_LINKS[:3]) == first and len(fits) == n + 1


@pytest.mark.parametrize('start, end, radius', [
    ((0.0, 0.0, 0.0), (0.3, 0.0, 0.0), 0.05),        # k = 3: four balls
    ((0.01, -0.02, 0.03), (-0.05, 0.04, 0.0), 0.08),  # shorter than 2 r: the two ends
    ((0.1, 0.1, 0.1), (0.1, 0.1, 0.1), 0.04),         # a ball
    ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.05),         # the planar arm's 1 m link: eleven
])
def test_covering_balls_contain_the_capsule(rng, start, end, radius):
    """Capsule.covering_balls: every point of the capsule (sampled uniformly in it, and on its
    surface) lies in one of the balls; each radius is at most sqrt(2) r; ends included."""
    cap = Capsule('l', start, end, radius)
    balls = cap.covering_balls()
    a, b = np.asarray(start), np.asarray(end)
    length = np.linalg.norm(b - a)
    k = int(math.ceil(length / (2 * radius)))
    assert len(balls) == k + 1
    C = np.array([c for c, _ in balls])
    R = np.array([r for _, r in balls])
    assert np.all(R <= math.sqrt(2) * radius + 1e-12) and np.all(R >= radius)
    np.testing.assert_allclose(C[0], a) and np.testing.assert_allclose(C[-1], b)
    # points of the capsule: a segment point plus an offset of length <= r (= r: the surface)
    t = rng.uniform(0.0, 1.0, 20000)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rho = radius * np.where(rng.uniform(size=20000) < 0.5, 1.0, rng.uniform(size=20000) ** (1 / 3))
    P = a + t[:, None] * (b - a) + rho[:, None] * u
    assert np.all(cap.distance(P) <= 1e-12)                 # they are in the capsule
    inside = np.linalg.norm(P[:, None] - C[None], axis=-1) <= R[None] + 1e-12
    assert inside.any(axis=1).all()
    # and the balls are not larger than the rule: a point just outside a ball's reach exists
    # for a capsule longer than its diameter (the radius is the cover's least one for k)
    if k > 1:
        mid = a + (b - a) * (0.5 / k)
        across = np.cross(b - a, [1.0, 0.0, 0.0] if abs((b - a)[0]) < 0.9 * length else
                          [0.0, 1.0, 0.0])
        p = mid + radius * across / np.linalg.norm(across)
        assert np.linalg.norm(p - C, axis=1).min() == pytest.approx(R[0], rel=1e-9)


def test_covering_balls_refuse_a_capsule_without_radius():
    with pytest.raises(ValidationError, match="capsule of 'l'"):
        Capsule('l', (0.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.0).covering_balls()


def test_covering_balls_contain_every_panda_collision_vertex():
    """The balls of each Panda link's capsule hold all of its URDF collision geometry (what the
    adapter's link_geometry keeps clear of obstacles)."""
    path = default_urdf_path()
    links = {el.get('name'): el for el in ET.parse(path).getroot().findall('link')}
    for cap in collision_capsules(path, PANDA_LINKS):
        centres, rho = collision_balls(links[cap.link], os.path.dirname(path), cap.link)
        C = np.array([c for c, _ in cap.covering_balls()])
        R = np.array([r for _, r in cap.covering_balls()])
        gap = (np.linalg.norm(centres[:, None] - C[None], axis=-1) + rho[:, None] - R).min(axis=1)
        assert gap.max() <= 1e-9, (cap.link, gap.max())
