"""Shutdown of every node as a real process (issue 10.5): SIGINT and SIGTERM end a node that is
up and working with exit code 0 and no traceback, a signal during start-up too, the recorder's
bag is closed and readable, and ``cdmp bringup`` forwards the signal and exits 0.

Every node is started from its config/*.yaml parameter file.  To keep the module short, the
processes of all cases start together (module fixture) and each test waits, with a generous
timeout, for positive evidence that its node works before it sends the signal:

- learner: an improvement (``~/improve``) is running (diagnostics ``improve: running k/N``,
  k >= 1); adapter: a solve is in progress (diagnostics ``solver_busy: True``, requests kept
  coming); streamer and sim: their diagnostics; recorder: messages of the test's topic in the
  bag file on disk; player: messages of a bag from bags/ received.

Cases run in one domain (module_domain(21)), isolated by namespaces (learner, adapter,
streamer, sim; their parameter files apply to ``/**``) or by remapped / selected topics
(recorder, player: their parameter file names the node, so they keep their name).  No timing
is asserted here: signal-to-exit times are measured by benchmarks/bench_shutdown.py.
"""
import os
import signal
import subprocess
import sys
import threading

import pytest

from conftest import REPO_ROOT, module_domain, ros_env
from conftest import wait_for as conftest_wait_for
from node_harness import NodeHarness, assert_bringup_stopped

pytestmark = pytest.mark.ros

DOMAIN = module_domain(21)
TIMEOUT = 60.0          # s, generous: the machine is shared and every case starts at once
SIGNALS = {'SIGINT': signal.SIGINT, 'SIGTERM': signal.SIGTERM}
NODES = ('learner', 'adapter', 'streamer', 'sim', 'recorder', 'player')
PARAMS_FILE = {'learner': 'learner.yaml', 'adapter': 'adapter.yaml',
               'streamer': 'streamer.yaml', 'sim': 'sim.yaml', 'recorder': 'bag.yaml',
               'player': 'bag.yaml'}
#: Signal used for the start-up case of each node (both signals are covered across nodes).
STARTUP_SIGNAL = {'learner': 'SIGINT', 'adapter': 'SIGTERM', 'streamer': 'SIGINT',
                  'sim': 'SIGTERM', 'recorder': 'SIGINT', 'player': 'SIGTERM'}
BAG = os.path.join(REPO_ROOT, 'bags', 'panda_reach', 'demo_00')


def wait_for(pred, timeout=TIMEOUT, period=0.02):
    """conftest's one wait, with this module's generous default."""
    return conftest_wait_for(pred, timeout, period)


def catches_sigterm(pid: int) -> bool:
    """True once the process has a handler for SIGTERM (node_main.catch_stop_signals ran):
    Python itself never catches SIGTERM, so this is the node's entry point at work."""
    try:
        with open(f'/proc/{pid}/status') as f:
            for line in f:
                if line.startswith('SigCgt:'):
                    return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    except OSError:
        return False
    return False


def rclpy_loaded(pid: int) -> bool:
    """True once the process has loaded rclpy's extension (imports nearly done)."""
    try:
        with open(f'/proc/{pid}/maps') as f:
            return '_rclpy_pybind11' in f.read()
    except OSError:
        return True


