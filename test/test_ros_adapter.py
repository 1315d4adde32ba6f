"""The adapter as a real process (``python -m cdmp_ros.nodes.adapter``), driven over DDS.

One adapter process serves the module (localhost only, the session's private domain id); the
test process publishes primitives, obstacles, goals, constraint sets and joint_states, and
records adapted_primitive, visualization and diagnostics. Each bad-input case publishes its
input, waits for the matching ``diagnostics`` entry and checks that the node is still up.
Bounded: every wait has a timeout.
"""
import json
import os
import time

import numpy as np
import pytest

from adapter_harness import (PANDA_JOINTS, Q_GOAL, Q_START, Harness, reach_cdmp,
                             reach_promp, start_adapter, stop_process)
from markers import MARKER_CASES, bad_marker
from node_harness import (GOAL_CASES, JOINT_STATE_CASES, assert_clean_stop, bad_joint_state,
                          expect_startup_failures, running)
from cdmp_ros.core.primitive_io import dumps_primitive

pytestmark = pytest.mark.ros
DOMAIN = int(os.environ['ROS_DOMAIN_ID'])
STARTUP = 60.0  # s; interpreter + rclpy start-up on a loaded 2-core machine (a bound)
TIMEOUT = 30.0  # s; bounds a failing wait only
PARAMS = ['diagnostics_period:=0.2', 'max_input_rate:=20.0', 'max_json_bytes:=300000',
          'adaptation.n_steps:=20', 'adaptation.alpha:=0.99', 'adaptation.max_outer:=4',
          'adaptation.max_inner:=150']
Q_ROBOT = Q_START + np.array([0.05, -0.05, 0.05, 0.05, -0.05, 0.05, -0.05])


@pytest.fixture(scope='module')
def prims():
    return {'promp': dumps_primitive(reach_promp(n_basis=5)),
            'cdmp': dumps_primitive(reach_cdmp())}


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log = tmp_path_factory.mktemp('adapter') / 'adapter.log'
    proc = start_adapter(DOMAIN, PARAMS, log_path=str(log))
    h = Harness(DOMAIN)
    with running(proc, h, log, lambda: bool(h.states_since(0)), STARTUP, 'adapter'):
        h.robot_q = Q_ROBOT
        # the ProMP tests condition on this state: wait until the adapter has it
        t0 = time.monotonic()
        assert h.wait_state(lambda m, lv, kv: kv.get('robot_state') == 'fresh', t0, TIMEOUT), \
            h.states_since(t0)[-1:]
        yield h, proc, log


def use(h, prims, kind):
    """Make ``kind`` the adapter's primitive (a ProMP is adapted at once: wait for it)."""
    from std_msgs.msg import String
    t0 = time.monotonic()
    n0 = h.n_adapted()
    with h.lock:   # (request ids grow; a refinement keeps the id of the request it refines)
        last = max((a[1].get('metadata', {}).get('adapter', {}).get('request_id', -1)
                    for a in h.adapted), default=-1)
    h.publish('primitive', String(data=prims[kind]))
    assert h.wait_state(lambda m, lv, kv: kv.get('primitive') == kind, t0, TIMEOUT)
    if kind == 'promp':
        # the answer to the request this primitive made: not a refinement of an earlier
        # request of the same text, which the harness may receive after it read ``last``
        # (then the test's next obstacle arrived while the primitive's request was pending,
        # and it rightly started the motion anew: a soak failure of the warm-start test)
        d = h.wait_adapted(n0, source=prims[kind], pred=lambda d: d['metadata']['adapter'].get(
            'request_id', -1) > last and d['metadata']['adapter'].get('trigger') == 'primitive')
        assert d is not None and d['kind'] == 'promp', h.states_since(t0)[-2:]
        return d
    return None


def alive(h, proc):
    """The node is up and still reporting."""
    t = time.monotonic()
    assert proc.poll() is None, 'adapter died'
    assert h.wait_state(lambda m, lv, kv: True, t, TIMEOUT), 'no diagnostics any more'


def no_obstacles(d):
    """An adapted primitive computed without obstacles (a wait_adapted predicate: not the
    refinement of an earlier request with obstacles, also triggered by 'obstacles')."""
    return d['metadata']['adapter']['obstacles_used'] == 0


