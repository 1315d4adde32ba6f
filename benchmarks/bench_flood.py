"""Flood benchmark (issue 10): bad and oversize input must not take a node off real time.

Starts sim, streamer, adapter and learner from their parameter files (config/*.yaml) as
processes, then for ``--duration`` seconds a bounded, loopback-only flood publisher sends, at
random intervals (exponential, mean ``1 / --rate``; seeded rng), malformed input drawn at
random from these categories:

- ``goal`` / ``joint_states`` / ``demonstration`` (sensor_msgs/JointState): NaN, missing or
  duplicate joints, lengths that do not match, 10,000 names, stamps 100 s in the future;
- ``constraints`` / ``primitive`` (std_msgs/String): not JSON, schema violations, 5 MB payloads;
- ``goal_point`` (geometry_msgs/PointStamped): NaN, wrong frame, future stamp;
- ``obstacles`` (visualization_msgs/MarkerArray): 1 to 5,000 markers with bad frames, types,
  actions, scales and poses.

- ``joint_reference`` (sensor_msgs/JointState, to the sim): NaN, missing, duplicate or
  unknown joints, lengths that do not match, 10,000 names.

Every message is serialized once at start (a pool per category) and published as bytes, so
the publisher itself stays cheap. Beside the flood, valid input arrives as a user's would:

- a valid ``goal`` alternates between two poses every ``--goal-period`` s so that the robot
  keeps moving (tracking error is measured while it moves);
- ``--valid-obstacles`` Hz (default 20) of valid ``obstacles``: one or two spheres (radius 2-5 cm)
  placed 15-30 cm from the measured tool centre point in a random direction and at least 15 cm
  from the polyline of the arm's link origins, jumping at every message, and a DELETEALL every
  tenth message;
- ``--valid-goal-points`` Hz (default 0.5) of valid ``goal_point``: the tool centre point of a
  random configuration inside the limits (reachable, so the adapter solves an IK and adapts).

Valid references are not injected: the sim's valid ``joint_reference`` come from the streamer
at its rate, and a second valid publisher would make two controllers fight over one robot.

Printed: sim slipped physics steps, joint-limit violations of the simulated robot
(measured ``joint_states`` against the URDF limits: samples outside, largest usage
|q - centre| / half range), the sim's own limit violations and tracking error, streamer ticks
on time (``late_ticks``: a slot published after the next slot's deadline; ``missed_ticks``:
slots skipped), whether every node is alive at the end, and messages sent per category
against the rejections each node counted on that topic.

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_flood.py [--duration 60] [--rate 200] [--seed 0]
        [--domain 70] [--code DIR]    # DIR: run the nodes from another checkout (before/after)
        [--param NODE:NAME:=VALUE ...]  # e.g. streamer:realtime_priority:=0 (default scheduling)
        [--valid-obstacles 20] [--valid-goal-points 0.5]
        [--probe]   # also tick benchmarks/tick_probe.py (a bare 500 Hz publisher in a
                    # process of its own) over the flood: the on-time ceiling of the load
"""
import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

NODES = ('sim', 'streamer', 'adapter', 'learner')
JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
GOALS = (np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7]),
         np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3]))
STARTUP = 90.0


def ros_env(domain, code):
    e = dict(os.environ)
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    e['ROS_DOMAIN_ID'] = str(domain)
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    e['PYTHONPATH'] = code
    return e


def start_nodes(domain, code, logdir, params=None, nice=None):
    """sim, streamer, adapter and learner from ``code``'s config/*.yaml; ``params``: more
    ``-p`` parameters per node (``{'streamer': {'rate': 1000.0}}``); ``nice``: node -> nice
    increment of its process (``nice -n``)."""
    procs = {}
    for name in NODES:
        cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{name}', '--ros-args', '--params-file',
               os.path.join(code, 'config', f'{name}.yaml')]
        if (nice or {}).get(name):
            cmd = ['nice', '-n', str(int(nice[name]))] + cmd
        for k, v in (params or {}).get(name, {}).items():
            cmd += ['-p', f'{k}:={v}']
        log = open(os.path.join(logdir, f'{name}.log'), 'w')
        procs[name] = subprocess.Popen(cmd, env=ros_env(domain, code), cwd=code, stdout=log,
                                       stderr=subprocess.STDOUT, start_new_session=True)
    return procs


