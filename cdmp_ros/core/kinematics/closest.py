"""Obstacles (spheres, axis-aligned and oriented boxes) and closest points between links
(segments, optionally capsules) and obstacles.

A link is modelled as the segment between two points rigidly attached to it (by default two
consecutive joint origins, :meth:`Chain.link_segments`), optionally inflated by a radius
(a capsule). Distances are *signed*: negative values are penetration depths, as in paper 000,
IV-B ("-1.37 cm, a collision"). :func:`box_signed_distance` and :func:`segment_sphere` are
batched over any leading shape; one segment to a box takes the exact plain-float path of
:mod:`.boxes` (slab clipping, :meth:`OrientedBox.segment`), which the obstacle coupling
(:mod:`cdmp_ros.core.coupling.obstacle`) evaluates every tick.
"""
from dataclasses import dataclass
from typing import Sequence, Tuple, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.boxes import FACE_TIE, point_box, segment_box_scalar
from cdmp_ros.core.validation import as_array, check_positive


@dataclass(frozen=True)
class Sphere:
    """Spherical obstacle (a repeller of paper 000 / 003).

    Attributes
    ----------
    center : tuple of 3 float
        Centre [m] (world, the robot base frame).
    radius : float
        Radius [m], >= 0.
    """

    center: tuple
    radius: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, 'center', tuple(as_array('Sphere.center', self.center,
                                                          (3,)).tolist()))
        object.__setattr__(self, 'radius', check_positive('Sphere.radius', self.radius,
                                                          allow_zero=True))


@dataclass(frozen=True)
class Box:
    """Axis-aligned box obstacle (a board).

    Attributes
    ----------
    lower, upper : tuple of 3 float
        Opposite corners [m], ``lower < upper`` on every axis.
    """

    lower: tuple
    upper: tuple

    def __post_init__(self):
        lo = as_array('Box.lower', self.lower, (3,))
        hi = as_array('Box.upper', self.upper, (3,))
        if np.any(hi <= lo):
            raise ValidationError(f'Box: expected lower < upper on every axis, got '
                                  f'lower={lo.tolist()}, upper={hi.tolist()}')
        object.__setattr__(self, 'lower', tuple(lo.tolist()))
        object.__setattr__(self, 'upper', tuple(hi.tolist()))

    @classmethod
    def from_center(cls, center: ArrayLike, size: ArrayLike) -> 'Box':
        """Box of full edge lengths ``size`` centred at ``center`` (a CUBE marker)."""
        c = as_array('center', center, (3,))
        s = as_array('size', size, (3,))
        return cls(tuple(c - s / 2), tuple(c + s / 2))


def quaternion_of(rotation) -> tuple:
    """Unit quaternion (x, y, z, w) of a rotation matrix (ROS and pybullet order), by the
    numerically stable branch on the largest of trace and diagonal; the inverse of
    :meth:`OrientedBox.from_quaternion` up to the sign of q."""
    R = np.asarray(rotation, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > max(R[0, 0], R[1, 1], R[2, 2]):
        w = 0.5 * np.sqrt(1.0 + tr)
        q = ((R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
             (R[1, 0] - R[0, 1]) / (4 * w), w)
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        r = np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 0.0))
        v = [0.0, 0.0, 0.0]
        v[i] = 0.5 * r
        v[j] = (R[j, i] + R[i, j]) / (2 * r)
        v[k] = (R[k, i] + R[i, k]) / (2 * r)
        q = (v[0], v[1], v[2], (R[k, j] - R[j, k]) / (2 * r))
    n = np.sqrt(sum(c * c for c in q))
    return tuple(float(c / n) for c in q)


