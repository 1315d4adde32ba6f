"""The sim node as a real process (``python -m cdmp_ros.nodes.sim``), driven over DDS.

One sim process (Panda, position control, real time, started from config/sim.yaml) serves the
module on its own private domain (localhost
only); start-up failures and other configurations are in
test_ros_sim_startup.py. Each bad-input case publishes its input,
waits for the matching ``diagnostics`` entry and checks that the node keeps publishing; an
accepted input is shown accepted by the node's own rejection counter (conftest
``assert_not_rejected``). Every wait is on a condition with a generous timeout; rates and
real-time figures are measured by benchmarks/bench_sim_node.py, not here. The module teardown
stops the sim with SIGINT and requires exit code 0.
"""
import os
import time

import numpy as np
import pytest

from conftest import assert_not_rejected, joint_state_rejected, marker_rejected, module_domain
from markers import MARKER_CASES, bad_marker, marker
from node_harness import bad_joint_state, running
from sim_harness import LOWER, PANDA_HOME, PANDA_JOINTS, SimHarness, start_sim, UPPER

pytestmark = pytest.mark.ros
DOMAIN = module_domain(5)
STARTUP = 30.0   # s; interpreter + rclpy + pybullet start-up on a loaded 2-core machine
TIMEOUT = 30.0   # s; bounds a failing wait only
TRACK_TOL = 0.005  # rad; settled position error after a reference ramp (position control)


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log = tmp_path_factory.mktemp('sim') / 'sim.log'
    proc = start_sim(DOMAIN, ['diagnostics_period:=0.2', 'max_input_rate:=50.0',
                              'max_reference_rate:=200.0'],
                     log_path=str(log), params_file='config/sim.yaml')
    h = SimHarness(DOMAIN)
    with running(proc, h, log, lambda: h.n_states() > 10, STARTUP, 'sim'):
        yield h, proc, log


def alive(h, proc, n=20):
    """The node is alive and joint_states keep coming."""
    n0 = h.n_states()
    ok = h.wait(lambda: h.n_states() >= n0 + n, TIMEOUT)
    assert proc.poll() is None, 'sim died'
    assert ok, 'joint_states stopped'


def go_home(h):
    q = h.q()
    if np.abs(q - PANDA_HOME).max() > 1e-3:
        h.ramp(q, PANDA_HOME, 0.5)
    assert h.wait(lambda: np.abs(h.q() - PANDA_HOME).max() < 0.01, TIMEOUT), h.q()


def at_rest(h, speed=1e-3, n=25):
    """The last ``n`` joint_states all report every joint slower than ``speed`` rad/s."""
    with h.lock:
        last = h.states[-n:]
    return len(last) == n and all(np.abs(s[4]).max() < speed for s in last)


def kv_float(kv, key):
    return float(kv[key])


def not_rejected(h, topic, action):
    """Run ``action`` and assert, on the sim's own rejection counter, that nothing it
    published on ``topic`` was rejected."""
    if topic == 'obstacles':
        send = marker_rejected(h, lambda msg: h.publish('obstacles', msg))
    else:
        send = joint_state_rejected(h, lambda msg: h.publish(topic, msg), PANDA_JOINTS,
                                    lambda: h.node.get_clock().now().nanoseconds)
    return assert_not_rejected(h, topic, send, action)


