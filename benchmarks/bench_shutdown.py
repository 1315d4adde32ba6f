"""Shutdown latency of every node (issue 10.5): time from SIGINT / SIGTERM to process exit.

For each node (learner, adapter, streamer, sim, recorder, player; ``python -m
cdmp_ros.nodes.<node>`` from its config/*.yaml parameter file) and each signal, ``--reps``
runs: start the node, wait until it logged that it is up (and, for the recorder, that it
subscribed to the topic a companion player publishes), let it work ``--settle`` s, send the
signal and time the exit. Two more rows stop a node in its heaviest state: ``adapter
(solving)`` gets a ProMP and goals at 5 Hz with ``adaptation.n_steps:=400`` and is
signalled once its diagnostics say ``solver_busy: True``; ``learner (improving)`` is
signalled once its ``~/improve`` (100,000 updates) reported progress. Prints median / max
per row, the exit codes, whether any output held a traceback, and checks max < 2 s.

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_shutdown.py [--reps 5] [--settle 1.0] [--domain 181]
"""
import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'test'))

TARGET_S = 2.0
READY = {'learner': 'published /primitive', 'adapter': 'adapting primitives',
         'streamer': 'streaming ', 'sim': 'simulating ', 'recorder': 'subscribed to',
         'player': 'playing '}
BAG = os.path.join(REPO, 'bags', 'panda_reach', 'demo_00')


def env(domain):
    e = dict(os.environ)
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    e['ROS_DOMAIN_ID'] = str(domain)
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    return e


def args_of(node, tmp, i):
    cfg = os.path.join(REPO, 'config')
    if node == 'recorder':
        return ['--params-file', os.path.join(cfg, 'bag.yaml'),
                '-p', f'output:={os.path.join(tmp, f"bag_{i}")}',
                '-p', "topics:=['/demonstration']"]
    if node == 'player':
        return ['--params-file', os.path.join(cfg, 'bag.yaml'), '-p', f'bag:={BAG}',
                '-p', 'loop:=true', '-r', '/demonstration:=/played']
    return ['--params-file', os.path.join(cfg, f'{node}.yaml')]


class Proc:
    def __init__(self, node, extra, domain):
        self.lines = []
        self.ready = threading.Event()
        self.node = node
        self.p = subprocess.Popen([sys.executable, '-m', f'cdmp_ros.nodes.{node}', '--ros-args',
                                   *extra], cwd=REPO, env=env(domain), stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, start_new_session=True)
        self.t = threading.Thread(target=self._pump, daemon=True)
        self.t.start()

    def _pump(self):
        for line in self.p.stdout:
            self.lines.append(line)
            if READY[self.node] in line:
                self.ready.set()

    def stop(self, sig, timeout=30.0):
        """(seconds from the signal to the exit, exit code or 'hung')."""
        t0 = time.monotonic()
        self.p.send_signal(sig)
        try:
            rc = self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.p.pid, signal.SIGKILL)
            self.p.wait()
            rc = 'hung'
        dt = time.monotonic() - t0
        self.t.join(5)
        return dt, rc

    def traceback(self):
        return any('Traceback' in x for x in self.lines)


class Peer:
    """In-process rclpy node: ProMP + goals for the adapter, ~/improve for the learner."""

    def __init__(self, domain):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node('bench_shutdown', context=self.ctx)
        self.diag = []
        from diagnostic_msgs.msg import DiagnosticArray
        from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
        self.node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_diag, 100)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self._stop = threading.Event()
        self.th = threading.Thread(target=self._spin, daemon=True)
        self.th.start()

    def _spin(self):
        while not self._stop.is_set():
            try:
                self.ex.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 -- shut down
                return

    def _on_diag(self, msg):
        for st in msg.status:
            self.diag.append({kv.key: kv.value for kv in st.values})

    def wait_diag(self, pred, timeout=60.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if any(pred(v) for v in list(self.diag)):
                return True
            time.sleep(0.02)
        return False

    def close(self):
        self._stop.set()
        self.th.join(5)
        self.ex.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.ctx)


