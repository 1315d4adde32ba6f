"""Accurate tail probabilities of the quadratic form Q = |x - c|^2 for Gaussian x.

For x ~ N(m, S) in k dimensions, Q follows a generalised chi-square law: with S = U diag(lam) U^T
and delta = U^T (m - c), Q = sum_i lam_i (z_i + delta_i / sqrt(lam_i))^2, z ~ N(0, I). Paper 003
replaces this law by a Gamma distribution with the same mean and variance (its Eq. 15 moment
match, :func:`cdmp_ros.core.promp.gaussian.gamma_cdf`); that law's tail is lighter than the true
one
exactly where a confidence alpha = 0.999 lives, so constraints met "with probability alpha" under
the Gamma match are violated 1.4-2.5 times more often than asked (see ../shared/design.md,
Numerics notes).

This module evaluates P(Q <= x) by the Lugannani-Rice saddle-point approximation, with Daniels'
second-order term in the upper tail, and analytic gradients with respect to the mean and the
covariance.

Cumulant generating function of Q, with b_i = 1 / (1 - 2 s lam_i), for s < 1 / (2 max lam):

    K(s)     = sum_i [ -1/2 log(1 - 2 s lam_i) + s delta_i^2 b_i ]
    K^(j)(s) = sum_i [ 2^(j-1) (j-1)! (lam_i b_i)^j + 2^(j-1) j! lam_i^(j-1) delta_i^2 b_i^(j+1) ]

(j >= 1; K' = sum_i [lam_i b_i + delta_i^2 b_i^2]). The saddle point s_hat solves K'(s_hat) = x;
then w = sign(s_hat) sqrt(2 (s_hat x - K(s_hat))), u = s_hat sqrt(K2), lambda_3 = K3 / K2^(3/2),
lambda_4 = K4 / K2^2 (K_j = K^(j)(s_hat)) and

    P(Q <= x) ~= Phi(w) + phi(w) (1/w - 1/u)                       (Lugannani and Rice, 1980)
                 - phi(w) [ (lambda_4/8 - 5 lambda_3^2/24) / u - lambda_3 / (2 u^2)
                            - 1/u^3 + 1/w^3 ]                      (Daniels, 1987)

The second line (``second_order``) is used above the mean of Q (s_hat > 0) by default, on both
sides or nowhere on request; near the mean it is blended in smoothly (see _W2_LO).

Accuracy (benchmarks/bench_quadratic_tail.py: relative error of the tail against an exact
reference, nested 1-D integrals of closed-form normal probabilities cross-checked against Imhof's
integral; 3528 tails at levels 1e-4 ... 5e-2, k = 2 and 3, eigenvalue ratios 1 ... 1e-6 with one
or two small eigenvalues, offsets 0 ... 5 standard deviations along the large, the small and the
diagonal direction; test/test_core_quadratic_tail.py holds the bounds):

- upper tail P(Q > x) (waypoints, the smoothness bound): -6.3 % ... +0.8 % at every ratio (the
  first-order formula: -9.6 % ... +8.2 %);
- lower tail P(Q <= x) (repellers), first order: -3.2 % ... +7.3 % at ratios >= 0.1, up to
  +26.6 % (tail overestimated: conservative) at smaller ratios, with the worst case a
  needle-shaped covariance (second and third eigenvalues < 1 % of the first) whose offset from c
  lies across the needle; -4.7 % is the largest underestimate. There Daniels' term overcorrects
  (``second_order='both'``: -13.2 % ... +6.1 %, the tail underestimated by up to 13 % at ratios
  <= 1e-2), so it is not used below the mean by default;
- k = 1: lower tail -3.7 % ... +15.6 %, upper -3.4 % ... +0.8 %.

Tiny eigenvalues are not treated as degenerate: the offset along their direction makes Q vary
linearly, by 2 |delta_i| sqrt(lam_i) per standard deviation, which is the scale of x - E[Q] in
the lower tail of a needle (ratio 1e-6, offset 1 along the thin axis: dropping the thin axis
gives P = 0 where the exact tail is 1e-2). The saddle point needs no such threshold (the
eigenvalues are floored only at 1e-12 of the row's scale).

Gradients: with theta any entry of (m, S), the envelope theorem gives dw/dtheta =
-(dK/dtheta) / w, and d s_hat / dtheta = -(dK'/dtheta) / K''(s_hat), so dP = sum_j A_j dK^(j)|_s
with scalars A_j per row. Each K^(j) = tr F_j(S) + d^T F_j'(S) d (d = m - c), so dP/dd =
2 f(S) d and dP/dS = f(S) + the Frechet derivative of d^T f(S) d, f = sum_j A_j F_j': in the
eigenbasis of S, diag(f(lam)) + (delta delta^T) o f[lam_p, lam_q], the divided differences
written as sums of products (no cancellation for close or repeated eigenvalues).
"""
from typing import Optional, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.gaussian import normal_cdf, normal_pdf

