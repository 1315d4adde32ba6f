#!/usr/bin/env python3
"""Two machines, simulated: the sim on a "robot PC", streamer, adapter and learner on a
"workstation", each in a network namespace of its own joined by a veth pair.

    sudo .venv/bin/python scripts/two_machines.py [--reps 20] [--domain 88] [--layout split]

What it does (root only, as CI is):

1. Makes two network namespaces, ``cdmp_robot_<pid>`` and ``cdmp_ws_<pid>``, and one veth
   pair whose ends are created directly inside them (10.213.213.1/30 on the robot side,
   .2/30 on the workstation side, a multicast route on each end). Nothing of it exists in the
   host's namespace, and before any ROS process starts it checks that each namespace has
   exactly two interfaces, ``lo`` and its veth end: DDS discovery (multicast included) can then
   reach the other namespace and nothing else. It never touches a host interface.
2. Starts the sim (``config/sim.yaml``) and a probe in the robot namespace, and the streamer,
   adapter and learner (``config/*.yaml``) in the workstation namespace, every process with
   ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (the setting of docs/nodes.md, several machines),
   the private ``--domain`` and ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` (no shared-memory
   shortcut: every sample crosses the veth as it would cross a network).
3. The probe waits until references reach the sim, then:
   - **avoidance**: with the reference at rest it drops a sphere (radius 2 cm) 12 cm beside the
     tool centre point, waits until the sim has simulated 1 s more with it and the reference
     moved the tool 5 mm away from the sphere (each wait bounded by 30 s: on a loaded machine
     the probe takes the references late), and checks both and that the sim reported no
     contact;
   - **latency**: ``--reps`` times, with the reference at rest, a sphere 10 cm from the tool
     centre point; the time from the probe's publish to the first ``joint_reference`` it
     receives that leaves the rest position by more than 1e-6 rad (obstacle -> first changed
     reference at the robot: two crossings of the veth, robot PC -> workstation -> robot PC).
4. Stops every process, deletes both namespaces (also on an error or SIGTERM) and prints one
   JSON line with the figures; exit status 0 only if references flowed, the obstacle was
   avoided and every repetition measured a latency.

``--layout single`` runs every process in one namespace (same transports and discovery
range): the same figures without the veth, for comparison.
"""
import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROBOT_ADDR, WS_ADDR, PREFIX = '10.213.213.1', '10.213.213.2', 30
WORKSTATION_NODES = ('streamer', 'adapter', 'learner')
STARTUP_S = 120.0   # bounds a failing start only (five interpreters on a loaded 2-core machine)
WAIT_S = 30.0       # bounds any other failing wait


def _read(path: str) -> str:
    with open(path, errors='replace') as f:
        return f.read()


# -- namespaces ------------------------------------------------------------------------------
def ip(*args: str) -> str:
    out = subprocess.run(['ip', *args], capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f'ip {" ".join(args)}: {out.stderr.strip()}')
    return out.stdout


class Namespaces:
    """The two namespaces and the veth pair; :meth:`remove` deletes them (idempotent)."""

    def __init__(self, tag: str, single: bool):
        self.robot, self.ws = f'cdmp_robot_{tag}', f'cdmp_ws_{tag}'
        self.veth = (f'cr{tag}'[:15], f'cw{tag}'[:15])
        self.single = single
        self.created = []

    def create(self):
        for ns in (self.robot,) if self.single else (self.robot, self.ws):
            ip('netns', 'add', ns)
            self.created.append(ns)
            ip('-n', ns, 'link', 'set', 'lo', 'up')
        if self.single:
            return
        ip('link', 'add', self.veth[0], 'netns', self.robot, 'type', 'veth',
           'peer', 'name', self.veth[1], 'netns', self.ws)
        for ns, dev, addr in ((self.robot, self.veth[0], ROBOT_ADDR),
                              (self.ws, self.veth[1], WS_ADDR)):
            ip('-n', ns, 'addr', 'add', f'{addr}/{PREFIX}', 'dev', dev)
            ip('-n', ns, 'link', 'set', dev, 'up', 'multicast', 'on')
            ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)

    def check_isolated(self):
        """Each namespace has exactly ``lo`` and its veth end (nothing reaches the host)."""
        for ns, dev in ((self.robot, self.veth[0]), (self.ws, self.veth[1])):
            if ns not in self.created:
                continue
            names = sorted(line.split(':')[1].strip().split('@')[0]
                           for line in ip('-n', ns, '-o', 'link').splitlines())
            want = ['lo'] if self.single else sorted(['lo', dev])
            if names != want:
                raise RuntimeError(f'namespace {ns}: interfaces {names}, expected {want}')

    @property
    def workstation(self) -> str:
        return self.robot if self.single else self.ws

    def remove(self):
        while self.created:
            ns = self.created.pop()
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True)


