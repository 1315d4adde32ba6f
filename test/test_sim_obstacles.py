"""Obstacles of cdmp_ros.sim: add/move/remove, closest-point distances vs. closed forms, contacts.

The planar arm's links are capsules of radius r around the segments between consecutive joints,
so link-sphere distances have the closed form dist(centre, segment) - r - R, and a board facing
a stretched arm is at (face offset - r).
"""
import numpy as np
import pytest

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.sim import panda_spec, planar_arm_spec, PositionController, World

R_LINK = 0.05


@pytest.fixture
def world():
    with World() as w:
        yield w


@pytest.fixture
def arm(world):
    return world.add_robot(planar_arm_spec(link_radius=R_LINK))


def joint_points(q, lengths=(1.0, 1.0, 1.0, 1.0)):
    """Planar forward kinematics: the n+1 joint/tip positions (n+1, 3), closed form."""
    angles = np.cumsum(q)
    steps = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], 1) \
        * np.asarray(lengths)[:, None]
    return np.vstack([np.zeros(3), np.cumsum(steps, 0)])


def point_segment_distance(p, a, b):
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))


def test_sphere_distance_matches_closed_form(world, arm, rng):
    for trial in range(4):
        q = rng.uniform(-1.5, 1.5, 4)
        arm.reset(q)
        centre = np.append(rng.uniform(-2.5, 2.5, 2), rng.uniform(-0.3, 0.3))
        radius = rng.uniform(0.05, 0.3)
        world.obstacles.add_sphere('ball', centre, radius, replace=True)
        report = world.obstacles.distances(arm, max_distance=10.0)
        P = joint_points(q)
        for i in range(4):
            expected = point_segment_distance(centre, P[i], P[i + 1]) - R_LINK - radius
            got = report.distance[report.link_names.index(f'link{i + 1}'), 0]
            assert got == pytest.approx(expected, abs=1e-4), (trial, i)
        best = report.minimum
        assert best.distance == pytest.approx(report.distance[np.isfinite(report.distance)]
                                              .min())
        # the closest points are consistent with the distance and the normal
        np.testing.assert_allclose(best.point_on_link - best.point_on_obstacle,
                                   best.distance * best.normal, atol=1e-4)


def test_box_distance_matches_closed_form(world, arm):
    """A board parallel to the stretched arm, 0.3 m to its side: distance 0.3 - r from the
    links it faces (link3 and link4), and the Euclidean corner distance from link2."""
    arm.reset(np.zeros(4))
    half = np.array([0.5, 0.05, 0.4])
    centre = np.array([3.0, 0.3 + half[1], 0.0])     # near face at y = 0.3, x in [2.5, 3.5]
    world.obstacles.add_box('board', centre, half)
    report = world.obstacles.distances(arm, max_distance=10.0)
    d = dict(zip(report.link_names, report.distance[:, 0]))
    assert d['link3'] == pytest.approx(0.3 - R_LINK, abs=1e-4)
    assert d['link4'] == pytest.approx(0.3 - R_LINK, abs=1e-4)
    corner = np.array([2.5, 0.3])                     # closest box edge to link2's tip (2, 0)
    # pybullet rounds box edges by its collision margin: allow 1 mm there
    assert d['link2'] == pytest.approx(np.linalg.norm(corner - [2.0, 0.0]) - R_LINK, abs=1e-3)


