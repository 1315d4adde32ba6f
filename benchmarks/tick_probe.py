"""Tick probe (issue 31 item 2): the streamer's schedule in a process of its own.

A bare fixed-rate publisher: one thread sleeps to the absolute deadlines of
:class:`~cdmp_ros.core.streaming.schedule.TickSchedule` (as the streamer's tick thread does,
with :class:`~cdmp_ros.common.realtime.DeadlineSleeper`), does about the work of a streamer
tick (numpy, ~0.1 ms) and publishes one 7-joint ``sensor_msgs/JointState`` per slot on
``--topic``. It subscribes to nothing, so no executor or middleware callback competes with it
for the GIL, and it runs at normal scheduling (SCHED_OTHER, nice 0). ``late_ticks`` and
``missed_ticks`` are counted by the same ``TickSchedule`` as the streamer's, so its on-time
share is what a tick that shares nothing with the node's intake could reach on the machine's
load: ``bench_flood.py --probe`` runs it beside the flooded graph.

Prints one JSON line: slots, ticks, late, missed, on-time share [%], wake-up lateness p99 /
max [ms].

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id
(set them in the environment; this script refuses to start without them).

    .venv/bin/python benchmarks/tick_probe.py --duration 60 [--rate 500] [--max-catch-up 10]
"""
import argparse
import json
import os
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--duration', type=float, required=True, help='seconds to tick')
    ap.add_argument('--rate', type=float, default=500.0, help='ticks per second')
    ap.add_argument('--max-catch-up', type=int, default=10,
                    help='slots integrated at most in one late tick (the streamer default)')
    ap.add_argument('--topic', default='tick_probe', help='JointState topic published')
    args = ap.parse_args(argv)
    if args.duration <= 0 or args.rate <= 0:
        ap.error('--duration and --rate must be positive')
    if (os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST'
            or not os.environ.get('ROS_DOMAIN_ID')):
        sys.exit('tick_probe: set ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private '
                 'ROS_DOMAIN_ID')

    import rclpy
    from sensor_msgs.msg import JointState

    from cdmp_ros.common.realtime import DeadlineSleeper
    from cdmp_ros.core.streaming.schedule import TickSchedule
    from cdmp_ros.ros import qos

    rclpy.init()
    node = rclpy.create_node('tick_probe')
    pub = node.create_publisher(JointState, args.topic, qos.REFERENCE)
    msg = JointState(name=[f'panda_joint{i}' for i in range(1, 8)])
    x = np.linspace(-1.0, 1.0, 2000)
    sleeper = DeadlineSleeper()
    sched = TickSchedule(args.rate, time.monotonic())
    wake_late = []
    ticks = 0
    end = time.monotonic() + args.duration
    while True:
        deadline = sched.deadline()
        sleeper.sleep_until(deadline)
        now = time.monotonic()
        if now >= end:
            break
        wake_late.append(sched.woke(now, False))
        _, steps, _ = sched.advance(now, args.max_catch_up)
        for _ in range(steps):  # about a streamer tick's numpy work, one message per slot
            msg.position = [float(np.tanh(x * 0.3).sum())] * 7
            pub.publish(msg)
        ticks += 1
    late, missed = sched.counts['late_ticks'], sched.counts['missed_ticks']
    slots = ticks + missed
    w = np.array(wake_late) * 1e3
    print(json.dumps({'slots': slots, 'ticks': ticks, 'late': late, 'missed': missed,
                      'on_time_pct': round(100.0 * (ticks - late) / slots, 3),
                      'wake_late_p99_ms': round(float(np.percentile(w, 99)), 3),
                      'wake_late_max_ms': round(float(w.max()), 3)}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == '__main__':
    main()
