"""The common part of the process-level node tests: node processes and a test-side rclpy node.

- :func:`start_node` starts ``python -m cdmp_ros.nodes.<executable>`` with ``--params-file``,
  ``-p`` parameters and ``-r`` remappings under :func:`conftest.ros_env` (localhost discovery,
  the test's private domain id); :func:`stop_process` stops it (SIGINT, then SIGKILL).
- :class:`NodeHarness` is a test-side node in its own rclpy context on a private domain id
  (:func:`conftest.module_domain`), spun by a background thread, with publishers and
  subscriptions helpers, the record of every ``/diagnostics`` status (:class:`Diag`, the
  records :mod:`conftest`'s evidence helpers read) and the waits on them, Trigger and
  parameter service calls, and stamped JointState messages. The per-node harnesses
  (``streamer_harness``, ``adapter_harness``, ``sim_harness``, ``learner_harness``,
  ``bag_ros_util``) subclass it with what is specific to their node.
- The Panda test data shared by those tests (joint names, limits, start and goal), the
  malformed JointState cases every node with JointState input rejects
  (:func:`bad_joint_state`), and the parameter files' contents and the defaults they mirror.
- :func:`running` (a node process serving a test) and :func:`expect_startup_failures`.

Every wait is on a condition (:func:`conftest.wait_for`) with a generous timeout.
"""
import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
import warnings
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Union

import numpy as np

from cdmp_ros.common.node_signals import teardown_hang
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from conftest import REPO_ROOT, ros_env, wait_for

PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
# Panda limits of pybullet_data's panda.urdf (checked against the URDF in test_core_streaming)
LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
Q_START = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
Q_GOAL = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])

#: The node input topics as the nodes subscribe them: topic -> (message module, message type,
#: name of the cdmp_ros.ros.qos profile); imported when a publisher is made (no rclpy here).
INPUT_TOPICS = {
    'primitive': ('std_msgs.msg', 'String', 'LATCHED'),
    'adapted_primitive': ('std_msgs.msg', 'String', 'LATCHED'),
    'goal': ('sensor_msgs.msg', 'JointState', 'COMMAND'),
    'goal_point': ('geometry_msgs.msg', 'PointStamped', 'COMMAND'),
    'constraints': ('std_msgs.msg', 'String', 'COMMAND'),
    'joint_states': ('sensor_msgs.msg', 'JointState', 'COMMAND'),
    'obstacles': ('visualization_msgs.msg', 'MarkerArray', 'COMMAND'),
    'joint_reference': ('sensor_msgs.msg', 'JointState', 'REFERENCE'),
}
#: Bound of a wait on a condition [s]: it only bounds a failure, a pass never waits it out.
WAIT_S = 30.0


# -- node processes ----------------------------------------------------------------------------
def _param_text(name: str, value) -> str:
    if isinstance(value, bool):
        value = 'true' if value else 'false'
    elif isinstance(value, (list, tuple)):
        value = '[' + ', '.join(f"'{x}'" for x in value) + ']'
    return f'{name}:={value}'