# Below this |w| the saddle point is at the mean of Q and Lugannani-Rice is 0/0 in floating
# point: the one-term Edgeworth expansion with the exact mean, variance and skewness of Q, which
# has the same limit at the mean, is used there (P ~ 0.5, far from any confidence level a
# constraint asks for; continuous across the switch up to O(_W_CENTER)).
_W_CENTER = 2e-4
_MAX_ITER = 200
# alpha_j = 2^(j-1) (j-1)! and beta_j = 2^(j-1) j! = j alpha_j of the cumulant formulas (index j)
_ALPHA = (0.0, 1.0, 2.0, 8.0, 48.0, 384.0)
_BETA = (0.0, 1.0, 4.0, 24.0, 192.0, 1920.0)
# The second-order term's 1/w^3 - 1/u^3 cancels to O(1) as w -> 0 (the mean of Q): it enters
# with a smoothstep weight that rises from 0 at w = _W2_LO (|w| with second_order='both') to 1
# at _W2_HI, so it is evaluated only where that cancellation costs < 1e-11; on the band P lies
# between about 0.3 and 0.8 (measured, k = 1 ... 30), far from any confidence level a
# constraint asks for.
_W2_LO = 0.02
_W2_HI = 0.2
_FAR = 9.0          # chi2_3 tail: P(chi2_3 > 81) < 1e-17
_FAR_DIR = 7.5      # normal tail: Phi(-7.5) < 4e-14


def _rowsum(a: NDArray) -> NDArray:
    """Sum over the last axis of a (n, k) array (a matrix-vector product: np.sum(axis=1) costs
    several times more on these short rows)."""
    return a @ np.ones(a.shape[-1])


def _cgf(s, lam, d2, nder=5):
    """b = 1 / (1 - 2 s lam) and the rows' K, K', ..., K^(nder) at s, stacked (nder + 1, n):
    K^(j)(s) = sum_i (lam_i b_i)^(j-1) [alpha_j lam_i b_i + beta_j delta_i^2 b_i^2], j >= 1."""
    sc = s[:, None]
    b = 1.0 / (1.0 - 2.0 * sc * lam)
    lb = lam * b
    t = d2 * b * b
    terms = np.empty((nder + 1,) + lam.shape)
    terms[0] = -0.5 * np.log1p(-2.0 * sc * lam) + sc * d2 * b
    terms[1] = lb + t
    p = lb                                      # (lam b)^(j-1)
    for j in range(2, nder + 1):
        terms[j] = p * (_ALPHA[j] * lb + _BETA[j] * t)
        p = p * lb
    return b, terms @ np.ones(lam.shape[-1])


def _log1p_plus(t):
    """log(1 - t) + t without cancellation (a series for |t| < 0.1)."""
    out = np.log1p(-t) + t
    small = np.abs(t) < 0.1
    if np.any(small):
        ts = t[small]
        acc = np.full(ts.shape, 1.0 / 18.0)
        for j in range(17, 1, -1):       # -(t^2/2 + t^3/3 + ... + t^18/18), |t|^17 < 1e-16
            acc = 1.0 / j + ts * acc
        out[small] = -ts * ts * acc
    return out


def _w2(s, lam, d2, b):
    """w^2 = 2 (s K'(s) - K(s)) at the saddle point, written so that it keeps full relative
    precision for s -> 0 (near the mean of Q); x = K'(s_hat) there, so w depends on s_hat
    alone and the root's last-digit error does not reach P."""
    t = 2.0 * s[:, None] * lam
    return _rowsum(t * t * b + _log1p_plus(t) + 2.0 * t * s[:, None] * d2 * b * b)


