"""Step-by-step (C)DMP integrator for streaming: ``update(input) -> (output, status)``.

The tick is small-vector work, so it runs on plain Python floats over preallocated lists: no
numpy call, no allocation of arrays. Everything that depends only on the phase is precomputed
when the stepper is (re)configured: the forcing profile ``phi_d(u) = sum_j phi_j(u) w_dj``
(Eq. 15-16/23-24) with its first and second derivatives at the nodes of a grid over the
normalised time ``u``, and the tick evaluates the quintic Hermite interpolant between two nodes
(six multiply-adds per joint). Beyond the last node the exponential tail of the basis is
evaluated exactly.

The grid's size does not depend on the duration: it is the coarser of

- the phase grid: ``m`` equal intervals over ``[0, U_END]``, ``m`` the smallest power of two
  from :data:`MIN_GRID_INTERVALS` to :data:`MAX_GRID_INTERVALS` at which the interpolation error
  of every basis feature (each in ``[0, 1]``) is at most :data:`FEATURE_TOL` (2048 for the
  default 30 kernels; :func:`grid_intervals`, a property of the basis alone), so the forcing of
  joint ``d`` is within ``FEATURE_TOL * sum_j |w_dj|`` of its exact value at every phase;
- the grid of the steps ``u_k = k dt / tau`` up to ``U_END`` when it has no more intervals (a
  short primitive): the forcing is then exact at every nominal step, as in earlier versions.

So a stepper holds at most ``3 (m + 1) n_dims`` floats whatever ``tau`` and ``dt`` (earlier
versions precomputed ``2 tau / dt`` rows: 165 MB for 300 s at 1 ms); ``feature_error`` reports
the interpolation error of its grid between the nodes.

The tick never raises: non-finite coupling entries are replaced by zero
(``StepStatus.INPUT_REJECTED``), accelerations and velocities are clamped to huge finite bounds,
and a CDMP's exogenous state is saturated at ``+-XI_SAT`` (``StepStatus.SATURATED``), so every
position is finite and, for a CDMP, strictly inside the limits.

Velocity-limit temporal coupling (beyond paper 000): with ``velocity_limits`` set, the whole
system runs in a warped time ``d sigma = kappa dt`` with ``0 < kappa <= 1``. After every step
``kappa = min(1, kappa_prev + recovery_rate * dt, min_d vmax_d / |yd_nominal_d|)``: it drops at
once when a joint would exceed its limit and recovers towards nominal speed at
``recovery_rate`` [1/s]. The reported velocity ``yd = kappa * yd_nominal`` never exceeds the
limits.
"""
import enum
import functools
import math
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.dmp.basis import PhaseBasis, U_END
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_positive

#: Relative back-off of the velocity-limited time scaling: reported |yd| <= vmax exactly.
VMAX_BACKOFF = 1.0 - 1e-12
#: Largest interpolation error of a basis feature (each in [0, 1]) on the forcing grid; the
#: forcing of joint d is then within FEATURE_TOL * sum_j |w_dj| of its exact value.
FEATURE_TOL = 1e-12
#: Fewest and most intervals of the forcing grid over [0, U_END] (powers of two).
MIN_GRID_INTERVALS = 256
MAX_GRID_INTERVALS = 16384
#: Largest normalised time accepted by :meth:`DmpStepper.reset` (larger ``phase_u`` is clamped
#: to it; the forcing has long vanished there).
MAX_PHASE_U = 1e9
#: Basis evaluations per chunk while building a grid (bounds the temporary memory).
_CHUNK = 1 << 16
#: Floor of ``1 - tanh(xi)^2`` in :func:`joint_coupling_to_exogenous` (the cap of the coupling
#: term near saturation).
SATURATION_FLOOR = 1e-2
#: Largest joint-space coupling entry accepted by :meth:`DmpStepper.set_joint_coupling`.
MAX_JOINT_COUPLING = 1e12


class StepStatus(enum.IntFlag):
    """Status flags of one tick (combinable)."""

    WORKING = 1           #: the nominal duration has not elapsed (u < 1)
    FINISHED = 2          #: u >= 1: the forcing has decayed, the system converges to the goal
    SATURATED = 4         #: a CDMP exogenous state hit the saturation bound this tick
    INPUT_REJECTED = 8    #: a non-finite coupling entry was replaced by zero
    VELOCITY_LIMITED = 16  #: the phase runs slower than nominal to respect velocity limits


_STATUS = [StepStatus(i) for i in range(32)]


class CouplingResult(enum.IntEnum):
    """What :meth:`DmpStepper.set_joint_coupling` did."""

    ZERO = 0       #: no coupling (None or all zeros): ``P = 0``
    APPLIED = 1    #: a non-zero coupling term was set
    REJECTED = 2   #: wrong length, not numbers, non-finite or huge: dropped, ``P = 0``


