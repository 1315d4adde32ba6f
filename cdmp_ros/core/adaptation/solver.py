"""Constrained ProMP adaptation (paper 003, Eq. 5-10, 23, Algorithm 1).

min_p KL(p || p0) [+ kappa E_p[R(w)]]  s.t.  F_k,t(p) >= alpha_k,t,
with p = N(mu, L L^T), L = L_tril + diag(exp(gamma)), solved by L-BFGS on the Lagrangian
(inner loop, analytic gradients) and the exponential method of multipliers
lambda <- lambda * exp(eta * (alpha - F)) (outer loop).

A multiplier step can overshoot: with one constraint's multiplier grown by orders of magnitude,
the inner loop may satisfy it by breaking others badly, whose multipliers then grow in turn
until the solve diverges (a sphere crossing the Panda's path, events 28-29 of the tracked
seed-3 stream of ``bench_adaptation_latency.py``: KL 7,000-136,000 after 2,300-2,700
evaluations, where the neighbouring events converge at KL 17-20). A jump alone is no proof:
on request 17 of heading 4 of ``bench_warm_track.py`` the largest violation also jumped
(0.05 -> 0.48), and the next outer iteration recovered to the optimum at KL 17.1, where
retrying at once ended at KL 59.6. So when an inner loop ends with its largest violation grown
:data:`BACKTRACK_GROWTH` times and by at least :data:`BACKTRACK_MIN` over the iterate before,
and the next inner loop is still that far above it, the solve goes back to the iterate before
the jump and retries with half the multiplier step that caused it (in log), at most
:data:`MAX_BACKTRACKS` times per solve: events 28 and 29 then converge at KL 17.8 and 18.6 in
951 and 826 evaluations, and 92 other problems solved cold (the 80 events of
``bench_adaptation_solve.py`` seeds 3 and 7, events 21-34 of the tracked stream) give the same
evaluations and KL with and without it.

The saddle point's check of the Gamma match (``AdaptationConfig.tail`` 'auto'): the rows of
points through the unscented transform are solved with the Gamma match, whose tail can be
several times too light. After the solve, :meth:`Problem.check_values` evaluates those rows
under the saddle-point law of the same Gaussian; where one violates more than allowed,
:func:`corrected_levels` tightens its Gamma level by the ratio of the two laws and the solve
continues warm, at most ``AdaptationConfig.max_level_corrections`` times. The reported
probability of a checked row is the lower of the two laws. The levels the last check implies
(:func:`implied_levels`) go into ``report.state``: a warm start solves those rows at them from
the start, so a request close to the last one needs no re-solve of its own. (Checking both
laws in the outer loop's stopping test instead was tried and not kept: RESULTS.md, "Link
points".)
"""
import time
from typing import Callable, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from cdmp_ros.core.adaptation.config import (AdaptationConfig, AdaptationReport, ConstraintReport,
                                             KKTResiduals, SolverState)
from cdmp_ros.core.adaptation.problem import Problem
from cdmp_ros.core.adaptation.verification import sample_points, verify
from cdmp_ros.core.errors import Cancelled, ValidationError
from cdmp_ros.core.promp.promp import ProMP

__all__ = ['AdaptationConfig', 'AdaptationReport', 'ConstraintReport', 'Problem', 'SolverState',
           'sample_points', 'monte_carlo_satisfaction', 'multiplier_update', 'solve_levels',
           'corrected_levels', 'implied_levels', 'carried_levels']


#: Backtracking of a multiplier step (module docstring): the largest violation of the stopping
#: level (alpha - F) grew by this factor ...
BACKTRACK_GROWTH = 2.0
#: ... and by at least this much (probability) over the last iterate's.
BACKTRACK_MIN = 0.05
#: Backtracks per solve at most (each one costs an outer iteration of ``max_outer``).
MAX_BACKTRACKS = 3


