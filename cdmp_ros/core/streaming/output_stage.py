"""The output stage: every published reference inside position, velocity, acceleration and jerk
limits, as a robot's controller sees it (differences of consecutive commands on their stamps).

:class:`OutputStage` follows a target position per tick (the primitive's reference) with a
discrete triple integrator whose state *is* the published stream::

    a_k = a_{k-1} + j_k dt,   v_k = v_{k-1} + a_k dt,   p_k = p_{k-1} + v_k dt

so ``v_k = (p_k - p_{k-1}) / dt``, ``a_k`` and ``j_k`` are exactly the first, second and third
backward differences of the published positions, and bounding ``j_k`` bounds all of them.
Each tick the jerk is chosen in three steps:

1. **Tracking** (the candidate): the target's own discrete differences are the feed-forward
   (a target that respects the limits is reproduced exactly, with no lag); an error is closed
   by a cascade of square-root controllers (position error -> velocity, velocity error ->
   acceleration, each along the braking curve of the next limit; linear near zero, with
   poles at ``-bandwidth``), so large errors are closed at the limits without overshoot.
   A target that outruns the limits is not chased: its velocity and acceleration enter
   clipped to the limits, and the feed-forward fades out beyond the linear region of the
   position error. Once a resting target can be landed on within the limits in three ticks,
   it is (a held reference is then published exactly, at zero velocity).
2. **Limits** as an interval of admissible jerks: ``|j| <= J``, ``|a| <= A``, the velocity
   viability ``v + a|a| / 2J`` inside ``[-V, V]`` (the velocity still reachable once the
   acceleration is ramped to zero), and the **braking-aware position guard**: after the tick,
   a maximal brake (jerk ``-J`` to ``-A``, then ``-A`` until at rest) must stop before
   ``upper - margin`` (and symmetrically before the lower limit). The brake's stopping
   distance is the closed form of the continuous motion (:func:`brake_excursion`); the
   discrete motion under the same jerk sequence stops no later (its velocity is a right
   Riemann sum of a decreasing acceleration), so the bound is conservative on the grid.
   The guard's jerk bound is found by bisection only when the candidate breaks it.
3. A last clamp of the position into ``[lower, upper]``, which only a state made infeasible
   from outside (limits tightened while moving) can reach; it is flagged ``CLAMPED``.

Non-finite targets are held (the last target is kept). The tick works on Python floats in
preallocated lists (7 joints: numpy call overhead would dominate), allocates nothing and never
raises.
"""
import math
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_limits

__all__ = ['OutputStage', 'brake_excursion', 'sqrt_controller', 'DEFAULT_BANDWIDTH']

#: Poles of the tracking error's linear region [1/s] (time constant ~ 1 / bandwidth).
DEFAULT_BANDWIDTH = 30.0
#: Fraction of what the feed-forward leaves of the acceleration limit (and of the jerk limit)
#: that the error loops plan with; the clamps of step 2 absorb the rest (a lower authority
#: overshoots a spiking target more, none overshoots on steps;
#: ``benchmarks/bench_output_stage.py``).
ERROR_AUTHORITY = 0.9
#: Least fraction of the acceleration limit the position loop plans with (a target at its
#: limit leaves nothing; the error must still close).
MIN_AUTHORITY = 0.1
#: Bisection steps of the position guard (the jerk interval shrinks 2^-k).
GUARD_ITERATIONS = 24


def sqrt_controller(x: float, k: float, limit: float) -> float:
    """``k x`` near zero, ``sign(x) sqrt(2 limit (|x| - limit / 2k^2))`` beyond ``limit / k^2``.

    The command that closes an error ``x`` along the braking curve of a second-order limit
    (continuous in value and slope at the switch).
    """
    lin = limit / (k * k)
    if x > lin:
        return math.sqrt(2.0 * limit * (x - 0.5 * lin))
    if x < -lin:
        return -math.sqrt(2.0 * limit * (-x - 0.5 * lin))
    return k * x


