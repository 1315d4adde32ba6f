"""Settings of the constrained ProMP adaptation (paper 003, Algorithm 1) and its report, and the
configuration of the adapter node (the slow path of the node graph), without ROS.

:class:`AdaptationConfig` and :class:`AdaptationReport`: the optimiser's settings and result.
Two more frozen dataclasses, mirrored 1:1 by the ROS parameters of the ``adapter`` node
(:mod:`cdmp_ros.ros.adapter_node`): :class:`AdapterConfig` (inputs, validation, visualisation;
top-level parameters) and :class:`AdaptRequestConfig` (how obstacles, goals and the current
state become a constrained ProMP adaptation problem, paper 003; parameters ``adaptation.*``).
Ranges and descriptions live in the field metadata (used for the parameter descriptors).
"""
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.config_fields import (accept_unstamped_param, check_chain_fields,
                                         check_fields, check_names, max_json_bytes_param,
                                         max_obstacles_param, obstacle_distance_param,
                                         obstacle_size_param, param as _param,
                                         robot_description_param,
                                         robot_description_timeout_param, stamp_age_param,
                                         stamp_lead_param, tcp_offset_param, tip_link_param,
                                         tip_links_param,
                                         urdf_path_param)
from cdmp_ros.core.adaptation.verification_report import GUARANTEES, Verification
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.builders import PANDA_JOINTS
from cdmp_ros.core.validation import check_positive


#: Ranges of the settings a constraint set may override (its schema's "optimizer", the
#: adapter's ROS parameters): bounded so that a file cannot ask for unbounded work.
RANGES = {'n_steps': (2, 1000), 'max_outer': (1, 100), 'max_inner': (1, 10000),
          'lambda0': (1e-6, 1e6), 'eta': (1e-6, 100.0), 'kappa': (0.0, 1e6)}
_INTEGERS = ('n_steps', 'max_outer', 'max_inner')
#: ConstraintReport.law of Gamma-matched rows checked by the saddle point (tail 'auto').
CHECKED_LAW = 'gamma, saddle-point checked'
#: ConstraintReport.law of Gamma-matched rows whose check samples the point's true law
#: (AdaptationConfig.check_law 'sampled').
SAMPLED_CHECK_LAW = 'gamma, importance-sampled check'
#: What checks the Gamma-matched rows (AdaptationConfig.check_law).
CHECK_LAWS = ('sampled', 'saddlepoint')
#: The 'sampled' check samples the rows whose saddle-point violation is at least this
#: fraction of their allowed 1 - alpha (far below it the rows do not move any level).
SAMPLED_CHECK_FRACTION = 0.1
#: Approximations of the law of quadratic forms (AdaptationConfig.tail).
TAILS = ('auto', 'saddlepoint', 'gamma', 'conservative')


#: When the outer loop of the solver stops (AdaptationConfig.stop_rule).
STOP_RULES = ('feasible', 'kkt')
#: Largest sampled verification a file or a parameter may ask for.
MAX_VERIFICATION_SAMPLES = 1_000_000


