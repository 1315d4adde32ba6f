"""Real-time helpers for periodic threads (Linux): SCHED_FIFO, CPU affinity, timer slack,
and sleeping to absolute deadlines with an early wake-up.

Used by the streamer's tick thread (and reusable by any node with a fixed-rate loop, e.g. the
recorder's writer). The pattern is the one of ros2_control's controller manager: its main
loop thread *attempts* ``SCHED_FIFO`` (priority 50 by default) and CPU affinity through
``realtime_tools`` (``configure_sched_fifo``, ``set_thread_affinity``) and only warns when the
process lacks the permission (ros-controls/ros2_control, controller_manager/doc/userdoc.rst,
"Determinism"). Here everything is done with ``os.sched_setscheduler`` /
``os.sched_setaffinity`` on the *calling thread* (on Linux, pid 0 in these calls is the
calling thread, not the whole process) and never raises on a refusal: the caller gets a
:class:`RealtimeStatus` saying what was applied and why not.

Rules for a thread under SCHED_FIFO (it preempts every normal process of its CPU):

- never busy-wait or yield-spin (``sched_yield`` under SCHED_FIFO only yields to threads of
  the same priority, so a spin loop would starve the machine): :class:`DeadlineSleeper`
  forces its spin margin to zero when told the thread is real-time;
- keep the work per period short and bounded; the kernel's RT throttling
  (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default) is the last safety net, not a
  budget.

The helpers allocate nothing per period: :meth:`DeadlineSleeper.sleep_until` is a
``time.sleep`` (``clock_nanosleep`` on CLOCK_MONOTONIC in CPython >= 3.11) or a timed
``Lock.acquire`` (``sem_clockwait`` on CLOCK_MONOTONIC) when a wake-up lock is given.

Standard library only (:mod:`cdmp_ros.common`): a bad argument raises ``ValueError`` (the
nodes validate their parameters before, with :class:`~cdmp_ros.core.errors.ValidationError`).
"""
import os
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

from cdmp_ros.common.prctl import PR_SET_TIMERSLACK, prctl

#: Highest SCHED_FIFO priority accepted (Linux: 1..99).
MAX_PRIORITY = 99


@dataclass(frozen=True)
class RealtimeStatus:
    """What :func:`configure_thread` did for the calling thread.

    Attributes
    ----------
    priority : int
        The requested SCHED_FIFO priority (0 = normal scheduling requested).
    realtime : bool
        True when the thread now runs under SCHED_FIFO.
    cpus : tuple of int
        The CPUs the thread may run on after the call.
    timer_slack_ns : int or None
        The timer slack set for the thread, None when it could not be set.
    message : str
        Empty when everything requested was applied, else the reasons it was not (for a log
        warning).
    """

    priority: int
    realtime: bool
    cpus: Tuple[int, ...]
    timer_slack_ns: Optional[int]
    message: str

    @property
    def ok(self) -> bool:
        return not self.message


def check_priority(name: str, priority: int) -> int:
    """Validate a SCHED_FIFO priority ``0..99`` (0 = off); returns it as int."""
    if isinstance(priority, bool) or not isinstance(priority, int) or not (
            0 <= priority <= MAX_PRIORITY):
        raise ValueError(f'{name}: expected an int in [0, {MAX_PRIORITY}] '
                         f'(0 = normal scheduling), got {priority!r}')
    return priority


def set_timer_slack(ns: int) -> bool:
    """Set the calling thread's timer slack (how late the kernel may fire its timers) [ns].

    The default slack of normal threads is 50 us, which shifts every wake-up of a 1 kHz loop;
    threads under SCHED_FIFO have none. Returns False when prctl is unavailable or refuses.
    """
    return prctl(PR_SET_TIMERSLACK, max(1, int(ns)))


def configure_thread(priority: int = 0, cpus: Sequence[int] = (),
                     timer_slack_ns: Optional[int] = 1000) -> RealtimeStatus:
    """Real-time settings for the CALLING thread; never raises on a refusal.

    Parameters
    ----------
    priority : int
        SCHED_FIFO priority 1..99; 0 leaves the scheduling policy unchanged.
    cpus : sequence of int
        CPUs the thread is pinned to; empty = unchanged. CPUs that do not exist are refused
        (reported, affinity unchanged).
    timer_slack_ns : int, optional
        Timer slack of the thread [ns]; None leaves it unchanged.

    Returns
    -------
    RealtimeStatus
    """
    priority = check_priority('priority', priority)
    problems = []
    realtime = False
    if priority > 0:
        if not hasattr(os, 'sched_setscheduler'):
            problems.append('SCHED_FIFO is not available on this platform')
        else:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
                realtime = True
            except OSError as exc:  # EPERM without CAP_SYS_NICE / RLIMIT_RTPRIO
                problems.append(f'SCHED_FIFO priority {priority} refused ({exc.strerror}); '
                                'running with normal scheduling (needs CAP_SYS_NICE or an '
                                'rtprio limit, e.g. /etc/security/limits.conf)')
    if hasattr(os, 'sched_getaffinity'):
        if cpus:
            try:
                os.sched_setaffinity(0, [int(c) for c in cpus])
            except (OSError, ValueError) as exc:
                problems.append(f'CPU affinity {list(cpus)} refused ({exc}); unchanged')
        current = tuple(sorted(os.sched_getaffinity(0)))
    else:
        current = ()
        if cpus:
            problems.append('CPU affinity is not available on this platform')
    slack = None
    if timer_slack_ns is not None:
        slack = int(timer_slack_ns) if set_timer_slack(timer_slack_ns) else None
    return RealtimeStatus(priority, realtime, current, slack, '; '.join(problems))