def brake_excursion(v: float, a: float, amax: float, jmax: float) -> float:
    """How far further forward (in ``+``) the motion goes under a maximal brake.

    The brake: jerk ``-jmax`` until the acceleration is ``-amax``, then ``-amax``, until the
    velocity is zero (continuous time, from velocity ``v`` and acceleration ``a``). Returns
    ``max(0, position at rest - position now)``; for the ``-`` direction call it with
    ``(-v, -a)``.
    """
    a = min(a, amax) if a > -amax else -amax
    # the velocity under jerk -J: v + a t - J t^2 / 2; it is positive somewhere ahead only
    # if the discriminant is positive
    disc = a * a + 2.0 * jmax * v
    if disc <= 0.0 or (v <= 0.0 and a <= 0.0):
        return 0.0
    t1 = (a + amax) / jmax  # acceleration reaches -amax
    ts = (a + math.sqrt(disc)) / jmax  # velocity reaches zero under the ramp alone
    if ts <= t1:
        return max(0.0, ts * (v + ts * (0.5 * a - ts * jmax / 6.0)))
    v1 = v + t1 * (a - 0.5 * jmax * t1)
    x1 = t1 * (v + t1 * (0.5 * a - t1 * jmax / 6.0))
    return max(0.0, x1 + 0.5 * v1 * v1 / amax)


