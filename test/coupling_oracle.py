"""The numpy reference of the obstacle coupling (paper 000, Eq. 7, 11 and 12): the oracle that
the tests compare the generated kernels of cdmp_ros/core/coupling/kernel.py with.

Batched over leading axes, by SVD (``np.linalg.svd``), independent of the closed-form
eigenvalues and damped inverses of the kernels. The formulas (selectively damped
pseudo-inverse, limit-aware weighted Eq. 12) are in the docstring of
:mod:`cdmp_ros.core.coupling.kernel`.
"""
from typing import Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.coupling.obstacle import DampingConfig
from cdmp_ros.core.errors import ValidationError


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