# -- normal operation --------------------------------------------------------------------------
def test_publishes_joint_states_and_ee_pose_on_the_slot_grid(graph):
    h, proc, _ = graph
    n0 = h.n_states()
    assert h.wait(lambda: h.n_states() >= n0 + 500, TIMEOUT), h.n_states() - n0
    with h.lock:
        states = h.states[n0:n0 + 500]
    # one message per 4 ms slot of simulated time, in order: consecutive stamps at least one
    # slot apart and whole physics steps (1 ms) apart; a larger gap where the simulation
    # slipped behind the wall clock (benchmarks/bench_sim_node.py measures how often)
    stamps = np.array([s[1] for s in states], dtype=np.int64)
    gaps_ms = np.diff(stamps) / 1e6
    assert np.all(gaps_ms > 4.0 - 1e-6), gaps_ms.min()
    assert np.abs(gaps_ms - np.round(gaps_ms)).max() < 1e-6, 'a stamp off the physics grid'
    assert h.wait_state(lambda m, kv: float(kv['real_time_factor']) > 0.0), h.last_state()
    names, q, qd, effort = states[-1][2:]
    assert names == list(PANDA_JOINTS) and q.shape == qd.shape == effort.shape == (7,)
    assert np.all(np.isfinite(effort)) and np.abs(effort).max() > 1.0  # holding against gravity
    assert np.abs(q - PANDA_HOME).max() < 0.01  # config/sim.yaml initial_positions
    # ee_pose: the tool centre point by an independent FK (core kinematics), same stamp
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain, PointOfInterest
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    by_stamp = {s[1]: s[3] for s in states}

    def poses():
        with h.lock:
            return [p for p in h.poses if p[1] in by_stamp]
    assert h.wait(lambda: len(poses()) == len(states), TIMEOUT), len(poses())  # one per state
    poses = poses()
    _, stamp, frame, pos, quat = poses[-1]
    assert frame == 'panda_link0'
    ee = chain.forward(by_stamp[stamp], [PointOfInterest('ee')])[0]
    assert np.abs(pos - ee).max() < 1e-4
    assert abs(np.linalg.norm(quat) - 1.0) < 1e-9


def test_tracks_a_published_reference(graph):
    h, proc, _ = graph
    goal = np.array([0.4, -0.3, 0.2, -1.9, 0.1, 1.8, 0.5])
    t0 = time.monotonic()
    h.ramp(h.q(), goal, 1.0)
    assert h.wait(lambda: np.abs(h.q() - goal).max() < TRACK_TOL, TIMEOUT), h.q() - goal
    assert h.wait_state(lambda m, kv: float(kv['tracking_error_rad']) < TRACK_TOL
                        and int(kv['references_received']) >= 10), \
        sorted(h.last_state()[1].items())
    assert h.wait_diag('tracking joint_reference', t0, name='sim: state')
    m, kv = h.last_state()
    assert kv['state'] in ('tracking', 'holding')  # holding once the reference is 0.5 s old
    # during the ramp the error depends on how evenly this process delivers the references
    # (test_sim_live checks the law itself: < 5 mrad on an evenly sampled ramp)
    span = np.abs(goal - PANDA_HOME).max()
    assert float(kv['tracking_error_rad']) <= float(kv['tracking_error_max_rad']) < span
    assert kv['limit_violations'] == '0'
    assert 0.5 <= float(kv['max_limit_usage_since_start']) < 1.0  # joint 4 at home: 0.5
    # the reference goes stale: the last position is held
    assert h.wait_diag('holding: joint_reference stale', t0, name='sim: state')
    assert np.abs(h.q() - goal).max() < TRACK_TOL
    go_home(h)


def test_shuffled_joint_names_are_mapped(graph):
    h, proc, _ = graph
    perm = [6, 2, 0, 5, 1, 3, 4]
    target = PANDA_HOME + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.2])

    def shuffled():
        for _ in range(20):  # a reference stream at 50 Hz
            h.publish('joint_reference', h.reference(target[perm],
                                                     names=[PANDA_JOINTS[i] for i in perm]))
            time.sleep(0.02)
        assert h.wait(lambda: np.abs(h.q() - target).max() < TRACK_TOL, TIMEOUT), \
            h.q() - target
    not_rejected(h, 'joint_reference', shuffled)
    go_home(h)


def _publish_markers(h, *markers):
    from visualization_msgs.msg import MarkerArray
    h.publish('obstacles', MarkerArray(markers=list(markers)))


