"""The adapter's solver thread: constrained ProMP adaptations off the executor thread.

:class:`SolveWorker` (a :class:`~cdmp_ros.common.latest_worker.LatestWorker`) runs one request at
a time; ``submit`` replaces a request that has not started yet (latest request wins: the
replaced one is counted as *dropped*). A running solve is never interrupted by a newer request,
except a refinement (a cold solve of the last request after a warm one,
:mod:`cdmp_ros.core.adaptation.warm`), which a waiting request cancels (the result says where
it was, ``JobResult.suspended``: the node resumes it after that request);
:meth:`SolveWorker.stop` (node shutdown) cancels any solve, within one evaluation of the
Lagrangian (``solve_job(job, chain, should_stop)``). When a solve finishes while a newer
request is already waiting, its result is marked *stale*; the node still publishes a stale
result if it converged (a newer plan follows within one solve time, and publishing avoids
starving the output while obstacles keep moving), and says so on ``/diagnostics``. A result
computed for a primitive that has been replaced in the meantime is discarded by the node
(counted as ``requests_outdated``).

The worker calls ``notify()`` (a ROS guard condition's ``trigger``) after each result, so the
executor publishes it without polling. Everything computed here is plain data (JSON text,
numpy arrays); no ROS call is made from this thread.
"""
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional

import numpy as np

from cdmp_ros.core.adaptation.requests import (AdaptRequest, AdaptResult, ee_band, ee_path,
                                               promp_message, refine_request, run_request)
from cdmp_ros.core.adaptation.config import AdaptRequestConfig, AdapterConfig
from cdmp_ros.core.adaptation.verification import worker_cpu_seconds
from cdmp_ros.core.adaptation.warm import Suspended, WarmStarts, suspend
from cdmp_ros.core.errors import Cancelled, CdmpError, ConstraintSetError
from cdmp_ros.core.streaming.selection import Provenance
from cdmp_ros.common.latest_worker import LatestWorker


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
    source_sha1: str = ''         # SHA-1 of that primitive's JSON text (its primitive_id)
    id: int = 0
    generation: int = 0           # adapter ROS time [ns] at the request
    refine_kl: Optional[float] = None  # a refinement of a warm solve of this KL (else None)
    refine_resume: Optional[Suspended] = None  # the suspended refinement it continues


@dataclass
class JobResult:
    """What the executor publishes for a finished job."""

    job: Job
    outcome: str                          # converged / infeasible / unconverged / rejected;
    #                                       refinements also cancelled / kept_warm
    solve_time: float                     # [s], building + solving (wall clock)
    text: Optional[str] = None            # adapted primitive JSON (all outcomes but rejected)
    result: Optional[AdaptResult] = None
    path: Optional[np.ndarray] = None     # (n, 3) end-effector mean path
    band: Optional[tuple] = None          # (centres (k, 3), radii (k,))
    error: Optional[str] = None
    error_topic: Optional[str] = None
    stale: bool = False
    finished: float = 0.0
    solve_cpu: float = 0.0                # [s], CPU time of the solver thread and of the
    #                                       verification's worker threads
    suspended: Optional[Suspended] = None  # a cancelled refinement: where it was


def job_provenance(job: Job) -> Provenance:
    """What the streamer needs to pick the newest adaptation of its current primitive
    (:mod:`cdmp_ros.core.streaming.selection`)."""
    return Provenance(job.source_sha1, int(job.generation), job.trigger,
                      int(job.trigger_stamp_ns), bool(job.request.continues))


