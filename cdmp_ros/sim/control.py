"""Joint-reference tracking laws for a simulated :class:`cdmp_ros.sim.robot.Robot`.

Select one with ``robot.set_controller(...)``; the world calls ``controller.apply(robot, q, qd,
reference)`` before every physics step. Torque controllers also expose the pure function
``torque(robot, q, qd, reference) -> tau`` ``(n_dofs,)``.

- :class:`PositionController`: pybullet's position motors (``POSITION_CONTROL``), forces capped
  at the URDF effort limits.
- :class:`ComputedTorqueController`: Eq. (2), paper 000,
  ``tau = M(q) (qdd_d - K_P (q - q_d) - K_D (qd - qd_d)) + C(q, qd) qd + G(q)``.
- :class:`PDController`: ``tau = K_P (q_d - q) + K_D (qd_d - qd) [+ G(q)]``, the model-free
  baseline with the same gain values.
- :class:`JointLimitAvoidingController`: Eq. (4)-(5), paper 000, the set-point law in the
  exogenous coordinates ``xi`` of Eq. (3):
  ``tau = -K_P (xi - xi_d) - K_D qd + C(q, qd) qd + G(q)``.

Gains are scalars (every joint) or per-joint sequences, held in frozen dataclasses. Torques are
not saturated (pybullet applies what is commanded).
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.dmp.transform import TanhTransform
from cdmp_ros.core.validation import as_array, check_positive, lookup

Gain = Union[float, Sequence[float]]
#: Margin of :func:`joint_to_exogenous` with ``margin = 0`` (fraction of the half-range).
_MIN_MARGIN = 1e-12


def _check_gain(name: str, value: Gain, allow_zero: bool = False):
    arr = as_array(name, value)
    if arr.ndim > 1 or arr.size == 0 or np.any(arr < 0) or (not allow_zero and np.any(arr == 0)):
        kind = 'non-negative' if allow_zero else 'positive'
        raise ValidationError(f'{name}: expected a {kind} scalar or per-joint vector, '
                              f'got {value!r}')
    return float(arr) if arr.ndim == 0 else tuple(float(v) for v in arr)


def gain_vector(name: str, value: Gain, n_dofs: int) -> NDArray[np.float64]:
    """Broadcast a scalar or per-joint gain to ``(n_dofs,)`` (checks the length)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return np.full(n_dofs, float(arr))
    if arr.shape != (n_dofs,):
        raise ValidationError(f'{name}: expected a scalar or shape ({n_dofs},), got {arr.shape}')
    return arr.copy()


def _transform(lower: ArrayLike, upper: ArrayLike, margin: float = 0.0) -> TanhTransform:
    """The :class:`TanhTransform` of the limits; ``margin = 0`` leaves 1e-12 of the range."""
    return TanhTransform(lower, upper, margin=max(float(margin), _MIN_MARGIN))


def joint_to_exogenous(q: ArrayLike, lower: ArrayLike, upper: ArrayLike,
                       margin: float = 0.0) -> NDArray[np.float64]:
    """Exogenous coordinates ``xi = arctanh(delta^-1 (q - q_o))``, Eq. (5), paper 000.

    A thin wrapper over :meth:`cdmp_ros.core.dmp.transform.TanhTransform.to_exogenous`:
    ``q_o = (q_min + q_max) / 2`` and ``delta = (q_max - q_min) / 2`` (Eq. 3). Positions are
    first clipped to ``q_o +- (1 - margin) delta`` so that a reference at or beyond a limit
    maps to a finite ``xi``; ``margin = 0`` leaves 1e-12 of the half-range.

    Parameters
    ----------
    q : (..., n_dofs) array-like
    lower, upper : (n_dofs,) array-like
    margin : float
        Fraction of the half-range kept free at each limit, in [0, 1).

    Returns
    -------
    (..., n_dofs) ndarray
    """
    return _transform(lower, upper, margin).to_exogenous(q)


def inertia_scaled_gains(robot, kp: float, kd: float, q: Optional[ArrayLike] = None
                         ) -> Tuple[Tuple[float, ...], Tuple[float, ...]]:
    """Per-joint torque gains ``(kp M_ii(q), kd M_ii(q))`` from acceleration-level gains.

    The Panda's joint inertias span two orders of magnitude (about 1.3 to 0.004 kg m^2), so one
    scalar torque gain is either too soft for the shoulder or unstable at 1 kHz for the wrist;
    scaling by the diagonal of ``M(q)`` (default: the current configuration) gives every joint
    the same bandwidth. Use for :class:`PDGains` and :class:`JointLimitAvoidingGains`.
    """
    m = np.diag(robot.mass_matrix(q))
    return tuple(float(v) for v in kp * m), tuple(float(v) for v in kd * m)