def test_obstacles_change_the_reported_distance(graph):
    from visualization_msgs.msg import Marker
    h, proc, _ = graph

    def add_modify_delete():
        _publish_markers(h, marker(position=(0.75, 0.0, 0.5), size=0.1))  # ~0.3 m from the hand
        assert h.wait_state(lambda m, kv: kv.get('obstacles') == '1'
                            and float(kv['min_obstacle_distance_m']) < 1.0)
        d1 = float(h.last_state()[1]['min_obstacle_distance_m'])
        assert 0.2 < d1 < 0.4, d1
        _publish_markers(h, marker(position=(0.65, 0.0, 0.5), size=0.1))  # MODIFY: 0.1 m closer
        assert h.wait_state(lambda m, kv: float(kv['min_obstacle_distance_m']) < d1 - 0.05)
        kv = h.last_state()[1]
        d2 = float(kv['min_obstacle_distance_m'])
        assert abs((d1 - d2) - 0.1) < 0.02, (d1, d2)
        assert float(kv['min_obstacle_distance_since_start_m']) <= d2 + 1e-9
        _publish_markers(h, Marker(ns='obs', id=1, action=Marker.DELETE))
        assert h.wait_state(lambda m, kv: kv.get('obstacles') == '0'
                            and kv['min_obstacle_distance_m'] == 'inf')
        assert float(h.last_state()[1]['min_obstacle_distance_since_start_m']) <= d2 + 1e-9
    not_rejected(h, 'obstacles', add_modify_delete)


def test_contact_when_the_arm_is_driven_into_a_box(graph):
    from visualization_msgs.msg import Marker
    h, proc, _ = graph
    go_home(h)
    m0, kv0 = h.last_state()
    n0 = int(kv0['contacts_since_start'])
    # a 6 cm cube on the circle of the hand, 0.7 rad further around joint 1 (4-7 cm away)
    a = 0.7
    box = marker(ns='box', id=3, kind='cube', size=0.06,
                 position=(0.307 * np.cos(a), 0.307 * np.sin(a), 0.56))
    t0 = time.monotonic()

    def add_box():
        _publish_markers(h, box)
        assert h.wait_state(lambda m, kv: kv.get('obstacles') == '1'
                            and 0.02 < float(kv['min_obstacle_distance_m']) < 0.1), \
            h.last_state()
    not_rejected(h, 'obstacles', add_box)
    target = PANDA_HOME + np.array([1.1, 0, 0, 0, 0, 0, 0])
    h.ramp(PANDA_HOME, target, 0.8)
    assert h.wait_state(lambda m, kv: int(kv['contacts_since_start']) > n0
                        and float(kv['min_obstacle_distance_since_start_m']) <= 0.0), \
        h.last_state()
    assert h.wait_diag('; contact panda_', t0, name='sim: state')
    _publish_markers(h, Marker(ns='box', action=Marker.DELETEALL))
    assert h.wait_state(lambda m, kv: kv['contacts'] == '0' and kv.get('obstacles') == '0')
    go_home(h)


# -- bad input: one test per case --------------------------------------------------------------
REFERENCE_CASES = {  # case -> (text in the diagnostics reason, rejected_<category>)
    'nan': ('expected a finite value, got nan', 'non_finite'),
    'inf': ('expected a finite value, got -inf', 'non_finite'),
    'nan_velocity': ("velocity of 'panda_joint7': expected a finite value", 'non_finite'),
    'wrong_length': ('position: expected 7 values', 'length'),
    'velocity_length': ('velocity: expected 0 or 7 values', 'length'),
    'unknown_name': ("unknown joints ['elbow_joint']", 'joint_names'),
    'missing_name': ("missing joints ['panda_joint7']", 'joint_names'),
    'duplicate_name': ('duplicate joint name', 'joint_names'),
    'future_stamp': ('in the future', 'stamp'),
    'past_stamp': ('in the past', 'stamp'),
}


@pytest.mark.parametrize('case', sorted(REFERENCE_CASES))
def test_bad_references_are_rejected(graph, case):
    h, proc, _ = graph
    text, category = REFERENCE_CASES[case]
    before = int(h.last_state()[1].get(f'rejected_{category}', 0))
    # the arm may still settle from the previous test: compare against a resting arm
    assert h.wait(lambda: at_rest(h), TIMEOUT), h.q()
    q_before = h.q()
    h.reject('joint_reference',
             lambda: bad_joint_state(lambda dt: h.reference(PANDA_HOME, stamp_offset=dt), case),
             text, name='sim: input joint_reference')
    assert h.wait_state(lambda m, kv: int(kv.get(f'rejected_{category}', 0)) > before)
    alive(h, proc)
    assert np.abs(h.q() - q_before).max() < 0.01  # nothing of it reached the robot