@dataclass(frozen=True)
class AdaptationConfig:
    """Optimiser settings (defaults: the authors' Table II settings, promp_benchmark_protocol).

    Parameters
    ----------
    n_steps : int
        Time grid s = linspace(0, 1, n_steps) on which path constraints are imposed.
    lambda0 : float
        Initial Lagrange multiplier of constraints without their own (Section III).
    eta : float
        EMM multiplier learning rate.
    max_outer : int
        Maximum number of multiplier (outer) updates.
    max_inner : int
        Maximum L-BFGS iterations per inner loop.
    objective_tol : float
        With the paper's absolute EMM step: stop (as infeasible) when the Lagrangian changes by
        less than this between outer iterations.
    feasibility_tol : float
        A constraint counts as satisfied when F >= alpha - feasibility_tol.
    kappa : float
        Weight of the smoothness regulariser kappa * E[R(w)] (Eq. 14-15); 0 disables it.
    smoothness_weights : tuple of float, optional
        Per-dimension weights of R(w) (default all 1).
    kl_blocks : tuple of (start, stop), optional
        Use the sum of the marginal KLs of these weight blocks (mutual avoidance objective
        (ii), Section II-E5) instead of the joint KL.
    ut_alpha : float
        Spread of the unscented transform's sigma points.
    lbfgs_ftol, lbfgs_gtol : float
        L-BFGS-B convergence tolerances of the inner loop.
    lbfgs_maxcor : int
        Number of L-BFGS correction pairs.
    lbfgs_ftol_first : float, optional
        Inexact early inner loops: outer iteration r (1-based) uses
        ftol = max(lbfgs_ftol, lbfgs_ftol_first * 10^-(r-1)) (None: lbfgs_ftol throughout).
        While the multipliers are far from their final values a precise inner solve is
        wasted; the final iterations are as precise as before.
    confidence_margin : float
        In (0, 1]: the optimiser enforces every constraint at the stricter confidence
        alpha_m = 1 - confidence_margin (1 - alpha) under the approximation (stopping rule and
        EMM), while the report still checks alpha; ``feasibility_tol`` is scaled by it. 1 (the
        default) is the paper's rule. With the saddle-point tail (``tail``) and linear points
        of interest the per-step levels are calibrated without it (Tables II-IV,
        test_core_promp_calibration); it remains a margin against other approximations, such
        as the unscented transform's Gaussian for strongly non-linear points of interest
        (mutual avoidance of two arms: per-step violations up to 5 (1 - alpha) at margin 1).
        Constraint sets set it as ``optimizer.confidence_margin``.
    violation_target : float
        Confidence margin of the EMM updates, in (0, 1]: the multipliers aim at the violation
        probability violation_target * (1 - alpha) (the step uses
        alpha' = 1 - violation_target (1 - alpha) in place of alpha), while the stopping rule
        (and ``converged``) still only requires F >= alpha - feasibility_tol. A target below 1
        overshoots slightly, so the outer loop typically stops after one or two multiplier
        updates instead of creeping up to alpha, at the price of a slightly larger KL; it
        also absorbs part of the Gamma approximation's underestimated tails.
    relative_step : bool
        EMM step lambda <- lambda exp(eta C / (1 - alpha)) (clipped to +-max_log_step) instead
        of the paper's lambda exp(eta C), C = alpha - F. With alpha close to 1 the paper's step
        changes lambda by at most a factor exp(1 - alpha) once F is near alpha, so a constraint
        that is almost satisfied stays slightly violated; the relative step is scale free.
    max_log_step : float
        Clip of the relative step's exponent (multiplier increases: at most a factor
        exp(max_log_step) per outer iteration).
    max_log_decrease : float
        Clip of the relative step's exponent for decreases: a multiplier falls by at most a
        factor exp(-max_log_decrease) per outer iteration. Per-step constraints are coupled
        in time: once the steps that were violated get larger multipliers, the worst step
        often moves to a neighbour; with a symmetric clip (the former behaviour,
        max_log_decrease = max_log_step = 3) that neighbour's multiplier has meanwhile
        shrunk by up to e^-1 per iteration (its constraint held with slack), and the
        violation returns there. A slow decrease (default 0.3, a factor 0.74) keeps them,
        which cuts the slowest solves without changing the median, the converged count or
        the KL (``benchmarks/bench_adaptation_solve.py``).
    tail : {'auto', 'saddlepoint', 'gamma', 'conservative'}
        Probability law of the quadratic forms |x_t - c|^2 (repellers, waypoints, unbound
        waypoints, mutual avoidance) and w^T Phi_R w (smoothness constraint): 'saddlepoint'
        evaluates the generalised chi-square law by the Lugannani-Rice saddle-point
        approximation, accurate in the tails a confidence alpha asks about (a few per cent
        relative error for violation probabilities 1e-4 ... 1e-2); 'gamma' is paper 003's
        moment match (Eq. 15), whose lighter tail lets the sampled per-step violations
        exceed 1 - alpha. 'auto' (default): the saddle point where the Gaussian of the
        point of interest is exact (linear points: coordinates of a Cartesian ProMP, joints;
        and smoothness), the Gamma match for points through the unscented transform. There
        the Gaussian itself is the larger error, and with the accurate tail the optimiser can
        lower the approximate collision probability by inflating the joint variance until the
        unscented Gaussian no longer describes the arm (the planar 4-link repeller of
        test_core_promp_planar fails that way with 'saddlepoint', not with 'gamma', whose
        small-shape lower tail penalises a wide distribution). 'conservative': per row the
        larger violation of the two laws; it behaves as 'gamma' on the planar arm and brings
        the ProMP demo's end-effector violation close to 1 - alpha; not yet the default of
        link points. Under 'auto' the Gamma-matched rows are checked by the saddle point of
        the same Gaussian after the solve, and their levels corrected where it shows more
        violation than allowed (``max_level_corrections``).
    max_level_corrections : int
        'auto' tail: how many times a solve whose Gamma-matched rows violate more than
        confidence_margin (1 - alpha) under the saddle-point law is re-solved, warm, with
        those rows' levels tightened by the ratio of the two laws there
        (:func:`~cdmp_ros.core.adaptation.solver.corrected_levels`; at most 20 times the
        asked level). 0: no check (the Gamma match alone, paper 003's Eq. 15). Default 2.
    check_law : {'sampled', 'saddlepoint'}
        What the check of the Gamma-matched rows reads. 'saddlepoint': the saddle point of
        the unscented Gaussian (the same moments, another tail), whose own error stays: at
        the ProMP demo's link points the sampled violation of warm answers was up to 1.7
        times what it read. 'sampled' (default): the repeller rows (obstacles, mutual
        avoidance) the saddle point puts at :data:`SAMPLED_CHECK_FRACTION` of their allowed
        1 - alpha or more are estimated by
        importance sampling of the point's true law (its joints' marginal is exact, the
        kinematics are not linearised; :mod:`cdmp_ros.core.adaptation.tail_sampling`,
        ``check_samples`` draws per row, the same draws at every check), and the check
        reads the estimate plus one standard error; the other rows keep the saddle point.
    check_samples : int
        Draws per row of the 'sampled' check (default 1024: ~10 % standard error at a
        violation of 1e-3 on the Panda's link points).
    whiten : bool
        Precondition the parameters with the prior's Cholesky factor L0: mu = mu0 + L0 nu,
        L = L0 L~, L~ = L~_tril + diag(exp(gamma~)). L stays lower triangular with
        diag(L) = diag(L0) exp(gamma~), so this is the paper's parameterisation up to a fixed
        linear map; the KL becomes 0.5 (|L~|_F^2 + |nu|^2 - n) - 1^T gamma~, perfectly
        conditioned, which cuts the L-BFGS iterations.
    guarantee : {'per_step', 'trajectory'}
        What each constraint's alpha claims: ``per_step`` (paper 003: every time step of its
        support holds with probability alpha) or ``trajectory`` (the whole trajectory
        satisfies every constraint at every step with probability min(alpha)); with
        ``trajectory`` the per-step levels are tightened until the sampled check confirms it
        (:mod:`cdmp_ros.core.adaptation.guarantee`).
    verification_samples : int, optional
        Trajectories of the sampled verification in every report
        (:mod:`cdmp_ros.core.adaptation.verification`); None: the default by the cost of the
        points of interest (:func:`cdmp_ros.core.adaptation.guarantee.default_samples`:
        without kinematics 10,000-100,000, enough for the per-step test to catch twice the
        asked level). With ``trajectory`` at least 20 / (1 - alpha) are drawn, so that the
        bound can reach the level.
    max_refinements : int
        ``trajectory``: tightenings of the per-step levels (re-solves) at most.
    stop_rule : {'feasible', 'kkt'}
        When the outer loop stops: ``feasible`` (default; the paper's rule) at the first
        iterate where every constraint holds; ``kkt`` only when, in addition, the slack
        the multipliers still pay for is small: the duality gap
        ``sum_i lambda_i max(F_i - alpha'_i, 0)`` (alpha' the aim level of
        ``violation_target``) is at most ``kkt_tol`` times ``max(1, KL)`` (complementary
        slackness: a row with a multiplier that matters sits at its level). Each further
        outer iteration lowers the multipliers of the rows with slack (at most
        ``max_log_decrease`` in log), so ``kkt`` costs outer iterations; the solve returns
        the feasible iterate of lowest objective. Residuals are reported either way
        (``AdaptationReport.kkt``).
    kkt_tol : float
        Relative duality gap of ``stop_rule='kkt'`` (a first-order bound of the KL still to
        gain, relative to the KL). 0.01: at 0.05 the unbound waypoints of Table III stopped
        with their worst step at a median 0.32-0.35 of the allowed violation (binding but
        cheap in KL), at 0.01 at 0.53-0.61, for ~30 % more evaluations.
    kkt_log_decrease : float
        ``stop_rule='kkt'``, once an iterate was feasible: the clip of the relative step's
        decreases in place of ``max_log_decrease`` (the multipliers of rows with slack come
        down by up to exp(-kkt_log_decrease) per outer iteration; Table II at alpha 0.99:
        median 7 outer iterations to the KKT point with 1.0, 20 with 0.3).
    max_evaluations : int, optional
        Evaluations of the Lagrangian at most over the whole solve (None: bounded by
        ``max_outer`` and ``max_inner`` only); a solve that reaches it ends with status
        ``evaluation_budget_exhausted``. L-BFGS-B checks it between its iterations, so the
        evaluations of one line search may run over it. The adapter's warm starts use it
        (:mod:`cdmp_ros.core.adaptation.warm`).
    """
    n_steps: int = 101
    lambda0: float = 20.0
    eta: float = 1.0
    max_outer: int = 10
    max_inner: int = 500
    objective_tol: float = 1e-2
    feasibility_tol: float = 1e-4
    kappa: float = 0.0
    smoothness_weights: Optional[Tuple[float, ...]] = None
    kl_blocks: Optional[Tuple[Tuple[int, int], ...]] = None
    ut_alpha: float = 1.0
    lbfgs_ftol: float = 1e-6
    lbfgs_gtol: float = 1e-4
    lbfgs_maxcor: int = 20
    lbfgs_ftol_first: Optional[float] = 3e-3
    lbfgs_ftol_decay: float = 0.1
    violation_target: float = 0.6
    confidence_margin: float = 1.0
    relative_step: bool = True
    max_log_step: float = 3.0
    max_log_decrease: float = 0.3
    tail: str = 'auto'
    max_level_corrections: int = 2
    check_law: str = 'sampled'
    check_samples: int = 1024
    whiten: bool = True
    guarantee: str = 'per_step'
    verification_samples: Optional[int] = None
    max_refinements: int = 6
    max_evaluations: Optional[int] = None
    stop_rule: str = 'feasible'
    kkt_tol: float = 0.01
    kkt_log_decrease: float = 1.0

    def __post_init__(self):
        for name, (lo, hi) in RANGES.items():
            v = getattr(self, name)
            kind = int if name in _INTEGERS else float
            if isinstance(v, bool) or not isinstance(v, (int, float)) or (
                    kind is int and not float(v).is_integer()):
                what = 'an integer' if kind is int else 'a number'
                raise ValidationError(f'{name}: expected {what} in [{lo}, {hi}], got {v!r}')
            if not lo <= v <= hi:  # also refuses NaN
                raise ValidationError(f'{name}: expected a value in [{lo}, {hi}], got {v!r}')
        check_positive('objective_tol', self.objective_tol, allow_zero=True)
        check_positive('feasibility_tol', self.feasibility_tol, allow_zero=True)
        check_positive('kappa', self.kappa, allow_zero=True)
        check_positive('ut_alpha', self.ut_alpha)
        check_positive('max_log_step', self.max_log_step)
        check_positive('max_log_decrease', self.max_log_decrease)
        if self.lbfgs_ftol_first is not None:
            check_positive('lbfgs_ftol_first', self.lbfgs_ftol_first)
        if not 0.0 < float(self.confidence_margin) <= 1.0:
            raise ValidationError(f'confidence_margin: expected a value in (0, 1], '
                                  f'got {self.confidence_margin!r}')
        if self.tail not in TAILS:
            raise ValidationError(f'tail: expected one of {list(TAILS)}, got {self.tail!r}')
        if self.check_law not in CHECK_LAWS:
            raise ValidationError(f'check_law: expected one of {list(CHECK_LAWS)}, got '
                                  f'{self.check_law!r}')
        if self.stop_rule not in STOP_RULES:
            raise ValidationError(f'stop_rule: expected one of {", ".join(STOP_RULES)}, got '
                                  f'{self.stop_rule!r}')
        check_positive('kkt_tol', self.kkt_tol)
        check_positive('kkt_log_decrease', self.kkt_log_decrease)
        if not 0.0 < float(self.violation_target) <= 1.0:
            raise ValidationError(f'violation_target: expected a value in (0, 1], '
                                  f'got {self.violation_target!r}')
        if self.guarantee not in GUARANTEES:
            raise ValidationError(f'guarantee: expected one of {list(GUARANTEES)}, got '
                                  f'{self.guarantee!r}')
        for name, lo, hi in (('verification_samples', 1, MAX_VERIFICATION_SAMPLES),
                             ('max_refinements', 0, 20), ('max_evaluations', 1, 10 ** 7),
                             ('max_level_corrections', 0, 10),
                             ('check_samples', 16, 1 << 16)):
            v = getattr(self, name)
            if v is None and name in ('verification_samples', 'max_evaluations'):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or \
                    not float(v).is_integer() or not lo <= v <= hi:
                raise ValidationError(f'{name}: expected an integer in [{lo}, {hi}], got {v!r}')

    def resolved_tail(self, linear: bool) -> str:
        """The tail law used for a point of interest (``linear``: exact Gaussian moments)."""
        if self.tail != 'auto':
            return self.tail
        return 'saddlepoint' if linear else 'gamma'


