"""Warm starts of consecutive adaptation requests: an obstacle that moves.

A tracker publishes an obstacle's pose at 30 Hz. Between two requests it moves by millimetres
to centimetres, so the next problem is nearly the last one, and its solution is nearly the
last solution. :class:`WarmStarts` remembers where the last converged solve ended (the
optimiser's :class:`~cdmp_ros.core.adaptation.config.SolverState`) and starts the next solve
there when

- the built problem has the same prior (mean, covariance and basis), optimiser settings,
  joint limits and user constraint set;
- every obstacle of both requests (by its place in the list) moved by at most
  ``warm_start_distance`` (:func:`obstacle_shift`). Obstacles may come and go (a sphere that
  enters ``influence_distance`` of the path adds its constraints): constraints of the last
  solve start from its multipliers, new ones from ``lambda0``.

**Predictor.** An obstacle tracked at constant velocity moves by the same displacement from
message to message, and a chain of warm solutions then moves along a smooth path of optima.
When the last solve was itself started warm from the one before, and every obstacle's
displacement since the last request equals its previous displacement (within
:data:`PREDICT_RTOL` of it, plus :data:`PREDICT_ATOL`), the solve starts from the secant
prediction theta_k + (theta_k - theta_{k-1}) with the last multipliers (a predictor-corrector
continuation), which needs fewer evaluations than a plain warm start on a steadily tracked
obstacle (``benchmarks/bench_warm_track.py``). Like a plain warm solve, a predicted one that
does not converge within its budget is followed by the cold solve
(``adaptation.warm_start_predict``).

The warm solve is bounded (``warm_start_max_evaluations``) and goes through the same sampled
verification as any other (only a solve that is kept is verified: an attempt that runs out of
evaluations is not). When it ends out of evaluations, or with a level check that had no
re-solve left (:data:`CONTINUED`), a second warm solve continues from where it ended (its
iterate, multipliers and implied levels) within the same budget: in the demo's obstacle
streams that took 4-15 more evaluations where the cold solve that replaced the first took
28-48. When that does not converge either, or the first stalled infeasible, the request is
solved cold as well. When
it converged it is kept; if its KL exceeds ``warm_start_kl_ratio`` x the KL of the last cold
solve + :data:`KL_SLACK` (the KL guard: a chain of warm starts does not drift far from what a
cold solve gives without one checking it; the result at hand, converged and verified, is not
held back for it), a cold solve checks it. With refinements (``warm_start_refine``, below)
that check is the refinement, off the request path: the next request still starts warm (a
cold check on the request path was most of the latency tail of a tracked obstacle). Without
refinements the next request starts cold. That cold check is bounded
(``warm_start_check_max_evaluations``, over all the resumptions of a refinement); when a next
request's check does not converge within the bound, the request is solved from the withheld
warm start instead, and that solution's KL becomes the guard's reference: a failed check
never loses the chain (an occasional cold solve takes many times the usual evaluations, or
diverged before the solver's backtracking,
:data:`cdmp_ros.core.adaptation.solver.BACKTRACK_GROWTH`). The report says which start was
kept (``start``) and why (``start_note``).

A warm solution keeps the side of an obstacle the last solution chose, where a cold solve may
pass on the other side from one request to the next (a jump of the path by centimetres
where the warm chain moves by millimetres). So a warm chain can stay in a local optimum worse
than the cold one within the guard. :meth:`WarmStarts.refine` is the remedy the adapter
applies when its solver is idle after a warm solve: it solves the same request cold and keeps
the result if its KL is at least :data:`REFINE_GAIN` lower (the adapter then publishes it).

**Resumed refinements.** A newer request cancels a running refinement within one evaluation,
and the refinement says where it was (:func:`suspend`: the best point of its inner loop, with
its multipliers, and the evaluations so far). After the newer request's warm solve, the next
refinement continues from there on the newer problem instead of starting cold again (the
obstacle moved by millimetres; the solve stays in the basin a cold start reached), so an
obstacle tracked at 30 Hz, whose requests leave the solver idle for less than a cold solve,
still gets its cold check.

Why warm starts: a sphere moving a few millimetres per request costs a few evaluations warm
against tens to hundreds cold, at the same KL (``benchmarks/bench_adaptation_solve.py``).
"""
import dataclasses
import time
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.adaptation.config import (AdaptationConfig, AdaptationReport,
                                             AdaptRequestConfig, SolverState)
from cdmp_ros.core.adaptation.guarantee import adapt, attach_verification
from cdmp_ros.core.adaptation.solver import solve_levels
from cdmp_ros.core.errors import Cancelled
from cdmp_ros.core.kinematics import Box, OrientedBox, Sphere
from cdmp_ros.core.promp.promp import ProMP