def test_reference_outside_the_limits_is_clipped_and_reported(graph):
    h, proc, _ = graph
    near = PANDA_HOME.copy()
    near[6] = 2.9  # joint 7, 0.067 rad below its upper limit 2.9671
    h.ramp(h.q(), near, 0.5)
    violations0 = int(h.last_state()[1]['limit_violations'])
    t0 = time.monotonic()
    target = near.copy()
    target[6] = 3.5  # beyond the limit
    h.publish('joint_reference', h.reference(target))
    assert h.wait_diag("position of 'panda_joint7' is outside the limits [-2.9671, 2.9671], "
                       'clipped to 2.9671', t0, name='sim: input joint_reference')
    assert h.wait(lambda: h.q()[6] > 2.96, TIMEOUT), h.q()
    # the step response is over after 0.3 s of simulated time (75 joint_states); the sim's
    # state reported after that counts its limit violations
    n0 = h.n_states()
    assert h.wait(lambda: h.n_states() >= n0 + 75, TIMEOUT)
    t1 = time.monotonic()
    assert h.wait(lambda: h.state_after(t1) is not None, TIMEOUT)
    with h.lock:
        qs = np.array([s[3] for s in h.states if s[0] >= t0])
    excess = max(float(np.max(qs - UPPER)), float(np.max(LOWER - qs)))
    # the clipped reference is exactly at the limit: the position motors' step response
    # overshoots it by a few mrad (measured 7 mrad), bounded by the URDF joint stop
    assert excess < 0.02, excess
    _, kv = h.state_after(t1)
    assert int(kv['rejected_limits']) >= 1
    # limit_violations counts measured excursions beyond limit_tolerance (1e-4 rad)
    violations = int(kv['limit_violations'])
    assert (violations > violations0) == (excess > 1e-4) or 0.9e-4 < excess < 1.1e-4, \
        (excess, violations0, violations)
    go_home(h)


def test_reference_velocity_above_the_limit_is_clipped(graph):
    h, proc, _ = graph
    t0 = time.monotonic()
    h.publish('joint_reference', h.reference(PANDA_HOME, [100.0] + [0.0] * 6))
    assert h.wait_diag("velocity of 'panda_joint1' exceeds the velocity limit 2.175, clipped",
                       t0, name='sim: input joint_reference')
    alive(h, proc)
    go_home(h)


@pytest.mark.parametrize('case', sorted(MARKER_CASES))
def test_bad_markers_are_rejected(graph, case):
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    m, text = bad_marker(case)
    h.reject('obstacles', lambda: MarkerArray(markers=[m]), text, name='sim: input obstacles')
    assert h.wait_state(lambda msg, kv: kv.get('obstacles') == '0'
                        and int(kv.get('rejected_total', 0)) > 0)
    alive(h, proc)


def test_flooding_is_dropped_and_reported(graph):
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    # low limits for this test, so that a flood is a flood even when this shared machine
    # starves the sim process; the flood goes on until the node reports the drops
    assert h.set_parameter('max_reference_rate', 20.0).successful
    assert h.set_parameter('max_input_rate', 5.0).successful
    try:
        t0 = time.monotonic()
        msg = h.reference(h.q(), zero=True)
        assert flood(h, 'joint_reference', msg, lambda: h.wait_diag(
            'flooding: more than 20 messages/s', t0, timeout=0.0,
            name='sim: input joint_reference')), [
            d[1:3] for d in h.diag_messages if d[0] > t0][-6:]
        assert h.wait_state(lambda m, kv: int(kv.get('rejected_flooding', 0)) > 0)
        msg = MarkerArray(markers=[marker(ns='flood', id=1, position=(2.0, 0.0, 0.0))])
        assert flood(h, 'obstacles', msg, lambda: h.wait_diag(
            'flooding: more than 5 messages/s', t0, timeout=0.0, name='sim: input obstacles'))
        alive(h, proc)
    finally:
        assert h.set_parameter('max_reference_rate', 200.0).successful
        assert h.set_parameter('max_input_rate', 50.0).successful
    _publish_markers(h, marker(ns='flood', action=3))
    assert h.wait_state(lambda m, kv: kv.get('obstacles') == '0')