def solving_adapter(peer, proc):
    """Publish a ProMP and goals at 5 Hz until the adapter reports a solve in progress."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from adapter_harness import PANDA_JOINTS, Q_GOAL, reach_promp
    from cdmp_ros.core.primitive_io import dumps_primitive
    from cdmp_ros.ros import qos
    prim = peer.node.create_publisher(String, 'primitive', qos.LATCHED)
    goal = peer.node.create_publisher(JointState, 'goal', qos.COMMAND)
    prim.publish(String(data=dumps_primitive(reach_promp())))
    peer.diag.clear()
    stop = threading.Event()

    def goals():
        k = 0
        while not stop.wait(0.2):
            goal.publish(JointState(name=list(PANDA_JOINTS),
                                    position=[float(x) for x in Q_GOAL + 0.01 * (k % 5)]))
            k += 1
    th = threading.Thread(target=goals, daemon=True)
    th.start()
    ok = peer.wait_diag(lambda v: v.get('solver_busy') == 'True')
    return ok, lambda: (stop.set(), th.join(2), peer.node.destroy_publisher(prim),
                        peer.node.destroy_publisher(goal))


def improving_learner(peer, proc):
    from std_srvs.srv import Trigger
    cli = peer.node.create_client(Trigger, '/learner/improve')
    peer.diag.clear()
    if not cli.wait_for_service(30.0):
        return False, lambda: None
    fut = cli.call_async(Trigger.Request())
    end = time.monotonic() + 30
    while not fut.done() and time.monotonic() < end:
        time.sleep(0.01)

    def running(v):
        r = v.get('improve', '')
        return r.startswith('running') and int(r.split()[1].split('/')[0]) >= 1
    ok = fut.done() and fut.result().success and peer.wait_diag(running)
    return ok, lambda: peer.node.destroy_client(cli)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--reps', type=int, default=5)
    ap.add_argument('--settle', type=float, default=1.0, help='s of work before the signal')
    ap.add_argument('--domain', type=int, default=181)
    ap.add_argument('--nodes', default='learner,adapter,streamer,sim,recorder,player')
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix='bench_shutdown_')
    peer = Peer(a.domain)
    companion = None
    rows = []
    runs = [(n, None) for n in a.nodes.split(',')]
    runs += [('adapter', solving_adapter), ('learner', improving_learner)]
    i = 0
    try:
        for node, prepare in runs:
            if node == 'recorder' and companion is None:  # something to record
                companion = Proc('player', ['--params-file', os.path.join(REPO, 'config',
                                                                          'bag.yaml'),
                                            '-p', f'bag:={BAG}', '-p', 'loop:=true'], a.domain)
            label = node + {solving_adapter: ' (solving)',
                            improving_learner: ' (improving)'}.get(prepare, '')
            for sig in (signal.SIGINT, signal.SIGTERM):
                times, codes, tb = [], [], False
                for _ in range(a.reps):
                    i += 1
                    extra = args_of(node, tmp, i)
                    if prepare is solving_adapter:
                        extra += ['-p', 'adaptation.n_steps:=400',
                                  '-p', 'adaptation.max_outer:=50']
                    if prepare is improving_learner:
                        extra += ['-p', 'improve.updates:=100000']
                    p = Proc(node, extra, a.domain)
                    if not p.ready.wait(60.0):
                        print(f'{label}: not up after 60 s:\n{"".join(p.lines)[-2000:]}')
                        p.stop(signal.SIGKILL)
                        continue
                    cleanup = lambda: None  # noqa: E731
                    if prepare is not None:
                        ok, cleanup = prepare(peer, p)
                        if not ok:
                            print(f'{label}: no evidence of work; signalled anyway')
                    else:
                        time.sleep(a.settle)  # a benchmark: let it work a while
                    dt, rc = p.stop(sig)
                    cleanup()
                    times.append(dt)
                    codes.append(rc)
                    tb = tb or p.traceback()
                    if rc != 0 or p.traceback():
                        print(f'{label} {sig.name}: rc {rc}\n{"".join(p.lines)[-3000:]}')
                rows.append((label, sig.name, times, codes, tb))
                print(f'{label:20s} {sig.name:8s} median {statistics.median(times):.3f} s  '
                      f'max {max(times):.3f} s  exit codes {sorted(set(map(str, codes)))}  '
                      f'traceback {"yes" if tb else "no"}', flush=True)
    finally:
        if companion is not None:
            companion.stop(signal.SIGINT)
        peer.close()
    worst = max(max(r[2]) for r in rows)
    bad = [r for r in rows if max(r[2]) >= TARGET_S or set(r[3]) != {0} or r[4]]
    print(f'\nworst signal-to-exit {worst:.3f} s over {sum(len(r[2]) for r in rows)} runs; '
          f'target < {TARGET_S} s, exit 0, no traceback: '
          f'{"met" if not bad else "NOT met for " + ", ".join(r[0] + " " + r[1] for r in bad)}')
    os.system('uptime')
    return 0 if not bad else 1


if __name__ == '__main__':
    sys.exit(main())
