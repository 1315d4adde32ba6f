"""Adaptation requests of the adapter (cdmp_ros.core.adaptation.requests): obstacles, goals and the
current state turned into a constrained ProMP problem, checked against independent
computations (closed-form distances, forward kinematics, Monte Carlo)."""
import dataclasses
import json

import numpy as np
import pytest

from adapter_harness import PANDA_JOINTS, Q_GOAL, Q_START, reach_cdmp
from cdmp_ros.core.adaptation.requests import (AdaptRequest, avoided_points, box_wall,
                                               build_problem, classify, clip_goal, ee_band,
                                               ee_path, link_balls, obstacle_distance,
                                               reorder_promp, retarget_primitive_dict, run_request,
                                               solve_goal_point)
from cdmp_ros.core.adaptation.solver import AdaptationReport, monte_carlo_satisfaction
from cdmp_ros.core.adaptation.config import AdaptRequestConfig, AdapterConfig
from cdmp_ros.core.adaptation.constraints import Hyperplane, JointLimit, Repeller, Waypoint
from cdmp_ros.core.errors import ConstraintSetError, ValidationError
from cdmp_ros.core.kinematics import Box, PointOfInterest, Sphere
from cdmp_ros.core.primitive_io import primitive_from_dict, primitive_to_dict

EE = PointOfInterest('ee')


def test_reorder_promp_keeps_every_joint_distribution(prior, rng):
    perm = [3, 0, 6, 1, 5, 2, 4]
    shuffled = reorder_promp(prior, [PANDA_JOINTS[i] for i in perm])
    back = reorder_promp(shuffled, PANDA_JOINTS)
    s = np.linspace(0, 1, 7)
    np.testing.assert_allclose(shuffled.mean(s), prior.mean(s)[:, perm], atol=1e-12)
    C, Cs = prior.cov(s), shuffled.cov(s)
    np.testing.assert_allclose(Cs, C[:, perm][:, :, perm], atol=1e-12)
    np.testing.assert_allclose(back.cov_w, prior.cov_w, atol=0)
    assert reorder_promp(prior, PANDA_JOINTS) is prior
    with pytest.raises(ValidationError, match=r"unknown \['panda_joint7'\]"):
        reorder_promp(prior, list(PANDA_JOINTS[:6]) + ['other'])


def test_clip_goal_keeps_the_cdmp_margin():
    lo, hi = np.array([-1.0, 0.0]), np.array([1.0, 4.0])
    g, clipped = clip_goal([5.0, 1.0], lo, hi, 0.01)
    assert clipped == [0]
    np.testing.assert_allclose(g, [0.99, 1.0])        # centre 0 + 0.99 * half range 1
    g, clipped = clip_goal([-3.0, -1.0], lo, hi, 0.01)
    assert clipped == [0, 1]
    np.testing.assert_allclose(g, [-0.99, 2.0 - 1.98])


def test_goal_point_ik_reaches_a_reachable_point(chain):
    q_true = np.array([0.3, 0.1, -0.2, -1.5, 0.1, 1.8, 0.4])
    target = chain.forward(q_true, [EE])[0]
    res = solve_goal_point(chain, target, [Q_START], tol=1e-4)
    x = chain.forward(res.q, [EE])[0]        # independent FK check
    assert np.linalg.norm(x - target) <= 1e-4
    assert np.all(res.q > chain.lower) and np.all(res.q < chain.upper)


def test_unreachable_goal_point_is_rejected_with_the_residual(chain):
    with pytest.raises(ValidationError, match=r'unreachable.*IK residual [0-9.]+ m > 0.001 m'):
        solve_goal_point(chain, [3.0, 0.0, 0.5], [Q_START, Q_GOAL], tol=1e-3, max_iter=100)
    with pytest.raises(ValidationError, match='goal_point.point'):
        solve_goal_point(chain, [np.nan, 0.0, 0.5], [Q_START])


def test_retarget_writes_the_goal_in_the_primitive_joint_order():
    d = primitive_to_dict(reach_cdmp())
    perm = [6, 5, 4, 3, 2, 1, 0]
    d['joint_names'] = [d['joint_names'][i] for i in perm]   # pretend it was stored reversed
    goal = np.array([0.1, 0.2, 0.3, -1.0, 0.5, 1.6, 0.7])     # robot order
    out = retarget_primitive_dict(d, goal, PANDA_JOINTS)
    by_name = dict(zip(out['joint_names'], out['dmp']['goal']))
    assert [by_name[n] for n in PANDA_JOINTS] == pytest.approx(goal.tolist())
    assert out['dmp']['weights'] == d['dmp']['weights']
    assert d['dmp']['goal'] != out['dmp']['goal']             # the input is not modified
    primitive_from_dict(out)                                  # still a valid primitive


