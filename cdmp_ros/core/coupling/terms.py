"""Obstacle coupling terms of CDMPs in joint space (paper 000, Section II-B and III-B).

End-effector avoidance, Eq. (7)::

    dq_dd_e = J^+ dx_dd_e

Link avoidance through the null space of the end-effector task, Eq. (11) and (12)::

    dq_dd_l = (I - J^+ J) (J_o (I - J^+ J))^+ dx_dd_l = (J_o (I - J^+ J))^+ dx_dd_l

Joint-limit-aware null space (beyond paper 000). Eq. (12) can push a redundant
joint into its limit: the CDMP keeps it strictly inside, but the exogenous map divides the
joint acceleration by ``y_delta (1 - tanh(xi)^2)``, so a null-space push that keeps pointing at
a limit grows as the joint approaches it and holds the joint saturated. The link term is
therefore the weighted least-norm solution (Chan and Dubey, IEEE T-RA 11(2), 1995) in the null
space of the end-effector task, with weights that are 1 away from the limits and infinite near
them::

    u_i = (q_i - q_o,i) / y_delta_i                                  (limit usage, signed)
    rho_i = clip((|u_i| - u_on) / (u_lock - u_on), 0, 1)
    s_i = 1 / w_i = (1 - rho_i)^2 (1 + 2 rho_i),     D = diag(sqrt(s_i)) = W^(-1/2)
    dq_dd_l = D (J_o D (I - (J D)^+ J D))^+ dx_dd_l                  (Eq. 12, weighted)

``dq_dd_l`` is, among the least-squares solutions of ``J_o dq_dd = dx_dd_l`` with
``J dq_dd = 0``, the one of least ``dq_dd^T W dq_dd``: the null-space task still leaves the end
effector alone (``J D z = 0`` implies ``J (D z) = 0``) and is steered away from the joints near
a limit. Where every ``|u_i| <= u_on`` (``CouplingConfig.limit_onset``, 0.9) ``D = I`` and this
is Eq. (12) unchanged. ``s`` is C^1 (``s' = 0`` at both ends of the band) and is 0 from
``u_lock`` (``CouplingConfig.limit_lock``, 0.95) on: the link term does not move a joint there
at all (its column of ``J_o D`` and its entry of ``D`` vanish), so it can no longer hold the
joint against its limit; in the band its contribution is ``O(s_i)``. The weights are the same
for both directions of motion (Chan and Dubey switch them off when the joint moves away from
the limit): the coupling stays a continuous function of ``q``, and the primitive's own motion,
not the null-space task, is what takes a joint away from a limit. Eq. (7) is never weighted.

Damped pseudo-inverse (selective damping of small singular values)::

    M^+ = sum_i sigma_i / (sigma_i^2 + lambda_i^2) v_i u_i^T,
    lambda_i^2 = lambda_max^2 (1 - (sigma_i / epsilon)^2)   if sigma_i < epsilon, else 0

so ``M^+`` is the Moore-Penrose inverse whenever every non-zero singular value is at least
``epsilon`` (exactly zero singular values contribute nothing, as in ``np.linalg.pinv``), and
stays bounded by ``1 / (2 lambda_max)``-ish gains at and near singularities. With
``A = M M^T = U diag(mu) U^T`` this is ``M^+ = M^T h(A)^{-1}`` with ``h(mu) = mu +
lambda^2(mu)``; the single-configuration path evaluates ``h(A)`` in closed form (eigenvalues by
the trigonometric formula, the projector on the damped eigenvalues by Sylvester's formula) on
plain floats. With damping active ``I - J^+ J`` is no longer idempotent, so Eq. (11) and (12)
agree only where the end-effector Jacobian is undamped.

This module holds the numpy reference implementations (batched over leading axes) and the
scalar kernels; :mod:`cdmp_ros.core.coupling.obstacle` assembles them with the kinematics and
the potential fields.
"""
import math
from operator import mul
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.config_fields import param
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import check_positive

Matrix = List[List[float]]


