"""Gaussian helpers of the constrained ProMP (paper 003): CDFs with gradients, the Gamma
approximation, batched Cholesky back-propagation and the unscented transform.

Every function works on batches (leading axes) and returns analytic gradients; the only
numerical derivative is the scalar d/d(shape) of the regularised incomplete gamma function,
which scipy does not provide (allowed by the design's numerics notes).
"""
from typing import Tuple

import numpy as np
from numpy.typing import NDArray
from scipy import special

_SQRT_2PI = np.sqrt(2.0 * np.pi)


def normal_pdf(x: NDArray) -> NDArray:
    """Standard normal density."""
    return np.exp(-0.5 * x * x) / _SQRT_2PI


def normal_cdf(x: NDArray) -> NDArray:
    """Standard normal CDF Phi (Eq. 13, paper 003)."""
    return special.ndtr(x)


def gamma_cdf(E: NDArray, V: NDArray, x: NDArray
              ) -> Tuple[NDArray, NDArray, NDArray]:
    """CDF at ``x`` of the Gamma distribution with mean ``E`` and variance ``V``.

    Shape k = E^2 / V and rate beta = E / V (moment matching, Section II-D2, paper 003).

    Parameters
    ----------
    E, V, x : ndarray, broadcastable
        Mean (> 0), variance (> 0) and threshold (>= 0).

    Returns
    -------
    P : ndarray
        P(c <= x) for c ~ Gamma(k, beta).
    dP_dE, dP_dV : ndarray
        Gradients of ``P`` w.r.t. ``E`` and ``V``.
    """
    E = np.maximum(E, 1e-300)
    V = np.maximum(V, 1e-300)
    k = E * E / V
    beta = E / V
    u = beta * x
    P = special.gammainc(k, u)
    # dP/du = u^(k-1) exp(-u) / Gamma(k)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        log_dens = (k - 1.0) * np.log(np.maximum(u, 1e-300)) - u - special.gammaln(k)
        dP_du = np.where(u > 0, np.exp(log_dens), 0.0)
    # dP/dk: the one scalar derivative without a closed form in scipy (central difference),
    # only where P is not 0 or 1 to working precision (elsewhere |dP/dk| < 1e-30 * O(1))
    h = 1e-5 * (1.0 + k)
    live = (P > 1e-30) & (P < 1.0 - 1e-16)
    if np.all(live):
        dP_dk = (special.gammainc(k + h, u) - special.gammainc(k - h, u)) / (2.0 * h)
    else:
        dP_dk = np.zeros(np.broadcast(k, u).shape)
        if np.any(live):
            kl, ul, hl = (np.broadcast_to(a, live.shape)[live] for a in (k, u, h))
            dP_dk[live] = (special.gammainc(kl + hl, ul)
                           - special.gammainc(kl - hl, ul)) / (2.0 * hl)
    dk_dE = 2.0 * E / V
    dk_dV = -k / V
    du_dE = x / V
    du_dV = -u / V
    dP_dE = dP_dk * dk_dE + dP_du * du_dE
    dP_dV = dP_dk * dk_dV + dP_du * du_dV
    return P, dP_dE, dP_dV


