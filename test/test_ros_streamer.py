"""The streamer as a real process (``python -m cdmp_ros.nodes.streamer``), driven over DDS.

One streamer process serves the module (its own private domain, localhost only); the test
process runs a fake robot (joint_states echoing the reference) and a listener that checks EVERY
reference it receives (names, size, finite, inside the limits). Each bad-input case publishes
its input, waits for the matching ``diagnostics`` entry, and checks that the stream continued
within the limits; an accepted input is shown accepted by the node's own rejection counter
(conftest ``assert_not_rejected``). Every wait is on a condition with a generous timeout;
timing and latency figures are benchmarks/bench_streamer.py's.
"""
import json
import time

import numpy as np
import pytest

from conftest import assert_not_rejected, joint_state_rejected, marker_rejected, module_domain
from markers import MARKER_CASES, bad_marker
from node_harness import (GOAL_CASES, JOINT_STATE_CASES, bad_joint_state,
                          expect_startup_failures, running)
from cdmp_ros.core.primitive_io import dumps_primitive
from streamer_harness import (LOWER, PANDA_JOINTS, Q_GOAL, Q_START, UPPER, Harness,
                              max_acceleration, reach_cdmp, start_streamer)

pytestmark = pytest.mark.ros
DOMAIN = module_domain(7)
MAX_ACC = 100.0  # rad/s^2; a velocity jump of 0.2 rad/s at 500 Hz would be 100
STARTUP = 30.0  # s; interpreter + rclpy start-up on a loaded 2-core machine
TIMEOUT = 30.0  # s; bounds a failing wait only


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log = tmp_path_factory.mktemp('streamer') / 'streamer.log'
    proc = start_streamer(DOMAIN, ['diagnostics_period:=0.2', 'max_input_rate:=50.0'],
                          log_path=str(log), params_file='config/streamer.yaml')
    h = Harness(DOMAIN)
    # holding the measured position (the fake robot's Q_START) before any primitive
    with running(proc, h, log, lambda: h.n_refs() > 10, STARTUP, 'streamer'):
        from std_msgs.msg import String
        assert np.abs(h.last_ref()[2] - Q_START).max() == 0.0
        h.publish('primitive', String(data=dumps_primitive(reach_cdmp(duration=1.5))))
        ok = h.wait(lambda: h.n_refs() > 50 or proc.poll() is not None, STARTUP)
        assert ok and proc.poll() is None, log.read_text()
        yield h, proc, log
    assert not h.violations, h.violations[:5]


def stream_continues(h, proc, n=20):
    """The node is alive, ``n`` more references came, every one of them valid."""
    n0 = h.n_refs()
    ok = h.wait(lambda: h.n_refs() >= n0 + n or proc.poll() is not None, TIMEOUT)
    assert proc.poll() is None, 'streamer died'
    assert ok, 'the stream stopped'
    assert not h.violations, h.violations[:3]


def not_rejected(h, topic, action):
    """Run ``action`` and assert, on the streamer's own rejection counter, that nothing it
    published on ``topic`` was rejected (joint_states is best effort: a lost evidence message
    is sent again)."""
    stamp = h.node.get_clock().now
    if topic == 'obstacles':
        send = marker_rejected(h, lambda msg: h.publish('obstacles', msg),
                               stamp=lambda: stamp().to_msg())
    else:
        send = joint_state_rejected(h, lambda msg: h.publish(topic, msg), PANDA_JOINTS,
                                    lambda: stamp().nanoseconds)
    return assert_not_rejected(h, topic, send, action, resend_after=5.0)


# -- normal operation --------------------------------------------------------------------------
def test_streams_the_primitive_towards_its_goal(graph):
    h, proc, _ = graph
    assert h.wait(lambda: np.abs(h.last_ref()[2] - Q_GOAL).max() < 0.02, TIMEOUT)
    refs = h.refs_since(0)
    assert np.abs(refs[0][2] - Q_START).max() < 0.05
    assert max_acceleration(refs) < MAX_ACC
    assert h.wait(lambda: h.last_state()[1].get('state') == 'running'
                  and 'cdmp from primitive' in h.last_state()[1].get('primitive', ''),
                  TIMEOUT), h.last_state()


def test_shuffled_joint_states_are_mapped(graph):
    h, proc, _ = graph
    perm = [6, 2, 0, 5, 1, 3, 4]
    q = h.last_ref()[2]

    def shuffled():
        for _ in range(30):  # a joint_states stream at 100 Hz
            h.publish('joint_states', h.joint_state(q[perm],
                                                    [PANDA_JOINTS[i] for i in perm]))
            time.sleep(0.01)
        stream_continues(h, proc)
    h.robot_on = False
    try:
        not_rejected(h, 'joint_states', shuffled)
    finally:
        h.robot_on = True


def test_goal_change_is_followed_without_a_jump(graph):
    h, proc, _ = graph
    i0 = h.n_refs()
    goal = np.array([0.3, 0.0, -0.2, -1.6, 0.1, 1.8, 0.5])
    h.publish('goal', h.joint_state(goal))
    assert h.wait(lambda: np.abs(h.last_ref()[2] - goal).max() < 0.02, TIMEOUT)
    refs = h.refs_since(i0)
    assert max_acceleration(refs) < MAX_ACC