class Observer(NodeHarness):
    """rclpy peer on the test domain: diagnostics per namespace, test publishers."""

    def __init__(self):
        super().__init__('shutdown_test', DOMAIN, diagnostics=None)
        self.diags = {}     # namespace -> list of (status name in it, message, {key: value})
        self.counts = {}    # topic -> messages received
        self._diag_sub = None

    def watch_diagnostics(self, ns):
        """Record the statuses of the nodes in namespace ``ns``: every node publishes on
        ``/diagnostics``, its status names start with its name (``sd_sim_sigint/sim: state``)."""
        from diagnostic_msgs.msg import DiagnosticArray
        from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
        with self.lock:
            self.diags[ns] = []
        if self._diag_sub is None:
            self._diag_sub = self.node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                                           self._on_ns_diag, 100)

    def _on_ns_diag(self, msg):
        with self.lock:
            for st in msg.status:
                ns = st.name.split(':')[0].rpartition('/')[0]
                if '/' + ns in self.diags:  # 'sd_sim_sigint/sim: state' -> 'sim: state'
                    self.diags['/' + ns].append((st.name[len(ns) + 1 if ns else 0:], st.message,
                                                 {kv.key: kv.value for kv in st.values}))

    def diag_values(self, ns):
        with self.lock:
            return [v for _, _, v in self.diags[ns]]

    def count(self, msg_type, topic):
        """Count messages on ``topic`` (best effort: matches any publisher)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        self.counts[topic] = 0

        def on_msg(_msg):
            with self.lock:
                self.counts[topic] += 1
        self.node.create_subscription(msg_type, topic, on_msg, QoSProfile(
            depth=100, reliability=ReliabilityPolicy.BEST_EFFORT), raw=True)


class Case:
    """One node process: ``python -m cdmp_ros.nodes.<node>`` from its parameter file."""

    def __init__(self, node, sig_name, tag, tmp, extra=(), namespace=None):
        self.node, self.sig_name, self.tag = node, sig_name, tag
        self.ns = namespace
        self.log_path = os.path.join(tmp, f'{tag}.log')
        cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{node}', '--ros-args', '--params-file',
               os.path.join(REPO_ROOT, 'config', PARAMS_FILE[node]), *extra]
        if namespace:
            cmd += ['-r', f'__ns:={namespace}']
        self.log = open(self.log_path, 'w')
        self.proc = subprocess.Popen(cmd, env=ros_env(DOMAIN), cwd=REPO_ROOT, stdout=self.log,
                                     stderr=subprocess.STDOUT, start_new_session=True)

    def output(self):
        self.log.flush()
        with open(self.log_path) as f:
            return f.read()

    def alive(self):
        return self.proc.poll() is None

    def signal_and_wait(self):
        """Send the case's signal; the exit code (None if it hung for TIMEOUT s)."""
        self.proc.send_signal(SIGNALS[self.sig_name])
        try:
            return self.proc.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            return None

    def kill(self):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        self.log.close()


def promp_text():
    from adapter_harness import reach_promp
    from cdmp_ros.core.primitive_io import dumps_primitive
    return dumps_primitive(reach_promp())


@pytest.fixture(scope='module')
def world(tmp_path_factory):
    """Every case's process, started together, and the observer with its inputs."""
    from std_msgs.msg import String
    from sensor_msgs.msg import JointState
    from cdmp_ros.ros import qos
    tmp = str(tmp_path_factory.mktemp('shutdown'))
    obs = Observer()
    cases = {}
    pubs = []
    try:
        for sig in SIGNALS:
            t = sig.lower()
            ns = {n: f'/sd_{n}_{t}' for n in NODES}
            for n in ('learner', 'adapter', 'streamer', 'sim'):
                obs.watch_diagnostics(ns[n])
            # learner: a long improvement, so that one runs when the signal comes
            cases['learner', sig] = Case('learner', sig, f'learner_{t}', tmp, namespace=ns[
                'learner'], extra=['-p', 'improve.updates:=100000'])
            # adapter: longer solves (more constraint time steps), requests keep coming
            cases['adapter', sig] = Case('adapter', sig, f'adapter_{t}', tmp, namespace=ns[
                'adapter'], extra=['-p', 'adaptation.n_steps:=400', '-p',
                                   'adaptation.max_outer:=50'])
            cases['streamer', sig] = Case('streamer', sig, f'streamer_{t}', tmp,
                                          namespace=ns['streamer'])
            cases['sim', sig] = Case('sim', sig, f'sim_{t}', tmp, namespace=ns['sim'])
            chatter = f'{ns["recorder"]}/chatter'
            cases['recorder', sig] = Case(
                'recorder', sig, f'recorder_{t}', tmp,
                extra=['-p', f'output:={os.path.join(tmp, "bag_" + t)}',
                       '-p', f"topics:=['{chatter}']"])
            cases['recorder', sig].topic = chatter
            cases['recorder', sig].bag = os.path.join(tmp, 'bag_' + t)
            played = f'{ns["player"]}/demonstration'
            obs.count(JointState, played)
            cases['player', sig] = Case('player', sig, f'player_{t}', tmp, extra=[
                '-p', f'bag:={BAG}', '-p', 'loop:=true', '-r', f'/demonstration:={played}'])
            cases['player', sig].topic = played
        # inputs: a ProMP for both adapters, sequence-numbered chatter for both recorders
        text = promp_text()
        for sig in SIGNALS:
            ns = f'/sd_adapter_{sig.lower()}'
            p = obs.node.create_publisher(String, f'{ns}/primitive', qos.LATCHED)
            p.publish(String(data=text))
            pubs.append(p)
        yield obs, cases, tmp
    finally:
        for c in cases.values():
            c.kill()
        obs.close()