@dataclass(frozen=True)
class DampingConfig:
    """Damping of the pseudo-inverses.

    Attributes
    ----------
    epsilon : float
        Singular value [m/rad for position Jacobians] below which damping starts.
    lambda_max : float
        Damping at an exact singularity (same unit as ``epsilon``).
    """

    epsilon: float = param(
        0.02, 'Singular value [m/rad for position Jacobians] below which the damping of the '
        'pseudo-inverses starts.')
    lambda_max: float = param(
        0.05, 'Damping of the pseudo-inverses at an exact singularity (same unit as '
        'epsilon).')

    def __post_init__(self):
        check_positive('DampingConfig.epsilon', self.epsilon)
        check_positive('DampingConfig.lambda_max', self.lambda_max)


# ----------------------------------------------------------------------------- numpy
def damped_pinv(M: ArrayLike, damping: DampingConfig = DampingConfig()) -> NDArray[np.float64]:
    """Selectively damped pseudo-inverse (module docstring), batched over leading axes.

    Parameters
    ----------
    M : array-like (..., m, n)

    Returns
    -------
    ndarray (..., n, m)
    """
    M = np.asarray(M, dtype=np.float64)
    U, S, Vt = np.linalg.svd(M, full_matrices=False)
    eps, lam = damping.epsilon, damping.lambda_max
    lam2 = np.where(S < eps, lam * lam * (1.0 - (S / eps) ** 2), 0.0)
    den = S * S + lam2
    f = np.where(den > 0, S / np.where(den > 0, den, 1.0), 0.0)
    return np.einsum('...ki,...k,...jk->...ij', Vt, f, U)


def null_space_projector(J: ArrayLike, damping: DampingConfig = DampingConfig()
                         ) -> NDArray[np.float64]:
    """``I - J^+ J`` (..., n, n) with the damped pseudo-inverse."""
    J = np.asarray(J, dtype=np.float64)
    return np.eye(J.shape[-1]) - damped_pinv(J, damping) @ J


def end_effector_term(J: ArrayLike, dx_dd_e: ArrayLike,
                      damping: DampingConfig = DampingConfig()) -> NDArray[np.float64]:
    """Eq. (7), paper 000: ``dq_dd_e = J^+ dx_dd_e``; J (..., m, n), dx_dd_e (..., m)."""
    return np.einsum('...ij,...j->...i', damped_pinv(J, damping),
                     np.asarray(dx_dd_e, dtype=np.float64))


def limit_scale(Q: ArrayLike, lower: ArrayLike, upper: ArrayLike, onset: float,
                lock: float) -> NDArray[np.float64]:
    """Inverse weights ``s = 1 / w`` of the limit-aware null space (module docstring).

    Parameters
    ----------
    Q : array-like (..., n)
        Joint positions.
    lower, upper : array-like (n,)
        Joint limits; joints with a non-finite limit always get ``s = 1``.
    onset, lock : float
        Limit usages ``u_on < u_lock`` where the weighting starts and where ``s`` reaches 0.

    Returns
    -------
    ndarray (..., n)
        ``s_i = (1 - rho_i)^2 (1 + 2 rho_i)`` in [0, 1].
    """
    Q = np.asarray(Q, dtype=np.float64)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    finite = np.isfinite(lo) & np.isfinite(hi)
    lo, hi = np.where(finite, lo, -1.0), np.where(finite, hi, 1.0)
    centre = np.where(finite, 0.5 * (lo + hi), 0.0)
    delta = np.where(finite, 0.5 * (hi - lo), np.inf)
    rho = np.clip((np.abs(Q - centre) / delta - onset) / (lock - onset), 0.0, 1.0)
    return (1.0 - rho) ** 2 * (1.0 + 2.0 * rho)


def link_term(J: ArrayLike, J_o: ArrayLike, dx_dd_l: ArrayLike,
              damping: DampingConfig = DampingConfig(), form: int = 12,
              scale: Optional[ArrayLike] = None) -> NDArray[np.float64]:
    """Link avoidance in the null space of the end-effector task.

    Parameters
    ----------
    J : array-like (..., m, n)
        End-effector Jacobian.
    J_o : array-like (..., m_o, n)
        Jacobian of the link's closest point.
    dx_dd_l : array-like (..., m_o)
        Cartesian acceleration of that point from the potential field.
    form : {11, 12}
        Eq. (11), ``(I - J^+ J) (J_o (I - J^+ J))^+ dx``, or its simplification Eq. (12),
        ``(J_o (I - J^+ J))^+ dx``.
    scale : array-like (..., n), optional
        Inverse joint weights ``s`` (:func:`limit_scale`): the weighted form
        ``D (J_o D (I - (J D)^+ J D))^+ dx`` with ``D = diag(sqrt(s))`` (module docstring).
    """
    if scale is not None:
        D = np.sqrt(np.asarray(scale, dtype=np.float64))[..., None, :]
        return D[..., 0, :] * link_term(np.asarray(J, dtype=np.float64) * D,
                                        np.asarray(J_o, dtype=np.float64) * D, dx_dd_l,
                                        damping, form)
    N = null_space_projector(J, damping)
    P = damped_pinv(np.asarray(J_o, dtype=np.float64) @ N, damping)
    if form == 11:
        P = N @ P                                    # Eq. (11), paper 000
    elif form != 12:                                 # Eq. (12), paper 000
        raise ValidationError(f'form: expected 11 or 12, got {form!r}')
    return np.einsum('...ij,...j->...i', P, np.asarray(dx_dd_l, dtype=np.float64))


