#!/usr/bin/env python3
"""Wall-clock figures of the bag nodes that the tests no longer assert (issue 10).

    .venv/bin/python benchmarks/bench_bag_timing.py [--rates 1 2] [--messages 100]
        [--dt-ms 20] [--trials 5] [--domain-id 144]

**Player timing fidelity.** A bag of ``--messages`` std_msgs/String ``--dt-ms`` apart is
played by the real ``player`` node (separate process, ``wait_subscribers``) at each
``--rates`` factor; an in-process subscriber stamps every arrival with the monotonic clock.
Printed: the expected gap (dt / rate), the median gap, the median and largest absolute gap
error, and the error of the whole span (last - first arrival against (n - 1) dt / rate).

**Recorder crash loss.** The real ``recorder`` node records a topic an in-process publisher
feeds at about 1 kHz; ``--trials`` times it is SIGKILLed at a random time 0.4-1.4 s after the
first chunk reached the file, the bag is rebuilt with ``recover_bag`` and the loss is the time
from the kill back to the last message kept, against the declared bound ``LOSS_BOUND_S``.

Loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), a private domain id, bounded in count
and time.  The 1-minute load average is printed with the figures.
"""
import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)

from cdmp_ros.bag import LOSS_BOUND_S, BagReader, BagWriter, recover_bag  # noqa: E402
from cdmp_ros.bag.cdr import encode_string  # noqa: E402

WAIT_S = 30.0


def child_env(domain_id):
    e = dict(os.environ)
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    e['ROS_DOMAIN_ID'] = str(domain_id)
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    return e


def start_node(node, params, domain_id, log_path):
    cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{node}', '--ros-args']
    for k, v in params.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        elif isinstance(v, (list, tuple)):
            v = '[' + ', '.join(f"'{x}'" for x in v) + ']'
        cmd += ['-p', f'{k}:={v}']
    return subprocess.Popen(cmd, env=child_env(domain_id), stdout=open(log_path, 'w'),
                            stderr=subprocess.STDOUT)


