"""Closest points of links to obstacles by candidate enumeration: the test oracle of the
obstacle coupling's plain-float path (:mod:`cdmp_ros.core.coupling.obstacle`,
:mod:`cdmp_ros.core.kinematics.boxes`) and of the batched distances of the package.

Batched over any leading shape. :func:`segment_box` of one segment takes the plain-float path
of :func:`~cdmp_ros.core.kinematics.boxes.segment_box_scalar`; batches evaluate every
candidate of :func:`box_candidates` (the signed distance along a segment is convex in t and
piecewise quadratic outside, piecewise linear inside) and keep the smallest.
:func:`link_closest_point` returns the point on the link as a :class:`PointOfInterest`, so its
Jacobian ``J_o`` (paper 000, Eq. 8) comes from :meth:`Chain.forward_and_jacobian`.
"""
from dataclasses import dataclass
from itertools import product
from typing import Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.boxes import point_box, segment_box_scalar
from cdmp_ros.core.kinematics.chain import Chain, PointOfInterest
from cdmp_ros.core.kinematics.closest import (Box, Obstacle, OrientedBox, Sphere,
                                              box_signed_distance, segment_sphere)
from cdmp_ros.core.validation import as_array


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


def box_candidates(A: NDArray, U: NDArray, lo: NDArray, hi: NDArray) -> NDArray:
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


def segment_box(A: ArrayLike, B: ArrayLike, lower: ArrayLike, upper: ArrayLike,
                link_radius: float = 0.0):
    """Closest point of segments ``A -> B`` (..., 3) to an axis-aligned box (exact).

    The signed distance along the segment is convex in t and piecewise quadratic (outside)
    or piecewise linear (inside). One segment (A and B of shape (3,)) goes through
    :func:`segment_box_scalar`; batches evaluate every candidate of :func:`box_candidates`
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
    T = box_candidates(A, U, lo, hi)                                 # (..., n_cand)
    P = A[..., None, :] + T[..., None] * U[..., None, :]
    dist, _, _ = box_signed_distance(P, lo, hi)
    best = np.argmin(dist, axis=-1)[..., None]
    t = np.take_along_axis(T, best, -1)[..., 0]
    X = A + t[..., None] * U
    distance, surface, normal = box_signed_distance(X, lo, hi)
    return t, distance - link_radius, surface, normal


def segment_obstacle(A: ArrayLike, B: ArrayLike, obstacle: Obstacle, link_radius: float = 0.0):
    """Dispatch to :func:`segment_sphere` or :func:`segment_box` (an :class:`OrientedBox`
    in its own frame)."""
    if isinstance(obstacle, Sphere):
        return segment_sphere(A, B, obstacle.center, obstacle.radius, link_radius)
    if isinstance(obstacle, Box):
        return segment_box(A, B, obstacle.lower, obstacle.upper, link_radius)
    if isinstance(obstacle, OrientedBox):
        R = np.array(obstacle.rotation)
        t, d, S, N = segment_box(obstacle.to_box_frame(A), obstacle.to_box_frame(B),
                                 obstacle._neg_half, obstacle.half, link_radius)
        return t, d, S @ R.T + obstacle.center, N @ R.T
    raise ValidationError(f'obstacle: expected Sphere, Box or OrientedBox, got '
                          f'{type(obstacle).__name__}')


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