def clear_obstacles(h, kind='promp'):
    """Remove every obstacle and wait until the adapter took it in: for a ProMP (``kind``, the
    adapter's primitive) the answer computed without obstacles (returned), for a DMP / CDMP
    the diagnostics counting none. A test that returned before would race the next test's
    primitive: the two topics are not ordered, and a late obstacle request supersedes a
    primitive's pending one (a soak failure of ``use``, which then waited for an answer with
    trigger 'primitive' that never came)."""
    from visualization_msgs.msg import Marker, MarkerArray
    t0 = time.monotonic()
    n0 = h.n_adapted()
    h.publish('obstacles', MarkerArray(markers=[Marker(action=Marker.DELETEALL)]))
    if kind == 'promp':
        # (not a refinement of the last request, also triggered by 'obstacles')
        d = h.wait_adapted(n0, trigger='obstacles', pred=no_obstacles)
        assert d is not None and d['metadata']['adapter']['obstacles_used'] == 0
        return d
    assert h.wait_state(lambda m, lv, kv: kv.get('obstacles') == '0', t0, TIMEOUT)
    return None


def promp_of(d):
    from cdmp_ros.core.primitive_io import promp_from_dict
    return promp_from_dict(d)


def ee(chain, Y):
    from cdmp_ros.core.kinematics import PointOfInterest
    return chain.forward(np.asarray(Y), [PointOfInterest('ee')])[..., 0, :]


def converged_state(h, t0, request_trigger):
    return h.wait_state(lambda m, lv, kv: kv.get('outcome') == 'converged'
                        and kv.get('trigger') == request_trigger, t0, TIMEOUT)


# -- ProMP -------------------------------------------------------------------------------------
def test_promp_is_adapted_conditioned_on_the_current_state(graph, prims):
    h, proc, _ = graph
    t0 = time.monotonic()
    d = use(h, prims, 'promp')
    assert d['metadata']['adapter']['trigger'] == 'primitive'
    assert d['metadata']['adapter']['outcome'] == 'converged'
    np.testing.assert_allclose(promp_of(d).mean([0.0])[0], Q_ROBOT, atol=0.03)
    m, level, kv = converged_state(h, t0, 'primitive')
    assert level == 0
    for key in ('solve_time_ms', 'kl', 'iterations', 'requests_received', 'requests_dropped',
                'p.limit_panda_joint4'):
        assert key in kv, kv
    assert float(kv['p.limit_panda_joint4'].split()[0]) >= 0.99


def test_sphere_obstacle_is_avoided_and_shown(graph, prims, chain):
    from visualization_msgs.msg import Marker, MarkerArray
    h, proc, _ = graph
    prior = promp_of(use(h, prims, 'promp'))
    centre = ee(chain, prior.mean([0.5]))[0]
    t0 = time.monotonic()
    n0 = h.n_adapted()
    h.publish('obstacles', MarkerArray(markers=[h.sphere(centre, 0.05)]))
    d = h.wait_adapted(n0, trigger='obstacles')
    assert d is not None and d['metadata']['adapter']['trigger'] == 'obstacles'
    # the primitive's motion was published: the obstacle reshapes it (continues), unconditioned
    # on the robot's state at phase 0 (the use() adaptation was: Q_ROBOT)
    assert d['metadata']['adapter']['continues'] is True
    assert np.abs(promp_of(d).mean([0.0])[0] - Q_ROBOT).max() > 0.03
    path = ee(chain, promp_of(d).mean(np.linspace(0, 1, 201)))
    assert np.linalg.norm(path - centre, axis=1).min() > 0.05
    m, level, kv = converged_state(h, t0, 'obstacles')
    assert kv['obstacles_used'] == '1' and 'p.obstacle_0_ee' in kv
    # link_geometry (config/adapter.yaml): panda_link4 as the two balls over its capsule
    assert 'p.obstacle_0_panda_link4_0' in kv and 'p.obstacle_0_panda_link4_1' in kv
    assert h.wait(lambda: any(mk.ns == 'obstacles' for mk in h.last_viz().markers), TIMEOUT)
    viz = h.last_viz().markers
    assert viz[0].action == Marker.DELETEALL
    line = [mk for mk in viz if mk.ns == 'path']
    assert len(line) == 1 and line[0].type == Marker.LINE_STRIP and len(line[0].points) == 50
    band = [mk for mk in viz if mk.ns == 'uncertainty']
    assert len(band) == 10 and all(mk.scale.x > 0 for mk in band)
    obs = [mk for mk in viz if mk.ns == 'obstacles']
    assert len(obs) == 1 and obs[0].scale.x == pytest.approx(0.1)
    clear_obstacles(h)