def test_new_primitive_switches_without_a_jump(graph):
    from std_msgs.msg import String
    h, proc, _ = graph
    q = h.last_ref()[2]
    target = np.array([-0.4, -0.1, -0.15, -1.5, -0.1, 1.0, -0.15])
    h.publish('goal', h.joint_state(target))  # goal override follows the new primitive
    i0 = h.n_refs()
    # the adapter's topic; starts far away, from a different start
    h.publish('adapted_primitive', String(data=dumps_primitive(reach_cdmp(Q_GOAL, target,
                                                                          1.0))))
    assert h.wait(lambda: np.abs(h.last_ref()[2] - target).max() < 0.02, TIMEOUT)
    refs = h.refs_since(i0)
    assert np.abs(refs[0][2] - q).max() < 0.05  # continued from where it was
    assert max_acceleration(refs) < MAX_ACC
    assert h.wait(lambda: 'adapted_primitive' in h.last_state()[1].get('primitive', ''),
                  TIMEOUT), h.last_state()


def test_sphere_obstacle_changes_the_reference(graph):
    from visualization_msgs.msg import Marker, MarkerArray
    from geometry_msgs.msg import Point
    import os
    import pybullet_data
    from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
    h, proc, _ = graph
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda/panda.urdf'))
    ee = chain.forward(h.last_ref()[2], [PointOfInterest('ee')])[0]
    m = Marker(ns='test', id=1, type=Marker.SPHERE, action=Marker.ADD)
    m.header.frame_id = 'panda_link0'
    m.pose.position = Point(x=float(ee[0]) + 0.06, y=float(ee[1]), z=float(ee[2]))
    m.scale.x = m.scale.y = m.scale.z = 0.1
    n_lat = int(h.last_state()[1].get('obstacle_latency_n', 0))

    def add_and_delete():
        m.header.stamp = h.node.get_clock().now().to_msg()  # the latency counts from here
        h.publish('obstacles', MarkerArray(markers=[m]))
        moved = h.wait(lambda: np.linalg.norm(
            chain.forward(h.last_ref()[2], [PointOfInterest('ee')])[0] - ee) > 0.01, TIMEOUT)
        assert moved
        assert h.wait(lambda: int(h.last_state()[1].get('coupled', 0)) > 0
                      and h.last_state()[1].get('obstacles') == '1', TIMEOUT)
        # 1 cm from the fingertips the repeller asks for more than the default bound
        # (coupling_max_acceleration, 500 rad/s^2): the streamer applied it bounded
        assert h.wait(lambda: int(h.last_state()[1].get('coupling_bounded', 0)) > 0,
                      TIMEOUT), h.last_state()
        # obstacle stamp -> first reference computed with it, reported on diagnostics (the
        # figures themselves are benchmarks/bench_streamer.py's)
        assert h.wait(lambda: int(h.last_state()[1].get('obstacle_latency_n', 0)) > n_lat,
                      TIMEOUT)
        values = h.last_state()[1]
        p50 = float(values['obstacle_latency_ms_p50'])
        p99 = float(values['obstacle_latency_ms_p99'])
        assert 0.0 < p50 <= p99, values
        stream_continues(h, proc)
        h.publish('obstacles', MarkerArray(markers=[Marker(ns='test', action=Marker.DELETEALL)]))
        assert h.wait(lambda: h.last_state()[1].get('obstacles') == '0', TIMEOUT)
    not_rejected(h, 'obstacles', add_and_delete)


# -- bad input: one test per case --------------------------------------------------------------
def _js(h, **kw):
    return h.joint_state(h.last_ref()[2], **kw)


def _bad_joint_state(h, case):
    q = h.last_ref()[2]
    return bad_joint_state(lambda dt: h.joint_state(q, stamp_offset=dt), case)


@pytest.mark.parametrize('case', sorted(JOINT_STATE_CASES))
def test_bad_joint_states_are_rejected(graph, case):
    h, proc, _ = graph
    # joint_states is best effort (sensor QoS): a sample may be lost, so the bad sample is
    # published until its rejection is reported
    h.reject('joint_states', lambda: _bad_joint_state(h, case), JOINT_STATE_CASES[case],
             resend=True)
    stream_continues(h, proc)


@pytest.mark.parametrize('case', sorted(GOAL_CASES))
def test_bad_goals_are_rejected(graph, case):
    h, proc, _ = graph
    h.reject('goal', lambda: _bad_joint_state(h, case), GOAL_CASES[case])
    stream_continues(h, proc)


def test_goal_outside_the_limits_is_clipped_and_reported(graph):
    h, proc, _ = graph
    t0 = time.monotonic()
    goal = np.array([0.3, 5.0, -0.2, 1.0, 0.1, 1.8, 0.5])  # joints 2 and 4 beyond the limits
    h.publish('goal', h.joint_state(goal))
    assert h.wait_diag('clipped with the CDMP margin: panda_joint2 5 -> 1.831', t0,
                       name='input goal')
    assert h.wait(lambda: h.last_ref()[2][1] > 1.8, TIMEOUT)
    refs = h.refs_since(0)
    assert all(np.all(r[2] <= UPPER) and np.all(r[2] >= LOWER) for r in refs)
    stream_continues(h, proc)
    h.publish('goal', h.joint_state(Q_GOAL))