def test_retarget_clips_into_the_primitive_limits():
    from cdmp_ros.core.adaptation.requests import retarget_clipped
    d = primitive_to_dict(reach_cdmp())
    d['limits']['upper'][1] = 0.5                          # tighter than the robot's 1.8326
    goal = np.array([0.1, 1.0, 0.3, -1.0, 0.5, 1.6, 0.7])
    out, clipped = retarget_clipped(d, goal, PANDA_JOINTS, margin=0.01)
    assert clipped == [1]
    lo, hi = d['limits']['lower'][1], d['limits']['upper'][1]
    assert out['dmp']['goal'][1] == pytest.approx(0.5 * (lo + hi) + 0.99 * 0.5 * (hi - lo))
    assert out['dmp']['goal'][0] == goal[0]
    _, none = retarget_clipped(d, goal, PANDA_JOINTS)      # no margin: no clipping
    assert none == []


def test_obstacle_distance_closed_form():
    X = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 3.0, 4.0]])
    np.testing.assert_allclose(obstacle_distance(Sphere((0.0, 0.0, 0.0), 0.5), X),
                               [0.5, -0.5, 4.5])
    box = Box((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1))
    np.testing.assert_allclose(obstacle_distance(box, X),
                               [0.9, -0.1, np.hypot(2.9, 3.9)], atol=1e-12)


def test_oriented_box_distance_and_wall_are_the_rotated_ones(rng):
    """An OrientedBox gives the same distance and wall as the axis-aligned box in its own
    frame, mapped back: checked against OrientedBox.signed_distance and by rotating the
    points and the box together."""
    from cdmp_ros.core.kinematics import OrientedBox
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    ob = OrientedBox.from_quaternion((0.5, 0.1, 0.3), (0.2, 0.4, 0.1), q)
    R, c = np.array(ob.rotation), np.array(ob.center)
    X = rng.uniform(-0.5, 1.0, (200, 3))
    np.testing.assert_allclose(obstacle_distance(ob, X), ob.signed_distance(X)[0], atol=1e-12)
    aabb = Box((-0.1, -0.2, -0.05), (0.1, 0.2, 0.05))          # the box in its own frame
    np.testing.assert_allclose(obstacle_distance(ob, X), obstacle_distance(aabb, (X - c) @ R),
                               atol=1e-12)
    Xb = np.column_stack([rng.uniform(-0.3, 0.3, 30), rng.uniform(0.25, 0.6, 30),
                          rng.uniform(-0.05, 0.05, 30)])      # +y side in the box frame
    normal, offset, clearance = box_wall(ob, c + Xb @ R.T, margin=0.01)
    n_b, o_b, cl_b = box_wall(aabb, Xb, margin=0.01)
    np.testing.assert_allclose(normal, R @ n_b, atol=1e-12)
    np.testing.assert_allclose(offset, c + R @ o_b, atol=1e-12)
    assert clearance == pytest.approx(cl_b)
    np.testing.assert_allclose(normal, -R[:, 1], atol=1e-12)  # into the box, rotated -y
    assert np.all((c + Xb @ R.T - offset) @ normal <= 1e-12)


def test_quaternion_of_inverts_from_quaternion(rng):
    from cdmp_ros.core.kinematics import OrientedBox
    special = [np.array(v, float) for v in ((0, 0, 0, 1), (1, 0, 0, 0), (0, 1, 0, 0),
                                            (0, 0, 1, 0), (0, 0, 1e-9, -1))]
    for q in list(rng.normal(size=(500, 4))) + special:
        q = q / np.linalg.norm(q)
        ob = OrientedBox.from_quaternion((0, 0, 0), (1, 1, 1), q)
        back = np.array(ob.quaternion())
        assert abs(abs(back @ q) - 1.0) < 1e-12, (q, back)


