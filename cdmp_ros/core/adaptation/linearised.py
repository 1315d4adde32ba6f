"""A fast first answer of the adaptation: the KL projection of the prior onto the constraints
linearised at the mean (issue 13, latency).

Paper 003 solves min KL(p || p0) subject to P(constraint holds at t) >= alpha by L-BFGS on a
Lagrangian whose every evaluation pushes sigma points through the kinematics; a Panda problem
with three spheres takes 30-170 evaluations. This module answers the same problem in a few
milliseconds when every constraint is a joint limit, a repeller or a wall, and serves as the
start of the full solve (:func:`cdmp_ros.core.adaptation.solver.solve_levels` with
``start``).

**The linearised problem.** Each constraint at each time step is a clearance that must stay
positive: ``g = q_j - a`` or ``b - q_j`` (joint limits, Eq. 12), ``|x - c| - r`` (repellers,
Eq. 18), ``-n^T (x - b) / |n|`` (walls, Eq. 16). Linearised at the current mean trajectory,
``g ~ g(mean) + h^T (w - mu)`` with ``h = (dg/dq)^T Psi_t`` (the Jacobian of the point and the
basis), so under p = N(mu, Sigma) it is Gaussian with mean ``h^T mu - beta`` and variance
``h^T Sigma h``, and the chance constraint becomes ``h^T mu - z sqrt(h^T Sigma h) >= beta``
with ``z = Phi^-1(alpha) + z_margin`` (the margin absorbs the linearisation error; the sampled
verification judges the result).

**Its solution.** A Gaussian p whose constraints touch only the k rows ``H w`` is best chosen
as the prior conditioned on them: p(w) = N(Hw; m, V) p0(w | Hw), whose KL to the prior is the
k-dimensional ``KL(N(m, V) || N(H mu0, A))``, A = H Sigma0 H^T (the chain rule of the KL), and
whose mean and covariance are ``mu = mu0 + K (m - H mu0)``, ``Sigma = Sigma0 - K (A - V) K^T``,
K = Sigma0 H^T A^-1. The k-dimensional problem min KL s.t. m_i - z_i sqrt(V_ii) >= beta_i is
solved at its optimality conditions (:func:`project_marginals`): for a given V the mean is the
exact projection m = a0 + A nu, nu >= 0 (non-negative least squares), and stationarity in V
gives V^-1 = A^-1 + diag(z_i nu_i / sqrt(V_ii)); the two alternate to a fixed point. With one
row it is the closed form of :func:`one_dimensional_ratio`.

**Passes.** The rows are the worst violated time step of every constraint (and side), added
pass by pass: each pass re-linearises every constraint at the new mean, stops when no time
step is violated under the linearisation, else adds the worst violated step of each constraint
and solves again over all rows so far.
"""
from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import nnls
from scipy.special import ndtri

from cdmp_ros.core.adaptation.constraints.hyperplane import Hyperplane
from cdmp_ros.core.adaptation.constraints.limits import JointLimit
from cdmp_ros.core.adaptation.constraints.points import ChainPoint, DofPoint
from cdmp_ros.core.adaptation.constraints.spheres import Repeller
from cdmp_ros.core.promp.gaussian import normal_pdf
from cdmp_ros.core.promp.promp import ProMP

__all__ = ['LinearisedResult', 'linearised_projection', 'one_dimensional_ratio',
           'project_marginals', 'supported']

#: Rows of the linearised problem at most (a pass adds at most one per constraint side).
MAX_ROWS = 200


@dataclass
class LinearisedResult:
    """Outcome of :func:`linearised_projection`.

    Attributes
    ----------
    promp : ProMP
        The projected distribution (the prior if nothing was violated).
    converged : bool
        No time step of any constraint is violated under the linearisation at ``promp``'s
        mean (with the margin z, within the tolerance).
    passes : int
        Linearisations done.
    rows : int
        Rows of the final k-dimensional problem.
    worst_margin : float
        The smallest linearised margin ``(mean - beta) / sd - z`` over all time steps at the
        last linearisation (>= -tolerance when converged).
    multipliers : ndarray (n_values,)
        The optimiser's multipliers implied by the projection's (``solve_levels`` with
        ``start``), one per time step of each constraint as :class:`Problem` orders them:
        ``max(lambda0, nu sd / phi(Phi^-1(alpha)))`` on the rows used (the chain rule from the
        clearance's mean, whose multiplier is nu, to its probability F ~ Phi((g - beta) / sd),
        dF/dg = phi / sd), ``lambda0`` elsewhere.
    """
    promp: ProMP
    converged: bool
    passes: int
    rows: int
    worst_margin: float
    multipliers: NDArray[np.float64]