def test_a_moved_obstacle_is_solved_from_the_last_solution(graph, prims, chain):
    """Warm starts (adaptation.warm_start): an obstacle that moved 1 cm is solved from the
    last solution (metadata and diagnostics say so), then refined cold while the solver is
    idle (published only if better); with the parameter off, cold."""
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    prior = promp_of(use(h, prims, 'promp'))
    centre = ee(chain, prior.mean([0.5]))[0]

    def move_to(x):
        n0 = h.n_adapted()
        m = h.sphere(x, 0.05)
        stamp = m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec
        h.publish('obstacles', MarkerArray(markers=[m]))
        # the answer to this message (a refinement of the last request, also triggered by
        # 'obstacles', may be published meanwhile)
        d = h.wait_adapted(n0, trigger='obstacles', pred=lambda d: d['metadata']['adapter'].get(
            'trigger_stamp_ns') == stamp)
        assert d is not None
        path = ee(chain, promp_of(d).mean(np.linspace(0, 1, 201)))
        assert np.linalg.norm(path - x, axis=1).min() > 0.05
        return d['metadata']['adaptation'], d['metadata']['adapter']['request_id']

    def ended(kv):  # refinements started, published, kept warm, cancelled, failed; if all
        n = [int(kv.get(f'refinements_{k}', 0)) for k in      # ended
             ('started', 'published', 'kept_warm', 'cancelled', 'failed')]
        return n if sum(n[1:]) == n[0] else None

    def settled(rid):  # the diagnostics after request rid's result (which started any
        # refinement of it, and counted it) with no refinement running
        return lambda m, lv, kv: kv.get('request_id') == str(rid) and ended(kv) is not None

    try:
        _, rid0 = move_to(centre)
        t = time.monotonic()  # (a refinement of this or an earlier warm solve may be running)
        st = h.wait_state(settled(rid0), t - 1.0, TIMEOUT)
        assert st is not None, h.states_since(t)[-1:]
        before = ended(st[2])
        t0 = time.monotonic()
        rep, rid = move_to(centre + [0.0, 0.01, 0.0])
        assert rep['start'] == 'warm', (rep.get('start_note'), rep['status'], h.history())
        assert rep['n_evaluations'] >= 1
        # the diagnostics of this request (the last one's are repeated every period)
        st = h.wait_state(lambda m, lv, kv: kv.get('request_id') == str(rid), t0, TIMEOUT)
        assert st is not None, h.states_since(t0)[-2:]
        kv = st[2]
        assert kv['start'] == 'warm' and int(kv['starts_warm']) >= 1, kv
        # its refinement ran to its end (nothing else was requested): published or dropped
        st = h.wait_state(lambda m, lv, kv: (ended(kv) or [0])[0] == before[0] + 1, t0,
                          TIMEOUT)
        assert st is not None, h.states_since(t0)[-1:]
        after = ended(st[2])
        assert after[3:] == before[3:] and after[1] + after[2] == before[1] + before[2] + 1
        assert h.set_parameter('adaptation.warm_start', False).successful
        rep, _ = move_to(centre + [0.0, 0.02, 0.0])
        assert rep['start'] == 'cold', rep
    finally:
        assert h.set_parameter('adaptation.warm_start', True).successful
        clear_obstacles(h)