def start_node(executable: str, params: Union[Sequence[str], Dict[str, object]] = (),
               domain_id: Optional[int] = None, params_file: Optional[str] = None,
               remaps: Sequence[str] = (), log_path=None, extra: Sequence[str] = (),
               env: Optional[dict] = None, cwd: Optional[str] = REPO_ROOT,
               new_session: bool = True) -> subprocess.Popen:
    """Start ``python -m cdmp_ros.nodes.<executable> --ros-args ...``.

    Parameters
    ----------
    executable : str
        ``streamer``, ``adapter``, ``sim``, ``learner``, ``recorder``, ``player``.
    params : sequence of 'name:=value' or dict
        ``-p`` parameters; dict values are formatted (bools, lists of strings).
    domain_id : int, optional
        The private ROS domain id (default: the session's ``ROS_DOMAIN_ID``).
    params_file : str, optional
        ``--params-file`` (before the ``-p`` parameters, which win).
    remaps : sequence of 'from:=to'
    log_path : path, optional
        stdout and stderr go there (else nowhere).
    extra : sequence of str
        More ROS arguments, first.
    env : dict, optional
        Environment variables added to :func:`conftest.ros_env`.
    cwd : str, optional
    new_session : bool
        Start the process in its own session (:func:`stop_process` kills its group).
    """
    cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{executable}', '--ros-args', *extra]
    if params_file:
        cmd += ['--params-file', params_file]
    items = params.items() if isinstance(params, dict) else None
    for p in (params if items is None else (_param_text(k, v) for k, v in items)):
        cmd += ['-p', p]
    for r in remaps:
        cmd += ['-r', r]
    child_env = ros_env(domain_id)
    child_env.update(env or {})
    out = open(log_path, 'w') if log_path else subprocess.DEVNULL
    return subprocess.Popen(cmd, env=child_env, cwd=cwd, stdout=out,
                            stderr=subprocess.STDOUT, start_new_session=new_session)