def stop_nodes(procs):
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs.values():
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(5)


# -- the flood ---------------------------------------------------------------------------------
def _stamp(msg, offset_s=0.0):
    t = time.time_ns() + int(offset_s * 1e9)
    msg.header.stamp.sec, msg.header.stamp.nanosec = t // 1_000_000_000, t % 1_000_000_000


def bad_joint_states(rng, n=12):
    from sensor_msgs.msg import JointState
    out = []
    for k in range(n):
        m = JointState()
        m.header.frame_id = 'flood'  # told apart from the sim's joint_states by the observer
        m.name = list(JOINTS)
        m.position = [0.1] * 7
        kind = k % 6
        if kind == 0:
            m.position[int(rng.integers(7))] = float('nan')
        elif kind == 1:
            m.name, m.position = m.name[:5], m.position[:5]            # missing joints
        elif kind == 2:
            m.name[1] = m.name[0]                                       # duplicate
        elif kind == 3:
            m.position = m.position[:3]                                 # lengths differ
        elif kind == 4:
            m.name = [f'j{i}' for i in range(10000)]                    # 10,000 names
            m.position = [0.0] * 10000
        else:
            _stamp(m, 100.0)                                            # future stamp
        out.append(m)
    return out


def bad_references(rng):
    """Malformed joint_reference messages for the sim (never a valid one: see the docstring)."""
    out = []
    for m in bad_joint_states(rng):
        if len(m.name) == 7 and len(m.position) == 7 and m.header.stamp.sec == 0:
            m.name[6] = 'panda_joint99'  # an unknown joint: nothing here is a valid reference
        out.append(m)
    return out


def bad_json(rng, kind):
    from std_msgs.msg import String
    texts = ['{not json', '[1, 2, 3]', json.dumps({'kind': 'cdmp', 'joint_names': 7}),
             '{"a": ' * 5000 + '1' + '}' * 5000]
    if kind == 'constraints':
        texts.append(json.dumps({'constraints': [{'type': 'sphere', 'radius': -1}]}))
    texts = texts * 2 + [json.dumps({'constraints': 'x' * 5_000_000})]  # 5 MB, 1 in 9-11
    return [String(data=t) for t in texts]


def bad_points(rng):
    from geometry_msgs.msg import PointStamped
    out = []
    for kind in range(3):
        m = PointStamped()
        m.header.frame_id = 'panda_link0'
        m.point.x, m.point.y, m.point.z = 0.5, 0.0, 0.5
        if kind == 0:
            m.point.y = float('nan')
        elif kind == 1:
            m.header.frame_id = 'world_of_nowhere'
        else:
            _stamp(m, 100.0)
        out.append(m)
    return out


def bad_markers(rng, sizes=(1, 3, 10, 65, 300, 1000, 5000)):
    from visualization_msgs.msg import Marker, MarkerArray
    out = []
    for n in sizes:
        arr = MarkerArray()
        for i in range(n):
            m = Marker(ns='flood', id=i, type=Marker.SPHERE, action=Marker.ADD)
            m.header.frame_id = 'panda_link0'
            m.pose.orientation.w = 1.0
            m.pose.position.x = 0.6
            m.scale.x = m.scale.y = m.scale.z = 0.1
            kind = int(rng.integers(6))
            if kind == 0:
                m.header.frame_id = 'elsewhere'
            elif kind == 1:
                m.type = Marker.TEXT_VIEW_FACING
            elif kind == 2:
                m.action = 7
            elif kind == 3:
                m.scale.x = float(rng.choice([-1.0, 0.0, float('inf'), 1e6]))
            elif kind == 4:
                m.pose.position.y = float(rng.choice([float('nan'), 1e9]))
            else:
                m.action, m.id = Marker.DELETE, 100000 + i                # unknown obstacle
            arr.markers.append(m)
        out.append(arr)
    return out


