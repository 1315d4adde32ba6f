"""The adapter's request policy, free of ROS: which input starts which adaptation, how the
results of the solver thread are judged, and when a warm solve is refined.

:class:`AdaptationSession` holds what the adapter knows (the primitive, the goal, the constraint
set), numbers the adaptations (generations), decides whether a request continues the running
motion or starts a new one, and turns every :class:`~cdmp_ros.core.adaptation.jobs.JobResult`
into a :class:`ResultAction`: what to publish, which state to report, which input to blame.
The adapter node (:mod:`cdmp_ros.ros.adapter_node`) is the glue around it, as the streamer node
is around :class:`~cdmp_ros.core.streaming.streamer.ReferenceStreamer`; the solver thread is
:class:`~cdmp_ros.core.adaptation.jobs.SolveWorker`.
"""
import dataclasses
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from cdmp_ros.core.adaptation.config import AdaptRequestConfig, AdapterConfig
from cdmp_ros.core.adaptation.jobs import Job, JobResult, Suspensions, result_values, violated
from cdmp_ros.core.adaptation.requests import (AdaptRequest, clip_goal, retarget_clipped,
                                               retarget_primitive_dict)
from cdmp_ros.core.streaming.selection import Provenance

#: Inputs whose adaptation continues the running motion (the streamer switches it in at its
#: phase) once a motion of the current primitive was published; the others start a motion.
CONTINUING_TRIGGERS = ('obstacles', 'constraints')

#: Levels of a reported state (the node maps them to diagnostic_msgs levels).
OK, WARN, ERROR = 'ok', 'warn', 'error'

#: The session's counters (diagnostics keys of the same names).
COUNTERS = ('published', 'outcome_converged', 'outcome_infeasible', 'outcome_unconverged',
            'outcome_rejected', 'requests_outdated', 'refinements_started',
            'refinements_published', 'refinements_kept_warm', 'refinements_cancelled',
            'refinements_failed', 'refinements_resumed')


@dataclass
class Trigger:
    """What an input asks of the node (:meth:`AdaptationSession.trigger`).

    ``action``: ``'wait'`` (no primitive yet: the input is stored), ``'report'`` (a DMP/CDMP
    primitive: only ``message`` to report, with ``retargeted`` the primitive dict to show),
    ``'retarget'`` (a DMP/CDMP goal: call :meth:`AdaptationSession.retarget`) or ``'solve'``
    (submit ``job`` to the solver thread)."""

    action: str
    message: str = ''
    job: Optional[Job] = None
    retargeted: Optional[dict] = None


@dataclass
class ResultAction:
    """What the node does with a result (:meth:`AdaptationSession.result`).

    ``publish``: the adapted primitive's JSON to publish (None: nothing), with ``markers``
    (end-effector mean path, band); ``level`` / ``message`` / ``values``: the state to report
    (``level`` None: the state stays); ``reject``: (topic, error) to count as a rejected input;
    ``warning``: a line to log; ``timings``: (name, seconds) to record; ``refine``: call
    :meth:`AdaptationSession.refinement` after publishing; ``report``: publish diagnostics."""

    publish: Optional[str] = None
    markers: Optional[Tuple[Any, Any]] = None
    level: Optional[str] = None
    message: str = ''
    values: Dict[str, Any] = field(default_factory=dict)
    reject: Optional[Tuple[str, str]] = None
    warning: Optional[str] = None
    timings: List[Tuple[str, float]] = field(default_factory=list)
    refine: bool = False
    report: bool = True