# -- gains ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PositionControlGains:
    """pybullet position-motor gains (dimensionless, pybullet's constraint formulation).

    Attributes
    ----------
    position_gain, velocity_gain : float
        ``positionGains`` / ``velocityGains`` of ``setJointMotorControlArray``.
    force_scale : float
        Maximum motor force as a fraction of the URDF effort limit.
    """

    position_gain: float = 0.1
    velocity_gain: float = 1.0
    force_scale: float = 1.0

    def __post_init__(self):
        check_positive('position_gain', self.position_gain)
        check_positive('velocity_gain', self.velocity_gain, allow_zero=True)
        check_positive('force_scale', self.force_scale)


@dataclass(frozen=True)
class ComputedTorqueGains:
    """Feedback gains of Eq. (2): ``K_P`` [1/s^2], ``K_D`` [1/s] (critically damped default)."""

    kp: Gain = 400.0
    kd: Gain = 40.0

    def __post_init__(self):
        object.__setattr__(self, 'kp', _check_gain('kp', self.kp, allow_zero=True))
        object.__setattr__(self, 'kd', _check_gain('kd', self.kd, allow_zero=True))


@dataclass(frozen=True)
class PDGains:
    """Gains of the PD baseline: ``K_P`` [N m/rad], ``K_D`` [N m s/rad].

    ``gravity_compensation`` adds ``G(q)`` (PD + gravity, the usual industrial baseline).
    """

    kp: Gain = 400.0
    kd: Gain = 40.0
    gravity_compensation: bool = True

    def __post_init__(self):
        object.__setattr__(self, 'kp', _check_gain('kp', self.kp, allow_zero=True))
        object.__setattr__(self, 'kd', _check_gain('kd', self.kd, allow_zero=True))


@dataclass(frozen=True)
class JointLimitAvoidingGains:
    """Gains of Eq. (4): ``K_P`` [N m per unit of xi], ``K_D`` [N m s/rad].

    ``margin`` is the fraction of each half-range kept free when a set point at or beyond a
    limit is mapped to ``xi_d`` (Eq. 5), in (0, 1). Scalar gains suit robots with similar joint
    inertias (the planar arm); for the Panda use :func:`inertia_scaled_gains`.
    """

    kp: Gain = 20.0
    kd: Gain = 5.0
    margin: float = 1e-2

    def __post_init__(self):
        object.__setattr__(self, 'kp', _check_gain('kp', self.kp))
        object.__setattr__(self, 'kd', _check_gain('kd', self.kd, allow_zero=True))
        if not 0.0 < float(self.margin) < 1.0:
            raise ValidationError(f'margin: expected a value in (0, 1), got {self.margin!r}')


# -- controllers ------------------------------------------------------------------------------
class PositionController:
    """Track ``reference.q`` (and ``reference.qd``) with pybullet's position motors."""

    def __init__(self, gains: PositionControlGains = PositionControlGains()):
        self.gains = gains

    def apply(self, robot, q: NDArray, qd: NDArray, reference) -> None:
        g = self.gains
        robot.send_position(reference.q, reference.qd, g.position_gain, g.velocity_gain,
                            g.force_scale)


class _TorqueController:
    gains = None

    def _k(self, robot):
        cache = getattr(self, '_cache', None)
        if cache is None or cache[0] != robot.n_dofs:
            cache = (robot.n_dofs, gain_vector('kp', self.gains.kp, robot.n_dofs),
                     gain_vector('kd', self.gains.kd, robot.n_dofs))
            self._cache = cache
        return cache[1], cache[2]

    def apply(self, robot, q: NDArray, qd: NDArray, reference) -> None:
        robot.send_torque(self.torque(robot, q, qd, reference))

    def torque(self, robot, q: NDArray, qd: NDArray, reference) -> NDArray[np.float64]:
        raise NotImplementedError