def supported(constraints: Sequence) -> bool:
    """Whether :func:`linearised_projection` handles every constraint: joint limits, and
    repellers and walls on chain points or plain joints, on the full time grid or a part."""
    for c in constraints:
        if type(c) is JointLimit:
            continue
        if type(c) not in (Repeller, Hyperplane):
            return False
        if callable(getattr(c, 'center', None)):
            return False
        if type(c.point) is not ChainPoint and type(c.point) is not DofPoint:
            return False
    return True


def one_dimensional_ratio(delta: NDArray, z: NDArray) -> NDArray:
    """s'/s of the KL projection of N(m, s^2) onto {m' - z s' >= beta}, delta = (beta - m)/s.

    The constraint is active at the optimum (if it is violated), m' = beta + z s', and
    d/ds' [-log s' + (s'^2 + (m' - m)^2) / (2 s^2)] = 0 gives
    (1 + z^2) r^2 + z delta r - 1 = 0 for r = s'/s."""
    delta = np.asarray(delta, float)
    z = np.asarray(z, float)
    return (-z * delta + np.sqrt(z * z * delta * delta + 4.0 * (1.0 + z * z))) / \
        (2.0 * (1.0 + z * z))


def project_marginals(A: NDArray, a0: NDArray, beta: NDArray, z: NDArray,
                      iterations: int = 40) -> Optional[Tuple[NDArray, NDArray, NDArray]]:
    """The k-dimensional problem of the module docstring: (m, V, nu) with
    ``m_i - z_i sqrt(V_ii) >= beta_i``; None if A is not positive definite.

    Fixed point of the optimality conditions: for a given V the mean is the exact projection
    m = a0 + A nu, nu >= 0 (non-negative least squares); for given multipliers nu,
    stationarity in V gives V^-1 = A^-1 + diag(z_i nu_i / sqrt(V_ii)). The two alternate
    (the precision half-way to its new value each time) from V = A."""
    try:
        Ai = np.linalg.inv(A)
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return None
    Ai = 0.5 * (Ai + Ai.T)
    V = A
    c = np.zeros(a0.size)
    for _ in range(iterations):
        s = np.sqrt(np.diag(V))
        d = beta + z * s - a0
        # min 1/2 (m - a0)^T A^-1 (m - a0) s.t. m >= a0 + d: m = a0 + A nu, nu >= 0
        # minimising 1/2 nu^T A nu - nu^T d = 1/2 |L^T nu - L^-1 d|^2 + const
        nu, _ = nnls(L.T, np.linalg.solve(L, d), maxiter=50 * a0.size)
        c_new = 0.5 * (c + z * nu / s)
        if np.allclose(c_new, c, rtol=1e-5, atol=1e-10 / np.mean(s) ** 2):
            c = c_new
            break
        c = c_new
        V = np.linalg.inv(Ai + np.diag(c))
        V = 0.5 * (V + V.T)
    s = np.sqrt(np.diag(V))
    d = beta + z * s - a0
    nu, _ = nnls(L.T, np.linalg.solve(L, d), maxiter=50 * a0.size)
    return a0 + A @ nu, V, nu


