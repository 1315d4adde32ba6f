"""The adapter's solver thread: constrained ProMP adaptations off the executor thread.

:class:`SolveWorker` runs one request at a time; ``submit`` replaces a request that has not
started yet (latest request wins: the replaced one is counted as *dropped*). A running solve is
never interrupted by a newer request; only :meth:`SolveWorker.stop` (node shutdown) cancels
it, within one evaluation of the Lagrangian (``solve_job(job, chain, worker.stopping)``).
When a solve finishes while a newer request is already waiting, its result is marked *stale*;
the node still publishes a stale result if it converged (a newer plan follows within one solve
time, and publishing avoids starving the output while obstacles keep moving), and says so on
``diagnostics``. A result computed for a primitive that has been replaced in the meantime is
discarded by the node (counted as ``requests_outdated``).

The worker calls ``notify()`` (a ROS guard condition's ``trigger``) after each result, so the
executor publishes it without polling. Everything computed here is plain data (JSON text,
numpy arrays); no ROS call is made from this thread.
"""
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional

import numpy as np

from cdmp_ros.core.adaptation.requests import (AdaptRequest, AdaptResult, ee_band, ee_path,
                                               promp_message, run_request)
from cdmp_ros.core.adaptation.config import AdaptRequestConfig, AdapterConfig
from cdmp_ros.core.errors import CdmpError, ConstraintSetError


@dataclass
class Job:
    """One adaptation request with its provenance."""

    request: AdaptRequest
    config: AdaptRequestConfig
    node_config: AdapterConfig
    trigger: str                  # topic whose message caused the request
    trigger_stamp_ns: int         # header stamp of that message (0 if none)
    received: float               # time.monotonic() of the triggering callback
    primitive_id: int = 0         # which received primitive the request adapts
    source_sha1: str = ''         # SHA-1 of that primitive's JSON text
    id: int = 0


@dataclass
class JobResult:
    """What the executor publishes for a finished job."""

    job: Job
    outcome: str                          # converged / infeasible / unconverged / rejected
    solve_time: float                     # [s], building + solving (wall clock)
    text: Optional[str] = None            # adapted primitive JSON (all outcomes but rejected)
    result: Optional[AdaptResult] = None
    path: Optional[np.ndarray] = None     # (n, 3) end-effector mean path
    band: Optional[tuple] = None          # (centres (k, 3), radii (k,))
    error: Optional[str] = None
    error_topic: Optional[str] = None
    stale: bool = False
    finished: float = 0.0
    solve_cpu: float = 0.0                # [s], CPU time of the solver thread (time.thread_time)


def solve_job(job: Job, chain, should_stop: Optional[Callable[[], bool]] = None) -> JobResult:
    """Build, solve and serialise one job (runs in the worker thread); ``should_stop``
    cancels the solve (:class:`~cdmp_ros.core.errors.Cancelled`, reported as rejected)."""
    t0, c0 = time.perf_counter(), time.thread_time()
    try:
        res = run_request(job.request, chain, job.config, should_stop)
    except ConstraintSetError as exc:
        return JobResult(job, 'rejected', time.perf_counter() - t0, error=str(exc),
                         error_topic='constraints')
    except CdmpError as exc:
        return JobResult(job, 'rejected', time.perf_counter() - t0, error=str(exc),
                         error_topic=job.trigger)
    t_solve, c_solve = time.perf_counter() - t0, time.thread_time() - c0
    adapted = res.adapted
    adapted.metadata = dict(job.request.prior.metadata or {})
    report = res.report.as_dict()
    adapted.metadata['adaptation'] = report
    adapted.metadata['adapter'] = {
        'request_id': job.id, 'trigger': job.trigger, 'source_sha1': job.source_sha1,
        'trigger_stamp_ns': int(job.trigger_stamp_ns), 'outcome': res.outcome,
        'obstacles_used': res.problem.obstacles_used,
        'obstacles_ignored': res.problem.obstacles_ignored, 'notes': res.problem.notes}
    text = promp_message(adapted)
    nc = job.node_config
    path = ee_path(chain, adapted.mean(np.linspace(0.0, 1.0, nc.path_points)))
    band = None
    if nc.band_points:
        band = ee_band(adapted, chain, np.linspace(0.0, 1.0, nc.band_points), nc.band_sigma)
    return JobResult(job, res.outcome, t_solve, text=text, result=res, path=path, band=band,
                     solve_cpu=c_solve)