class ComputedTorqueController(_TorqueController):
    """Computed torque control, Eq. (2), paper 000.

    ``M(q) a + C(q, qd) qd + G(q)`` with ``a = qdd_d - K_P (q - q_d) - K_D (qd - qd_d)`` is
    evaluated in one recursive Newton-Euler call (pybullet ``calculateInverseDynamics(q, qd,
    a)``), which equals ``calculateMassMatrix(q) @ a`` plus the bias forces (checked in
    test_sim_control.py).
    """

    def __init__(self, gains: ComputedTorqueGains = ComputedTorqueGains()):
        self.gains = gains

    def torque(self, robot, q, qd, reference):
        kp, kd = self._k(robot)
        a = reference.qdd - kp * (q - reference.q) - kd * (qd - reference.qd)  # Eq. (2), 000
        return robot._inverse_dynamics(q, qd, a)


class PDController(_TorqueController):
    """``tau = K_P (q_d - q) + K_D (qd_d - qd)``, plus ``G(q)`` if gravity-compensated."""

    def __init__(self, gains: PDGains = PDGains()):
        self.gains = gains

    def torque(self, robot, q, qd, reference):
        kp, kd = self._k(robot)
        tau = kp * (reference.q - q) + kd * (reference.qd - qd)
        if self.gains.gravity_compensation:
            zeros = np.zeros(robot.n_dofs)
            tau = tau + robot._inverse_dynamics(q, zeros, zeros)
        return tau


class JointLimitAvoidingController(_TorqueController):
    """Joint-limit-avoiding set-point law in exogenous coordinates, Eq. (4)-(5), paper 000.

    ``tau = -K_P (xi - xi_d) - K_D qd + C(q, qd) qd + G(q)`` with ``xi = arctanh(delta^-1
    (q - q_o))`` and ``xi_d`` the same map of the set point ``reference.q``, clipped to
    ``q_o +- (1 - margin) delta`` first (so a set point beyond a limit is accepted). The
    restoring torque grows without bound as a joint approaches a limit. ``reference.qd`` and
    ``reference.qdd`` are ignored (set-point law): feeding a trajectory re-targets the set
    point every step.

    Caveat (measured, see test_sim_control.py): the torque grows without bound but its
    potential does not (``int arctanh = ln 2`` at the limit), so the bound holds only when the
    damping dissipates the energy a set-point change injects. A reference that moves towards
    (or beyond) a limit at joint-velocity pace stays strictly inside; a large *step* of the set
    point to within a few percent of a limit can overshoot it by several mrad with moderate
    damping (joint 2 of the Panda: about 9 mrad with ``margin`` 0.01; about 45 mrad with
    0.001). Measured at 1 kHz; a larger ``margin`` reduced it in every case tried.
    """

    def __init__(self, gains: JointLimitAvoidingGains = JointLimitAvoidingGains()):
        self.gains = gains

    def _transforms(self, robot) -> Tuple[TanhTransform, TanhTransform]:
        """(state map, set-point map with ``gains.margin``), cached per robot."""
        cache = getattr(self, '_tr_cache', None)
        if cache is None or cache[0] is not robot:
            cache = (robot, _transform(robot.lower, robot.upper),
                     _transform(robot.lower, robot.upper, self.gains.margin))
            self._tr_cache = cache
        return cache[1], cache[2]

    def torque(self, robot, q, qd, reference):
        kp, kd = self._k(robot)
        state, setpoint = self._transforms(robot)
        xi = state.to_exogenous(q)                                              # Eq. (5), 000
        xi_d = setpoint.to_exogenous(reference.q)
        bias = robot._inverse_dynamics(q, qd, np.zeros(robot.n_dofs))        # C qd + G
        return -kp * (xi - xi_d) - kd * qd + bias                              # Eq. (4), 000


CONTROLLERS = {
    'position': (PositionController, PositionControlGains),
    'computed_torque': (ComputedTorqueController, ComputedTorqueGains),
    'pd': (PDController, PDGains),
    'joint_limit': (JointLimitAvoidingController, JointLimitAvoidingGains),
}


def make_controller(mode: str, **gains):
    """Controller by name: ``'position'``, ``'computed_torque'``, ``'pd'``, ``'joint_limit'``.

    ``**gains`` are the fields of the matching gains dataclass (e.g. ``kp=100.0``).
    """
    cls, gains_cls = lookup('mode', CONTROLLERS, mode, sort=True)
    return cls(gains_cls(**gains))