@dataclass(frozen=True)
class OrientedBox:
    """Box obstacle of any orientation: full edge lengths ``size`` [m] along the columns of
    ``rotation`` (box frame -> world), centred at ``center`` [m]. In its own frame
    (``x_b = rotation^T (x - center)``) it is the axis-aligned box ``[-half, half]``; every
    distance is computed there and mapped back (rotations preserve distances and segment
    parameters). :class:`Box` remains the axis-aligned kind (boards, Eq. 30-31)."""

    center: tuple
    size: tuple
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def __post_init__(self):
        c = as_array('OrientedBox.center', self.center, (3,))
        size = as_array('OrientedBox.size', self.size, (3,))
        if np.any(size <= 0):
            raise ValidationError(f'OrientedBox.size: expected positive edge lengths, got '
                                  f'{size.tolist()}')
        R = as_array('OrientedBox.rotation', self.rotation, (3, 3))
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
            raise ValidationError(f'OrientedBox.rotation: expected a rotation matrix, got '
                                  f'{R.tolist()}')
        object.__setattr__(self, 'center', tuple(c.tolist()))
        object.__setattr__(self, 'size', tuple(size.tolist()))
        object.__setattr__(self, 'rotation', tuple(map(tuple, R.tolist())))
        object.__setattr__(self, 'half', tuple((size / 2).tolist()))
        object.__setattr__(self, '_neg_half', tuple((-size / 2).tolist()))

    @classmethod
    def from_quaternion(cls, center: ArrayLike, size: ArrayLike,
                        quaternion: ArrayLike) -> 'OrientedBox':
        """From a unit quaternion ``(x, y, z, w)`` (a CUBE marker's orientation)."""
        x, y, z, w = as_array('quaternion', quaternion, (4,)) / np.linalg.norm(quaternion)
        R = ((1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
             (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
             (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)))
        return cls(center, size, R)

    def quaternion(self) -> tuple:
        """The box's orientation as a unit quaternion ``(x, y, z, w)``."""
        return quaternion_of(self.rotation)

    def to_box_frame(self, X: ArrayLike) -> NDArray[np.float64]:
        """Points (..., 3) in the box frame."""
        return (np.asarray(X, dtype=np.float64) - self.center) @ np.array(self.rotation)

    def signed_distance(self, X: ArrayLike) -> Tuple[NDArray, NDArray, NDArray]:
        """As :func:`box_signed_distance` (distance, surface point, normal; world)."""
        R = np.array(self.rotation)
        d, S, N = box_signed_distance(self.to_box_frame(X), self._neg_half, self.half)
        return d, S @ R.T + self.center, N @ R.T

    # plain-float versions for the single-configuration coupling
    def _frame(self, x: Sequence[float]) -> Tuple[float, float, float]:
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self.rotation
        c = self.center
        v0, v1, v2 = x[0] - c[0], x[1] - c[1], x[2] - c[2]
        return (r00 * v0 + r10 * v1 + r20 * v2, r01 * v0 + r11 * v1 + r21 * v2,
                r02 * v0 + r12 * v1 + r22 * v2)

    def point(self, x: Sequence[float]) -> Tuple[float, tuple]:
        """Signed distance and outward normal (world) of one point (plain floats)."""
        d, _, (n0, n1, n2) = point_box(self._frame(x), self._neg_half, self.half)
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self.rotation
        return d, (r00 * n0 + r01 * n1 + r02 * n2, r10 * n0 + r11 * n1 + r12 * n2,
                   r20 * n0 + r21 * n1 + r22 * n2)

    def segment(self, a: Sequence[float], b: Sequence[float]) -> float:
        """:func:`segment_box_scalar` of the segment ``a -> b`` (world, plain floats)."""
        return segment_box_scalar(self._frame(a), self._frame(b), self._neg_half, self.half)


Obstacle = Union[Sphere, Box, OrientedBox]


def _unit(v: NDArray, fallback: NDArray) -> NDArray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    safe = np.where(norm > 1e-12, norm, 1.0)
    return np.where(norm > 1e-12, v / safe, fallback)


def box_signed_distance(X: ArrayLike, lower: ArrayLike, upper: ArrayLike
                        ) -> Tuple[NDArray, NDArray, NDArray]:
    """Signed distance of points to an axis-aligned box, surface point and outward normal.

    Parameters
    ----------
    X : array-like (..., 3)
    lower, upper : array-like (3,)

    Returns
    -------
    distance : ndarray (...)
        Euclidean distance outside, minus the depth below the nearest face inside.
    surface : ndarray (..., 3)
        Closest point of the box surface.
    normal : ndarray (..., 3)
        Unit vector from ``surface`` towards the outside (for points outside: towards X).
    """
    X = np.asarray(X, dtype=np.float64)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    d = np.maximum(lo - X, X - hi)                       # per-axis slab excess
    clamped = np.clip(X, lo, hi)
    outside = np.linalg.norm(X - clamped, axis=-1)
    inside = np.minimum(d.max(axis=-1), 0.0)
    # nearest face's axis (inside); ties within FACE_TIE: lowest axis, lower face
    k = np.argmax(d >= d.max(axis=-1, keepdims=True) - FACE_TIE, axis=-1)[..., None]
    upper_face = np.take_along_axis(X - (lo + hi) / 2, k, -1) > FACE_TIE
    face_normal = np.zeros(X.shape)
    np.put_along_axis(face_normal, k, np.where(upper_face, 1.0, -1.0), -1)
    face_point = X.copy()
    np.put_along_axis(face_point, k, np.where(upper_face, np.take_along_axis(
        np.broadcast_to(hi, X.shape), k, -1), np.take_along_axis(
        np.broadcast_to(lo, X.shape), k, -1)), -1)
    is_out = (outside > 0)[..., None]
    normal = np.where(is_out, _unit(X - clamped, face_normal), face_normal)
    surface = np.where(is_out, clamped, face_point)
    return outside + inside, surface, normal


def segment_sphere(A: ArrayLike, B: ArrayLike, center: ArrayLike, radius: float = 0.0,
                   link_radius: float = 0.0):
    """Closest point of segments ``A -> B`` (..., 3) to a sphere.

    Returns
    -------
    t : ndarray (...)
        Segment parameter of the closest point ``A + t (B - A)``.
    distance : ndarray (...)
        Signed distance between the capsule of radius ``link_radius`` and the sphere.
    surface : ndarray (..., 3)
        Closest point on the sphere.
    normal : ndarray (..., 3)
        Unit vector from the sphere centre to the segment point (+z if they coincide).
    """
    A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64)
    U = B - A
    uu = np.einsum('...i,...i->...', U, U)
    t = np.clip(np.einsum('...i,...i->...', c - A, U) / np.where(uu > 0, uu, 1.0), 0.0, 1.0)
    P = A + t[..., None] * U
    normal = _unit(P - c, np.array([0.0, 0.0, 1.0]))
    distance = np.linalg.norm(P - c, axis=-1) - radius - link_radius
    return t, distance, c + radius * normal, normal