def joint_coupling_to_exogenous(dq_dd: Sequence[float], xi: Sequence[float], tau: float,
                                y_delta: Optional[Sequence[float]], out: List[float],
                                floor: float = SATURATION_FLOOR) -> None:
    """The coupling term ``P`` of the stepper from a joint acceleration change, into ``out``.

    CDMP (``y_delta`` given): Eq. (29), paper 000, at fixed ``(xi, xid)`` gives
    ``dxi_dd = dq_dd / (y_delta (1 - tanh(xi)^2))`` and Eq. (21) takes ``P = tau^2 dxi_dd``;
    DMP (``y_delta`` None): ``P = tau^2 dq_dd`` (Eq. 13).

    Cap near saturation: ``1 - tanh(xi)^2`` is floored at ``floor``, so
    ``|P| <= tau^2 |dq_dd| / (y_delta floor)``. Without it the divisor falls to ~2e-9 at the
    saturation bound ``XI_SAT``: a coupling that turns away from a limit the state was pushed
    into asks for an exogenous acceleration so large that ``xi`` crosses the whole range in one
    tick (a jump from one joint limit to the other; test_core_coupling.py). With the floor the
    coupling only acts attenuated, by ``(1 - tanh(xi)^2) / floor``, within
    ``1 - sqrt(1 - floor)`` (0.5 % for the default) of the half-range from a limit.
    ``floor = 0`` gives the uncapped map (divisor floored at 1e-300).

    Parameters
    ----------
    dq_dd : sequence of float (n_dims)
        Joint acceleration change [rad/s^2 or m/s^2].
    xi : sequence of float (n_dims)
        Current internal state (the exogenous state of a CDMP).
    tau : float
        Temporal scaling of the primitive.
    y_delta : sequence of float (n_dims), optional
        Half ranges of the CDMP's limits; None for a plain DMP.
    out : list of float (n_dims)
        Receives ``P``.
    """
    tau2 = tau * tau
    if y_delta is None:
        for d, a in enumerate(dq_dd):
            out[d] = tau2 * a
        return
    tanh = math.tanh
    for d, a in enumerate(dq_dd):
        t = tanh(xi[d])
        s = 1.0 - t * t
        if s < floor:
            s = floor
        out[d] = tau2 * a / max(y_delta[d] * s, 1e-300)  # Eq. (21)/(29), paper 000


def feature_derivatives(basis: PhaseBasis, u: ArrayLike):
    """Basis features and their first and second derivatives in the normalised time.

    With ``r_j = psi_j / sum_k psi_k`` (Eq. 17/25), ``q_j = d log psi_j / ds = -h_j (s - c_j)``
    and the ``r``-weighted mean ``q_bar`` and variance ``v`` of ``q``:
    ``dr_j/ds = r_j (q_j - q_bar)``, ``d2r_j/ds2 = r_j ((q_j - q_bar)^2 - h_j - v + sum_k r_k
    h_k)``; ``phi_j = s r_j`` (Eq. 16/24) and ``ds/du = -alpha_s s`` (Eq. 18/26) give
    ``dphi/du = -alpha_s s phi_s`` and ``d2phi/du2 = alpha_s^2 s (phi_s + s phi_ss)``. Beyond
    ``U_END`` the exponential tail of :class:`~cdmp_ros.core.dmp.basis.PhaseBasis`:
    ``-alpha_s phi`` and ``alpha_s^2 phi``.

    Parameters
    ----------
    basis : PhaseBasis
    u : array-like, shape (n,)
        Normalised times (>= 0).

    Returns
    -------
    Phi, dPhi, ddPhi : ndarray, shape (n, n_weights_per_dim)
    """
    u = np.maximum(np.asarray(u, dtype=np.float64), 0.0)
    a = basis.alpha_s
    s = np.exp(-a * np.minimum(u, U_END))[:, None]
    h, c = basis.widths, basis.centers
    logpsi = -0.5 * h * (s - c) ** 2  # Eq. (17), paper 000
    logpsi -= logpsi.max(axis=1, keepdims=True)
    r = np.exp(logpsi)
    r /= r.sum(axis=1, keepdims=True)
    dq = -h * (s - c)
    dq -= (r * dq).sum(axis=1, keepdims=True)  # q - q_bar
    var = (r * dq * dq).sum(axis=1, keepdims=True)
    h_bar = (r * h).sum(axis=1, keepdims=True)
    r1 = r * dq
    r2 = r * (dq * dq - h - var + h_bar)
    phi_s = r + s * r1
    Phi = s * r  # Eq. (16), paper 000
    dPhi = -a * s * phi_s
    ddPhi = a * a * s * (phi_s + s * (2.0 * r1 + s * r2))
    tail = u > U_END
    if np.any(tail):
        Phi[tail] *= np.exp(-a * (u[tail] - U_END))[:, None]
        dPhi[tail] = -a * Phi[tail]
        ddPhi[tail] = a * a * Phi[tail]
    return Phi, dPhi, ddPhi


