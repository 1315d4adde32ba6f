"""Streamer timing across processes: on-time fraction, missing messages, CPU.

Starts the streamer (``python -m cdmp_ros.nodes.streamer``) as one process and a listener as
another (this file with ``--listen``); the listener publishes a 7-DoF Panda CDMP on
``primitive`` (and optionally a sphere obstacle so the coupling terms run every tick), then
records every ``joint_reference`` for ``--seconds``. A message is *on time* when it arrives
within one period of its schedule (its header stamp is the scheduled tick time); *missing*
messages are schedule slots between the first and the last received stamp that never arrived.
The streamer's CPU is measured with psutil over the same window (user + system time / wall
time, in % of one core).

Every process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.
Bounded: about (start-up + seconds + 2) s per configuration.

Options: ``--params-file FILE`` (repeatable) gives the streamer a parameter file (e.g.
``config/streamer.yaml``, the shipped coupling on the whole arm; default: the code's defaults);
``--param name:=value`` (repeatable, after the files) is passed to the streamer (e.g.
``realtime_priority:=50``, ``tick_thread:=false``); ``--listener-priority P`` runs the
measuring subscriber under SCHED_FIFO priority P (set before ``rclpy.init`` so the DDS threads
inherit it, as a controller's would); ``--configs 1000,1000o`` selects configurations (``o`` =
with a sphere obstacle); ``--graph sim,adapter`` starts the sim node (pybullet, 1 kHz physics,
tracking ``joint_reference``, publishing ``joint_states``) and the adapter node (idle: it
receives the primitive and the obstacles) next to the streamer, with their config files, and
the measurement starts once ``joint_states`` flow.

    .venv/bin/python benchmarks/bench_streamer.py [--seconds 8] [--domain 165]
"""
import argparse
import json
import os
import subprocess
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def env(domain):
    e = dict(os.environ)
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    e['ROS_DOMAIN_ID'] = str(domain)
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    return e


def panda_primitive_json():
    import numpy as np
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.primitive_io import dumps_primitive
    lower = [-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671]
    upper = [2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671]
    y0 = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
    y1 = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])
    T = np.linspace(0.0, 2.0, 401)
    s = T / 2.0
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    names = [f'panda_joint{i}' for i in range(1, 8)]
    Y = y0 + s[:, None] * (y1 - y0)
    return dumps_primitive(CDMP(lower, upper, joint_names=names).fit(T, Y))


def realtime_listener(priority):
    """SCHED_FIFO for the listener's main thread (before rclpy.init: DDS threads inherit)."""
    if priority:
        from cdmp_ros.common.realtime import configure_thread
        st = configure_thread(priority)
        if not st.ok:
            print(f'listener: {st.message}', file=sys.stderr)


def wait_joint_states(node, ex, n=20, timeout=90.0):
    """Spin until ``n`` joint_states arrived (the sim is up); False on timeout."""
    from sensor_msgs.msg import JointState
    from cdmp_ros.ros import qos
    got = []
    sub = node.create_subscription(JointState, 'joint_states', lambda m: got.append(1),
                                   qos.SENSOR)
    end = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
    node.destroy_subscription(sub)
    return len(got) >= n


