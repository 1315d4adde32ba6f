"""Closest points between links (segments, optionally capsules) and obstacles.

A link is modelled as the segment between two points rigidly attached to it (by default two
consecutive joint origins, :meth:`Chain.link_segments`), optionally inflated by a radius
(a capsule). Obstacles are spheres and axis-aligned boxes (boards). Distances are *signed*:
negative values are penetration depths, as in paper 000, IV-B ("-1.37 cm, a collision").

Segment functions are batched over any leading shape; :func:`link_closest_point` returns the
point on the link as a :class:`PointOfInterest`, so its Jacobian ``J_o`` (paper 000, Eq. 8)
comes from :meth:`Chain.forward_and_jacobian`.
"""
import math
from dataclasses import dataclass
from itertools import product
from typing import Sequence, Tuple, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.chain import Chain, PointOfInterest
from cdmp_ros.core.validation import as_array, check_positive


@dataclass(frozen=True)
class Sphere:
    """Spherical obstacle (a repeller of paper 000 / 003). ``center`` [m], ``radius`` [m]."""

    center: tuple
    radius: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, 'center', tuple(as_array('Sphere.center', self.center,
                                                          (3,)).tolist()))
        object.__setattr__(self, 'radius', check_positive('Sphere.radius', self.radius,
                                                          allow_zero=True))


@dataclass(frozen=True)
class Box:
    """Axis-aligned box obstacle (a board), corners ``lower`` < ``upper`` [m]."""

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


Obstacle = Union[Sphere, Box]


@dataclass(frozen=True)
class ClosestPoint:
    """Result of :func:`link_closest_point`.

    Attributes
    ----------
    distance : float
        Signed distance between the link (capsule) and the obstacle [m]; < 0: penetration.
    point : ndarray (3,)
        Closest point on the link's axis segment (world).
    obstacle_point : ndarray (3,)
        Closest point on the obstacle's surface (world).
    normal : ndarray (3,)
        Unit direction in which the link point should move to increase the distance.
    poi : PointOfInterest
        ``point`` as a point rigidly attached to the link (for ``J_o``).
    t : float
        Position of ``point`` along the segment, in [0, 1].
    """

    distance: float
    point: NDArray[np.float64]
    obstacle_point: NDArray[np.float64]
    normal: NDArray[np.float64]
    poi: PointOfInterest
    t: float


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
    k = np.argmax(d, axis=-1)[..., None]                 # nearest face's axis (inside)
    upper_face = np.take_along_axis(X - (lo + hi) / 2, k, -1) > 0
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


def _box_candidates(A: NDArray, U: NDArray, lo: NDArray, hi: NDArray) -> NDArray:
    """Every parameter t in [0, 1] where the segment-box signed distance can be minimal:
    segment ends, slab-plane crossings, mid-planes, equal-depth crossings (inside, where the
    distance is the max of linear pieces) and stationary points of every outside piece."""
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = np.where(U != 0, 1.0 / np.where(U != 0, U, 1.0), np.nan)
        cand = [np.zeros(A.shape[:-1] + (1,)), np.ones(A.shape[:-1] + (1,)),
                (lo - A) * inv, (hi - A) * inv, ((lo + hi) / 2 - A) * inv]
        # branch values d_k = alpha + beta t: lower side (lo - x), upper side (x - hi)
        branches = [(lo - A, -U), (A - hi, U)]
        for i, j in ((0, 1), (1, 2), (0, 2)):
            for (ai, bi), (aj, bj) in product(branches, branches):
                den = bi[..., i] - bj[..., j]
                cand.append(((aj[..., j] - ai[..., i]) / np.where(den != 0, den, np.nan))[
                    ..., None])
        # outside pieces: sum over active axes of (a_k + t u_k - bound_k)^2
        for sides in product((None, 'lo', 'hi'), repeat=3):
            if sides == (None, None, None):
                continue
            num = 0.0
            den = 0.0
            for k, side in enumerate(sides):
                if side is None:
                    continue
                bound = lo[k] if side == 'lo' else hi[k]
                num = num + (A[..., k] - bound) * U[..., k]
                den = den + U[..., k] ** 2
            cand.append((-num / np.where(den > 0, den, np.nan))[..., None])
    T = np.concatenate(cand, axis=-1)
    return np.clip(np.nan_to_num(T, nan=0.0), 0.0, 1.0)