@pytest.mark.parametrize('case', sorted(MARKER_CASES))
def test_bad_markers_are_rejected(graph, case):
    from visualization_msgs.msg import MarkerArray
    h, proc, _ = graph
    m, text = bad_marker(case)
    h.reject('obstacles', lambda: MarkerArray(markers=[m]), text)
    assert h.last_state()[1].get('obstacles') == '0'
    stream_continues(h, proc)


PRIMITIVE_CASES = {
    'malformed_json': (lambda d: json.dumps(d)[:-5], 'not valid JSON'),
    'schema_violation': (lambda d: json.dumps(dict(d, duration=-1.0)),
                         'primitive.duration: expected a value >= 0.001, got -1.0'),
    'wrong_joints': (lambda d: json.dumps(dict(d, joint_names=[f'j{i}' for i in range(7)])),
                     'expected the streamer joints'),
    'not_an_object': (lambda d: '[1, 2, 3]', 'expected a JSON object'),
    'nan_constant': (lambda d: json.dumps(d).replace('"alpha_y": 25.0', '"alpha_y": NaN'),
                     'primitive.dmp.alpha_y: expected a finite number, got nan'),
    'nan_weights': (lambda d: json.dumps(d).replace('"weights": [[', '"weights": [[NaN, '),
                    'primitive.dmp.weights[0][0]: expected a finite number, got nan'),
}


@pytest.mark.parametrize('case', sorted(PRIMITIVE_CASES))
def test_bad_primitives_are_rejected(graph, case):
    from std_msgs.msg import String
    h, proc, _ = graph
    make, text = PRIMITIVE_CASES[case]
    d = json.loads(dumps_primitive(reach_cdmp(duration=1.5)))
    h.reject('primitive', lambda: String(data=make(d)), text)
    _, kv = h.last_state()
    assert 'adapted_primitive' in kv.get('primitive', '')  # the active one is kept
    stream_continues(h, proc)


def test_flooding_is_dropped_and_reported(graph):
    h, proc, _ = graph
    t0 = time.monotonic()
    msg = h.joint_state(Q_GOAL, zero=True)

    def burst():  # until the node reports the drops
        for _ in range(50):
            h.publish('goal', msg)
        return h.wait_diag('flooding: more than 50 messages/s', t0, timeout=0.0,
                           name='input goal')
    assert h.wait(burst, TIMEOUT), h.diag_messages[-3:]
    stream_continues(h, proc)


def test_stale_joint_states_stop_smoothly_and_resume(graph):
    h, proc, _ = graph
    h.publish('goal', h.joint_state(Q_START))
    # moving towards Q_START (from the clipped goal of an earlier test, or from Q_GOAL)
    assert h.wait(lambda: np.abs(h.last_ref()[3]).max() > 0.05, TIMEOUT)
    i0 = h.n_refs()
    t0 = time.monotonic()
    h.robot_on = False
    try:
        assert h.wait_diag('holding: joint_states stale', t0, name='state')
        # the stream goes on while holding, at rest
        stream_continues(h, proc, n=100)
        refs = h.refs_since(i0)
        assert np.abs(refs[-1][3]).max() == 0.0
        assert max_acceleration(refs) < MAX_ACC
    finally:
        h.robot_on = True
    t1 = time.monotonic()
    assert h.wait(lambda: h.last_state()[1].get('state') == 'running'
                  and h.diag_messages[-1][0] > t1, TIMEOUT)
    assert max_acceleration(h.refs_since(i0)) < MAX_ACC


def test_runtime_parameter_changes_are_validated(graph):
    h, proc, _ = graph
    assert 'stop_time' in h.refusal('stop_time', -2.0)
    assert 'RepellerField.gain' in h.refusal('repeller.gain', -1.0)
    assert 'read-only' in h.refusal('rate', 100.0).lower()
    r = h.set_parameter('stop_time', 1)  # an integer for a float parameter is accepted
    assert r.successful, r.reason
    r = h.set_parameter('repeller.gain', 0.02)
    assert r.successful, r.reason
    stream_continues(h, proc)


# -- start-up --------------------------------------------------------------------------------
STARTUP_CASES = [('stop_time:=-1.0', 'stop_time'), ('joint_names:=[a,b]', 'joint_names'),
                 ("urdf_path:='/nonexistent.urdf'", 'urdf_path'),
                 ('repeller.gain:=-1.0', 'RepellerField.gain')]


def test_bad_startup_parameters_exit_nonzero_with_a_reason(tmp_path):
    logs = [str(tmp_path / f'{i}.log') for i in range(len(STARTUP_CASES))]
    expect_startup_failures([(start_streamer(163 + i, [param], log_path=logs[i]), text, logs[i])
                             for i, (param, text) in enumerate(STARTUP_CASES)], STARTUP)
