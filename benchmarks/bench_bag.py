#!/usr/bin/env python3
"""Recording throughput of the recorder node: JointState messages/s, sustained, and loss.

    .venv/bin/python benchmarks/bench_bag.py [--rates 20000 25000] [--count 100000]
        [--pub-depth 1000] [--rec-param take_period:=0.005 ...] [--rec-env KEY=VALUE ...]
        [--rec-prefix 'chrt -f 10'] [--pub-prefix 'chrt -f 5']

For each target rate a publisher process (rclpy, reliable, keep-last ``--pub-depth``, default
1000; 0 = keep-all) publishes ``--count`` 7-joint ``sensor_msgs/JointState`` messages (header
stamp = message index) on loopback in 1 ms batches, waits until every sample is acknowledged
(reliable delivery may lag behind publishing on a loaded machine: "delivery lag"), and the
real ``recorder`` node (separate process, default parameters unless ``--rec-param``) records
them.  The bag is then read back: recorded messages, lost = indices missing (and the bursts of
consecutive missing indices), and the sustained rate = recorded / (last - first receive time).
Bounded in count and time; ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id
(default 143).  The recorder's CPU time per recorded message (user + system, from the
publisher's start to the last acknowledgement) gives its capacity independent of the load of
the machine: 1e6 / (CPU us per message) messages/s on one free core; it is split by thread
(python = interpreter, take and write; shm / udp = Fast DDS receive threads; other = Fast DDS
event threads).  The 1-minute load average at the start of each row is printed.  Prints a
markdown table.
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
    # reliable delivery may lag behind publishing on a loaded machine: the recorder is
    # stopped only when every subscriber acknowledged every sample (or after 30 s)
    from rclpy.duration import Duration
    acked = pub.wait_for_all_acked(Duration(seconds=30))
    print(f'ACKED {acked} {time.monotonic() - t0 - elapsed:.3f}', flush=True)
    time.sleep(0.2)
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


def thread_cpu(pid):
    """CPU seconds (user + system) of every thread of ``pid``, summed per thread group:
    ``python`` (interpreter and rclpy), ``dds.shm`` / ``dds.udp`` (Fast DDS receive threads),
    ``dds.other`` (event, async, watchdog threads)."""
    tick = os.sysconf('SC_CLK_TCK')
    groups = {'python': 0.0, 'dds.shm': 0.0, 'dds.udp': 0.0, 'dds.other': 0.0}
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            with open(f'/proc/{pid}/task/{tid}/stat') as f:
                stat = f.read()
        except OSError:
            continue
        name = stat[stat.index('(') + 1:stat.rindex(')')]
        fields = stat[stat.rindex(')') + 2:].split()
        cpu = (int(fields[11]) + int(fields[12])) / tick
        key = next((g for g in ('dds.shm', 'dds.udp') if name.startswith(g)),
                   'dds.other' if name.startswith('dds.') else 'python')
        groups[key] += cpu
    return groups


def run_one(rate, count, domain_id, timeout, pub_depth, queue_depth, rec_params=(),
            rec_env=None, rec_prefix=(), pub_prefix=()):
    from cdmp_ros.bag import BagReader
    from cdmp_ros.bag.cdr import decode_joint_state
    tmp = tempfile.mkdtemp(prefix='bench_bag_')
    bag = os.path.join(tmp, 'bench')
    topic = f'/bench_js_{rate}'
    rec = subprocess.Popen([*rec_prefix, sys.executable, '-m', 'cdmp_ros.nodes.recorder',
                            '--ros-args',
                            '-p', f'output:={bag}', '-p', f"topics:=['{topic}']",
                            '-p', f'queue_depth:={queue_depth}', *rec_params],
                           env=dict(env(domain_id), **(rec_env or {})),
                           stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    pub = subprocess.Popen([*pub_prefix, sys.executable, __file__, '--publisher', topic,
                            str(count), str(rate), str(timeout), str(pub_depth)],
                           env=env(domain_id), stdout=subprocess.PIPE, text=True)
    import psutil
    cpu = psutil.Process(rec.pid)
    published, pub_s, cpu0, ack_lag = 0, float('nan'), None, float('nan')
    threads0 = threads1 = {}
    try:
        deadline = time.monotonic() + timeout + 60
        for line in pub.stdout:  # bounded: the publisher exits after `timeout` s
            if line.startswith('START'):
                cpu0 = sum(cpu.cpu_times()[:2])
                threads0 = thread_cpu(rec.pid)
            elif line.startswith('PUBLISHED'):
                published, pub_s = int(line.split()[1]), float(line.split()[2])
            elif line.startswith('ACKED'):
                ack_lag = float(line.split()[2])
                time.sleep(0.3)
                break
            if time.monotonic() > deadline:
                break
        cpu1 = sum(cpu.cpu_times()[:2])
        threads1 = thread_cpu(rec.pid)
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
    where = next((f' @{a}' for a, b in runs if b - a + 1 == longest), '')
    in_order = stamps == sorted(stamps)
    span = (times[-1] - times[0]) / 1e9 if received > 1 else float('nan')
    size = os.path.getsize(os.path.join(bag, 'bench_0.mcap'))
    cpu_us = (cpu1 - cpu0) / max(received, 1) * 1e6 if cpu0 is not None else float('nan')
    split = '/'.join(f'{(threads1[k] - threads0[k]) / max(received, 1) * 1e6:.0f}'
                     for k in threads0) if threads0 else ''
    return {'target': rate, 'split': split, 'ack_lag': ack_lag, 'published': published,
            'pub_rate': published / pub_s,
            'cpu_us': cpu_us, 'rss': rss, 'bursts': f'{len(runs)} / {longest}{where}',
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
    parser.add_argument('--rec-param', action='append', default=[], metavar='NAME:=VALUE',
                        help='extra recorder parameter (repeatable)')
    parser.add_argument('--rec-env', action='append', default=[], metavar='KEY=VALUE',
                        help='extra environment variable of the recorder (repeatable)')
    parser.add_argument('--rec-prefix', default='',
                        help="command prefix of the recorder process, e.g. 'chrt -f 10'")
    parser.add_argument('--pub-prefix', default='',
                        help="command prefix of the publisher process, e.g. 'chrt -f 10'")
    parser.add_argument('--no-writer-cost', action='store_true',
                        help='skip the in-process BagWriter.write measurement')
    args = parser.parse_args(argv)
    rec_params = [x for p in args.rec_param for x in ('-p', p)]
    rec_env = dict(kv.split('=', 1) for kv in args.rec_env)
    if not args.no_writer_cost:
        print(f'\nBagWriter.write, 7-joint JointState, zstd: {writer_cost():.2f} us CPU per '
              'message (median of 5 x 100000)\n')
    print(f'publisher keep-last depth {args.pub_depth or "keep-all"}, recorder '
          f'{" ".join(args.rec_param) or "defaults"}{" " + str(rec_env) if rec_env else ""}'
          f'{" under " + args.rec_prefix if args.rec_prefix else ""}'
          f'{", publisher under " + args.pub_prefix if args.pub_prefix else ""}\n')
    print('| target msg/s | load avg (1 min) | published | publish rate msg/s | recorded | lost '
          '| loss bursts / longest @first index | in order '
          '| sustained recording msg/s | delivery lag s | recorder CPU us/msg '
          '| CPU us/msg python/shm/udp/other | recorder RSS MiB | bag MiB |')
    print('|---|---|---|---|---|---|---|---|---|---|---|---|---|---|')
    for rate in args.rates:
        load = os.getloadavg()[0]
        r = run_one(rate, args.count, args.domain_id, args.timeout, args.pub_depth,
                    args.queue_depth, rec_params, rec_env, args.rec_prefix.split(),
                    args.pub_prefix.split())
        print(f"| {r['target']} | {load:.1f} | {r['published']} | {r['pub_rate']:.0f} "
              f"| {r['recorded']} | {r['lost']} | {r['bursts']} | {r['in_order']} "
              f"| {r['rec_rate']:.0f} | {r['ack_lag']:.2f} | {r['cpu_us']:.1f} | {r['split']} "
              f"| {r['rss']:.0f} | {r['mb']:.1f} |", flush=True)
        if args.baseline:
            published, got = run_baseline(rate, args.count, args.domain_id, args.timeout,
                                          args.pub_depth, args.queue_depth)
            print(f'| {rate} (baseline: count-only subscriber) | | {published} | | {got} '
                  f'| {published - got} | | | | | | | | |', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
