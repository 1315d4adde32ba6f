"""The input gate (cdmp_ros/ros/input_gate.py): oversize input is rejected in constant time,
before it is deserialised, by every node; the rejection is counted by topic and reason on
diagnostics, and a following valid input is still accepted.

Unit tests of the CDR peeks and of the gate's order (rate limit, size, deserialisation) run
without processes; one process test per node (sim, streamer, adapter, learner).
"""
import contextlib
import json
import struct
import time

import numpy as np
import pytest

from conftest import module_domain
from node_harness import running

DOMAIN = module_domain(17)
STARTUP = 60.0   # s; interpreter + rclpy + pybullet start-up on a loaded 2-core machine
EVIDENCE = 30.0  # s; diagnostics arrive every 0.2-0.5 s, generous on a loaded machine
JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
Q_HOME = np.array([0.0, -0.785398163, 0.0, -2.35619449, 0.0, 1.570796327, 0.785398163])


# -- helpers -----------------------------------------------------------------------------------
def marker_array(n, frame='panda_link0', stamp=None, start_id=0):
    """``n`` SPHERE markers of 5 cm radius in front of the robot."""
    from visualization_msgs.msg import Marker, MarkerArray
    out = MarkerArray()
    for i in range(n):
        m = Marker(ns='gate', id=start_id + i, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = frame
        if stamp is not None:
            m.header.stamp = stamp
        m.pose.position.x, m.pose.position.z = 0.6, 0.5
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 0.1
        out.markers.append(m)
    return out


def joint_state(n_names, positions=None):
    from sensor_msgs.msg import JointState
    msg = JointState()
    msg.name = [f'j{i}' for i in range(n_names)] if positions is None else list(JOINTS)
    msg.position = [0.0] * n_names if positions is None else [float(v) for v in positions]
    return msg


def last_kv(h, name):
    """The key/values of the latest diagnostics status called ``name`` ({} if none)."""
    with h.lock:
        for rec in reversed(h.diag_messages):
            if rec[1] == name:
                return rec[-1]
    return {}


def count(h, name, key):
    return int(last_kv(h, name).get(key, 0))


def wait_for(pred, timeout=EVIDENCE):
    from conftest import wait_for as _wait_for
    return _wait_for(pred, timeout)


def until(pred, publish, period=0.5, timeout=EVIDENCE):
    """Publish every ``period`` (a message may go out before discovery completes, and stays
    far below every rate limit) until ``pred()``."""
    last = [-1e9]

    def check():
        if pred():
            return True
        if time.monotonic() - last[0] >= period:
            last[0] = time.monotonic()
            publish()
        return False
    return wait_for(check, timeout)


def expect_oversize(h, node, topic, text, publish):
    """Publish until ``node: input topic`` shows one more oversize rejection, whose reason
    contains ``text``; returns that reason."""
    name = f'{node}: input {topic}'
    before = count(h, name, 'rejected_oversize')
    assert until(lambda: count(h, name, 'rejected_oversize') > before, publish), \
        (name, last_kv(h, name))
    reason = last_kv(h, name)['last_reason']
    assert text in reason and 'rejected unparsed' in reason, reason
    return reason


def too_many_markers(h):
    """The oversize case of ``obstacles`` (for :func:`expect_all_oversize`)."""
    return 'obstacles', '640 markers exceed', lambda: h.publish('obstacles', marker_array(640))


def too_many_names(h, topic):
    """The oversize case of the JointState topic ``topic``."""
    return (topic, '10000 names exceed the limit of 7',
            lambda: h.publish(topic, joint_state(10000)))


def accepts_an_obstacle(h, node):
    """A valid obstacle (after the rejected ones) is accepted: the node's state counts it."""
    assert until(lambda: count(h, f'{node}: state', 'obstacles') == 1,
                 lambda: h.publish('obstacles', marker_array(1)))


@contextlib.contextmanager
def serving(tmp_path, start, harness, params, ready, **kw):
    """The node process ``start(DOMAIN, ['diagnostics_period:=0.2'] + params, ...)`` and a
    test-side ``harness``, once ``ready(h)``: yields (h, process)."""
    log = tmp_path / 'node.log'
    proc = start(DOMAIN, ['diagnostics_period:=0.2'] + params, log_path=str(log), **kw)
    h = harness(DOMAIN)
    with running(proc, h, log, lambda: ready(h), STARTUP, exit_code=None):
        yield h, proc


def expect_all_oversize(h, node, cases):
    """:func:`expect_oversize` of each of ``cases`` [(topic, text, publish)] in turn, then the
    node's state counts them all; returns their reasons."""
    reasons = [expect_oversize(h, node, topic, text, publish) for topic, text, publish in cases]
    assert wait_for(lambda: count(h, f'{node}: state', 'rejected_oversize') >= len(cases))
    return reasons


def rejects_oversize_and_accepts_an_obstacle(tmp_path, node, start, harness, ready, cases, **kw):
    """The JSON-reading ``node`` (max_json_bytes 1000) rejects each of ``cases(h)`` unparsed,
    then accepts a valid obstacle, and is still up."""
    with serving(tmp_path, start, harness, ['max_json_bytes:=1000'], ready, **kw) as (h, proc):
        expect_all_oversize(h, node, cases(h))
        accepts_an_obstacle(h, node)
        assert proc.poll() is None


# -- unit tests of the CDR peeks and of the gate -------------------------------------------------
def test_cdr_peeks_read_the_counts_of_serialized_messages():
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from cdmp_ros.bag.cdr import cdr_first_count, cdr_joint_state_names
    for n in (0, 1, 7, 123):
        assert cdr_first_count(serialize_message(marker_array(n))) == n
    for frame in ('', 'a', 'ab', 'abc', 'abcd', 'base_link_0'):
        for n in (0, 1, 7, 10000):
            msg = joint_state(n)
            msg.header.frame_id = frame
            assert cdr_joint_state_names(serialize_message(msg)) == n, (frame, n)
    text = 'ü' * 10
    assert cdr_first_count(serialize_message(String(data=text))) == len(text.encode()) + 1
    # big-endian CDR (encapsulation 0x0000) and truncated messages
    assert cdr_first_count(b'\x00\x00\x00\x00' + struct.pack('>I', 5000)) == 5000
    assert cdr_first_count(b'\x00\x01\x00') is None
    assert cdr_joint_state_names(b'\x00\x01\x00\x00' + b'\x00' * 8) is None


def test_size_checks_name_what_is_too_large():
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from cdmp_ros.ros.input_gate import joint_names, json_bytes, marker_count, message_bytes
    check = marker_count(lambda: 64)
    reason = check('obstacles', serialize_message(marker_array(640)))
    assert 'obstacles.markers: 640 markers exceed max_obstacles + 1 = 65' in reason
    assert check('obstacles', serialize_message(marker_array(65))) is None
    check = json_bytes(lambda: 1000)
    reason = check('constraints', serialize_message(String(data='x' * 1001)))
    assert 'constraints: payload of 1001 bytes exceeds max_json_bytes = 1000' in reason
    assert check('constraints', serialize_message(String(data='x' * 1000))) is None
    check = joint_names(lambda: 7)
    reason = check('goal', serialize_message(joint_state(10000)))
    assert 'goal.name: 10000 names exceed the limit of 7' in reason
    assert check('goal', serialize_message(joint_state(7, Q_HOME))) is None
    long_positions = joint_state(7, Q_HOME)
    long_positions.position = [0.0] * 100000  # 7 names, an oversize array
    assert 'bytes per joint' in check('goal', serialize_message(long_positions))
    assert 'exceeds 10 bytes' in message_bytes(lambda: 10)('goal_point', b'x' * 11)


class _Node:
    """The parts of rclpy.node.Node the gate and the reporter use."""

    def __init__(self):
        import rclpy.clock
        self.subscriptions = {}
        self.groups = {}
        self.clock = rclpy.clock.Clock()
        self.logged = []

    def create_subscription(self, msg_type, topic, callback, qos, raw=False,
                            callback_group=None):
        assert raw, 'the gate must subscribe serialized messages'
        self.subscriptions[topic] = callback
        if callback_group is not None:
            self.groups[topic] = callback_group
            return _TakenSub()

    def get_clock(self):
        return self.clock

    def get_logger(self):
        node = self

        class Logger:
            def warning(self, text):
                node.logged.append(text)
        return Logger()

    def get_fully_qualified_name(self):
        return '/gate_test'


class _TakenSub:
    """A subscription whose reader holds ``queue``: (serialized message, message info)."""

    last = None

    def __init__(self):
        self.queue = []
        self.takes = 0
        self.handle = self
        self.msg_type = None
        _TakenSub.last = self

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def take_message(self, msg_type, raw):
        assert raw, 'a polled subscription takes serialized messages'
        self.takes += 1
        return self.queue.pop(0) if self.queue else None


class _Config:
    max_stamp_age, max_stamp_lead, accept_unstamped = 5.0, 1.0, True


def _gate():
    from cdmp_ros.ros.diagnostics import DiagnosticsReporter
    from cdmp_ros.ros.input_gate import InputGate

    class Pub:
        def __init__(self):
            self.sent = []

        def publish(self, msg):
            self.sent.append(msg)
    node = _Node()
    reporter = DiagnosticsReporter(node, Pub(), 'gate')
    return node, reporter, InputGate(node, reporter, lambda: _Config())


def test_gate_rejects_oversize_before_deserializing_and_counts_by_topic_and_reason():
    from rclpy.serialization import serialize_message
    from visualization_msgs.msg import MarkerArray

    from cdmp_ros.ros.input_gate import marker_count
    node, reporter, gate = _gate()
    gate.set_rates({'obstacles': 1000.0})
    got = []
    gate.subscribe(MarkerArray, 'obstacles', got.append, 10, size=marker_count(lambda: 4))
    deliver = node.subscriptions['obstacles']
    # only the CDR header of a 5,000-marker array: rejected by its count, never parsed
    deliver(b'\x00\x01\x00\x00' + struct.pack('<I', 5000))
    assert got == [] and gate.by_reason == {'oversize': 1}
    deliver(b'\x00\x01\x00\x00' + struct.pack('<I', 2) + b'garbage')  # not 2 markers
    assert got == [] and gate.by_reason == {'oversize': 1, 'malformed': 1}
    deliver(serialize_message(marker_array(3)))
    assert len(got) == 1 and len(got[0].markers) == 3
    status = {s.name: {kv.key: kv.value for kv in s.values}
              for s in reporter.build(node.clock.now().to_msg()).status}
    assert status['gate: input obstacles']['rejected_total'] == '2'
    assert status['gate: input obstacles']['rejected_oversize'] == '1'
    assert status['gate: input obstacles']['rejected_malformed'] == '1'
    assert gate.values() == {'rejected_total': 2, 'rejected_oversize': 1,
                             'rejected_malformed': 1, 'received_obstacles': 3}


def test_gate_applies_the_rate_limit_before_the_size_check():
    from std_msgs.msg import String
    node, reporter, gate = _gate()
    gate.set_rates({'primitive': 1.0})  # burst of 10, then 1/s
    sizes = []

    def size(topic, data):
        sizes.append(len(data))
        return None
    got = []
    gate.subscribe(String, 'primitive', got.append, 10, size=size)
    from rclpy.serialization import serialize_message
    data = serialize_message(String(data='{}'))
    for _ in range(30):
        node.subscriptions['primitive'](data)
    assert len(got) == len(sizes) and 10 <= len(got) < 30
    assert gate.by_reason['flooding'] == 30 - len(got)
    assert reporter.rejected_count('primitive') == 30 - len(got)
    assert 'flooding: more than 1 messages/s' in node.logged[0]


def test_gate_checks_stamps_after_deserializing():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    node, reporter, gate = _gate()
    gate.set_rates({'goal': 1000.0})
    got = []
    gate.subscribe(JointState, 'goal', got.append, 10, stamped=True)
    msg = joint_state(7, Q_HOME)
    msg.header.stamp.sec = int(time.time()) + 100
    node.subscriptions['goal'](serialize_message(msg))
    assert got == [] and gate.by_reason == {'stamp': 1}
    msg.header.stamp.sec = 0
    node.subscriptions['goal'](serialize_message(msg))
    assert len(got) == 1


def test_a_polled_subscription_checks_only_the_newest_message_when_polled():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from cdmp_ros.ros.input_gate import joint_names
    from cdmp_ros.ros.recorder_take import ThreadTakenGroup
    node, reporter, gate = _gate()
    got = []
    poll = gate.subscribe_polled(JointState, 'joint_states', lambda m, t: got.append((m, t)),
                                 _Qos(5), size=joint_names(lambda: 7), stamped=True)
    sub = _TakenSub.last
    # the executor never runs it: its group refuses every execution
    assert isinstance(node.groups['joint_states'], ThreadTakenGroup)
    assert not node.groups['joint_states'].can_execute(sub)
    poll()
    assert got == [] and gate.values() == {'rejected_total': 0}

    def queued(q, age):
        info = {'received_timestamp': time.time_ns() - int(age * 1e9)}
        return serialize_message(joint_state(7, q)), info
    future = joint_state(7, Q_HOME)
    future.header.stamp.sec = int(time.time()) + 100
    before = time.monotonic()
    sub.queue = [(serialize_message(future), {}), queued(Q_HOME, 0.3), queued(Q_HOME + 0.1, 0.2)]
    poll()
    after = time.monotonic()
    # the newest only: the older ones (one with a bad stamp) are superseded, not checked
    assert len(got) == 1 and np.allclose(got[0][0].position, Q_HOME + 0.1)
    # received 0.2 s before it was queued, in time.monotonic(): whatever the delays in between
    # (they only widen [before, after]); 1e-2 s for the two clocks' rates
    assert before - 0.2 - 1e-2 <= got[0][1] <= after - 0.2 + 1e-2
    assert gate.values() == {'rejected_total': 0, 'received_joint_states': 3}
    # a bad newest message is rejected and reported, and nothing is delivered
    sub.queue = [queued(Q_HOME, 0.0), (serialize_message(joint_state(10000)), {})]
    poll()
    assert len(got) == 1 and gate.by_reason == {'oversize': 1}
    assert reporter.rejected_count('joint_states') == 1
    # bounded: a reader that keeps filling is taken at most 4 x depth times per poll
    sub.queue = [queued(Q_HOME, 0.0)] * 100
    sub.takes = 0
    poll()
    assert sub.takes == 20 and len(got) == 2


class _Qos:
    def __init__(self, depth):
        self.depth = depth


# -- one process test per node -----------------------------------------------------------------
@pytest.mark.ros
def test_sim_rejects_oversize_input_and_accepts_the_next(tmp_path):
    from sim_harness import SimHarness, start_sim
    with serving(tmp_path, start_sim, SimHarness, [], lambda h: h.n_states() > 0,
                 params_file='config/sim.yaml') as (h, proc):
        reason, _ = expect_all_oversize(h, 'sim', [too_many_markers(h),
                                                   too_many_names(h, 'joint_reference')])
        assert 'max_obstacles + 1 = 65' in reason
        n0 = count(h, 'sim: state', 'references_received')
        assert until(lambda: count(h, 'sim: state', 'references_received') > n0,
                     lambda: h.publish('joint_reference', h.reference(Q_HOME)))
        accepts_an_obstacle(h, 'sim')
        assert proc.poll() is None


@pytest.mark.ros
def test_streamer_rejects_oversize_input_and_accepts_the_next(tmp_path):
    from std_msgs.msg import String
    from streamer_harness import Harness, start_streamer
    rejects_oversize_and_accepts_an_obstacle(
        tmp_path, 'streamer', start_streamer, Harness, lambda h: h.n_refs() > 0,
        lambda h: [too_many_markers(h), too_many_names(h, 'goal'),
                   ('adapted_primitive', 'payload of 2000 bytes exceeds max_json_bytes = 1000',
                    lambda: h.publish('adapted_primitive', String(data='x' * 2000)))],
        params_file='config/streamer.yaml')


@pytest.mark.ros
def test_adapter_rejects_oversize_input_and_accepts_the_next(tmp_path):
    from std_msgs.msg import String
    from adapter_harness import Harness, start_adapter
    big = json.dumps({'constraints': [], 'pad': 'x' * 5000})
    rejects_oversize_and_accepts_an_obstacle(
        tmp_path, 'adapter', start_adapter, Harness, lambda h: bool(last_kv(h, 'adapter: state')),
        lambda h: [('constraints', 'exceeds max_json_bytes = 1000',
                    lambda: h.publish('constraints', String(data=big))),
                   too_many_markers(h), too_many_names(h, 'goal')])


@pytest.mark.ros
def test_learner_rejects_oversize_input_and_accepts_the_next(tmp_path):
    from learner_harness import LearnerHarness, start_learner
    with serving(tmp_path, start_learner, LearnerHarness, ['fit_on_start:=false'],
                 lambda h: bool(last_kv(h, 'learner: state'))) as (h, proc):
        expect_oversize(h, 'learner', *too_many_names(h, 'demonstration'))
        n0 = count(h, 'learner: state', 'samples')
        assert until(lambda: count(h, 'learner: state', 'samples') > n0,
                     lambda: h.demo_pub.publish(joint_state(7, Q_HOME)))
        assert count(h, 'learner: state', 'rejected_oversize') >= 1
        assert proc.poll() is None


def test_a_primitive_replaced_before_it_was_parsed_is_reported():
    """The streamer's latest-wins worker returns the topic of a waiting message that a newer
    one of the same topic replaced, so the node counts it (reason 'superseded') instead of
    losing it silently; primitive and adapted_primitive wait in separate slots (a restarted
    streamer needs both latched messages)."""
    from cdmp_ros.ros.input_gate import reason_category
    from cdmp_ros.common.latest_worker import LatestWorker
    worker = LatestWorker(lambda req: req, lambda req, exc: None, name='test',
                          key=lambda req: req[0])  # as the streamer's; not started
    assert worker.submit(('primitive', 'a')) is None
    assert worker.submit(('adapted_primitive', 'b')) is None
    assert worker.submit(('primitive', 'c')) == ('primitive', 'a')
    assert worker.submit(('adapted_primitive', 'd')) == ('adapted_primitive', 'b')
    assert worker.counts['superseded'] == 2
    single = LatestWorker(lambda req: req, lambda req, exc: None, name='test')  # one slot
    assert single.submit(('primitive', 'a')) is None
    assert single.submit(('adapted_primitive', 'b')) == ('primitive', 'a')
    assert reason_category('primitive: superseded by a newer primitive before it was '
                           'parsed') == 'superseded'