# ----------------------------------------------------------------------------- scalar
class LimitScale:
    """:func:`limit_scale` on plain floats for one configuration (the tick path).

    ``LimitScale(lower, upper, onset, lock)(q)`` returns None when every joint is within the
    onset
    (``D = I``: Eq. 12 unchanged, checked against precomputed bounds) and the list of ``s_i``
    otherwise.
    """

    __slots__ = ('onset', '_bounds', '_centre', '_inv_delta', '_inv_width')

    @property
    def bounds(self) -> List[Tuple[float, float]]:
        """Per joint ``(q_o - u_on y_delta, q_o + u_on y_delta)``: ``s = 1`` within (``-inf,
        inf`` for a joint without finite limits)."""
        return list(self._bounds)

    def __init__(self, lower: Sequence[float], upper: Sequence[float], onset: float,
                 lock: float):
        self.onset = float(onset)
        self._bounds, self._centre, self._inv_delta = [], [], []
        for lo, hi in zip(lower, upper):
            lo, hi = float(lo), float(hi)
            if math.isfinite(lo) and math.isfinite(hi):
                c, d = 0.5 * (lo + hi), 0.5 * (hi - lo)
                self._bounds.append((c - self.onset * d, c + self.onset * d))
                self._centre.append(c)
                self._inv_delta.append(1.0 / d)
            else:
                self._bounds.append((-math.inf, math.inf))
                self._centre.append(0.0)
                self._inv_delta.append(0.0)
        self._inv_width = 1.0 / (float(lock) - self.onset)

    def __call__(self, q: Sequence[float]) -> Optional[List[float]]:
        for x, (lo, hi) in zip(q, self._bounds):
            if x < lo or x > hi:
                break
        else:
            return None
        onset, inv_width = self.onset, self._inv_width
        out = []
        for x, c, inv_d in zip(q, self._centre, self._inv_delta):
            rho = (abs(x - c) * inv_d - onset) * inv_width
            if rho <= 0.0:
                out.append(1.0)
            elif rho >= 1.0:
                out.append(0.0)
            else:
                r = 1.0 - rho
                out.append(r * r * (1.0 + 2.0 * rho))
        return out


def _scaled_links(J: Matrix, links: Sequence[tuple], scale: Sequence[float]):
    """``(J D, [(J_o D, dx)], sqrt(s))`` of the weighted Eq. (12) (module docstring); the
    rows of a ``J_o`` may be truncated to its first columns."""
    d = [math.sqrt(x) for x in scale]
    Jd = [[a * b for a, b in zip(row, d)] for row in J] if J is not None else None
    return Jd, [([[a * b for a, b in zip(row, d)] for row in J_o], dx) for J_o, dx in links], d


def _sym_eigenvalues(A: Matrix) -> List[float]:
    """Eigenvalues (ascending) of a symmetric 1x1, 2x2 or 3x3 matrix, closed form."""
    m = len(A)
    if m == 1:
        return [A[0][0]]
    if m == 2:
        a, b, d = A[0][0], A[0][1], A[1][1]
        h = 0.5 * (a + d)
        r = math.hypot(0.5 * (a - d), b)
        return [h - r, h + r]
    return list(_eigenvalues3(A[0][0], A[0][1], A[0][2], A[1][1], A[1][2], A[2][2]))


