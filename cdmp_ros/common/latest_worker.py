"""A latest-request-wins worker thread: slow work off the executor (and tick) threads.

:class:`LatestWorker` runs one request at a time. A request submitted while another waits
replaces it (latest wins): :meth:`LatestWorker.submit` returns the replaced request, so the
caller reports it (the streamer rejects it on ``/diagnostics`` with the reason ``superseded``,
the adapter counts it as ``requests_dropped``); it is never worked on. A running request is
never interrupted by a newer one; only :meth:`LatestWorker.stop` (node shutdown) ends the
thread, and long work may poll :meth:`LatestWorker.stopping` to cancel itself. A result
finished while a newer request already waits is *stale* (:meth:`LatestWorker._finished`
receives the flag). ``work`` may raise anything: ``fail(request, exc)`` turns the exception
into a result and the thread goes on.

With ``key`` (a function of the request), requests of different keys wait in separate slots
and the latest wins per key: the streamer prepares ``primitive`` and ``adapted_primitive`` this
way, because a restarted streamer receives both latched messages at once and needs both
(:mod:`cdmp_ros.core.streaming.selection`). Slots are served oldest first.

Results are collected with :meth:`LatestWorker.take` (from the executor or the tick thread);
``notify()`` (e.g. a ROS guard condition's ``trigger``) is called after each result so the
executor does not poll. No ROS call is made from the worker thread.

Used by the adapter's solver (:class:`cdmp_ros.core.adaptation.jobs.SolveWorker`) and the
streamer's primitive parsing (``StreamerNode.worker``). The learner's ``~/improve`` run
(:class:`cdmp_ros.ros.learner_improve.ImproveWorker`) is not a latest-wins queue: it is one
long run per service call, refused (not replaced) while another runs, and reports progress.
"""
import threading
from typing import Callable, Dict, Generic, Hashable, List, Optional, TypeVar

Request = TypeVar('Request')
Result = TypeVar('Result')


class LatestWorker(threading.Thread, Generic[Request, Result]):
    """Latest-request-wins worker thread (see the module docstring).

    Parameters
    ----------
    work : callable
        ``work(request) -> result``, run in this thread.
    fail : callable
        ``fail(request, exc) -> result`` for an exception raised by ``work``.
    name : str
        Thread name.
    notify : callable, optional
        Called (from this thread) after each result is queued; an exception it raises (a
        guard condition destroyed at shutdown) ends the thread.
    key : callable, optional
        ``key(request)``: requests of different keys do not replace each other (default: one
        slot for all).

    Attributes
    ----------
    counts : dict
        ``received``, ``superseded`` (replaced while waiting), ``done`` and ``stale``.
    busy : bool
        True while a request is being worked on.
    """

    def __init__(self, work: Callable[[Request], Result],
                 fail: Callable[[Request, Exception], Result], name: str,
                 notify: Optional[Callable[[], None]] = None,
                 key: Optional[Callable[[Request], Hashable]] = None):
        super().__init__(name=name, daemon=True)
        self._key = key if key is not None else (lambda request: None)
        self._work = work
        self._fail = fail
        self._notify = notify
        self._cv = threading.Condition()
        self._pending: Dict[Hashable, Request] = {}  # key -> the newest waiting request
        self._results: List[Result] = []
        self._stop_event = threading.Event()  # read without the lock by running work
        self.busy = False
        self.counts: Dict[str, int] = {'received': 0, 'superseded': 0, 'done': 0, 'stale': 0}

    def submit(self, request: Request) -> Optional[Request]:
        """Queue ``request``; returns the waiting request it replaced (never worked on), or
        None."""
        with self._cv:
            self.counts['received'] += 1
            self._accepted(request, self.counts['received'])
            k = self._key(request)
            replaced = self._pending.pop(k, None)
            self._pending[k] = request  # at the end: slots are served oldest first
            if replaced is not None:
                self.counts['superseded'] += 1
            self._cv.notify()
        return replaced

    def take(self) -> List[Result]:
        """The results finished since the last call, oldest first."""
        if not self._results:  # the common case, without the lock (the tick polls it)
            return []
        with self._cv:
            out, self._results = self._results, []
        return out

    def stop(self) -> None:
        """Stop the thread: a waiting request is dropped, running work ends when it polls
        :meth:`stopping` (or when it returns); join the thread afterwards."""
        self._stop_event.set()
        with self._cv:
            self._cv.notify()

    def has_pending(self) -> bool:
        """True while a request waits (read without the lock: a hint for running work that
        gives way to newer requests, such as the adapter's refinements)."""
        return bool(self._pending)

    def stopping(self) -> bool:
        """True once :meth:`stop` was called (the ``should_stop`` of long work)."""
        return self._stop_event.is_set()

    def run(self) -> None:
        stopping = self._stop_event.is_set
        while True:
            with self._cv:
                while not self._pending and not stopping():
                    self._cv.wait()
                if stopping():
                    return
                k = next(iter(self._pending))
                request = self._pending.pop(k)
                self.busy = True
            try:
                result = self._work(request)
            except Exception as exc:  # noqa: BLE001 -- the worker must survive anything
                result = self._fail(request, exc)
            with self._cv:
                self.busy = False
                if stopping():  # the node is shutting down: nobody takes results
                    return
                stale = k in self._pending
                self.counts['done'] += 1
                self.counts['stale'] += stale
                self._results.append(self._finished(request, result, stale))
            if self._notify is not None:
                try:
                    self._notify()
                except Exception:  # noqa: BLE001 -- guard condition destroyed at shutdown
                    return

    def _accepted(self, request: Request, number: int) -> None:
        """Hook (under the lock): ``request`` is the ``number``-th one received."""

    def _finished(self, request: Request, result: Result, stale: bool) -> Result:
        """Hook (under the lock): the result as it is queued for :meth:`take`."""
        return result