class Chatter:
    """Publishes String 'seq' on a recorder case's topic at 100 Hz from a thread."""

    def __init__(self, obs, topic):
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String
        self.String = String
        self.pub = obs.node.create_publisher(String, topic, QoSProfile(
            depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        self.seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.wait(0.01):
            self.pub.publish(self.String(data=str(self.seq)))
            self.seq += 1

    def stop(self):
        self._stop.set()
        self._thread.join(5)


class Goals(Chatter):
    """Publishes joint-space goals near the ProMP's goal at about 16 Hz (under the adapter's
    20/s input limit) on an adapter case's topic: faster than the solves finish, so the solver
    is busy nearly all the time and its diagnostics say so at the next report."""

    def __init__(self, obs, topic):
        from sensor_msgs.msg import JointState
        from adapter_harness import PANDA_JOINTS, Q_GOAL
        from cdmp_ros.ros import qos
        self.msg = JointState(name=list(PANDA_JOINTS))
        self.q = Q_GOAL
        self.pub = obs.node.create_publisher(JointState, topic, qos.COMMAND)
        self.seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.wait(0.06):
            self.msg.position = [float(x) for x in self.q + 0.01 * (self.seq % 5)]
            self.pub.publish(self.msg)
            self.seq += 1


def recorded_on_disk(bag_dir):
    """Sequence numbers of the messages already in the (open) bag file."""
    from rclpy.serialization import deserialize_message
    from std_msgs.msg import String
    from cdmp_ros.bag.errors import BagError
    from cdmp_ros.bag.scan import MessageRec, scan
    files = [f for f in os.listdir(bag_dir) if f.endswith('.mcap')] \
        if os.path.isdir(bag_dir) else []
    seqs = []
    for f in files:
        try:
            for rec in scan(os.path.join(bag_dir, f), require_footer=False):
                if isinstance(rec, MessageRec):
                    seqs.append(int(deserialize_message(rec.data, String).data))
        except BagError:  # a chunk being written: what came before it counts
            pass
    return seqs


def check_bag(bag_dir):
    """The bag is closed and readable by cdmp_ros.bag and rosbags; returns its seq numbers."""
    from pathlib import Path
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from std_msgs.msg import String
    from cdmp_ros.bag import BagReader
    assert os.path.isfile(os.path.join(bag_dir, 'metadata.yaml'))
    reader = BagReader(bag_dir)
    reader.verify()  # every CRC, the footer and the summary
    seqs = [int(deserialize_message(m.data, String).data) for m in reader.messages()]
    with Reader(Path(bag_dir)) as rb:
        assert rb.message_count == len(seqs)
        assert len(list(rb.messages())) == len(seqs)
    return seqs


def wait_working(obs, case):
    """Positive evidence that the case's node is up and doing its work."""
    n = case.node
    if n == 'learner':
        from std_srvs.srv import Trigger
        assert wait_for(lambda: any(v.get('primitive', 'none') != 'none'
                                    for v in obs.diag_values(case.ns))), case.output()
        cli = obs.node.create_client(Trigger, f'{case.ns}/learner/improve')
        assert cli.wait_for_service(TIMEOUT), case.output()
        fut = cli.call_async(Trigger.Request())
        assert wait_for(fut.done), case.output()
        assert fut.result().success, fut.result().message

        def improving():
            for v in obs.diag_values(case.ns):
                run = v.get('improve', '')
                if run.startswith('running') and int(run.split()[1].split('/')[0]) >= 1:
                    return True
            return False
        assert wait_for(improving), case.output()
    elif n == 'adapter':
        # a solve in progress: requests keep coming (goals at 16 Hz, each one a new solve)
        # until diagnostics say the solver is busy
        goals = Goals(obs, f'{case.ns}/goal')
        try:
            assert wait_for(lambda: any(v.get('solver_busy') == 'True'
                                        for v in obs.diag_values(case.ns))), case.output()
        finally:
            goals.stop()
    elif n in ('streamer', 'sim'):
        assert wait_for(lambda: len(obs.diag_values(case.ns)) > 0), case.output()
    elif n == 'recorder':
        case.chatter = Chatter(obs, case.topic)
        assert wait_for(lambda: len(recorded_on_disk(case.bag)) >= 10), case.output()
        case.on_disk = max(recorded_on_disk(case.bag))
    elif n == 'player':
        assert wait_for(lambda: obs.counts[case.topic] > 0), case.output()
    assert case.alive(), case.output()


@pytest.mark.parametrize('sig', list(SIGNALS))
@pytest.mark.parametrize('node', NODES)
def test_a_working_node_stops_cleanly(world, node, sig):
    obs, cases, _ = world
    case = cases[node, sig]
    wait_working(obs, case)
    rc = case.signal_and_wait()
    out = case.output()
    assert rc == 0, out
    assert 'Traceback' not in out, out
    if node == 'recorder':
        case.chatter.stop()
        seqs = check_bag(case.bag)
        # everything recorded up to the signal, in order, nothing lost in between
        assert seqs == list(range(seqs[0], seqs[-1] + 1)), seqs
        assert seqs[-1] >= case.on_disk
        assert f'closed {case.bag}: {len(seqs)} messages' in out
    if node == 'adapter':
        assert 'solver thread still busy' not in out, out


@pytest.mark.parametrize('node', NODES)
def test_a_signal_during_start_up_ends_the_node_cleanly(world, node):
    """Sent while the node is still importing (its entry point already catches the signals,
    rclpy is not loaded yet): exit code 0, no traceback; the recorder, stopped before it
    was built, leaves no bag (or, had it been built, a closed and readable one)."""
    _, cases, tmp = world
    sig = STARTUP_SIGNAL[node]
    for attempt in range(3):  # the test may be descheduled past the imports: start again
        tag = f'{node}_startup{attempt}'
        bag = os.path.join(tmp, f'bag_{tag}')
        extra = {'player': ['-p', f'bag:={BAG}'],
                 'recorder': ['-p', f'output:={bag}',
                              '-p', "topics:=['/sd_recorder_startup/chatter']"]}.get(node, [])
        case = Case(node, sig, tag, tmp, extra=extra,
                    namespace=None if node in ('recorder', 'player') else f'/sd_{tag}')
        cases[node, tag] = case  # killed by the fixture if it hangs
        assert wait_for(lambda: catches_sigterm(case.proc.pid) or not case.alive(),
                        period=0.001), case.output()
        importing = not rclpy_loaded(case.proc.pid)
        rc = case.signal_and_wait()
        out = case.output()
        assert rc == 0, out
        assert 'Traceback' not in out, out
        if node == 'recorder' and os.path.exists(bag):
            assert check_bag(bag) == []
        if importing:
            break
    assert importing, 'the signal never arrived during the imports'


def test_adapt_is_cancelled_by_should_stop():
    """The adapter's shutdown cancels a solve within one evaluation of the Lagrangian."""
    from adapter_harness import reach_promp
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.core.adaptation.constraints.limits import JointLimit
    from cdmp_ros.core.errors import Cancelled
    calls = []

    def should_stop():
        calls.append(1)
        return len(calls) > 3
    prior = reach_promp()
    with pytest.raises(Cancelled):  # joint 1 held far from the prior: a long solve
        adapt(prior, [JointLimit(0, lower=-0.1, upper=0.1, alpha=0.99)],
              should_stop=should_stop)
    assert len(calls) == 4


@pytest.mark.parametrize('sig', list(SIGNALS))
def test_bringup_forwards_the_signal_and_exits_0(tmp_path, sig):
    import yaml
    ns = f'/sd_bringup_{sig.lower()}'
    graph = tmp_path / 'graph.yaml'
    graph.write_text(yaml.safe_dump({'stop_timeout': 30.0, 'nodes': [
        {'name': 'sim', 'executable': 'sim', 'params_file': 'sim.yaml', 'namespace': ns},
        {'name': 'streamer', 'executable': 'streamer', 'params_file': 'streamer.yaml',
         'namespace': ns}]}))
    obs = Observer()
    proc = None
    try:
        obs.watch_diagnostics(ns)
        proc = subprocess.Popen([sys.executable, '-m', 'cdmp_ros.cli.main', 'bringup',
                                 str(graph)], env=ros_env(DOMAIN), cwd=REPO_ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)

        def both_up():
            with obs.lock:
                return {'sim', 'streamer'} <= {name.split(':')[0] for name, _, _ in obs.diags[ns]}
        assert wait_for(both_up), [name for name, _, _ in obs.diags[ns]]
        proc.send_signal(SIGNALS[sig])
        out, _ = proc.communicate(timeout=TIMEOUT)
    finally:
        if proc is not None and proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        obs.close()
    assert_bringup_stopped(proc.returncode, out)
    assert 'Traceback' not in out, out