#: The saddle point's correction of the Gamma levels (:func:`corrected_levels`) tightens a
#: row's level to at most this many times below the asked 1 - alpha.
MAX_LEVEL_RATIO = 20.0
#: A warm start carries the implied level of a checked row (:func:`implied_levels`) whose
#: saddle-point violation at the solution is at least this fraction of the asked 1 - alpha.
CARRY_FRACTION = 0.1


def _jumped(worst: float, before: float) -> bool:
    """Whether the largest violation ``worst`` jumped away from ``before`` (its value at the
    iterate before): BACKTRACK_GROWTH times and by BACKTRACK_MIN at least."""
    return worst - before >= BACKTRACK_MIN and worst > BACKTRACK_GROWTH * before


def solve_levels(prior: ProMP, constraints: Sequence, config: Optional[AdaptationConfig] = None,
                 should_stop: Optional[Callable[[], bool]] = None,
                 start: Optional[SolverState] = None) -> Tuple[ProMP, AdaptationReport]:
    """Adapt ``prior`` to the constraints (Algorithm 1, paper 003), each time step of each
    constraint at its confidence under the approximation; no sampled verification.

    Parameters
    ----------
    prior : ProMP
    constraints : sequence of constraints
    config : AdaptationConfig, optional
    should_stop : callable, optional
        Polled before every evaluation of the Lagrangian; when it returns True the solve is
        abandoned with :class:`~cdmp_ros.core.errors.Cancelled` (a node shutting down stops
        a long solve within one evaluation); the exception's ``state`` is the best point of
        the inner loop it was in, with the multipliers of that loop, and ``n_evaluations``
        the evaluations it took.
    start : SolverState, optional
        Start from these parameters and multipliers (``report.state`` of an earlier solve
        of a problem with the same prior; constraints it does not name start at their
        ``lambda0``) instead of the prior and ``lambda0``: a warm start
        (``report.start == 'warm'``); the rows its ``levels`` name are solved at those
        levels (:func:`carried_levels`) instead of the asked ones.

    Returns
    -------
    adapted : ProMP
    report : AdaptationReport
        ``converged`` is True only if every constraint holds at its confidence (within
        ``feasibility_tol``) under the approximation; ``report.state`` is where the
        optimiser ended.

    Raises
    ------
    ValidationError
        ``start`` does not fit the problem (the size of theta: another prior).
    """
    config = config or AdaptationConfig()
    t_start = time.perf_counter()
    prob = Problem(prior, constraints, config)

    best = [np.inf, None]   # lowest Lagrangian value of the current inner loop, its theta

    def fun(theta, lam):
        if should_stop is not None and should_stop():
            raise Cancelled('adaptation cancelled')
        value, grad = prob.lagrangian(theta, lam)
        if value < best[0]:
            best[0], best[1] = value, theta.copy()
        return value, grad
    theta = prob.initial_theta()
    lam = np.concatenate([np.full(s.stop - s.start, c.lambda0 or config.lambda0)
                          for c, s in zip(prob.constraints, prob.slices)]) \
        if prob.constraints else np.zeros(0)
    if start is not None:
        if start.theta.shape != theta.shape:
            raise ValidationError(f'solve_levels: the warm start has {start.theta.size} '
                                  f'parameters, the problem {theta.size}')
        theta = start.theta.copy()
        known = dict(start.multipliers)
        for c, sl in zip(prob.constraints, prob.slices):
            m = known.get(c.name)
            if m is not None and m.size == sl.stop - sl.start:
                lam[sl] = m
    budget = config.max_evaluations
    eta = np.concatenate([np.full(s.stop - s.start, c.eta or config.eta)
                          for c, s in zip(prob.constraints, prob.slices)]) \
        if prob.constraints else np.zeros(0)
    kkt_stop = config.stop_rule == 'kkt'
    counts = {'outer': 0, 'inner': 0, 'back': 0}

    def outer_loop(theta, lam, alpha):
        """Algorithm 1's outer loop from (theta, lam) for the levels ``alpha`` (per value):
        (theta, lam, jac, feasible, status, alpha_aim, alpha_stop) where it ended."""
        # stopping level: violation probability confidence_margin * (1 - alpha) (1: alpha
        # itself); EMM aim: violation_target times that
        alpha_stop = 1.0 - config.confidence_margin * (1.0 - alpha)
        alpha_aim = 1.0 - config.violation_target * (1.0 - alpha_stop)
        # feasibility_tol, in proportion where a level was tightened (corrected_levels)
        tol = (config.feasibility_tol * config.confidence_margin
               * (1.0 - alpha) / np.maximum(1.0 - prob.alpha, 1e-300))
        prev = None
        status = 'max_outer_reached'
        feasible = False
        last = None      # (theta, multipliers, largest violation) of the last kept iterate
        jump = None      # last + the multipliers that made the next inner loop jump away
        n_back = 0
        best_feasible = None   # kkt: (objective, theta, multipliers, gradient) of the lowest
        jac = None
        for n_outer in range(1, int(config.max_outer) + 1):
            counts['outer'] += 1
            ftol = config.lbfgs_ftol
            if config.lbfgs_ftol_first is not None:
                # inexact early inner loops: the multipliers are still far from their values
                ftol = max(ftol, config.lbfgs_ftol_first
                           * config.lbfgs_ftol_decay ** (n_outer - 1))
            options = {'maxiter': int(config.max_inner), 'ftol': ftol,
                       'gtol': config.lbfgs_gtol, 'maxcor': config.lbfgs_maxcor}
            if budget is not None:
                options['maxfun'] = max(1, int(budget) - prob.n_evaluations)
            best[0], best[1] = np.inf, None
            try:
                res = minimize(fun, theta, args=(lam,), jac=True, method='L-BFGS-B',
                               options=options)
            except Cancelled as exc:   # where it was: a refinement resumes from there
                exc.state = _state(prob, theta if best[1] is None else best[1], lam, alpha)
                exc.n_evaluations = prob.n_evaluations
                raise
            if np.all(np.isfinite(res.x)):
                theta = res.x
                jac = res.jac
            counts['inner'] += int(res.nit)
            F = _values(prob, theta)
            C = alpha_stop - F
            worst = float(np.max(C)) if C.size else 0.0
            if jump is not None and _jumped(worst, jump[2]) and n_back < MAX_BACKTRACKS:
                # not recovered one outer iteration after the jump: the multiplier step
                # overshot; retry from the iterate before the jump with half that step
                theta, lam = jump[0].copy(), np.sqrt(jump[1] * jump[3])
                last, jump = jump[:3], None
                n_back += 1
                counts['back'] += 1
                continue
            jump = (*last, lam.copy()) if last is not None and _jumped(worst, last[2]) else None
            feasible = bool(np.all(C <= tol))
            value = float(res.fun)
            if feasible:
                status = 'converged'
                if not kkt_stop:
                    break
                objective = value - float(np.sum(lam * (alpha - F)))
                if best_feasible is None or objective < best_feasible[0]:
                    best_feasible = (objective, theta.copy(), lam.copy(), jac)
                if kkt_residuals(prob, F, lam, jac, alpha_aim, alpha_stop, objective,
                                 config).reached:
                    best_feasible = None     # a KKT point: this iterate
                    break
            if budget is not None and prob.n_evaluations >= budget:
                status = 'evaluation_budget_exhausted'
                break
            if (not config.relative_step and prev is not None
                    and abs(value - prev) < config.objective_tol):
                status = 'converged' if feasible else 'stalled_infeasible'
                break
            prev = value
            last = (theta.copy(), lam.copy(), worst)
            lam = multiplier_update(lam, F, eta, alpha_aim, config,
                                    None if best_feasible is None else config.kkt_log_decrease)
        if best_feasible is not None:
            # kkt not reached: the feasible iterate of lowest objective (the last one may
            # have lost feasibility while the multipliers came down)
            _, theta, lam, jac = best_feasible
            feasible, status = True, 'converged'
        return theta, lam, jac, feasible, status, alpha_aim, alpha_stop

    # a warm start solves the checked rows at the levels its solve's check implied
    alpha = prob.alpha if start is None else carried_levels(prob, start.levels)
    theta, lam, jac, feasible, status, alpha_aim, alpha_stop = outer_loop(theta, lam, alpha)
    # The Gamma match's levels corrected by the saddle point (AdaptationConfig.tail 'auto',
    # points through the unscented transform): see level_correction.
    n_corrections = 0
    F_check, checked = prob.check_values(theta)
    while (feasible and n_corrections < config.max_level_corrections
           and (budget is None or prob.n_evaluations < budget)):
        alpha_new = corrected_levels(alpha, prob.alpha, _values(prob, theta), F_check, checked,
                                     config)
        if alpha_new is None:
            break
        n_corrections += 1
        alpha = alpha_new
        theta, lam, jac, feasible, status, alpha_aim, alpha_stop = outer_loop(theta, lam, alpha)
        F_check, checked = prob.check_values(theta)
    n_outer, n_inner, n_back = counts['outer'], counts['inner'], counts['back']
    mu, L, gamma = prob.unpack(theta)
    Sigma = L @ L.T
    adapted = prior.copy(mu, 0.5 * (Sigma + Sigma.T))
    kl = float(prob.kl(mu, L))
    F = _values(prob, theta)
    F_report = np.where(checked, np.minimum(F, F_check), F)
    reports = []
    for c, sl, law in zip(prob.constraints, prob.slices, prob.laws):
        p = float(np.min(F_report[sl]))
        reports.append(ConstraintReport(c.name, c.kind, c.alpha, p,
                                        p >= c.alpha - config.feasibility_tol,
                                        float(np.max(lam[sl])), law))
    if (feasible and config.max_level_corrections > 0
            and any(r.checked and r.probability < r.alpha for r in reports)):
        # the check still finds a checked row over its level (strictly: the stopping rule's
        # feasibility_tol is a tolerance of the optimiser's law, not of the check's), and no
        # re-solve is left (the corrections or the evaluation budget ran out): not an answer
        # at its confidence
        feasible, status = False, 'level_check_failed'
    if not feasible and all(r.satisfied for r in reports):
        # the stricter margin level was not reached, the constraints' own alpha was
        feasible, status = True, 'converged_without_margin'
    if not feasible and status == 'max_outer_reached':
        status = 'infeasible_or_unconverged'
    report = AdaptationReport(feasible, status, kl, kl / prior.n_basis, n_outer, n_inner,
                              prob.n_evaluations, time.perf_counter() - t_start, reports,
                              start='cold' if start is None else 'warm', n_backtracks=n_back,
                              n_level_corrections=n_corrections,
                              kkt=kkt_residuals(prob, F, lam, jac, alpha_aim, alpha_stop, kl,
                                                config),
                              state=_state(prob, theta, lam,
                                           implied_levels(prob.alpha, F, F_check, checked,
                                                          config)))
    return adapted, report


