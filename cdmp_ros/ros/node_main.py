"""The shared entry-point pattern of every cdmp_ros node (ROS 2 Jazzy).

:func:`run_node` ends every node the same way (``close()`` hook, ``destroy_node``,
``rclpy.try_shutdown``) and exits 0 on SIGINT / SIGTERM. The signals only set a flag (rclpy's
own signal handlers are not installed); the node keeps a valid context while its ``close()``
runs, so it can still take pending messages or publish a last diagnostic (the recorder drains
its subscriptions there). rclpy's handlers are left out for a second reason: in about 1 of
150 stops they crash the process (SIGSEGV) when the executor's shutdown destroys its SIGINT
guard condition while rclpy's signal thread still triggers it (reproduced with a bare node,
2026-12-07; the standard ``rclpy.spin`` pattern this module also offered until then).

Every node executable calls :func:`catch_stop_signals` first thing in its ``main()``, before
importing rclpy, numpy or the node class, so that a signal that arrives
while the process is still starting (imports, ``rclpy.init``, the node's constructor) is
remembered instead of raising ``KeyboardInterrupt`` (a traceback and exit code -2) or killing
the process (SIGTERM's default, exit code -15, no ``close()``). Such a signal lets the node
finish building, skips the spin loop and closes the node: exit code 0. A signal that arrives
before Python runs the entry module at all (the first ~0.1 s of the interpreter) still gets
Python's defaults; ``cdmp bringup`` counts that exit (-SIGINT) as a clean stop.

A stop is bounded even when something below the node hangs (a DDS teardown, a call into C
that does not return): :func:`catch_stop_signals` also starts a stop watchdog
(:func:`_watch_stop`) that sees the signal through Python's wakeup fd, and allows
:data:`STOP_LIMIT` until ``close()`` starts and again after it returns; a node that overruns
writes the stack of every thread to stderr and exits (:data:`EXIT_STUCK` if ``close()`` never
started). The watchdog is Python and needs the GIL; a main thread blocked in C while holding it
(the sim's hung stop: rclpy's teardown of an event waiting for a DDS mutex) would starve it, so
the same bounds plus :data:`BACKSTOP_MARGIN` are also armed in faulthandler's C thread
(``dump_traceback_later``: the stacks and exit code
:data:`~cdmp_ros.common.node_signals.EXIT_BACKSTOP`). SIGUSR1 writes the same stacks at any time
(``cdmp bringup`` sends it before SIGKILL).

The one such hang still seen is below rclpy: ``destroy_node`` of the process's last node
deletes the Fast DDS 2.14 participant, whose ``set_listener(nullptr)`` busy-waits, holding its
mutex, for a participant-discovery callback in flight (a peer that left at the same moment)
that needs that mutex to finish; the callback usually gets the mutex within a second, rarely
not within the bound. Such an exit is recognised from the node's stack dump by
:func:`cdmp_ros.common.node_signals.teardown_hang`; ``cdmp bringup`` names it.

Usage in ``cdmp_ros/nodes/<name>.py``::

    def main(args=None):
        catch_stop_signals()
        from cdmp_ros.ros.my_node import MyNode   # the heavy imports come after
        return run_node(MyNode, args)

A node may define ``close(self)`` (called once at shutdown) and ``done(self) -> bool`` (the
loop ends when it returns True, e.g. a player that finished its bag).  ``make_node`` errors
that are :class:`~cdmp_ros.core.errors.CdmpError` are logged and give exit code 2, as do
invalid ROS arguments (a malformed ``--params-file``), reported in one line.
"""
import faulthandler
import os
import signal
import sys
import threading
import time
from typing import Callable, List, Optional

from cdmp_ros.core.errors import CdmpError
from cdmp_ros.common.node_signals import DUMP_SIGNAL, STOP_SIGNALS

