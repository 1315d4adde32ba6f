"""The reflex of a real arm, without ROS: every received reference checked against the joint
limits, as a Franka Panda checks the commands of its 1 kHz interface.

A real arm differentiates consecutive commands: a Panda stops with a reflex error when they
break its velocity, acceleration or jerk limits, or command a position outside its range.
:class:`ReflexMonitor` does the same for a stream of stamped references:

- the differences are ``k!`` times the divided differences of consecutive positions on their
  own stamps (the definition of :func:`cdmp_ros.core.run_metrics.stamped_differences`: exact
  for a cubic whatever the gaps; on an exact grid of period ``dt`` they are the first, second
  and third backward differences divided by ``dt^k``)::

      v_k = (q_k - q_{k-1}) / h_k,                          h_k = t_k - t_{k-1}
      a_k = (v_k - v_{k-1}) / ((h_k + h_{k-1}) / 2)
      j_k = (a_k - a_{k-1}) / ((h_k + h_{k-1} + h_{k-2}) / 3)

- a reference violates the limits when a position is outside ``[lower, upper]`` or a
  difference exceeds its limit by more than the relative ``tolerance`` (the rounding of
  stamps; 2 % as :func:`~cdmp_ros.core.run_metrics.kinematic_report`);
- the first reference after the start or a :meth:`ReflexMonitor.reset`, and a reference whose
  stamp is not after the previous one, only (re-)seed the history: their position is checked,
  their differences are not (the orders come back one reference after another);
- mode ``count``: a violating reference is counted and passes; mode ``stop``: the first one
  trips the reflex (the robot halts, as a Panda does) and every further reference is refused
  until :meth:`ReflexMonitor.reset`.

The check runs for every reference (up to 1-2 kHz): it works on Python floats in preallocated
lists and allocates only when it reports a violation.

Typical use::

    monitor = ReflexMonitor(limits, tolerance=0.02, mode='stop')
    status, violations = monitor.update(stamp_ns, q)      # q in limits.joint_names order
    if status == STOP:       # this reference tripped the reflex: halt the robot
        ...
    elif status in (ACCEPTED, VIOLATION):
        ...                  # apply the reference
"""
import math
from typing import Dict, NamedTuple, Sequence, Tuple

from cdmp_ros.core.errors import ValidationError

__all__ = ['ReflexMonitor', 'ReflexViolation', 'ORDERS', 'MODES', 'ACCEPTED', 'VIOLATION',
           'STOP', 'REFUSED', 'DEFAULT_TOLERANCE', 'describe_violations']

#: The orders checked, in the order reported.
ORDERS = ('position', 'velocity', 'acceleration', 'jerk')
#: ``count``: violations are counted and the reference passes; ``stop``: the first one halts.
MODES = ('count', 'stop')
#: Relative slack of the difference checks (stamps rounded to the nanosecond, positions to
#: float64; equal to :data:`cdmp_ros.core.run_metrics.KINEMATIC_TOLERANCE`).
DEFAULT_TOLERANCE = 0.02

#: Status of :meth:`ReflexMonitor.update`: the reference respects the limits.
ACCEPTED = 0
#: It violates them and passes (mode ``count``).
VIOLATION = 1
#: It violates them and trips the reflex (mode ``stop``): halt, refuse the following ones.
STOP = 2
#: It arrived while the reflex holds: refused, not checked.
REFUSED = 3

_NO_VIOLATIONS: Tuple = ()


class ReflexViolation(NamedTuple):
    """One limit broken by one reference.

    Attributes
    ----------
    joint : str
    order : str
        One of :data:`ORDERS`.
    value : float
        The position [rad or m], or the difference of that order [rad/s^k].
    limit : float
        The bound passed (position: the lower or upper limit; else the positive limit).
    ratio : float
        Position: ``|q - centre| / half-range`` (above 1: outside); else ``|value| / limit``.
    """

    joint: str
    order: str
    value: float
    limit: float
    ratio: float

    def __str__(self) -> str:
        if self.order == 'position':
            return (f'{self.joint} position {self.value:.6g} outside the limit '
                    f'{self.limit:.6g}')
        return (f'{self.joint} {self.order} {self.value:.6g} exceeds the limit '
                f'{self.limit:.6g} ({self.ratio:.3g} times)')