def _values(prob: Problem, theta: NDArray) -> NDArray:
    """F of every multiplier at ``theta`` (the inner loop's tail laws)."""
    F = prob.cached_values(theta)
    if F is None:
        mu, L, _ = prob.unpack(theta)
        F = prob.constraint_values(mu, L) if prob.n_values else np.zeros(0)
    return F


def corrected_levels(alpha: NDArray, alpha_asked: NDArray, F: NDArray, F_check: NDArray,
                     checked: NDArray, config: AdaptationConfig) -> Optional[NDArray]:
    """The levels of a re-solve whose Gamma-matched rows meet the asked level under the
    saddle-point law, or None when no row needs (or can get) a tighter level.

    A row of a point through the unscented transform is solved with the Gamma match (see
    ``AdaptationConfig.tail``), whose tail can be several times lighter than the saddle point
    of the same Gaussian (which agrees with sampled trajectories). Where a solve ended with a
    row's saddle-point violation v_s above its allowed confidence_margin (1 - alpha), the
    row's Gamma level becomes (1 - alpha) v_g / (v_s k), v_g its Gamma violation there and
    k = 1 + feasibility_tol / (1 - alpha) the stopping rule's tolerance (it accepts k times
    the level): the level at which the saddle point ends within 1 - alpha, tolerance
    included, if the ratio of the two laws stays what it is near the solution (the next
    check says whether it did). Never looser than the current level, never tighter than
    1 / :data:`MAX_LEVEL_RATIO` of the asked one.

    Parameters
    ----------
    alpha, alpha_asked : (n_values,)
        The levels of the last solve and the asked ones.
    F, F_check : (n_values,)
        Satisfaction probabilities of the inner loop's laws and of the check
        (:meth:`Problem.check_values`) at the solution.
    checked : (n_values,) bool
        The rows the check covers.
    """
    v_asked = 1.0 - alpha_asked
    v_check = 1.0 - F_check
    need = checked & (v_check > config.confidence_margin * v_asked)
    if not np.any(need):
        return None
    v = 1.0 - alpha
    target = _level_target(v_asked, F, F_check, config)
    v_new = np.where(need, np.clip(np.minimum(v, target), v_asked / MAX_LEVEL_RATIO, None), v)
    if np.all(v_new[need] >= v[need]):
        return None
    return 1.0 - v_new