class SolveWorker(threading.Thread):
    """Latest-request-wins solver thread (see the module docstring).

    Parameters
    ----------
    solve : callable
        ``solve(job) -> JobResult``.
    notify : callable
        Called (from this thread) after each result is queued.
    """

    def __init__(self, solve: Callable[[Job], JobResult], notify: Callable[[], None]):
        super().__init__(name='adapter-solver', daemon=True)
        self._solve = solve
        self._notify = notify
        self._cv = threading.Condition()
        self._pending: Optional[Job] = None
        self._results: List[JobResult] = []
        self._stopping = False
        self._stop_event = threading.Event()  # read without the lock by a running solve
        self.busy = False
        self.counts: Dict[str, int] = {'requests_received': 0, 'requests_dropped': 0,
                                       'requests_stale': 0, 'requests_solved': 0}

    def submit(self, job: Job) -> None:
        with self._cv:
            self.counts['requests_received'] += 1
            job.id = self.counts['requests_received']
            if self._pending is not None:
                self.counts['requests_dropped'] += 1   # coalesced: only the newest counts
            self._pending = job
            self._cv.notify()

    def take(self) -> List[JobResult]:
        with self._cv:
            out, self._results = self._results, []
        return out

    def stop(self) -> None:
        """Stop the thread: a waiting request is dropped, a running solve is cancelled (when
        the solve polls :meth:`stopping`); join the thread afterwards."""
        self._stop_event.set()
        with self._cv:
            self._stopping = True
            self._cv.notify()

    def stopping(self) -> bool:
        """True once :meth:`stop` was called (``should_stop`` of a running solve)."""
        return self._stop_event.is_set()

    def run(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                job, self._pending = self._pending, None
                self.busy = True
            try:
                res = self._solve(job)
            except Exception as exc:  # noqa: BLE001 -- the solver thread must survive anything
                res = JobResult(job, 'rejected', 0.0, error=f'adaptation failed: {exc!r}',
                                error_topic=job.trigger)
            res.finished = time.monotonic()
            with self._cv:
                self.busy = False
                if self._stopping:  # the node is shutting down: nobody takes results
                    return
                res.stale = self._pending is not None
                self.counts['requests_solved'] += 1
                if res.stale:
                    self.counts['requests_stale'] += 1
                self._results.append(res)
            try:
                self._notify()
            except Exception:  # noqa: BLE001 -- guard condition destroyed at shutdown
                return

    def summary(self) -> Dict[str, Any]:
        with self._cv:
            return dict(self.counts, solver_busy=self.busy)


def result_values(res: JobResult) -> Dict[str, Any]:
    """Diagnostics key/values of a solved job: outcome, solve_time_ms, kl, iterations and
    ``p.<constraint>`` = satisfaction probability (with its alpha) of every constraint."""
    job = res.job
    kv: Dict[str, Any] = {'outcome': res.outcome, 'solve_time_ms': f'{res.solve_time * 1e3:.1f}',
                          'solve_cpu_ms': f'{res.solve_cpu * 1e3:.1f}', 'trigger': job.trigger,
                          'request_id': job.id, 'stale': res.stale}
    if res.result is None:
        return kv
    rep = res.result.report
    kv.update(kl=f'{rep.kl:.6g}', iterations=rep.n_inner, outer_iterations=rep.n_outer,
              obstacles_used=res.result.problem.obstacles_used,
              obstacles_ignored=res.result.problem.obstacles_ignored)
    for c in rep.constraints:
        kv[f'p.{c.name}'] = f'{c.probability:.6f} (alpha {c.alpha:g})'
    kv.update(verification_values(rep))
    return kv


def verification_values(rep) -> Dict[str, Any]:
    """Diagnostics key/values of a report's sampled verification (the figures of ``cdmp adapt
    --json``'s ``verification``): ``verification.n_samples``, ``.guarantee``, ``.holds``,
    ``.trajectory_violation`` and ``.trajectory_violation_upper95``, and per constraint
    ``v.<name>`` = ``per_step_max <f> trajectory <f> upper95 <f>``."""
    ver = rep.verification
    if ver is None:
        return {}
    kv: Dict[str, Any] = {
        'verification.n_samples': ver.n_samples, 'verification.guarantee': ver.guarantee,
        'verification.holds': ver.holds,
        'verification.trajectory_violation': f'{ver.trajectory_violation:.6g}',
        'verification.trajectory_violation_upper95': f'{ver.trajectory_violation_upper95:.6g}',
        'verification.time_ms': f'{ver.time_s * 1e3:.1f}'}
    for c in ver.constraints:
        kv[f'v.{c.name}'] = (f'per_step_max {c.per_step_max:.6g} trajectory '
                             f'{c.trajectory:.6g} upper95 {c.upper95:.6g}')
    return kv


def violated(res: JobResult) -> List[str]:
    """``name P=... < alpha`` of every violated constraint of a solved job, then
    ``name sampled ...`` of every constraint its sampled verification does not confirm."""
    if res.result is None:
        return []
    rep = res.result.report
    out = [f'{c.name} P={c.probability:.4f} < {c.alpha:g}'
           for c in rep.constraints if not c.satisfied]
    if rep.verification is not None:
        out += [f'{c.name} sampled per-step max {c.per_step_max:.4g} (limit '
                f'{c.per_step_limit:.4g}), trajectory {c.trajectory:.4g} (upper95 '
                f'{c.upper95:.4g})' for c in rep.verification.constraints if not c.holds]
    return out