def describe_violations(violations: Sequence[ReflexViolation], most: int = 3) -> str:
    """One line: the ``most`` worst violations (by ratio) and how many more there are."""
    if not violations:
        return 'none'
    worst = sorted(violations, key=lambda v: -v.ratio)
    text = '; '.join(str(v) for v in worst[:most])
    if len(worst) > most:
        text += f' (+{len(worst) - most} more)'
    return text


class ReflexMonitor:
    """Checks every received reference against a :class:`~cdmp_ros.core.joint_limits.
    KinematicLimits` (see the module docstring).

    Parameters
    ----------
    limits : KinematicLimits
        The limits in force; references carry positions in ``limits.joint_names`` order.
    tolerance : float
        Relative slack of the velocity, acceleration and jerk checks, in [0, 1).
    mode : str
        ``'count'`` or ``'stop'`` (:data:`MODES`).

    Attributes
    ----------
    checked : int
        References checked (not the refused ones).
    errors : int
        References that violated at least one limit.
    counts : dict order -> int
        References that violated a limit of that order.
    worst : dict order -> float
        The largest ratio seen per order over every checked reference (position: the limit
        usage ``|q - centre| / half-range``; above ``1 + tolerance`` for the differences, or
        above 1 for the position, is a violation).
    refused : int
        References refused while the reflex held (mode ``stop``).
    stopped : bool
        The reflex holds (until :meth:`reset`).
    stop_reason : str
        What tripped it (empty when not stopped).
    last_error : str
        The violations of the last violating reference, one line (empty: none yet).
    """

    def __init__(self, limits, tolerance: float = DEFAULT_TOLERANCE, mode: str = 'count'):
        self.joint_names = tuple(limits.joint_names)
        n = self.n_dims = len(self.joint_names)
        self._lo = [float(x) for x in limits.lower]
        self._hi = [float(x) for x in limits.upper]
        self._centre = [0.5 * (lo + hi) for lo, hi in zip(self._lo, self._hi)]
        self._inv_half = [2.0 / (hi - lo) for lo, hi in zip(self._lo, self._hi)]
        # inverse limits: 0 where there is none (inf), so that the ratio is 0
        self._inv = tuple([0.0 if not math.isfinite(float(x)) else 1.0 / float(x)
                           for x in getattr(limits, order)]
                          for order in ORDERS[1:])
        self._lim = tuple([float(x) for x in getattr(limits, order)] for order in ORDERS[1:])
        self.set_tolerance(tolerance)
        self.set_mode(mode)
        self._q = [0.0] * n
        self._v = [0.0] * n
        self._a = [0.0] * n
        self.checked = 0
        self.errors = 0
        self.counts: Dict[str, int] = {o: 0 for o in ORDERS}
        self.worst: Dict[str, float] = {o: 0.0 for o in ORDERS}
        self.refused = 0
        self.stopped = False
        self.stop_reason = ''
        self.last_error = ''
        self.reset()

    # -- configuration ------------------------------------------------------------------------
    def set_tolerance(self, tolerance: float) -> None:
        """The relative slack of the difference checks, in [0, 1)."""
        tol = float(tolerance)
        if not 0.0 <= tol < 1.0:
            raise ValidationError(f'tolerance: expected a value in [0, 1), got {tolerance!r}')
        self.tolerance = tol
        self._over = 1.0 + tol

    def set_mode(self, mode: str) -> None:
        """``'count'`` or ``'stop'``; a reflex that holds keeps holding until :meth:`reset`."""
        if mode not in MODES:
            raise ValidationError(f'mode: expected one of {list(MODES)}, got {mode!r}')
        self.mode = mode

    def reset(self) -> None:
        """Clear the reflex; the next reference re-seeds the history (the counts stay)."""
        self._seen = 0      # references in the history since the (re)seed: 0 .. 3
        self._t = 0
        self._h1 = 0.0      # the last two stamp gaps [s]
        self._h2 = 0.0
        self.stopped = False
        self.stop_reason = ''

    # -- the check ----------------------------------------------------------------------------
    def update(self, stamp_ns: int, q: Sequence[float]) -> Tuple[int, Tuple[ReflexViolation, ...]]:
        """Check one reference; returns ``(status, violations)``.

        Parameters
        ----------
        stamp_ns : int
            Its stamp [ns].
        q : sequence of float, length n_dims
            Its positions in ``joint_names`` order (a list is fastest).

        Returns
        -------
        status : int
            :data:`ACCEPTED`, :data:`VIOLATION` (mode count), :data:`STOP` (mode stop: this
            reference tripped the reflex) or :data:`REFUSED` (the reflex holds: not checked).
        violations : tuple of ReflexViolation
            Empty unless the status is VIOLATION or STOP.
        """
        if self.stopped:
            self.refused += 1
            return REFUSED, _NO_VIOLATIONS
        if len(q) != self.n_dims:
            raise ValidationError(f'q: expected {self.n_dims} positions, got {len(q)}')
        self.checked += 1
        stamp_ns = int(stamp_ns)
        h = (stamp_ns - self._t) * 1e-9
        seen = self._seen if h > 0.0 else 0   # a gap that is not positive re-seeds
        bad = None
        worst = self.worst
        lo, hi, centre, inv_half = self._lo, self._hi, self._centre, self._inv_half
        Q, V, A = self._q, self._v, self._a
        over = self._over
        iv, ia, ij = self._inv
        # position, velocity, acceleration, jerk: the worst ratio of each over the joints
        wp = wv = wa = wj = 0.0
        if seen >= 1:
            inv_h = 1.0 / h
            inv_ha = 2.0 / (h + self._h1) if seen >= 2 else 0.0
            inv_hj = 3.0 / (h + self._h1 + self._h2) if seen >= 3 else 0.0
        for d in range(self.n_dims):
            x = float(q[d])
            r = abs(x - centre[d]) * inv_half[d]
            if r > wp:
                wp = r
            if not lo[d] <= x <= hi[d]:   # also NaN
                bad = self._add(bad, d, 'position', x, lo[d] if x < centre[d] else hi[d], r)
            if seen >= 1:
                v = (x - Q[d]) * inv_h
                r = abs(v) * iv[d]
                if r > wv:
                    wv = r
                if r > over:
                    bad = self._add(bad, d, 'velocity', v, self._lim[0][d], r)
                if seen >= 2:
                    a = (v - V[d]) * inv_ha
                    r = abs(a) * ia[d]
                    if r > wa:
                        wa = r
                    if r > over:
                        bad = self._add(bad, d, 'acceleration', a, self._lim[1][d], r)
                    if seen >= 3:
                        j = (a - A[d]) * inv_hj
                        r = abs(j) * ij[d]
                        if r > wj:
                            wj = r
                        if r > over:
                            bad = self._add(bad, d, 'jerk', j, self._lim[2][d], r)
                    A[d] = a
                V[d] = v
            Q[d] = x
        if wp > worst['position']:
            worst['position'] = wp
        if wv > worst['velocity']:
            worst['velocity'] = wv
        if wa > worst['acceleration']:
            worst['acceleration'] = wa
        if wj > worst['jerk']:
            worst['jerk'] = wj
        self._h2 = self._h1 if seen >= 1 else 0.0
        self._h1 = h if seen >= 1 else 0.0
        self._t = stamp_ns
        self._seen = seen + 1 if seen < 3 else 3
        if bad is None:
            return ACCEPTED, _NO_VIOLATIONS
        violations = tuple(bad)
        self.errors += 1
        for order in {v.order for v in violations}:
            self.counts[order] += 1
        self.last_error = describe_violations(violations)
        if self.mode == 'stop':
            self.stopped = True
            self.stop_reason = self.last_error
            return STOP, violations
        return VIOLATION, violations

    def _add(self, bad, d, order, value, limit, ratio):
        if bad is None:
            bad = []
        bad.append(ReflexViolation(self.joint_names[d], order, float(value), float(limit),
                                   float(ratio)))
        return bad

    # -- report -------------------------------------------------------------------------------
    def as_values(self) -> Dict[str, str]:
        """The figures as diagnostics key/values (strings): ``reflex`` (the mode),
        ``reflex_errors``, ``reflex_errors_<order>``, ``reflex_worst_ratio_<order>``,
        ``reflex_last_error``, ``reflex_stopped``, ``references_checked_reflex`` and
        ``references_refused_reflex``."""
        out = {'reflex': self.mode, 'reflex_errors': str(self.errors),
               'reflex_stopped': 'true' if self.stopped else 'false',
               'reflex_last_error': self.last_error,
               'reflex_tolerance': f'{self.tolerance:g}',
               'references_checked_reflex': str(self.checked),
               'references_refused_reflex': str(self.refused)}
        for order in ORDERS:
            out[f'reflex_errors_{order}'] = str(self.counts[order])
            out[f'reflex_worst_ratio_{order}'] = f'{self.worst[order]:.4f}'
        return out