class _Rows:
    """The clearances of the constraints on the time grid, linearised at a mean trajectory.

    The rows (constraint, side, step) keep their order from pass to pass: first the joint
    limits, which are linear in w (built once), then the repellers and walls."""

    def __init__(self, prior: ProMP, constraints: Sequence, grid: NDArray, z_margin: float):
        self.phi = prior.basis.features(grid)                 # (n, M)
        self.D, self.M = prior.n_dims, prior.n_basis
        self.constraints = list(constraints)
        lim_H, lim_beta, zs, keys, lim_joint, lim_step = [], [], [], [], [], []
        self.nonlinear = []   # (constraint index, steps)
        self.steps = {}       # constraint index -> its time steps (indices into the grid)
        for i, c in enumerate(constraints):
            steps = np.nonzero(np.isin(grid, c.times(grid)))[0]
            self.steps[i] = steps
            z = float(ndtri(c.alpha)) + z_margin
            if type(c) is not JointLimit:
                self.nonlinear.append((i, steps))
                continue
            for side, sign, bound in zip(('lower', 'upper'), (1.0, -1.0),
                                         c.bounds(grid[steps])):
                bound = np.broadcast_to(np.asarray(bound, float), steps.shape)
                if not np.all(np.isfinite(bound)):
                    continue
                H = np.zeros((steps.size, self.D, self.M))
                H[:, c.joint] = sign * self.phi[steps]
                lim_H.append(H.reshape(steps.size, -1))
                lim_beta.append(sign * bound)                 # sign (q_j - bound) >= 0
                lim_joint.append(np.full(steps.size, c.joint))
                lim_step.append(steps)
                zs.append(np.full(steps.size, z))
                keys += [(i, side, int(t)) for t in steps]
        self.n_linear = len(keys)
        self.lim_joint = np.concatenate(lim_joint) if lim_joint else np.zeros(0, int)
        self.lim_step = np.concatenate(lim_step) if lim_step else np.zeros(0, int)
        for i, steps in self.nonlinear:
            zs.append(np.full(steps.size, float(ndtri(constraints[i].alpha)) + z_margin))
            keys += [(i, 'clear', int(t)) for t in steps]
        dm = self.D * self.M
        self.H_linear = np.concatenate(lim_H) if lim_H else np.zeros((0, dm))
        self.beta_linear = np.concatenate(lim_beta) if lim_beta else np.zeros(0)
        self.z = np.concatenate(zs) if zs else np.zeros(0)
        self.keys = keys
        self.index = {key: r for r, key in enumerate(keys)}
        chains: Dict[int, list] = {}
        for i, _ in self.nonlinear:
            p = constraints[i].point
            if type(p) is ChainPoint:
                pts = chains.setdefault(id(p.chain), [p.chain, []])[1]
                if all(o is not p for o in pts):
                    pts.append(p)
        self.chains = list(chains.values())

    def linearise(self, mu: NDArray) -> Tuple[NDArray, NDArray]:
        """Rows at the mean of weights ``mu``: H (N, D M) and beta (N,) with clearance
        ~ H w - beta (the rows of ``keys``, with ``z``)."""
        D, M = self.D, self.M
        q = self.phi @ mu.reshape(D, M).T                      # (n, D)
        fk = {}
        for chain, pts in self.chains:
            dofs = list(pts[0].dofs)
            X, J = chain.forward_and_jacobian(q[:, dofs], [p.point for p in pts])
            for k, p in enumerate(pts):
                fk[id(p)] = (X[:, k], J[:, k], dofs)
        Hs, betas = [self.H_linear], [self.beta_linear]
        for i, steps in self.nonlinear:
            g, dg = self._clearance(self.constraints[i], q, steps, fk)   # (s,), (s, D)
            H = (dg[:, :, None] * self.phi[steps, None, :]).reshape(steps.size, D * M)
            Hs.append(H)
            betas.append(H @ mu - g)
        return np.concatenate(Hs), np.concatenate(betas)

    def margins(self, H: NDArray, beta: NDArray, mu: NDArray, S: NDArray) -> NDArray:
        """(H mu - beta) / sd - z per row under N(mu, S), sd = sqrt(h^T S h); the joint-limit
        rows from the joints' marginal variances (h = +-Psi_t e_j)."""
        n = self.n_linear
        var = np.empty(H.shape[0])
        var[n:] = np.sum((H[n:] @ S) * H[n:], axis=1)
        if n:
            D, M = self.D, self.M
            blocks = S.reshape(D, M, D, M)[np.arange(D), :, np.arange(D), :]   # (D, M, M)
            joint_var = np.einsum('tm,jmk,tk->jt', self.phi, blocks, self.phi)
            var[:n] = joint_var[self.lim_joint, self.lim_step]
        return (H @ mu - beta) / np.sqrt(np.maximum(var, 1e-300)) - self.z

    def _clearance(self, c, q, steps, fk):
        """Clearance g (s,) of a repeller or wall at the steps and dg/dq (s, D)."""
        dg = np.zeros((steps.size, self.D))
        p = c.point
        if type(p) is ChainPoint:
            X, J, dofs = fk[id(p)]
            axes = list(p.axes)
            X, J = X[steps][:, axes], J[steps][:, axes]        # (s, k), (s, k, nd)
        else:
            dofs = list(p.dofs)
            X = q[steps][:, dofs]
            J = np.broadcast_to(np.eye(len(dofs)), (steps.size, len(dofs), len(dofs)))
        if type(c) is Repeller:
            v = X - c.center
            d = np.linalg.norm(v, axis=1)
            n = v / np.maximum(d, 1e-12)[:, None]
            g = d - c.radius
        else:  # Hyperplane: n^T (x - b) <= 0
            n = np.broadcast_to(-c.normal / np.linalg.norm(c.normal), X.shape)
            g = (X - c.offset) @ n[0]
        dg[:, dofs] = np.matmul(n[:, None, :], J)[:, 0]
        return g, dg