#: How often the spin loop checks the stop flag and ``done()`` (seconds).
SPIN_PERIOD = 0.05
#: Set by SIGINT / SIGTERM once :func:`catch_stop_signals` ran (one per process).
STOP = threading.Event()
#: [s] The stop watchdog's bound (:func:`_watch_stop`) on each of the two parts of a stop
#: that have no bound of their own: from the stop signal (or the end of the start-up, if later)
#: to the start of ``close()``, and from the end of ``close()`` to the exit. Twice the 2 s
#: shutdown target, well above what a whole stop takes (``benchmarks/bench_shutdown.py``).
#: ``close()`` itself bounds its own waits (the recorder's final drain,
#: the adapter's solver thread).
STOP_LIMIT = 4.0
#: Exit code of a node that the stop watchdog ended before its ``close()`` had started.
EXIT_STUCK = 3
#: Set when the node is built (:func:`run_node`), when its ``close()`` starts and when it
#: has returned.
BUILT = threading.Event()
CLOSING = threading.Event()
CLOSED = threading.Event()
_built_at = [0.0]
_exit_code = [0]     # run_node's exit code once close() has returned
_watchdog: List[threading.Thread] = []
#: [s] The GIL-free backstop (:func:`_arm_backstop`) acts this long after the Python watchdog
#: would have.
BACKSTOP_MARGIN = 1.0
_backstop_lock = threading.Lock()


def _on_stop_signal(signum, frame) -> None:
    STOP.set()


def _watch_stop(fd: int) -> None:
    """The stop watchdog (a daemon thread started by :func:`catch_stop_signals`).

    It reads the signal numbers that the C signal handler writes to ``fd`` (Python's wakeup
    fd), so it sees SIGINT / SIGTERM even while the main thread is blocked in C code and
    cannot run the Python handler. Then it allows :data:`STOP_LIMIT` from the later of the
    signal and the end of the node's start-up until ``close()`` starts, and again from the
    end of ``close()`` until the process exits. A node that overruns either writes the stack
    of every thread to stderr (where it was stuck) and exits at once: with
    :data:`EXIT_STUCK` if its ``close()`` never started (the main loop was stuck), with its
    own exit code if ``close()`` had returned (what hung is the middleware teardown:
    ``destroy_node``, the executor, ``rclpy.try_shutdown``)."""
    numbers = {int(sig) for sig in STOP_SIGNALS}
    while True:
        try:
            data = os.read(fd, 64)
        except OSError:
            return
        if not data:
            return
        if numbers.intersection(data):
            break
    signalled = time.monotonic()
    STOP.set()
    BUILT.wait()
    start = max(signalled, _built_at[0])
    with _backstop_lock:
        if not CLOSING.is_set():
            _arm_backstop(start + STOP_LIMIT - time.monotonic())
    if not CLOSING.wait(max(0.0, start + STOP_LIMIT - time.monotonic())):
        _stuck('its main loop did not end, close() never started', EXIT_STUCK)
    CLOSED.wait()
    time.sleep(STOP_LIMIT)
    _stuck('its close() had returned: the middleware teardown hangs', _exit_code[0])


def _arm_backstop(seconds: float) -> None:
    """Arm the GIL-free backstop of the stop watchdog: faulthandler's C thread writes every
    thread's stack and exits with code 1
    (:data:`~cdmp_ros.common.node_signals.EXIT_BACKSTOP`) ``seconds`` + :data:`BACKSTOP_MARGIN`
    from now unless :func:`_disarm_backstop` comes first.

    The Python watchdog needs the GIL to act; a main thread blocked in C while holding it (an
    rclpy teardown call waiting for a DDS mutex, as seen in the sim's stop) starves it, the
    backstop not."""
    faulthandler.dump_traceback_later(max(0.0, seconds) + BACKSTOP_MARGIN, exit=True,
                                      file=sys.stderr)


def _disarm_backstop() -> None:
    faulthandler.cancel_dump_traceback_later()


def _stuck(where: str, code: int) -> None:
    """The end of a node that overran the stop watchdog's bound (:func:`_watch_stop`)."""
    sys.stdout.flush()
    sys.stderr.write(f'[node_main] the node has not exited {STOP_LIMIT:g} s after the stop '
                     f'signal ({where}); the stack of every thread follows, then it exits\n')
    faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
    sys.stderr.flush()
    os._exit(code)