def duality_gap(lam: NDArray, F: NDArray, alpha_aim: NDArray) -> float:
    """sum_i lambda_i max(F_i - alpha'_i, 0): what the multipliers still pay for slack
    above the aim level (0 at a KKT point of the problem at alpha')."""
    return float(np.sum(lam * np.maximum(F - alpha_aim, 0.0))) if lam.size else 0.0


def kkt_residuals(prob: Problem, F: NDArray, lam: NDArray, jac: Optional[NDArray],
                  alpha_aim: NDArray, alpha_stop: NDArray, objective: float,
                  config: AdaptationConfig) -> KKTResiduals:
    """The :class:`~cdmp_ros.core.adaptation.config.KKTResiduals` of an iterate with
    constraint values ``F`` and multipliers ``lam`` (``jac``: the Lagrangian's gradient where
    the inner loop ended; None: not known, reported as NaN)."""
    gap = duality_gap(lam, F, alpha_aim)
    rel = gap / max(1.0, objective)
    binding = tuple(float((1.0 - np.min(F[sl])) / (1.0 - c.alpha))
                    for c, sl in zip(prob.constraints, prob.slices))
    feas = float(np.max(np.maximum(alpha_stop - F, 0.0))) if F.size else 0.0
    stat = float(np.max(np.abs(jac))) if jac is not None and jac.size else float('nan')
    reached = bool(rel <= config.kkt_tol
                   and feas <= config.feasibility_tol * config.confidence_margin)
    return KKTResiduals(gap, rel, stat, feas, binding, reached)