def _k1(s, lam2, lam, d2, ones):
    """K'(s) and K''(s) (lam2 = 2 lam; row sums as a matrix-vector product)."""
    b = 1.0 / (1.0 - s[:, None] * lam2)
    lb = lam * b
    t = d2 * b * b
    return (lb + t) @ ones, (lb * (lb + t + t)) @ (ones + ones)


def saddle_point(lam: NDArray, d2: NDArray, x: NDArray, s0: Optional[NDArray] = None
                 ) -> NDArray:
    """Solve K'(s) = x for every row (safeguarded Newton on log K', bisection fallback).

    Parameters
    ----------
    lam : ndarray, shape (n, k)
        Eigenvalues of S, all > 0.
    d2 : ndarray, shape (n, k)
        Squared mean offsets in the eigenbasis, delta_i^2.
    x : ndarray, shape (n,)
        Thresholds, > 0.
    s0 : ndarray, shape (n,), optional
        Initial guesses (a warm start, e.g. the roots of a nearby problem); rows whose guess
        lies outside the bracket of the root start from the default guess instead.

    Returns
    -------
    s_hat : ndarray, shape (n,)
    """
    n, k = lam.shape
    lam_max = np.max(lam, axis=1)
    E = _rowsum(lam + d2)
    upper = x > E
    # bracket: (0, pole) above the mean; below it, K'(s) <= k / (2|s|) + sum d2/lam^2 / (4 s^2)
    pole = 0.5 / lam_max
    lo = np.where(upper, 0.0,
                  -(k / x + np.sqrt(_rowsum(d2 / (lam * lam)) / x)))
    hi = np.where(upper, pole, 0.0)
    s = np.where(upper, 0.5 * pole, 0.0)
    if s0 is not None:
        s = np.where((s0 > lo) & (s0 < hi), s0, s)
    log_x = np.log(x)
    lam2 = 2.0 * lam
    ones = np.ones(k)
    for _ in range(_MAX_ITER):
        K1, K2 = _k1(s, lam2, lam, d2, ones)
        f = np.log(K1) - log_x
        if np.all(np.abs(f) < 1e-13):
            break
        lo = np.where(f < 0.0, s, lo)
        hi = np.where(f > 0.0, s, hi)
        step = s - f * K1 / K2
        inside = (step > lo) & (step < hi)
        s = np.where(inside, step, 0.5 * (lo + hi))
    return s


def _eigh(S: NDArray) -> Tuple[NDArray, NDArray]:
    """Eigenvalues (ascending) and eigenvectors of symmetric (n, k, k) matrices; closed forms
    for k = 2 and 3 (LAPACK's per-matrix overhead dominates such small batches)."""
    k = S.shape[-1]
    if k == 2:
        return _eigh2(S)
    if k == 3:
        return _eigh3(S)
    return np.linalg.eigh(S)


def _eigh2(S):
    a, b, c = S[:, 0, 0], 0.5 * (S[:, 0, 1] + S[:, 1, 0]), S[:, 1, 1]
    half = 0.5 * (a + c)
    r = np.hypot(0.5 * (a - c), b)
    big = half + r
    with np.errstate(divide='ignore', invalid='ignore'):
        small = np.where(big > 0.0, (a * c - b * b) / big, half - r)   # no cancellation
    theta = 0.5 * np.arctan2(2.0 * b, a - c)       # direction of the larger eigenvalue
    cs, sn = np.cos(theta), np.sin(theta)
    U = np.empty(S.shape)
    U[:, 0, 0], U[:, 1, 0] = -sn, cs
    U[:, 0, 1], U[:, 1, 1] = cs, sn
    return np.stack([small, big], axis=1), U


# relative eigenvalue gap below which a 3 x 3 matrix goes to LAPACK (eigenvectors from cross
# products lose accuracy as gap -> 0)
_GAP3 = 1e-5


