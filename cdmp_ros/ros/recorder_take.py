"""The recorder's receive path: one thread drains every recorded subscription in batches.

Why not executor callbacks: with the rclpy executors every wake-up of the executor costs tens
of microseconds of Python (wait-set rebuild, callback dispatch), and an event-driven executor
wakes up as often as messages arrive, so at 20,000 messages/s the per-wake-up overhead, not
the take or the write, dominates the recorder's CPU.  Here a dedicated thread wakes up every
``period`` seconds (default 5 ms, i.e. 200 wake-ups/s whatever the message rate) and takes
everything queued in the DDS readers with ``take_message(raw=True)``, writing each serialized
message straight into the :class:`~cdmp_ros.bag.BagWriter`.  Messages wait at most ``period``
in the DDS reader's history (depth ``queue_depth`` per topic, ~100 messages at 20 kHz), with no
per-message queue.  The executor thread still registers topics it discovers while this thread
writes; the :class:`~cdmp_ros.bag.BagWriter`'s lock keeps the two apart.  The subscriptions
belong to a callback group the executor never waits on (:class:`ThreadTakenGroup`), so the
executor does not compete for their messages. The same pieces (:class:`ThreadTakenGroup`,
:func:`never_called`, :func:`take_newest`) serve the polled subscriptions of
:meth:`cdmp_ros.ros.input_gate.InputGate.subscribe_polled` (the adapter's ``joint_states``)
and the demo driver's ``joint_reference``: read now and then, newest message only.

Optionally (``priority`` > 0) the take thread, the main (executor) thread and the process's
Fast DDS receive threads (``dds.shm.*``, ``dds.udp.*``) run under SCHED_FIFO, through
:func:`cdmp_ros.common.realtime.configure_thread` for the calling thread and
``os.sched_setscheduler`` by thread id for the others; a refusal is logged, never fatal.  The
main thread is included because it shares the GIL with the take thread: a normal-priority
holder of the GIL descheduled by the machine's load would stall the real-time take thread.
"""
import os
import threading
import time
from typing import Callable, List, Optional, Tuple

from rclpy.callback_groups import CallbackGroup

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.common.realtime import configure_thread

#: Prefixes of the Fast DDS receive threads' names (Fast DDS >= 2.13 names its threads).
DDS_RECEIVE_THREADS = ('dds.shm.', 'dds.udp.')


class ThreadTakenGroup(CallbackGroup):
    """Callback group of subscriptions that no executor waits on (a thread takes them)."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def never_called(_msg) -> None:  # pragma: no cover - ThreadTakenGroup is never executed
    """The callback of a subscription in a :class:`ThreadTakenGroup`."""
    raise RuntimeError('a thread-taken subscription was executed by an executor')


def dds_receive_threads() -> List[int]:
    """Thread ids of this process's Fast DDS receive threads."""
    tids = []
    for tid in os.listdir('/proc/self/task'):
        try:
            with open(f'/proc/self/task/{tid}/comm') as f:
                name = f.read().strip()
        except OSError:
            continue
        if name.startswith(DDS_RECEIVE_THREADS):
            tids.append(int(tid))
    return tids


def set_fifo(tids: List[int], priority: int) -> str:
    """SCHED_FIFO ``priority`` for the given thread ids; returns '' or what was refused."""
    refused = []
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            refused.append(f'{tid} ({exc.strerror})')
    return f'SCHED_FIFO refused for DDS threads {", ".join(refused)}' if refused else ''


def write_taken(write: Callable, topic: str, data: bytes, info: dict) -> None:
    """``write(topic, data, log_time, publish_time)`` of one taken raw message: log time = its
    receive time (now if the middleware gives none), publish time = its source time (else the
    log time)."""
    recv = info.get('received_timestamp') or time.time_ns()
    write(topic, data, recv, info.get('source_timestamp') or recv)


def to_monotonic(system_ns: int) -> float:
    """A past system-clock time [ns] (a taken message's ``received_timestamp``) in
    ``time.monotonic()`` seconds."""
    return time.monotonic() - max(0, time.time_ns() - system_ns) * 1e-9


def drain_subscription(topic: str, sub, write: Callable) -> int:
    """Take every message queued in raw subscription ``sub`` of ``topic`` and pass each to
    :func:`write_taken`; returns the count."""
    handle = sub.handle
    take = handle.take_message
    msg_type = sub.msg_type
    n = 0
    with handle:
        while True:
            taken = take(msg_type, True)
            if taken is None:
                return n
            write_taken(write, topic, taken[0], taken[1])
            n += 1


def take_newest(sub, max_count: int):
    """The newest ``(data, info)`` queued in raw subscription ``sub`` (None if none), taking
    at most ``max_count`` messages (bounded while a publisher keeps sending); returns
    ``(newest, n_taken)``. For a subscription in a :class:`ThreadTakenGroup` that a node
    reads now and then and of which only the latest message matters."""
    handle = sub.handle
    take = handle.take_message
    msg_type = sub.msg_type
    newest, n = None, 0
    with handle:
        while n < max_count:
            taken = take(msg_type, True)
            if taken is None:
                break
            newest, n = taken, n + 1
    return newest, n