def listen(seconds, rate, obstacle, warmup, priority=0, graph=False):
    """Listener process: publish the inputs, record joint_reference, print JSON stats."""
    realtime_listener(priority)
    import gc
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray
    from cdmp_ros.ros import qos

    rclpy.init()
    node = rclpy.create_node('bench_listener')
    prim_pub = node.create_publisher(String, 'primitive', qos.LATCHED)
    obs_pub = node.create_publisher(MarkerArray, 'obstacles', qos.COMMAND)
    rec = []
    clock = node.get_clock()

    def on_ref(msg):
        rec.append((clock.now().nanoseconds,
                    msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))

    ref_qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(JointState, 'joint_reference', on_ref, ref_qos)
    timing = {}

    def on_diag(msg):  # the streamer's own tick figures (wake-up lateness, tick duration)
        for st in msg.status:
            if st.name == 'streamer: timing':  # not the sim's or adapter's timings
                timing.update({v.key: v.value for v in st.values})

    node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diag, 50)
    try:  # the listener must not be the bottleneck at 1 kHz
        from rclpy.experimental import EventsExecutor
        ex = EventsExecutor()
    except ImportError:
        ex = SingleThreadedExecutor()
    ex.add_node(node)
    prim_pub.publish(String(data=panda_primitive_json()))
    if obstacle:
        m = Marker(ns='bench', id=0, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = 'panda_link0'
        m.pose.position.x, m.pose.position.y, m.pose.position.z = 0.45, 0.1, 0.45
        m.scale.x = m.scale.y = m.scale.z = 0.1
    if graph:
        assert wait_joint_states(node, ex), 'no joint_states from the sim'
    end = time.monotonic() + 60.0
    while len(rec) < 50 and time.monotonic() < end:  # the streamer is up and streaming
        ex.spin_once(timeout_sec=0.05)
        if obstacle and obs_pub.get_subscription_count():
            obs_pub.publish(MarkerArray(markers=[m]))
    print(json.dumps({'event': 'streaming'}), flush=True)
    # the instrument must not pause: no garbage collection during the measured window
    gc.collect()
    gc.freeze()
    t_end = time.monotonic() + warmup
    while time.monotonic() < t_end:
        ex.spin_once(timeout_sec=0.01)
    rec.clear()
    gc.disable()
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        ex.spin_once(timeout_sec=0.01)
    gc.enable()
    period_ns = 1e9 / rate
    arrivals = [a for a, _ in rec]
    stamps = sorted(s for _, s in rec)
    late = [(a - s) for a, s in rec]
    on_time = sum(1 for d in late if d <= period_ns)
    slots = int(round((stamps[-1] - stamps[0]) / period_ns)) + 1 if stamps else 0
    lat = sorted(late)
    out = {'received': len(rec), 'slots': slots, 'missing': max(0, slots - len(set(stamps))),
           'on_time_fraction': on_time / len(rec) if rec else 0.0,
           'delay_ms_p50': lat[len(lat) // 2] / 1e6 if lat else None,
           'delay_ms_p99': lat[int(0.99 * (len(lat) - 1))] / 1e6 if lat else None,
           'rate_hz': (len(rec) - 1) / ((arrivals[-1] - arrivals[0]) * 1e-9)
           if len(rec) > 1 else 0.0,
           'streamer_timing': timing}
    print(json.dumps(out), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def listen_latency(reps, priority=0, graph=False):
    """Listener: obstacle message -> first joint_reference that reflects it.

    The open-loop reference converges to the goal and rests; a sphere is then published
    0.1 m from the end effector (inside the repeller's influence distance); the first reference
    whose position leaves the rest position by more than 1e-6 rad reflects it. The sphere is
    deleted and the reference converges again before the next repetition.

    The latency runs from the ``publish`` call of the serialized message (``p50_ms``...) and,
    for comparison with figures before 2026-11-29, from before the listener built and
    serialized it in Python (``from_build_*``: 0.1-0.4 ms more, cold).
    """
    realtime_listener(priority)
    import numpy as np
    import pybullet_data
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray
    from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
    from cdmp_ros.ros import qos
    from rclpy.experimental import EventsExecutor

    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))
    rclpy.init()
    node = rclpy.create_node('bench_latency')
    prim_pub = node.create_publisher(String, 'primitive', qos.LATCHED)
    obs_pub = node.create_publisher(MarkerArray, 'obstacles', qos.COMMAND)
    clock = node.get_clock()
    last = {}

    def on_ref(msg):
        last['t'] = clock.now().nanoseconds
        last['y'] = np.array(msg.position)
        last['yd'] = np.array(msg.velocity)
        watch = last.get('watch')
        if watch is not None and 'hit' not in last and \
                np.abs(last['y'] - watch).max() > 1e-6:
            last['hit'] = last['t']

    node.create_subscription(JointState, 'joint_reference', on_ref,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    inside = {}

    def on_diag(msg):  # the streamer's own figures: marker stamp -> first reference published
        for st in msg.status:
            kv = {v.key: v.value for v in st.values}
            if st.name.startswith('streamer') and 'obstacle_latency_n' in kv:
                inside.update(kv)

    node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diag, 50)
    ex = EventsExecutor()
    ex.add_node(node)
    prim_pub.publish(String(data=panda_primitive_json()))

    def spin_until(pred, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not pred():
            ex.spin_once(timeout_sec=0.01)
        return pred()

    def rested():
        return 'yd' in last and np.abs(last['yd']).max() < 1e-9

    if graph:
        assert wait_joint_states(node, ex), 'no joint_states from the sim'
    assert spin_until(lambda: obs_pub.get_subscription_count() > 0 and 'y' in last, 60.0)
    print(json.dumps({'event': 'streaming'}), flush=True)
    lat, lat_build = [], []
    for i in range(reps):
        if not spin_until(rested, 15.0):
            break
        y0 = last['y'].copy()
        ee = chain.forward(y0, [PointOfInterest('ee')])[0]
        m = Marker(ns='bench', id=0, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = 'panda_link0'
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (ee + [0.1, 0.0, 0.0]).tolist()
        m.scale.x = m.scale.y = m.scale.z = 0.04
        last.pop('hit', None)
        last['watch'] = y0
        t_build = clock.now().nanoseconds
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_build, 1_000_000_000)
        raw = serialize_message(MarkerArray(markers=[m]))
        t_pub = clock.now().nanoseconds
        obs_pub.publish(raw)
        if spin_until(lambda: 'hit' in last, 2.0):
            lat.append((last['hit'] - t_pub) * 1e-6)
            lat_build.append((last['hit'] - t_build) * 1e-6)
        last['watch'] = None
        obs_pub.publish(MarkerArray(markers=[Marker(ns='bench', action=Marker.DELETEALL)]))
    spin_until(lambda: False, 1.2)  # one more diagnostics message of the streamer
    lat.sort()
    lat_build.sort()
    print(json.dumps({'n': len(lat), 'p50_ms': lat[len(lat) // 2] if lat else None,
                      'p99_ms': lat[int(0.99 * (len(lat) - 1))] if lat else None,
                      'max_ms': lat[-1] if lat else None,
                      'from_build_p50_ms': lat_build[len(lat) // 2] if lat else None,
                      'from_build_p99_ms': lat_build[int(0.99 * (len(lat) - 1))] if lat
                      else None,
                      'inside': {k: v for k, v in inside.items()
                                 if k.startswith('obstacle_latency')}}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


#: Parameter files of the streamer (``--params-file``), applied before every ``-p``.
PARAMS_FILES = []


def start_streamer(rate, domain, params):
    cmd = [sys.executable, '-m', 'cdmp_ros.nodes.streamer', '--ros-args']
    for f in PARAMS_FILES:
        cmd += ['--params-file', f]
    cmd += ['-p', f'rate:={rate}', '-p', 'joint_states_timeout:=0.0']
    for p in params:
        cmd += ['-p', p]
    return subprocess.Popen(cmd, env=env(domain), cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


GRAPH_NODES = {'sim': 'sim.yaml', 'adapter': 'adapter.yaml'}


def start_graph(graph, domain):
    """The sim / adapter nodes as processes, with their config files."""
    procs = []
    for name in graph:
        procs.append(subprocess.Popen(
            [sys.executable, '-m', f'cdmp_ros.nodes.{name}', '--ros-args', '--params-file',
             os.path.join(REPO, 'config', GRAPH_NODES[name])],
            env=env(domain), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    return procs


def cpu_percent(procs, c0, t0):
    """CPU [% of one core] of each process since the (cpu_times, time) of c0/t0."""
    out = []
    for p, c in zip(procs, c0):
        c1 = p.cpu_times()
        out.append((c1.user + c1.system - c.user - c.system) / (time.monotonic() - t0) * 100)
    return out


def stop_all(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(2)
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_latency(rate, reps, domain, params=(), priority=0, graph=()):
    others = start_graph(graph, domain)
    streamer = start_streamer(rate, domain, params)
    listener = subprocess.Popen(
        [sys.executable, __file__, '--listen-latency', str(reps),
         '--listener-priority', str(priority)] + (['--graph', ','.join(graph)] if graph else []),
        env=env(domain), cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        first = listener.stdout.readline()
        assert 'streaming' in first, f'listener: {first!r}'
        out = json.loads(listener.stdout.readline())
        listener.wait(20)
        return out
    finally:
        stop_all([listener, streamer] + others)


def run_config(rate, obstacle, seconds, domain, measure_cpu, params=(), priority=0, graph=()):
    import psutil
    others = start_graph(graph, domain)
    streamer = start_streamer(rate, domain, params)
    listener = subprocess.Popen(
        [sys.executable, __file__, '--listen', '--rate', str(rate), '--seconds', str(seconds),
         '--listener-priority', str(priority)]
        + (['--obstacle'] if obstacle else []) + (['--graph', ','.join(graph)] if graph else []),
        env=env(domain), cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        first = listener.stdout.readline()
        assert 'streaming' in first, f'listener: {first!r}'
        time.sleep(1.0)  # same warm-up as the listener
        procs = [psutil.Process(p.pid) for p in [streamer] + others]
        c0, t0 = [p.cpu_times() for p in procs], time.monotonic()
        line = listener.stdout.readline()
        cpus = cpu_percent(procs, c0, t0)
        stats = json.loads(line)
        stats['cpu_percent'] = cpus[0] if measure_cpu else None
        stats['graph_cpu'] = dict(zip(graph, cpus[1:]))
        for name, p in zip(graph, others):
            assert p.poll() is None, f'{name} died'
        listener.wait(20)
        return stats
    finally:
        stop_all([listener, streamer] + others)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=8.0)
    ap.add_argument('--domain', type=int, default=165)
    ap.add_argument('--listen', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('--rate', type=float, default=1000.0, help=argparse.SUPPRESS)
    ap.add_argument('--obstacle', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('--latency-reps', type=int, default=15,
                    help='repetitions of the obstacle -> reference latency measurement')
    ap.add_argument('--listen-latency', type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument('--param', action='append', default=[],
                    help='streamer parameter name:=value (repeatable)')
    ap.add_argument('--listener-priority', type=int, default=0,
                    help='SCHED_FIFO priority of the measuring subscriber (0 = normal)')
    ap.add_argument('--configs', default='1000,1000o,500,500o',
                    help='rates to measure, comma-separated; suffix o = with a sphere obstacle')
    ap.add_argument('--latency-rate', type=float, default=500.0)
    ap.add_argument('--graph', default='',
                    help='nodes started next to the streamer: sim, adapter (comma-separated)')
    ap.add_argument('--params-file', action='append', default=[], metavar='FILE',
                    help='a parameter file of the streamer, before the --param values '
                    '(repeatable; e.g. config/streamer.yaml, the shipped coupling); default: '
                    "the code's defaults")
    args = ap.parse_args()
    PARAMS_FILES[:] = [os.path.abspath(f) for f in args.params_file]
    graph = tuple(filter(None, args.graph.split(',')))
    for name in graph:
        if name not in GRAPH_NODES:
            ap.error(f'--graph: expected names from {sorted(GRAPH_NODES)}, got {name!r}')
    if args.listen:
        return listen(args.seconds, args.rate, args.obstacle, warmup=1.0,
                      priority=args.listener_priority, graph=bool(graph))
    if args.listen_latency:
        return listen_latency(args.listen_latency, args.listener_priority, bool(graph))
    rows = []
    load0 = os.getloadavg()[0]
    for c in filter(None, args.configs.split(',')):
        rate, obstacle = float(c.rstrip('o')), c.endswith('o')
        s = run_config(rate, obstacle, args.seconds, args.domain, measure_cpu=True,
                       params=args.param, priority=args.listener_priority, graph=graph)
        rows.append((rate, obstacle, s))
    print(f'Streamer timing, {args.seconds:g} s per configuration, separate subscriber '
          f'process, load average {load0:.2f} -> {os.getloadavg()[0]:.2f} on '
          f'{os.cpu_count()} cores; streamer parameter files '
          f'{[os.path.relpath(f, REPO) for f in PARAMS_FILES] or "none"}, parameters '
          f'{args.param or "defaults"}; '
          f'listener SCHED_FIFO {args.listener_priority or "off"}; alongside: '
          f'{", ".join(graph) or "nothing (streamer and listener only)"}\n')
    print('| rate [Hz] | obstacle (coupling every tick) | received | missing | on time (<= 1 '
          'period) | delay p50 [ms] | delay p99 [ms] | measured rate [Hz] | streamer CPU '
          '[% of one core] | streamer wake-up late p99 / max [ms] | tick p99 / max [ms] |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for rate, obstacle, s in rows:
        t = s.get('streamer_timing', {})
        wake = ' / '.join(t.get(f'tick_wake_late_{k}_ms', 'n/a') for k in ('p99', 'max'))
        tick = ' / '.join(t.get(f'tick_{k}_ms', 'n/a') for k in ('p99', 'max'))
        print(f'| {rate:g} | {"1 sphere" if obstacle else "none"} | {s["received"]} | '
              f'{s["missing"]} | {100 * s["on_time_fraction"]:.2f} % | '
              f'{s["delay_ms_p50"]:.3f} | {s["delay_ms_p99"]:.3f} | {s["rate_hz"]:.1f} | '
              f'{s["cpu_percent"]:.1f} | {wake} | {tick} |')
    for rate, obstacle, s in rows:
        if s.get('graph_cpu'):
            what = ' with the sphere' if obstacle else ''
            cpus = ', '.join(f'{k} {v:.1f} %' for k, v in s['graph_cpu'].items())
            print(f'\nCPU of the other nodes at {rate:g} Hz{what}: {cpus}')
    if args.latency_reps:
        print(f'\nObstacle message published -> first joint_reference that reflects it (across '
              f'processes, {args.latency_rate:g} Hz, reference at rest, sphere 0.1 m from the '
              f'end effector); from build = from before the listener built and serialized the '
              f'message; inside = the streamer diagnostics (marker stamp -> first reference '
              f'published after it)\n')
        print('| repetitions | p50 [ms] | p99 [ms] | max [ms] | from build p50 / p99 [ms] | '
              'inside p50 / p99 / max [ms] |')
        print('|---|---|---|---|---|---|')
        lat = run_latency(args.latency_rate, args.latency_reps, args.domain, args.param,
                          args.listener_priority, graph)
        fmt = (lambda v: 'n/a' if v is None else f'{v:.2f}')
        ins = lat.get('inside', {})
        inside = ' / '.join(ins.get(f'obstacle_latency_ms_{k}', 'n/a')
                            for k in ('p50', 'p99', 'max'))
        print(f'| {lat["n"]} | {fmt(lat["p50_ms"])} | {fmt(lat["p99_ms"])} | '
              f'{fmt(lat["max_ms"])} | {fmt(lat["from_build_p50_ms"])} / '
              f'{fmt(lat["from_build_p99_ms"])} | {inside} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
