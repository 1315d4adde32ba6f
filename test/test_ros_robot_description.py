"""The ``robot_description`` topic in the streamer, the adapter and the sim (issue 31, item 7):
the latched URDF that robot_state_publisher publishes in Jazzy gives the robot model when the
``robot_description`` parameter is empty and ``robot_description_timeout`` > 0; a garbage
description, or one of other joints, is rejected with the reason on diagnostics and the node
keeps its model and runs on; a different description arriving later is a standing warning,
never swapped in. The decisions are unit-tested in test_core_robot_description.py; here the
ROS side: the size bound before deserialisation, the diagnostics condition, the glue with a
stand-in node, and the nodes as processes.

The test-side publisher latches pybullet_data's Panda URDF with panda_joint1's velocity limit
tightened to 1.5 rad/s (the datasheet's 2.175 otherwise), so that the source of the limits in
force is visible in the ``limits`` a node reports.
"""
import pytest

from conftest import module_domain
from node_harness import assert_clean_stop, running
from test_core_robot_description import FILE, PANDA, tightened

pytestmark = pytest.mark.ros
DOMAIN = module_domain(61)
STARTUP = 60.0   # s; interpreter + rclpy + pybullet start-up on a loaded 2-core machine
EVIDENCE = 30.0  # s; diagnostics every 0.2 s, generous on a loaded machine
TIGHT = 'velocity [1.5, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]'
WRONG_JOINTS = PANDA.replace('panda_joint1', 'joint_a')


def last_kv(h, name):
    """The key/values of the newest diagnostics status called ``name`` ({} if none)."""
    with h.lock:
        for d in reversed(h.diag_messages):
            if d.name == name:
                return d.values
    return {}


def last_status(h, name):
    """The newest diagnostics status called ``name`` (None if none)."""
    with h.lock:
        for d in reversed(h.diag_messages):
            if d.name == name:
                return d
    return None


def rejected(h, node, category):
    return int(last_kv(h, f'{node}: input robot_description').get(f'rejected_{category}', 0))


# -- without processes ---------------------------------------------------------------------
class _Logger:
    def __init__(self, out):
        self.out = out

    def info(self, text):
        self.out.append(('info', text))

    def warning(self, text):
        self.out.append(('warning', text))


class _Node:
    """The parts of rclpy.node.Node the gate, the reporter and the glue use."""

    def __init__(self):
        import rclpy.clock
        self.callbacks = {}
        self.clock = rclpy.clock.Clock()
        self.logged = []

    def create_subscription(self, msg_type, topic, callback, qos, raw=False):
        assert raw, 'robot_description must be subscribed serialized (bounded before parsing)'
        self.callbacks[topic] = callback
        return object()

    def get_clock(self):
        return self.clock

    def get_logger(self):
        return _Logger(self.logged)

    def get_fully_qualified_name(self):
        return '/rd_test'


class _Config:
    max_stamp_age, max_stamp_lead, accept_unstamped = 5.0, 1.0, True


class _Pub:
    def __init__(self):
        self.last = None

    def publish(self, msg):
        self.last = msg


def state_status(reporter, node):
    """(level, message, values) of the state status ``reporter`` publishes now."""
    reporter.publish(node.clock.now().to_msg())
    for s in reporter.publisher.last.status:
        if s.name.endswith(': state'):
            return s.level, s.message, {kv.key: kv.value for kv in s.values}


