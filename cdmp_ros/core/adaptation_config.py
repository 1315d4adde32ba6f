"""Settings and report of the constrained ProMP adaptation (paper 003, Algorithm 1)."""
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import check_positive


#: Ranges of the settings a constraint set may override (its schema's "optimizer", the
#: adapter's ROS parameters): bounded so that a file cannot ask for unbounded work.
RANGES = {'n_steps': (2, 1000), 'max_outer': (1, 100), 'max_inner': (1, 10000),
          'lambda0': (1e-6, 1e6), 'eta': (1e-6, 100.0), 'kappa': (0.0, 1e6)}
_INTEGERS = ('n_steps', 'max_outer', 'max_inner')


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
        EMM), while the report still checks alpha. Below 1 it buys a margin against the
        approximation error (the Gamma approximation underestimates the tails of |x - c|^2,
        and a trajectory violates if any of its time steps does); 1 is the paper's rule.
        ``feasibility_tol`` is scaled by it.
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
        Clip of the relative step's exponent.
    whiten : bool
        Precondition the parameters with the prior's Cholesky factor L0: mu = mu0 + L0 nu,
        L = L0 L~, L~ = L~_tril + diag(exp(gamma~)). L stays lower triangular with
        diag(L) = diag(L0) exp(gamma~), so this is the paper's parameterisation up to a fixed
        linear map; the KL becomes 0.5 (|L~|_F^2 + |nu|^2 - n) - 1^T gamma~, perfectly
        conditioned, which cuts the L-BFGS iterations.
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
    whiten: bool = True

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
        if self.lbfgs_ftol_first is not None:
            check_positive('lbfgs_ftol_first', self.lbfgs_ftol_first)
        if not 0.0 < float(self.confidence_margin) <= 1.0:
            raise ValidationError(f'confidence_margin: expected a value in (0, 1], '
                                  f'got {self.confidence_margin!r}')
        if not 0.0 < float(self.violation_target) <= 1.0:
            raise ValidationError(f'violation_target: expected a value in (0, 1], '
                                  f'got {self.violation_target!r}')


@dataclass
class ConstraintReport:
    name: str
    kind: str
    alpha: float
    probability: float      # the approximation's satisfaction probability (worst time)
    satisfied: bool
    lagrange_max: float


@dataclass
class AdaptationReport:
    """Outcome of :func:`adapt`. ``converged`` is False for infeasible/unconverged problems."""
    converged: bool
    status: str
    kl: float
    kl_per_basis: float
    n_outer: int
    n_inner: int
    n_evaluations: int
    time_s: float
    constraints: List[ConstraintReport] = field(default_factory=list)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d['constraints'] = [dict(c.__dict__) for c in self.constraints]
        return d

    def to_text(self) -> str:
        lines = [f'status: {self.status} (converged: {self.converged})',
                 f'KL(p || p0) = {self.kl:.6g} ({self.kl_per_basis:.4g} per basis function)',
                 f'outer iterations: {self.n_outer}, L-BFGS iterations: {self.n_inner}, '
                 f'evaluations: {self.n_evaluations}, time: {self.time_s * 1e3:.1f} ms']
        for c in self.constraints:
            lines.append(f'  {c.name} [{c.kind}]: P = {c.probability:.6f} '
                         f'(alpha = {c.alpha}) {"ok" if c.satisfied else "VIOLATED"}')
        return '\n'.join(lines)