def _eigenvalues3(a00: float, a01: float, a02: float, a11: float, a12: float,
                  a22: float) -> tuple:
    """Ascending eigenvalues of a symmetric 3x3 matrix (trigonometric formula)."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    if p2 <= 1e-300:
        return q, q, q
    p = math.sqrt(p2 / 6.0)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
           + a02 * (a01 * a12 - b11 * a02))
    r = max(-1.0, min(1.0, det / (2.0 * p * p * p)))
    phi = math.acos(r) / 3.0
    hi = q + 2.0 * p * math.cos(phi)
    lo = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    return lo, 3.0 * q - lo - hi, hi


_TWO_PI_3 = 2.0 * math.pi / 3.0


def _matmul(A: Matrix, B: Matrix) -> Matrix:
    Bt = list(zip(*B))
    return [[sum(a * b for a, b in zip(row, col)) for col in Bt] for row in A]


def _solve_spd(H: Matrix, v: Sequence[float]) -> List[float]:
    """``H^{-1} v`` for a symmetric positive definite 1x1, 2x2 or 3x3 ``H`` (Cramer)."""
    m = len(H)
    if m == 1:
        return [v[0] / H[0][0]]
    if m == 2:
        a, b, d = H[0][0], H[0][1], H[1][1]
        det = a * d - b * b
        return [(d * v[0] - b * v[1]) / det, (a * v[1] - b * v[0]) / det]
    (a, b, c), (_, d, e), (_, _, f) = H
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    det = a * c00 + b * c01 + c * c02
    x, y, z = v
    return [(c00 * x + c01 * y + c02 * z) / det, (c01 * x + c11 * y + c12 * z) / det,
            (c02 * x + c12 * y + c22 * z) / det]


def _damped_gram(M: Matrix, eps2: float, lam2: float) -> Matrix:
    """``h(M M^T)`` (module docstring): ``A + lam2 * (P_s - A P_s / eps2)`` with ``P_s`` the
    projector on the eigenvalues of ``A = M M^T`` below ``eps2``."""
    m = len(M)
    A = [[sum(a * b for a, b in zip(M[i], M[j])) for j in range(m)] for i in range(m)]
    return _h_of(A, _sym_eigenvalues(A), eps2, lam2)


def _h_of(A: Matrix, mu: List[float], eps2: float, lam2: float) -> Matrix:
    """``h(A)`` given the ascending eigenvalues ``mu`` of the symmetric ``A``."""
    m = len(A)
    small = [x < eps2 for x in mu]
    if not any(small):
        return A
    eye = [[float(i == j) for j in range(m)] for i in range(m)]
    if all(small):
        Ps = eye
    else:
        # m <= 3 and mixed: one group is a single eigenvalue g. Sylvester's formula gives its
        # projector prod_{j != g} (A - mu_j I) / (mu_g - mu_j), valid for repeated mu_j.
        g = 0 if sum(small) == 1 else m - 1
        Pg = eye
        for j in range(m):
            if j != g:
                F = [[(A[r][c] - (mu[j] if r == c else 0.0)) / (mu[g] - mu[j])
                      for c in range(m)] for r in range(m)]
                Pg = _matmul(Pg, F)
        Ps = Pg if small[g] else [[e - p for e, p in zip(r1, r2)] for r1, r2 in zip(eye, Pg)]
    APs = _matmul(A, Ps)
    return [[A[r][c] + lam2 * (Ps[r][c] - APs[r][c] / eps2) for c in range(m)]
            for r in range(m)]


def damped_pinv_apply(M: Matrix, v: Sequence[float], damping: DampingConfig) -> List[float]:
    """``M^+ v`` on plain floats for M with 1 to 3 rows (list of rows), v (m,)."""
    H = _damped_gram(M, damping.epsilon ** 2, damping.lambda_max ** 2)
    w = _solve_spd(H, v)
    n = len(M[0])
    out = [0.0] * n
    for wi, row in zip(w, M):
        for k in range(n):
            out[k] += wi * row[k]
    return out


def _inverse_h3(a00: float, a01: float, a02: float, a11: float, a12: float, a22: float,
                eps2: float, lam2: float) -> tuple:
    """``(h(A)^{-1}, damped)``: the inverse as a row-major 9-tuple for a symmetric positive
    semi-definite 3x3 ``A``, and whether any eigenvalue was damped.

    Undamped (plain inverse) when the cheap bound ``mu_min >= 4 det(A) / tr(A)^2`` already
    clears ``eps2``; otherwise ``h(A)`` in closed form (as :func:`_h_of`, unrolled)."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    tr = a00 + a11 + a22
    damped = False
    if not (det > 0.0 and 4.0 * det >= eps2 * tr * tr):
        # _eigenvalues3, inlined (the same operations)
        q = tr / 3.0
        b00, b11, b22 = a00 - q, a11 - q, a22 - q
        p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
        if p2 <= 1e-300:
            mu0 = mu1 = mu2 = q
        else:
            p = math.sqrt(p2 / 6.0)
            r = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
                 + a02 * (a01 * a12 - b11 * a02)) / (2.0 * p * p * p)
            phi = math.acos(-1.0 if r < -1.0 else (1.0 if r > 1.0 else r)) / 3.0
            mu2 = q + 2.0 * p * math.cos(phi)
            mu0 = q + 2.0 * p * math.cos(phi + _TWO_PI_3)
            mu1 = 3.0 * q - mu0 - mu2
        if mu0 < eps2:
            damped = True
            # h(A) = x A + y I + z P with P the projector of the isolated eigenvalue
            # (Sylvester: P = (A - a I)(A - b I) / ((mu_g - a)(mu_g - b)) = (A^2 - (a + b) A
            # + a b I) / den), see _h_of
            if mu2 < eps2:                                   # all damped
                x, y, z = 1.0 - lam2 / eps2, lam2, 0.0
                ea = eb = den = 1.0
            elif mu1 < eps2:                                 # mu0, mu1 damped; P of mu2
                x, y, z = 1.0 - lam2 / eps2, lam2, lam2 * (mu2 / eps2 - 1.0)
                ea, eb, den = mu0, mu1, (mu2 - mu0) * (mu2 - mu1)
            else:                                            # mu0 damped; P of mu0
                x, y, z = 1.0, 0.0, lam2 * (1.0 - mu0 / eps2)
                ea, eb, den = mu1, mu2, (mu0 - mu1) * (mu0 - mu2)
            if z:
                z /= den
                ab, sab = ea * eb, ea + eb
                p00 = a00 * a00 + a01 * a01 + a02 * a02 - sab * a00 + ab
                p11 = a01 * a01 + a11 * a11 + a12 * a12 - sab * a11 + ab
                p22 = a02 * a02 + a12 * a12 + a22 * a22 - sab * a22 + ab
                p01 = a00 * a01 + a01 * a11 + a02 * a12 - sab * a01
                p02 = a00 * a02 + a01 * a12 + a02 * a22 - sab * a02
                p12 = a01 * a02 + a11 * a12 + a12 * a22 - sab * a12
            else:
                p00 = p11 = p22 = p01 = p02 = p12 = 0.0
            a00, a11, a22 = x * a00 + y + z * p00, x * a11 + y + z * p11, x * a22 + y + z * p22
            a01, a02, a12 = x * a01 + z * p01, x * a02 + z * p02, x * a12 + z * p12
            c00 = a11 * a22 - a12 * a12
            c01 = a02 * a12 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            det = a00 * c00 + a01 * c01 + a02 * c02
    inv = 1.0 / det
    c00 *= inv
    c01 *= inv
    c02 *= inv
    c11 = (a00 * a22 - a02 * a02) * inv
    c12 = (a01 * a02 - a00 * a12) * inv
    c22 = (a00 * a11 - a01 * a01) * inv
    return (c00, c01, c02, c01, c11, c12, c02, c12, c22), damped