def flood(h, topic, msg, reported, timeout=TIMEOUT):
    """Publish ``msg`` on ``topic`` in bursts of 50 until ``reported()``; returns it."""
    def burst():
        for _ in range(50):
            h.publish(topic, msg)
        return reported()
    return h.wait(burst, timeout)


# -- services and parameters -------------------------------------------------------------------
def test_snapshot_and_reset_services(graph, tmp_path):
    h, proc, _ = graph
    res = h.call('snapshot')
    assert res.success, res.message
    with open(res.message, 'rb') as f:
        assert f.read(8) == b'\x89PNG\r\n\x1a\n'
    os.remove(res.message)
    assert h.set_parameter('snapshot_path', '/proc/cdmp_no_such_dir/snap.png').successful
    res = h.call('snapshot')
    assert not res.success and 'snapshot failed' in res.message
    path = str(tmp_path / 'snap.png')
    assert h.set_parameter('snapshot_path', path).successful
    res = h.call('snapshot')
    assert res.success and res.message == path and os.path.getsize(path) > 1000
    # reset: the robot is back at initial_positions at once
    h.ramp(h.q(), PANDA_HOME + 0.2 * np.array([1, 1, 1, 1, 1, 0, 0]), 0.4)
    assert h.wait(lambda: np.abs(h.q() - PANDA_HOME).max() > 0.1, TIMEOUT)
    t0 = time.monotonic()
    res = h.call('reset')
    assert res.success and 'reset to initial_positions' in res.message
    assert h.wait(lambda: np.abs(h.q() - PANDA_HOME).max() < 1e-3, TIMEOUT)
    assert h.wait_diag('waiting: holding initial_positions', t0, name='sim: state')
    alive(h, proc)


def test_runtime_parameter_changes_are_validated(graph):
    h, proc, _ = graph
    assert 'kp' in h.refusal('kp', -1.0)
    assert "control: expected one of ['position'" in h.refusal('control', 'velocity')
    assert 'read-only' in h.refusal('physics_rate', 500.0).lower()
    assert 'expected 7 values' in h.refusal('initial_positions', [0.0, 1.0])
    assert 'initial_positions[3] (panda_joint4)' in h.refusal(
        'initial_positions', [0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0])
    for value in (False, True):  # switching the pacing keeps the node publishing
        r = h.set_parameter('real_time', value)
        assert r.successful, r.reason
        alive(h, proc)
    for mode in ('computed_torque', 'exogenous', 'position'):
        r = h.set_parameter('control', mode)
        assert r.successful, r.reason
        assert h.wait_state(lambda m, kv: kv['control'] == mode)
        goal = PANDA_HOME + np.array([0.2, 0.1, 0, 0.1, 0, 0, 0])
        h.ramp(h.q(), goal, 0.5)
        assert h.wait(lambda: np.abs(h.q() - goal).max() < 0.01, TIMEOUT), (mode, h.q() - goal)
        go_home(h)
    alive(h, proc)


def test_reason_categories_and_rate_limiter():
    from cdmp_ros.common.rate_limit import RateLimiter
    from cdmp_ros.ros.input_gate import reason_category
    assert reason_category("joint_reference.position of 'a': expected a finite value, got nan"
                           ) == 'non_finite'
    assert reason_category('x.header.stamp: stamp 3.0 s in the future') == 'stamp'
    assert reason_category('obstacles.markers[0].scale.x: expected at most 10 m') == \
        'marker_scale'
    assert reason_category('something new') == 'other'
    lim = RateLimiter(100.0)  # burst 10
    assert sum(lim.allow(0.0) for _ in range(50)) == 10 and lim.dropped == 40
    assert sum(lim.allow(0.05) for _ in range(50)) == 5  # 0.05 s refills 5 tokens
    assert sum(lim.allow(t * 0.01) for t in range(6, 106)) >= 99  # 100/s passes