def solve_job(job: Job, chain, should_stop: Optional[Callable[[], bool]] = None,
              warm: Optional[WarmStarts] = None) -> JobResult:
    """Build, solve and serialise one job (runs in the worker thread); ``should_stop``
    cancels the solve (:class:`~cdmp_ros.core.errors.Cancelled`, reported as rejected);
    ``warm``: the warm starts of the worker's stream of jobs
    (:mod:`cdmp_ros.core.adaptation.warm`)."""
    t0, c0 = time.perf_counter(), time.thread_time() + worker_cpu_seconds()
    try:
        if job.refine_kl is not None:
            try:
                res = refine_request(job.request, chain, job.config, warm, job.refine_kl,
                                     should_stop, job.refine_resume)
            except Cancelled as exc:
                return JobResult(job, 'cancelled', time.perf_counter() - t0,
                                 suspended=suspend(exc, job.refine_resume))
            if res is None:
                return JobResult(job, 'kept_warm', time.perf_counter() - t0,
                                 solve_cpu=time.thread_time() + worker_cpu_seconds() - c0)
        else:
            res = run_request(job.request, chain, job.config, should_stop, warm)
    except ConstraintSetError as exc:
        return JobResult(job, 'rejected', time.perf_counter() - t0, error=str(exc),
                         error_topic='constraints')
    except CdmpError as exc:
        return JobResult(job, 'rejected', time.perf_counter() - t0, error=str(exc),
                         error_topic=job.trigger)
    t_solve, c_solve = time.perf_counter() - t0, time.thread_time() + worker_cpu_seconds() - c0
    adapted = res.adapted
    adapted.metadata = dict(job.request.prior.metadata or {})
    if job.request.limits is not None:  # the limits it was adapted within: the file's limits
        adapted.metadata['limits'] = {'lower': [float(v) for v in job.request.limits[0]],
                                      'upper': [float(v) for v in job.request.limits[1]]}
    report = res.report.as_dict()
    adapted.metadata['adaptation'] = report
    adapted.metadata['adapter'] = {
        'request_id': job.id, 'source_sha1': job.source_sha1, 'outcome': res.outcome,
        'obstacles_used': res.problem.obstacles_used,
        'obstacles_ignored': res.problem.obstacles_ignored, 'notes': res.problem.notes,
        **job_provenance(job).as_dict()}
    text = promp_message(adapted)
    nc = job.node_config
    path = ee_path(chain, adapted.mean(np.linspace(0.0, 1.0, nc.path_points)))
    band = None
    if nc.band_points:
        band = ee_band(adapted, chain, np.linspace(0.0, 1.0, nc.band_points), nc.band_sigma)
    return JobResult(job, res.outcome, t_solve, text=text, result=res, path=path, band=band,
                     solve_cpu=c_solve)


class SolveWorker(LatestWorker):
    """The adapter's latest-request-wins solver thread (see the module docstring): a
    :class:`~cdmp_ros.common.latest_worker.LatestWorker` of :class:`Job` -> :class:`JobResult`
    that numbers the jobs, marks stale results and time-stamps them.

    Parameters
    ----------
    solve : callable
        ``solve(job) -> JobResult``.
    notify : callable
        Called (from this thread) after each result is queued.
    """

    def __init__(self, solve: Callable[[Job], JobResult], notify: Callable[[], None]):
        super().__init__(solve, _failed, name='adapter-solver', notify=notify)
        # the refinements among ``counts`` (the node reports them apart)
        self._refinements = {'received': 0, 'superseded': 0, 'done': 0, 'stale': 0}

    def submit(self, job: Job) -> Optional[Job]:
        replaced = super().submit(job)
        if replaced is not None and replaced.refine_kl is not None:
            with self._cv:
                self._refinements['superseded'] += 1
        return replaced

    def _accepted(self, job: Job, number: int) -> None:
        job.id = number
        self._refinements['received'] += job.refine_kl is not None   # (under the lock)

    def _finished(self, job: Job, res: JobResult, stale: bool) -> JobResult:
        res.finished = time.monotonic()
        res.stale = stale
        if job.refine_kl is not None:   # (under the lock)
            self._refinements['done'] += 1
            self._refinements['stale'] += stale
        return res

    def summary(self) -> Dict[str, Any]:
        """The request counters (diagnostics names), refinements not included, and whether a
        solve (or a refinement) is running."""
        with self._cv:
            c = {k: v - self._refinements[k] for k, v in self.counts.items()}
            busy = self.busy
        return {'requests_received': c['received'], 'requests_dropped': c['superseded'],
                'requests_stale': c['stale'], 'requests_solved': c['done'],
                'solver_busy': busy}


