"""Dynamic Movement Primitives and Constrained DMPs (paper 000, Eq. 13-29).

A :class:`DMP` integrates the transformation system in joint space; a :class:`CDMP` integrates
the same system in the exogenous space ``xi`` of the tanh map (:mod:`cdmp_ros.core.dmp.transform`),
so every produced position lies strictly inside ``(y_min, y_max)``.

With the scaled velocity ``z = tau * dx/dt`` the transformation system (Eq. 13/21) reads
``tau * dz/dt = alpha_y * (beta_y * (g - x) - z) + f + P``, the goal system (Eq. 14/22)
``tau * dg/dt = alpha_g * (g_0 - g)`` and the canonical system (Eq. 18/26)
``tau * ds/dt = -alpha_s * s``. ``x`` is ``y`` for a DMP and ``xi`` for a CDMP. Integration is
semi-implicit Euler with a fixed step ``dt``.

Two integrators share these equations: :meth:`DMP.rollout` (vectorised over time when no
state-dependent coupling is given, through the equivalent second-order linear recursion,
:func:`cdmp_ros.core.dmp.recursion.second_order_recursion`) and
:class:`cdmp_ros.core.dmp.stepper.DmpStepper` (one step per call, for streaming). They agree to
rounding (tested).
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.dmp.basis import PhaseBasis
from cdmp_ros.core.dmp.recursion import second_order_recursion
from cdmp_ros.core.config_fields import check_fields, param
from cdmp_ros.core.coupling.contract import Coupling
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.dmp.transform import TanhTransform, XI_SAT
from cdmp_ros.core.validation import as_array, check_positive

#: Clamp of |tau * dz/dt| (internal units); keeps any finite input finite.
ACC_CLAMP = 1e15
#: Clamp of |z| (internal units).
VEL_CLAMP = 1e12
#: Largest number of samples of one rollout (duration / dt + 1).
MAX_ROLLOUT_STEPS = 10_000_000


@dataclass(frozen=True)
class DmpConfig:
    """Constants of a (C)DMP. Mirrored 1:1 by ROS parameters of the nodes.

    Attributes
    ----------
    n_weights_per_dim : int
        Number of Gaussian kernels per degree of freedom.
    alpha_y, beta_y : float
        Spring-damper constants of the transformation system (Eq. 13/21).
        ``beta_y = alpha_y / 4`` is critically damped.
    alpha_g : float
        Goal dynamics constant (Eq. 14/22).
    alpha_s : float
        Canonical system decay (Eq. 18/26); kept separate from ``alpha_y`` (papers/README).
    basis_width : float
        Kernel standard deviation in units of the spacing between neighbouring centres.
    regularization : float
        Ridge factor of the weight regression, relative to the mean diagonal of the normal
        matrix.
    demo_margin : float
        CDMP: fraction of the half range kept free when clipping demonstrations, goals and
        starts that touch or cross a limit (see :mod:`cdmp_ros.core.dmp.transform`).
    """

    n_weights_per_dim: int = param(30, 'Gaussian kernels per degree of freedom.', 1, 1000)
    alpha_y: float = param(25.0, 'Spring constant alpha_y of the transformation system.',
                           1e-6, 1e4)
    beta_y: float = param(6.25, 'Damper constant beta_y (alpha_y / 4: critically damped).',
                          1e-6, 1e4)
    alpha_g: float = param(12.5, 'Goal dynamics constant alpha_g.', 1e-6, 1e4)
    alpha_s: float = param(4.0, 'Canonical system decay alpha_s.', 1e-6, 100.0)
    basis_width: float = param(1.0, 'Kernel standard deviation in centre spacings.',
                               1e-3, 1e3)
    regularization: float = param(1e-8, 'Ridge factor of the weight regression.', 0.0, 1.0)
    demo_margin: float = param(1e-3, 'CDMP: fraction of the half range kept free when '
                               'clipping positions at a limit.', 1e-9, 0.5)

    def __post_init__(self):
        # The ranges are those of the primitive file (msg_schemas/primitive.schema.json).
        check_fields(self)
        PhaseBasis(self.n_weights_per_dim, self.alpha_s, self.basis_width)


@dataclass
class Trajectory:
    """A rollout (:meth:`DMP.rollout`).

    Attributes
    ----------
    T : ndarray, shape (n_steps,)
        Times [s].
    Y, Yd, Ydd : ndarray, shape (n_steps, n_dims)
        Joint positions, velocities, accelerations.
    X, Xd : ndarray, shape (n_steps, n_dims)
        Internal states (``xi, xid`` for a CDMP, equal to ``Y, Yd`` for a DMP).
    phase : ndarray, shape (n_steps,)
        The canonical system ``s`` at every step.
    """

    T: NDArray[np.float64]
    Y: NDArray[np.float64]
    Yd: NDArray[np.float64]
    Ydd: NDArray[np.float64]
    X: NDArray[np.float64]
    Xd: NDArray[np.float64]
    phase: NDArray[np.float64]


class DMP:
    """A discrete DMP in joint space (paper 000, Eq. 13-18).

    Parameters
    ----------
    n_dims : int
        Number of degrees of freedom.
    config : DmpConfig
    joint_names : sequence of str, optional
        Defaults to ``joint_0 .. joint_{n-1}``.
    """

    kind = 'dmp'

    def __init__(self, n_dims: int, config: Optional[DmpConfig] = None,
                 joint_names: Optional[Sequence[str]] = None):
        if not isinstance(n_dims, (int, np.integer)) or n_dims < 1:
            raise ValidationError(f'n_dims: expected an integer >= 1, got {n_dims!r}')
        self.n_dims = int(n_dims)
        self.config = config if config is not None else DmpConfig()
        self.basis = PhaseBasis(self.config.n_weights_per_dim, self.config.alpha_s,
                                self.config.basis_width)
        names = list(joint_names) if joint_names is not None else [
            f'joint_{i}' for i in range(self.n_dims)]
        if len(names) != self.n_dims or len(set(names)) != len(names):
            raise ValidationError(f'joint_names: expected {self.n_dims} unique names, got '
                                  f'{names!r}')
        self.joint_names = names
        self.weights_: Optional[NDArray[np.float64]] = None
        self.start_y_: Optional[NDArray[np.float64]] = None
        self.goal_y_: Optional[NDArray[np.float64]] = None
        self.tau_: Optional[float] = None
        self.fit_rms_error_: Optional[float] = None

    # -- internal space (identity for a DMP) --------------------------------------------------
    def to_internal(self, Y: ArrayLike) -> NDArray[np.float64]:
        """Joint positions -> internal state ``x``."""
        return np.asarray(Y, dtype=np.float64)

    def from_internal(self, X, Xd, Xdd):
        """Internal ``(x, xd, xdd)`` -> joint ``(y, yd, ydd)``."""
        return X, Xd, Xdd

    def internal_velocity(self, X: ArrayLike, Yd: ArrayLike) -> NDArray[np.float64]:
        """Joint velocity at internal state ``X`` -> internal velocity."""
        return np.asarray(Yd, dtype=np.float64)

    x_clamp = np.inf  # internal position clamp (CDMP: XI_SAT)

    # -- learning ------------------------------------------------------------------------------
    def fit(self, T: ArrayLike, Y: ArrayLike) -> 'DMP':
        """Fit to one demonstration; see :meth:`fit_demonstrations`.

        Parameters
        ----------
        T : array-like, shape (n_steps,)
            Strictly increasing times [s].
        Y : array-like, shape (n_steps, n_dims)
            Joint positions.

        Returns
        -------
        self
        """
        return self.fit_demonstrations([(T, Y)])

    def fit_demonstrations(self, demos: Sequence[Tuple[ArrayLike, ArrayLike]]) -> 'DMP':
        """Learn the weights from one or several demonstrations.

        Each demonstration is ``(T, Y)`` with ``T`` shape (n_steps,) strictly increasing and
        ``Y`` shape (n_steps, n_dims). The forcing targets
        ``f = tau^2 xdd - alpha_y (beta_y (g - x) - tau xd)`` (Eq. 13/21 solved for f, with
        ``g`` the demonstration's end) are regressed on the features scaled by ``(g - x0)``
        (Eq. 16/24) by ridge regression, jointly over all demonstrations. ``start_y_``,
        ``goal_y_`` and ``tau_`` are the means over demonstrations.
        """
        if len(demos) == 0:
            raise ValidationError('demos: expected at least one demonstration, got none')
        cfg = self.config
        n_w = cfg.n_weights_per_dim
        M = np.zeros((self.n_dims, n_w, n_w))
        b = np.zeros((self.n_dims, n_w))
        starts, goals, taus, pieces = [], [], [], []
        for i, (T, Y) in enumerate(demos):
            T = as_array(f'demos[{i}].T', T, (None,))
            Y = as_array(f'demos[{i}].Y', Y, (T.shape[0], self.n_dims))
            if T.shape[0] < 3:
                raise ValidationError(f'demos[{i}].T: expected at least 3 samples, got '
                                      f'{T.shape[0]}')
            if not np.all(np.diff(T) > 0):
                raise ValidationError(f'demos[{i}].T: expected strictly increasing times')
            tau = float(T[-1] - T[0])
            X = self.to_internal(Y)
            Xd = np.gradient(X, T, axis=0, edge_order=2)
            Xdd = np.gradient(Xd, T, axis=0, edge_order=2)
            g, x0 = X[-1], X[0]
            f_target = tau ** 2 * Xdd - cfg.alpha_y * (cfg.beta_y * (g - X) - tau * Xd)
            Phi = self.basis.features((T - T[0]) / tau)  # (n_t, n_w)
            scale = g - x0  # (n_dims,)
            PtP = Phi.T @ Phi
            M += scale[:, None, None] ** 2 * PtP
            b += scale[:, None] * (f_target.T @ Phi)
            starts.append(Y[0])
            goals.append(Y[-1])
            taus.append(tau)
            pieces.append((T, Y))
        diag_mean = np.trace(M, axis1=1, axis2=2) / n_w
        lam = cfg.regularization * np.maximum(diag_mean, 1e-300) + 1e-12
        M += lam[:, None, None] * np.eye(n_w)
        self.weights_ = np.linalg.solve(M, b[..., None])[..., 0]
        self.start_y_ = np.mean(starts, axis=0)
        self.goal_y_ = np.mean(goals, axis=0)
        self.tau_ = float(np.mean(taus))
        # Reconstruction error of each demonstration from its own start, goal and duration.
        errs = []
        for T, Y in pieces:
            dt = float(np.min(np.diff(T)))
            tr = self.rollout(dt=dt, tau=float(T[-1] - T[0]), start_y=Y[0], goal_y=Y[-1])
            Yi = np.stack([np.interp(T - T[0], tr.T, tr.Y[:, d])
                           for d in range(self.n_dims)], axis=1)
            errs.append(np.mean((Yi - Y) ** 2))
        self.fit_rms_error_ = float(np.sqrt(np.mean(errs)))
        return self

    def set_parameters(self, weights: ArrayLike, start_y: ArrayLike, goal_y: ArrayLike,
                       tau: float) -> 'DMP':
        """Set the learned parameters directly (weights in internal units)."""
        n_w = self.config.n_weights_per_dim
        self.weights_ = as_array('weights', weights, (self.n_dims, n_w)).copy()
        self.start_y_ = as_array('start_y', start_y, (self.n_dims,)).copy()
        self.goal_y_ = as_array('goal_y', goal_y, (self.n_dims,)).copy()
        self.tau_ = check_positive('tau', tau)
        return self

    def _check_fitted(self):
        if self.weights_ is None:
            raise CdmpError(f'{type(self).__name__} is not fitted: call fit() or '
                            'set_parameters() first')

    # -- rollout -------------------------------------------------------------------------------
    def rollout(self, dt: float = 0.001, tau: Optional[float] = None,
                start_y: Optional[ArrayLike] = None, goal_y: Optional[ArrayLike] = None,
                duration: Optional[float] = None, start_yd: Optional[ArrayLike] = None,
                coupling: Optional[Coupling] = None, obstacles: Sequence = (),
                weight_noise: Optional[ArrayLike] = None,
                goal_noise: Optional[ArrayLike] = None,
                velocity_limits: Optional[ArrayLike] = None) -> Trajectory:
        """Integrate the primitive open loop.

        Parameters
        ----------
        dt : float
            Integration step [s].
        tau : float, optional
            Temporal scaling (duration of the movement); default the fitted ``tau_``.
        start_y, goal_y : array-like, shape (n_dims,), optional
            Start and goal; default the fitted ones. CDMP: values at or beyond a limit are
            clipped (see :mod:`cdmp_ros.core.dmp.transform`).
        duration : float, optional
            Integrated time span; default ``tau``.
        start_yd : array-like, shape (n_dims,), optional
            Initial joint velocity (default zero).
        coupling : Coupling, optional
            Evaluated every step at the joint state, ``coupling.joint_acceleration(y, yd,
            obstacles)`` (:class:`cdmp_ros.core.coupling.contract.Coupling`); the stepper maps
            it into the coupling term of Eq. 13/21
            (:meth:`cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling`). Forces the
            step-by-step integrator.
        obstacles : sequence
            The obstacle set passed to ``coupling``.
        weight_noise : array-like, shape (n_steps, n_dims, n_weights_per_dim), optional
            Exploration noise on the shape parameters per time step (Eq. 32).
        goal_noise : array-like, shape (n_dims,), optional
            Exploration noise on the internal goal (Eq. 33).
        velocity_limits : array-like, shape (n_dims,), optional
            Per-joint velocity limits: the phase is slowed so that ``|yd|`` stays within them
            (see :class:`cdmp_ros.core.dmp.stepper.DmpStepper`).

        Returns
        -------
        Trajectory
            ``n_steps = round(duration / dt) + 1`` samples, the first being the start state.
        """
        self._check_fitted()
        dt = check_positive('dt', dt)
        tau = self.tau_ if tau is None else check_positive('tau', tau)
        duration = tau if duration is None else check_positive('duration', duration)
        n_steps = duration / dt + 1.0
        if not n_steps <= MAX_ROLLOUT_STEPS:
            raise ValidationError(f'dt: duration / dt = {duration:.6g} / {dt:.6g} gives more '
                                  f'than {MAX_ROLLOUT_STEPS} steps; use a larger dt')
        n_steps = int(round(duration / dt)) + 1
        start_y = (self.start_y_ if start_y is None
                   else as_array('start_y', start_y, (self.n_dims,)))
        goal_y = self.goal_y_ if goal_y is None else as_array('goal_y', goal_y, (self.n_dims,))
        start_yd = (np.zeros(self.n_dims) if start_yd is None
                    else as_array('start_yd', start_yd, (self.n_dims,)))
        eps = None
        if weight_noise is not None:
            eps = as_array('weight_noise', weight_noise,
                           (n_steps, self.n_dims, self.config.n_weights_per_dim))
        g_noise = (np.zeros(self.n_dims) if goal_noise is None
                   else as_array('goal_noise', goal_noise, (self.n_dims,)))
        if coupling is None and velocity_limits is None:
            with np.errstate(over='ignore', invalid='ignore'):  # overflow -> stepwise path
                traj = self._rollout_vectorised(dt, tau, n_steps, start_y, start_yd, goal_y,
                                                eps, g_noise)
            if traj is not None:
                return traj
        return self._rollout_stepwise(dt, tau, n_steps, start_y, start_yd, goal_y, eps,
                                      g_noise, coupling, obstacles, velocity_limits)

    def initial_state(self, start_y, start_yd, goal_y, goal_noise=None):
        """Internal start ``x0``, scaled velocity factor input, goal state and goal target."""
        x0 = self.to_internal(start_y)
        xd0 = self.internal_velocity(x0, start_yd)
        g = self.to_internal(goal_y)
        g0 = g if goal_noise is None else g + goal_noise
        return x0, xd0, g, g0

    def _rollout_vectorised(self, dt, tau, n_steps, start_y, start_yd, goal_y, eps, g_noise):
        cfg = self.config
        h = dt / tau
        x0, xd0, g_init, g0 = self.initial_state(start_y, start_yd, goal_y, g_noise)
        k = np.arange(n_steps)
        u = k * h
        Phi = self.basis.features(u)  # (n_steps, n_w)
        # Goal dynamics, Eq. (14)/(22) discretised: g_{k+1} = g_k + h alpha_g (g0 - g_k).
        decay = (1.0 - h * cfg.alpha_g) ** k
        G = g0 + (g_init - g0) * decay[:, None]
        if eps is None:
            phi = Phi @ self.weights_.T
        else:
            phi = np.einsum('kj,kdj->kd', Phi, self.weights_[None] + eps)
        F = phi * (G - x0)  # Eq. (15)-(16)/(23)-(24), paper 000
        a, ab = cfg.alpha_y, cfg.alpha_y * cfg.beta_y
        U = ab * G + F  # input of the linear recursion
        X = np.empty((n_steps, self.n_dims))
        Z = np.empty((n_steps, self.n_dims))
        X[0] = x0
        Z[0] = tau * xd0
        if n_steps > 1:
            Z[1] = Z[0] + h * (U[0] - ab * X[0] - a * Z[0])
            X[1] = X[0] + h * Z[1]
        if n_steps > 2:
            # x_{k+1} = tr x_k - det x_{k-1} + h^2 u_k, the semi-implicit Euler recursion.
            tr = 2.0 - h * a - h * h * ab
            det = 1.0 - h * a
            X[2:] = second_order_recursion(tr, det, h * h, U[1:-1], X[1], X[0])
            Z[2:] = (X[2:] - X[1:-1]) / h
        if not np.all(np.isfinite(X)) or np.max(np.abs(X)) > self.x_clamp:
            return None  # needs the clamps of the step-by-step integrator
        Acc = (U - ab * X - a * Z) / tau ** 2  # xdd, Eq. (13)/(21)
        Xd = Z / tau
        if not (np.all(np.isfinite(Acc)) and np.all(np.abs(Z) <= VEL_CLAMP)):
            return None
        Y, Yd, Ydd = self.from_internal(X, Xd, Acc)
        return Trajectory(k * dt, Y, Yd, Ydd, X, Xd, self.basis.phase(u))

    def _rollout_stepwise(self, dt, tau, n_steps, start_y, start_yd, goal_y, eps, g_noise,
                          coupling, obstacles, velocity_limits):
        from cdmp_ros.core.dmp.stepper import DmpStepper
        noise_phi = None
        if eps is not None:
            Phi = self.basis.features(np.arange(n_steps) * (dt / tau))
            with np.errstate(over='ignore', invalid='ignore'):
                noise_phi = np.einsum('kj,kdj->kd', Phi, eps)
        st = DmpStepper(self, dt, start_y=start_y, start_yd=start_yd, goal_y=goal_y, tau=tau,
                        velocity_limits=velocity_limits, noise_phi=noise_phi,
                        goal_noise=g_noise)
        n = self.n_dims
        out_arrays = [np.empty((n_steps, n)) for _ in range(5)]
        Y, Yd, Ydd, X, Xd = out_arrays
        phase = np.empty(n_steps)
        o = st.output
        Y[0], Yd[0], Ydd[0], X[0], Xd[0], phase[0] = o.y, o.yd, o.ydd, o.xi, o.xid, o.phase
        inp = st.input
        for k in range(1, n_steps):
            if coupling is not None:
                st.set_joint_coupling(coupling.joint_acceleration(o.y, o.yd, obstacles))
            o, _ = st.update(inp)
            Y[k], Yd[k], Ydd[k], X[k], Xd[k], phase[k] = o.y, o.yd, o.ydd, o.xi, o.xid, o.phase
        return Trajectory(np.arange(n_steps) * dt, Y, Yd, Ydd, X, Xd, phase)

    def stepper(self, dt: float, start_y: Optional[ArrayLike] = None,
                start_yd: Optional[ArrayLike] = None, goal_y: Optional[ArrayLike] = None,
                tau: Optional[float] = None, velocity_limits: Optional[ArrayLike] = None):
        """A :class:`cdmp_ros.core.dmp.stepper.DmpStepper` for streaming this primitive.

        Parameters
        ----------
        dt : float
            Step [s].
        start_y, start_yd, goal_y : array-like, shape (n_dims,), optional
            Start position and velocity, goal (defaults: the fitted start, zero, the fitted
            goal).
        tau : float, optional
            Duration [s] (default the fitted one).
        velocity_limits : array-like, shape (n_dims,), optional
            The phase slows so that ``|yd| <= velocity_limits``.
        """
        from cdmp_ros.core.dmp.stepper import DmpStepper
        return DmpStepper(self, dt, start_y=start_y, start_yd=start_yd, goal_y=goal_y,
                          tau=tau, velocity_limits=velocity_limits)


class CDMP(DMP):
    """A Constrained DMP (paper 000, Eq. 19-29): a DMP integrated in the exogenous space.

    Parameters
    ----------
    y_min, y_max : array-like, shape (n_dims,)
        Joint limits; every produced position lies strictly inside ``(y_min, y_max)``.
    config : DmpConfig
    joint_names : sequence of str, optional
    """

    kind = 'cdmp'
    x_clamp = XI_SAT

    def __init__(self, y_min: ArrayLike, y_max: ArrayLike, config: Optional[DmpConfig] = None,
                 joint_names: Optional[Sequence[str]] = None):
        config = config if config is not None else DmpConfig()
        self.transform = TanhTransform(y_min, y_max, margin=config.demo_margin)
        super().__init__(self.transform.n_dims, config, joint_names)

    @property
    def y_min(self) -> NDArray[np.float64]:
        return self.transform.y_min

    @property
    def y_max(self) -> NDArray[np.float64]:
        return self.transform.y_max

    def to_internal(self, Y: ArrayLike) -> NDArray[np.float64]:
        """Eq. (20), paper 000, after clipping to the margin."""
        return self.transform.to_exogenous(Y)

    def from_internal(self, X, Xd, Xdd):
        """Eq. (27)-(29), paper 000."""
        tr = self.transform
        return tr.to_joint(X), tr.velocity(X, Xd), tr.acceleration(X, Xd, Xdd)

    def internal_velocity(self, X: ArrayLike, Yd: ArrayLike) -> NDArray[np.float64]:
        """Inverse of Eq. (28): ``xid = yd / J(xi)``."""
        return np.asarray(Yd, dtype=np.float64) / np.maximum(self.transform.jacobian(X),
                                                             1e-300)


def limit_usage(Y: ArrayLike, y_min: ArrayLike, y_max: ArrayLike) -> float:
    """Largest ``|y - centre| / half_range`` over all samples and joints (> 1 = violation)."""
    Y = np.asarray(Y, dtype=np.float64)
    lo = np.asarray(y_min, dtype=np.float64)
    hi = np.asarray(y_max, dtype=np.float64)
    return float(np.max(np.abs(Y - 0.5 * (lo + hi)) / (0.5 * (hi - lo))))
