"""What a constraint's confidence alpha guarantees, checked by sampling, and
:func:`adapt`, the entry point of the constrained ProMP adaptation: the optimiser
(:func:`~cdmp_ros.core.adaptation.solver.solve_levels`, paper 003) at the levels the guarantee
asks for, then the sampled verification of the result.

- :func:`attach_verification`: every adaptation report carries the sampled
  :class:`~cdmp_ros.core.adaptation.verification.Verification` of the adapted distribution, and
  ``converged`` requires that it confirms the claimed level.
- :func:`adapt_trajectory`: the trajectory-level guarantee (constraint-set field
  ``"guarantee": "trajectory"``): P(the whole trajectory satisfies every constraint at every
  step of its support) >= alpha, alpha the smallest confidence of the set. The per-step
  optimiser (paper 003) is run at tightened per-step levels 1 - alpha'_k = s_k (1 - alpha_k),
  an outer loop driven by the sampled check: after each solve the trajectory-level violation
  v_k of every constraint is sampled; while the overall violation's 95 % upper bound exceeds
  1 - alpha, the scales of the constraints that were violated are multiplied by
  (TARGET (1 - alpha) / sum_k v_k)^(1 / g), with g the sampled elasticity of the violation with
  respect to the level (d log v / d log s, estimated from the previous solves; 1 at first).
  The union of the constraints is accounted for by aiming at the sum of their violations
  (union-aware: each constraint gets a share of the budget proportional to its violation).
  When a tightening overshoots (sampled violation below LOOSEN_BELOW (1 - alpha)), the levels
  are bisected (log scale) between the passing and the last failing ones to give back KL;
  the passing solution with the smallest KL is returned. The checks that steered the loop
  also selected the solution (it is returned because its sample passed), so the returned
  solution is verified once more on fresh samples: that check is the report's
  ``verification`` (and decides ``converged``), the one that selected it is kept as
  ``selection_verification``.
"""
import copy
import math
import time
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from cdmp_ros.core.adaptation.config import (AdaptationConfig, AdaptationReport,
                                             MAX_VERIFICATION_SAMPLES, SolverState)
from cdmp_ros.core.adaptation.constraints.base import Constraint
from cdmp_ros.core.adaptation.solver import solve_levels
from cdmp_ros.core.adaptation.verification import critical_count, detectable_violation, verify
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.promp import ProMP

__all__ = ['TARGET', 'adapt', 'adapt_trajectory', 'attach_verification', 'default_samples',
           'samples_to_detect', 'verification_samples']

#: Trajectory mode aims the sampled violation at this fraction of 1 - alpha, so that its
#: 95 % upper bound falls below 1 - alpha with the default sample counts.
TARGET = 0.5
#: Largest tightening of one refinement, and the smallest per-step level enforced (the
#: approximation's tail is not meaningful below it in double precision).
MIN_FACTOR = 0.02
MIN_LEVEL = 1e-9
#: A passing solution whose sampled violation is below LOOSEN_BELOW (1 - alpha) (the
#: tightening overshot) is followed by bisections (in log scale) between it and the last
#: failing levels, while refinements remain and the levels differ by more than a factor
#: exp(BISECTION_TOL); the passing solution with the smallest KL is returned.
LOOSEN_BELOW = 0.25
BISECTION_TOL = 0.35

#: Default sampled trajectories of problems with link points: at most FK_BUDGET
#: forward-kinematics evaluations (sample x time step), between SAMPLES_MIN and SAMPLES_MAX.
SAMPLES_MAX = 10000
SAMPLES_MIN = 1000
FK_BUDGET = 100_000
#: Problems whose points of interest are linear in the ProMP dimensions (no kinematics: one
#: matrix product per sample chunk, ~1.4 ms per 1,000 samples of 101 steps on one core) draw
#: the first count of SAMPLES_LINEAR at which the per-step test catches a violation of
#: DETECTABLE_TARGET times the asked level with 95 % power (``detectable_excess``) for every
#: constraint; the last count if none does (Tables II-IV at alpha 0.999, 3 constraints of 101
#: steps: 60,000 samples, 1.84 times, 80-95 ms on one core).
SAMPLES_LINEAR = (10_000, 20_000, 40_000, 60_000, 80_000, 100_000)
DETECTABLE_TARGET = 2.0