class AdaptationSession:
    """The adapter's state and request policy (module docstring).

    Parameters
    ----------
    joint_names : sequence of str
        The robot's joints, in the order of every array here.
    """

    def __init__(self, joint_names: Sequence[str]):
        self.joint_names = list(joint_names)
        #: dict: kind, d (validated dict), prim, perm, sha1, limits (lower, upper)
        self.primitive: Optional[Dict[str, Any]] = None
        self.primitive_id = 0
        self.generation = 0            # of the last adaptation (ROS time [ns] at the request)
        #: the refinement a newer request cancelled: the next refinement continues it
        self.suspensions = Suspensions()
        # continuing requests need a motion to continue: the primitive_id whose motion-starting
        # (phase-0 conditioned) adaptation was published, and the generation of the newest
        # motion-starting request still to be published (0: none)
        self.motion_of = 0
        self.restart_generation = 0
        self.constraint_doc: Optional[dict] = None
        #: the balls of the avoided links' collision geometry (None: their frame origins),
        #: set by the node from the robot model (:func:`~cdmp_ros.core.adaptation.requests.
        #: link_balls`); every request carries them
        self.link_balls = None
        self.goal_y: Optional[np.ndarray] = None
        self.goal_point: Optional[np.ndarray] = None
        self.counts: Dict[str, int] = {k: 0 for k in COUNTERS}

    # -- inputs ------------------------------------------------------------------------------
    def set_primitive(self, prim: Dict[str, Any]) -> None:
        """A new primitive (validated, with its ``limits``): a new task, the goal is cleared;
        obstacles and constraints are kept."""
        self.primitive_id += 1
        self.primitive = prim
        self.goal_y = self.goal_point = None

    def set_constraints(self, doc: Optional[dict]) -> None:
        self.constraint_doc = doc

    def set_goal(self, g: np.ndarray, point: Optional[np.ndarray], lower: np.ndarray,
                 upper: np.ndarray, margin: float) -> List[int]:
        """Store a goal clipped into the limits the primitive is adapted within (the robot's
        ``lower`` / ``upper`` before the first primitive) with the CDMP ``margin``; returns the
        joints that were clipped."""
        p = self.primitive
        lo, hi = p['limits'] if p is not None else (lower, upper)
        gc, clipped = clip_goal(g, lo, hi, margin)
        self.goal_y, self.goal_point = gc, point
        return list(clipped)

    @property
    def is_promp(self) -> bool:
        return self.primitive is not None and self.primitive['kind'] == 'promp'

    def next_generation(self, now_ns: int) -> int:
        """Generation of a new adaptation: the ROS time ``now_ns``, strictly increasing (also
        across adapter restarts, as the clock moves on)."""
        self.generation = max(int(now_ns), self.generation + 1)
        return self.generation

    # -- requests ----------------------------------------------------------------------------
    def trigger(self, topic: str, stamp_ns: int, obstacles: Sequence, start: Optional[np.ndarray],
                config: AdaptRequestConfig, node_config: AdapterConfig, now_ns: int,
                received: float) -> Trigger:
        """What an input on ``topic`` (header stamp ``stamp_ns``) asks for, with the current
        ``obstacles``, the measured ``start`` (None: stale or none), the configurations, the
        ROS time ``now_ns`` and the monotonic time ``received`` of the callback."""
        p = self.primitive
        if p is None:
            return Trigger('wait', f'waiting for a primitive ({topic} stored)')
        if p['kind'] != 'promp':
            if topic == 'constraints':
                return Trigger('report', f'constraint set stored: it applies to ProMPs, the '
                                         f'primitive is a {p["kind"]}')
            if topic == 'goal' and not node_config.retarget_dmp_on_goal:
                return Trigger('report', f'goal left to the streamer ({p["kind"]}, '
                                         f'retarget_dmp_on_goal false)',
                               retargeted=retarget_primitive_dict(p['d'], self.goal_y,
                                                                  self.joint_names))
            return Trigger('retarget')
        # obstacles and constraints reshape the running motion (the streamer continues it at
        # its phase), once a motion of this primitive was published and no motion-starting
        # request waits (it may be superseded by this one); a new primitive or goal starts a
        # motion from the current state
        continues = (topic in CONTINUING_TRIGGERS and self.motion_of == self.primitive_id
                     and not self.restart_generation)
        generation = self.next_generation(now_ns)
        if not continues:
            self.restart_generation = generation
        req = AdaptRequest(p['prim'], tuple(obstacles), self.constraint_doc, self.goal_y, start,
                           p['limits'], continues=continues, link_balls=self.link_balls)
        return Trigger('solve', job=Job(req, config, node_config, topic, stamp_ns, received,
                                        self.primitive_id, p['sha1'], generation=generation))

    def replaced(self, job: Optional[Job]) -> None:
        """The solver thread dropped ``job`` (not started) for a newer one: a refinement that
        had not started gives way, counted as cancelled."""
        if job is not None and job.refine_kl is not None:
            self.counts['refinements_cancelled'] += 1

    def retarget(self, topic: str, stamp_ns: int, margin: float,
                 now_ns: int) -> Tuple[Optional[dict], List[int]]:
        """DMP / CDMP with a goal: the primitive dict with the new goal (same weights) and its
        provenance, and the joints whose goal was clipped into the primitive's limits; (None,
        []) without a goal."""
        if self.goal_y is None:
            return None, []
        p = self.primitive
        d, clipped = retarget_clipped(p['d'], self.goal_y, self.joint_names, margin)
        d['metadata'] = dict(d.get('metadata') or {})
        d['metadata']['adapter'] = {'outcome': 'retargeted', 'source_sha1': p['sha1'],
                                    **Provenance(p['sha1'], self.next_generation(now_ns), topic,
                                                 stamp_ns).as_dict()}
        self.counts['published'] += 1
        return d, list(clipped)

    # -- results -----------------------------------------------------------------------------
    def result(self, res: JobResult, now: float) -> ResultAction:
        """Judge a result of the solver thread (``now``: monotonic time, for the latency)."""
        job = res.job
        outdated = job.primitive_id != self.primitive_id  # adapted a primitive replaced since
        if job.refine_kl is not None and (outdated or res.stale or res.outcome != 'converged'):
            # a refinement that gave way to a newer request, found no lower KL or failed: the
            # warm solution stays published; a cancelled one resumes on the newer request
            self.suspensions.refinement_ended(res, outdated)
            if res.outcome == 'kept_warm':
                key = 'kept_warm'
            elif res.outcome == 'rejected' and not (outdated or res.stale):
                key = 'failed'
            else:
                key = 'cancelled'
            self.counts[f'refinements_{key}'] += 1
            return ResultAction(warning=(f'refinement {job.id} failed: {res.error}'
                                         if key == 'failed' else None))
        if outdated:
            self.counts['requests_outdated'] += 1
            return ResultAction(report=False)
        self.counts[f'outcome_{res.outcome}'] += 1
        kv = result_values(res)
        timings = [('solve', res.solve_time)]
        if res.outcome == 'rejected':
            return ResultAction(level=ERROR, values=kv, timings=timings,
                                message=f'request {job.id} ({job.trigger}) rejected: {res.error}',
                                reject=(res.error_topic or job.trigger, res.error))
        if res.outcome == 'converged':
            self.suspensions.published(res)
            if not job.request.continues and job.generation >= self.restart_generation:
                self.motion_of, self.restart_generation = job.primitive_id, 0
            self.counts['published'] += 1
            if job.refine_kl is not None:
                self.counts['refinements_published'] += 1
            latency = now - job.received
            timings.append(('request_to_publish', latency))
            kv['latency_ms'] = f'{latency * 1e3:.1f}'
            return ResultAction(
                publish=res.text, markers=(res.path, res.band), level=OK, values=kv,
                timings=timings, refine=True,
                message=(f'request {job.id} ({job.trigger}) converged'
                         + (' (refinement)' if job.refine_kl is not None else '')
                         + (' (stale: a newer request is pending)' if res.stale else '')))
        bad = '; '.join(res.result.problem.infeasible[:2] + violated(res)[:5])
        return ResultAction(
            level=ERROR if res.outcome == 'infeasible' else WARN, values=kv, timings=timings,
            message=f'request {job.id} ({job.trigger}) {res.outcome}: {bad}; last good '
                    f'primitive kept',
            warning=f'adaptation {res.outcome} ({res.result.report.status}): {bad}')

    def refinement(self, res: JobResult, solver_idle: bool, now_ns: int,
                   received: float) -> Optional[Job]:
        """After a published warm solve, with the solver idle (``solver_idle``: not busy and
        nothing pending): the cold solve of the same request, or the continuation of the
        refinement a newer request suspended, on this request (``adaptation.
        warm_start_refine``; :mod:`cdmp_ros.core.adaptation.warm`); None otherwise. A
        refinement must run before any newer request (its generation is newer than theirs),
        which then cancels it."""
        job = res.job
        if (res.stale or job.refine_kl is not None or res.result.report.start != 'warm'
                or not job.config.warm_start_refine or not solver_idle):
            return None
        self.counts['refinements_started'] += 1
        resume = self.suspensions.resume_for(job)
        self.counts['refinements_resumed'] += resume is not None
        return dataclasses.replace(job, refine_kl=float(res.result.report.kl),
                                   refine_resume=resume, generation=self.next_generation(now_ns),
                                   received=received)
