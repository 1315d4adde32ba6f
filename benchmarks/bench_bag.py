#!/usr/bin/env python3
"""Recording throughput of the recorder node: JointState messages/s, sustained, and loss.

    .venv/bin/python benchmarks/bench_bag.py [--rates 20000 25000] [--count 100000]

For each target rate a publisher process (rclpy, reliable, keep-last 1000) publishes
``--count`` 7-joint ``sensor_msgs/JointState`` messages (header stamp = message index) on
loopback in 1 ms batches, and the real ``recorder`` node (separate process, default
parameters) records them.  The bag is then read back: received = recorded messages, lost =
indices missing, and the sustained rate = recorded / (last - first receive time).  Bounded in
count and time; ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id (default 143).
The recorder's CPU time per recorded message (user + system, while publishing) gives its
capacity independent of the load of the machine: 1e6 / (CPU us per message) messages/s on
one free core.  Prints a markdown table.
"""
import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JOINTS = [f'panda_joint{i}' for i in range(1, 8)]


def env(domain_id):
    e = dict(os.environ)
    e['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    e['ROS_DOMAIN_ID'] = str(domain_id)
    e['AMENT_PREFIX_PATH'] = sys.prefix
    e['PYTHONUNBUFFERED'] = '1'
    return e


def publisher(topic, count, rate, timeout, depth):
    """Child process: wait for the recorder, publish ``count`` messages at ``rate``/s."""
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from cdmp_ros.bag.cdr import encode_joint_state
    rclpy.init()
    node = rclpy.create_node('bench_publisher')
    history = HistoryPolicy.KEEP_ALL if depth == 0 else HistoryPolicy.KEEP_LAST
    pub = node.create_publisher(JointState, topic, QoSProfile(
        history=history, depth=max(depth, 1), reliability=ReliabilityPolicy.RELIABLE))
    t_end = time.monotonic() + timeout
    while pub.get_subscription_count() < 1 and time.monotonic() < t_end:
        time.sleep(0.01)
    time.sleep(0.5)
    payloads = [encode_joint_state(i, JOINTS, [0.1 * k + i * 1e-6 for k in range(7)],
                                   [0.01] * 7, [0.0] * 7) for i in range(count)]
    batch = max(1, int(rate / 1000))
    print('START', flush=True)
    t0 = time.monotonic()
    i = 0
    while i < count and time.monotonic() < t_end:
        for data in payloads[i:i + batch]:
            pub.publish(data)
        i += batch
        due = t0 + i / rate
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    elapsed = time.monotonic() - t0
    print(f'PUBLISHED {min(i, count)} {elapsed:.4f}', flush=True)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.try_shutdown()


def counter(topic, depth, seconds):
    """Child process (baseline): a raw subscriber that only counts, draining like the
    recorder; tells how much the transport alone loses under the current load."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    rclpy.init()
    node = rclpy.create_node('bench_counter')
    got = [0]
    holder = []

    def on_message(_data):
        got[0] += 1
        sub = holder[0]
        with sub.handle:
            while sub.handle.take_message(sub.msg_type, True) is not None:
                got[0] += 1

    holder.append(node.create_subscription(
        JointState, topic, on_message,
        QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE), raw=True))
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(f'COUNT {got[0]}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


def run_baseline(rate, count, domain_id, timeout, pub_depth, queue_depth):
    """Publisher -> counting subscriber: messages lost by the transport alone."""
    topic = f'/bench_count_{rate}'
    seconds = count / rate + 15
    sub = subprocess.Popen([sys.executable, __file__, '--counter', topic, str(queue_depth),
                            str(seconds)], env=env(domain_id), stdout=subprocess.PIPE,
                           text=True)
    pub = subprocess.Popen([sys.executable, __file__, '--publisher', topic, str(count),
                            str(rate), str(timeout), str(pub_depth)], env=env(domain_id),
                           stdout=subprocess.PIPE, text=True)
    try:
        out, _ = pub.communicate(timeout=timeout + 30)
        sub_out, _ = sub.communicate(timeout=seconds + 30)
    finally:
        for p in (pub, sub):
            if p.poll() is None:
                p.kill()
                p.wait()
    published = next((int(x.split()[1]) for x in out.splitlines()
                      if x.startswith('PUBLISHED')), 0)
    got = next((int(x.split()[1]) for x in sub_out.splitlines() if x.startswith('COUNT')), 0)
    return published, got


def run_one(rate, count, domain_id, timeout, pub_depth, queue_depth):
    from cdmp_ros.bag import BagReader
    from cdmp_ros.bag.cdr import decode_joint_state
    tmp = tempfile.mkdtemp(prefix='bench_bag_')
    bag = os.path.join(tmp, 'bench')
    topic = f'/bench_js_{rate}'
    rec = subprocess.Popen([sys.executable, '-m', 'cdmp_ros.nodes.recorder', '--ros-args',
                            '-p', f'output:={bag}', '-p', f"topics:=['{topic}']",
                            '-p', f'queue_depth:={queue_depth}'],
                           env=env(domain_id), stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    pub = subprocess.Popen([sys.executable, __file__, '--publisher', topic, str(count),
                            str(rate), str(timeout), str(pub_depth)], env=env(domain_id),
                           stdout=subprocess.PIPE, text=True)
    import psutil
    cpu = psutil.Process(rec.pid)
    published, pub_s, cpu0 = 0, float('nan'), None
    try:
        deadline = time.monotonic() + timeout + 60
        for line in pub.stdout:  # bounded: the publisher exits after `timeout` s
            if line.startswith('START'):
                cpu0 = sum(cpu.cpu_times()[:2])
            elif line.startswith('PUBLISHED'):
                published, pub_s = int(line.split()[1]), float(line.split()[2])
                time.sleep(0.5)
                break
            if time.monotonic() > deadline:
                break
        cpu1 = sum(cpu.cpu_times()[:2])
        rss = cpu.memory_info().rss / 2 ** 20
        rec.send_signal(signal.SIGINT)
        rec.wait(timeout=60)
        pub.wait(timeout=30)
    finally:
        for p in (pub, rec):
            if p.poll() is None:
                p.kill()
                p.wait()
    stamps, times = [], []
    for m in BagReader(bag).messages():
        stamps.append(decode_joint_state(m.data).stamp_ns)
        times.append(m.log_time)
    received = len(stamps)
    lost = published - len(set(stamps))
    missing = sorted(set(range(published)) - set(stamps))
    runs = []  # contiguous blocks of missing messages (a burst = a transport overflow)
    for k in missing:
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    longest = max((b - a + 1 for a, b in runs), default=0)
    in_order = stamps == sorted(stamps)
    span = (times[-1] - times[0]) / 1e9 if received > 1 else float('nan')
    size = os.path.getsize(os.path.join(bag, 'bench_0.mcap'))
    cpu_us = (cpu1 - cpu0) / max(received, 1) * 1e6 if cpu0 is not None else float('nan')
    return {'target': rate, 'published': published, 'pub_rate': published / pub_s,
            'cpu_us': cpu_us, 'rss': rss, 'bursts': f'{len(runs)} / {longest}',
            'recorded': received, 'lost': lost, 'in_order': in_order,
            'rec_rate': received / span if span else float('nan'), 'mb': size / 2 ** 20}


def writer_cost(n=100000):
    """CPU cost of BagWriter.write for one 7-joint JointState (us, median of 5 runs)."""
    import statistics
    from cdmp_ros.bag import BagWriter
    from cdmp_ros.bag.cdr import encode_joint_state
    data = encode_joint_state(1, JOINTS, [0.1] * 7, [0.2] * 7, [0.3] * 7)
    costs = []
    for k in range(5):
        with BagWriter(tempfile.mkdtemp(prefix='bench_writer_'), flush_period=0.1) as w:
            w.add_topic('/js', 'sensor_msgs/msg/JointState')
            t = time.process_time()
            for i in range(n):
                w.write('/js', data, i)
            costs.append((time.process_time() - t) / n * 1e6)
    return statistics.median(costs)


def main(argv=None):
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == '--publisher':
        publisher(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5]),
                  int(sys.argv[6]))
        return 0
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == '--counter':
        counter(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--rates', type=int, nargs='+', default=[20000, 25000])
    parser.add_argument('--count', type=int, default=100000)
    parser.add_argument('--domain-id', type=int, default=143)
    parser.add_argument('--pub-depth', type=int, default=1000,
                        help='publisher keep-last depth (0: keep-all)')
    parser.add_argument('--queue-depth', type=int, default=10000,
                        help='recorder subscription queue depth')
    parser.add_argument('--baseline', action='store_true',
                        help='also run each rate against a subscriber that only counts')
    parser.add_argument('--timeout', type=float, default=60.0,
                        help='longest publishing time per rate (s)')
    args = parser.parse_args(argv)
    print(f'\nBagWriter.write, 7-joint JointState, zstd: {writer_cost():.2f} us CPU per message '
          '(median of 5 x 100000)\n')
    print('| target msg/s | published | publish rate msg/s | recorded | lost '
          '| loss bursts / longest | in order '
          '| sustained recording msg/s | recorder CPU us/msg | recorder RSS MiB | bag MiB |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    for rate in args.rates:
        r = run_one(rate, args.count, args.domain_id, args.timeout, args.pub_depth,
                    args.queue_depth)
        print(f"| {r['target']} | {r['published']} | {r['pub_rate']:.0f} | {r['recorded']} "
              f"| {r['lost']} | {r['bursts']} | {r['in_order']} | {r['rec_rate']:.0f} "
              f"| {r['cpu_us']:.1f} | {r['rss']:.0f} | {r['mb']:.1f} |",
              flush=True)
        if args.baseline:
            published, got = run_baseline(rate, args.count, args.domain_id, args.timeout,
                                          args.pub_depth, args.queue_depth)
            print(f'| {rate} (baseline: count-only subscriber) | {published} | | {got} '
                  f'| {published - got} | | | | | | |', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