@dataclass(frozen=True)
class SolverState:
    """The optimiser's variables at the end of a solve: theta (whitened parameters of
    :class:`~cdmp_ros.core.adaptation.problem.Problem`, relative to its prior) and the
    multipliers lambda of each constraint, by name. A solve of a problem with the same prior
    can start from it (``solve_levels(..., start=state)``): its constraints of the same name
    and size start from these multipliers, the others from their ``lambda0``.

    ``levels``: per constraint, by name, the levels of its rows that the saddle point's check
    of the Gamma match implied at the end of the solve (``AdaptationConfig.tail`` 'auto';
    :func:`~cdmp_ros.core.adaptation.solver.implied_levels`), for the constraints that have
    such rows. A warm start solves those rows at these levels from the start (never looser
    than asked), so that a request close to the last one needs no re-solve of its own."""
    theta: NDArray[np.float64]
    multipliers: Tuple[Tuple[str, NDArray[np.float64]], ...]
    levels: Tuple[Tuple[str, NDArray[np.float64]], ...] = ()


@dataclass
class ConstraintReport:
    name: str
    kind: str
    alpha: float
    probability: float      # the approximation's satisfaction probability (worst time)
    satisfied: bool
    lagrange_max: float
    #: the law of ``probability``: 'gaussian' (a linear form: joint limits, hyperplanes,
    #: corners), the quadratic forms' ``AdaptationConfig.tail`` ('saddlepoint', 'gamma',
    #: 'conservative'), or under 'auto' for points through the unscented transform
    #: :data:`CHECKED_LAW`: solved with the Gamma match, ``probability`` the lower of it and
    #: of the saddle point's check of the same Gaussian (``max_level_corrections``), or
    #: :data:`SAMPLED_CHECK_LAW`: the check sampled the point's true law where the saddle
    #: point found the row near its level (``check_law``)
    law: str = ''

    @property
    def checked(self) -> bool:
        """Whether a check corrected the Gamma match (:data:`CHECKED_LAW`,
        :data:`SAMPLED_CHECK_LAW`)."""
        return self.law in (CHECKED_LAW, SAMPLED_CHECK_LAW)