def quadratic_moments(m: NDArray, S: NDArray, center: NDArray
                      ) -> Tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Mean and variance of c = |x - center|^2 for x ~ N(m, S), with gradients.

    E[c] = |d|^2 + tr(S),  V[c] = 4 d^T S d + 2 tr(S S),  d = m - center.

    Parameters
    ----------
    m : ndarray, shape (n, k)
    S : ndarray, shape (n, k, k)
    center : ndarray, shape (n, k) or (k,)

    Returns
    -------
    E, V : ndarray, shape (n,)
    dE_dm : (n, k); dE_dS : (n, k, k); dV_dm : (n, k); dV_dS : (n, k, k)
    """
    d = m - center
    Sd = np.matmul(S, d[:, :, None])[:, :, 0]
    E = np.sum(d * d, axis=1) + np.trace(S, axis1=1, axis2=2)
    ST = np.swapaxes(S, 1, 2)
    V = 4.0 * np.sum(d * Sd, axis=1) + 2.0 * np.sum(S * ST, axis=(1, 2))
    dE_dm = 2.0 * d
    dE_dS = np.broadcast_to(np.eye(m.shape[1]), S.shape)
    dV_dm = 8.0 * Sd
    dV_dS = 4.0 * (d[:, :, None] * d[:, None, :] + ST)
    return E, V, dE_dm, dE_dS, dV_dm, dV_dS


def batched_cholesky(S: NDArray, jitter: float = 1e-12) -> NDArray:
    """Lower Cholesky factors of a batch (..., k, k) of symmetric PSD matrices."""
    k = S.shape[-1]
    scale = np.maximum(np.trace(S, axis1=-2, axis2=-1) / k, 1e-300)
    return np.linalg.cholesky(S + (jitter * scale)[..., None, None] * np.eye(k))


def inv_lower(A: NDArray) -> NDArray:
    """Inverses of a batch (..., k, k) of lower-triangular matrices by forward substitution,
    vectorised over the batch (for small k much cheaper than the general batched inverse)."""
    k = A.shape[-1]
    X = np.zeros_like(A)
    dinv = 1.0 / np.diagonal(A, axis1=-2, axis2=-1)
    for i in range(k):
        # row i: X[i, :] = (e_i - A[i, :i] X[:i, :]) / A[i, i]
        if i:
            r = -np.matmul(A[..., i:i + 1, :i], X[..., :i, :])[..., 0, :]
        else:
            r = np.zeros(A.shape[:-2] + (k,))
        r[..., i] += 1.0
        X[..., i, :] = r * dinv[..., i, None]
    return X


_MASKS = {}


def _masks(k: int):
    m = _MASKS.get(k)
    if m is None:
        low = np.tril(np.ones((k, k)))
        m = _MASKS[k] = (low, low - 0.5 * np.eye(k))
    return m


def cholesky_backward(A: NDArray, A_bar: NDArray) -> NDArray:
    """Back-propagate a gradient through A = chol(S) (Murray 2016), batched.

    Parameters
    ----------
    A : ndarray, shape (..., k, k)
        Lower Cholesky factor.
    A_bar : ndarray, shape (..., k, k)
        dF/dA (only the lower triangle is used).

    Returns
    -------
    S_bar : ndarray, shape (..., k, k)
        Symmetric gradient dF/dS (treating S's entries as independent).
    """
    low, phi = _masks(A.shape[-1])
    P = np.swapaxes(A, -1, -2) @ (A_bar * low)
    P *= phi                               # lower triangle, half diagonal
    inv = inv_lower(A)
    X = np.swapaxes(inv, -1, -2) @ P @ inv
    return 0.5 * (X + np.swapaxes(X, -1, -2))


class UnscentedTransform:
    """Sigma points z_m = m +- alpha sqrt(k) A e_i, weights 1 / (2 alpha^2 k) and
    W_0 = 1 - 1 / alpha^2 for the centre (Section II-E, paper 003); the centre is omitted when
    W_0 = 0 (alpha = 1).

    Parameters
    ----------
    k : int
        Dimension of the random variable.
    alpha : float
        Spread of the sigma points (alpha = 1: no centre point, all weights positive).
    """

    def __init__(self, k: int, alpha: float = 1.0):
        self.k = int(k)
        self.alpha = float(alpha)
        self.scale = self.alpha * np.sqrt(self.k)
        w = 1.0 / (2.0 * self.alpha ** 2 * self.k)
        w0 = 1.0 - 1.0 / self.alpha ** 2
        # the centre point is dropped when its weight is zero (alpha = 1): it changes neither
        # moment, and the kinematics are then evaluated at 2k instead of 2k + 1 points
        self.n_centre = 0 if w0 == 0.0 else 1
        self.weights = np.concatenate([[w0] * self.n_centre, np.full(2 * self.k, w)])
        # signs (n_centre + 2k, k): [centre,] plus rows, minus rows
        self.offsets = np.concatenate([np.zeros((self.n_centre, self.k)), np.eye(self.k),
                                       -np.eye(self.k)])

    def points(self, m: NDArray, S: NDArray) -> Tuple[NDArray, NDArray]:
        """Sigma points Z (n, n_centre + 2k, k) of N(m, S), and the Cholesky factors
        A (n, k, k)."""
        A = batched_cholesky(S)
        sAT = self.scale * np.swapaxes(A, 1, 2)          # row j = scale * A e_j
        mm = m[:, None, :]
        parts = [mm, mm + sAT, mm - sAT] if self.n_centre else [mm + sAT, mm - sAT]
        Z = np.concatenate(parts, axis=1)
        return Z, A

    def moments(self, X: NDArray) -> Tuple[NDArray, NDArray]:
        """Weighted mean (n, q) and covariance (n, q, q) of transformed points X (n, p, q)."""
        mx = np.matmul(self.weights, X)
        D = X - mx[:, None, :]
        Sx = np.matmul(np.swapaxes(D * self.weights[None, :, None], 1, 2), D)
        return mx, Sx

    def backward(self, X: NDArray, mx: NDArray, J: NDArray, A: NDArray,
                 g_mx: NDArray, g_Sx: NDArray) -> Tuple[NDArray, NDArray]:
        """Gradients w.r.t. the input mean and covariance.

        Parameters
        ----------
        X : (n, p, q) transformed sigma points; mx : (n, q) their mean;
        J : (n, p, q, k) Jacobians dX/dZ at the sigma points; A : (n, k, k) Cholesky factors;
        g_mx : (n, q); g_Sx : (n, q, q) gradients w.r.t. the output moments.

        Returns
        -------
        g_m : (n, k); g_S : (n, k, k)
        """
        D = X - mx[:, None, :]
        g_Ss = g_Sx + np.swapaxes(g_Sx, 1, 2)
        # the term through mx vanishes because sum_p W_p (X_p - mx) = 0
        g_X = self.weights[None, :, None] * (g_mx[:, None, :] + np.matmul(D, g_Ss))
        g_Z = np.matmul(g_X[:, :, None, :], J)[:, :, 0, :]
        g_m = g_Z.sum(axis=1)
        # Z_p = m +- scale * A e_j  ->  dA[:, i, j] = scale * (g_Z[+j, i] - g_Z[-j, i])
        k, c = self.k, self.n_centre
        g_A = self.scale * np.swapaxes(g_Z[:, c:c + k, :] - g_Z[:, c + k:, :], 1, 2)
        g_S = cholesky_backward(A, g_A)
        return g_m, g_S
