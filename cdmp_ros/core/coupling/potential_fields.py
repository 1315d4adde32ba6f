"""Potential fields giving Cartesian accelerations for the obstacle coupling terms (paper 000).

Every field is a frozen dataclass (its gains, validated in ``__post_init__``) with a method
``acceleration(x, xd, obstacle, distance, normal) -> (ax, ay, az)`` on plain floats, where
``distance`` is the signed distance from the point (or link) to the obstacle and ``normal``
the unit direction that increases it (see :mod:`cdmp_ros.core.kinematics.closest`). The
result is the Cartesian acceleration change ``dx_dd`` of Eq. (7) (end effector) or Eq. (12)
(link point) of paper 000.
"""
import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

from cdmp_ros.core.config_fields import param
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.closest import Box
from cdmp_ros.core.validation import check_positive

Vec3 = Tuple[float, float, float]
ZERO = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RepellerField:
    """Smooth repeller with an influence distance (Khatib's FIRAS potential) plus an optional
    damping of the approach velocity.

    With ``d = max(distance, min_distance)`` and ``n`` the unit normal::

        U(d) = gain / 2 * (1/d - 1/d0)^2                 for d < d0, else 0
        a    = -grad U = gain * (1/d - 1/d0) / d^2 * n    (C1 at d = d0)
             - damping * (1 - d/d0)^2 * min(n . xd, 0) * n

    Attributes
    ----------
    gain : float
        ``gain`` [m^3/s^2]; at distance d << d0 the acceleration is about gain / d^3.
    influence_distance : float
        ``d0`` [m]; no effect at or beyond it.
    min_distance : float
        Floor of ``d`` [m] (caps the field at contact or penetration).
    damping : float
        Gain [1/s] on the approach speed (``xd`` towards the obstacle), 0 to disable.
    """

    gain: float = param(
        0.01, 'Repeller gain [m^3/s^2]; at distance d << influence_distance the acceleration '
        'is about gain / d^3.')
    influence_distance: float = param(
        0.2, 'Influence distance d0 [m] of the repeller; no effect at or beyond it.')
    min_distance: float = param(
        0.005, 'Floor of the distance d [m] (caps the repeller at contact or penetration).')
    damping: float = param(
        0.0, 'Gain [1/s] on the approach speed (towards the obstacle), 0 to disable.')

    def __post_init__(self):
        check_positive('RepellerField.gain', self.gain, allow_zero=True)
        check_positive('RepellerField.influence_distance', self.influence_distance)
        check_positive('RepellerField.min_distance', self.min_distance)
        check_positive('RepellerField.damping', self.damping, allow_zero=True)
        if not self.min_distance < self.influence_distance:
            raise ValidationError(f'RepellerField: expected min_distance < influence_distance, '
                                  f'got {self.min_distance} >= {self.influence_distance}')

    def potential(self, distance: float) -> float:
        """``U(d)`` [m^2/s^2] (for tests and diagnostics)."""
        d0 = self.influence_distance
        if distance >= d0:
            return 0.0
        d = max(distance, self.min_distance)
        return 0.5 * self.gain * (1.0 / d - 1.0 / d0) ** 2

    def acceleration(self, x: Sequence[float], xd: Sequence[float], obstacle,
                     distance: float, normal: Sequence[float]) -> Vec3:
        d0 = self.influence_distance
        if distance >= d0:
            return ZERO
        d = distance if distance > self.min_distance else self.min_distance
        s = self.gain * (1.0 / d - 1.0 / d0) / (d * d)
        if self.damping:
            approach = normal[0] * xd[0] + normal[1] * xd[1] + normal[2] * xd[2]
            if approach < 0.0:
                w = 1.0 - d / d0
                s -= self.damping * w * w * approach
        return (s * normal[0], s * normal[1], s * normal[2])


@dataclass(frozen=True)
class ConstantField:
    """The constant potential field of paper 000, IV-B: a constant acceleration ``magnitude``
    [m/s^2] while the point is closer than ``influence_distance`` [m] to the obstacle, along
    ``direction`` (a fixed world vector, normalised) or, if ``direction`` is None, along the
    obstacle normal (away from the obstacle).

    Attributes
    ----------
    magnitude : float
        Acceleration [m/s^2], >= 0.
    influence_distance : float
        Distance [m] below which the field acts.
    direction : tuple of 3 float, optional
        Fixed world direction (normalised); None: the obstacle normal.
    """

    magnitude: float = param(
        1.0, 'Acceleration [m/s^2] of the constant box field (paper 000, IV-B), away from the '
        'box, while the point is closer than influence_distance.')
    influence_distance: float = param(
        0.1, 'Distance [m] from the box below which the constant box field acts.')
    direction: Optional[tuple] = None

    def __post_init__(self):
        check_positive('ConstantField.magnitude', self.magnitude, allow_zero=True)
        check_positive('ConstantField.influence_distance', self.influence_distance)
        if self.direction is not None:
            try:
                v = tuple(float(c) for c in self.direction)
            except (TypeError, ValueError):
                v = ()
            norm = math.sqrt(sum(c * c for c in v)) if len(v) == 3 else 0.0
            if not norm > 0 or not math.isfinite(norm):
                raise ValidationError(f'ConstantField.direction: expected a non-zero 3-vector, '
                                      f'got {self.direction!r}')
            object.__setattr__(self, 'direction', tuple(c / norm for c in v))

    def acceleration(self, x, xd, obstacle, distance: float, normal: Sequence[float]) -> Vec3:
        if distance >= self.influence_distance:
            return ZERO
        n = self.direction if self.direction is not None else normal
        m = self.magnitude
        return (m * n[0], m * n[1], m * n[2])