def test_box_wall_is_the_face_leaving_the_most_room(rng):
    box = Box((0.4, -0.2, 0.0), (0.6, 0.2, 0.5))
    X = np.column_stack([rng.uniform(0.0, 1.0, 30), rng.uniform(0.25, 0.9, 30),
                         rng.uniform(0.0, 0.5, 30)])          # all on the +y side
    normal, offset, clearance = box_wall(box, X, margin=0.01)
    np.testing.assert_allclose(normal, [0.0, -1.0, 0.0])     # into the box
    assert offset[1] == pytest.approx(0.21)
    assert clearance == pytest.approx(X[:, 1].min() - 0.21)
    # independent: the best face over all six by brute force
    lo, hi = np.asarray(box.lower), np.asarray(box.upper)
    best = max(min(s * (X[:, a] - f)) for a in range(3)
               for s, f in ((1, hi[a]), (-1, lo[a])))
    assert clearance == pytest.approx(best - 0.01)
    assert np.all((X - offset) @ normal <= 0.0)               # the points satisfy the wall


def test_build_problem_collects_limits_near_obstacles_and_conditions(chain, prior):
    cfg = AdaptRequestConfig(n_steps=20, obstacle_margin=0.02, influence_distance=1.0)
    x_mid = ee_path(chain, prior.mean([0.5]))[0]
    near = Sphere(tuple(x_mid + [0.03, 0.0, 0.0]), 0.04)
    far = Sphere((3.0, 3.0, 3.0), 0.1)
    box = Box(tuple(x_mid + [0.15, -0.05, -0.05]), tuple(x_mid + [0.25, 0.05, 0.05]))
    q0 = Q_START + 0.05
    req = AdaptRequest(prior, (near, far, box), None, Q_GOAL - 0.05, q0)
    prob = build_problem(req, chain, cfg)
    assert (prob.obstacles_used, prob.obstacles_ignored) == (2, 1)
    kinds = [type(c) for c in prob.constraints]
    assert kinds.count(JointLimit) == 7
    points = 1 + len(cfg.avoid_links)     # the end effector, panda_link4 and panda_hand
    assert cfg.avoid_links == ('panda_link4', 'panda_hand')
    assert kinds.count(Repeller) == points and kinds.count(Hyperplane) == points
    rep = [c for c in prob.constraints if isinstance(c, Repeller)]
    assert rep[0].radius == pytest.approx(0.06)
    np.testing.assert_allclose(prob.prior.mean([0.0])[0], q0, atol=0.02)
    np.testing.assert_allclose(prob.prior.mean([1.0])[0], Q_GOAL - 0.05, atol=0.02)
    assert prob.config.n_steps == 20
    assert prob.notes == ['conditioned on the current state and the goal']
    # a request that continues the running motion: the current state is not a phase-0
    # observation; the prior's start stays
    cont = build_problem(AdaptRequest(prior, (near,), None, Q_GOAL - 0.05, q0, continues=True),
                         chain, cfg)
    assert cont.notes == ['conditioned on the goal']
    np.testing.assert_allclose(cont.prior.mean([0.0])[0], prior.mean([0.0])[0], atol=0.015)
    assert np.abs(cont.prior.mean([0.0])[0] - q0).min() > 0.03
    with pytest.raises(ValidationError, match='avoid_links'):
        build_problem(req, chain, AdaptRequestConfig(avoid_links=('no_such_link',)))


def _panda_balls(links=('panda_link4', 'panda_hand')):
    from cdmp_ros.core.kinematics.capsules import collision_capsules
    from cdmp_ros.ros.robot_model import default_urdf_path
    return link_balls(collision_capsules(default_urdf_path(), list(links)))


def test_avoided_points_are_the_links_balls(chain):
    """avoided_points: the tool centre point, then each avoided link as the balls covering its
    collision capsule (named <link>_<i>), or as its origin without balls."""
    balls = _panda_balls()
    assert len(balls['panda_link4']) == 2 and len(balls['panda_hand']) == 3
    pts = avoided_points(chain, ('panda_link4', 'panda_hand'), balls)
    assert [p.name for p in pts] == ['ee', 'panda_link4_0', 'panda_link4_1', 'panda_hand_0',
                                     'panda_hand_1', 'panda_hand_2']
    assert pts[0].radius == 0.0 and pts[0].poi == EE
    for p, (centre, radius) in zip(pts[3:], balls['panda_hand']):
        assert p.poi == PointOfInterest('panda_hand', centre) and p.radius == radius
    origins = avoided_points(chain, ('panda_link4',))
    assert [(p.name, p.poi, p.radius) for p in origins] == [
        ('ee', EE, 0.0), ('panda_link4', PointOfInterest('panda_link4'), 0.0)]
    with pytest.raises(ValidationError, match="no collision balls of 'panda_link5'"):
        avoided_points(chain, ('panda_link5',), balls)
    with pytest.raises(ValidationError, match=r"avoid_links\[0\]: 'nowhere' is not a link"):
        avoided_points(chain, ('nowhere',), balls)