@dataclass(frozen=True)
class KKTResiduals:
    """How far an iterate is from a KKT point of min KL s.t. F >= alpha' (alpha' the aim
    level of ``violation_target``).

    ``gap``: the duality gap sum_i lambda_i max(F_i - alpha'_i, 0) (KL units: what the
    multipliers still pay for slack), ``gap_relative`` = gap / max(1, KL);
    ``stationarity``: the largest entry of the Lagrangian's gradient in the (whitened)
    parameters where the inner loop ended; ``feasibility``: the largest violation
    max(alpha_stop - F, 0) of the stopping level; ``binding``: per constraint, its worst
    row's violation probability over its allowed 1 - alpha (1: at its level; the
    complementary slackness of a constraint whose multiplier matters asks for about
    ``violation_target``); ``reached``: the ``kkt`` stopping rule's test held.
    """
    gap: float
    gap_relative: float
    stationarity: float
    feasibility: float
    binding: Tuple[float, ...]
    reached: bool

    def as_dict(self) -> dict:
        return {'gap': self.gap, 'gap_relative': self.gap_relative,
                'stationarity': self.stationarity, 'feasibility': self.feasibility,
                'binding': list(self.binding), 'reached': self.reached}


@dataclass
class AdaptationReport:
    """Outcome of :func:`~cdmp_ros.core.adaptation.guarantee.adapt` (``as_dict``:
    ``cdmp adapt --json``; ``to_text``: its summary).

    Attributes
    ----------
    converged : bool
        Every constraint holds at its confidence under the approximation and the sampled
        ``verification`` confirms it; False for infeasible or unconverged problems.
    status : str
        ``converged``, ``converged_without_margin``, ``max_outer_reached``,
        ``stalled_infeasible``, ``infeasible_or_unconverged``, ``evaluation_budget_exhausted``,
        ``level_check_failed`` (feasible under the Gamma match, but the check of its rows
        still finds one over its level, strictly, when no re-solve is left:
        ``max_level_corrections`` or the evaluation budget ran out) or
        ``verification_failed``.
    kl, kl_per_basis : float
        KL(adapted || prior), and divided by the number of weights D * M.
    n_outer, n_inner, n_evaluations : int
        Multiplier updates, L-BFGS iterations and Lagrangian evaluations.
    time_s : float
        Wall time of the solve and its verification [s].
    constraints : list of ConstraintReport
        Per constraint: name, kind, alpha, approximate probability at the worst time,
        satisfied, largest multiplier.
    guarantee : {'per_step', 'trajectory'}
    verification : Verification or None
        The sampled check of the adapted distribution.

    The other fields (levels, warm starts, KKT residuals, solver state) are commented in the
    source.
    """
    converged: bool
    status: str
    kl: float
    kl_per_basis: float
    n_outer: int
    n_inner: int
    n_evaluations: int
    time_s: float
    constraints: List[ConstraintReport] = field(default_factory=list)
    guarantee: str = 'per_step'
    #: sampled check of the adapted distribution (cdmp_ros.core.adaptation.verification)
    verification: Optional[Verification] = None
    #: guarantee ``trajectory``: the check that selected the returned solution among the
    #: solves (``verification`` re-checks it on fresh samples); None otherwise
    selection_verification: Optional[Verification] = None
    #: per constraint (order of ``constraints``), the per-step violation level 1 - alpha'
    #: the optimiser enforced (guarantee ``trajectory``: tightened below 1 - alpha)
    levels: List[float] = field(default_factory=list)
    #: solves of the optimiser (guarantee ``trajectory``: 1 + refinements of the levels)
    n_solves: int = 1
    #: where the optimiser started: ``cold`` (the prior, multipliers lambda0) or ``warm``
    #: (an earlier solution; :mod:`cdmp_ros.core.adaptation.warm`), with the reason of a cold
    #: start that replaced a warm one in ``start_note``
    start: str = 'cold'
    start_note: str = ''
    #: outer iterations whose multiplier step was halved and retried from the last iterate
    #: (:data:`cdmp_ros.core.adaptation.solver.BACKTRACK_GROWTH`)
    n_backtracks: int = 0
    #: re-solves whose Gamma levels the saddle point's check tightened
    #: (AdaptationConfig.max_level_corrections)
    n_level_corrections: int = 0
    #: KKT residuals of the returned iterate (:class:`KKTResiduals`); None when the solve
    #: did not get to an iterate (trajectory guarantee: those of the returned solve)
    kkt: Optional['KKTResiduals'] = None
    #: where the optimiser ended (whitened parameters and multipliers), the start of a warm
    #: solve of the next request; not part of :meth:`as_dict`
    state: Optional['SolverState'] = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d.pop('state', None)
        d['constraints'] = [dict(c.__dict__) for c in self.constraints]
        d['verification'] = None if self.verification is None else self.verification.as_dict()
        d['selection_verification'] = (None if self.selection_verification is None
                                       else self.selection_verification.as_dict())
        d['levels'] = list(self.levels)
        d['kkt'] = None if self.kkt is None else self.kkt.as_dict()
        return d

    def to_text(self) -> str:
        lines = [f'status: {self.status} (converged: {self.converged})',
                 f'KL(p || p0) = {self.kl:.6g} ({self.kl_per_basis:.4g} per basis function)',
                 f'outer iterations: {self.n_outer}, L-BFGS iterations: {self.n_inner}, '
                 f'evaluations: {self.n_evaluations}, time: {self.time_s * 1e3:.1f} ms']
        for c in self.constraints:
            lines.append(f'  {c.name} [{c.kind}]: P = {c.probability:.6f} '
                         f'(alpha = {c.alpha}) {"ok" if c.satisfied else "VIOLATED"}'
                         f'{f" [{c.law}]" if c.law else ""}')
        if self.n_level_corrections:
            by = ('importance sampling' if any(c.law == SAMPLED_CHECK_LAW
                                               for c in self.constraints)
                  else 'the saddle point')
            lines.append(f'Gamma levels corrected by {by}: '
                         f'{self.n_level_corrections} re-solve(s)')
        if self.kkt is not None:
            k = self.kkt
            lines.append(f'KKT: duality gap {k.gap:.3g} ({k.gap_relative:.3g} of max(1, KL)), '
                         f'stationarity {k.stationarity:.3g}, feasibility {k.feasibility:.3g}'
                         f'{" (KKT point)" if k.reached else ""}; worst step over its '
                         'allowed violation: ' + ', '.join(
                             f'{c.name} {b:.2f}' for c, b in zip(self.constraints, k.binding)))
        if self.guarantee != 'per_step':
            lines.append(f'guarantee: {self.guarantee} ({self.n_solves} solves); per-step '
                         'violation levels enforced: ' + ', '.join(
                             f'{c.name} {v:.3g}' for c, v in zip(self.constraints, self.levels)))
        if self.verification is not None:
            sel = self.selection_verification
            if sel is not None:
                lines.append('re-checked on fresh samples (the check that selected it: '
                             f'{sel.trajectory_violation * 100:.3f} %, upper bound '
                             f'{sel.trajectory_violation_upper95 * 100:.3f} %):')
            lines.append(self.verification.to_text())
        return '\n'.join(lines)