def test_box_obstacle_becomes_a_wall(graph, prims, chain):
    from cdmp_ros.core.adaptation.requests import obstacle_distance
    from cdmp_ros.core.kinematics import Box
    from visualization_msgs.msg import Marker, MarkerArray
    h, proc, _ = graph
    prior = promp_of(use(h, prims, 'promp'))
    centre = ee(chain, prior.mean([0.5]))[0] + np.array([0.0, 0.0, -0.12])
    m = h.sphere(centre, 0.05, mid=2)
    m.type = Marker.CUBE
    m.scale.x, m.scale.y, m.scale.z = 0.3, 0.3, 0.1
    n0 = h.n_adapted()
    h.publish('obstacles', MarkerArray(markers=[m]))
    d = h.wait_adapted(n0, trigger='obstacles',
                       pred=lambda d: d['metadata']['adapter']['obstacles_used'] == 1)
    assert d is not None and d['metadata']['adapter']['obstacles_used'] == 1
    box = Box(tuple(centre - [0.15, 0.15, 0.05]), tuple(centre + [0.15, 0.15, 0.05]))
    path = ee(chain, promp_of(d).mean(np.linspace(0, 1, 201)))
    assert obstacle_distance(box, path).min() > 0.0
    clear_obstacles(h)


def test_goal_and_goal_point_condition_the_end(graph, prims, chain):
    h, proc, _ = graph
    use(h, prims, 'promp')
    goal = Q_GOAL + 0.1
    n0 = h.n_adapted()
    h.publish('goal', h.joint_state(goal))
    d = h.wait_adapted(n0, trigger='goal', pred=lambda d: np.allclose(
        promp_of(d).mean([1.0])[0], goal, atol=0.03))
    assert d is not None
    np.testing.assert_allclose(promp_of(d).mean([1.0])[0], goal, atol=0.03)
    target = ee(chain, Q_GOAL - 0.1)
    n0 = h.n_adapted()
    h.publish('goal_point', h.make_point(target))
    d = h.wait_adapted(n0, trigger='goal_point')
    assert d['metadata']['adapter']['trigger'] == 'goal_point'
    assert np.linalg.norm(ee(chain, promp_of(d).mean([1.0])[0]) - target) < 0.02
    assert h.wait(lambda: any(mk.ns == 'goal' for mk in h.last_viz().markers), TIMEOUT)


def test_user_constraint_set_is_applied(graph, prims):
    from std_msgs.msg import String
    h, proc, _ = graph
    before = promp_of(use(h, prims, 'promp'))
    via = float(before.mean([0.5])[0][0]) + 0.08   # about one standard deviation away
    doc = {'constraints': [{'type': 'waypoint', 'name': 'via', 'point': {'joint': 0},
                            'center': [via], 'radius': 0.03, 'support': [0.5, 0.5],
                            'alpha': 0.95}]}
    t0 = time.monotonic()
    n0 = h.n_adapted()
    h.publish('constraints', String(data=json.dumps(doc)))
    d = h.wait_adapted(n0, trigger='constraints')
    assert abs(promp_of(d).mean([0.5])[0][0] - via) < 0.03
    m, level, kv = converged_state(h, t0, 'constraints')
    assert float(kv['p.via'].split()[0]) >= 0.95 - 1e-3
    # the sampled verification of the solve (issue 12): the figures of cdmp adapt --json
    assert kv['verification.guarantee'] == 'per_step' and kv['verification.holds'] == 'True'
    n = int(kv['verification.n_samples'])
    traj = float(kv['verification.trajectory_violation'])
    assert n >= 1000 and 0.0 <= traj <= float(kv['verification.trajectory_violation_upper95'])
    via = kv['v.via'].split()
    assert via[0::2] == ['per_step_max', 'trajectory', 'upper95', 'detectable_excess']
    # the weakest constraint's figure is the report's (joint limits are constraints too)
    assert 1.0 < float(via[7]) <= float(kv['verification.detectable_excess']) < 20.0
    assert float(via[1]) <= 0.05 + 5 * (0.05 * 0.95 / n) ** 0.5
    assert d['metadata']['adaptation']['verification']['n_samples'] == n
    n0 = h.n_adapted()
    h.publish('constraints', String(data=json.dumps({'constraints': []})))
    assert h.wait_adapted(n0, trigger='constraints') is not None