def test_a_description_is_bounded_before_it_is_deserialised():
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from cdmp_ros.ros.input_gate import ROBOT_DESCRIPTION_BYTES, description_bytes, read_raw
    check = description_bytes()
    big = serialize_message(String(data='x' * (ROBOT_DESCRIPTION_BYTES + 1)))
    msg, reason, category = read_raw(String, 'robot_description', big, check)
    assert msg is None and category == 'oversize'
    assert reason == (f'robot_description: payload of {ROBOT_DESCRIPTION_BYTES + 1} bytes '
                      f'exceeds ROBOT_DESCRIPTION_BYTES = {ROBOT_DESCRIPTION_BYTES}; rejected '
                      'unparsed')
    # only the CDR header of a 1 GB string: rejected by its length field, never read
    header = b'\x00\x01\x00\x00' + (10 ** 9 + 1).to_bytes(4, 'little')
    assert read_raw(String, 'robot_description', header, check)[2] == 'oversize'
    msg, reason, category = read_raw(String, 'robot_description', header)   # no bound
    assert msg is None and category == 'malformed' and 'cannot be deserialized' in reason
    msg, reason, _ = read_raw(String, 'robot_description', serialize_message(String(data=PANDA)),
                              check)
    assert reason is None and msg.data == PANDA


def test_a_standing_condition_raises_the_state_level_until_cleared():
    from cdmp_ros.ros.diagnostics import ERROR, OK, WARN, DiagnosticsReporter
    node = _Node()
    reporter = DiagnosticsReporter(node, _Pub(), 'rd')
    reporter.set_state(OK, 'running')
    reporter.set_condition('model', WARN, 'the model differs')
    assert state_status(reporter, node)[:2] == (WARN, 'running; the model differs')
    reporter.set_state(ERROR, 'failed')             # a worse state wins, the text stays
    assert state_status(reporter, node)[:2] == (ERROR, 'failed; the model differs')
    reporter.set_state(OK, 'running')
    reporter.set_condition('model', WARN, None)
    assert state_status(reporter, node)[:2] == (OK, 'running')