def point_box(x: Sequence[float], lower: Sequence[float], upper: Sequence[float]
              ) -> Tuple[float, Tuple[float, float, float], Tuple[float, float, float]]:
    """:func:`box_signed_distance` of one point on plain floats (same conventions).

    Returns
    -------
    distance : float
    surface : (3,) tuple
    normal : (3,) tuple
    """
    x0, x1, x2 = x
    l0, l1, l2 = lower
    h0, h1, h2 = upper
    c0 = l0 if x0 < l0 else (h0 if x0 > h0 else x0)
    c1 = l1 if x1 < l1 else (h1 if x1 > h1 else x1)
    c2 = l2 if x2 < l2 else (h2 if x2 > h2 else x2)
    v0, v1, v2 = x0 - c0, x1 - c1, x2 - c2
    out = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if out > 0.0:
        if out > 1e-12:
            return out, (c0, c1, c2), (v0 / out, v1 / out, v2 / out)
        # as box_signed_distance: a (sub-1e-12) outside point takes the face normal below
    # on or inside the surface: the face of the largest per-axis excess (first on ties)
    k, best = 0, max(l0 - x0, x0 - h0)
    e = max(l1 - x1, x1 - h1)
    if e > best:
        k, best = 1, e
    e = max(l2 - x2, x2 - h2)
    if e > best:
        k, best = 2, e
    xk, lk, hk = x[k], lower[k], upper[k]
    up = xk - (lk + hk) / 2 > 0
    surface = [x0, x1, x2]
    surface[k] = hk if up else lk
    normal = [0.0, 0.0, 0.0]
    normal[k] = 1.0 if up else -1.0
    if out > 0.0:
        return out, (c0, c1, c2), tuple(normal)
    return min(best, 0.0), tuple(surface), tuple(normal)


def segment_box_scalar(a: Sequence[float], b: Sequence[float], lower: Sequence[float],
                       upper: Sequence[float]) -> float:
    """Segment parameter ``t`` in [0, 1] of the point of ``a -> b`` with the smallest signed
    distance to the axis-aligned box (exact; plain floats, a few microseconds).

    The signed distance along the segment is convex in t. If the segment meets the box
    (slab clipping gives ``[t_in, t_out]``), the minimum is inside, where the distance is
    the maximum of the six lines ``lo_k - x_k(t)`` and ``x_k(t) - hi_k``: it is attained at
    ``t_in``, ``t_out`` or where a rising line meets a falling one. Otherwise the squared
    distance is a convex piecewise quadratic whose pieces change where the segment crosses a
    slab plane; each piece is minimised in closed form.
    """
    a0, a1, a2 = a
    u = (b[0] - a0, b[1] - a1, b[2] - a2)
    lo, hi = lower, upper
    t_in, t_out = 0.0, 1.0
    cuts = []
    for k in range(3):
        ak, uk = a[k], u[k]
        if uk == 0.0:
            if ak < lo[k] or ak > hi[k]:
                t_in, t_out = 1.0, 0.0                          # never inside this slab
            continue
        t1, t2 = (lo[k] - ak) / uk, (hi[k] - ak) / uk
        if t1 > t2:
            t1, t2 = t2, t1
        if t1 > t_in:
            t_in = t1
        if t2 < t_out:
            t_out = t2
        cuts += (t1, t2)
    if t_in <= t_out:                                            # meets the box
        # per axis: max(lo_k - x_k, x_k - hi_k) = |c_k + u_k t| - h_k (a V; c, h: offset
        # from the centre and half-size); candidates: the rising branch of axis k meets the
        # falling branch of axis l (k == l: the vertex, a mid-plane crossing)
        c0, c1, c2 = [a[k] - 0.5 * (lo[k] + hi[k]) for k in range(3)]
        h0, h1, h2 = [0.5 * (hi[k] - lo[k]) for k in range(3)]
        s0, s1, s2 = u
        axes = [(c, h, -1.0 if s < 0.0 else 1.0, abs(s)) for c, h, s in
                ((c0, h0, s0), (c1, h1, s1), (c2, h2, s2)) if s != 0.0]
        cand = [t_in, t_out]
        for ck, hk, sk, ak in axes:
            for cl, hl, sl, al in axes:
                t = (hk - hl - sk * ck - sl * cl) / (ak + al)
                if t_in < t < t_out:
                    cand.append(t)
        best_t, best = t_in, math.inf
        for t in cand:
            f = max(abs(c0 + s0 * t) - h0, abs(c1 + s1 * t) - h1, abs(c2 + s2 * t) - h2)
            if f < best:
                best_t, best = t, f
        return best_t
    # outside everywhere: squared distance, one quadratic per piece between slab crossings
    knots = sorted([0.0, 1.0] + [t for t in cuts if 0.0 < t < 1.0])
    best_t, best = 0.0, math.inf
    for t_l, t_r in zip(knots[:-1], knots[1:]):
        tm = 0.5 * (t_l + t_r)
        num = den = 0.0
        for k in range(3):
            xk = a[k] + tm * u[k]
            bound = lo[k] if xk < lo[k] else (hi[k] if xk > hi[k] else None)
            if bound is not None:
                num += (a[k] - bound) * u[k]
                den += u[k] * u[k]
        t = -num / den if den > 0.0 else t_l
        t = t_l if t < t_l else (t_r if t > t_r else t)
        g = 0.0
        for k in range(3):
            xk = a[k] + t * u[k]
            e = lo[k] - xk if xk < lo[k] else (xk - hi[k] if xk > hi[k] else 0.0)
            g += e * e
        if g < best:
            best_t, best = t, g
    return best_t