def thread_policy(tid: int = 0) -> Tuple[int, int]:
    """``(policy, priority)`` of a thread (native id; 0 = the calling thread)."""
    return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority


def process_thread_ids() -> Tuple[int, ...]:
    """Native ids of every thread of this process (Linux ``/proc/self/task``; () elsewhere)."""
    try:
        return tuple(sorted(int(t) for t in os.listdir('/proc/self/task')))
    except OSError:
        return ()


def set_threads_fifo(priority: int, tids: Sequence[int]) -> Tuple[int, str]:
    """SCHED_FIFO ``priority`` for the given threads of this process (native ids).

    Used to lift the threads a real-time loop depends on (the executor thread that holds the
    GIL in callbacks, the middleware's receive/event threads) above the normal processes, so
    none of them is preempted while the loop waits for it (priority inversion through the
    GIL). Threads that ended meanwhile are skipped. Returns ``(number set, problems)``;
    never raises on a refusal.
    """
    priority = check_priority('priority', priority)
    if priority == 0:
        return 0, ''
    done, problems = 0, []
    for tid in tids:
        try:
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
            done += 1
        except ProcessLookupError:
            continue
        except (OSError, AttributeError) as exc:
            problems.append(f'thread {tid}: SCHED_FIFO {priority} refused ({exc})')
            break
    return done, '; '.join(problems)


def lift_other_threads(logger, priority: int, tick_thread, worker) -> str:
    """SCHED_FIFO for the threads a real-time tick depends on (the streamer's
    ``realtime_threads: all``): every thread of the process but the tick thread at
    ``priority - 1``, the (primitive) worker at 1. Returns the text appended to the log line."""
    own, wid = tick_thread.native_id, worker.native_id
    others = [t for t in process_thread_ids() if t not in (own, wid)]
    n, problems = set_threads_fifo(max(1, priority - 1), others)
    _, worker_problems = set_threads_fifo(1, [wid])
    problems = '; '.join(p for p in (problems, worker_problems) if p)
    if problems:
        logger.warning(f'tick thread: {problems}')
    return (f'; {n} other threads at SCHED_FIFO {max(1, priority - 1)}, primitive worker '
            f'at 1')


def report_scheduling(logger, status: Optional[RealtimeStatus], realtime_threads: str,
                      tick_thread, worker, spin: float) -> None:
    """Log a tick thread's scheduling (``status``: its RealtimeStatus, None if it did not
    start) and lift the other threads (:func:`lift_other_threads`) when it runs under
    SCHED_FIFO and ``realtime_threads`` is ``'all'``."""
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


def reset_thread() -> None:
    """Back to normal scheduling (SCHED_OTHER) for the calling thread, if permitted."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass


class DeadlineSleeper:
    """Sleep to absolute deadlines of a monotonic clock, optionally woken early.

    Parameters
    ----------
    spin : float
        Seconds before the deadline at which the sleep ends and a ``sched_yield`` loop takes
        over (tighter wake-up for a normal thread, at a CPU cost). Forced to 0 when
        ``realtime`` is True: a real-time thread must never spin.
    realtime : bool
        The calling thread runs under SCHED_FIFO.
    clock : callable
        Monotonic clock in seconds (``time.monotonic``).

    Notes
    -----
    :meth:`wake` (from any thread) ends the current or the next sleep at once; wake-ups are
    not counted (several wakes before a sleep end one sleep).
    """

    def __init__(self, spin: float = 0.0, realtime: bool = False,
                 clock: Callable[[], float] = time.monotonic):
        if not (0.0 <= spin < 1.0):
            raise ValueError(f'spin: expected a value in [0, 1) s, got {spin!r}')
        self.spin = 0.0 if realtime else float(spin)
        self.clock = clock
        self._wake = threading.Lock()
        self._wake.acquire()  # held = no wake-up pending

    def wake(self) -> None:
        """End the current (or the next) :meth:`sleep_until` early."""
        try:
            self._wake.release()
        except RuntimeError:  # already pending
            pass

    def sleep_until(self, deadline: float) -> bool:
        """Sleep until ``clock() >= deadline``; True when woken early by :meth:`wake`."""
        clock = self.clock
        remaining = deadline - self.spin - clock()
        if remaining > 0.0:
            if self._wake.acquire(timeout=remaining):
                return True
        elif self._wake.acquire(blocking=False):
            return True
        if self.spin:
            yield_ = os.sched_yield
            while clock() < deadline:
                yield_()
        return False