class Suspensions:
    """Which suspended refinement the adapter's next refinement continues (the node's
    bookkeeping, in the executor thread; :mod:`cdmp_ros.core.adaptation.warm`, resumed
    refinements).

    A refinement that a newer request cancelled is held with the primitive it adapts; the
    refinement after that request's warm solve continues it. A refinement that ended (published,
    no lower KL, failed) or a cold solve that was published (the chain restarted cold) drops
    it, and so does a new primitive."""

    def __init__(self):
        self._held: Optional[tuple] = None   # (primitive id, Suspended)

    def refinement_ended(self, res: JobResult, outdated: bool) -> None:
        """A refinement's result arrived: hold where a cancelled one was, else drop."""
        self._held = ((res.job.primitive_id, res.suspended)
                      if res.suspended is not None and not outdated else None)

    def published(self, res: JobResult) -> None:
        """A converged result was published: a refinement or a cold solve drops the hold."""
        if res.job.refine_kl is not None or res.result.report.start == 'cold':
            self._held = None

    def resume_for(self, job: Job) -> Optional[Suspended]:
        """The suspended refinement a refinement of ``job``'s request continues, or None."""
        if self._held is not None and self._held[0] == job.primitive_id:
            return self._held[1]
        return None


def _failed(job: Job, exc: Exception) -> JobResult:
    """A solve that raised: a rejected result (the solver thread goes on)."""
    return JobResult(job, 'rejected', 0.0, error=f'adaptation failed: {exc!r}',
                     error_topic=job.trigger)


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
              backtracks=rep.n_backtracks,
              evaluations=rep.n_evaluations, start=rep.start,
              obstacles_used=res.result.problem.obstacles_used,
              obstacles_ignored=res.result.problem.obstacles_ignored)
    if rep.start_note:
        kv['start_note'] = rep.start_note
    for c in rep.constraints:
        kv[f'p.{c.name}'] = f'{c.probability:.6f} (alpha {c.alpha:g})'
    kv.update(verification_values(rep))
    return kv


def verification_values(rep) -> Dict[str, Any]:
    """Diagnostics key/values of a report's sampled verification (the figures of ``cdmp adapt
    --json``'s ``verification``): ``verification.n_samples``, ``.guarantee``, ``.holds``,
    ``.trajectory_violation``, ``.trajectory_violation_upper95`` and ``.detectable_excess``
    (the weakest constraint's: how many times its asked level a violation must be for the
    test to catch it with 95 % power), and per constraint ``v.<name>`` =
    ``per_step_max <f> trajectory <f> upper95 <f> detectable_excess <f>``."""
    ver = rep.verification
    if ver is None:
        return {}
    kv: Dict[str, Any] = {
        'verification.n_samples': ver.n_samples, 'verification.guarantee': ver.guarantee,
        'verification.holds': ver.holds,
        'verification.trajectory_violation': f'{ver.trajectory_violation:.6g}',
        'verification.trajectory_violation_upper95': f'{ver.trajectory_violation_upper95:.6g}',
        'verification.detectable_excess': f'{ver.detectable_excess:.3g}',
        'verification.time_ms': f'{ver.time_s * 1e3:.1f}'}
    for c in ver.constraints:
        kv[f'v.{c.name}'] = (f'per_step_max {c.per_step_max:.6g} trajectory '
                             f'{c.trajectory:.6g} upper95 {c.upper95:.6g} detectable_excess '
                             f'{c.detectable_excess:.3g}')
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