@dataclass(frozen=True)
class AdapterConfig:
    """Parameters of the adapter node (top level); see the field descriptions."""

    joint_names: Tuple[str, ...] = _param(
        PANDA_JOINTS, 'Joints of the robot, in the order of the published primitives.',
        read_only=True)
    urdf_path: str = urdf_path_param('limits, kinematics of the points of interest and of '
                                     'the IK')
    tip_link: str = tip_link_param()
    tip_links: Tuple[str, ...] = tip_links_param()
    tcp_offset: Tuple[float, ...] = tcp_offset_param()
    robot_description: str = robot_description_param()
    robot_description_timeout: float = robot_description_timeout_param()
    base_frame: str = _param(
        'panda_link0', 'Robot base frame: obstacles and goal_point must be given in it (or '
        'with an empty frame_id).', read_only=True)
    max_stamp_age: float = stamp_age_param()
    max_stamp_lead: float = stamp_lead_param()
    accept_unstamped: bool = accept_unstamped_param()
    max_input_rate: float = _param(
        50.0, 'Messages per second accepted on each of primitive, obstacles, goal, goal_point '
        'and constraints (a 30 Hz obstacle tracker fits); the excess is dropped and reported '
        '(flooding); the solver itself takes the newest request only.', 0.1, 10000.0)
    max_json_bytes: int = max_json_bytes_param()
    max_obstacles: int = max_obstacles_param()
    max_obstacle_size: float = obstacle_size_param()
    max_obstacle_distance: float = obstacle_distance_param()
    goal_margin: float = _param(
        1e-3, 'Goals outside the limits are clipped to centre +- (1 - goal_margin) * half '
        'range (the CDMP margin).', 1e-9, 0.5)
    joint_states_tolerance: float = _param(
        0.05, 'joint_states further than this [rad] outside the limits are rejected.',
        0.0, 1.0)
    joint_states_timeout: float = _param(
        1.0, 'joint_states older than this [s] are not used as the start of an adaptation '
        '(the ProMP is then not conditioned on the current state).', 0.001, 3600.0)
    ik_tolerance: float = _param(
        1e-3, 'A goal_point is reachable when the IK leaves at most this position error [m].',
        1e-6, 0.1)
    ik_max_iter: int = _param(200, 'Iterations of the damped least-squares IK per seed.',
                              1, 10000)
    retarget_dmp_on_goal: bool = _param(
        True, 'With a DMP / CDMP primitive, publish an adapted primitive with the new goal for '
        'goal messages too (goal_point always is). False leaves joint goals to the streamer, '
        'which subscribes goal itself and moves the goal without restarting the movement.')
    diagnostics_period: float = _param(0.5, 'Period of the diagnostics messages [s].',
                                       0.01, 60.0)
    path_points: int = _param(
        50, 'Points of the planned end-effector path (LINE_STRIP on visualization).', 2, 1000)
    band_points: int = _param(
        10, 'Uncertainty spheres of a ProMP on visualization (0 = none).', 0, 200)
    band_sigma: float = _param(
        2.0, 'Radius of the uncertainty spheres in standard deviations of the end effector.',
        0.1, 10.0)

    def __post_init__(self):
        check_fields(self)
        check_names('joint_names', self.joint_names)
        check_chain_fields(self)