def test_the_glue_reports_through_the_gate_and_keeps_the_model():
    """RobotDescriptionInput with a stand-in node: no wait (timeout 0, the default), then
    messages as the executor would deliver them."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from cdmp_ros.core.kinematics.builders import PANDA_JOINTS
    from cdmp_ros.ros.diagnostics import OK, WARN, DiagnosticsReporter
    from cdmp_ros.ros.input_gate import InputGate
    from cdmp_ros.ros.robot_description import RobotDescriptionInput
    from cdmp_ros.ros.robot_model import RobotModelSelector
    node = _Node()
    robot = RobotDescriptionInput(node, RobotModelSelector('', PANDA_JOINTS))
    model = robot.load(node.create_subscription(String, 'robot_description', robot.on_raw,
                                                None, raw=True))
    assert model.source == FILE and node.logged == []
    reporter = DiagnosticsReporter(node, _Pub(), 'rd')
    reporter.set_state(OK, 'running')
    gate = InputGate(node, reporter, lambda: _Config())
    robot.attach(gate, reporter)
    assert state_status(reporter, node) == (OK, 'running', {'robot_description_topic':
                                                            'none received'})
    deliver = node.callbacks['robot_description']

    def send(text):
        deliver(serialize_message(String(data=text)))
        return state_status(reporter, node)
    level, message, kv = send('<robot')
    assert level == WARN and gate.by_reason == {'malformed': 1}
    assert kv['robot_description_topic'] == ('rejected: not a valid URDF: malformed XML '
                                             '(unclosed token: line 1, column 0)')
    assert 'robot_description topic rejected: not a valid URDF' in message
    level, message, kv = send(WRONG_JOINTS)
    assert gate.by_reason == {'malformed': 1, 'joint_names': 1}
    assert kv['robot_description_topic'].startswith('rejected: not a robot of the configured '
                                                    'joint_names')
    level, message, kv = send(tightened())
    assert level == WARN and kv['robot_description_topic'] == (
        f'differs from the model in use ({FILE}): panda_joint1 velocity 2.175 -> 1.5; a '
        'restart of the node with robot_description_timeout > 0 applies it')
    assert message == 'running; robot_description topic ' + kv['robot_description_topic']
    assert node.logged[-1] == ('warning', 'robot_description topic: '
                               + kv['robot_description_topic'])
    n_logged = len(node.logged)
    send(tightened())                                   # a repeat: not logged again
    assert len(node.logged) == n_logged
    assert robot.selector.model is model                # never swapped
    level, message, kv = send(PANDA)                    # the model in use: all clear
    assert (level, message) == (OK, 'running')
    assert kv['robot_description_topic'] == f'matches the model in use ({FILE})'
    assert gate.values()['received_robot_description'] == 5


# -- the nodes as processes ---------------------------------------------------------------
def streamer_given(tmp_path, description, timeout):
    """A streamer harness that published ``description`` on the latched robot_description
    before starting the streamer (robot_description_timeout ``timeout`` [s]): (harness,
    process, log path)."""
    from std_msgs.msg import String

    from cdmp_ros.ros import qos
    from streamer_harness import Harness, start_streamer
    h = Harness(DOMAIN)
    h.publisher(String, 'robot_description', qos.LATCHED)
    h.publish('robot_description', String(data=description))   # latched before the start
    log = tmp_path / 'streamer.log'
    proc = start_streamer(DOMAIN, [f'robot_description_timeout:={timeout}',
                                   'diagnostics_period:=0.2'], log_path=str(log))
    return h, proc, log


def test_the_streamer_takes_its_limits_from_the_topic_and_keeps_them(tmp_path):
    from std_msgs.msg import String
    h, proc, log = streamer_given(tmp_path, tightened(), 60.0)
    state = 'streamer: state'
    with running(proc, h, log, lambda: last_kv(h, state), STARTUP, 'streamer'):
        kv = last_kv(h, state)
        assert kv['limits_source'] == 'robot_description topic'
        assert TIGHT in kv['limits'], kv['limits']
        assert 'urdf robot_description topic: position, velocity' in kv['limits_sources']
        assert kv['robot_description_topic'] == 'in use'
        assert 'robot model from the robot_description topic' in log.read_text()
        assert h.wait(lambda: h.n_refs() > 10, EVIDENCE), log.read_text()

        # garbage: rejected with the reason, the model and the stream go on
        h.publish('robot_description', String(data='<robot name="broken"'))
        assert h.wait(lambda: rejected(h, 'streamer', 'malformed') == 1, EVIDENCE), \
            last_kv(h, 'streamer: input robot_description')
        reason = last_kv(h, 'streamer: input robot_description')['last_reason']
        assert reason.startswith('robot_description: not a valid URDF: malformed XML'), reason
        n0 = h.n_refs()
        assert h.wait(lambda: h.n_refs() > n0 + 50 and proc.poll() is None, EVIDENCE)
        kv = last_kv(h, state)
        assert kv['limits_source'] == 'robot_description topic' and TIGHT in kv['limits']
        assert kv['robot_description_topic'].startswith('rejected: not a valid URDF')

        # other joints: rejected
        h.publish('robot_description', String(data=WRONG_JOINTS))
        assert h.wait(lambda: rejected(h, 'streamer', 'joint_names') == 1, EVIDENCE), \
            last_kv(h, 'streamer: input robot_description')
        reason = last_kv(h, 'streamer: input robot_description')['last_reason']
        assert 'not a robot of the configured joint_names' in reason and 'joint_a' in reason

        # another robot model: a standing warning, not applied
        h.publish('robot_description', String(data=tightened('1.2')))
        assert h.wait(lambda: last_kv(h, state).get('robot_description_topic', '').startswith(
            'differs'), EVIDENCE), last_kv(h, state)
        st = last_status(h, state)
        assert st.values['robot_description_topic'] == (
            'differs from the model in use (the robot_description topic at start-up): '
            'panda_joint1 velocity 1.5 -> 1.2; a restart of the node applies it')
        assert 'robot_description topic differs from the model in use' in st.message
        assert TIGHT in st.values['limits']
        # the model in use again: the warning clears
        h.publish('robot_description', String(data=tightened()))
        assert h.wait(lambda: last_kv(h, state).get('robot_description_topic') == 'in use',
                      EVIDENCE), (last_kv(h, state), log.read_text())
        assert 'robot_description topic' not in last_status(h, state).message
        n0 = h.n_refs()
        assert h.wait(lambda: h.n_refs() > n0 + 50, EVIDENCE)
    assert not h.violations, h.violations[:5]


def test_a_garbage_description_at_start_up_gives_urdf_path_at_once(tmp_path):
    """The wait ends with the (rejected) message: the test waits far less than the
    node's 600 s timeout."""
    h, proc, log = streamer_given(tmp_path, 'not xml at all', 600.0)
    state = 'streamer: state'
    with running(proc, h, log, lambda: last_kv(h, state), STARTUP, 'streamer'):
        kv = last_kv(h, state)
        assert kv['limits_source'] == FILE
        assert 'velocity [2.175, 2.175' in kv['limits']
        assert kv['robot_description_topic'].startswith('rejected: not a valid URDF')
        assert h.wait(lambda: rejected(h, 'streamer', 'malformed') == 1, EVIDENCE)
        assert 'robot_description topic rejected' in last_status(h, state).message
        text = log.read_text()
        assert 'robot_description: not a valid URDF' in text and f'using urdf_path {FILE}' in text
        assert h.wait(lambda: h.n_refs() > 50 and proc.poll() is None, EVIDENCE)


