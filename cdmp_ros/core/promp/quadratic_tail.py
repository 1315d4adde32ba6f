"""Accurate tail probabilities of the quadratic form Q = |x - c|^2 for Gaussian x.

For x ~ N(m, S) in k dimensions, Q follows a generalised chi-square law: with S = U diag(lam) U^T
and delta = U^T (m - c), Q = sum_i lam_i (z_i + delta_i / sqrt(lam_i))^2, z ~ N(0, I). Paper 003
replaces this law by a Gamma distribution with the same mean and variance (its Eq. 15 moment
match, :func:`cdmp_ros.core.promp.gaussian.gamma_cdf`); that law's tail is lighter than the true
one
exactly where a confidence alpha = 0.999 lives, so constraints met "with probability alpha" under
the Gamma match are violated 1.4-2.5 times more often than asked (see ../shared/design.md,
Numerics notes).

This module evaluates P(Q <= x) by the Lugannani-Rice saddle-point approximation, whose relative
error in the 1e-4 ... 1e-2 tails is a few per cent (checked against Monte Carlo sampling and an
exact cubature of the Gaussian over the ball in test/test_core_quadratic_tail.py: at most 7 %
over 72 tails where the Gamma match errs by up to 600 %), with analytic gradients with respect to
the mean and the covariance.

Cumulant generating function of Q, with b_i = 1 / (1 - 2 s lam_i), for s < 1 / (2 max lam):

    K(s)   = sum_i [ -1/2 log(1 - 2 s lam_i) + s delta_i^2 b_i ]
    K'(s)  = sum_i [ lam_i b_i + delta_i^2 b_i^2 ]
    K''(s) = sum_i [ 2 lam_i^2 b_i^2 + 4 lam_i delta_i^2 b_i^3 ]

The saddle point s_hat solves K'(s_hat) = x; then w = sign(s_hat) sqrt(2 (s_hat x - K(s_hat))),
u = s_hat sqrt(K''(s_hat)) and

    P(Q <= x) ~= Phi(w) + phi(w) (1/w - 1/u)            (Lugannani and Rice, 1980)

Gradients: with theta any entry of (m, S), the envelope theorem gives dw/dtheta =
-(dK/dtheta) / w, and d s_hat / dtheta = -(dK'/dtheta) / K''(s_hat); the partial derivatives of
K, K' and K'' at fixed s are closed-form matrix functions of S (written here in the eigenbasis of
S, where they need no divided differences, so repeated eigenvalues are harmless).
"""
from typing import Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.promp.gaussian import normal_cdf, normal_pdf

# Below this |w| the saddle point is at the mean of Q and Lugannani-Rice is 0/0: the normal
# approximation with the exact mean and variance of Q is used there (P ~ 0.5, far from any
# confidence level a constraint asks for).
_W_CENTER = 1e-4
_MAX_ITER = 200


def _cgf(s, lam, d2):
    """K, K', K'', K''' at s (rows), and b = 1 / (1 - 2 s lam)."""
    b = 1.0 / (1.0 - 2.0 * s[:, None] * lam)
    lb = lam * b
    d2b = d2 * b
    K = np.sum(-0.5 * np.log1p(-2.0 * s[:, None] * lam) + s[:, None] * d2b, axis=1)
    K1 = np.sum(lb + d2b * b, axis=1)
    K2 = np.sum(2.0 * lb * lb + 4.0 * lb * d2b * b, axis=1)
    K3 = np.sum(8.0 * lb * lb * lb + 24.0 * lb * lb * d2b * b, axis=1)
    return b, K, K1, K2, K3


def _k1(s, lam, d2):
    b = 1.0 / (1.0 - 2.0 * s[:, None] * lam)
    return np.sum(lam * b + d2 * b * b, axis=1), np.sum(
        2.0 * (lam * b) ** 2 + 4.0 * lam * d2 * b ** 3, axis=1)


def saddle_point(lam: NDArray, d2: NDArray, x: NDArray) -> NDArray:
    """Solve K'(s) = x for every row (safeguarded Newton on log K', bisection fallback).

    Parameters
    ----------
    lam : ndarray, shape (n, k)
        Eigenvalues of S, all > 0.
    d2 : ndarray, shape (n, k)
        Squared mean offsets in the eigenbasis, delta_i^2.
    x : ndarray, shape (n,)
        Thresholds, > 0.

    Returns
    -------
    s_hat : ndarray, shape (n,)
    """
    n, k = lam.shape
    lam_max = np.max(lam, axis=1)
    E = np.sum(lam + d2, axis=1)
    upper = x > E
    # bracket: (0, pole) above the mean; below it, K'(s) <= k / (2|s|) + sum d2/lam^2 / (4 s^2)
    pole = 0.5 / lam_max
    lo = np.where(upper, 0.0,
                  -(k / x + np.sqrt(np.sum(d2 / (lam * lam), axis=1) / x)))
    hi = np.where(upper, pole, 0.0)
    s = np.where(upper, 0.5 * pole, 0.0)
    log_x = np.log(x)
    for _ in range(_MAX_ITER):
        K1, K2 = _k1(s, lam, d2)
        f = np.log(K1) - log_x
        if np.all(np.abs(f) < 1e-13):
            break
        lo = np.where(f < 0.0, s, lo)
        hi = np.where(f > 0.0, s, hi)
        step = s - f * K1 / K2
        inside = (step > lo) & (step < hi)
        s = np.where(inside, step, 0.5 * (lo + hi))
    return s


