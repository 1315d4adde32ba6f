"""Sim node figures: physics step cost, real-time factor, joint_states rate, CPU.

1. In process (no ROS): the cost of one physics step of :class:`cdmp_ros.sim.live.LiveSim`
   (Panda, 1 kHz, with the per-step limit / tracking bookkeeping) per control law, and of one
   distance + contact query with two obstacles; the implied largest real-time factor.
2. Across processes: the sim node (``python -m cdmp_ros.nodes.sim``, config/sim.yaml) with a
   listener in this process (another DDS participant) for ``--seconds``: joint_states received
   per second, the fraction of consecutive stamps exactly one publish period apart, the
   real-time factor and slipped steps the node reports on diagnostics, and the node's CPU
   (psutil: user + system time / wall time, % of one core).

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_sim_node.py [--seconds 8] [--domain 131]
"""
import argparse
import os
import subprocess
import sys
import threading
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


def step_costs(n=3000):
    from cdmp_ros.core.kinematics.closest import Box, Sphere
    from cdmp_ros.sim.live import LiveSim
    from cdmp_ros.sim.node_config import SimConfig
    rows = []
    for control in ('position', 'computed_torque', 'exogenous'):
        sim = LiveSim(SimConfig(control=control))
        sim.set_reference(sim.initial_positions + 0.1)
        sim.step(100)
        t = time.perf_counter()
        sim.step(n)
        per_step = (time.perf_counter() - t) / n
        rows.append((control, per_step * 1e6, 1e-3 / per_step))
        if control == 'position':
            sim.sync_obstacles({'s': Sphere((0.6, 0.0, 0.5), 0.05),
                                'b': Box((0.2, 0.3, 0.0), (0.4, 0.5, 0.6))})
            t = time.perf_counter()
            for _ in range(200):
                sim.monitor()
            query = (time.perf_counter() - t) / 200
        sim.close()
    return rows, query * 1e3


def listen(domain, seconds, warmup, markers):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import Marker, MarkerArray
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('sim_bench', context=ctx)
    recv, diag = [], {}

    def on_js(msg):
        recv.append((time.monotonic(), msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec))

    def on_diag(msg):
        for s in msg.status:
            diag[s.name] = {kv.key: kv.value for kv in s.values}
    node.create_subscription(JointState, 'joint_states', on_js,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diag, 10)
    pub = node.create_publisher(MarkerArray, 'obstacles', 10)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    stop = threading.Event()
    th = threading.Thread(target=lambda: [ex.spin_once(timeout_sec=0.05)
                                          for _ in iter(stop.is_set, True)], daemon=True)
    th.start()
    end = time.monotonic() + 60
    while not recv and time.monotonic() < end:
        time.sleep(0.05)
    if markers:
        arr = MarkerArray()
        for i, (kind, pos, size) in enumerate([(Marker.SPHERE, (0.6, 0.0, 0.5), 0.1),
                                               (Marker.CUBE, (0.3, 0.4, 0.3), 0.2)]):
            m = Marker(ns='bench', id=i, type=kind, action=Marker.ADD)
            m.header.frame_id = 'panda_link0'
            m.pose.position.x, m.pose.position.y, m.pose.position.z = pos
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = m.scale.z = size
            arr.markers.append(m)
        pub.publish(arr)
    time.sleep(warmup)
    return node, ctx, ex, stop, th, recv, diag


def run_config(label, params, domain, seconds, markers=False):
    import numpy as np
    import psutil
    cmd = [sys.executable, '-m', 'cdmp_ros.nodes.sim', '--ros-args', '--params-file',
           'config/sim.yaml', '-p', 'diagnostics_period:=1.0'] + sum(
               (['-p', p] for p in params), [])
    proc = subprocess.Popen(cmd, env=env(domain), cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.STDOUT)
    node = None
    try:
        node, ctx, ex, stop, th, recv, diag = listen(domain, seconds, 1.5, markers)
        p = psutil.Process(proc.pid)
        c0, t0 = p.cpu_times(), time.monotonic()
        i0 = len(recv)
        time.sleep(seconds)
        c1, t1 = p.cpu_times(), time.monotonic()
        window = recv[i0:]
        cpu = (c1.user + c1.system - c0.user - c0.system) / (t1 - t0) * 100.0
        stamps = np.array([s for _, s in window])
        state = diag.get('sim: state', {})
        timing = diag.get('sim: timing', {})
        # real time: stamps are the wall-clock slots (4 ms apart unless the sim slipped);
        # as fast as possible: stamps are the publication times (not compared)
        one = (f'{float(np.mean(np.abs(np.diff(stamps) - 4e6) < 1e3)) * 100.0:.2f} %'
               if 'real_time:=false' not in params and len(stamps) > 1 else 'n/a')
        return dict(label=label, rate=len(window) / (t1 - t0), one_period=one,
                    rtf=state.get('real_time_factor', '?'),
                    slipped=state.get('slipped_steps', '?'),
                    tick_p99=timing.get('tick_p99_ms', '?'), cpu=cpu)
    finally:
        if node is not None:
            stop.set()
            th.join(2)
            ex.shutdown()
            node.destroy_node()
            import rclpy
            rclpy.try_shutdown(context=ctx)
        proc.send_signal(2)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=8.0)
    ap.add_argument('--domain', type=int, default=131)
    args = ap.parse_args()
    print(f'load average before: {os.getloadavg()[0]:.2f}\n')
    rows, query_ms = step_costs()
    print('| control (Panda, 1 kHz) | physics step incl. bookkeeping [us] | largest real-time '
          'factor |')
    print('|---|---|---|')
    for control, us, rtf in rows:
        print(f'| {control} | {us:.1f} | {rtf:.1f} |')
    print(f'\nDistance + contact query, 2 obstacles (sphere, box), all links: {query_ms:.3f} ms\n')
    configs = [
        ('real time, position, no obstacle', []),
        ('real time, computed_torque, 2 obstacles (queries at 100 Hz)',
         ['control:=computed_torque'], True),
        ('as fast as possible, computed_torque', ['control:=computed_torque',
                                                  'real_time:=false']),
    ]
    print('| configuration | joint_states received [1/s] | consecutive stamps 1 period apart '
          '| real-time factor (node) | slipped steps | tick p99 [ms] | sim CPU [% of one core] |')
    print('|---|---|---|---|---|---|---|')
    for cfg in configs:
        label, params = cfg[0], cfg[1]
        r = run_config(label, params, args.domain, args.seconds,
                       markers=len(cfg) > 2 and cfg[2])
        print(f'| {r["label"]} | {r["rate"]:.1f} | {r["one_period"]} | {r["rtf"]} | '
              f'{r["slipped"]} | {r["tick_p99"]} | {r["cpu"]:.1f} |', flush=True)


if __name__ == '__main__':
    main()