def segment_box(A: ArrayLike, B: ArrayLike, lower: ArrayLike, upper: ArrayLike,
                link_radius: float = 0.0):
    """Closest point of segments ``A -> B`` (..., 3) to an axis-aligned box (exact).

    The signed distance along the segment is convex in t and piecewise quadratic (outside)
    or piecewise linear (inside). One segment (A and B of shape (3,)) goes through
    :func:`segment_box_scalar`; batches evaluate every candidate of :func:`_box_candidates`
    and keep the smallest.

    Returns
    -------
    t, distance, surface, normal
        As :func:`segment_sphere` (``normal`` points out of the box towards the link).
    """
    A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    if A.shape == (3,) and B.shape == (3,) and lo.shape == (3,) and hi.shape == (3,):
        a, b, lo_l, hi_l = A.tolist(), B.tolist(), lo.tolist(), hi.tolist()
        t = segment_box_scalar(a, b, lo_l, hi_l)
        x = [a[k] + t * (b[k] - a[k]) for k in range(3)]
        d, surface, normal = point_box(x, lo_l, hi_l)
        return (np.float64(t), np.float64(d - link_radius), np.array(surface),
                np.array(normal))
    U = B - A
    T = _box_candidates(A, U, lo, hi)                                 # (..., n_cand)
    P = A[..., None, :] + T[..., None] * U[..., None, :]
    dist, _, _ = box_signed_distance(P, lo, hi)
    best = np.argmin(dist, axis=-1)[..., None]
    t = np.take_along_axis(T, best, -1)[..., 0]
    X = A + t[..., None] * U
    distance, surface, normal = box_signed_distance(X, lo, hi)
    return t, distance - link_radius, surface, normal


def segment_obstacle(A: ArrayLike, B: ArrayLike, obstacle: Obstacle, link_radius: float = 0.0):
    """Dispatch to :func:`segment_sphere` or :func:`segment_box`."""
    if isinstance(obstacle, Sphere):
        return segment_sphere(A, B, obstacle.center, obstacle.radius, link_radius)
    if isinstance(obstacle, Box):
        return segment_box(A, B, obstacle.lower, obstacle.upper, link_radius)
    raise ValidationError(f'obstacle: expected Sphere or Box, got {type(obstacle).__name__}')


Segment = Tuple[str, Sequence[float], Sequence[float]]


def link_closest_point(chain: Chain, q: ArrayLike, segment: Segment,
                       obstacle: Obstacle, link_radius: float = 0.0) -> ClosestPoint:
    """Closest point of one link to one obstacle at configuration ``q`` (n_dofs,).

    Parameters
    ----------
    chain : Chain
    q : array-like (n_dofs,)
    segment : (link, start, end)
        The link and two points in its frame (e.g. an entry of ``chain.link_segments()``).
    obstacle : Sphere or Box
    link_radius : float
        Radius of the capsule modelling the link [m].
    """
    link, start, end = segment
    start = as_array('segment start', start, (3,))
    end = as_array('segment end', end, (3,))
    ends = chain.forward(np.asarray(q, dtype=np.float64),
                         (PointOfInterest(link, tuple(start)), PointOfInterest(link, tuple(end))))
    t, distance, surface, normal = segment_obstacle(ends[0], ends[1], obstacle, link_radius)
    t = float(t)
    point = ends[0] + t * (ends[1] - ends[0])
    poi = PointOfInterest(link, tuple((start + t * (end - start)).tolist()))
    return ClosestPoint(float(distance), point, surface, normal, poi, t)


def closest_distances(chain: Chain, Q: ArrayLike, segments: Sequence[Tuple[str, tuple, tuple]],
                      obstacles: Sequence[Obstacle], link_radius: float = 0.0
                      ) -> NDArray[np.float64]:
    """Signed distances (..., n_segments, n_obstacles) for configurations Q (..., n_dofs)."""
    points = []
    for link, start, end in segments:
        points += [PointOfInterest(link, tuple(start)), PointOfInterest(link, tuple(end))]
    X = chain.forward(Q, points)
    A, B = X[..., 0::2, :], X[..., 1::2, :]
    return np.stack([segment_obstacle(A, B, obs, link_radius)[1] for obs in obstacles], -1)
