"""Cost of turning a serialized ``obstacles`` MarkerArray into what the nodes read: rclpy's
``deserialize_message`` against :func:`cdmp_ros.bag.cdr.decode_marker_array`.

An obstacle message arrives seconds after the previous one, when its code path has gone cold,
so each case is timed hot (back to back), after 2 ms (a tick's period) and after 100 ms of
sleep; medians and maxima over the repetitions, in microseconds.

Run: .venv/bin/python benchmarks/bench_marker_decode.py [--reps 60]
"""
import argparse
import statistics
import time

from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import Marker, MarkerArray

from cdmp_ros.bag.cdr import decode_marker_array


def sphere(i):
    m = Marker(ns='bench', id=i, type=Marker.SPHERE, action=Marker.ADD)
    m.header.frame_id = 'panda_link0'
    m.pose.position.x, m.pose.orientation.w = 0.5, 1.0
    m.scale.x = m.scale.y = m.scale.z = 0.04
    return m


def timed(fn, raw, pause, reps):
    out = []
    for _ in range(reps):
        if pause:
            time.sleep(pause)
        t = time.perf_counter_ns()
        fn(raw)
        out.append((time.perf_counter_ns() - t) * 1e-3)
    return statistics.median(out), max(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--reps', type=int, default=60)
    args = ap.parse_args()
    decoders = {'rclpy deserialize_message': lambda raw: deserialize_message(raw, MarkerArray),
                'cdr': decode_marker_array}
    print('| markers | decoder | hot median / max [us] | after 2 ms | after 100 ms |')
    print('|---|---|---|---|---|')
    for n in (1, 3, 64):
        raw = serialize_message(MarkerArray(markers=[sphere(i) for i in range(n)]))
        for name, fn in decoders.items():
            cells = [timed(fn, raw, pause, args.reps) for pause in (0.0, 0.002, 0.1)]
            print(f'| {n} | {name} | ' + ' | '.join(f'{a:.1f} / {b:.1f}' for a, b in cells)
                  + ' |', flush=True)


if __name__ == '__main__':
    main()