def _state(prob: Problem, theta: NDArray, lam: NDArray,
           levels: Optional[NDArray] = None) -> SolverState:
    """The optimiser's variables as a :class:`SolverState` (multipliers by constraint;
    ``levels``: the rows' levels for the next solve, kept for the constraints where they
    differ from the asked ones)."""
    pairs = tuple(zip(prob.constraints, prob.slices))
    kept = () if levels is None else tuple(
        (c.name, levels[sl].copy()) for c, sl in pairs if np.any(levels[sl] != prob.alpha[sl]))
    return SolverState(theta.copy(), tuple((c.name, lam[sl].copy()) for c, sl in pairs), kept)


def carried_levels(prob: Problem, levels) -> NDArray:
    """The levels a warm start solves ``prob`` at: the asked ones, tightened to the
    ``levels`` of a :class:`SolverState` (by constraint name, where the size matches)."""
    alpha = prob.alpha.copy()
    known = dict(levels)
    for c, sl in zip(prob.constraints, prob.slices):
        a = known.get(c.name)
        if a is not None and a.size == sl.stop - sl.start:
            alpha[sl] = np.maximum(alpha[sl], a)
    return alpha


def implied_levels(alpha_asked: NDArray, F: NDArray, F_check: NDArray, checked: NDArray,
                   config: AdaptationConfig) -> NDArray:
    """The levels at which the Gamma-matched rows of a solution would meet the asked level
    under the saddle-point law, for the next solve of a nearby problem (a warm start).

    The level of :func:`corrected_levels`, computed afresh from the two laws' ratio at the
    solution rather than from the levels the solve used, so a stream of warm starts carries
    no tightening that its problems no longer need: (1 - alpha) v_g / (v_s k) for a checked
    row whose saddle-point violation v_s is at least :data:`CARRY_FRACTION` of the asked
    1 - alpha (far from its level the two tails' ratio says nothing about it there), clipped
    to [1 / :data:`MAX_LEVEL_RATIO`, 1] times the asked 1 - alpha; the asked level elsewhere.
    The check after the next solve still decides: it tightens further where this was not
    enough (it never loosens).
    """
    v_asked = 1.0 - alpha_asked
    v_check = 1.0 - F_check
    near = checked & (v_check >= CARRY_FRACTION * v_asked)
    if not np.any(near):
        return alpha_asked.copy()
    target = _level_target(v_asked, F, F_check, config)
    v = np.where(near, np.clip(target, v_asked / MAX_LEVEL_RATIO, v_asked), v_asked)
    return 1.0 - v