def stop_process(proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = WAIT_S) -> int:
    """``sig`` (SIGINT), then SIGKILL (of the process group when it has its own session) if
    it has not ended within ``timeout``; returns the exit code."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            try:
                own_group = os.getpgid(proc.pid) == proc.pid
            except ProcessLookupError:
                own_group = False
            if own_group:
                os.killpg(proc.pid, signal.SIGKILL)
            else:
                proc.kill()
            return proc.wait(5)
    return proc.returncode


@contextlib.contextmanager
def running(proc: subprocess.Popen, harness: 'NodeHarness', log, ready: Callable,
            timeout: float, what: str = 'node', exit_code: Optional[int] = 0):
    """The node process ``proc`` (log file ``log``) serving a test with ``harness``: waits
    until ``ready()`` (asserting that the process is alive then); at the end closes the
    harness and stops the process (:func:`stop_process`), which must exit with ``exit_code``
    (None: not checked) when the body did not fail."""
    try:
        ok = harness.wait(lambda: ready() or proc.poll() is not None, timeout)
        assert ok and proc.poll() is None, log.read_text()
        yield
    finally:
        harness.close()
        code = stop_process(proc)
    if exit_code is not None:
        if exit_code == 0:
            assert_clean_stop(code, log.read_text(), what)
        else:
            assert code == exit_code, f'{what} exit code {code}\n{log.read_text()}'


@contextlib.contextmanager
def graph_running(bringup, harness: 'NodeHarness', log):
    """A started node graph (:class:`cdmp_ros.cli.cmd_bringup.Bringup` ``bringup``, writing to
    the open file ``log``) serving a test with ``harness``: at the end closes the harness,
    stops the graph and the log; every node must have exited with 0 or by SIGINT when the body
    did not fail."""
    try:
        yield
    finally:
        harness.close()
        codes = bringup.stop()
        log.close()
    with open(log.name) as f:
        tail = f.read()[-3000:]
    hung = set(bringup.teardown_hangs())
    for name in hung:
        warn_teardown_hang(name, codes[name])
    assert all(c in (0, -signal.SIGINT) or n in hung for n, c in codes.items()), \
        f'{codes}\n{tail}'


def assert_clean_stop(code: int, output: str, what: str = 'node') -> None:
    """A node stopped by SIGINT / SIGTERM exited with 0, or its exit was the known teardown
    hang below rclpy (:func:`warn_teardown_hang`: a warning); ``output`` is its log."""
    if code != 0 and teardown_hang(code, output):
        warn_teardown_hang(what, code)
        return
    assert code == 0, f'{what} exit code {code}\n{output}'


def assert_bringup_stopped(code: int, text: str, expected: int = 0) -> None:
    """``cdmp bringup``'s exit ``code`` and output ``text``: every node stopped cleanly and
    the code is ``expected``; or the nodes that did not are the teardown hang below rclpy
    (:func:`warn_teardown_hang`, named by bringup; exit code 4, or ``expected`` if not 0)."""
    from cdmp_ros.cli.cmd_bringup import TEARDOWN_HANG_EXIT_CODE, TEARDOWN_HANG_LINE
    if 'all nodes stopped cleanly' in text:
        assert code == expected, text
        return
    before, after = (re.escape(part.strip('\n')) for part in TEARDOWN_HANG_LINE.split('{nodes}'))
    hung = re.findall(f'^{before}(.+?){after}$', text, re.M)
    assert hung and code == (expected or TEARDOWN_HANG_EXIT_CODE), f'exit code {code}\n{text}'
    warn_teardown_hang(', '.join(hung), code)


def warn_teardown_hang(what: str, code: int) -> None:
    """A node's exit after SIGINT was the known, bounded hang of rclpy's middleware teardown
    after the node's close() returned (:func:`cdmp_ros.common.node_signals.teardown_hang`;
    rare, below rclpy, issue 31 item 3; its rate is in benchmarks/RESULTS.md). The fixtures
    check the stop of the node's own code, which finished: such an exit is a warning, any
    other non-zero exit fails the test."""
    warnings.warn(f"{what}: rclpy's middleware teardown hung after close() returned; the "
                  f'stop backstop ended it with exit code {code} (issue 31 item 3)')


def expect_startup_failures(procs, timeout: float) -> None:
    """Each of ``procs`` [(process, text, log path)], started together (start-up is slow),
    exits with code 2 and ``text`` in its log; every one is stopped in the end."""
    try:
        for proc, text, log_path in procs:
            code = proc.wait(timeout)
            with open(log_path) as f:
                log = f.read()
            assert code == 2 and text in log, log
    finally:
        for proc, _, _ in procs:
            stop_process(proc)


# -- bad input ---------------------------------------------------------------------------------
#: JointState case of :func:`bad_joint_state` -> the text of the nodes' rejection reason.
JOINT_STATE_CASES = {
    'nan': 'expected a finite value, got nan', 'inf': 'expected a finite value, got -inf',
    'wrong_length': 'position: expected 7 values', 'velocity_length': 'velocity: expected 0 or',
    'missing_name': "missing joints ['panda_joint7']", 'duplicate_name': 'duplicate joint name',
    'future_stamp': 'in the future', 'past_stamp': 'in the past'}
#: The same on a goal, where the joints must be the robot's ones only.
GOAL_CASES = dict(JOINT_STATE_CASES, unknown_name="unknown joints ['elbow_joint']")


def bad_joint_state(make: Callable, case: str, names: Sequence[str] = PANDA_JOINTS,
                    inf: float = float('-inf')):
    """A JointState broken as ``case`` says: 'nan' / 'inf' (``inf``) / 'nan_velocity' values,
    'wrong_length' / 'velocity_length' arrays, 'unknown_name' / 'missing_name' /
    'duplicate_name' joints, 'future_stamp' (60 s ahead) / 'past_stamp' (an hour behind).

    ``make(stamp_offset)`` returns a valid message of the joints ``names`` stamped now +
    ``stamp_offset`` [s]; a case not listed here returns that valid message unchanged, for
    the caller to break."""
    if case == 'future_stamp':
        return make(60.0)
    if case == 'past_stamp':
        return make(-3600.0)
    names = list(names)
    msg = make(0.0)
    if case == 'nan':
        msg.position[2] = float('nan')
    elif case == 'inf':
        msg.position[4] = inf
    elif case == 'nan_velocity':
        msg.velocity = [0.0] * 6 + [float('nan')]
    elif case == 'wrong_length':
        msg.position = msg.position[:5]
    elif case == 'velocity_length':
        msg.velocity = [0.0, 0.0]
    elif case == 'unknown_name':
        msg.name = names[:6] + ['elbow_joint']
    elif case == 'missing_name':
        msg.name = names[:6]
        msg.position = msg.position[:6]
    elif case == 'duplicate_name':
        msg.name = names[:6] + [names[0]]
    return msg


# -- parameter files ---------------------------------------------------------------------------
def config_file_parameters(name: str) -> dict:
    """The ``/**`` parameters of ``config/<name>.yaml``, one level of sections flattened to
    'section.name' keys, lists as tuples."""
    import yaml
    with open(os.path.join(REPO_ROOT, 'config', f'{name}.yaml')) as f:
        params = yaml.safe_load(f)['/**']['ros__parameters']
    flat = {}
    for k, v in params.items():
        if isinstance(v, dict):
            flat.update({f'{k}.{kk}': vv for kk, vv in v.items()})
        else:
            flat[k] = tuple(v) if isinstance(v, list) else v
    return flat


def parameter_defaults(sections) -> dict:
    """'prefix.name' (or 'name' for the prefix '') -> default of every parameter of the
    config classes of ``sections`` [(prefix, class)]."""
    from cdmp_ros.ros.params import parameter_fields
    expected = {}
    for prefix, cls in sections:
        for f, kind, default in parameter_fields(cls):
            expected[f'{prefix}.{f.name}' if prefix else f.name] = default
    return expected


# -- the test-side node ------------------------------------------------------------------------
class Diag(NamedTuple):
    """One received diagnostics status."""

    t: float          # time.monotonic() at reception
    name: str
    message: str
    level: int
    values: Dict[str, str]


def stamp_ns(stamp) -> int:
    """A builtin_interfaces/Time in ns."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def set_stamp(header, t_ns: int) -> None:
    header.stamp.sec, header.stamp.nanosec = divmod(int(t_ns), 1_000_000_000)


class NodeHarness:
    """A test-side node in its own rclpy context, spun by a background thread.

    Parameters
    ----------
    name : str
        Node name.
    domain_id : int, optional
        Private domain id (default: the session's ``ROS_DOMAIN_ID``).
    diagnostics : str or None
        Topic whose statuses are recorded in :attr:`diag_messages` (default ``/diagnostics``,
        every node's; None: none).
    diagnostics_depth : int
        Queue depth of that subscription.
    spin_period : float
        ``spin_once`` timeout of the background thread [s].
    spin : bool
        Start spinning at once; a subclass passes False, creates its publishers and
        subscriptions, then calls :meth:`start`.

    Attributes
    ----------
    lock : threading.Lock
        Guards everything the callbacks record.
    diag_messages : list of Diag
    pub : dict
        Topic -> publisher (:meth:`publisher`).
    """

    def __init__(self, name: str, domain_id: Optional[int] = None,
                 diagnostics: Optional[str] = DIAGNOSTICS_TOPIC, diagnostics_depth: int = 50,
                 spin_period: float = 0.05, spin: bool = True):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.context = rclpy.Context()
        if domain_id is None:
            domain_id = int(os.environ['ROS_DOMAIN_ID'])
        rclpy.init(context=self.context, domain_id=int(domain_id))
        self.node = rclpy.create_node(name, context=self.context)
        self.lock = threading.Lock()
        self.diag_messages: List[Diag] = []
        self.pub: Dict[str, object] = {}
        self._matched = set()  # topics whose publisher was seen matched (see publish)
        if diagnostics is not None:
            from diagnostic_msgs.msg import DiagnosticArray
            self.node.create_subscription(DiagnosticArray, diagnostics, self._on_diag,
                                          diagnostics_depth)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._spin_period = spin_period
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        if spin:
            self.start()

    def start(self) -> None:
        """Start the background spin thread."""
        self.thread.start()

    # -- background --------------------------------------------------------------------------
    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=self._spin_period)
            except Exception:  # noqa: BLE001 -- context shut down at teardown
                if self._stop.is_set():
                    return
                raise

    def _on_diag(self, msg) -> None:
        t = time.monotonic()
        with self.lock:
            for s in msg.status:
                level = (int.from_bytes(s.level, 'little') if isinstance(s.level, bytes)
                         else int(s.level))
                self.diag_messages.append(Diag(t, s.name, s.message, level,
                                               {kv.key: kv.value for kv in s.values}))

    # -- publishers and subscriptions ---------------------------------------------------------
    def publisher(self, msg_type, topic: str, qos=None, depth: int = 1000):
        """A publisher on ``topic`` (also :attr:`pub` [topic]); default QoS reliable keep-last
        ``depth``: with ``depth`` at least the number of messages a test publishes, no sample
        is replaced before every reader acknowledged it."""
        if qos is None:
            from rclpy.qos import QoSProfile, ReliabilityPolicy
            qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        pub = self.node.create_publisher(msg_type, topic, qos)
        self.pub[topic] = pub
        return pub

    def input_publishers(self, *topics: str) -> None:
        """Publishers on the named node input topics, each with the message type and QoS the
        nodes subscribe it with (:data:`INPUT_TOPICS`)."""
        import importlib
        from cdmp_ros.ros import qos
        for topic in topics:
            module, msg_type, profile = INPUT_TOPICS[topic]
            self.publisher(getattr(importlib.import_module(module), msg_type), topic,
                           getattr(qos, profile))

    def publish(self, topic: str, msg) -> None:
        """Publish on ``topic``; on a volatile topic the first time only after the publisher
        matched a subscription (up to WAIT_S): a one-shot message published before the node's
        reader is discovered would be lost, and the test would wait for nothing. A
        transient-local (latched) message reaches late readers anyway: no wait."""
        from rclpy.qos import DurabilityPolicy
        pub = self.pub[topic]
        if topic not in self._matched:
            if pub.qos_profile.durability != DurabilityPolicy.TRANSIENT_LOCAL:
                wait_matched(pub)
            self._matched.add(topic)
        pub.publish(msg)

    def subscribe(self, msg_type, topic: str, callback: Callable, qos=None, raw: bool = False):
        """A subscription (default QoS reliable keep-last 1000: lose nothing)."""
        if qos is None:
            from rclpy.qos import QoSProfile, ReliabilityPolicy
            qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        return self.node.create_subscription(msg_type, topic, callback, qos, raw=raw)

    def collect(self, msg_type, topic: str, qos=None, raw: bool = True) -> list:
        """Subscribe; returns a list that fills with (monotonic time, message)."""
        got = []
        self.subscribe(msg_type, topic, lambda m: got.append((time.monotonic(), m)), qos, raw)
        return got

    # -- waits and diagnostics ----------------------------------------------------------------
    def wait(self, pred: Callable, timeout: float = WAIT_S):
        return wait_for(pred, timeout)

    def wait_diag(self, text: str, since: float, timeout: float = WAIT_S,
                  name: Optional[str] = None):
        """Wait for a diagnostics status (after ``since``) whose message contains ``text``
        (and whose name contains ``name``)."""
        def found():
            with self.lock:
                return any(d.t >= since and text in d.message
                           and (name is None or name in d.name) for d in self.diag_messages)
        return self.wait(found, timeout)

    def reject(self, topic: str, make: Callable, text: str, name: Optional[str] = None,
               resend: bool = False, timeout: float = WAIT_S) -> float:
        """Publish ``make()`` (a message or a list of them) on ``topic`` and assert that the
        node reports its rejection: a diagnostics status whose message contains ``text`` and
        whose name contains ``name`` (default 'input <topic>'). With ``resend`` it is
        published again at every poll until reported (a best-effort topic may lose it).
        Returns the time before the first publication."""
        name = f'input {topic}' if name is None else name
        t0 = time.monotonic()

        def send():
            msgs = make()
            for msg in (msgs if isinstance(msgs, list) else [msgs]):
                self.publish(topic, msg)
        if resend:
            def reported():
                send()
                return self.wait_diag(text, t0, timeout=0.0, name=name)
            ok = self.wait(reported, timeout)
        else:
            send()
            ok = self.wait_diag(text, t0, timeout, name)
        assert ok, [d[1:3] for d in self.diag_messages if d.t >= t0][-6:]
        return t0

    def _is_state(self, name: str) -> bool:
        return name.endswith(': state')

    def last_state(self):
        """(message, values) of the newest state status, or (None, {})."""
        with self.lock:
            for d in reversed(self.diag_messages):
                if self._is_state(d.name):
                    return d.message, d.values
        return None, {}

    def statuses_since(self, since: float):
        """(message, level, values) of every state status received after ``since``."""
        with self.lock:
            return [(d.message, d.level, d.values) for d in self.diag_messages
                    if d.t >= since and self._is_state(d.name)]

    # -- services ------------------------------------------------------------------------------
    def call_trigger(self, client, timeout: float = WAIT_S):
        """Call a std_srvs/Trigger ``client``; returns the response."""
        from std_srvs.srv import Trigger
        assert client.wait_for_service(timeout_sec=timeout), f'no service {client.srv_name}'
        fut = client.call_async(Trigger.Request())
        assert self.wait(fut.done, timeout), f'{client.srv_name}: no answer'
        return fut.result()

    #: Name of the node under test, whose parameters :meth:`set_parameter` sets.
    target: Optional[str] = None

    def set_parameter(self, name: str, value, timeout: float = WAIT_S):
        """Set parameter ``name`` of the node under test (:attr:`target`)."""
        return self.set_node_parameter(self.target, name, value, timeout)

    def refusal(self, name: str, value, timeout: float = WAIT_S) -> str:
        """Set parameter ``name`` of the node under test to ``value``; asserts that the node
        refused it and returns the reason."""
        r = self.set_parameter(name, value, timeout)
        assert not r.successful, f'{name} := {value!r} was accepted'
        return r.reason

    def set_node_parameter(self, node_name: str, name: str, value, timeout: float = 10.0):
        """Set parameter ``name`` of node ``node_name`` by its service; returns the
        SetParametersResult."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        client = self.node.create_client(SetParameters, f'/{node_name}/set_parameters')
        try:
            assert client.wait_for_service(timeout_sec=timeout)
            req = SetParameters.Request(
                parameters=[Parameter(name, value=value).to_parameter_msg()])
            fut = client.call_async(req)
            assert self.wait(fut.done, timeout)
            return fut.result().results[0]
        finally:
            self.node.destroy_client(client)

    # -- messages ------------------------------------------------------------------------------
    def now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def joint_state(self, positions, names=PANDA_JOINTS, velocities=None,
                    stamp_offset: float = 0.0, zero: bool = False,
                    stamp_ns: Optional[int] = None):
        """A sensor_msgs/JointState stamped now + ``stamp_offset`` [s] (``stamp_ns`` if
        given; unstamped with ``zero``)."""
        from sensor_msgs.msg import JointState
        msg = JointState()
        if not zero:
            set_stamp(msg.header, stamp_ns if stamp_ns is not None
                      else self.now_ns() + int(stamp_offset * 1e9))
        msg.name = list(names)
        msg.position = [float(v) for v in positions]
        if velocities is not None:
            msg.velocity = [float(v) for v in velocities]
        return msg

    def close(self) -> None:
        self._stop.set()
        if self.thread.is_alive():
            self.thread.join(timeout=WAIT_S)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def wait_matched(pub, n: int = 1, timeout: float = WAIT_S):
    """Wait until ``pub`` matched ``n`` subscriptions.

    A reliable volatile writer delivers every sample written after it matched a reader, even
    when the reader side completes its own match later (the reader asks for what it missed),
    so no sleep is needed after this.
    """
    return wait_for(lambda: pub.get_subscription_count() >= n, timeout)


def wait_acked(pub, timeout: float = WAIT_S):
    """Wait until every matched reader acknowledged every sample of ``pub`` (reliable)."""
    from rclpy.duration import Duration
    return pub.wait_for_all_acked(Duration(seconds=float(timeout)))
