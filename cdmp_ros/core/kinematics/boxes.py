"""Closest points to axis-aligned boxes on plain floats (single points and segments).

The single-configuration coupling (:mod:`cdmp_ros.core.coupling.kernel`) calls these every
tick; :mod:`.closest` holds the batched numpy versions and uses these for one segment.
"""
import math
from typing import Sequence, Tuple

#: Inside a box the normal is that of the nearest face. The deepest point of a segment inside a
#: box is generically a tie between two faces (two depths equal, or the mid-plane of a thin
#: board), decided by rounding; ties within FACE_TIE [m] go to the lowest axis and to the
#: lower face, in the numpy and the plain-float functions alike.
FACE_TIE = 1e-12


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
    # on or inside the surface: the face of the largest per-axis excess (ties: FACE_TIE)
    e0, e1, e2 = max(l0 - x0, x0 - h0), max(l1 - x1, x1 - h1), max(l2 - x2, x2 - h2)
    best = max(e0, e1, e2)
    k = 0 if e0 >= best - FACE_TIE else (1 if e1 >= best - FACE_TIE else 2)
    xk, lk, hk = x[k], lower[k], upper[k]
    up = xk - (lk + hk) / 2 > FACE_TIE
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
    if u[0] == 0.0 and u[1] == 0.0 and u[2] == 0.0:           # a point
        return 0.0
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