class OutputStage:
    """Jerk-limited tracking of a target with a braking-aware position guard.

    Parameters
    ----------
    lower, upper : array-like, shape (n_dims,)
        Position limits; published positions stay inside ``[lower + margin, upper - margin]``.
    max_velocity, max_acceleration, max_jerk : array-like, shape (n_dims,)
        Positive limits; ``inf`` disables one (the jerk limit must be finite when the position
        guard is to brake in time: an infinite jerk is treated as ``1e12``).
    dt : float
        Period of the published stream [s].
    bandwidth : float
        Poles of the tracking error [1/s].
    margin : float
        Distance [rad or m] kept from the position limits.

    Attributes
    ----------
    p, v, a, j : list of float, length n_dims
        The last published position and its first, second and third backward differences.
    """

    def __init__(self, lower: ArrayLike, upper: ArrayLike, max_velocity: ArrayLike,
                 max_acceleration: ArrayLike, max_jerk: ArrayLike, dt: float,
                 bandwidth: float = DEFAULT_BANDWIDTH, margin: float = 1e-6):
        lo, hi = check_limits(lower, upper)
        n = self.n_dims = lo.size
        self.lower, self.upper = lo, hi
        self.dt = float(dt)
        if not (self.dt > 0.0 and math.isfinite(self.dt)):
            raise ValidationError(f'dt: expected a positive period [s], got {dt!r}')
        lims = []
        for name, value in (('max_velocity', max_velocity),
                            ('max_acceleration', max_acceleration), ('max_jerk', max_jerk)):
            arr = as_array(name, value, (n,), finite=False)
            if not np.all(arr > 0.0) or np.any(np.isnan(arr)):
                raise ValidationError(f'{name}: expected positive limits, got {arr.tolist()}')
            lims.append(np.minimum(arr, 1e12))
        self.max_velocity, self.max_acceleration, self.max_jerk = lims
        if not (bandwidth > 0.0 and math.isfinite(bandwidth)):
            raise ValidationError(f'bandwidth: expected a positive rate [1/s], got {bandwidth!r}')
        self.bandwidth = float(bandwidth)
        half = 0.5 * (hi - lo)
        if not (0.0 <= margin < float(np.min(half))):
            raise ValidationError(f'margin: expected 0 <= margin < half the smallest range '
                                  f'{float(np.min(half)):.6g}, got {margin!r}')
        self._lo = lo.tolist()
        self._hi = hi.tolist()
        self._glo = (lo + margin).tolist()
        self._ghi = (hi - margin).tolist()
        self._V, self._A, self._J = (x.tolist() for x in lims)
        self.p = [0.0] * n
        self.v = [0.0] * n
        self.a = [0.0] * n
        self.j = [0.0] * n
        # the target's last position and its differences (feed-forward)
        self._r = [0.0] * n
        self._rv = [0.0] * n
        self._ra = [0.0] * n
        self._restart = [False] * n
        self.clamped = 0   # ticks on which the last clamp acted (a state made infeasible)
        self.limited = 0   # ticks on which the limits changed the tracking jerk

    def set_limits(self, max_velocity: Sequence[float], max_acceleration: Sequence[float],
                   max_jerk: Sequence[float]) -> None:
        """New velocity, acceleration and jerk limits (positive; ``inf``: none), from the
        next tick on. A state beyond the new limits is brought inside at the jerk limit (the
        admissible interval is then the nearest bound, never a jump)."""
        for name, arr in (('max_velocity', max_velocity),
                          ('max_acceleration', max_acceleration), ('max_jerk', max_jerk)):
            if len(arr) != self.n_dims or not all(x > 0.0 for x in arr):
                raise ValidationError(f'{name}: expected {self.n_dims} positive limits, got '
                                      f'{list(arr)}')
        self._V = [min(float(x), 1e12) for x in max_velocity]
        self._A = [min(float(x), 1e12) for x in max_acceleration]
        self._J = [min(float(x), 1e12) for x in max_jerk]
        self.max_velocity = np.array(self._V)
        self.max_acceleration = np.array(self._A)
        self.max_jerk = np.array(self._J)

    # -- state ------------------------------------------------------------------------------
    def reset(self, p: Sequence[float], v: Sequence[float] = (), a: Sequence[float] = ()
              ) -> None:
        """Start at position ``p`` (clipped into the guarded limits), with velocity ``v`` and
        acceleration ``a`` (default rest); the target starts there too."""
        n = self.n_dims
        for d in range(n):
            x = float(p[d])
            if not math.isfinite(x):
                x = 0.5 * (self._lo[d] + self._hi[d])
            self.p[d] = min(max(x, self._glo[d]), self._ghi[d])
            # velocity and acceleration start within their limits
            vv = float(v[d]) if len(v) == n and math.isfinite(v[d]) else 0.0
            aa = float(a[d]) if len(a) == n and math.isfinite(a[d]) else 0.0
            self.v[d] = min(max(vv, -self._V[d]), self._V[d])
            self.a[d] = min(max(aa, -self._A[d]), self._A[d])
            self._restart[d] = False
            self.j[d] = 0.0
            self._r[d] = self.p[d]
            self._rv[d] = self.v[d]
            self._ra[d] = self.a[d]

    def retarget(self, r: Sequence[float]) -> None:
        """The target continues from ``r`` at rest (a target that jumps by design, such as a
        primitive restarted at the measured position): its first step then differs by the
        target's own motion only, not by the jump."""
        for d in range(self.n_dims):
            x = float(r[d])
            if math.isfinite(x):
                self._r[d] = x
                self._rv[d] = 0.0
                self._ra[d] = 0.0

    @property
    def position(self) -> NDArray[np.float64]:
        return np.array(self.p)

    # -- the tick ---------------------------------------------------------------------------
    def update(self, target: Sequence[float]) -> int:
        """One period: move toward ``target`` (length n_dims); returns the number of joints on
        which the limits changed the tracking jerk (0: the target was followed as planned).

        Never raises; non-finite targets hold the last one.
        """
        dt = self.dt
        inv = 1.0 / dt
        k_v = 2.0 * self.bandwidth   # velocity loop; position loop k_v / 4: critical damping
        k_p = 0.25 * k_v
        limited = 0
        p, v, a, jj = self.p, self.v, self.a, self.j
        restart = self._restart
        R, RV, RA = self._r, self._rv, self._ra
        for d in range(self.n_dims):
            r = target[d]
            if not math.isfinite(r):
                r = R[d]
            pd, vd, ad = p[d], v[d], a[d]
            if restart[d]:  # after the last clamp: on from rest (see step 3)
                restart[d] = False
                vd = ad = 0.0
            V, A, J = self._V[d], self._A[d], self._J[d]
            # the error of the last tick against the target as far as it can be followed
            # (its velocity within the limit: a target that outruns the limits is not chased)
            rv0 = RV[d]
            rv0 = V if rv0 > V else (-V if rv0 < -V else rv0)
            ep, ev = pd - R[d], vd - rv0
            rv = (r - R[d]) * inv
            ra = (rv - RV[d]) * inv
            # 1. tracking: the target's acceleration is fed forward only on a tick on which
            # the target itself keeps the limits (a jump or a spike is not followed by its own
            # acceleration: the stage could not undo it in time), and fades beyond the linear
            # region of the error; the cascade on the error gets what the feed-forward leaves
            if abs(ra) <= A and abs(ra - RA[d]) <= J * dt and abs(rv) <= V:
                lin = ERROR_AUTHORITY * A / (k_p * k_p)
                ea = abs(ep)
                if ea > lin:
                    ra_ff = ra * lin / ea
                else:
                    ra_ff = ra
                ep_next = ep + ev * dt   # where the last error drifts in this tick
            else:
                # not fed forward: the error is taken against the new target at once, so the
                # stage reacts on this tick (an obstacle's coupling is reflected at once)
                ra_ff = 0.0
                rvc = V if rv > V else (-V if rv < -V else rv)
                ep_next, ev = pd + vd * dt - r, vd - rvc
            R[d], RV[d], RA[d] = r, rv, ra
            ra = ra_ff
            a_err = max(ERROR_AUTHORITY * (A - abs(ra)), MIN_AUTHORITY * A)
            ev_des = -sqrt_controller(ep_next, k_p, a_err)
            ea_des = sqrt_controller(ev_des - ev, k_v, ERROR_AUTHORITY * J)
            a_des = ra + ea_des
            j = (a_des - ad) * inv
            if not math.isfinite(j):
                j = 0.0
            # 2. the admissible interval of jerks
            jlo, jhi = -J, J
            x_lo, x_hi = (-A - ad) * inv, (A - ad) * inv  # acceleration
            jlo, jhi = _intersect(jlo, jhi, x_lo, x_hi)
            # velocity viability: a_next within [amin_v, amax_v]
            room = V - vd
            amax_v = (room * inv if room <= 0.0
                      else -J * dt + math.sqrt(J * J * dt * dt + 2.0 * J * room))
            room = V + vd
            amin_v = (-room * inv if room <= 0.0
                      else J * dt - math.sqrt(J * J * dt * dt + 2.0 * J * room))
            jlo, jhi = _intersect(jlo, jhi, (amin_v - ad) * inv, (amax_v - ad) * inv)
            # braking-aware position guard (only evaluated where it can bind)
            jhi2 = self._guard(_EXCESS_HIGH, d, pd, vd, ad, jhi, jlo)
            jlo2 = self._guard(_EXCESS_LOW, d, pd, vd, ad, jlo, jhi)
            if jlo2 <= jhi2:
                jlo, jhi = jlo2, jhi2
            else:  # cannot honour both: brake toward the nearer limit
                jlo = jhi = jhi2 if vd > 0.0 else jlo2
            jc = jhi if j > jhi else (jlo if j < jlo else j)
            if jc != j:
                limited += 1
            ad = ad + jc * dt
            vd = vd + ad * dt
            pn = pd + vd * dt
            if rv == 0.0 and ra == 0.0 and self._lands(d, r, pd, v[d], a[d]):
                # a resting target close enough to be reached, and rest kept, within the
                # limits in three ticks: land on it (a held reference is then published
                # unchanged at zero velocity, not approached forever)
                pn = r
                vd = (pn - pd) * inv
                ad = (vd - v[d]) * inv
                jc = (ad - a[d]) * inv
            # 3. the last clamp (only a state made infeasible from outside reaches it)
            if not self._lo[d] < pn < self._hi[d] or not math.isfinite(pn):
                self.clamped += 1
                pn = min(max(pn, self._glo[d]), self._ghi[d]) if math.isfinite(pn) else pd
                vd = (pn - pd) * inv
                ad = (vd - v[d]) * inv
                jc = (ad - a[d]) * inv
                # published as it is (the differences the positions imply), but continued from
                # rest: the state that broke the limits is not carried on (it would swing
                # between the limits with a growing amplitude)
                restart[d] = True
            p[d], v[d], a[d], jj[d] = pn, vd, ad, jc
        if limited:
            self.limited += 1
        return limited

    def _lands(self, d: int, r: float, pd: float, vd: float, ad: float) -> bool:
        """Whether stepping onto ``r`` now and resting there from the next tick on (three
        ticks: position, velocity, acceleration each become exact) keeps every limit."""
        if not self._glo[d] <= r <= self._ghi[d]:
            return False
        inv = 1.0 / self.dt
        V, A, J = self._V[d], self._A[d], self._J[d]
        v1 = (r - pd) * inv
        a1 = (v1 - vd) * inv
        a2 = -v1 * inv
        return (abs(v1) <= V and abs(a1) <= A and abs(a2) <= A
                and abs(a1 - ad) * inv <= J and abs(a2 - a1) * inv <= J and abs(a2) * inv <= J)

    def _next_excess_high(self, d: int, pd: float, vd: float, ad: float, j: float) -> float:
        """How far the brake after a tick with jerk ``j`` would end beyond the upper guard."""
        dt = self.dt
        an = ad + j * dt
        vn = vd + an * dt
        return pd + vn * dt + brake_excursion(vn, an, self._A[d], self._J[d]) - self._ghi[d]

    def _next_excess_low(self, d: int, pd: float, vd: float, ad: float, j: float) -> float:
        dt = self.dt
        an = ad + j * dt
        vn = vd + an * dt
        return self._glo[d] - (pd + vn * dt - brake_excursion(-vn, -an, self._A[d],
                                                              self._J[d]))

    def _guard(self, excess, d, pd, vd, ad, want, fallback) -> float:
        """The jerk between ``fallback`` and ``want`` nearest ``want`` after which the brake
        stops inside the guard, ``excess(self, d, pd, vd, ad, j) <= 0`` (``fallback`` if none
        does: the strongest brake available). Upper guard: :meth:`_next_excess_high`, ``want``
        ``jhi``, ``fallback`` ``jlo``; lower guard: :meth:`_next_excess_low`, ``jlo``, ``jhi``
        (the excess is monotonic in the jerk: bisection)."""
        if excess(self, d, pd, vd, ad, want) <= 0.0:
            return want
        if excess(self, d, pd, vd, ad, fallback) > 0.0:
            return fallback
        ok, bad = fallback, want   # excess(ok) <= 0 < excess(bad)
        for _ in range(GUARD_ITERATIONS):
            mid = 0.5 * (ok + bad)
            if excess(self, d, pd, vd, ad, mid) <= 0.0:
                ok = mid
            else:
                bad = mid
        return ok


#: The excess functions of the two position guards (plain functions: no bound method per call).
_EXCESS_HIGH = OutputStage._next_excess_high
_EXCESS_LOW = OutputStage._next_excess_low


def _intersect(lo: float, hi: float, lo2: float, hi2: float):
    """``[lo, hi] & [lo2, hi2]``; if empty, the end of ``[lo, hi]`` nearest the second."""
    nlo, nhi = max(lo, lo2), min(hi, hi2)
    if nlo <= nhi:
        return nlo, nhi
    x = hi if hi2 > hi else lo   # the second lies entirely above or below
    return x, x