def adapt(prior: ProMP, constraints: Sequence, config: Optional[AdaptationConfig] = None,
          should_stop: Optional[Callable[[], bool]] = None,
          rng: Optional[np.random.Generator] = None,
          start: Optional[SolverState] = None) -> Tuple[ProMP, AdaptationReport]:
    """Adapt ``prior`` to the constraints (Algorithm 1, paper 003) and verify the result.

    With ``config.guarantee == 'per_step'`` (the paper's semantics) one solve of
    :func:`solve_levels`; with ``'trajectory'`` the per-step levels are tightened until the
    sampled trajectory-level violation's upper bound is <= 1 - alpha
    (:func:`adapt_trajectory`). Either way the report
    carries the sampled :class:`~cdmp_ros.core.adaptation.verification.Verification` of the
    adapted distribution (``config.verification_samples`` trajectories).

    Parameters
    ----------
    prior : ProMP
        The learned distribution (D dimensions, M basis functions: weights of shape
        (D * M,)).
    constraints : sequence of Constraint or WeightConstraint
        Each with its confidence ``alpha`` (e.g. from
        :func:`~cdmp_ros.core.adaptation.constraints.parse.parse_constraint_set`).
    config : AdaptationConfig, optional
    should_stop : callable, optional
        Polled during the solve; True abandons it with
        :class:`~cdmp_ros.core.errors.Cancelled` (:func:`solve_levels`).
    rng : numpy.random.Generator, optional
        Of the sampled verification (default: ``numpy.random.default_rng(0)``, reproducible
        reports).
    start : SolverState, optional
        Warm start (:func:`solve_levels`); guarantee ``per_step`` only (the ``trajectory``
        guarantee re-solves at tightened levels and always starts cold).

    Returns
    -------
    adapted : ProMP
    report : AdaptationReport
        ``converged`` is True only if every constraint holds at its confidence under the
        approximation and the sampled verification confirms the claimed level (per step or
        per trajectory; rules in :mod:`cdmp_ros.core.adaptation.verification`).
    """
    config = config or AdaptationConfig()
    rng = np.random.default_rng(0) if rng is None else rng
    if config.guarantee == 'trajectory':
        if start is not None:
            raise ValidationError('adapt: a warm start needs the per_step guarantee')
        return adapt_trajectory(prior, constraints, config, should_stop, rng)
    t_start = time.perf_counter()
    adapted, report = solve_levels(prior, constraints, config, should_stop, start)
    attach_verification(report, adapted, constraints, config, rng, t_start)
    return adapted, report