def test_build_problem_keeps_the_links_balls_clear(chain, prior):
    """With link_balls, every repeller's radius is the sphere's plus the margin plus its ball's,
    every wall is moved out by the ball's radius too, and an obstacle counts as near when it
    comes within influence_distance of a ball's surface; a ball (not the origin) inside an
    obstacle at the conditioned start is infeasible."""
    cfg = AdaptRequestConfig(n_steps=20, obstacle_margin=0.02, influence_distance=1.0)
    balls = _panda_balls()
    pts = avoided_points(chain, cfg.avoid_links, balls)
    x_mid = ee_path(chain, prior.mean([0.5]))[0]
    near = Sphere(tuple(x_mid + [0.03, 0.0, 0.0]), 0.04)
    box = Box(tuple(x_mid + [0.15, -0.05, -0.05]), tuple(x_mid + [0.25, 0.05, 0.05]))
    req = AdaptRequest(prior, (near, box), None, Q_GOAL - 0.05, Q_START + 0.05,
                       link_balls=balls)
    prob = build_problem(req, chain, cfg)
    rep = {c.name: c for c in prob.constraints if isinstance(c, Repeller)}
    walls = {c.name: c for c in prob.constraints if isinstance(c, Hyperplane)}
    assert sorted(rep) == sorted(f'obstacle_0_{p.name}' for p in pts)
    assert sorted(walls) == sorted(f'obstacle_1_{p.name}' for p in pts)
    plain = build_problem(dataclasses.replace(req, link_balls=None), chain, cfg)
    plain_walls = {c.name: c for c in plain.constraints if isinstance(c, Hyperplane)}
    for p in pts:
        assert rep[f'obstacle_0_{p.name}'].radius == pytest.approx(0.04 + 0.02 + p.radius)
        assert rep[f'obstacle_0_{p.name}'].point.point == p.poi
    # the wall of the end effector (radius 0) is the plain one; a ball's is moved out by its
    # radius along the wall's normal
    ee_wall = walls['obstacle_1_ee']
    np.testing.assert_allclose(ee_wall.offset, plain_walls['obstacle_1_ee'].offset)
    same_face = 0
    for p in pts[1:]:
        w = walls[f'obstacle_1_{p.name}']
        if np.allclose(w.normal, ee_wall.normal):
            assert float((ee_wall.offset - w.offset) @ w.normal) == pytest.approx(p.radius)
            same_face += 1
    assert same_face >= 1
    # influence_distance per point: only the balls that come that close to the sphere along
    # the (conditioned) prior mean get its repeller
    grid = np.linspace(0.0, 1.0, cfg.n_steps)
    X = chain.forward(prob.prior.mean(grid), [p.poi for p in pts])       # (n, P, 3)
    gap = (np.linalg.norm(X - np.asarray(near.center), axis=-1) - near.radius
           - np.array([p.radius for p in pts])).min(axis=0)
    assert gap.min() < 0.1 < gap.max()
    tight = build_problem(req, chain, dataclasses.replace(cfg, influence_distance=0.1))
    assert sorted(c.name for c in tight.constraints if isinstance(c, Repeller)) == sorted(
        f'obstacle_0_{p.name}' for p, g in zip(pts, gap) if g <= 0.1)
    # a sphere 5 cm beside the hand's balls at the start: near with balls, a contact at the
    # conditioned start with the ball; 5 cm past the origin's margin without
    x0 = chain.forward(Q_START, [p.poi for p in pts])
    hand = max(range(len(pts)), key=lambda i: pts[i].radius)
    out = x0[hand] + np.array([0.0, 0.0, 1.0]) * (pts[hand].radius + 0.04 + 0.01)
    start = Sphere(tuple(out), 0.04)
    bad = build_problem(AdaptRequest(prior, (start,), None, None, Q_START, link_balls=balls),
                        chain, cfg)
    assert any(f'contains the {pts[hand].name} at the conditioned start' in m
               for m in bad.infeasible), bad.infeasible