def coupling_3d(J: Matrix, dx_dd_e: Sequence[float], links: Sequence[tuple],
                damping: DampingConfig, scale: Optional[Sequence[float]] = None
                ) -> List[float]:
    """:func:`scalar_coupling` unrolled for 3 task rows (the usual Cartesian case).

    With ``H = h(J J^T)``, ``K = J J_o^T``, ``W = H^{-1} K``: ``J_o (I - J^+ J) = J_o - W^T J``,
    its Gram matrix is ``J_o J_o^T - K^T W - W^T K + W^T (J J^T) W`` and
    ``(J_o N)^+ dx = J_o^T w - J^T (W w)`` with ``w = h(Gram)^{-1} dx``; all joint-space
    vectors are accumulated as one combination of the rows of J and of the J_o. The rows of a
    J_o may be truncated to the joints that move the point (the others are zero). ``scale``
    (the ``s_i`` of :class:`LimitScale`, or None for all ones) gives the limit-aware Eq. (12)
    (module docstring).
    """
    if scale is not None and links:
        Jd, links_d, d = _scaled_links(J, links, scale)
        dq = coupling_3d(J, dx_dd_e, (), damping)                    # Eq. (7)
        dq_l = coupling_3d(Jd, None, links_d, damping)               # Eq. (12), weighted
        return [a + di * b for a, di, b in zip(dq, d, dq_l)]
    eps2 = damping.epsilon * damping.epsilon
    lam2 = damping.lambda_max * damping.lambda_max
    j0, j1, j2 = J
    a00, a01, a02 = sum(map(mul, j0, j0)), sum(map(mul, j0, j1)), sum(map(mul, j0, j2))
    a11, a12, a22 = sum(map(mul, j1, j1)), sum(map(mul, j1, j2)), sum(map(mul, j2, j2))
    (h00, h01, h02, _, h11, h12, _, _, h22), ee_damped = _inverse_h3(
        a00, a01, a02, a11, a12, a22, eps2, lam2)
    if dx_dd_e is not None:                                   # Eq. (7), paper 000
        e0, e1, e2 = dx_dd_e
        c0 = h00 * e0 + h01 * e1 + h02 * e2
        c1 = h01 * e0 + h11 * e1 + h12 * e2
        c2 = h02 * e0 + h12 * e1 + h22 * e2
    else:
        c0 = c1 = c2 = 0.0
    link_us = []
    for J_o, dx in links:                                     # Eq. (12), paper 000
        o0, o1, o2 = J_o
        k00, k01, k02 = sum(map(mul, j0, o0)), sum(map(mul, j0, o1)), sum(map(mul, j0, o2))
        k10, k11, k12 = sum(map(mul, j1, o0)), sum(map(mul, j1, o1)), sum(map(mul, j1, o2))
        k20, k21, k22 = sum(map(mul, j2, o0)), sum(map(mul, j2, o1)), sum(map(mul, j2, o2))
        # W = H^{-1} K
        w00 = h00 * k00 + h01 * k10 + h02 * k20
        w01 = h00 * k01 + h01 * k11 + h02 * k21
        w02 = h00 * k02 + h01 * k12 + h02 * k22
        w10 = h01 * k00 + h11 * k10 + h12 * k20
        w11 = h01 * k01 + h11 * k11 + h12 * k21
        w12 = h01 * k02 + h11 * k12 + h12 * k22
        w20 = h02 * k00 + h12 * k10 + h22 * k20
        w21 = h02 * k01 + h12 * k11 + h22 * k21
        w22 = h02 * k02 + h12 * k12 + h22 * k22
        # Gram of M = J_o - W^T J: G - K^T W - W^T K + W^T A W, entry (r, s), with
        # (K^T W)_rs = sum_i k_ir w_is. Undamped (H = A^-1): W^T A W = K^T W.
        q00 = k00 * w00 + k10 * w10 + k20 * w20
        q01 = k00 * w01 + k10 * w11 + k20 * w21
        q02 = k00 * w02 + k10 * w12 + k20 * w22
        q11 = k01 * w01 + k11 * w11 + k21 * w21
        q12 = k01 * w02 + k11 * w12 + k21 * w22
        q22 = k02 * w02 + k12 * w12 + k22 * w22
        s00 = sum(map(mul, o0, o0)) - q00
        s01 = sum(map(mul, o0, o1)) - q01
        s02 = sum(map(mul, o0, o2)) - q02
        s11 = sum(map(mul, o1, o1)) - q11
        s12 = sum(map(mul, o1, o2)) - q12
        s22 = sum(map(mul, o2, o2)) - q22
        if ee_damped:
            v00 = a00 * w00 + a01 * w10 + a02 * w20
            v01 = a00 * w01 + a01 * w11 + a02 * w21
            v02 = a00 * w02 + a01 * w12 + a02 * w22
            v10 = a01 * w00 + a11 * w10 + a12 * w20
            v11 = a01 * w01 + a11 * w11 + a12 * w21
            v12 = a01 * w02 + a11 * w12 + a12 * w22
            v20 = a02 * w00 + a12 * w10 + a22 * w20
            v21 = a02 * w01 + a12 * w11 + a22 * w21
            v22 = a02 * w02 + a12 * w12 + a22 * w22
            # - K^T W - W^T K + W^T V  =  -q - q^T + W^T V, and s already holds -q
            s00 += w00 * v00 + w10 * v10 + w20 * v20 - q00
            s11 += w01 * v01 + w11 * v11 + w21 * v21 - q11
            s22 += w02 * v02 + w12 * v12 + w22 * v22 - q22
            s01 += (w00 * v01 + w10 * v11 + w20 * v21
                    - (w00 * k01 + w10 * k11 + w20 * k21))
            s02 += (w00 * v02 + w10 * v12 + w20 * v22
                    - (w00 * k02 + w10 * k12 + w20 * k22))
            s12 += (w01 * v02 + w11 * v12 + w21 * v22
                    - (w01 * k02 + w11 * k12 + w21 * k22))
        (g00, g01, g02, _, g11, g12, _, _, g22), _ = _inverse_h3(
            s00, s01, s02, s11, s12, s22, eps2, lam2)
        d0, d1, d2 = dx
        u0 = g00 * d0 + g01 * d1 + g02 * d2
        u1 = g01 * d0 + g11 * d1 + g12 * d2
        u2 = g02 * d0 + g12 * d1 + g22 * d2
        # M^T u = J_o^T u - J^T (W u)
        c0 -= w00 * u0 + w01 * u1 + w02 * u2
        c1 -= w10 * u0 + w11 * u1 + w12 * u2
        c2 -= w20 * u0 + w21 * u1 + w22 * u2
        link_us.append((o0, o1, o2, u0, u1, u2))
    dq = [c0 * x + c1 * y + c2 * z for x, y, z in zip(j0, j1, j2)]
    for o0, o1, o2, u0, u1, u2 in link_us:
        k = len(o0)
        dq[:k] = [d + u0 * x + u1 * y + u2 * z for d, x, y, z in zip(dq, o0, o1, o2)]
    return dq