def test_add_move_remove(world, arm):
    obs = world.obstacles
    obs.add_sphere('a', (1.5, 1.0, 0.0), 0.1)
    obs.add_box('b', (0.0, -2.0, 0.0), (0.1, 0.1, 0.1))
    assert obs.names == ('a', 'b') and len(obs) == 2 and 'a' in obs
    with pytest.raises(ValidationError, match='name'):
        obs.add_sphere('a', (0.0, 0.0, 0.0), 0.1)
    before = obs.distances(arm, 10.0).distance[:, 0].min()
    assert before == pytest.approx(1.0 - R_LINK - 0.1, abs=1e-4)
    obs.move('a', (1.5, 0.5, 0.0))
    assert obs.get('a').position == (1.5, 0.5, 0.0)
    assert obs.distances(arm, 10.0).distance[:, 0].min() == pytest.approx(0.35, abs=1e-4)
    obs.remove('a')
    assert obs.names == ('b',)
    report = obs.distances(arm, 10.0)
    assert report.obstacle_names == ('b',) and report.distance.shape == (len(arm.link_names), 1)
    with pytest.raises(ValidationError, match="got 'a'"):
        obs.move('a', (0.0, 0.0, 0.0))
    obs.clear()
    assert len(obs) == 0 and obs.distances(arm).minimum is None
    assert obs.min_distance(arm) == np.inf


def test_pairs_beyond_max_distance_are_inf(world, arm):
    world.obstacles.add_sphere('far', (0.0, 5.0, 0.0), 0.1)
    report = world.obstacles.distances(arm, max_distance=0.5)
    assert np.all(np.isinf(report.distance)) and not report.pairs


@pytest.mark.parametrize('collide', [False, True])
def test_penetration_is_reported_as_contact(world, arm, collide):
    world.obstacles.add_sphere('ball', (1.5, 0.1, 0.0), 0.1, collide=collide)
    contacts = world.obstacles.contacts(arm)
    links = {c.link for c in contacts}
    assert links == {'link2'}, contacts
    depth = contacts[0].depth
    assert depth == pytest.approx(0.1 + R_LINK - 0.1, abs=1e-4)   # overlap of 0.05 m
    assert contacts[0].obstacle == 'ball'
    assert world.obstacles.distances(arm).minimum.distance == pytest.approx(-depth)


def test_colliding_box_stops_the_arm_and_reports_force(world, arm):
    """A physical board in the arm's sweep: the arm is blocked, and the contact carries force."""
    world.obstacles.add_box('board', (2.0, 1.2, 0.0), (0.6, 0.05, 0.3), collide=True)
    arm.set_controller(PositionController())
    arm.set_reference(np.array([1.2, 0.0, 0.0, 0.0]))
    world.run(1.5)
    contacts = world.obstacles.contacts(arm, threshold=1e-3)
    assert contacts and max(c.normal_force for c in contacts) > 0.0, contacts
    assert arm.q[0] < 0.6          # the board (y from 1.15) blocks joint 1 well before 1.2 rad


def test_ghost_obstacle_does_not_block(world, arm):
    world.obstacles.add_box('board', (2.0, 1.2, 0.0), (0.6, 0.05, 0.3), collide=False)
    arm.set_reference(np.array([1.2, 0.0, 0.0, 0.0]))
    seen = []
    world.run(1.5, callback=lambda w: seen.extend(w.obstacles.contacts(arm)))
    assert arm.q[0] > 1.0                     # swept through the board
    assert seen                               # and yet the overlaps were reported
    assert all(c.normal_force == 0.0 for c in seen)


def test_panda_distance_report_covers_every_link(world):
    robot = world.add_robot(panda_spec())
    world.obstacles.add_sphere('s', (0.5, 0.0, 0.5), 0.05)
    world.obstacles.add_box('b', (0.0, 0.6, 0.3), (0.3, 0.01, 0.3))
    report = world.obstacles.distances(robot, max_distance=5.0)
    assert report.distance.shape == (len(robot.link_names), 2)
    assert report.link_names[0] == 'panda_link0' and 'panda_hand' in report.link_names
    # links with collision geometry get a finite distance to both obstacles
    for link in ('panda_link1', 'panda_link4', 'panda_hand'):
        assert np.all(np.isfinite(report.distance[report.link_names.index(link)]))
    hand = robot.link_pose('panda_hand')[0]
    d_hand = report.distance[report.link_names.index('panda_hand'), 0]
    assert d_hand <= np.linalg.norm(hand - [0.5, 0.0, 0.5]) - 0.05 + 1e-6