def test_user_constraint_set_is_added_and_validated(chain, prior):
    doc = {'constraints': [{'type': 'waypoint', 'name': 'via', 'point': {'link': 'ee'},
                            'center': [0.4, 0.0, 0.5], 'radius': 0.05, 'support': [0.5, 0.5]}],
           'optimizer': {'max_outer': 3}}
    prob = build_problem(AdaptRequest(prior, (), doc), chain, AdaptRequestConfig())
    assert isinstance(prob.constraints[-1], Waypoint) and prob.constraints[-1].name == 'via'
    assert prob.config.max_outer == 3
    bad = json.loads(json.dumps(doc))
    bad['constraints'][0]['point'] = {'joint': 9}
    with pytest.raises(ConstraintSetError, match='joint'):
        build_problem(AdaptRequest(prior, (), bad), chain, AdaptRequestConfig())


def test_run_request_avoids_a_sphere_on_the_mean_path(chain, prior, rng):
    cfg = AdaptRequestConfig(n_steps=25, alpha=0.95, obstacle_margin=0.0)
    centre = ee_path(chain, prior.mean([0.5]))[0]
    ob = Sphere(tuple(centre), 0.05)
    res = run_request(AdaptRequest(prior, (ob,), None, None, Q_START), chain, cfg)
    assert res.outcome == 'converged', res.report.to_text()
    path = ee_path(chain, res.adapted.mean(np.linspace(0, 1, 201)))
    assert np.min(np.linalg.norm(path - centre, axis=1)) > 0.05     # the mean goes around
    # Monte Carlo over sampled trajectories on the optimiser's grid (independent of the
    # Gamma approximation): every per-time satisfaction close to alpha or better
    reps = [c for c in res.problem.constraints if isinstance(c, Repeller)]
    per_time, _, _ = monte_carlo_satisfaction(res.adapted, reps, 4000, rng, n_steps=25)
    assert np.all(per_time >= 0.93), per_time


def test_obstacle_at_the_conditioned_start_is_infeasible(chain, prior):
    x0 = ee_path(chain, Q_START[None])[0]
    cfg = AdaptRequestConfig(n_steps=15)
    res = run_request(AdaptRequest(prior, (Sphere(tuple(x0), 0.05),), None, None, Q_START),
                      chain, cfg)
    assert res.outcome == 'infeasible'
    assert res.problem.infeasible == ['obstacle 0 (with its margin) contains the ee at the '
                                      'conditioned start']
    p_ee = [c.probability for c in res.report.constraints if c.name == 'obstacle_0_ee']
    assert p_ee[0] < 0.5
    assert res.report.n_outer == 1 and res.report.n_inner <= 50   # a short solve only


def test_promp_message_is_the_primitive_file_document(prior):
    from cdmp_ros.core.adaptation.requests import promp_message
    p = prior.copy()
    p.metadata = {'adapter': {'outcome': 'converged'}}
    d = json.loads(promp_message(p))
    assert np.array_equal(primitive_from_dict(d).cov_w, p.cov_w)   # bit for bit
    d['promp']['cov_w'] = p.cov_w.tolist()   # the compact covariance aside, the same document
    del d['promp']['cov_w_base64']
    assert d == primitive_to_dict(p)          # which validates against the schema


def test_classify():
    def report(conv, status):
        return AdaptationReport(conv, status, 0.0, 0.0, 1, 1, 1, 0.0, [])
    assert classify(report(True, 'converged')) == 'converged'
    assert classify(report(False, 'stalled_infeasible')) == 'infeasible'
    assert classify(report(False, 'infeasible_or_unconverged')) == 'unconverged'
    assert classify(report(False, 'infeasible_or_unconverged'), ['reason']) == 'infeasible'


def test_ee_band_matches_monte_carlo(chain, prior, rng):
    s = np.linspace(0.1, 0.9, 5)
    centres, radii = ee_band(prior, chain, s, n_sigma=2.0)
    Y = prior.sample_trajectories(s, 20000, rng)              # (n_samples, 5, 7)
    X = chain.forward(Y, [EE])[:, :, 0]                       # (n_samples, 5, 3)
    for i in range(len(s)):
        C = np.cov(X[:, i].T)
        sd = np.sqrt(np.linalg.eigvalsh(C)[-1])
        assert radii[i] == pytest.approx(2.0 * sd, rel=0.1)
        np.testing.assert_allclose(centres[i], X[:, i].mean(axis=0), atol=0.01)