def build_pool(rng):
    """category -> (topic, msg type, list of serialized messages)."""
    from geometry_msgs.msg import PointStamped
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from visualization_msgs.msg import MarkerArray
    pool = {
        'goal': ('goal', JointState, bad_joint_states(rng)),
        'joint_states': ('joint_states', JointState, bad_joint_states(rng)),
        'demonstration': ('demonstration', JointState, bad_joint_states(rng)),
        'constraints': ('constraints', String, bad_json(rng, 'constraints')),
        'primitive': ('primitive', String, bad_json(rng, 'primitive')),
        'goal_point': ('goal_point', PointStamped, bad_points(rng)),
        'obstacles': ('obstacles', MarkerArray, bad_markers(rng)),
        'joint_reference': ('joint_reference', JointState, bad_references(rng)),
    }
    return {k: (t, cls, [serialize_message(m) for m in msgs])
            for k, (t, cls, msgs) in pool.items()}


def polyline_distance(c, P):
    """Distance [m] from the point ``c`` to the polyline through the rows of ``P``."""
    A, B = P[:-1], P[1:]
    AB = B - A
    t = np.clip(np.einsum('ij,ij->i', c - A, AB) / np.maximum(np.einsum('ij,ij->i', AB, AB),
                                                              1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(A + t[:, None] * AB - c, axis=1)))