def default_samples(constraints: Sequence, n_steps: int) -> int:
    """Default sample count of the verification: for problems without kinematics the
    smallest of :data:`SAMPLES_LINEAR` whose per-step test detects :data:`DETECTABLE_TARGET`
    times the asked level (:func:`samples_to_detect`); with link points
    :data:`FK_BUDGET` / steps within [SAMPLES_MIN, SAMPLES_MAX] (1,000 for the 7-DoF Panda
    with link points on 100 time steps)."""
    grid = np.linspace(0.0, 1.0, int(n_steps))
    fk = set()
    for c in constraints:
        if isinstance(c, Constraint) and not c.point.linear:
            fk.add((id(getattr(c.point, 'chain', c.point)), c.times(grid).tobytes()))
    steps = sum(np.frombuffer(key, float).size for _, key in fk)
    if not steps:
        return samples_to_detect(constraints, grid)
    return int(min(SAMPLES_MAX, max(SAMPLES_MIN, FK_BUDGET // steps)))


def samples_to_detect(constraints: Sequence, grid: np.ndarray,
                      target: float = DETECTABLE_TARGET, significance: float = 0.01) -> int:
    """The first count of :data:`SAMPLES_LINEAR` at which the per-step rule of
    :func:`~cdmp_ros.core.adaptation.verification.verify` (Bonferroni over every tested
    step) detects, for every constraint, a per-step violation of ``target`` times its level
    with 95 % power; the last count if none does."""
    tests = sum(c.times(grid).size if isinstance(c, Constraint) else 1 for c in constraints)
    eps = sorted({1.0 - c.alpha for c in constraints})
    for n in SAMPLES_LINEAR:
        if all(detectable_violation(n, critical_count(n, e, significance / max(tests, 1)))
               <= target * e for e in eps):
            return n
    return SAMPLES_LINEAR[-1]


def verification_samples(config: AdaptationConfig, constraints: Sequence) -> int:
    """Samples of the verification for ``config`` (see AdaptationConfig.verification_samples):
    with the trajectory guarantee at least 20 / (1 - alpha), so that the 95 % upper bound of
    the trajectory-level violation can fall below 1 - alpha."""
    n = config.verification_samples
    n = default_samples(constraints, config.n_steps) if n is None else int(n)
    if config.guarantee == 'trajectory' and constraints:
        eps = 1.0 - min(c.alpha for c in constraints)
        n = max(n, int(math.ceil(20.0 / eps)))
    return min(n, MAX_VERIFICATION_SAMPLES)


def attach_verification(report: AdaptationReport, adapted: ProMP, constraints: Sequence,
                        config: AdaptationConfig, rng: np.random.Generator,
                        t_start: float) -> AdaptationReport:
    """Sample ``adapted``, store the verification in ``report`` and make ``converged`` require
    it (status ``verification_failed`` when the approximation converged but the check does
    not confirm the claimed level); ``time_s`` becomes the time since ``t_start``."""
    ver = verify(adapted, constraints, verification_samples(config, constraints), rng,
                 config.n_steps, config.guarantee)
    report.verification = ver
    report.guarantee = config.guarantee
    if not report.levels:
        report.levels = [1.0 - c.alpha for c in constraints]
    if report.converged and not ver.holds:
        report.converged = False
        report.status = 'verification_failed'
    report.time_s = time.perf_counter() - t_start
    return report


def _with_level(c, scale: float):
    """A shallow copy of constraint ``c`` with the per-step violation level scale (1 - alpha)
    (the copy shares the point of interest, so the optimiser still shares its moments)."""
    if scale == 1.0:
        return c
    t = copy.copy(c)
    t.alpha = float(1.0 - scale * (1.0 - c.alpha))
    return t


def adapt_trajectory(prior: ProMP, constraints: Sequence, config: AdaptationConfig,
                     should_stop: Optional[Callable[[], bool]], rng: np.random.Generator
                     ) -> Tuple[ProMP, AdaptationReport]:
    """:func:`adapt` with the trajectory-level guarantee
    (module docstring); at most ``1 + config.max_refinements`` solves."""
    t_start = time.perf_counter()
    constraints = list(constraints)
    n = verification_samples(config, constraints)
    eps = 1.0 - min((c.alpha for c in constraints), default=1.0 - 1e-3)
    scales = np.ones(len(constraints))
    alphas = np.array([c.alpha for c in constraints])
    history: List[Tuple[np.ndarray, np.ndarray]] = []     # (scales, violations), failed checks
    best = None            # (kl, adapted, report, verification, scales) of the best passing
    failing = None         # scales of the last failing check once a passing one is known
    n_outer = n_inner = n_evals = n_solves = n_back = 0
    for r in range(int(config.max_refinements) + 1):
        tight = [_with_level(c, s) for c, s in zip(constraints, scales)]
        adapted, report = solve_levels(prior, tight, config, should_stop)
        n_solves += 1
        n_outer += report.n_outer
        n_inner += report.n_inner
        n_evals += report.n_evaluations
        n_back += report.n_backtracks
        ver = verify(adapted, constraints, n, rng, config.n_steps, 'trajectory')
        last = (report.kl, adapted, report, ver, scales)
        if ver.holds and report.converged:
            if best is None or report.kl < best[0]:
                best = last
            if failing is None and ver.trajectory_violation >= LOOSEN_BELOW * eps:
                break
            # far below the level (the tightening overshot): try looser levels between
            lo, hi = scales, (failing if failing is not None else history[-1][0]
                              if history else None)
            if hi is None:
                break
        elif not report.converged:
            break          # the approximation is infeasible at these levels
        elif best is not None:
            failing = scales
            lo, hi = best[4], scales
        else:
            v = np.array([cv.trajectory for cv in ver.constraints])
            history.append((scales.copy(), v))
            total = max(float(v.sum()), ver.trajectory_violation, 1.0 / n)
            g = _elasticity(history)
            factor = float(np.clip((TARGET * eps / total) ** (1.0 / g), MIN_FACTOR, 0.8))
            new = np.where(v > 0, np.maximum(scales * factor, MIN_LEVEL / (1.0 - alphas)),
                           scales)
            if np.array_equal(new, scales):
                break         # every violated constraint is at the smallest level already
            scales = new
            continue
        # bisection in log scale between a passing (lo) and a failing (hi) set of levels
        new = np.sqrt(lo * hi)
        if np.all(np.abs(np.log(new) - np.log(lo)) < BISECTION_TOL):
            break
        scales = new
    kl, adapted, report, selected, scales = best if best is not None else last
    # fresh samples (the rng has moved on): free of the selection by the loop's checks
    ver = verify(adapted, constraints, n, rng, config.n_steps, 'trajectory')
    report.selection_verification = selected
    for cr, c in zip(report.constraints, constraints):
        cr.alpha = c.alpha
    report.levels = [float(s * (1.0 - c.alpha)) for s, c in zip(scales, constraints)]
    report.n_outer, report.n_inner, report.n_evaluations = n_outer, n_inner, n_evals
    report.n_solves, report.n_backtracks = n_solves, n_back
    report.verification = ver
    report.guarantee = 'trajectory'
    if report.converged and not ver.holds:
        report.converged = False
        report.status = 'verification_failed'
    report.time_s = time.perf_counter() - t_start
    return adapted, report


def _elasticity(history) -> float:
    """d log v / d log s of the summed violation between the last two solves, clipped to
    [0.3, 1.5] (1 before there are two)."""
    if len(history) < 2:
        return 1.0
    (s0, v0), (s1, v1) = history[-2], history[-1]
    a, b = float(v0.sum()), float(v1.sum())
    m = (v0 > 0) & (v1 > 0)
    if not m.any() or a <= 0 or b <= 0:
        return 1.0
    ds = float(np.mean(np.log(s1[m]) - np.log(s0[m])))
    if abs(ds) < 1e-9:
        return 1.0
    return float(np.clip((math.log(b) - math.log(a)) / ds, 0.3, 1.5))