def quadratic_form_cdf(m: NDArray, S: NDArray, center: NDArray, x: NDArray
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

    Returns
    -------
    P : ndarray, shape (n,)
    dP_dm : ndarray, shape (n, k)
    dP_dS : ndarray, shape (n, k, k)
        Symmetric gradient (for symmetric perturbations of S).
    """
    m = np.asarray(m, float)
    S = np.asarray(S, float)
    n, k = m.shape
    x = np.broadcast_to(np.asarray(x, float), (n,))
    d = m - center
    lam, U = np.linalg.eigh(S)
    scale = np.trace(S, axis1=1, axis2=2) + np.sum(d * d, axis=1) + x
    lam = np.maximum(lam, 1e-12 * scale[:, None])
    delta = np.einsum('nij,ni->nj', U, d)
    d2 = delta * delta
    s = saddle_point(lam, d2, x)
    b, K, K1, K2, K3 = _cgf(s, lam, d2)
    w2 = np.maximum(2.0 * (s * x - K), 0.0)
    w = np.sign(s) * np.sqrt(w2)
    sqK2 = np.sqrt(K2)
    u = s * sqK2
    center_rows = np.abs(w) < _W_CENTER
    with np.errstate(divide='ignore', invalid='ignore'):
        pw = normal_pdf(w)
        P = normal_cdf(w) + pw * (1.0 / w - 1.0 / u)
        # dP/dw and dP/du of the Lugannani-Rice formula
        P_w = pw * (w / u - 1.0 / (w * w))
        P_u = pw / (u * u)
        a_K = -P_w / w
        a_1 = -P_u * (sqK2 + s * K3 / (2.0 * sqK2)) / K2
        a_2 = P_u * s / (2.0 * sqK2)
    a_K, a_1, a_2 = (np.where(center_rows, 0.0, a) for a in (a_K, a_1, a_2))
    # eigenbasis gradient: dP/d delta = c * delta, dP/dS_eig = diag(g) + outer-product terms
    lb = lam * b
    sc = s[:, None]
    c = 2.0 * a_K[:, None] * sc * b + 2.0 * a_1[:, None] * b * b + 8.0 * a_2[:, None] * lb * b * b
    g = a_K[:, None] * sc * b + a_1[:, None] * b * b + 4.0 * a_2[:, None] * lb * b * b
    p = b * delta
    q = b * p
    r = b * q
    v = lam * q
    y = lam * r

    def sym_outer(a, bb):
        return a[:, :, None] * bb[:, None, :] + bb[:, :, None] * a[:, None, :]

    G = (2.0 * (s * s * a_K)[:, None, None] * p[:, :, None] * p[:, None, :]
         + (2.0 * s * a_1)[:, None, None] * sym_outer(p, q)
         + (2.0 * a_2)[:, None, None] * sym_outer(p, r)
         + (4.0 * s * a_2)[:, None, None] * (sym_outer(v, q) + sym_outer(y, p)))
    G[:, np.arange(k), np.arange(k)] += g
    dP_dm = np.einsum('nij,nj->ni', U, c * delta)
    dP_dS = np.matmul(np.matmul(U, G), np.swapaxes(U, 1, 2))
    if np.any(center_rows):
        P, dP_dm, dP_dS = _center_normal(m, S, center, x, center_rows, P, dP_dm, dP_dS)
    return np.clip(P, 0.0, 1.0), dP_dm, dP_dS


def _center_normal(m, S, center, x, rows, P, dP_dm, dP_dS):
    """Normal approximation with the exact mean and variance of Q on the given rows."""
    from cdmp_ros.core.promp.gaussian import quadratic_moments
    c = np.broadcast_to(center, m.shape)[rows]
    E, V, dE_dm, dE_dS, dV_dm, dV_dS = quadratic_moments(m[rows], S[rows], c)
    sd = np.sqrt(V)
    z = (x[rows] - E) / sd
    pz = normal_pdf(z)
    dz_dE = -1.0 / sd
    dz_dV = -0.5 * z / V
    P = P.copy()
    P[rows] = normal_cdf(z)
    dP_dm = dP_dm.copy()
    dP_dS = dP_dS.copy()
    dP_dm[rows] = pz[:, None] * (dz_dE[:, None] * dE_dm + dz_dV[:, None] * dV_dm)
    G = pz[:, None, None] * (dz_dE[:, None, None] * dE_dS + dz_dV[:, None, None] * dV_dS)
    dP_dS[rows] = 0.5 * (G + np.swapaxes(G, 1, 2))
    return P, dP_dm, dP_dS
