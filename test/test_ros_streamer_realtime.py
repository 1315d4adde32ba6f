"""The streamer's tick thread as a real process (``python -m cdmp_ros.nodes.streamer``).

- ``realtime_priority``: the scheduling policy of every thread of the streamer process is read
  back from the kernel (``sched_getscheduler`` by native thread id): the tick thread at the
  priority, with ``realtime_threads: all`` the other threads one below and the primitive worker
  at 1, with ``tick`` every other thread unchanged.
- ``obstacle_wakeup``: obstacle messages wake the tick thread, which publishes the next slot at
  once; the published stamps must stay on the fixed grid (each slot at most once, stamps
  exactly whole periods apart), and the early publications are counted on ``diagnostics``
  (``early_ticks``). A wake-up that comes when the tick is already due (a loaded machine)
  publishes on time instead, so obstacles are sent one at a time, each after the previous one
  was used, until an early publication is counted.

Localhost only; every wait is on a condition with a generous timeout.
"""
import os
import threading

import numpy as np
import pytest

from cdmp_ros.core.primitive_io import dumps_primitive
from streamer_harness import Harness, reach_cdmp, start_streamer, stop_process, wait_for
from node_harness import assert_clean_stop
from conftest import module_domain

pytestmark = pytest.mark.ros
DOMAIN = module_domain(8)
STARTUP = 30.0
TIMEOUT = 30.0  # s; bounds a failing wait only
MAX_OBSTACLES = 300  # bounds the wake-ups sent until one is early


def fifo_permitted():
    out = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            out.append(True)
        except (OSError, AttributeError):
            out.append(False)
    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return out[0]


def thread_policies(pid):
    """[(policy, priority)] of every thread of a process."""
    out = []
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            out.append((os.sched_getscheduler(int(tid)),
                        os.sched_getparam(int(tid)).sched_priority))
        except ProcessLookupError:
            pass
    return out


@pytest.mark.skipif(not fifo_permitted(), reason='SCHED_FIFO not permitted here')
@pytest.mark.parametrize('scope', ['all', 'tick'])
def test_realtime_priority_is_applied_to_the_tick_thread(tmp_path, scope):
    log = tmp_path / 'streamer.log'
    proc = start_streamer(DOMAIN, ['realtime_priority:=20', f'realtime_threads:={scope}'],
                          log_path=str(log), params_file='config/streamer.yaml')
    try:
        assert wait_for(lambda: 'tick thread: SCHED_FIFO priority 20' in log.read_text()
                        or proc.poll() is not None, STARTUP, period=0.1), log.read_text()
        assert proc.poll() is None, log.read_text()
        pol = thread_policies(proc.pid)
        fifo = sorted(p for s, p in pol if s == os.SCHED_FIFO)
        assert fifo.count(20) == 1, pol  # the tick thread
        if scope == 'tick':
            assert fifo == [20], pol
        else:
            assert fifo.count(1) == 1, pol  # the primitive worker
            assert fifo.count(19) == len(pol) - 2, pol  # executor, middleware, ...
    finally:
        code = stop_process(proc)
    assert_clean_stop(code, log.read_text(), 'streamer')


def test_obstacle_wakeups_keep_the_stamps_on_the_grid(tmp_path):
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray
    log = tmp_path / 'streamer.log'
    proc = start_streamer(DOMAIN, ['diagnostics_period:=0.05'], log_path=str(log),
                          params_file='config/streamer.yaml')
    h = Harness(DOMAIN)

    def used():  # obstacle messages whose first reference was published
        return int(h.last_state()[1].get('obstacle_latency_n', 0))
    try:
        assert h.wait(lambda: h.n_refs() > 10 or proc.poll() is not None, STARTUP), \
            log.read_text()
        h.publish('primitive', String(data=dumps_primitive(reach_cdmp(duration=3.0))))
        assert h.wait(lambda: h.last_state()[1].get('state') == 'running', TIMEOUT)
        i0 = h.n_refs()
        k = 0
        while k < 30 or int(h.last_state()[1].get('early_ticks', 0)) == 0:
            assert k < MAX_OBSTACLES, h.last_state()  # no wake-up was ever early
            # a far sphere: no coupling force, but a new obstacle set each time
            m = Marker(ns='grid', id=k % 3, type=Marker.SPHERE, action=Marker.ADD)
            m.header.frame_id = 'panda_link0'
            m.header.stamp = h.node.get_clock().now().to_msg()
            m.pose.position.x = 3.0 + 0.01 * k
            m.scale.x = m.scale.y = m.scale.z = 0.1
            h.publish('obstacles', MarkerArray(markers=[m]))
            k += 1
            assert h.wait(lambda: used() >= k, TIMEOUT), (k, h.last_state())
        assert h.wait(lambda: h.n_refs() >= i0 + 100, TIMEOUT)
        refs = h.refs_since(i0)
        stamps = np.array([r[1] for r in refs], dtype=np.int64)
        d = np.diff(stamps) * 1e-9
        dt = 1.0 / 500.0
        assert np.all(d > 0.0), 'stamps must increase: every slot once, in order'
        periods = d / dt
        # exact grid (1 ns rounding); gaps are allowed here: this test process is not
        # real-time and loses messages on a loaded machine (the benchmark counts missing ones)
        assert np.abs(periods - np.round(periods)).max() < 1e-5, 'a stamp off the grid'
        assert int(h.last_state()[1].get('early_ticks', 0)) > 0  # published after a wake-up
    finally:
        h.close()
        code = stop_process(proc)
    assert_clean_stop(code, log.read_text(), 'streamer')
    assert not h.violations, h.violations[:5]