def kill(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def wait_for(pred, timeout, period=0.005):
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            return False
        time.sleep(period)
    return True


class Node:
    """An rclpy node in this process, spun by a background thread."""

    def __init__(self, domain_id):
        import threading
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('bench_bag_timing', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while not self._stop and self.context.ok():
            self.executor.spin_once(timeout_sec=0.02)

    def close(self):
        import rclpy
        self._stop = True
        self._thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def player_fidelity(node, tmp, rate, n, dt_ns, domain_id, run):
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    bag = os.path.join(tmp, f'timed{run}')
    with BagWriter(bag) as w:
        w.add_topic(f'/timed{run}', 'std_msgs/msg/String')
        for i in range(n):
            w.write(f'/timed{run}', encode_string(str(i)), 10 ** 12 + i * dt_ns)
    got = []
    node.node.create_subscription(
        String, f'/timed{run}', lambda _m: got.append(time.monotonic()),
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE), raw=True)
    play = start_node('player', {'bag': bag, 'rate': float(rate),
                                 'wait_subscribers': float(WAIT_S)}, domain_id,
                      os.path.join(tmp, f'play{run}.log'))
    try:
        play.wait(timeout=WAIT_S + n * dt_ns / 1e9 / rate + 30)
        wait_for(lambda: len(got) >= n, WAIT_S)
    finally:
        kill(play)
    if len(got) != n:
        return None
    gaps = np.diff(got)
    expected = dt_ns / 1e9 / rate
    err = np.abs(gaps - expected)
    span_err = (got[-1] - got[0]) - (n - 1) * expected
    return expected, float(np.median(gaps)), float(np.median(err)), float(err.max()), span_err


def crash_loss(node, tmp, trial, kill_after, domain_id):
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    topic = f'/crash{trial}'
    bag = os.path.join(tmp, f'crash{trial}')
    pub = node.node.create_publisher(String, topic, QoSProfile(
        depth=10000, reliability=ReliabilityPolicy.RELIABLE))
    rec = start_node('recorder', {'output': bag, 'topics': [topic]}, domain_id,
                     os.path.join(tmp, f'rec{trial}.log'))
    kill_ns = None
    try:
        if not wait_for(lambda: pub.get_subscription_count() >= 1, WAIT_S):
            return None
        mcap = os.path.join(bag, f'crash{trial}_0.mcap')
        base = os.path.getsize(mcap)
        start = None
        i = 0
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline and i < 10000:
            pub.publish(encode_string(f'{trial}:{i}'))
            i += 1
            if start is None and os.path.getsize(mcap) > base:
                start = time.monotonic()
            if start is not None and time.monotonic() - start >= kill_after:
                kill_ns = time.time_ns()
                rec.send_signal(signal.SIGKILL)
                break
            time.sleep(0.001)
    finally:
        kill(rec)
    if kill_ns is None:
        return None
    report = recover_bag(bag)
    kept = sum(1 for _ in BagReader(bag).messages())
    if report.last_log_time_ns is None:
        return kill_after, kept, float('inf')
    return kill_after, kept, (kill_ns - report.last_log_time_ns) / 1e9


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--rates', type=float, nargs='+', default=[1.0, 2.0])
    ap.add_argument('--messages', type=int, default=100, help='messages per played bag')
    ap.add_argument('--dt-ms', type=float, default=20.0, help='bag time between messages')
    ap.add_argument('--trials', type=int, default=5, help='recorder kills')
    ap.add_argument('--domain-id', type=int, default=144)
    args = ap.parse_args(argv)
    if not 0 <= args.domain_id <= 200:
        ap.error('--domain-id: expected a value in [0, 200]')
    node = Node(args.domain_id)
    print(f'Python {sys.version.split()[0]}, load average {os.getloadavg()[0]:.2f}, '
          f'{os.cpu_count()} CPUs\n')
    try:
        with tempfile.TemporaryDirectory(prefix='bench_bag_timing_') as tmp:
            print('Player timing fidelity (arrival times at a subscriber in another process)\n')
            print('| rate | messages | expected gap (ms) | median gap (ms) | '
                  'median abs gap error (ms) | max abs gap error (ms) | span error (ms) |')
            print('|---|---|---|---|---|---|---|')
            for run, rate in enumerate(args.rates):
                r = player_fidelity(node, tmp, rate, args.messages, int(args.dt_ms * 1e6),
                                    args.domain_id, run)
                if r is None:
                    print(f'| {rate:g} | {args.messages} | not every message arrived | | | | |')
                    continue
                exp, med, med_err, max_err, span = r
                print(f'| {rate:g} | {args.messages} | {exp * 1e3:.1f} | {med * 1e3:.2f} | '
                      f'{med_err * 1e3:.2f} | {max_err * 1e3:.2f} | {span * 1e3:+.1f} |')
            print(f'\nRecorder crash loss (SIGKILL; declared bound LOSS_BOUND_S = '
                  f'{LOSS_BOUND_S} s)\n')
            print('| trial | kill after (s) | messages kept | lost (s) | within bound |')
            print('|---|---|---|---|---|')
            rng = np.random.default_rng(2026)
            losses = []
            for trial, after in enumerate(rng.uniform(0.4, 1.4, size=args.trials)):
                r = crash_loss(node, tmp, trial, after, args.domain_id)
                if r is None:
                    print(f'| {trial} | {after:.2f} | the recorder never matched | | |')
                    continue
                after, kept, lost = r
                losses.append(lost)
                print(f'| {trial} | {after:.2f} | {kept} | {lost:.3f} | '
                      f'{"yes" if lost <= LOSS_BOUND_S else "NO"} |')
            if losses:
                print(f'\nlargest loss {max(losses):.3f} s over {len(losses)} kills '
                      f'(bound {LOSS_BOUND_S} s)')
    finally:
        node.close()


if __name__ == '__main__':
    main()