@dataclass(frozen=True)
class BoardField:
    """The piecewise board field of paper 000, Eq. (30)-(31), for a point escaping from
    under (or over) an axis-aligned board around one of its vertical edges.

    Let ``h = horizontal_axis``, ``v = vertical_axis``; the edge is the board's upper face on
    axis h if ``edge_side = +1`` (lower face if -1); the near horizontal surface is the board's
    lower face on axis v if ``vertical_side = -1`` (the point is under the board) or its upper
    face if +1. While the point is on the near side of that surface and has not passed the
    edge (Eq. 30)::

        a_h = edge_side * beta_y * dy / dz        (towards the edge)
        a_v = vertical_side * beta_z / dz          (away from the surface)

    with ``dy`` the horizontal distance to the edge and ``dz`` the vertical distance to the
    surface (floored at ``min_distance``). Once past the edge or beyond the surface (Eq. 31)::

        a_v = alpha * sqrt(|dz_g|) * sign(dz_g),   dz_g = goal_height - x_v

    (attraction towards the height of the final goal), other components zero.

    Attributes
    ----------
    beta_y : float
        Gain [m/s^2] of the horizontal escape towards the edge (Eq. 30).
    beta_z : float
        Gain [m^2/s^2] of the vertical push away from the surface (Eq. 30).
    alpha : float
        Gain [m^0.5/s^2] of the attraction towards ``goal_height`` (Eq. 31).
    goal_height : float
        Height [m] (on the vertical axis) of the final goal (Eq. 31).
    horizontal_axis, vertical_axis : int
        World axes (0, 1, 2) of the escape direction and of the vertical.
    edge_side : int
        +1: escape past the board's upper face on the horizontal axis; -1: its lower face.
    vertical_side : int
        -1: the point is under the board; +1: over it.
    min_distance : float
        Floor [m] of the vertical distance in Eq. (30).
    """

    beta_y: float = param(0.01, 'Gain [m/s^2] of the horizontal escape towards the edge '
                          '(paper 000 Eq. 30).')
    beta_z: float = param(0.01, 'Gain [m^2/s^2] of the vertical push away from the board '
                          'surface (Eq. 30).')
    alpha: float = param(1.0, 'Gain [m^0.5/s^2] of the attraction towards goal_height once '
                         'past the edge (Eq. 31).')
    goal_height: float = param(0.0, 'Height [m] on the vertical axis of the final goal '
                               '(Eq. 31).')
    horizontal_axis: int = param(1, 'World axis (0, 1, 2) of the escape direction.', 0, 2)
    vertical_axis: int = param(2, 'World axis (0, 1, 2) of the vertical.', 0, 2)
    edge_side: int = param(1, '+1: escape past the board face on the upper side of the '
                           'horizontal axis; -1: past its lower face.', -1, 1)
    vertical_side: int = param(-1, '-1: the point is under the board; +1: over it.', -1, 1)
    min_distance: float = param(0.005, 'Floor [m] of the vertical distance in Eq. 30.')

    def __post_init__(self):
        for name in ('beta_y', 'beta_z', 'alpha'):
            check_positive(f'BoardField.{name}', getattr(self, name), allow_zero=True)
        check_positive('BoardField.min_distance', self.min_distance)
        if not math.isfinite(float(self.goal_height)):
            raise ValidationError(f'BoardField.goal_height: expected a finite number, got '
                                  f'{self.goal_height!r}')
        if (self.horizontal_axis not in (0, 1, 2) or self.vertical_axis not in (0, 1, 2)
                or self.horizontal_axis == self.vertical_axis):
            raise ValidationError(f'BoardField axes: expected two different axes in 0..2, got '
                                  f'horizontal_axis={self.horizontal_axis}, '
                                  f'vertical_axis={self.vertical_axis}')
        for name in ('edge_side', 'vertical_side'):
            if getattr(self, name) not in (-1, 1):
                raise ValidationError(f'BoardField.{name}: expected -1 or +1, got '
                                      f'{getattr(self, name)!r}')

    def acceleration(self, x: Sequence[float], xd, obstacle, distance=None,
                     normal=None) -> Vec3:
        if not isinstance(obstacle, Box):
            raise ValidationError(f'BoardField: expected a Box obstacle, got '
                                  f'{type(obstacle).__name__}')
        h, v = self.horizontal_axis, self.vertical_axis
        edge = obstacle.upper[h] if self.edge_side > 0 else obstacle.lower[h]
        surface = obstacle.lower[v] if self.vertical_side < 0 else obstacle.upper[v]
        dy = self.edge_side * (edge - x[h])          # > 0: not past the edge
        dz = self.vertical_side * (x[v] - surface)   # > 0: on the near side of the surface
        a = [0.0, 0.0, 0.0]
        if dy > 0.0 and dz > 0.0:                    # Eq. (30), paper 000
            dz = max(dz, self.min_distance)
            a[h] = self.edge_side * self.beta_y * dy / dz
            a[v] = self.vertical_side * self.beta_z / dz
        else:                                        # Eq. (31), paper 000
            dzg = self.goal_height - x[v]
            a[v] = math.copysign(self.alpha * math.sqrt(abs(dzg)), dzg)
        return (a[0], a[1], a[2])