#: Statuses of a warm solve that a second warm solve continues from where it ended, before
#: the request is solved cold: the first ran out of evaluations, or its level correction
#: had no re-solve left (in the demo's streams the cold solve that replaced such a solve took
#: 28-48 evaluations on top of the 30 spent; the continuation 4-15).
CONTINUED = ('evaluation_budget_exhausted', 'level_check_failed')

__all__ = ['KL_SLACK', 'PREDICT_ATOL', 'PREDICT_RTOL', 'REFINE_GAIN', 'Suspended',
           'WarmStarts', 'obstacle_shift', 'predict_state', 'suspend']

#: Additive slack [nats] of the KL guard: small KLs (an obstacle barely touching the band) may
#: double between requests without a cold check.
KL_SLACK = 1.0
#: A refinement (:meth:`WarmStarts.refine`) replaces the warm solution when its KL is lower by
#: at least this fraction.
REFINE_GAIN = 0.05
#: The predictor applies when every point of every obstacle (sphere centre and radius, box
#: corners) moved by the same displacement as in the last request, within PREDICT_RTOL of the
#: larger of the two moves plus PREDICT_ATOL [m].
PREDICT_RTOL = 0.25
PREDICT_ATOL = 5e-4


def _corners(ob) -> NDArray[np.float64]:
    """The 8 corners (8, 3) of a box obstacle."""
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    if isinstance(ob, Box):
        lo, hi = np.asarray(ob.lower), np.asarray(ob.upper)
        return 0.5 * (lo + hi) + signs * 0.5 * (hi - lo)
    R = np.asarray(ob.rotation, float)
    return np.asarray(ob.center) + (signs * 0.5 * np.asarray(ob.size)) @ R.T


def obstacle_shift(a, b) -> float:
    """How far any point of obstacle ``a`` moved to become ``b`` [m], bounded above:
    spheres |c_a - c_b| + |r_a - r_b|; boxes the largest move of a corner (a point of a box
    is an affine combination of its corners, so no point moves farther). Obstacles of
    different kinds: infinity."""
    if type(a) is not type(b):
        return float('inf')
    if isinstance(a, Sphere):
        return float(np.linalg.norm(np.subtract(a.center, b.center)) + abs(a.radius - b.radius))
    if isinstance(a, (Box, OrientedBox)):
        return float(np.max(np.linalg.norm(_corners(a) - _corners(b), axis=1)))
    return 0.0 if a == b else float('inf')


def _points(ob) -> Optional[NDArray[np.float64]]:
    """Points whose displacement is the obstacle's motion: a sphere's centre and (as a
    fourth coordinate) its radius; a box's corners; None for anything else."""
    if isinstance(ob, Sphere):
        return np.append(np.asarray(ob.center, float), float(ob.radius))[None]
    if isinstance(ob, (Box, OrientedBox)):
        return _corners(ob)
    return None


def _steady_motion(before, last, now) -> bool:
    """Whether every obstacle moved from ``last`` to ``now`` as it moved from ``before`` to
    ``last`` (same obstacles by place and kind; see PREDICT_RTOL)."""
    if not len(before) == len(last) == len(now):
        return False
    for a, b, c in zip(before, last, now):
        if not type(a) is type(b) is type(c):
            return False
        pa, pb, pc = _points(a), _points(b), _points(c)
        if pa is None or pb is None or pc is None:
            return False
        d1, d2 = pb - pa, pc - pb
        scale = max(float(np.max(np.linalg.norm(d1, axis=1))),
                    float(np.max(np.linalg.norm(d2, axis=1))))
        if float(np.max(np.linalg.norm(d2 - d1, axis=1))) > PREDICT_RTOL * scale + PREDICT_ATOL:
            return False
    return True


def predict_state(before: SolverState, last: SolverState) -> SolverState:
    """The secant prediction of the next solution from the last two of a warm chain:
    theta = 2 theta_last - theta_before, with the multipliers of ``last`` (extrapolating them
    as well, by their growth factor clipped to [1/2, 2], cost more evaluations on the tracked
    streams of ``benchmarks/bench_warm_track.py``)."""
    return SolverState(2.0 * last.theta - before.theta, last.multipliers, last.levels)


def _same_prior(a: ProMP, b: ProMP) -> bool:
    if a is b:
        return True
    if (a.n_dims, a.n_basis) != (b.n_dims, b.n_basis):
        return False
    grid = np.linspace(0.0, 1.0, 7)
    return (np.array_equal(a.mean_w, b.mean_w) and np.array_equal(a.cov_w, b.cov_w)
            and np.array_equal(a.basis.features(grid), b.basis.features(grid)))