class Observer:
    """Diagnostics of every node and the measured joint_states."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        self.lock = threading.Lock()
        self.status = {}   # name -> {key: value}
        self.q = []        # measured positions (7,)
        node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._diag, 200)
        node.create_subscription(JointState, 'joint_states', self._js,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))

    def _diag(self, msg):
        with self.lock:
            for s in msg.status:
                kv = {x.key: x.value for x in s.values}
                kv['_message'] = s.message
                self.status[s.name] = kv

    def _js(self, msg):
        if (msg.header.frame_id != 'flood' and len(msg.position) >= 7
                and list(msg.name[:7]) == list(JOINTS)):
            with self.lock:
                self.q.append(np.array(msg.position[:7]))

    def get(self, name, key, default=None):
        with self.lock:
            return self.status.get(name, {}).get(key, default)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--duration', type=float, default=60.0)
    ap.add_argument('--rate', type=float, default=200.0, help='flood messages/s (mean)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--domain', type=int, default=int(os.environ.get('ROS_DOMAIN_ID', 70)))
    ap.add_argument('--goal-period', type=float, default=3.0)
    ap.add_argument('--code', default=REPO, help='checkout the nodes run from')
    ap.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                    help='a -p parameter of one node, e.g. streamer:realtime_priority:=0 '
                         '(repeatable)')
    ap.add_argument('--nice', action='append', default=[], metavar='NODE:N',
                    help="start NODE's process with nice -n N (repeatable; 'bench' for the "
                         'flood publisher itself)')
    ap.add_argument('--categories', default='',
                    help='comma-separated categories of bad messages to send (default: all)')
    ap.add_argument('--probe', action='store_true',
                    help='also run benchmarks/tick_probe.py (the streamer schedule in a process '
                         'of its own, subscribing to nothing) during the flood')
    ap.add_argument('--valid-obstacles', type=float, default=20.0,
                    help='Hz of valid sphere obstacles near the arm (0: none)')
    ap.add_argument('--valid-goal-points', type=float, default=0.5,
                    help='Hz of valid (reachable) goal_point messages (0: none)')
    args = ap.parse_args()
    params = {}
    for text in args.param:
        node_name, sep, assignment = text.partition(':')
        if node_name not in NODES or not sep or ':=' not in assignment:
            ap.error(f'--param: expected NODE:NAME:=VALUE with NODE one of {NODES}, got {text!r}')
        key, value = assignment.split(':=', 1)
        params.setdefault(node_name, {})[key] = value
    nice = {}
    for text in args.nice:
        node_name, _, n = text.partition(':')
        if node_name not in NODES + ('bench',) or not n.lstrip('-').isdigit():
            ap.error(f'--nice: expected NODE:N with NODE one of {NODES + ("bench",)}, '
                     f'got {text!r}')
        nice[node_name] = int(n)
    if nice.get('bench'):
        os.nice(nice['bench'])
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ['ROS_DOMAIN_ID'] = str(args.domain)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import Marker, MarkerArray

    from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
    from cdmp_ros.ros import qos
    from cdmp_ros.ros.robot_model import default_urdf_path
    chain = panda_chain(default_urdf_path())
    lower, upper = chain.lower, chain.upper

    rng = np.random.default_rng(args.seed)
    pool = build_pool(rng)
    if args.categories:
        wanted = args.categories.split(',')
        unknown = sorted(set(wanted) - set(pool))
        if unknown:
            ap.error(f'--categories: unknown {unknown}; known: {sorted(pool)}')
        pool = {k: v for k, v in pool.items() if k in wanted}
    logdir = tempfile.mkdtemp(prefix='bench_flood_')
    procs = start_nodes(args.domain, os.path.abspath(args.code), logdir, params, nice)
    rclpy.init(domain_id=args.domain)
    node = rclpy.create_node('flood')
    obs = Observer(node)
    topic_qos = {'primitive': qos.LATCHED, 'joint_states': qos.COMMAND,
                 'demonstration': qos.COMMAND}
    pubs = {t: node.create_publisher(cls, t, topic_qos.get(t, qos.COMMAND))
            for t, cls, _ in pool.values()}
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.05)
                                               for _ in iter(stop.is_set, True)], daemon=True)
    spinner.start()
    sent = {k: 0 for k in pool}
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < STARTUP and not all(
                obs.get(f'{n}: state', '_message') for n in NODES):
            time.sleep(0.2)
        missing = [n for n in NODES if not obs.get(f'{n}: state', '_message')]
        if missing:
            raise SystemExit(f'no diagnostics from {missing}; logs in {logdir}')
        # the learner's primitive is streamed; wait until the streamer runs it
        t0 = time.monotonic()
        while (time.monotonic() - t0 < 30
               and obs.get('streamer: state', 'primitive', 'none') == 'none'):
            time.sleep(0.2)
        time.sleep(2.0)  # let the first movement start before the baseline
        base = {n: {k: obs.get(f'{n}: state', k, '0') for k in
                    ('slipped_steps', 'missed_ticks', 'late_ticks', 'ticks', 'limit_violations',
                     'contacts_since_start')}
                for n in ('sim', 'streamer')}
        with obs.lock:
            n_q0 = len(obs.q)
        print(f'nodes up; flooding {args.duration:g} s at ~{args.rate:g} msg/s '
              f'(seed {args.seed}, domain {args.domain}, code {args.code})', flush=True)
        cats = list(pool)
        goal_pub = node.create_publisher(JointState, 'goal', qos.COMMAND)
        obstacle_pub = node.create_publisher(MarkerArray, 'obstacles', qos.COMMAND)
        point_pub = node.create_publisher(PointStamped, 'goal_point', qos.COMMAND)
        tcp = [PointOfInterest('ee')]
        arm = [PointOfInterest(f'panda_link{i}') for i in range(1, 8)] + [
            PointOfInterest('panda_hand'), PointOfInterest('ee')]
        valid = {'goal': 0, 'obstacles': 0, 'goal_point': 0}
        import psutil
        ps = {n: psutil.Process(procs[n].pid) for n in NODES}
        ps['bench (publisher)'] = psutil.Process()
        probe = None
        if args.probe:  # inside the flood's window: ~2 s to start, 5 s shorter than the flood
            probe = subprocess.Popen(
                [sys.executable, os.path.join(REPO, 'benchmarks', 'tick_probe.py'),
                 '--duration', str(max(1.0, args.duration - 5.0))],
                env=ros_env(args.domain, REPO),
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            ps['probe'] = psutil.Process(probe.pid)
        cpu0 = {n: p.cpu_times() for n, p in ps.items()}
        t_start = time.monotonic()
        next_goal, g = t_start, 0
        inf = float('inf')
        next_obstacle = t_start if args.valid_obstacles > 0 else inf
        next_point = t_start + 1.0 if args.valid_goal_points > 0 else inf
        deadline = t_start + args.duration
        t_next = t_start
        while True:
            now = time.monotonic()
            if now >= deadline:
                break
            if now >= next_goal:
                gm = JointState(name=list(JOINTS), position=[float(v) for v in GOALS[g % 2]])
                goal_pub.publish(gm)
                g += 1
                valid['goal'] += 1
                next_goal += args.goal_period
            if now >= next_obstacle:
                arr = MarkerArray()
                if valid['obstacles'] % 10 == 9:
                    arr.markers.append(Marker(ns='valid', action=Marker.DELETEALL))
                else:
                    with obs.lock:
                        q = obs.q[-1] if obs.q else GOALS[0]
                    P = chain.forward(q, arm)
                    x = P[-1]
                    for i in range(int(rng.integers(1, 3))):
                        for _ in range(50):  # clear of the whole arm, not only the tool
                            d = rng.normal(size=3)
                            c = x + d / np.linalg.norm(d) * rng.uniform(0.15, 0.30)
                            if polyline_distance(c, P) >= 0.15:
                                break
                        m = Marker(ns='valid', id=i, type=Marker.SPHERE, action=Marker.ADD)
                        m.header.frame_id = 'panda_link0'
                        _stamp(m)
                        m.pose.position.x, m.pose.position.y, m.pose.position.z = (
                            float(v) for v in c)
                        m.pose.orientation.w = 1.0
                        m.scale.x = m.scale.y = m.scale.z = 2.0 * float(rng.uniform(0.02, 0.05))
                        arr.markers.append(m)
                obstacle_pub.publish(arr)
                valid['obstacles'] += 1
                next_obstacle += 1.0 / args.valid_obstacles
            if now >= next_point:
                q = lower + (upper - lower) * rng.uniform(0.2, 0.8, size=7)
                x = chain.forward(q, tcp)[0]
                pm = PointStamped()
                pm.header.frame_id = 'panda_link0'
                _stamp(pm)
                pm.point.x, pm.point.y, pm.point.z = (float(v) for v in x)
                point_pub.publish(pm)
                valid['goal_point'] += 1
                next_point += 1.0 / args.valid_goal_points
            if now >= t_next:
                cat = cats[int(rng.integers(len(cats)))]
                topic, _, msgs = pool[cat]
                pubs[topic].publish(msgs[int(rng.integers(len(msgs)))])
                sent[cat] += 1
                t_next = now + rng.exponential(1.0 / args.rate)
            time.sleep(max(0.0, min(t_next, next_goal, next_obstacle, next_point, deadline)
                           - time.monotonic()))
        cpu = {n: (p.cpu_times().user + p.cpu_times().system - cpu0[n].user - cpu0[n].system)
               / (time.monotonic() - t_start) * 100 for n, p in ps.items()}
        time.sleep(3.0)  # the last rejections and diagnostics arrive
        alive = {n: procs[n].poll() is None for n in NODES}
        probe_out = probe.communicate(timeout=60)[0].strip() if probe else ''
    finally:
        stop.set()
        spinner.join(timeout=5)
        stop_nodes(procs)

    def num(n, k, default='0'):
        return float(obs.get(f'{n}: state', k, default) or 0)
    with obs.lock:
        Q = np.array(obs.q[n_q0:]) if len(obs.q) > n_q0 else np.zeros((0, 7))
    centre, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
    usage = np.abs(Q - centre) / half if len(Q) else np.zeros((0, 7))
    outside = int(np.sum(np.any((Q < lower) | (Q > upper), axis=1))) if len(Q) else 0
    slipped = num('sim', 'slipped_steps') - float(base['sim']['slipped_steps'])
    ticks = num('streamer', 'ticks') - float(base['streamer']['ticks'])
    missed = num('streamer', 'missed_ticks') - float(base['streamer']['missed_ticks'])
    late = num('streamer', 'late_ticks') - float(base['streamer']['late_ticks'])
    slots = ticks + missed
    on_time = (ticks - late) / slots if slots else float('nan')
    print(f'\n== flood {args.duration:g} s, {sum(sent.values())} bad messages, valid: '
          f"{valid['goal']} goals, {valid['obstacles']} obstacle sets, "
          f"{valid['goal_point']} goal points; parameters {params or 'config/*.yaml'}; "
          f"nice {nice or 'none'}; "
          f'logs {logdir}')
    print(f'sim slipped physics steps      {slipped:.0f}')
    print(f'joint_states samples           {len(Q)}; outside the URDF limits: {outside}; '
          f'largest limit usage {usage.max() if len(Q) else float("nan"):.4f}')
    print(f'sim limit_violations (steps)   '
          f'{num("sim", "limit_violations") - float(base["sim"]["limit_violations"]):.0f}; '
          f'max_limit_usage_since_start {obs.get("sim: state", "max_limit_usage_since_start")}')
    print(f'sim tracking error max         {obs.get("sim: state", "tracking_error_max_rad")} rad')
    print(f'sim contacts                   '
          f'{num("sim", "contacts_since_start") - float(base["sim"]["contacts_since_start"]):.0f}'
          f'; reflex_errors {obs.get("sim: state", "reflex_errors")}')
    print(f'streamer slots                 {slots:.0f} at {obs.get("streamer: state", "rate_hz")}'
          f' Hz: on time {on_time * 100:.3f} % (late {late:.0f}, missed {missed:.0f}); '
          f'tick_wake_late p99 / max '
          f'{obs.get("streamer: timing", "tick_wake_late_p99_ms")} / '
          f'{obs.get("streamer: timing", "tick_wake_late_max_ms")} ms')
    if args.probe:
        print(f'tick probe (own process)       {probe_out.splitlines()[-1] if probe_out else "-"}')
    print(f'alive at the end               {alive}')
    timing = {k: v for k, v in obs.status.get('streamer: timing', {}).items()
              if k.endswith(('_p99_ms', '_max_ms'))}
    print(f'streamer timing                {timing}')
    print('CPU during the flood [% of one core]  '
          + ', '.join(f'{n} {c:.0f}' for n, c in cpu.items()))
    print('\ncategory        sent   per node: received by the gate / rejections counted on the '
          'topic (of which flooding)')
    subscribers = {'goal': ('streamer', 'adapter'), 'joint_states': ('streamer', 'adapter'),
                   'demonstration': ('learner',), 'constraints': ('adapter',),
                   'primitive': ('streamer', 'adapter'), 'goal_point': ('adapter',),
                   'obstacles': ('sim', 'streamer', 'adapter'),
                   'joint_reference': ('sim',)}
    all_counted = True
    for cat, n in sent.items():
        cells = []
        for node_name in subscribers[cat]:
            kv = obs.status.get(f'{node_name}: input {cat}', {})
            total = int(kv.get('rejected_total', 0))
            received = int(num(node_name, f'received_{cat}', '-1'))
            cells.append(f'{node_name} {received} / {total} ({kv.get("rejected_flooding", 0)})')
            if cat == 'joint_states':  # the sim's valid joint_states arrive too: compare sent
                continue
            if cat == 'joint_reference':  # the streamer's valid references arrive too
                continue
            ok = {'primitive': 1}.get(cat, valid.get(cat, 0))  # valid ones, the learner's fit
            all_counted &= total >= (received - ok if received >= 0 else n)
        print(f'{cat:14s} {n:6d}   ' + ', '.join(cells))
    print(f'\nevery bad message that reached a node counted there (joint_states and '
          f'joint_reference excluded: valid ones arrive too): {all_counted}')
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    main()
