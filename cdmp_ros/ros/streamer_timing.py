"""Timing helpers of the streamer node: the stamp grid's clock offset, the obstacle-latency
percentiles on diagnostics, and the report (and lifting) of the threads' scheduling."""
import time

import numpy as np

from cdmp_ros.ros.realtime import process_thread_ids, set_threads_fifo

#: Obstacle-to-reference latencies kept for the diagnostics percentiles (a ring).
LATENCY_SAMPLES = 4096


def clock_offset_ns(clock) -> int:
    """ROS clock - steady clock [ns], from the closest of three back-to-back readings."""
    best = None
    for _ in range(3):
        a = time.monotonic_ns()
        ros = clock.now().nanoseconds
        b = time.monotonic_ns()
        if best is None or b - a < best[0]:
            best = (b - a, ros - (a + b) // 2)
    return best[1]


def latency_values(n_total: int, lat) -> dict:
    """Obstacle message stamp -> first joint_reference published with it, over the last
    :data:`LATENCY_SAMPLES` obstacle messages (ms), as diagnostics key/values."""
    if n_total == 0:
        return {'obstacle_latency_n': 0}
    p50, p99, top = np.percentile(lat, [50.0, 99.0, 100.0])
    return {'obstacle_latency_n': n_total,
            'obstacle_latency_ms_p50': f'{p50:.3f}', 'obstacle_latency_ms_p99': f'{p99:.3f}',
            'obstacle_latency_ms_max': f'{top:.3f}'}


def lift_other_threads(logger, priority: int, tick_thread, worker) -> str:
    """SCHED_FIFO for the threads the tick depends on (``realtime_threads: all``): every
    thread of the process but the tick thread at ``priority - 1``, the primitive worker at 1."""
    own, wid = tick_thread.native_id, worker.native_id
    others = [t for t in process_thread_ids() if t not in (own, wid)]
    n, problems = set_threads_fifo(max(1, priority - 1), others)
    _, worker_problems = set_threads_fifo(1, [wid])
    problems = '; '.join(p for p in (problems, worker_problems) if p)
    if problems:
        logger.warning(f'tick thread: {problems}')
    return (f'; {n} other threads at SCHED_FIFO {max(1, priority - 1)}, primitive worker '
            f'at 1')


def report_scheduling(logger, status, realtime_threads: str, tick_thread, worker,
                      spin: float) -> None:
    """Log the tick thread's scheduling (``status``: its RealtimeStatus, None if it did not
    start) and lift the other threads when it runs under SCHED_FIFO."""
    if status is None:
        logger.error('tick thread: did not start within 5 s')
        return
    if not status.ok:
        logger.warning(f'tick thread: {status.message}')
    others = ''
    if status.realtime and realtime_threads == 'all':
        others = lift_other_threads(logger, status.priority, tick_thread, worker)
    policy = f'SCHED_FIFO priority {status.priority}' if status.realtime else 'normal'
    logger.info(f'tick thread: {policy} scheduling, CPUs {list(status.cpus)}, '
                f'spin {spin * 1e3:g} ms{others}')