def _level_target(v_asked: NDArray, F: NDArray, F_check: NDArray,
                  config: AdaptationConfig) -> NDArray:
    """(1 - alpha) v_g / (v_s k) per row: the Gamma violation at which the saddle point's
    ends within the asked 1 - alpha (tolerance k = 1 + feasibility_tol / (1 - alpha) of the
    stopping rule included) if the two laws' ratio v_g / v_s stays what it is at ``F`` and
    ``F_check`` (:func:`corrected_levels`, :func:`implied_levels`)."""
    v_gamma = np.maximum(1.0 - F, 0.0)
    k = 1.0 + config.feasibility_tol / np.maximum(v_asked, 1e-300)
    return v_asked * v_gamma / (np.maximum(1.0 - F_check, 1e-300) * k)


def multiplier_update(lam: NDArray, F: NDArray, eta: NDArray, alpha_aim: NDArray,
                      config: AdaptationConfig,
                      max_log_decrease: Optional[float] = None) -> NDArray:
    """One step of the exponential method of multipliers (Algorithm 1, paper 003):
    lambda * exp(eta (alpha' - F)), with alpha' the aim level (``violation_target``).

    With ``config.relative_step`` the exponent is divided by 1 - alpha' and clipped to
    [-max_log_decrease, max_log_step] (:class:`AdaptationConfig`; ``max_log_decrease``
    overrides the config's: ``kkt_log_decrease`` once the ``kkt`` rule has a feasible
    iterate); otherwise the paper's step.
    """
    C_aim = alpha_aim - F
    if config.relative_step:
        down = config.max_log_decrease if max_log_decrease is None else max_log_decrease
        step = np.clip(eta * C_aim / (1.0 - alpha_aim), -down, config.max_log_step)
    else:
        step = eta * C_aim
    return lam * np.exp(step)


def monte_carlo_satisfaction(promp: ProMP, constraints: Sequence, n_samples: int,
                             rng: np.random.Generator, n_steps: int = 101
                             ) -> Tuple[NDArray, NDArray, float]:
    """Monte-Carlo check of the constraints on trajectories sampled from ``promp`` (the
    satisfaction frequencies of :func:`cdmp_ros.core.adaptation.verification.verify`).

    Returns
    -------
    per_time_min : (n_constraints,)
        For each constraint, the worst per-time satisfaction frequency ('each') or the
        frequency of satisfying it somewhere in its support ('max'/weight constraints).
    whole : (n_constraints,)
        Frequency of trajectories satisfying the constraint at every time of its support.
    all_ok : float
        Frequency of trajectories satisfying every constraint (1 - violation rate).
    """
    ver = verify(promp, constraints, n_samples, rng, n_steps)
    per_time = np.array([1.0 - c.per_step_max for c in ver.constraints])
    whole = np.array([1.0 - c.trajectory for c in ver.constraints])
    return per_time, whole, 1.0 - ver.trajectory_violation