def hermite_weights(t: float) -> Tuple[float, float, float, float, float, float]:
    """Quintic Hermite basis on ``[0, 1]`` at ``t``: the weights of (value, first, second
    derivative) at 0, then (value, first, second derivative) at 1 (derivatives in units of
    the interval). The tick evaluates the same expressions inline."""
    t2 = t * t
    t3 = t2 * t
    s = 1.0 - t
    w3 = t3 * (10.0 - 15.0 * t + 6.0 * t2)
    return (1.0 - w3, t * s * s * s * (1.0 + 3.0 * t), 0.5 * t2 * s * s * s,
            w3, -t3 * s * (4.0 - 3.0 * t), 0.5 * t3 * s * s)


def _chunks(n: int, width: int):
    step = max(1, _CHUNK // max(width, 1))
    return [(i, min(i + step, n)) for i in range(0, n, step)]


def _grid_error(basis: PhaseBasis, m: int, H: float) -> float:
    """Largest interpolation error of the features on the grid of ``m`` intervals of ``H``
    from 0, at the middle of every interval (where the error term of the quintic Hermite
    interpolant, ``t^3 (1 - t)^3 H^6 phi^(6) / 720``, peaks)."""
    w = hermite_weights(0.5)
    err = 0.0
    with np.errstate(over='ignore', invalid='ignore', under='ignore'):
        for lo, hi in _chunks(m, 4 * basis.n_weights_per_dim):
            P, D, E = feature_derivatives(basis, np.arange(lo, hi + 1) * H)
            approx = (w[0] * P[:-1] + w[1] * H * D[:-1] + w[2] * H * H * E[:-1]
                      + w[3] * P[1:] + w[4] * H * D[1:] + w[5] * H * H * E[1:])
            e = float(np.max(np.abs(approx - basis.features((np.arange(lo, hi) + 0.5) * H))))
            err = max(err, e if math.isfinite(e) else math.inf)
    return err


@functools.lru_cache(maxsize=64)
def _grid_intervals_cached(alpha_s: float, centers: bytes, widths: bytes) -> Tuple[int, float]:
    basis = PhaseBasis.from_arrays(np.frombuffer(centers), np.frombuffer(widths), alpha_s)
    m = MIN_GRID_INTERVALS
    while True:
        err = _grid_error(basis, m, U_END / m)
        if err <= FEATURE_TOL or m >= MAX_GRID_INTERVALS:
            return m, err
        m *= 2


def grid_intervals(basis: PhaseBasis) -> Tuple[int, float]:
    """Intervals of the forcing grid over ``[0, U_END]`` for ``basis`` and the interpolation
    error of its features there: the smallest power of two from :data:`MIN_GRID_INTERVALS` to
    :data:`MAX_GRID_INTERVALS` whose error is at most :data:`FEATURE_TOL` (else the largest).
    Depends on the basis only (cached per basis)."""
    return _grid_intervals_cached(float(basis.alpha_s),
                                  np.ascontiguousarray(basis.centers, np.float64).tobytes(),
                                  np.ascontiguousarray(basis.widths, np.float64).tobytes())


def _forcing_nodes(basis: PhaseBasis, weights: NDArray[np.float64], u: NDArray[np.float64],
                   H: float):
    """Forcing profile, ``H`` times its first and ``H^2`` times its second derivative at the
    nodes ``u`` (lists of rows of n_dims floats), finite whatever the weights."""
    n_w = basis.n_weights_per_dim
    rows = ([], [], [])
    with np.errstate(over='ignore', invalid='ignore', under='ignore'):
        for lo, hi in _chunks(len(u), 4 * n_w):
            for out, M, scale in zip(rows, feature_derivatives(basis, u[lo:hi]),
                                     (1.0, H, H * H)):
                # Eq. (15)-(16)/(23)-(24); clipped: keeps phi * (g - x0) finite for any weights
                V = np.clip(np.nan_to_num((M @ weights.T) * scale, nan=0.0), -1e290, 1e290)
                out.extend(V.tolist())
    return rows


class StepInput:
    """Per-tick input of :meth:`DmpStepper.update`.

    Attributes
    ----------
    coupling : list of float, length n_dims
        The coupling term ``P`` of Eq. 13/21 in the internal space (``tau^2`` times an
        internal acceleration; CDMP: the exogenous space).
    """

    __slots__ = ('coupling',)

    def __init__(self, n_dims: int):
        self.coupling: List[float] = [0.0] * n_dims


class StepOutput:
    """Per-tick output of :meth:`DmpStepper.update` (lists of floats, reused between ticks:
    copy what you keep).

    Attributes
    ----------
    t : float
        Time since the start [s].
    phase : float
        Canonical system ``s`` (1 at the start, decays towards 0).
    u : float
        Normalised (warped) time, 1 at the nominal end of the movement.
    kappa : float
        Phase speed factor in (0, 1] of the velocity limits (1: nominal).
    y, yd, ydd : list of float, length n_dims
        Joint position, velocity and acceleration.
    xi, xid : list of float, length n_dims
        Internal state and its velocity (CDMP: exogenous; DMP: equal to ``y``, ``yd``).
    """

    __slots__ = ('t', 'phase', 'u', 'kappa', 'y', 'yd', 'ydd', 'xi', 'xid')

    def __init__(self, n_dims: int):
        self.t = 0.0
        self.phase = 1.0
        self.u = 0.0
        self.kappa = 1.0
        self.y = [0.0] * n_dims
        self.yd = [0.0] * n_dims
        self.ydd = [0.0] * n_dims
        self.xi = [0.0] * n_dims
        self.xid = [0.0] * n_dims


class DmpStepper:
    """Integrates a fitted :class:`~cdmp_ros.core.dmp.dmp.DMP` or ``CDMP`` one step per call.

    Parameters
    ----------
    prim : DMP or CDMP
        A fitted primitive.
    dt : float
        Step [s].
    start_y, start_yd, goal_y : array-like, shape (n_dims,), optional
        Initial position and velocity, goal (defaults: fitted start, zero, fitted goal).
    tau : float, optional
        Temporal scaling (default the fitted duration).
    velocity_limits : array-like, shape (n_dims,), optional
        Enables the velocity-limit temporal coupling.
    recovery_rate : float
        Rate [1/s] at which ``kappa`` recovers towards 1.
    noise_phi : array-like, shape (n_steps, n_dims), optional
        Per-tick exploration forcing ``phi(u_k) . eps_k`` added to the forcing profile (PI2).
    goal_noise : array-like, shape (n_dims,), optional
        Exploration noise on the internal goal target (Eq. 33).

    Attributes
    ----------
    n_grid_intervals : int
        Intervals of the forcing grid (see the module docstring): at most
        :func:`grid_intervals` of the basis, whatever ``tau`` and ``dt``.
    grid_step : float
        Their length in normalised time (``dt / tau`` when the nodes are the steps).
    feature_error : float
        Interpolation error of the basis features between the nodes.
    table_floats : int
        Floats held by the forcing grid, ``3 (n_grid_intervals + 1) n_dims``. (``noise_phi``,
        a rollout's exploration, is held as given: ``n_steps x n_dims``.)
    """

    def __init__(self, prim, dt: float, start_y: Optional[ArrayLike] = None,
                 start_yd: Optional[ArrayLike] = None, goal_y: Optional[ArrayLike] = None,
                 tau: Optional[float] = None, velocity_limits: Optional[ArrayLike] = None,
                 recovery_rate: float = 2.0, noise_phi: Optional[ArrayLike] = None,
                 goal_noise: Optional[ArrayLike] = None):
        prim._check_fitted()
        self.prim = prim
        n = self.n_dims = prim.n_dims
        self.dt = check_positive('dt', dt)
        self.tau = prim.tau_ if tau is None else check_positive('tau', tau)
        self.recovery_rate = check_positive('recovery_rate', recovery_rate)
        cfg = prim.config
        self._a = cfg.alpha_y
        self._ab = cfg.alpha_y * cfg.beta_y
        self._ag = cfg.alpha_g
        self._alpha_s = cfg.alpha_s
        self._h = self.dt / self.tau
        # The semi-implicit Euler recursion x_{k+1} = tr x_k - det x_{k-1} + ... must be stable.
        h = self._h
        roots = np.roots([1.0, -(2.0 - h * cfg.alpha_y - h * h * cfg.alpha_y * cfg.beta_y),
                          1.0 - h * cfg.alpha_y])
        if h * cfg.alpha_y >= 1.0 or np.max(np.abs(roots)) >= 1.0:
            raise ValidationError(f'dt: dt / tau = {h:.3g} is too large for alpha_y = '
                                  f'{cfg.alpha_y} (need dt / tau * alpha_y < 1 and a stable '
                                  f'recursion); use a smaller dt or a larger tau')
        self._inv_tau = 1.0 / self.tau
        self._cdmp = prim.kind == 'cdmp'
        self._yo = self._yd_ = None
        self._zeros = [0.0] * n
        self._xclamp = float(prim.x_clamp)
        if self._cdmp:
            self._yo = prim.transform.y_o.tolist()
            self._yd_ = prim.transform.y_delta.tolist()
        else:
            self._yo = self._yd_ = [0.0] * n
        self._vmax = None
        if velocity_limits is not None:
            vl = as_array('velocity_limits', velocity_limits, (n,))
            if np.any(vl <= 0):
                raise ValidationError(f'velocity_limits: expected positive values, got '
                                      f'{vl}')
            self._vmax = vl.tolist()
        self._noise = None
        if noise_phi is not None:
            noise = np.nan_to_num(np.asarray(noise_phi, dtype=np.float64), nan=0.0)
            self._noise = np.clip(noise, -1e290, 1e290).tolist()
        # Forcing profile on a grid of the phase whose size does not depend on tau or dt,
        # Eq. (15)-(16)/(23)-(24) (see the module docstring).
        m = grid_intervals(prim.basis)[0]
        n_steps = int(math.ceil(U_END / self._h))
        self._on_steps = n_steps <= m
        if self._on_steps:  # the nominal steps u_k = k h are the nodes: exact at every one
            m, H = n_steps, self._h
        else:
            H = U_END / m
        self.n_grid_intervals = m
        self.grid_step = H
        self._feature_error = None
        self._inv_H = 1.0 / H
        self._F, self._D, self._E = _forcing_nodes(prim.basis, prim.weights_,
                                                   np.arange(m + 1) * H, H)
        self._n_int = m
        self._u_last = m * H
        self.input = StepInput(n)
        self.output = StepOutput(n)
        self._x = [0.0] * n
        self._z = [0.0] * n
        self._g = [0.0] * n
        self._g0 = [0.0] * n
        self._x0 = [0.0] * n
        self._phi = [0.0] * n
        self._base = [0.0] * n
        self._clean = [0.0] * n
        self.reset(start_y, start_yd, goal_y, goal_noise)

    # -- configuration (outside the tick; may allocate) ---------------------------------------
    def reset(self, start_y=None, start_yd=None, goal_y=None, goal_noise=None,
              phase_u: float = 0.0, origin_y=None) -> None:
        """Restart the movement from ``start_y`` with velocity ``start_yd``.

        ``phase_u`` > 0 continues a movement instead of starting one: the state is
        ``start_y``/``start_yd`` at normalised time ``phase_u`` (``t / tau``, rounded to the
        grid of ``dt``, at most :data:`MAX_PHASE_U`), and the forcing term scales with
        ``g - origin_y`` (Eq. 15-16; default the primitive's own start, so from a state on its
        trajectory the stepper reproduces the rest of it). At ``phase_u = 0`` with no
        ``origin_y`` the start is the origin, as before.
        """
        prim, n = self.prim, self.n_dims
        sy = prim.start_y_ if start_y is None else as_array('start_y', start_y, (n,))
        syd = np.zeros(n) if start_yd is None else as_array('start_yd', start_yd, (n,))
        gy = prim.goal_y_ if goal_y is None else as_array('goal_y', goal_y, (n,))
        try:
            u_start = float(phase_u) if not isinstance(phase_u, bool) else math.nan
        except (TypeError, ValueError):
            u_start = math.nan
        if not (math.isfinite(u_start) and u_start >= 0.0):
            raise ValidationError(f'phase_u: expected a finite number >= 0, got {phase_u!r}')
        x0, xd0, g, g0 = prim.initial_state(sy, syd, gy, goal_noise)
        if origin_y is None and u_start > 0.0:
            origin_y = prim.start_y_
        origin = x0 if origin_y is None else prim.to_internal(
            as_array('origin_y', origin_y, (n,)))
        self._x[:] = x0.tolist()
        self._x0[:] = np.asarray(origin, dtype=np.float64).tolist()
        self._z[:] = np.clip(self.tau * xd0, -1e12, 1e12).tolist()
        self._g[:] = g.tolist()
        self._g0[:] = g0.tolist()
        k = int(round(min(u_start, MAX_PHASE_U) / self._h))
        self._k = k
        self._u = k * self._h
        self._kappa = 1.0
        self._t = k * self.dt
        self._forcing_into(self._u, self._phi, k)
        self._finish_outputs(self._zeros, init=True)
        out = self.output
        self._lists = (self._x, self._z, self._g, self._g0, self._x0, self._base, out.y,
                       out.yd, out.ydd, out.xid, self._yo, self._yd_)
        self._consts = (self._a, self._ab, self._h, self._h * self._ag, self._xclamp,
                        self._inv_tau, self._inv_tau * self._inv_tau, self._cdmp)
        out.xi = self._x  # the exogenous state itself (read-only for users)
        if self._vmax is None and self._noise is None:
            self.update = self._update_fast

    def set_goal(self, goal_y: ArrayLike) -> None:
        """Change the goal target; the goal state follows through Eq. 14/22 (no jump)."""
        g0 = self.prim.to_internal(as_array('goal_y', goal_y, (self.n_dims,)))
        self._g0[:] = g0.tolist()

    def set_joint_coupling(self, dq_dd: Optional[Sequence[float]]) -> CouplingResult:
        """Set the coupling term of the next ticks (``input.coupling``) from a joint-space
        acceleration change (a :class:`~cdmp_ros.core.coupling.contract.Coupling` result) at
        the current state, by :func:`joint_coupling_to_exogenous` (capped near saturation).

        Never raises: None gives ``P = 0`` (``ZERO``); a value of the wrong length, not
        numbers, non-finite or beyond :data:`MAX_JOINT_COUPLING` is dropped (``P = 0``,
        ``REJECTED``).
        """
        P = self.input.coupling
        n = self.n_dims
        if dq_dd is None:
            P[:] = self._zeros
            return CouplingResult.ZERO
        try:
            vals = [float(v) for v in dq_dd]
        except (TypeError, ValueError):
            vals = []
        if len(vals) != n or not all(-MAX_JOINT_COUPLING < v < MAX_JOINT_COUPLING
                                     for v in vals):
            P[:] = self._zeros
            return CouplingResult.REJECTED
        joint_coupling_to_exogenous(vals, self._x, self.tau, self._yd_ if self._cdmp else None,
                                    P)
        return CouplingResult.APPLIED if any(vals) else CouplingResult.ZERO

    # -- the tick -----------------------------------------------------------------------------
    def _node_weights(self, u: float):
        """Nodes and quintic Hermite weights of the forcing profile at u (outside the tick; the
        ticks use :meth:`_tick_interpolants`, the same on Python floats)."""
        pos = u * self._inv_H
        if pos < self._n_int:
            i = int(pos)
            return i, i + 1, hermite_weights(pos - i)
        decay = math.exp(-self._alpha_s * (u - self._u_last))  # the basis' exponential tail
        return self._n_int, self._n_int, (decay, 0.0, 0.0, 0.0, 0.0, 0.0)

    def _forcing_into(self, u: float, out: List[float], k: Optional[int] = None) -> None:
        """Forcing profile at normalised time u into ``out`` (+ the exploration of tick k)."""
        i, j, w = self._node_weights(u)
        F, D, E = self._F, self._D, self._E
        noise = self._noise
        nk = noise[k] if noise is not None and k is not None and k < len(noise) else self._zeros
        for d in range(self.n_dims):
            out[d] = (w[0] * F[i][d] + w[1] * D[i][d] + w[2] * E[i][d] + w[3] * F[j][d]
                      + w[4] * D[j][d] + w[5] * E[j][d]) + nk[d]

    def forcing_profile(self, u: float) -> List[float]:
        """The interpolated forcing profile ``phi_d(u) = sum_j phi_j(u) w_dj`` (no exploration
        noise) at normalised time ``u`` [per joint]; within ``feature_error * sum_j |w_dj|`` of
        the exact value."""
        out = [0.0] * self.n_dims
        self._forcing_into(max(float(u), 0.0), out)
        return out

    @property
    def feature_error(self) -> float:
        """Largest interpolation error of a basis feature between the nodes of the forcing
        grid (computed on first use; the forcing is exact at the nodes)."""
        if self._feature_error is None:
            basis = self.prim.basis
            self._feature_error = (_grid_error(basis, self.n_grid_intervals, self.grid_step)
                                   if self._on_steps else grid_intervals(basis)[1])
        return self._feature_error

    @property
    def table_floats(self) -> int:
        """Floats held by the forcing grid (value and two derivatives per node and joint)."""
        return 3 * (self._n_int + 1) * self.n_dims

    def _tick_interpolants(self, u: float):
        """The two grid nodes around normalised time ``u`` (forcing, first and second phase
        derivatives) and their quintic Hermite weights (as :func:`hermite_weights`); beyond the
        grid, the last node decayed by the basis' exponential tail."""
        pos = u * self._inv_H
        if pos < self._n_int:  # quintic Hermite between two nodes (as hermite_weights)
            i = int(pos)
            fr = pos - i
            F, D, E = self._F, self._D, self._E
            f0 = F[i]
            d0 = D[i]
            e0 = E[i]
            i += 1
            f1 = F[i]
            d1 = D[i]
            e1 = E[i]
            fr2 = fr * fr
            fr3 = fr2 * fr
            om = 1.0 - fr
            om2 = om * om
            w3 = fr3 * (10.0 - 15.0 * fr + 6.0 * fr2)
            w0 = 1.0 - w3
            w1 = fr * om2 * om * (1.0 + 3.0 * fr)
            w2 = 0.5 * fr2 * om2 * om
            w4 = -fr3 * om * (4.0 - 3.0 * fr)
            w5 = 0.5 * fr3 * om2
        else:  # the exponential tail of the basis beyond the grid
            f0 = f1 = self._F[-1]
            d0 = d1 = e0 = e1 = self._zeros
            w0 = math.exp(-self._alpha_s * (u - self._u_last))
            w1 = w2 = w3 = w4 = w5 = 0.0
        return f0, f1, d0, d1, e0, e1, w0, w1, w2, w3, w4, w5

    def update(self, inp: StepInput):
        """Advance one step of ``dt``. Never raises.

        Parameters
        ----------
        inp : StepInput
            The coupling term of this step (``self.input``, or one of your own).

        Returns
        -------
        output : StepOutput
            The new state (``y``, ``yd``, ``ydd``: n_dims floats each), reused by every call.
        status : StepStatus
        """
        status = 0
        P = inp.coupling
        n = self.n_dims
        try:
            bad = len(P) != n or not (-1e300 < sum(P) < 1e300)
        except TypeError:
            bad = True
        if bad:
            P = self._sanitize(P)
            status |= 8  # INPUT_REJECTED
        x, z, g, g0, x0, base = self._x, self._z, self._g, self._g0, self._x0, self._base
        a, ab = self._a, self._ab
        kappa = self._kappa
        hk = self._h * kappa
        hkag = hk * self._ag
        xc = self._xclamp
        u = self._u + hk
        k = self._k + 1
        f0, f1, d0, d1, e0, e1, w0, w1, w2, w3, w4, w5 = self._tick_interpolants(u)
        noise = self._noise
        nk = noise[k] if noise is not None and k < len(noise) else self._zeros
        fast = self._vmax is None
        out = self.output
        y, yd, ydd, xo, xdo = out.y, out.yd, out.ydd, out.xi, out.xid
        inv_tau = self._inv_tau
        inv_tau2 = inv_tau * inv_tau
        cdmp = self._cdmp
        yo, ydel = self._yo, self._yd_
        for d in range(n):
            p = P[d]
            # tau dz/dt = alpha_y (beta_y (g - x) - z) + f + P, Eq. (13)/(21); base = all but P
            zv = z[d] + hk * (base[d] + p)
            if not (-1e12 < zv < 1e12):
                zv = 1e12 if zv > 0 else (-1e12 if zv < 0 else 0.0)
            xv = x[d] + hk * zv
            if xv > xc:
                xv = xc
                if zv > 0.0:
                    zv = 0.0
                status |= 4  # SATURATED
            elif xv < -xc:
                xv = -xc
                if zv < 0.0:
                    zv = 0.0
                status |= 4
            x[d] = xv
            z[d] = zv
            gd = g[d]
            gd += hkag * (g0[d] - gd)  # Eq. (14)/(22)
            g[d] = gd
            fv = (w0 * f0[d] + w1 * d0[d] + w2 * e0[d] + w3 * f1[d] + w4 * d1[d] + w5 * e1[d]
                  + nk[d])
            b = ab * (gd - xv) - a * zv + fv * (gd - x0[d])  # Eq. (15)-(16)
            base[d] = b
            if fast:  # kappa == 1: joint-space outputs in the same pass
                vel = zv * inv_tau
                ac = (b + p) * inv_tau2
                xo[d] = xv
                xdo[d] = vel
                if cdmp:
                    t = math.tanh(xv)
                    de = ydel[d] * (1.0 - t * t)
                    y[d] = ydel[d] * t + yo[d]  # Eq. (27)
                    yd[d] = de * vel  # Eq. (28)
                    ydd[d] = de * (ac - 2.0 * t * vel * vel)  # Eq. (29)
                else:
                    y[d] = xv
                    yd[d] = vel
                    ydd[d] = ac
        self._u = u
        self._k = k
        self._t += self.dt
        if fast:
            out.t = self._t
            out.u = u
            out.phase = math.exp(-self._alpha_s * u)
        else:
            status |= self._finish_outputs(P)
        status |= 1 if u < 1.0 else 2  # WORKING / FINISHED
        return out, _STATUS[status]

    def _update_fast(self, inp: StepInput):
        """:meth:`update` without velocity limits (kappa == 1): one pass over the joints."""
        status = 0
        P = inp.coupling
        try:
            if len(P) != self.n_dims or not (-1e300 < sum(P) < 1e300):
                P = self._sanitize(P)
                status = 8  # INPUT_REJECTED
        except TypeError:
            P = self._sanitize(P)
            status = 8
        x, z, g, g0, x0, base, y, yd, ydd, xdo, yo, ydel = self._lists
        a, ab, hk, hkag, xc, inv_tau, inv_tau2, cdmp = self._consts
        k = self._k + 1
        u = k * self._h
        f0, f1, d0, d1, e0, e1, w0, w1, w2, w3, w4, w5 = self._tick_interpolants(u)
        tanh = math.tanh
        for d in range(self.n_dims):
            p = P[d]
            # tau dz/dt = alpha_y (beta_y (g - x) - z) + f + P, Eq. (13)/(21); base = all but P
            zv = z[d] + hk * (base[d] + p)
            if not -1e12 < zv < 1e12:  # finite and bounded, also for a plain DMP
                zv = 1e12 if zv > 0 else (-1e12 if zv < 0 else 0.0)
            xv = x[d] + hk * zv
            if not -xc <= xv <= xc:
                xv = xc if xv > 0 else -xc
                if zv * xv > 0.0:
                    zv = 0.0
                status |= 4  # SATURATED
            x[d] = xv
            z[d] = zv
            gd = g[d]
            gd += hkag * (g0[d] - gd)  # Eq. (14)/(22)
            g[d] = gd
            fv = w0 * f0[d] + w1 * d0[d] + w2 * e0[d] + w3 * f1[d] + w4 * d1[d] + w5 * e1[d]
            b = ab * (gd - xv) - a * zv + fv * (gd - x0[d])  # Eq. (15)-(16)
            base[d] = b
            vel = zv * inv_tau
            xdo[d] = vel
            if cdmp:
                t = tanh(xv)
                de = ydel[d]
                s = de * (1.0 - t * t)
                y[d] = de * t + yo[d]  # Eq. (27)
                yd[d] = s * vel  # Eq. (28)
                ydd[d] = s * ((b + p) * inv_tau2 - 2.0 * t * vel * vel)  # Eq. (29)
            else:
                y[d] = xv
                yd[d] = vel
                ydd[d] = (b + p) * inv_tau2
        self._k = k
        self._u = u
        t_now = k * self.dt
        self._t = t_now
        out = self.output
        out.t = t_now
        out.u = u
        out.phase = math.exp(-self._alpha_s * u)
        return out, _STATUS[status | (1 if u < 1.0 else 2)]

    def _sanitize(self, P) -> List[float]:
        """Coupling of the wrong length or with non-finite/huge entries -> safe list."""
        clean = self._clean
        try:
            vals = list(P)
        except TypeError:
            vals = []
        for d in range(self.n_dims):
            p = vals[d] if d < len(vals) else 0.0
            try:
                p = float(p)
            except (TypeError, ValueError):
                p = 0.0
            clean[d] = p if -1e300 < p < 1e300 else 0.0
        return clean

    def _finish_outputs(self, P, init: bool = False) -> int:
        """Kappa update and joint outputs at the current state (Eq. 27-29).

        With ``init`` the acceleration base (everything but P) is computed first.
        """
        status = 0
        out = self.output
        x, z, g, x0, phi, base = self._x, self._z, self._g, self._x0, self._phi, self._base
        a, ab = self._a, self._ab
        inv_tau = self._inv_tau
        if init:
            for d in range(self.n_dims):
                gd = g[d]
                base[d] = ab * (gd - x[d]) - a * z[d] + phi[d] * (gd - x0[d])
        kappa = 1.0
        cdmp = self._cdmp
        vmax = self._vmax
        if vmax is not None:
            kappa = min(1.0, self._kappa + self.recovery_rate * self.dt)
            for d in range(self.n_dims):
                v = z[d] * inv_tau
                if cdmp:
                    t = math.tanh(x[d])
                    v *= self._yd_[d] * (1.0 - t * t)
                v = abs(v)
                if v * kappa > vmax[d]:
                    # backed off by 1e-12: kappa * v rounds to at most vmax (a consumer that
                    # checks |yd| <= vmax strictly must not see a 1-ulp excess)
                    kappa = vmax[d] / v * VMAX_BACKOFF
            if kappa < 1.0:
                status |= StepStatus.VELOCITY_LIMITED
            self._kappa = kappa
        k2 = kappa * kappa * inv_tau * inv_tau
        y, yd, ydd, xo, xdo = out.y, out.yd, out.ydd, out.xi, out.xid
        for d in range(self.n_dims):
            xv = x[d]
            vel = kappa * z[d] * inv_tau
            ac = k2 * (base[d] + P[d])
            xo[d] = xv
            xdo[d] = vel
            if cdmp:
                t = math.tanh(xv)
                s = 1.0 - t * t
                de = self._yd_[d]
                y[d] = de * t + self._yo[d]  # Eq. (27)
                yd[d] = de * s * vel  # Eq. (28)
                ydd[d] = de * s * (ac - 2.0 * t * vel * vel)  # Eq. (29)
            else:
                y[d] = xv
                yd[d] = vel
                ydd[d] = ac
        out.t = self._t
        out.u = self._u
        out.kappa = kappa
        out.phase = math.exp(-self._alpha_s * self._u)
        return status