def catch_stop_signals() -> None:
    """Make SIGINT and SIGTERM set :data:`STOP` (idempotent; main thread only), and SIGUSR1
    write the Python stack of every thread to stderr (:data:`DUMP_SIGNAL`).

    Call it before the slow imports of a node executable: from then on a signal never
    interrupts the start-up, it ends the node once it is built (see the module docstring).
    """
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not _on_stop_signal:
            signal.signal(sig, _on_stop_signal)
    # written by the C signal handler: works while the main thread is blocked in C code
    faulthandler.register(DUMP_SIGNAL, file=sys.stderr, all_threads=True)
    if not _watchdog:
        r, w = os.pipe()
        os.set_blocking(w, False)
        signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        _watchdog.append(threading.Thread(target=_watch_stop, args=(r,), daemon=True,
                                          name='stop-watchdog'))
        _watchdog[0].start()


def stop_requested() -> bool:
    """True once SIGINT or SIGTERM arrived (after :func:`catch_stop_signals`); long start-up
    work in a node constructor may poll it to cut the start-up short."""
    return STOP.is_set()


def make_executor():
    """rclpy's EventsExecutor when this rclpy has it, else None (:func:`run_node` then uses a
    ``SingleThreadedExecutor``).

    The streamer and the sim spin with it: a timer callback costs far less CPU than with the
    SingleThreadedExecutor, whose wait-set rebuild per callback dominates.
    """
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return None
    return EventsExecutor()


def run_node(make_node: Callable[[], object], args: Optional[List[str]] = None,
             executor=None) -> int:
    """Initialise rclpy, build the node, spin until shutdown, clean up; return an exit code.

    Parameters
    ----------
    make_node : callable
        Builds the node after ``rclpy.init`` (typically the node class).
    args : list of str, optional
        Command-line arguments (``--ros-args ...``); default ``sys.argv``.
    executor : rclpy executor, optional
        Default: a ``SingleThreadedExecutor``.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    try:
        from rclpy._rclpy_pybind11 import RCLError
    except ImportError:  # pragma: no cover - other rclpy builds
        RCLError = RuntimeError

    try:
        catch_stop_signals()  # usually done already by the executable's main()
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RCLError as exc:  # e.g. a malformed --params-file or --ros-args
        print(f'error: invalid ROS arguments or parameter file: {exc}', file=sys.stderr)
        return 2
    node = None
    code = 0
    executor = executor if executor is not None else SingleThreadedExecutor()
    try:
        if STOP.is_set():  # stopped while importing or initialising: nothing to build
            return code
        node = make_node()
        _built_at[0] = time.monotonic()
        BUILT.set()
        executor.add_node(node)
        done = getattr(node, 'done', None)
        while not STOP.is_set() and rclpy.ok() and not (done is not None and done()):
            executor.spin_once(timeout_sec=SPIN_PERIOD)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # A signal can shut the context down between two waits of the executor; rcl then
        # refuses to build the next wait set.  That is a shutdown, not a failure.
        if rclpy.ok():
            raise
    except CdmpError as exc:
        print(f'[{getattr(node, "get_name", lambda: "node")()}] error: {exc}', file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            with _backstop_lock:    # close() bounds its own waits: no backstop meanwhile
                CLOSING.set()
                _disarm_backstop()
            if close is not None:
                try:
                    close()
                except CdmpError as exc:
                    print(f'error while closing: {exc}', file=sys.stderr)
                    code = code or 2
            code = code or int(getattr(node, 'exit_code', 0))
            _exit_code[0] = code
            CLOSED.set()
            if STOP.is_set():       # the teardown below is where the stop hung
                _arm_backstop(STOP_LIMIT)
            executor.remove_node(node)
        # The executor lets go of the node's entities before the node destroys them. Reversed,
        # rclpy's EventsExecutor holds every entity "in use" until its shutdown, so the DDS
        # entities are deleted from inside that shutdown's callback teardown (the stack of the
        # hung stops of the sim and the streamer: an event's __exit__ under
        # executor.shutdown()); in this order they are deleted by destroy_node() with no
        # executor callback left on them, as the SingleThreadedExecutor's nodes always did.
        executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