def test_infeasible_request_keeps_the_last_good_primitive(graph, prims, chain):
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    use(h, prims, 'promp')
    # the robot is inside the sphere; the obstacle's own request continues the running motion
    # (not conditioned on the robot's state), a new goal restarts the motion from the robot's
    # state: the ProMP is conditioned to start inside the sphere
    t0 = time.monotonic()
    h.publish('obstacles', MarkerArray(markers=[h.sphere(ee(chain, Q_ROBOT), 0.1, mid=3)]))
    assert h.wait_state(lambda m, lv, kv: kv.get('trigger') == 'obstacles'
                        and kv.get('outcome') in ('converged', 'infeasible', 'unconverged'),
                        t0, 30.0) is not None
    t0 = time.monotonic()
    n0 = h.n_adapted()
    h.publish('goal', h.joint_state(Q_GOAL))
    st = h.wait_state(lambda m, lv, kv: kv.get('outcome') == 'infeasible'
                      and kv.get('trigger') == 'goal', t0, 30.0)
    assert st is not None
    m, level, kv = st
    assert level == 2 and 'last good primitive kept' in m
    assert 'obstacle 0 (with its margin) contains the ee at the conditioned start' in m
    assert 'p.obstacle_0_ee' in kv and float(kv['p.obstacle_0_ee'].split()[0]) < 0.99
    assert h.n_adapted() == n0
    # the goal's motion-starting request failed: the next request starts the motion too
    assert clear_obstacles(h)['metadata']['adapter']['continues'] is False
    alive(h, proc)


# -- DMP / CDMP --------------------------------------------------------------------------------
def test_cdmp_goal_is_retargeted_with_the_same_weights(graph, prims):
    h, proc, _ = graph
    use(h, prims, 'cdmp')
    goal = np.array([0.3, 0.0, -0.2, -1.6, 0.1, 1.8, 0.5])
    n0 = h.n_adapted()
    h.publish('goal', h.joint_state(goal[::-1], names=PANDA_JOINTS[::-1]))  # shuffled
    d = h.wait_adapted(n0, trigger='goal', pred=lambda d: d['kind'] == 'cdmp' and np.allclose(
        d['dmp']['goal'], goal))
    assert d['kind'] == 'cdmp' and d['metadata']['adapter']['outcome'] == 'retargeted'
    np.testing.assert_allclose(d['dmp']['goal'], goal)
    assert d['dmp']['weights'] == json.loads(prims['cdmp'])['dmp']['weights']


def test_cdmp_goal_outside_the_limits_is_clipped(graph, prims, chain):
    h, proc, _ = graph
    use(h, prims, 'cdmp')
    t0 = time.monotonic()
    goal = np.array([0.3, 5.0, -0.2, 1.0, 0.1, 1.8, 0.5])
    n0 = h.n_adapted()
    h.publish('goal', h.joint_state(goal))
    d = h.wait_adapted(n0, trigger='goal', pred=lambda d: d['dmp']['goal'][1] > 1.8)
    assert h.wait_diag('clipped with the CDMP margin: panda_joint2 5 -> 1.831', t0,
                       name='input goal')
    g = np.array(d['dmp']['goal'])
    assert np.all(g < chain.upper) and np.all(g > chain.lower)


def test_cdmp_goal_point_goes_through_the_ik(graph, prims, chain):
    h, proc, _ = graph
    use(h, prims, 'cdmp')
    target = ee(chain, np.array([0.5, 0.1, 0.2, -1.4, 0.1, 1.9, 0.4]))
    n0 = h.n_adapted()
    h.publish('goal_point', h.make_point(target))
    d = h.wait_adapted(n0, trigger='goal_point')
    assert np.linalg.norm(ee(chain, d['dmp']['goal']) - target) <= 1e-3 + 1e-9


def test_cdmp_joint_goals_can_be_left_to_the_streamer(graph, prims):
    h, proc, _ = graph
    use(h, prims, 'cdmp')
    assert h.set_parameter('retarget_dmp_on_goal', False).successful
    try:
        t0 = time.monotonic()
        n0 = h.n_adapted()
        h.publish('goal', h.joint_state(Q_GOAL - 0.05))
        assert h.wait_state(lambda m, lv, kv: 'goal left to the streamer' in m, t0, TIMEOUT)
        # no answer to this goal (an answer to the primitive itself, or to an earlier
        # request, may still arrive after n0 on a loaded machine)
        with h.lock:
            late = [d['metadata'].get('adapter', {}) for _, d in h.adapted[n0:]]
        assert not [m for m in late if m.get('trigger') == 'goal'], late
    finally:
        assert h.set_parameter('retarget_dmp_on_goal', True).successful