class TakeThread:
    """Drain raw subscriptions into a bag writer every ``period`` seconds.

    Parameters
    ----------
    writer : cdmp_ros.bag.BagWriter
        Messages are written by this thread while it runs (and by :meth:`drain` after
        :meth:`stop`); topics are added by the executor thread (the writer locks).
    period : float
        Seconds between two drains (> 0).
    priority : int
        SCHED_FIFO priority of this thread (and of the DDS receive threads if
        ``realtime_dds``); 0 = normal.
    realtime_dds : bool
        Also put the process's Fast DDS receive threads under SCHED_FIFO ``priority``.
    log : callable
        ``log(level, text)`` with level ``'info'`` or ``'warning'``.
    """

    def __init__(self, writer, period: float, priority: int = 0, realtime_dds: bool = True,
                 log: Callable[[str, str], None] = lambda level, text: None):
        if not period > 0:
            raise ValidationError(f'period: expected > 0 s, got {period!r}')
        self.writer = writer
        self.period = float(period)
        self.priority = int(priority)
        self.realtime_dds = bool(realtime_dds)
        self.log = log
        self.error: Optional[BaseException] = None
        self._subs: List[Tuple[str, object]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='recorder_take', daemon=True)

    def add(self, topic: str, sub) -> None:
        """Start draining ``sub`` (a raw subscription of ``topic``); any thread."""
        self._subs = self._subs + [(topic, sub)]  # replace, never mutate: the thread iterates

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> bool:
        """Stop the thread and wait for it (up to 10 s); True when it ended (the caller then
        drains once more; never while it runs: two drains of one reader reorder messages)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)
        return not self._thread.is_alive()

    def drain(self) -> int:
        """Take and write every queued message of every subscription; returns the count."""
        write = self.writer.write
        return sum(drain_subscription(topic, sub, write) for topic, sub in self._subs)

    def _run(self) -> None:
        if self.priority > 0:
            status = configure_thread(self.priority, timer_slack_ns=None)
            # the main (executor) thread too: it takes the GIL for discovery and timers, and a
            # normal-priority GIL holder descheduled by the load would stall the real-time
            # take thread (priority inversion); it never wakes per message
            problems = [status.message,
                        set_fifo([threading.main_thread().native_id], self.priority)]
            if self.realtime_dds:
                problems.append(set_fifo(dds_receive_threads(), self.priority))
            problems = [p for p in problems if p]
            if problems:
                self.log('warning', '; '.join(problems))
            else:
                self.log('info', f'take and main threads'
                                 f'{" and DDS receive threads" * self.realtime_dds} '
                                 f'under SCHED_FIFO priority {self.priority}')
        writer = self.writer
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                if not self.drain() and writer.flush_period:
                    writer.flush_if_due()
                next_t += self.period
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_t = time.monotonic()
        except Exception as exc:  # context shut down under the thread: the caller reports
            self.error = exc


#: Environment variables through which Fast DDS 2.x (rmw_fastrtps, Jazzy) and 3.x load an
#: XML profile file.
PROFILE_ENV = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
#: File name of the recorder's Fast DDS profile (in config/, installed to share/cdmp_ros/config).
PROFILE_FILE = 'recorder_fastdds.xml'
#: Set to a path to use another profile file, or to an empty string to load none.
PROFILE_OVERRIDE = 'CDMP_RECORDER_DDS_PROFILE'


def find_profile() -> Optional[str]:
    """The recorder's Fast DDS profile: the source tree's config/ or the installed share/."""
    here = os.path.dirname(os.path.abspath(__file__))
    candidates = [os.path.join(here, '..', '..', 'config', PROFILE_FILE)]
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(os.path.join(get_package_share_directory('cdmp_ros'), 'config',
                                       PROFILE_FILE))
    except Exception:  # not installed with an ament index: source tree only
        pass
    for path in candidates:
        if os.path.isfile(path):
            return os.path.normpath(path)
    return None


def apply_dds_profile(environ=os.environ) -> Optional[str]:
    """Make this process's Fast DDS participant load the recorder's profile.

    Must run before ``rclpy.init``.  Does nothing when the user already set a profile file
    (``FASTRTPS_DEFAULT_PROFILES_FILE`` / ``FASTDDS_DEFAULT_PROFILES_FILE``), when another
    rmw than Fast DDS is selected, or when ``CDMP_RECORDER_DDS_PROFILE`` is set to ''.
    Returns the profile path now in use by the recorder, or None.
    """
    if any(environ.get(k) for k in PROFILE_ENV):
        return None
    if environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') != 'rmw_fastrtps_cpp':
        return None
    path = environ.get(PROFILE_OVERRIDE)
    if path is None:
        path = find_profile()
    if not path:
        return None
    environ[PROFILE_ENV[0]] = path  # the variable Fast DDS 2.x (Jazzy) reads
    return path
