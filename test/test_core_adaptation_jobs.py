"""The adapter's solver thread (cdmp_ros.core.adaptation.jobs.SolveWorker), without ROS: latest
request wins, a running solve is not interrupted, its result is marked stale when a newer
request waits, a failing solve becomes a 'rejected' result and the thread survives;
refinements are not counted among the requests; a refinement a newer request cancels says
where it was, and the node's next refinement continues it (Suspensions)."""
import threading

import numpy as np

from cdmp_ros.core.adaptation.jobs import Job, JobResult, SolveWorker


def _job(name, refine_kl=None):
    return Job(request=None, config=None, node_config=None, trigger=name, trigger_stamp_ns=0,
               received=0.0, refine_kl=refine_kl)


def test_latest_request_wins_and_stale_results_are_marked():
    release = threading.Event()
    started = threading.Event()
    notified = threading.Semaphore(0)

    def solve(job):
        started.set()
        if job.trigger == 'first':
            assert release.wait(30.0)
        if job.trigger == 'boom':
            raise RuntimeError('solver exploded')
        return JobResult(job, 'converged', 0.0)

    w = SolveWorker(solve, notified.release)
    w.start()
    try:
        w.submit(_job('first'))
        assert started.wait(30.0)          # 'first' is running
        w.submit(_job('second'))          # waiting ...
        w.submit(_job('third'))           # ... replaced: 'second' is dropped
        assert w.summary()['solver_busy']
        release.set()
        assert notified.acquire(timeout=30.0) and notified.acquire(timeout=30.0)
        results = w.take()
        assert [(r.job.trigger, r.stale) for r in results] == [('first', True),
                                                               ('third', False)]
        assert [r.job.id for r in results] == [1, 3]
        w.submit(_job('boom'))
        assert notified.acquire(timeout=30.0)
        (bad,) = w.take()
        assert bad.outcome == 'rejected' and 'solver exploded' in bad.error
        assert bad.error_topic == 'boom'
        w.submit(_job('after'))           # the thread survived
        assert notified.acquire(timeout=30.0)
        assert [r.outcome for r in w.take()] == ['converged']
        c = w.summary()
        assert (c['requests_received'], c['requests_dropped'], c['requests_stale'],
                c['requests_solved']) == (5, 1, 1, 4)
        # refinements: one solved, one replaced while waiting (behind a running 'first')
        w.submit(_job('refine', 1.0))
        assert notified.acquire(timeout=30.0)
        assert [r.job.refine_kl for r in w.take()] == [1.0]
        release.clear()
        started.clear()
        w.submit(_job('first'))
        assert started.wait(30.0)
        assert w.submit(_job('refine', 2.0)) is None
        assert w.submit(_job('request')).refine_kl == 2.0     # the waiting refinement gives way
        release.set()
        assert notified.acquire(timeout=30.0) and notified.acquire(timeout=30.0)
        assert [r.job.trigger for r in w.take()] == ['first', 'request']
        c = w.summary()
        assert (c['requests_received'], c['requests_dropped'], c['requests_stale'],
                c['requests_solved']) == (7, 1, 2, 6)
        assert w.counts['received'] == 9 and w.counts['superseded'] == 2
    finally:
        w.stop()
        w.join(5.0)
    assert not w.is_alive()


def test_a_cancelled_refinement_says_where_it_was_and_resumes(chain, prior):
    """solve_job: a refinement that a newer request cancels returns where it was
    (``JobResult.suspended``); the node's next refinement job carries it and continues the
    solve on the newer request (cdmp_ros.core.adaptation.warm, resumed refinements)."""
    from cdmp_ros.core.adaptation.config import AdapterConfig, AdaptRequestConfig
    from cdmp_ros.core.adaptation.requests import AdaptRequest, ee_path
    from cdmp_ros.core.adaptation.warm import WarmStarts
    from cdmp_ros.core.kinematics import Sphere
    from cdmp_ros.core.adaptation.jobs import solve_job
    cfg = AdaptRequestConfig(n_steps=25, alpha=0.99, verification_samples=1000)
    centre = ee_path(chain, prior.mean([0.5]))[0]

    def job(dy, refine_kl=None, resume=None):
        req = AdaptRequest(prior, (Sphere(tuple(centre + [0.0, dy, 0.0]), 0.05),),
                           continues=True)
        return Job(req, cfg, AdapterConfig(), 'obstacles', 0, 0.0, refine_kl=refine_kl,
                   refine_resume=resume)
    ws = WarmStarts()
    assert solve_job(job(0.0), chain, warm=ws).outcome == 'converged'
    assert solve_job(job(0.005), chain, warm=ws).result.report.start == 'warm'
    polls = iter(range(10 ** 6))
    res = solve_job(job(0.005, 1e6), chain, lambda: next(polls) >= 5, ws)
    assert res.outcome == 'cancelled' and res.suspended is not None
    assert (res.suspended.n_evaluations, res.suspended.n_requests) == (5, 1)
    assert solve_job(job(0.01), chain, warm=ws).result.report.start == 'warm'
    out = solve_job(job(0.01, 1e6, res.suspended), chain, warm=ws)
    assert out.outcome == 'converged' and out.text is not None
    assert 'resumed on each newer one' in out.result.report.start_note


def test_the_node_resumes_only_the_refinement_a_newer_request_suspended():
    """Suspensions (the adapter node's bookkeeping): a refinement cancelled with a state is
    held for its primitive; the next refinement of that primitive continues it; an ended
    refinement, a published cold solve or refinement, an outdated result or another primitive
    drop it or do not get it; a published warm solve keeps it."""
    from types import SimpleNamespace
    from cdmp_ros.core.adaptation.config import SolverState
    from cdmp_ros.core.adaptation.warm import Suspended
    from cdmp_ros.core.adaptation.jobs import Suspensions

    def job(primitive_id=1, refine_kl=None):
        j = _job('obstacles', refine_kl)
        j.primitive_id = primitive_id
        return j

    def result(j, outcome, suspended=None, start='warm'):
        res = JobResult(j, outcome, 0.0, suspended=suspended)
        res.result = SimpleNamespace(report=SimpleNamespace(start=start))
        return res
    sus = Suspended(SolverState(np.zeros(3), ()), 12, 1)
    s = Suspensions()
    assert s.resume_for(job()) is None
    s.refinement_ended(result(job(refine_kl=1.0), 'cancelled', sus), outdated=False)
    assert s.resume_for(job()) is sus and s.resume_for(job(primitive_id=2)) is None
    s.published(result(job(), 'converged', start='warm'))      # the newer request, warm
    assert s.resume_for(job()) is sus
    s.published(result(job(), 'converged', start='cold'))      # the chain restarted cold
    assert s.resume_for(job()) is None
    s.refinement_ended(result(job(refine_kl=1.0), 'cancelled', sus), outdated=False)
    s.published(result(job(refine_kl=1.0), 'converged', start='cold'))   # a refinement
    assert s.resume_for(job()) is None
    s.refinement_ended(result(job(refine_kl=1.0), 'cancelled', sus), outdated=True)
    assert s.resume_for(job()) is None                          # another primitive's
    s.refinement_ended(result(job(refine_kl=1.0), 'cancelled', sus), outdated=False)
    s.refinement_ended(result(job(refine_kl=1.0), 'kept_warm'), outdated=False)
    assert s.resume_for(job()) is None                          # it ended: nothing to resume