def test_cdmp_obstacles_are_only_shown(graph, prims):
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    use(h, prims, 'cdmp')
    n0 = h.n_adapted()
    h.publish('obstacles', MarkerArray(markers=[h.sphere([0.4, 0.3, 0.4], 0.05, mid=9)]))
    assert h.wait(lambda: any(mk.ns == 'obstacles' for mk in h.last_viz().markers)
                  and any(mk.ns == 'path' for mk in h.last_viz().markers), TIMEOUT)
    assert h.n_adapted() == n0
    clear_obstacles(h, 'cdmp')


# -- bad input: one test per case --------------------------------------------------------------
def _bad_joint_state(h, case):
    msg = bad_joint_state(lambda dt: h.joint_state(Q_ROBOT, stamp_offset=dt), case)
    if case == 'outside_limits':
        msg.position[3] = 1.0
    return msg


JS_CASES = dict(JOINT_STATE_CASES, outside_limits="'panda_joint4': 1 is outside the limits")


@pytest.mark.parametrize('case', sorted(JS_CASES))
def test_bad_joint_states_are_rejected(graph, case):
    h, proc, _ = graph
    # joint_states is best effort (sensor QoS): published until the rejection is reported
    h.reject('joint_states', lambda: _bad_joint_state(h, case), JS_CASES[case], resend=True)
    alive(h, proc)


@pytest.mark.parametrize('case', sorted(GOAL_CASES))
def test_bad_goals_are_rejected(graph, case):
    h, proc, _ = graph
    n0 = h.n_adapted()
    h.reject('goal', lambda: _bad_joint_state(h, case), GOAL_CASES[case])
    assert h.n_adapted() == n0
    alive(h, proc)


GOAL_POINT_CASES = {
    'nan': (dict(xyz=[float('nan'), 0.0, 0.5]), 'point.x: expected a finite value, got nan'),
    'inf': (dict(xyz=[0.3, float('inf'), 0.5]), 'point.y: expected a finite value, got inf'),
    'other_frame': (dict(frame='camera'), "expected the robot base frame 'panda_link0'"),
    'future_stamp': (dict(stamp_offset=60.0), 'in the future'),
    'past_stamp': (dict(stamp_offset=-3600.0), 'in the past'),
    'unreachable': (dict(xyz=[3.0, 0.0, 0.5]), 'unreachable inside the joint limits (IK '
                                               'residual'),
}


@pytest.mark.parametrize('case', sorted(GOAL_POINT_CASES))
def test_bad_goal_points_are_rejected(graph, case):
    h, proc, _ = graph
    kw, text = GOAL_POINT_CASES[case]
    kw = dict(kw)
    xyz = kw.pop('xyz', [0.4, 0.0, 0.5])
    n0 = h.n_adapted()
    h.reject('goal_point', lambda: h.make_point(xyz, **kw), text)
    assert h.n_adapted() == n0
    alive(h, proc)


@pytest.mark.parametrize('case', sorted(MARKER_CASES))
def test_bad_markers_are_rejected(graph, case):
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    m, text = bad_marker(case)
    t0 = h.reject('obstacles', lambda: MarkerArray(markers=[m]), text)
    assert h.wait_state(lambda msg, lv, kv: kv.get('obstacles') == '0', t0, TIMEOUT)
    alive(h, proc)


def _promp_dict(prims):
    return json.loads(prims['promp'])


PRIMITIVE_CASES = {
    'malformed_json': (lambda d: json.dumps(d)[:-5], 'primitive: not valid JSON'),
    'not_an_object': (lambda d: '[1, 2, 3]', 'expected a JSON object'),
    'schema_violation': (lambda d: json.dumps(dict(d, duration=-1.0)),
                         'primitive.duration: expected a value >= 0.001, got -1.0'),
    'wrong_joints': (lambda d: json.dumps(dict(d, joint_names=[f'j{i}' for i in range(7)])),
                     'expected the robot joints'),
    'nan_mean': (lambda d: json.dumps(d).replace('"mean_w": [', '"mean_w": [NaN, ', 1),
                 'primitive.promp'),
    'too_large': (lambda d: json.dumps(dict(d, metadata={'pad': 'x' * 400000})),
                  'exceeds max_json_bytes = 300000'),
}