def linearised_projection(prior: ProMP, constraints: Sequence, grid: NDArray,
                          lambda0: float = 20.0, z_margin: float = 0.3,
                          max_passes: int = 12, tolerance: float = 0.05) -> LinearisedResult:
    """The linearised KL projection of ``prior`` onto ``constraints`` (module docstring).

    Parameters
    ----------
    prior : ProMP
    constraints : sequence
        Joint limits, repellers and walls (:func:`supported`).
    grid : ndarray (n,)
        The time grid of the constraints (the optimiser's).
    lambda0 : float
        The optimiser's initial multiplier (the floor of ``multipliers``).
    z_margin : float
        Added to Phi^-1(alpha) of every constraint.
    max_passes : int
        Linearisations at most.
    tolerance : float
        Converged when every linearised margin is >= -tolerance (in standard deviations;
        the margin already includes ``z_margin``).

    Returns
    -------
    LinearisedResult
    """
    rows = _Rows(prior, constraints, grid, z_margin)
    mu0, S0 = prior.mean_w, prior.cov_w
    mu, S = mu0, S0
    active: Dict[tuple, int] = {}
    nu = sd_rows = None
    result = prior
    worst = np.inf
    passes = 0
    z, keys = rows.z, rows.keys
    for passes in range(1, max_passes + 1):
        H, beta = rows.linearise(mu)
        margin = rows.margins(H, beta, mu, S)
        worst = float(margin.min()) if margin.size else np.inf
        if worst >= -tolerance:
            break
        # the worst violated step of each constraint side joins the rows
        first: Dict[tuple, int] = {}
        for r in np.nonzero(margin < -tolerance)[0]:
            side = keys[r][:2]
            if side not in first or margin[r] < margin[first[side]]:
                first[side] = r
        for r in first.values():
            if keys[r] not in active and len(active) < MAX_ROWS:
                active[keys[r]] = len(active)
        sel = [rows.index[key] for key in active]
        Hs = H[sel]
        A = Hs @ S0 @ Hs.T
        A = 0.5 * (A + A.T) + 1e-10 * np.mean(np.diag(A)) * np.eye(len(sel))
        a0 = Hs @ mu0
        solved = project_marginals(A, a0, beta[sel], z[sel])
        if solved is None:
            break
        m, V, nu = solved
        sd_rows = np.sqrt(np.diag(V))
        K = np.linalg.solve(A, Hs @ S0).T                      # Sigma0 H^T A^-1
        mu = mu0 + K @ (m - a0)
        S = S0 - K @ (A - V) @ K.T
        S = 0.5 * (S + S.T)
        result = prior.copy(mu, S)
    else:
        H, beta = rows.linearise(mu)
        margin = rows.margins(H, beta, mu, S)
        worst = float(margin.min()) if margin.size else np.inf
    lam = _multipliers(rows, grid, active, nu, sd_rows, lambda0)
    return LinearisedResult(result, worst >= -tolerance, passes, len(active), worst, lam)


def _multipliers(rows: _Rows, grid: NDArray, active: Dict[tuple, int], nu, sd, lambda0):
    """The optimiser's multipliers (:class:`LinearisedResult`); a joint limit's two sides
    share its row (its F is two-sided)."""
    offsets, n = [], 0
    for c in rows.constraints:
        offsets.append(n)
        n += c.times(grid).size
    lam = np.full(n, float(lambda0))
    if nu is None:
        return lam
    first = {}
    for i, steps in rows.steps.items():
        first[i] = {int(t): k for k, t in enumerate(steps)}
    for (i, _, t), k in active.items():
        row = offsets[i] + first[i][t]
        phi = float(normal_pdf(np.array(ndtri(rows.constraints[i].alpha))))
        lam[row] = max(lam[row], float(nu[k] * sd[k] / phi))
    return lam