def ros_env(domain: int) -> dict:
    e = dict(os.environ)
    e.pop('ROS_LOCALHOST_ONLY', None)
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'   # inside namespaces that reach nothing else
    e['ROS_DOMAIN_ID'] = str(domain)
    e['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    e['PYTHONPATH'] = REPO + os.pathsep + e.get('PYTHONPATH', '')
    return e


def start_in(ns: str, argv, domain: int, log):
    return subprocess.Popen(['ip', 'netns', 'exec', ns, *argv], env=ros_env(domain), cwd=REPO,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def node_argv(name: str):
    return [sys.executable, '-m', f'cdmp_ros.nodes.{name}', '--ros-args', '--params-file',
            os.path.join(REPO, 'config', f'{name}.yaml')]


def stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    end = time.monotonic() + 20.0
    for p in procs:
        try:
            p.wait(max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(5)


# -- the probe (runs inside the robot namespace) ---------------------------------------------
def probe(reps: int) -> dict:
    import numpy as np
    import pybullet_data
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.experimental import EventsExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import Marker, MarkerArray

    from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
    from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
    from cdmp_ros.ros import qos

    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))
    tcp = [PointOfInterest('ee')]
    rclpy.init()
    node = rclpy.create_node('two_machines_probe')
    obs_pub = node.create_publisher(MarkerArray, 'obstacles', qos.COMMAND)
    clock = node.get_clock()
    last = {'n': 0}
    sim = {}

    def on_ref(msg):
        last['t'] = clock.now().nanoseconds
        last['y'] = np.array(msg.position)
        last['yd'] = np.array(msg.velocity)
        last['names'] = list(msg.name)
        last['n'] += 1
        watch = last.get('watch')
        if watch is not None and 'hit' not in last and np.abs(last['y'] - watch).max() > 1e-6:
            last['hit'] = last['t']

    def on_diag(msg):
        for st in msg.status:
            if st.name.startswith('sim') and st.name.endswith(': state'):
                sim.clear()
                sim.update({v.key: v.value for v in st.values})

    node.create_subscription(JointState, 'joint_reference', on_ref,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diag, 50)
    ex = EventsExecutor()
    ex.add_node(node)

    def spin_until(pred, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not pred():
            ex.spin_once(timeout_sec=0.01)
        return bool(pred())

    def rested():
        return 'yd' in last and np.abs(last['yd']).max() < 1e-9

    def sphere(center, radius, ident):
        m = Marker(ns='two_machines', id=ident, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = 'panda_link0'
        m.pose.position.x, m.pose.position.y, m.pose.position.z = [float(c) for c in center]
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 2.0 * radius
        t = clock.now().nanoseconds
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 1_000_000_000)
        obs_pub.publish(MarkerArray(markers=[m]))
        return t

    def clear():
        obs_pub.publish(MarkerArray(markers=[Marker(ns='two_machines', action=Marker.DELETEALL)]))

    out = {'references': 0}
    # 1. references reach the robot PC, and the sim reports on /diagnostics
    flowing = spin_until(lambda: last['n'] >= 100 and 'joint_states_published' in sim
                         and obs_pub.get_subscription_count() >= 3, STARTUP_S)
    out.update(references=last['n'], joint_names=last.get('names'),
               obstacle_subscribers=obs_pub.get_subscription_count())
    if not flowing:
        out['error'] = 'no references at the robot PC (or no sim diagnostics)'
        return out
    # 2. avoidance: a sphere 12 cm beside the tool, 1 s of simulated time with it
    if not spin_until(rested, WAIT_S):
        out['error'] = 'the reference did not come to rest'
        return out
    y0 = last['y'].copy()
    ee0 = chain.forward(y0, tcp)[0]
    centre = ee0 + np.array([0.0, 0.12, 0.0])
    contacts0 = int(sim.get('contacts_since_start', 0))
    sphere(centre, 0.02, 1)
    seen = spin_until(lambda: sim.get('obstacles') == '1', WAIT_S)
    js0 = int(sim.get('joint_states_published', 0))
    # 1 s of simulated time with the sphere, and the reference moved the tool away (waited
    # for: on a loaded machine this process takes the references late, up to its queue)
    spin_until(lambda: int(sim.get('joint_states_published', 0)) >= js0 + 250, WAIT_S)
    spin_until(lambda: float(np.linalg.norm(chain.forward(last['y'], tcp)[0] - centre))
               > float(np.linalg.norm(ee0 - centre)) + 0.005, WAIT_S)
    ee1 = chain.forward(last['y'], tcp)[0]
    out['avoidance'] = {
        'sim_saw_sphere': seen,
        'tcp_to_sphere_before_m': round(float(np.linalg.norm(ee0 - centre)), 4),
        'tcp_to_sphere_after_m': round(float(np.linalg.norm(ee1 - centre)), 4),
        'contacts': int(sim.get('contacts_since_start', 0)) - contacts0,
        'min_obstacle_distance_m': float(sim.get('min_obstacle_distance_m', 'nan')),
        'simulated_joint_states_with_sphere': int(sim.get('joint_states_published', 0)) - js0}
    clear()
    spin_until(lambda: sim.get('obstacles') == '0', WAIT_S)
    # 3. obstacle -> first changed reference, at rest each time
    lat = []
    for i in range(reps):
        if not spin_until(rested, WAIT_S):
            break
        y0 = last['y'].copy()
        ee = chain.forward(y0, tcp)[0]
        last.pop('hit', None)
        last['watch'] = y0
        t_pub = sphere(ee + [0.1, 0.0, 0.0], 0.02, 2)
        if spin_until(lambda: 'hit' in last, 5.0):
            lat.append((last['hit'] - t_pub) * 1e-6)
        last['watch'] = None
        clear()
    lat.sort()
    out['latency_ms'] = {
        'n': len(lat), 'reps': reps,
        'p50': round(lat[len(lat) // 2], 3) if lat else None,
        'p95': round(lat[int(0.95 * (len(lat) - 1))], 3) if lat else None,
        'max': round(lat[-1], 3) if lat else None,
        'all': [round(x, 3) for x in lat]}
    node.destroy_node()
    rclpy.try_shutdown()
    return out


def verdict(out: dict) -> list:
    """What failed (empty: references flowed, the sphere was avoided, every rep measured)."""
    bad = []
    names = [f'panda_joint{i}' for i in range(1, 8)]
    if out.get('references', 0) < 100 or out.get('joint_names') != names:
        bad.append(f"references at the robot PC: {out.get('references')} with names "
                   f"{out.get('joint_names')}")
    av = out.get('avoidance')
    if not av:
        bad.append('avoidance not measured')
    else:
        if not av['sim_saw_sphere'] or av['simulated_joint_states_with_sphere'] < 250:
            bad.append(f'the sim did not simulate 1 s with the sphere: {av}')
        if av['contacts'] != 0 or not av['min_obstacle_distance_m'] > 0.0:
            bad.append(f'contact with the sphere: {av}')
        if not av['tcp_to_sphere_after_m'] > av['tcp_to_sphere_before_m'] + 0.005:
            bad.append(f'the reference did not move the tool away from the sphere: {av}')
    lat = out.get('latency_ms') or {}
    if lat.get('n') != lat.get('reps'):
        bad.append(f"latency measured in {lat.get('n')} of {lat.get('reps')} repetitions")
    if out.get('error'):
        bad.append(out['error'])
    return bad


# -- main ------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog='Needs root (ip netns). See the module docstring.')
    ap.add_argument('--reps', type=int, default=20,
                    help='repetitions of the obstacle -> reference latency (default 20)')
    ap.add_argument('--domain', type=int, default=88, help='private ROS_DOMAIN_ID (0-232)')
    ap.add_argument('--layout', choices=('split', 'single'), default='split',
                    help='split: sim and probe in one namespace, the other nodes in the other '
                         '(default); single: everything in one namespace (comparison)')
    ap.add_argument('--log-dir', default=None,
                    help='write each process log there (default: a temporary directory, '
                         'removed on success)')
    ap.add_argument('--probe', type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.probe is not None:
        print(json.dumps(probe(args.probe)), flush=True)
        return 0
    if not 1 <= args.reps <= 1000:
        ap.error(f'--reps: expected 1-1000, got {args.reps}')
    if not 0 <= args.domain <= 232:
        ap.error(f'--domain: expected 0-232, got {args.domain}')
    if os.geteuid() != 0:
        print('two_machines.py: needs root (network namespaces)', file=sys.stderr)
        return 2
    if shutil.which('ip') is None:
        print('two_machines.py: needs the ip command (iproute2)', file=sys.stderr)
        return 2
    import tempfile
    log_dir = args.log_dir or tempfile.mkdtemp(prefix='two_machines_')
    os.makedirs(log_dir, exist_ok=True)
    nss = Namespaces(str(os.getpid()), args.layout == 'single')
    procs, logs = [], []
    out = {}

    def on_term(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, on_term)
    try:
        nss.create()
        nss.check_isolated()
        for ns, name, argv in (
                [(nss.robot, 'sim', node_argv('sim'))]
                + [(nss.workstation, n, node_argv(n)) for n in WORKSTATION_NODES]):
            logs.append(open(os.path.join(log_dir, f'{name}.log'), 'w'))
            procs.append(start_in(ns, argv, args.domain, logs[-1]))
        logs.append(open(os.path.join(log_dir, 'probe.log'), 'w'))
        probe_proc = subprocess.Popen(
            ['ip', 'netns', 'exec', nss.robot, sys.executable, os.path.abspath(__file__),
             '--probe', str(args.reps)], env=ros_env(args.domain), cwd=REPO,
            stdout=subprocess.PIPE, stderr=logs[-1], text=True, start_new_session=True)
        procs.append(probe_proc)
        line = probe_proc.stdout.readline()
        probe_proc.wait(WAIT_S)
        out = json.loads(line) if line.strip() else {'error': 'the probe printed nothing'}
        out['alive_at_end'] = {name: p.poll() is None
                               for name, p in zip(('sim',) + WORKSTATION_NODES, procs)}
    finally:
        stop(procs)
        for f in logs:
            f.close()
        nss.remove()
    left = [ns for ns in (nss.robot, nss.ws) if ns in ip('netns', 'list')]
    from cdmp_ros.common.node_signals import teardown_hang
    names = ('sim',) + WORKSTATION_NODES + ('probe',)
    codes = {name: p.returncode for name, p in zip(names, procs)}
    out.update(layout=args.layout, domain=args.domain, namespaces_left=left, exit_codes=codes,
               teardown_hangs=[n for n, c in codes.items() if c != 0 and teardown_hang(
                   c, _read(os.path.join(log_dir, f'{n}.log')))])
    bad = verdict(out) + ([f'namespaces left: {left}'] if left else [])
    if not all(out.get('alive_at_end', {'all': False}).values()):
        bad.append(f"a node ended early: {out.get('alive_at_end')}")
    out['failures'] = bad
    out['log_dir'] = log_dir
    print(json.dumps(out), flush=True)
    if not bad and not args.log_dir:
        shutil.rmtree(log_dir, ignore_errors=True)
    return 0 if not bad else 1


if __name__ == '__main__':
    sys.exit(main())