def _same_limits(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(np.array_equal(x, y) for x, y in zip(a, b))


@dataclass
class _Memory:
    """The last converged solve of the stream."""
    prior: ProMP
    config: AdaptationConfig
    constraint_doc: Optional[dict]
    limits: Optional[Tuple[NDArray, NDArray]]
    obstacles: Tuple
    state: SolverState
    anchor_kl: float          # KL of the last cold solve (or of a warm one it confirmed)
    cold_next: bool = False   # the last warm solve exceeded the KL guard
    #: (state, obstacles) of the solve this one was started warm from (None: it was cold)
    before: Optional[Tuple[SolverState, Tuple]] = None


def _warm_solve(built, cfg: AdaptRequestConfig, should_stop: Optional[Callable[[], bool]],
                start: SolverState) -> Tuple[ProMP, AdaptationReport]:
    """Solve ``built`` from ``start`` within ``warm_start_max_evaluations``; verified only when
    it converged (an attempt that is replaced by a cold solve is not)."""
    config = dataclasses.replace(built.config,
                                 max_evaluations=int(cfg.warm_start_max_evaluations))
    t0 = time.perf_counter()
    adapted, rep = solve_levels(built.prior, built.constraints, config, should_stop, start)
    if rep.converged:
        attach_verification(rep, adapted, built.constraints, config, np.random.default_rng(0),
                            t0)
    return adapted, rep


def _warm_attempt(built, cfg: AdaptRequestConfig, should_stop: Optional[Callable[[], bool]],
                  start: SolverState) -> Tuple[ProMP, AdaptationReport,
                                               Optional[AdaptationReport]]:
    """:func:`_warm_solve` from ``start``; when it ends for a reason in :data:`CONTINUED`, a
    second one from where it ended (its iterate, multipliers and implied levels), within the
    same budget: ``(adapted, report, first)`` with ``first`` the report of the first solve
    when the second ran (the report's counts are of both), else None."""
    adapted, rep = _warm_solve(built, cfg, should_stop, start)
    if rep.converged or rep.status not in CONTINUED or rep.state is None:
        return adapted, rep, None
    first = rep
    adapted, rep = _warm_solve(built, cfg, should_stop, first.state)
    rep.n_evaluations += first.n_evaluations
    rep.n_outer += first.n_outer
    rep.n_inner += first.n_inner
    rep.n_backtracks += first.n_backtracks
    rep.n_level_corrections += first.n_level_corrections
    rep.time_s += first.time_s
    return adapted, rep, first


@dataclass(frozen=True)
class Suspended:
    """A refinement that gave way to a newer request: where its solve was (the best point of
    its inner loop, with its multipliers), the evaluations it took so far and the requests it
    spanned. The next refinement continues from there (:meth:`WarmStarts.refine`)."""
    state: SolverState
    n_evaluations: int
    n_requests: int


def suspend(exc: Cancelled, resume: Optional[Suspended] = None) -> Optional[Suspended]:
    """Where the refinement cancelled with ``exc`` was (it had resumed ``resume``, if given),
    or None when it had not started solving."""
    if exc.state is None:
        return None
    before = resume or Suspended(exc.state, 0, 0)
    return Suspended(exc.state, before.n_evaluations + exc.n_evaluations, before.n_requests + 1)


class WarmStarts:
    """Warm starts of a stream of requests (see the module docstring). One instance per
    solver thread; not thread-safe.

    Attributes
    ----------
    counts : dict
        ``warm`` (warm solves kept), ``predicted`` (of those, started from the predictor),
        ``continued`` (of those, a second warm solve from where the first ended,
        :data:`CONTINUED`), ``cold`` (no warm start possible, or disabled; or the KL guard's
        check),
        ``cold_then_warm`` (the guard's cold solve did not converge: solved from the withheld
        warm start),
        ``warm_then_cold`` (warm solves that did not converge, so the request was solved cold
        as well), ``over_guard`` (warm solves kept over the KL guard: the next request starts
        cold), ``refined`` / ``refine_kept_warm`` (refinements that replaced the warm solution
        / that did not lower the KL by REFINE_GAIN).
    """

    def __init__(self):
        self._memory: Optional[_Memory] = None
        self.counts = {'warm': 0, 'predicted': 0, 'continued': 0, 'cold': 0, 'warm_then_cold': 0,
                       'cold_then_warm': 0, 'over_guard': 0, 'refined': 0,
                       'refine_kept_warm': 0}

    def forget(self) -> None:
        """The next request starts cold."""
        self._memory = None

    def start_for(self, req, built, cfg: AdaptRequestConfig, guard: bool = True
                  ) -> Optional[SolverState]:
        """The state a solve of ``built`` (the problem of request ``req``) may start from, or
        None (cold); ``guard=False``: also when the KL guard asks for a cold solve."""
        return self._start(req, built, cfg, guard)[0]

    def _start(self, req, built, cfg: AdaptRequestConfig, guard: bool = True
               ) -> Tuple[Optional[SolverState], str]:
        """(:meth:`start_for`, why it is None: '' when there is no earlier solve, or warm
        starts are off, else the reason, for the report's ``start_note``)."""
        m = self._memory
        if m is None or not cfg.warm_start:
            return None, ''
        if guard and m.cold_next:
            return None, 'the KL guard asked for a cold solve'
        if built.config.guarantee != 'per_step':
            return None, f'not warm: guarantee {built.config.guarantee}'
        if built.infeasible:
            return None, 'not warm: the request is known infeasible'
        for differs, what in ((m.config != built.config, 'the solver settings'),
                              (m.constraint_doc != req.constraint_doc, 'the constraint set'),
                              (not _same_limits(m.limits, req.limits), 'the joint limits'),
                              (not _same_prior(m.prior, built.prior),
                               'the prior (conditioned anew, or another primitive)')):
            if differs:
                return None, f'not warm: {what} changed since the last solve'
        shift = max((obstacle_shift(a, b) for a, b in zip(m.obstacles, req.obstacles)),
                    default=0.0)
        if shift > cfg.warm_start_distance:
            return None, (f'not warm: an obstacle moved {shift:.3g} m > warm_start_distance '
                          f'{cfg.warm_start_distance:g} m')
        return m.state, ''

    def predicted_start(self, req) -> Optional[SolverState]:
        """The predictor's start for ``req`` (module docstring), or None when it does not
        apply; call after :meth:`start_for` gave a warm start."""
        m = self._memory
        if m is None or m.before is None:
            return None
        state, obstacles = m.before
        if not _steady_motion(obstacles, m.obstacles, tuple(req.obstacles)):
            return None
        return predict_state(state, m.state)

    def solve(self, req, built, cfg: AdaptRequestConfig,
              should_stop: Optional[Callable[[], bool]] = None) -> Tuple[ProMP,
                                                                         AdaptationReport]:
        """Adapt ``built`` (the problem of ``req``), warm when :meth:`start_for` allows it
        (from the predictor's start first when it applies); remembers the outcome. Returns
        ``(adapted, report)`` as :func:`~cdmp_ros.core.adaptation.guarantee.adapt`."""
        usable, note = self._start(req, built, cfg, guard=False)
        guarded = usable is not None and self._memory.cold_next
        start, withheld = (None, usable) if guarded else (usable, None)
        if guarded:
            note = 'the KL guard checks the last warm solve cold (its KL was over the guard)'
        if start is not None:
            predicted = self.predicted_start(req) if cfg.warm_start_predict else None
            adapted, rep, first = _warm_attempt(built, cfg, should_stop,
                                                start if predicted is None else predicted)
            if rep.converged:   # (and the verification confirmed it)
                self.counts['warm'] += 1
                self.counts['predicted'] += predicted is not None
                self.counts['continued'] += first is not None
                anchor = self._memory.anchor_kl
                self._remember(req, built, rep, anchor, before=(start, self._memory.obstacles))
                rep.start_note = ('started from the prediction of a steady obstacle motion'
                                  if predicted is not None else '')
                if first is not None:
                    rep.start_note = ((rep.start_note + '; ' if rep.start_note else '')
                                      + f'continued where the first warm solve ended '
                                      f'({first.status} after {first.n_evaluations} '
                                      f'evaluations)')
                bound = cfg.warm_start_kl_ratio * anchor + KL_SLACK
                if rep.kl > bound:   # kept (converged and verified); checked cold
                    self.counts['over_guard'] += 1
                    over = (f'KL {rep.kl:.4g} > {cfg.warm_start_kl_ratio:g} x {anchor:.4g} + '
                            f'{KL_SLACK:g} (last cold solve): ')
                    over += ('the refinement checks it' if cfg.warm_start_refine   # off the path
                             else 'the next request starts cold')
                    if not cfg.warm_start_refine:
                        self._memory.cold_next = True
                    rep.start_note = (rep.start_note + '; ' if rep.start_note else '') + over
                return adapted, rep
            self.counts['warm_then_cold'] += 1
            note = (f'{"predicted" if predicted is not None else "warm"} start replaced: '
                    f'{rep.status} after {rep.n_evaluations} evaluations')
        else:
            self.counts['cold'] += 1
        config = built.config
        if withheld is not None:   # the guard's check, bounded: the warm start is at hand
            config = dataclasses.replace(
                config, max_evaluations=int(cfg.warm_start_check_max_evaluations))
        cold = adapt(built.prior, built.constraints, config, should_stop)
        cold[1].start_note = note
        if cold[1].converged:
            self._remember(req, built, cold[1], cold[1].kl)
            return cold
        if withheld is not None:   # only the guard sent it cold: the warm chain stays
            out = self._after_failed_check(req, built, cfg, should_stop, withheld, cold[1])
            if out is not None:
                return out
        self.forget()
        return cold

    def _after_failed_check(self, req, built, cfg: AdaptRequestConfig,
                            should_stop: Optional[Callable[[], bool]], start: SolverState,
                            cold: AdaptationReport) -> Optional[Tuple[ProMP, AdaptationReport]]:
        """Solve ``built`` warm from ``start`` (the state the KL guard withheld) after its
        cold solve ended ``cold`` (not converged); the result when it converged and its
        verification holds (its KL becomes the guard's reference), else None."""
        adapted, rep = _warm_solve(built, cfg, should_stop, start)
        if not rep.converged:
            return None
        self.counts['cold_then_warm'] += 1
        self._remember(req, built, rep, rep.kl, before=(start, self._memory.obstacles))
        rep.start_note = (f"the KL guard's cold solve ended {cold.status} after "
                          f'{cold.n_evaluations} evaluations: solved from the warm start '
                          f"instead (its KL {rep.kl:.4g} is the guard's new reference)")
        return adapted, rep

    def refine(self, req, built, kl: float, should_stop: Optional[Callable[[], bool]] = None,
               resume: Optional[Suspended] = None, max_evaluations: Optional[int] = None
               ) -> Optional[Tuple[ProMP, AdaptationReport]]:
        """Solve ``built`` (the problem of ``req``, the last request, solved warm with KL
        ``kl``) cold. Returns ``(adapted, report)`` when it converged with a KL at least
        :data:`REFINE_GAIN` lower, and remembers it for the next warm start; otherwise None,
        and the warm solution stays (its KL becomes the guard's reference). ``should_stop``
        cancels it (:class:`~cdmp_ros.core.errors.Cancelled`; :func:`suspend` keeps where it
        was). ``resume``: continue a refinement of an earlier request that was suspended
        (module docstring). ``max_evaluations`` bounds the evaluations of the refinement over
        all its resumptions (at least one more is allowed). Only a solve that would be kept
        is verified (a refinement that finds no lower KL, most of them, costs no sampled
        verification, which a newer request could not interrupt)."""
        t0 = time.perf_counter()
        config = built.config
        if max_evaluations is not None:
            spent = resume.n_evaluations if resume is not None else 0
            config = dataclasses.replace(config, max_evaluations=max(1, max_evaluations - spent))
        adapted, rep = solve_levels(built.prior, built.constraints, config, should_stop,
                                    None if resume is None else resume.state)
        rep.start = 'cold'   # (a resumed refinement continues a cold solve)
        lower = rep.converged and rep.kl < (1.0 - REFINE_GAIN) * kl
        if lower:   # converged stays True only if the sampled verification confirms it
            attach_verification(rep, adapted, built.constraints, built.config,
                                np.random.default_rng(0), t0)
        if lower and rep.converged:
            rep.start_note = f'refinement of a warm solve: KL {kl:.4g} -> {rep.kl:.4g}'
            if resume is not None:
                rep.start_note += (f' (a cold solve started {resume.n_requests} requests '
                                   f'before, resumed on each newer one; '
                                   f'{resume.n_evaluations + rep.n_evaluations} evaluations)')
            self.counts['refined'] += 1
            self._remember(req, built, rep, rep.kl)
            return adapted, rep
        self.counts['refine_kept_warm'] += 1
        if self._memory is not None:   # checked by a cold solve: the new reference
            self._memory.anchor_kl = float(kl)
            self._memory.cold_next = False
        return None

    def _remember(self, req, built, rep: AdaptationReport, anchor_kl: float,
                  before: Optional[Tuple[SolverState, Tuple]] = None) -> None:
        self._memory = _Memory(built.prior, built.config, req.constraint_doc, req.limits,
                               tuple(req.obstacles), rep.state, float(anchor_kl),
                               before=before)