def _eigh3(S):
    """Trigonometric eigenvalues (Smith 1961) and cross-product eigenvectors of the extreme
    eigenvalues, element-wise over the rows; rows with nearly repeated eigenvalues are handed
    to np.linalg.eigh."""
    a = S[:, 0, 0]
    b = S[:, 1, 1]
    c = S[:, 2, 2]
    d = 0.5 * (S[:, 0, 1] + S[:, 1, 0])
    e = 0.5 * (S[:, 1, 2] + S[:, 2, 1])
    f = 0.5 * (S[:, 0, 2] + S[:, 2, 0])
    q = (a + b + c) / 3.0
    aq, bq, cq = a - q, b - q, c - q
    p = np.sqrt((aq * aq + bq * bq + cq * cq + 2.0 * (d * d + e * e + f * f)) / 6.0)
    bad = ~(p > 0.0)
    ps = np.where(bad, 1.0, p)
    det = aq * (bq * cq - e * e) - d * (d * cq - e * f) + f * (d * e - bq * f)
    r = np.clip(0.5 * det / (ps * ps * ps), -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    big = q + 2.0 * p * np.cos(phi)
    small = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    mid = 3.0 * q - big - small
    bad |= np.minimum(big - mid, mid - small) < _GAP3 * ps

    # eigenvectors of the largest and the smallest eigenvalue together (leading axis 2): rows
    # of S - lam I are (a', d, f), (d, b', e), (f, e, c'); the largest of their pairwise cross
    # products spans the null space
    lam2 = np.stack([big, small])
    a_, b_, c_ = a - lam2, b - lam2, c - lam2
    de, fd, ff, dd, ee, ef, df = d * e, f * d, f * f, d * d, e * e, e * f, d * f
    c01 = np.stack([de - f * b_, fd - a_ * e, a_ * b_ - dd], axis=2)
    c02 = np.stack([d * c_ - ef, ff - a_ * c_, a_ * e - df], axis=2)
    c12 = np.stack([b_ * c_ - ee, ef - d * c_, de - b_ * f], axis=2)
    n01, n02, n12 = (_rowsum(v * v) for v in (c01, c02, c12))
    v = np.where((n01 >= n02)[:, :, None], c01, c02)
    nv = np.maximum(n01, n02)
    v = np.where((n12 > nv)[:, :, None], c12, v)
    nv = np.maximum(nv, n12)
    v /= np.sqrt(np.maximum(nv, 1e-300))[:, :, None]
    v_big, v_small = v[0], v[1]
    bad |= np.abs(_rowsum(v_big * v_small)) > 1e-9
    v_mid = np.stack([v_big[:, 1] * v_small[:, 2] - v_big[:, 2] * v_small[:, 1],
                      v_big[:, 2] * v_small[:, 0] - v_big[:, 0] * v_small[:, 2],
                      v_big[:, 0] * v_small[:, 1] - v_big[:, 1] * v_small[:, 0]], axis=1)
    U = np.stack([v_small, v_mid, v_big], axis=2)
    lam = np.stack([small, mid, big], axis=1)
    if np.any(bad):
        lam[bad], U[bad] = np.linalg.eigh(S[bad])
    return lam, U


def quadratic_form_cdf(m: NDArray, S: NDArray, center: NDArray, x: NDArray,
                       state: Optional[dict] = None, second_order: str = 'upper'
                       ) -> Tuple[NDArray, NDArray, NDArray]:
    """P(|x - center|^2 <= x) for x ~ N(m, S), saddle-point approximation, with gradients.

    Parameters
    ----------
    m : ndarray, shape (n, k)
        Means.
    S : ndarray, shape (n, k, k)
        Covariances (symmetric positive semi-definite; eigenvalues are floored at 1e-12 of the
        row's scale so that a degenerate direction is treated as nearly deterministic).
    center : ndarray, shape (n, k) or (k,)
    x : ndarray, shape (n,) or scalar
        Thresholds (squared radii), > 0.
    state : dict, optional
        Warm start carried between calls on the same rows (an optimiser evaluating nearby
        moments): the saddle points of the previous call start the root search of this one
        (key ``'s'``), which cuts the Newton iterations from about 8 to 2-3. The result does
        not depend on it (each root is solved to 1e-13 in log K').
    second_order : {'upper', 'both', 'none'}
        Where Daniels' second-order term is added to the Lugannani-Rice formula: above the mean
        of Q only (default: the upper tail, where it is more accurate on both sides), on both
        sides (most accurate on average, but it underestimates lower tails of needle-shaped
        covariances by up to 14 %), or nowhere (the first-order formula). See the module
        docstring for the measured errors.

    Returns
    -------
    P : ndarray, shape (n,)
    dP_dm : ndarray, shape (n, k)
    dP_dS : ndarray, shape (n, k, k)
        Symmetric gradient (for symmetric perturbations of S).
    """
    if second_order not in ('upper', 'both', 'none'):
        raise ValidationError("second_order: expected 'upper', 'both' or 'none', got "
                              f'{second_order!r}')
    m = np.asarray(m, float)
    S = np.asarray(S, float)
    n, k = m.shape
    x = np.broadcast_to(np.asarray(x, float), (n,))
    center = np.broadcast_to(np.asarray(center, float), (n, k))
    s0 = None if state is None else state.get('s')
    if s0 is not None and s0.shape != (n,):
        s0 = None
    act = None
    if k <= 3:
        # Rows whose ball lies beyond the half-space u.(y - m) >= dist - r, u = (c - m) / dist,
        # more than _FAR_DIR standard deviations of u.x away (P <= Phi(-7.5) < 4e-14), or that
        # contain the _FAR sqrt(tr S) neighbourhood of the mean (1 - P <= P(chi2_3 > _FAR^2)
        # < 1e-17): P is 0 or 1 with zero gradient. Most steps of a path constraint are such.
        d = m - center
        dist2 = _rowsum(d * d)
        dist = np.sqrt(dist2)
        r = np.sqrt(x)
        var_u = _rowsum(d * np.matmul(S, d[:, :, None])[:, :, 0])
        gap = dist - r
        far = (gap > 0.0) & (gap * gap * dist2 > _FAR_DIR * _FAR_DIR * var_u)
        spread = _FAR * np.sqrt(np.maximum(np.trace(S, axis1=1, axis2=2), 0.0))
        inside = dist + spread < r
        skip = far | inside
        if np.any(skip):
            act = ~skip
    if act is None:
        P, dP_dm, dP_dS, s = _saddle_cdf(m, S, center, x, s0, second_order)
    else:
        P = inside.astype(float)
        dP_dm = np.zeros((n, k))
        dP_dS = np.zeros((n, k, k))
        s = np.zeros(n) if s0 is None else s0.copy()
        if np.any(act):
            P[act], dP_dm[act], dP_dS[act], s[act] = _saddle_cdf(
                m[act], S[act], center[act], x[act], None if s0 is None else s0[act],
                second_order)
    if state is not None:
        state['s'] = s
    return P, dP_dm, dP_dS


def _saddle_cdf(m, S, center, x, s0, second_order='upper'):
    """quadratic_form_cdf on rows that need it; also returns the saddle points."""
    n, k = m.shape
    d = m - center
    lam, U = _eigh(S)
    scale = np.trace(S, axis1=1, axis2=2) + _rowsum(d * d) + x
    lam = np.maximum(lam, 1e-12 * scale[:, None])
    delta = np.matmul(d[:, None, :], U)[:, 0, :]
    d2 = delta * delta
    s = saddle_point(lam, d2, x, s0)
    order2 = second_order != 'none'
    b, K = _cgf(s, lam, d2, 5 if order2 else 3)
    w2 = np.maximum(_w2(s, lam, d2, b), 0.0)
    w = np.sign(s) * np.sqrt(w2)
    K2 = K[2]
    sqK2 = np.sqrt(K2)
    u = s * sqK2
    l3 = K[3] / (K2 * sqK2)
    center_rows = np.abs(w) < _W_CENTER
    with np.errstate(divide='ignore', invalid='ignore'):
        pw = normal_pdf(w)
        iw = 1.0 / w
        iu = 1.0 / u
        P = normal_cdf(w) + pw * (iw - iu)
        # dP/dw and dP/du (then dP/dlambda3, dP/dlambda4 of the second-order term)
        P_w = pw * (w * iu - iw * iw)
        P_u = pw * iu * iu
        # dP = sum_j A_j dK^(j) at fixed s (envelope theorem for w; ds = -dK' / K'')
        A0 = -P_w * iw
        D_s = P_u * (sqK2 + 0.5 * s * K[3] / sqK2)
        A2 = 0.5 * P_u * s / sqK2
        if order2 and (second_order == 'both' or np.any(w > _W2_LO)):
            # T2 = -phi(w) C, C = (l4/8 - 5 l3^2/24)/u - l3/(2 u^2) - 1/u^3 + 1/w^3, weighted by
            # the smoothstep h(|w|) ('both') or h(w) ('upper': 0 below the mean); see _W2_LO
            l4 = K[4] / (K2 * K2)
            l5 = K[5] / (K2 * K2 * sqK2)
            wa = np.abs(w) if second_order == 'both' else w
            a = np.minimum(np.maximum((wa - _W2_LO) * (1.0 / (_W2_HI - _W2_LO)), 0.0), 1.0)
            h = a * a * (3.0 - 2.0 * a)
            dh = (6.0 / (_W2_HI - _W2_LO)) * a * (1.0 - a)
            if second_order == 'both':
                dh = dh * np.sign(w)
            if not np.all(a > 0.0):
                iw = np.where(a > 0.0, iw, 0.0)
                iu = np.where(a > 0.0, iu, 0.0)
            iu2 = iu * iu
            iu3 = iu2 * iu
            iw3 = iw * iw * iw
            c4 = l4 / 8.0 - (5.0 / 24.0) * l3 * l3
            C = c4 * iu - 0.5 * l3 * iu2 - iu3 + iw3
            hp = h * pw
            T2 = -pw * C
            P = P + h * T2
            P_w2 = dh * T2 + hp * (w * C + 3.0 * iw3 * iw)
            P_u2 = hp * (c4 * iu2 - l3 * iu3 - 3.0 * iu3 * iu)
            P_3 = hp * ((5.0 / 12.0) * l3 * iu + 0.5 * iu2)
            P_4 = (-1.0 / 8.0) * hp * iu
            A0 = A0 - P_w2 * np.where(a > 0.0, 1.0 / w, 0.0)
            D_s = D_s + P_u2 * (sqK2 + 0.5 * s * K[3] / sqK2) \
                + sqK2 * (P_3 * (l4 - 1.5 * l3 * l3) + P_4 * (l5 - 2.0 * l3 * l4))
            A2 = A2 + 0.5 * P_u2 * s / sqK2 - (1.5 * P_3 * l3 + 2.0 * P_4 * l4) / K2
            A = (A0, -D_s / K2, A2, P_3 / (K2 * sqK2), P_4 / (K2 * K2))
        else:
            A = (A0, -D_s / K2, A2, 0.0 * A2, 0.0 * A2)
    if np.any(center_rows):
        A = [np.where(center_rows, 0.0, a_j) for a_j in A]
    A = [a_j[:, None] for a_j in A]
    # Every K^(j) = tr F_j(S) + d^T F_j'(S) d with F_j' = beta_j S^(j-1) B^(j+1) (F_0' = s B),
    # B = (I - 2 s S)^-1, so with f = A_0 s B + sum_j A_j beta_j S^(j-1) B^(j+1):
    # dP/dd = 2 f(S) d, and dP/dS = f(S) + the Frechet derivative of d^T f(S) d, in the
    # eigenbasis diag(f(lam)) + (delta delta^T) o f[lam_p, lam_q] (divided differences).
    # With y = lam b: f = A_0 s b + b^2 poly(y), poly(y) = sum_j c_j y^(j-1), c_j = A_j beta_j;
    # b[p, q] = 2 s b_p b_q and y[p, q] = b_p b_q give f[p, q] = b_p b_q T_pq,
    #   T_pq = 2 A_0 s^2 + 2 s (b_p + b_q) poly(y_q) + b_p^2 (c_2 + c_3 (y_p + y_q)
    #          + c_4 (y_p^2 + y_p y_q + y_q^2)),
    # sums of products (no cancellation for close or repeated eigenvalues). dP/dS is
    # symmetrised, so a term g h^T may be written h g^T: T ~ (P1 + 2 s b poly) 1^T
    # + 2 s b poly^T + P2 y^T + P3 (y^2)^T, P1 = 2 A_0 s^2 + b^2 (c_2 + c_3 y + c_4 y^2),
    # P2 = b^2 (c_3 + c_4 y), P3 = c_4 b^2, and U G U^T = sym(Vp Vq^T) with the columns
    # Vp = [U (e o (P1 + 2 s b poly)), U (e o 2 s b), U (e o P2), U (e o P3), U diag(f)],
    # Vq = [U e, U (e o poly), U (e o y), U (e o y^2), U], e = delta o b.
    sc = s[:, None]
    c1, c2, c3, c4 = (A[j] * _BETA[j] for j in range(1, 5))
    y = lam * b
    c34 = c3 + y * c4
    poly = c1 + y * (c2 + y * c34)
    b2 = b * b
    f = A[0] * sc * b + b2 * poly
    e = delta * b
    e2sb = e * (2.0 * sc * b)
    ep = e * poly
    ey = e * y
    V = np.matmul(U, np.stack((e * (2.0 * A[0] * sc * sc + b2 * (c2 + y * c34)) + e2sb * poly,
                               e2sb, e * (b2 * c34), e * (c4 * b2), e, ep, ey, ey * y,
                               2.0 * f * delta), axis=2))                  # (n, k, 9)
    Vp = np.concatenate([V[:, :, :4], U * f[:, None, :]], axis=2)
    Vq = np.concatenate([V[:, :, 4:8], U], axis=2)
    Y = np.matmul(Vp, np.swapaxes(Vq, 1, 2))
    dP_dS = 0.5 * (Y + np.swapaxes(Y, 1, 2))
    dP_dm = V[:, :, 8]
    if np.any(center_rows):
        P, dP_dm, dP_dS = _center_edgeworth(m, S, center, x, center_rows, P, dP_dm, dP_dS)
    return np.clip(P, 0.0, 1.0), dP_dm, dP_dS, s


def _center_edgeworth(m, S, center, x, rows, P, dP_dm, dP_dS):
    """One-term Edgeworth expansion P ~ Phi(z) - phi(z) lambda3 / 6 (z^2 - 1) on the given
    rows (z = (x - E) / sqrt(V), lambda3 = kappa3 / V^1.5 the skewness of Q): at the mean of
    Q it equals the limit of the Lugannani-Rice formula, so P stays continuous (to
    O(_W_CENTER)) where that formula is 0/0.

    kappa3 = 8 tr(S^3) + 24 d^T S^2 d, d = m - center.
    """
    from cdmp_ros.core.promp.gaussian import quadratic_moments
    m, S = m[rows], S[rows]
    c = np.broadcast_to(center, P.shape + (m.shape[1],))[rows]
    E, V, dE_dm, dE_dS, dV_dm, dV_dS = quadratic_moments(m, S, c)
    d = m - c
    S2 = np.matmul(S, S)
    Sd = np.matmul(S, d[:, :, None])[:, :, 0]
    S2d = np.matmul(S, Sd[:, :, None])[:, :, 0]
    k3 = 8.0 * np.trace(np.matmul(S2, S), axis1=1, axis2=2) + 24.0 * np.sum(d * S2d, axis=1)
    dk3_dm = 48.0 * S2d
    dk3_dS = 24.0 * (S2 + d[:, :, None] * Sd[:, None, :] + Sd[:, :, None] * d[:, None, :])
    sd = np.sqrt(V)
    z = (x[rows] - E) / sd
    l3 = k3 / (V * sd)
    pz = normal_pdf(z)
    Pc = normal_cdf(z) - pz * l3 / 6.0 * (z * z - 1.0)
    P_z = pz * (1.0 - l3 / 6.0 * (3.0 * z - z ** 3))
    P_l3 = -pz * (z * z - 1.0) / 6.0
    a_E = -P_z / sd
    a_V = -P_z * z / (2.0 * V) - P_l3 * 1.5 * l3 / V
    a_3 = P_l3 / (V * sd)
    P = P.copy()
    dP_dm = dP_dm.copy()
    dP_dS = dP_dS.copy()
    P[rows] = Pc
    dP_dm[rows] = a_E[:, None] * dE_dm + a_V[:, None] * dV_dm + a_3[:, None] * dk3_dm
    G = (a_E[:, None, None] * dE_dS + a_V[:, None, None] * dV_dS
         + a_3[:, None, None] * dk3_dS)
    dP_dS[rows] = 0.5 * (G + np.swapaxes(G, 1, 2))
    return P, dP_dm, dP_dS
