"""Position inverse kinematics by damped least squares within joint limits.

Used to turn a Cartesian goal (``goal_point``) into a joint goal, and by experiments.
"""
from dataclasses import dataclass
from typing import Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.validation import as_array


@dataclass
class IkResult:
    q: NDArray[np.float64]     # (n_dofs,) solution inside [lower + margin, upper - margin]
    error: float               # remaining position error [m]
    iterations: int
    converged: bool


def solve_position_ik(chain, point, target: ArrayLike, q0: ArrayLike,
                      lower: Optional[ArrayLike] = None, upper: Optional[ArrayLike] = None,
                      tol: float = 1e-4, max_iter: int = 200, damping: float = 1e-2,
                      margin: float = 1e-3, q_rest: Optional[ArrayLike] = None,
                      rest_gain: float = 0.0) -> IkResult:
    """Move ``point`` (a PointOfInterest of ``chain``) to ``target`` (3,) from ``q0``.

    Damped least squares ``dq = J^T (J J^T + damping^2 I)^-1 e``, clipped into the limits
    (shrunk by ``margin``) after every step; with ``rest_gain > 0`` the null space pulls
    towards ``q_rest``.
    """
    target = as_array('target', target, (3,))
    q = as_array('q0', q0, (chain.n_dofs,)).copy()
    lo = (chain.lower if lower is None else as_array('lower', lower, (chain.n_dofs,))) + margin
    hi = (chain.upper if upper is None else as_array('upper', upper, (chain.n_dofs,))) - margin
    rest = q.copy() if q_rest is None else as_array('q_rest', q_rest, (chain.n_dofs,))
    q = np.clip(q, lo, hi)
    err = np.inf
    for it in range(1, max_iter + 1):
        X, J = chain.forward_and_jacobian(q, [point])
        e = target - X[0]
        err = float(np.linalg.norm(e))
        if err < tol:
            return IkResult(q, err, it, True)
        J = J[0]
        A = J @ J.T + damping ** 2 * np.eye(3)
        dq = J.T @ np.linalg.solve(A, e)
        if rest_gain > 0:
            N = np.eye(chain.n_dofs) - J.T @ np.linalg.solve(A, J)
            dq += rest_gain * N @ (rest - q)
        q = np.clip(q + dq, lo, hi)
    return IkResult(q, err, max_iter, False)
