"""cdmp_ros.common.realtime: SCHED_FIFO / affinity / timer slack of the calling thread, and the
deadline sleeper of periodic threads. Each setting is checked by reading it back from the
kernel in the thread that made it (other threads must stay untouched)."""
import ctypes
import os
import threading
import time

import pytest

from cdmp_ros.common import realtime
from cdmp_ros.common.realtime import DeadlineSleeper, configure_thread, thread_policy

PR_GET_TIMERSLACK = 30


def in_thread(fn):
    """Run fn() in a fresh thread (settings die with it); returns its result."""
    out = {}

    def run():
        try:
            out['value'] = fn()
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the caller
            out['error'] = exc
    t = threading.Thread(target=run)
    t.start()
    t.join(60)
    assert not t.is_alive(), f'{fn} did not return within 60 s'
    if 'error' in out:
        raise out['error']
    return out['value']


def fifo_permitted():
    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except OSError:
            return False
        realtime.reset_thread()
        return True
    return in_thread(probe)


@pytest.mark.parametrize('bad', [-1, 100, 1.5, True, '10', None])
def test_bad_priorities_are_refused_naming_the_variable(bad):
    with pytest.raises(ValueError, match=r'priority: expected an int in \[0, 99\]'):
        realtime.check_priority('priority', bad)


def test_priority_zero_leaves_normal_scheduling():
    st, pol = in_thread(lambda: (configure_thread(0), thread_policy()))
    assert st.ok and not st.realtime and st.priority == 0
    assert pol == (os.SCHED_OTHER, 0)
    assert set(st.cpus) == os.sched_getaffinity(0)


@pytest.mark.skipif(not fifo_permitted(), reason='SCHED_FIFO not permitted here')
def test_fifo_applies_to_the_calling_thread_only():
    main_before = thread_policy()
    st, pol = in_thread(lambda: (configure_thread(7), thread_policy()))
    assert st.ok and st.realtime
    assert pol == (os.SCHED_FIFO, 7)
    assert thread_policy() == main_before  # the main thread is untouched


@pytest.mark.skipif(not fifo_permitted(), reason='SCHED_FIFO not permitted here')
def test_other_threads_are_lifted_by_native_id():
    started, release = threading.Event(), threading.Event()
    seen = {}

    def idle():
        seen['tid'] = threading.get_native_id()
        started.set()
        release.wait(60)
        seen['policy'] = thread_policy()
    t = threading.Thread(target=idle)
    t.start()
    assert started.wait(60)
    assert seen['tid'] in realtime.process_thread_ids()
    done, problems = realtime.set_threads_fifo(3, [seen['tid'], 2 ** 22 + 12345])
    release.set()
    t.join(60)
    assert (done, problems) == (1, '')  # the id of no thread is skipped
    assert seen['policy'] == (os.SCHED_FIFO, 3)
    assert thread_policy()[0] == os.SCHED_OTHER
    assert realtime.set_threads_fifo(0, [threading.get_native_id()]) == (0, '')


def test_refused_fifo_is_reported_and_scheduling_stays_normal(monkeypatch):
    def refuse(*_):
        raise PermissionError(1, 'Operation not permitted')
    monkeypatch.setattr(realtime.os, 'sched_setscheduler', refuse)
    st, pol = in_thread(lambda: (configure_thread(50), thread_policy()))
    assert not st.realtime and not st.ok
    assert 'SCHED_FIFO priority 50 refused' in st.message
    assert pol[0] == os.SCHED_OTHER


def test_affinity_pins_the_thread_and_a_missing_cpu_is_reported():
    cpu = max(os.sched_getaffinity(0))
    st, aff = in_thread(lambda: (configure_thread(0, cpus=[cpu]), os.sched_getaffinity(0)))
    assert st.ok and st.cpus == (cpu,) and aff == {cpu}
    assert os.sched_getaffinity(0) != {cpu} or os.cpu_count() == 1  # main thread unpinned
    st = in_thread(lambda: configure_thread(0, cpus=[4096]))
    assert not st.ok and 'CPU affinity [4096] refused' in st.message
    assert set(st.cpus) == os.sched_getaffinity(0)


def test_timer_slack_is_set_for_the_calling_thread():
    libc = ctypes.CDLL(None, use_errno=True)

    def run():
        st = configure_thread(0, timer_slack_ns=2000)
        return st, libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
    st, slack = in_thread(run)
    assert st.timer_slack_ns == 2000 and slack == 2000
    assert libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0) != 2000  # main thread unchanged


def test_sleeper_never_wakes_before_the_deadline():
    """How late it wakes is a figure of the machine's load (benchmarks/bench_streamer.py);
    that it never wakes early is exact."""
    s = DeadlineSleeper()
    for _ in range(5):
        deadline = time.monotonic() + 0.01
        assert s.sleep_until(deadline) is False
        assert time.monotonic() >= deadline - 1e-6
    assert s.sleep_until(time.monotonic() - 1.0) is False  # past deadline: returns at once


def test_sleeper_does_not_sleep_for_a_past_deadline():
    """A deadline already passed (a late tick) returns without blocking: the clock is a fake
    one far beyond the deadline, and a blocking wait would use the real time-out."""
    s = DeadlineSleeper(clock=lambda: 1e9)
    s._wake = _NoBlockLock()
    assert s.sleep_until(1.0) is False


class _NoBlockLock:
    """Stands in for the sleeper's wake lock: any blocking acquire is a test failure."""

    def acquire(self, blocking=True, timeout=-1):
        assert not blocking, f'blocking acquire (timeout {timeout})'
        return False


def test_sleeper_spin_ends_exactly_after_the_deadline():
    s = DeadlineSleeper(spin=0.002)
    deadline = time.monotonic() + 0.005
    assert s.sleep_until(deadline) is False
    assert time.monotonic() >= deadline


def test_wake_ends_the_current_sleep_early():
    s = DeadlineSleeper()
    t = threading.Timer(0.05, s.wake)
    t.start()
    # True only when woken (a sleep that ran to its deadline returns False); the deadline is
    # far enough that a loaded machine still wakes it first
    assert s.sleep_until(time.monotonic() + 120.0) is True
    t.join()
    # a wake before the sleep ends the next sleep at once; several wakes count once
    s.wake()
    s.wake()
    assert s.sleep_until(time.monotonic() + 5.0) is True
    assert s.sleep_until(time.monotonic() + 0.01) is False


def test_realtime_sleeper_never_spins_and_bad_spin_is_refused():
    assert DeadlineSleeper(spin=0.001, realtime=True).spin == 0.0
    assert DeadlineSleeper(spin=0.001).spin == 0.001
    with pytest.raises(ValueError, match='spin: expected a value in'):
        DeadlineSleeper(spin=-0.1)