@pytest.mark.parametrize('case', sorted(PRIMITIVE_CASES))
def test_bad_primitives_are_rejected(graph, prims, case):
    from std_msgs.msg import String
    h, proc, _ = graph
    use(h, prims, 'cdmp')
    make, text = PRIMITIVE_CASES[case]
    n0 = h.n_adapted()
    t0 = h.reject('primitive', lambda: String(data=make(_promp_dict(prims))), text)
    assert h.wait_state(lambda m, lv, kv: kv.get('primitive') == 'cdmp', t0, TIMEOUT)  # kept
    assert h.n_adapted() == n0
    alive(h, proc)


CONSTRAINT_CASES = {
    'malformed_json': ('{"constraints": [', 'constraints: not valid JSON'),
    'not_an_object': ('[]', 'constraint_set: expected a JSON object'),
    'unknown_type': (json.dumps({'constraints': [{'type': 'teleport'}]}),
                     'constraints[0].type (teleport): expected one of'),
    'bad_alpha': (json.dumps({'constraints': [{'type': 'joint_limit', 'joint': 0,
                                               'upper': 1.0, 'alpha': 1.5}]}),
                  'constraints[0].alpha (joint_limit): expected a value < 1, got 1.5'),
    'joint_out_of_range': (json.dumps({'constraints': [
        {'type': 'joint_limit', 'joint': 9, 'upper': 1.0}]}), 'expected an index < 7'),
    'nan_center': ('{"constraints": [{"type": "repeller", "point": {"link": "ee"}, '
                   '"center": [NaN, 0, 0], "radius": 0.1}]}',
                   'constraints[0].center[0] (repeller): expected a finite number, got nan'),
    'too_large': (json.dumps({'constraints': [], 'pad': 'x' * 400000}),
                  'exceeds max_json_bytes = 300000'),
    'unknown_link': (json.dumps({'constraints': [
        {'type': 'repeller', 'point': {'link': 'nose'}, 'center': [0, 0, 0], 'radius': 0.1}]}),
        'expected "ee" or one of'),
}


@pytest.mark.parametrize('case', sorted(CONSTRAINT_CASES))
def test_bad_constraint_sets_are_rejected(graph, prims, case):
    from std_msgs.msg import String
    h, proc, _ = graph
    use(h, prims, 'promp')
    text, reason = CONSTRAINT_CASES[case]
    h.reject('constraints', lambda: String(data=text), reason)
    alive(h, proc)


def test_parameters_have_descriptors_with_ranges(graph):
    from rcl_interfaces.srv import DescribeParameters
    h, proc, _ = graph
    client = h.node.create_client(DescribeParameters, '/adapter/describe_parameters')
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        fut = client.call_async(DescribeParameters.Request(
            names=['adaptation.alpha', 'path_points', 'joint_names']))
        assert h.wait(fut.done, TIMEOUT)
        alpha, points, names = fut.result().descriptors
    finally:
        h.node.destroy_client(client)
    assert alpha.floating_point_range[0].from_value == 0.5
    assert 'Confidence' in alpha.description
    assert (points.integer_range[0].from_value, points.integer_range[0].to_value) == (2, 1000)
    assert names.read_only


def test_runtime_parameter_changes_are_validated(graph):
    h, proc, _ = graph
    assert 'alpha' in h.refusal('adaptation.alpha', 1.5)
    assert "['nose'] are not links of the robot" in h.refusal('adaptation.avoid_links',
                                                              ['panda_link4', 'nose'])
    # link_geometry (default true) needs collision geometry: the flange has none
    assert "'panda_link8': no <collision> geometry" in h.refusal('adaptation.avoid_links',
                                                                 ['panda_link8'])
    assert 'max_input_rate' in h.refusal('max_input_rate', -5.0)
    assert 'read-only' in h.refusal('joint_names', ['a']).lower()
    r = h.set_parameter('adaptation.obstacle_margin', 0)  # an integer for a float is accepted
    assert r.successful, r.reason
    r = h.set_parameter('adaptation.obstacle_margin', 0.02)
    assert r.successful, r.reason
    assert 'guarantee' in h.refusal('adaptation.guarantee', 'sometimes')
    for mode in ('trajectory', 'per_step'):
        r = h.set_parameter('adaptation.guarantee', mode)
        assert r.successful, r.reason
    assert 'verification_samples' in h.refusal('adaptation.verification_samples', -1)
    alive(h, proc)