@pytest.mark.parametrize('cls, kw, text', [
    (AdapterConfig, dict(max_input_rate=-1.0), 'max_input_rate'),
    (AdapterConfig, dict(joint_names=('a', 'a')), 'joint_names'),
    (AdapterConfig, dict(path_points=1), 'path_points'),
    (AdaptRequestConfig, dict(alpha=1.0), 'alpha'),
    (AdaptRequestConfig, dict(n_steps=2.5), 'n_steps'),
    (AdaptRequestConfig, dict(avoid_links=('x', 'x')), 'avoid_links'),
    (AdaptRequestConfig, dict(joint_limits=1), 'joint_limits')])
def test_configs_refuse_bad_values(cls, kw, text):
    with pytest.raises(ValidationError, match=text):
        cls(**kw)


def test_config_file_mirrors_every_parameter_with_its_default(repo_root):
    """config/adapter.yaml lists every parameter of the adapter node, with the defaults."""
    import dataclasses
    import os
    import yaml
    with open(os.path.join(repo_root, 'config', 'adapter.yaml')) as f:
        params = yaml.safe_load(f)['/**']['ros__parameters']
    sections = {AdapterConfig: params, AdaptRequestConfig: params.pop('adaptation')}
    for cls, values in sections.items():
        assert set(values) == {f.name for f in dataclasses.fields(cls)}, cls.__name__
        default = cls()
        for name, v in values.items():
            expected = getattr(default, name)
            assert (tuple(v) if isinstance(v, list) else v) == expected, name


#: Event 28 of the tracked seed-3 stream of bench_adaptation_latency.py: three spheres (centre,
#: radius) crossing the path of the Panda ProMP of panda_problem(rng 3).
CROSSING = (
    ((0.14197434090346323, -0.5559164448230759, 0.41622114747200323), 0.078123423470853),
    ((0.10719368055708747, -0.612828266953128, 0.43926122747502144), 0.08929553957831061),
    ((0.016736904811588002, 0.022277103212172245, 0.7151874133861116), 0.08200094956121073))


#: Request 17 of heading 4 of bench_warm_track.py (the same prior; start_y of its events): its
#: largest violation jumps 0.05 -> 0.48 at the 4th outer iteration, and the 5th recovers.
RECOVERING = (
    ((0.15219578955832813, -0.5123146764940745, 0.41622114747200323), 0.078123423470853),
    ((0.16327702150668166, -0.6409375753513192, 0.43926122747502144), 0.08929553957831061),
    ((0.02592431615030491, -0.011338352731755135, 0.7151874133861116), 0.08200094956121073))
RECOVERING_START = (-0.9924980133188688, -0.4096203595543825, 0.7252253064460099,
                    -1.4624724944170997, -0.9642424079274414, 1.7655299206634298,
                    -0.04945764163532023)


@pytest.fixture(scope='module')
def panda_rng3():
    """The Panda chain and the ProMP of panda_problem(rng 3) (the benchmarks' prior)."""
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.experiments.promp_problems import panda_problem
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    chain = panda_chain(panda_urdf_path())
    prior, _, _ = panda_problem(chain, np.random.default_rng(3), n_spheres=1)
    prior.joint_names = list(chain.joint_names)
    return chain, prior


@pytest.mark.parametrize('spheres', [RECOVERING, CROSSING], ids=['recovering', 'crossing'])
def test_requests_whose_multiplier_steps_jump_converge(panda_rng3, spheres):
    """Two requests whose largest violation jumps during the solve (RECOVERING: the next outer
    iteration recovers; CROSSING: the step overshoots, and without the backtracking the solve
    diverged, KL 136,461 after 2,673 evaluations) converge and pass their sampled verification.
    Whether a given solve backtracks flips with the last bit of its inputs (with the BLAS of
    the machine), so the backtracking itself is tested on scripted inner loops
    (test_core_promp_backtracking.py)."""
    chain, prior = panda_rng3
    start = RECOVERING_START if spheres is RECOVERING else prior.mean([0.0])[0]
    req = AdaptRequest(prior, tuple(Sphere(c, r) for c, r in spheres), start_y=start,
                       continues=True)
    res = run_request(req, chain, AdaptRequestConfig())
    assert res.outcome == 'converged' and res.report.verification.holds