@dataclass(frozen=True)
class AdaptRequestConfig:
    """How the adapter builds the constrained ProMP problem (paper 003); ``adaptation.*``."""

    alpha: float = _param(
        0.999, 'Confidence of the obstacle and joint-limit constraints (required satisfaction '
        'probability at every time step).', 0.5, 0.999999)
    obstacle_margin: float = _param(
        0.02, 'Clearance added to every obstacle (sphere radius, box faces) [m].', 0.0, 1.0)
    influence_distance: float = _param(
        0.3, 'An obstacle constrains the points of interest (and balls of avoid_links) '
        'that come within this distance [m] of it along the prior mean path; one farther '
        'from all of them is left out of the problem.', 0.0, 100.0)
    avoid_links: Tuple[str, ...] = _param(
        ('panda_link4', 'panda_hand'), 'Links that avoid obstacles besides the end effector '
        '(the Panda elbow and its hand by default), as their collision geometry '
        '(link_geometry) or their frame origin.')
    link_geometry: bool = _param(
        True, 'true: each link of avoid_links keeps obstacle_margin clear with all of its '
        'collision geometry (balls covering the capsule fitted to its URDF <collision>, as '
        'the capsules of the streamer parameter coupling_capsule_links); false: with its '
        'frame origin only (a link '
        'with no collision geometry needs false).')
    arm_clearance: float = _param(
        0.0, 'A robot of several arms (tip_links): every point of one arm (its tool centre '
        'point and its avoid_links: their balls with link_geometry, else their origins) '
        'keeps at least this distance [m] from every point of another arm, with probability '
        'alpha at every step (paper 003 Eq. 22, mutual avoidance; between the surfaces of '
        'the balls, or between the points). 0: no constraint between the arms.', 0.0, 10.0)
    joint_limits: bool = _param(
        True, 'Constrain every joint to the robot limits (paper 003 Eq. 12).')
    condition_start: bool = _param(
        True, 'Condition the ProMP on the current joint_states at phase 0 (when available) '
        'for a request that starts a motion (a new primitive or goal); one that reshapes the '
        'running motion (obstacles, constraints) is not conditioned there.')
    start_var: float = _param(
        1e-4, 'Observation variance of the start conditioning [rad^2].', 1e-10, 1.0)
    goal_var: float = _param(
        1e-4, 'Observation variance of the goal conditioning at phase 1 [rad^2].', 1e-10, 1.0)
    n_steps: int = _param(
        50, 'Time steps on which the path constraints are imposed.', 2, 1000)
    max_outer: int = _param(10, 'Multiplier (outer) updates of the optimiser at most.', 1, 100)
    max_inner: int = _param(300, 'L-BFGS iterations per inner loop at most.', 1, 10000)
    lambda0: float = _param(20.0, 'Initial Lagrange multiplier.', 1e-6, 1e6)
    guarantee: str = _param(
        'per_step', 'What alpha guarantees: per_step (paper 003: each time step holds with '
        'probability alpha) or trajectory (the whole trajectory satisfies every constraint '
        'with probability alpha; per-step levels are tightened until a sampled check '
        'confirms it). A constraint set\'s "guarantee" overrides it.', choices=GUARANTEES)
    verification_samples: int = _param(
        0, 'Sampled trajectories of the verification of every solve (0: the default by the '
        'kinematics cost, at most 100,000 forward-kinematics evaluations, 1,000 to 10,000).',
        0, MAX_VERIFICATION_SAMPLES)
    warm_start: bool = _param(
        True, "Start a request's solve from the last converged solution when only obstacles "
        'moved (same primitive, constraints and settings; every obstacle moved at most '
        'warm_start_distance): a tracked obstacle costs a few evaluations instead of a full '
        'solve (cdmp_ros.core.adaptation.warm).')
    warm_start_distance: float = _param(
        0.1, 'Largest move of any obstacle [m] between two requests for a warm start.',
        0.0, 10.0)
    warm_start_kl_ratio: float = _param(
        2.0, "After a warm solve whose KL exceeds this times the last cold solve's (+ 1), "
        'a cold solve checks it (the warm result is kept): the refinement, off the request '
        'path, or without warm_start_refine the next request, started cold.',
        1.0, 100.0)
    warm_start_max_evaluations: int = _param(
        30, 'Evaluations of the Lagrangian a warm solve may take before the request is '
        'solved cold instead.', 1, 10000)
    warm_start_check_max_evaluations: int = _param(
        600, "Evaluations the KL guard's cold check may take: a refinement over all its "
        'resumptions (then the warm solution stays), or without warm_start_refine the next '
        "request's cold solve (then it is solved from the warm start the guard withheld).",
        1, 100000)
    warm_start_predict: bool = _param(
        True, 'An obstacle moving by the same displacement as in the last request (constant '
        'velocity): start the warm solve from the secant prediction of the last two warm '
        'solutions.')
    warm_start_refine: bool = _param(
        True, 'When the solver is idle after a warm solve, solve the same request cold and '
        'publish the result if its KL is at least 5 % lower. A newer request suspends it; '
        'it resumes on that request after its warm solve, from where it was.')

    def __post_init__(self):
        check_fields(self)
        check_names('avoid_links', self.avoid_links, allow_empty=True)