def test_flooding_is_dropped_and_latest_request_wins(graph, prims):
    """Above max_input_rate (lowered to 2/s at run time, so that the node sees a flood even
    when the loaded machine slows its executor down) the excess is dropped and reported; the
    accepted goals of a ProMP coalesce in the solver thread (requests_dropped). Each part
    publishes until the node reports it."""
    h, proc, _ = graph
    use(h, prims, 'promp')
    sent = [0]

    def goals(n):
        for _ in range(n):
            h.publish('goal', h.joint_state(Q_GOAL + 0.001 * (sent[0] % 50), zero=True))
            sent[0] += 1
    assert h.set_parameter('max_input_rate', 2.0).successful
    try:
        t0 = time.monotonic()
        assert h.wait(lambda: goals(20) or h.wait_diag('flooding: more than 2 messages/s', t0,
                                                       timeout=0.0, name='input goal'),
                      TIMEOUT)
        # goals admitted faster than the solver runs: the waiting request is replaced
        assert h.set_parameter('max_input_rate', 1000.0).successful
        t1 = time.monotonic()
        _, _, kv = h.wait_state(lambda m, lv, kv: True, t1)  # the count before this part
        dropped0 = int(kv.get('requests_dropped', 0))
        assert h.wait(lambda: goals(5) or h.wait_state(
            lambda m, lv, kv: int(kv.get('requests_dropped', 0)) > dropped0, t1, 0.0),
            TIMEOUT), h.states_since(t1)[-1:]
    finally:
        assert h.set_parameter('max_input_rate', 20.0).successful
    alive(h, proc)


# -- start-up --------------------------------------------------------------------------------
STARTUP_CASES = [('adaptation.alpha:=2.0', 'alpha'), ("urdf_path:='/nonexistent.urdf'",
                                                      'urdf_path'),
                 ('adaptation.avoid_links:=[nose]', 'avoid_links'),
                 ('max_input_rate:=-1.0', 'max_input_rate')]


def test_startup_bad_parameters_exit_nonzero_and_a_restarted_adapter_gets_the_primitive(
        graph, prims, tmp_path):
    """Bad start-up parameters (or file) make the adapter exit 2 naming the parameter. In
    parallel (start-up is slow), a good adapter started after the primitive was published
    (as after a crash and restart) receives it from the transient-local ``primitive`` and
    publishes its adaptation; it runs beside the module's adapter, with its outputs remapped."""
    from std_msgs.msg import String
    from cdmp_ros.ros import qos
    h, proc, _ = graph
    use(h, prims, 'promp')
    got = []
    sub = h.node.create_subscription(String, 'adapted_restart',
                                     lambda m: got.append(json.loads(m.data)),
                                     qos.LATCHED)
    bad_file = tmp_path / 'bad.yaml'
    bad_file.write_text('/**:\n  ros__parameters:\n    adaptation:\n      n_steps: 1\n')
    cases = [([p], None, text) for p, text in STARTUP_CASES]
    cases.append(([], str(bad_file), 'n_steps'))
    logs = [str(tmp_path / f'{i}.log') for i in range(len(cases))]
    procs = [(start_adapter(DOMAIN, params, log_path=path,
                            params_file=pf or 'config/adapter.yaml'), text, path)
             for path, (params, pf, text) in zip(logs, cases)]
    log = tmp_path / 'restart.log'
    second = start_adapter(DOMAIN, PARAMS, log_path=str(log),
                           remaps=['__node:=adapter_restart', 'adapted_primitive:=adapted_restart',
                                   'visualization:=viz_restart', '/diagnostics:=/diag_restart'])
    try:
        expect_startup_failures(procs, STARTUP)
        assert h.wait(lambda: bool(got) or second.poll() is not None, STARTUP), log.read_text()
        meta = got[0]['metadata']['adapter']
        assert meta['trigger'] == 'primitive' and meta['outcome'] == 'converged'
    finally:
        code = stop_process(second)
        h.node.destroy_subscription(sub)
    assert_clean_stop(code, log.read_text(), 'adapter')