def scalar_coupling(J: Matrix, dx_dd_e: Sequence[float], links: Sequence[tuple],
                    damping: DampingConfig, scale: Optional[Sequence[float]] = None
                    ) -> List[float]:
    """Total joint acceleration coupling ``J^+ dx_e + sum_l (J_o,l (I - J^+ J))^+ dx_l``.

    Parameters
    ----------
    J : list of m rows of n floats
        End-effector Jacobian (m = 1..3 task rows); ``None`` for no end-effector task (the
        link terms then use the full joint space, ``I - J^+ J = I``).
    dx_dd_e : sequence of m floats or None
        End-effector acceleration (Eq. 7); None or all zero to skip.
    links : sequence of (J_o, dx_dd_l)
        Link-point Jacobians (rows) and accelerations (Eq. 12).
    damping : DampingConfig
    scale : sequence of n floats, optional
        ``s_i`` of :class:`LimitScale`: the limit-aware Eq. (12) (module docstring).
    """
    if scale is not None and links:
        Jd, links_d, d = _scaled_links(J, links, scale)
        dq = scalar_coupling(J, dx_dd_e, (), damping) if J is not None else [0.0] * len(d)
        dq_l = scalar_coupling(Jd, None, links_d, damping)
        return [a + di * b for a, di, b in zip(dq, d, dq_l)]
    n = len(J[0]) if J is not None else len(links[0][0][0])
    out = [0.0] * n
    if J is not None:
        H = _damped_gram(J, damping.epsilon ** 2, damping.lambda_max ** 2)
        m = len(J)
        if dx_dd_e is not None and any(dx_dd_e):     # Eq. (7), paper 000
            w = _solve_spd(H, dx_dd_e)
            for wi, row in zip(w, J):
                for k in range(n):
                    out[k] += wi * row[k]
    for J_o, dx in links:
        if not any(dx):
            continue
        if J is not None:
            # J_o (I - J^+ J) = J_o - ((J_o J^T) H^{-1}) J, with J^+ = J^T H^{-1}
            K = [[sum(a * b for a, b in zip(ro, rj)) for rj in J] for ro in J_o]
            L = [_solve_spd(H, k) for k in K]        # rows of K H^{-1} (H symmetric)
            Mo = [[ro[c] - sum(L[r][i] * J[i][c] for i in range(m)) for c in range(n)]
                  for r, ro in enumerate(J_o)]
        else:
            Mo = J_o
        dq = damped_pinv_apply(Mo, dx, damping)      # Eq. (12), paper 000
        for k in range(n):
            out[k] += dq[k]
    return out
