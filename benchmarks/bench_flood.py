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

Every message is serialized once at start (a pool per category) and published as bytes, so
the publisher itself stays cheap. Beside the flood, a valid ``goal`` alternates between two
poses every ``--goal-period`` s so that the robot keeps moving (tracking error is measured
while it moves).

Printed: sim slipped physics steps, joint-limit violations of the simulated robot
(measured ``joint_states`` against the URDF limits: samples outside, largest usage
|q - centre| / half range), the sim's own limit violations and tracking error, streamer ticks
on time (``late_ticks``: a slot published after the next slot's deadline; ``missed_ticks``:
slots skipped), whether every node is alive at the end, and messages sent per category
against the rejections each node counted on that topic.

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_flood.py [--duration 60] [--rate 200] [--seed 0]
        [--domain 70] [--code DIR]    # DIR: run the nodes from another checkout (before/after)
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


def start_nodes(domain, code, logdir, params=None):
    """sim, streamer, adapter and learner from ``code``'s config/*.yaml; ``params``: more
    ``-p`` parameters per node (``{'streamer': {'rate': 1000.0}}``)."""
    procs = {}
    for name in NODES:
        cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{name}', '--ros-args', '--params-file',
               os.path.join(code, 'config', f'{name}.yaml')]
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
    }
    return {k: (t, cls, [serialize_message(m) for m in msgs])
            for k, (t, cls, msgs) in pool.items()}


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
    args = ap.parse_args()
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ['ROS_DOMAIN_ID'] = str(args.domain)

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.ros import qos
    from cdmp_ros.ros.robot_model import default_urdf_path
    chain = panda_chain(default_urdf_path())
    lower, upper = chain.lower, chain.upper

    rng = np.random.default_rng(args.seed)
    pool = build_pool(rng)
    logdir = tempfile.mkdtemp(prefix='bench_flood_')
    procs = start_nodes(args.domain, os.path.abspath(args.code), logdir)
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
                    ('slipped_steps', 'missed_ticks', 'late_ticks', 'ticks', 'limit_violations')}
                for n in ('sim', 'streamer')}
        with obs.lock:
            n_q0 = len(obs.q)
        print(f'nodes up; flooding {args.duration:g} s at ~{args.rate:g} msg/s '
              f'(seed {args.seed}, domain {args.domain}, code {args.code})', flush=True)
        cats = list(pool)
        goal_pub = node.create_publisher(JointState, 'goal', qos.COMMAND)
        t_start = time.monotonic()
        next_goal, g = t_start, 0
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
                next_goal += args.goal_period
            if now >= t_next:
                cat = cats[int(rng.integers(len(cats)))]
                topic, _, msgs = pool[cat]
                pubs[topic].publish(msgs[int(rng.integers(len(msgs)))])
                sent[cat] += 1
                t_next = now + rng.exponential(1.0 / args.rate)
            time.sleep(max(0.0, min(t_next, next_goal, deadline) - time.monotonic()))
        time.sleep(3.0)  # the last rejections and diagnostics arrive
        alive = {n: procs[n].poll() is None for n in NODES}
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
    print(f'\n== flood {args.duration:g} s, {sum(sent.values())} bad messages, '
          f'{g} valid goals; logs {logdir}')
    print(f'sim slipped physics steps      {slipped:.0f}')
    print(f'joint_states samples           {len(Q)}; outside the URDF limits: {outside}; '
          f'largest limit usage {usage.max() if len(Q) else float("nan"):.4f}')
    print(f'sim limit_violations (steps)   '
          f'{num("sim", "limit_violations") - float(base["sim"]["limit_violations"]):.0f}; '
          f'max_limit_usage_since_start {obs.get("sim: state", "max_limit_usage_since_start")}')
    print(f'sim tracking error max         {obs.get("sim: state", "tracking_error_max_rad")} rad')
    print(f'streamer slots                 {slots:.0f} at {obs.get("streamer: state", "rate_hz")}'
          f' Hz: on time {on_time * 100:.3f} % (late {late:.0f}, missed {missed:.0f}); '
          f'tick_wake_late p99 / max '
          f'{obs.get("streamer: timing", "tick_wake_late_p99_ms")} / '
          f'{obs.get("streamer: timing", "tick_wake_late_max_ms")} ms')
    print(f'alive at the end               {alive}')
    print('\ncategory        sent   per node: received by the gate / rejections counted on the '
          'topic (of which flooding)')
    subscribers = {'goal': ('streamer', 'adapter'), 'joint_states': ('streamer', 'adapter'),
                   'demonstration': ('learner',), 'constraints': ('adapter',),
                   'primitive': ('streamer', 'adapter'), 'goal_point': ('adapter',),
                   'obstacles': ('sim', 'streamer', 'adapter')}
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
            valid = {'goal': g, 'primitive': 1}.get(cat, 0)  # valid goals, the learner's fit
            all_counted &= total >= (received - valid if received >= 0 else n)
        print(f'{cat:14s} {n:6d}   ' + ', '.join(cells))
    print(f'\nevery bad message that reached a node counted there (joint_states excluded: '
          f'valid ones arrive too, best effort keep-last-5): {all_counted}')
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    main()
