"""What the sampled verification of an adapted ProMP reports
(:func:`cdmp_ros.core.adaptation.verification.verify`): plain result types, kept apart from
the sampling (numpy, scipy) so that the adaptation settings and report
(:mod:`cdmp_ros.core.adaptation.config`) hold them without importing it.
"""
from dataclasses import dataclass, field
from typing import List

#: Meanings of alpha (constraint-set field ``guarantee``, parameter adaptation.guarantee).
GUARANTEES = ('per_step', 'trajectory')

#: Power at which :func:`~cdmp_ros.core.adaptation.verification.detectable_violation` states
#: what a test detects.
DETECTION_POWER = 0.95


@dataclass
class ConstraintVerification:
    """Sampled figures of one constraint (see :mod:`cdmp_ros.core.adaptation.verification`).

    Attributes
    ----------
    name, kind : str
    alpha : float
        The constraint's confidence.
    steps : int
        Time steps tested (1 for temporally unbound waypoints and weight constraints, whose
        event is one per trajectory).
    per_step_max : float
        Largest sampled per-step violation frequency.
    per_step_limit : float
        Critical frequency of the per-step rule (a larger per_step_max rejects the per-step
        level alpha beyond Monte Carlo noise).
    trajectory : float
        Fraction of samples violating the constraint at any step of its support.
    upper95 : float
        One-sided 95 % Clopper-Pearson upper bound of ``trajectory``.
    holds : bool
        The claimed level holds by the rule of the report's guarantee.
    detectable : float
        The smallest true violation probability (per step, or per trajectory with the
        trajectory guarantee) that the rule rejects with 95 % power
        (:func:`detectable_violation`).
    detectable_excess : float
        ``detectable / (1 - alpha)``: how many times the asked level a violation must be to
        be caught (below 1 for the trajectory rule, which is conservative).
    """
    name: str
    kind: str
    alpha: float
    steps: int
    per_step_max: float
    per_step_limit: float
    trajectory: float
    upper95: float
    holds: bool
    detectable: float = float('nan')
    detectable_excess: float = float('nan')


@dataclass
class Verification:
    """Result of :func:`~cdmp_ros.core.adaptation.verification.verify` (``cdmp adapt
    --json``: key ``verification``).

    Attributes
    ----------
    n_samples : int
        Sampled trajectories.
    guarantee : {'per_step', 'trajectory'}
        The claim checked (selects the decision rule).
    trajectory_violation, trajectory_violation_upper95 : float
        Fraction of samples violating any constraint at any step, and its one-sided 95 %
        Clopper-Pearson upper bound.
    holds : bool
        The claimed level holds by the rule of ``guarantee``.
    time_s : float
        Time of the check [s].
    constraints : list of ConstraintVerification
        One per constraint, in the order given.
    kinematics_fraction : float
        Fraction of (sample, step) pairs of chain points whose forward kinematics ran.
    """
    n_samples: int
    guarantee: str
    trajectory_violation: float
    trajectory_violation_upper95: float
    holds: bool
    time_s: float = 0.0
    constraints: List[ConstraintVerification] = field(default_factory=list)
    #: fraction of the (sample, step) pairs of chain points whose forward kinematics ran;
    #: the screen decided the others exactly (1.0 without chain points)
    kinematics_fraction: float = 1.0

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d['constraints'] = [dict(c.__dict__) for c in self.constraints]
        return d

    def to_text(self) -> str:
        claim = {'per_step': 'per-step level', 'trajectory': 'trajectory level'}[self.guarantee]
        lines = [f'sampled verification ({self.n_samples} trajectories, {self.time_s * 1e3:.1f} '
                 f'ms): trajectory-level violation {self.trajectory_violation * 100:.3f} % '
                 f'(95 % upper bound {self.trajectory_violation_upper95 * 100:.3f} %); '
                 f'{claim} {"holds" if self.holds else "NOT MET"}']
        for c in self.constraints:
            lines.append(f'  {c.name}: per-step max {c.per_step_max * 100:.3f} % (limit '
                         f'{c.per_step_limit * 100:.3f} %), trajectory {c.trajectory * 100:.3f} % '
                         f'(upper95 {c.upper95 * 100:.3f} %) {"ok" if c.holds else "NOT MET"}; '
                         f'detects {c.detectable_excess:.2g}x the asked level with '
                         f'{DETECTION_POWER * 100:.0f} % power')
        return '\n'.join(lines)

    @property
    def detectable_excess(self) -> float:
        """The largest :attr:`ConstraintVerification.detectable_excess` of the report (what
        its weakest test needs to catch a violation; nan without constraints)."""
        return max((c.detectable_excess for c in self.constraints), default=float('nan'))