def test_adapter_and_sim_with_and_without_the_wait(tmp_path):
    """The adapter waits (robot_description_timeout > 0) and uses the topic; the sim, with the
    default 0, runs with urdf_path and reports the different description as a warning that
    says how to apply it."""
    from std_msgs.msg import String

    from adapter_harness import start_adapter
    from cdmp_ros.ros import qos
    from cdmp_ros.ros.diagnostics import WARN
    from node_harness import NodeHarness, stop_process
    from sim_harness import start_sim
    h = NodeHarness('rd_test', DOMAIN)
    h.publisher(String, 'robot_description', qos.LATCHED)
    h.publish('robot_description', String(data=tightened()))
    logs = {name: tmp_path / f'{name}.log' for name in ('adapter', 'sim')}
    procs = {'adapter': start_adapter(DOMAIN, ['robot_description_timeout:=60.0',
                                               'diagnostics_period:=0.2'],
                                      log_path=str(logs['adapter'])),
             'sim': start_sim(DOMAIN, ['diagnostics_period:=0.2'], log_path=str(logs['sim']))}

    def text():
        return '\n'.join(f'--- {n}\n{p.read_text()}' for n, p in logs.items())
    try:
        ok = h.wait(lambda: (last_kv(h, 'adapter: state') and last_kv(h, 'sim: state'))
                    or any(p.poll() is not None for p in procs.values()), STARTUP)
        assert ok and all(p.poll() is None for p in procs.values()), text()
        kv = last_kv(h, 'adapter: state')
        assert kv['limits_source'] == 'robot_description topic'
        assert kv['robot_description_topic'] == 'in use'
        kv = last_kv(h, 'sim: state')
        assert kv['limits_source'] == FILE
        assert 'velocity [2.175, 2.175' in kv['limits']
        expected = (f'differs from the model in use ({FILE}): panda_joint1 velocity 2.175 -> '
                    '1.5; a restart of the node with robot_description_timeout > 0 applies it')
        assert h.wait(lambda: last_kv(h, 'sim: state').get('robot_description_topic')
                      == expected, EVIDENCE), last_kv(h, 'sim: state')
        st = last_status(h, 'sim: state')
        assert st.level == WARN[0], st
        assert st.message.endswith('; robot_description topic ' + expected), st.message
        assert 'robot_description topic: ' + expected in logs['sim'].read_text()
    finally:
        h.close()
        codes = {n: stop_process(p) for n, p in procs.items()}
    for name, code in codes.items():
        assert_clean_stop(code, logs[name].read_text(), name)
