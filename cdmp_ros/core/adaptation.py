"""Constrained ProMP adaptation (paper 003, Eq. 5-10, 23, Algorithm 1).

min_p KL(p || p0) [+ kappa E_p[R(w)]]  s.t.  F_k,t(p) >= alpha_k,t,
with p = N(mu, L L^T), L = L_tril + diag(exp(gamma)), solved by L-BFGS on the Lagrangian
(inner loop, analytic gradients) and the exponential method of multipliers
lambda <- lambda * exp(eta * (alpha - F)) (outer loop).
"""
import time
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from cdmp_ros.core.constraints.base import Constraint, WeightConstraint
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.gaussian import UnscentedTransform
from cdmp_ros.core.promp import ProMP
from cdmp_ros.core.validation import check_positive


@dataclass(frozen=True)
class AdaptationConfig:
    """Optimiser settings (defaults: the authors' Table II settings, promp_benchmark_protocol).

    Parameters
    ----------
    n_steps : int
        Time grid s = linspace(0, 1, n_steps) on which path constraints are imposed.
    lambda0 : float
        Initial Lagrange multiplier of constraints without their own (Section III).
    eta : float
        EMM multiplier learning rate.
    max_outer : int
        Maximum number of multiplier (outer) updates.
    max_inner : int
        Maximum L-BFGS iterations per inner loop.
    objective_tol : float
        With the paper's absolute EMM step: stop (as infeasible) when the Lagrangian changes by
        less than this between outer iterations.
    feasibility_tol : float
        A constraint counts as satisfied when F >= alpha - feasibility_tol.
    kappa : float
        Weight of the smoothness regulariser kappa * E[R(w)] (Eq. 14-15); 0 disables it.
    smoothness_weights : tuple of float, optional
        Per-dimension weights of R(w) (default all 1).
    kl_blocks : tuple of (start, stop), optional
        Use the sum of the marginal KLs of these weight blocks (mutual avoidance objective
        (ii), Section II-E5) instead of the joint KL.
    ut_alpha : float
        Spread of the unscented transform's sigma points.
    lbfgs_ftol, lbfgs_gtol : float
        L-BFGS-B convergence tolerances of the inner loop.
    lbfgs_maxcor : int
        Number of L-BFGS correction pairs.
    relative_step : bool
        EMM step lambda <- lambda exp(eta C / (1 - alpha)) (clipped to +-max_log_step) instead
        of the paper's lambda exp(eta C), C = alpha - F. With alpha close to 1 the paper's step
        changes lambda by at most a factor exp(1 - alpha) once F is near alpha, so a constraint
        that is almost satisfied stays slightly violated; the relative step is scale free.
    max_log_step : float
        Clip of the relative step's exponent.
    whiten : bool
        Precondition the parameters with the prior's Cholesky factor L0: mu = mu0 + L0 nu,
        L = L0 L~, L~ = L~_tril + diag(exp(gamma~)). L stays lower triangular with
        diag(L) = diag(L0) exp(gamma~), so this is the paper's parameterisation up to a fixed
        linear map; the KL becomes 0.5 (|L~|_F^2 + |nu|^2 - n) - 1^T gamma~, perfectly
        conditioned, which cuts the L-BFGS iterations.
    """
    n_steps: int = 101
    lambda0: float = 20.0
    eta: float = 1.0
    max_outer: int = 10
    max_inner: int = 500
    objective_tol: float = 1e-2
    feasibility_tol: float = 1e-4
    kappa: float = 0.0
    smoothness_weights: Optional[Tuple[float, ...]] = None
    kl_blocks: Optional[Tuple[Tuple[int, int], ...]] = None
    ut_alpha: float = 1.0
    lbfgs_ftol: float = 1e-10
    lbfgs_gtol: float = 1e-6
    lbfgs_maxcor: int = 20
    relative_step: bool = True
    max_log_step: float = 3.0
    whiten: bool = True

    def __post_init__(self):
        if int(self.n_steps) < 2:
            raise ValidationError(f'n_steps: expected an integer >= 2, got {self.n_steps!r}')
        check_positive('lambda0', self.lambda0)
        check_positive('eta', self.eta)
        for name in ('max_outer', 'max_inner'):
            if int(getattr(self, name)) < 1:
                raise ValidationError(f'{name}: expected an integer >= 1, '
                                      f'got {getattr(self, name)!r}')
        check_positive('objective_tol', self.objective_tol, allow_zero=True)
        check_positive('feasibility_tol', self.feasibility_tol, allow_zero=True)
        check_positive('kappa', self.kappa, allow_zero=True)
        check_positive('ut_alpha', self.ut_alpha)


@dataclass
class ConstraintReport:
    name: str
    kind: str
    alpha: float
    probability: float      # the approximation's satisfaction probability (worst time)
    satisfied: bool
    lagrange_max: float


@dataclass
class AdaptationReport:
    """Outcome of :func:`adapt`. ``converged`` is False for infeasible/unconverged problems."""
    converged: bool
    status: str
    kl: float
    kl_per_basis: float
    n_outer: int
    n_inner: int
    n_evaluations: int
    time_s: float
    constraints: List[ConstraintReport] = field(default_factory=list)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d['constraints'] = [dict(c.__dict__) for c in self.constraints]
        return d

    def to_text(self) -> str:
        lines = [f'status: {self.status} (converged: {self.converged})',
                 f'KL(p || p0) = {self.kl:.6g} ({self.kl_per_basis:.4g} per basis function)',
                 f'outer iterations: {self.n_outer}, L-BFGS iterations: {self.n_inner}, '
                 f'evaluations: {self.n_evaluations}, time: {self.time_s * 1e3:.1f} ms']
        for c in self.constraints:
            lines.append(f'  {c.name} [{c.kind}]: P = {c.probability:.6f} '
                         f'(alpha = {c.alpha}) {"ok" if c.satisfied else "VIOLATED"}')
        return '\n'.join(lines)


class _Group:
    """Marginals of z_t at one set of times, shared by the constraints using them."""

    def __init__(self, promp: ProMP, times: NDArray):
        self.times = times
        self.phi = promp.basis.features(times)          # (n, M)
        self.D, self.M = promp.n_dims, promp.n_basis

    def forward(self, mu, L):
        D, M = self.D, self.M
        self.m = self.phi @ mu.reshape(D, M).T          # (n, D)
        Bd = np.matmul(self.phi, L.reshape(D, M, -1))  # (D, n, nw)
        self.B = np.ascontiguousarray(Bd.transpose(1, 0, 2))   # (n, D, nw)
        self.S = np.matmul(self.B, Bd.transpose(1, 2, 0))      # (n, D, D)
        self.g_m = np.zeros_like(self.m)
        self.g_S = np.zeros_like(self.S)

    def backward(self, g_mu, g_L):
        D, M = self.D, self.M
        g_mu += (self.phi.T @ self.g_m).T.ravel()
        g_B = np.matmul(self.g_S + np.swapaxes(self.g_S, 1, 2), self.B)   # (n, D, nw)
        g_L += np.matmul(self.phi.T, g_B.transpose(1, 0, 2)).reshape(D * M, -1)


class _PointMoments:
    """Gaussian moments of one point of interest at the times of one group (shared by every
    constraint on that point), with the backward pass to the group's marginals."""

    def __init__(self, point, group: _Group, n_dims: int, ut_alpha: float):
        self.point = point
        self.group = group
        point.check(n_dims)
        self.dofs = np.asarray(point.dofs)
        self.linear = point.linear
        k = len(self.dofs)
        self.identity = False
        if self.linear:
            X0, J0 = point.forward_and_jacobian(np.zeros(k))
            self.A = np.asarray(J0, float)
            self.x0 = np.asarray(X0, float)
            self.identity = (k == n_dims and np.array_equal(self.dofs, np.arange(n_dims))
                             and np.array_equal(self.A, np.eye(k)) and not np.any(self.x0))
        else:
            self.ut = UnscentedTransform(k, ut_alpha)

    def compute(self):
        g = self.group
        if self.identity:
            self.mx, self.Sx = g.m, g.S
        else:
            m = g.m[:, self.dofs]
            S = g.S[:, self.dofs][:, :, self.dofs]
            if self.linear:
                self.mx, self.Sx = m @ self.A.T + self.x0, self.A @ S @ self.A.T
            else:
                Z, Achol = self.ut.points(m, S)
                X, J = self.point.forward_and_jacobian(Z)
                self.mx, self.Sx = self.ut.moments(X)
                self._cache = (X, J, Achol)
        self.g_mx = np.zeros_like(self.mx)
        self.g_Sx = np.zeros_like(self.Sx)

    def backward(self):
        g = self.group
        g_mx, g_Sx = self.g_mx, self.g_Sx
        if self.identity:
            g.g_m += g_mx
            g.g_S += g_Sx
            return
        if self.linear:
            g_m = g_mx @ self.A
            g_S = self.A.T @ g_Sx @ self.A
        else:
            X, J, Achol = self._cache
            g_m, g_S = self.ut.backward(X, self.mx, J, Achol, g_mx, g_Sx)
        ix = np.ix_(np.arange(g.m.shape[0]), self.dofs)
        g.g_m[ix] += g_m
        g.g_S[:, self.dofs[:, None], self.dofs[None, :]] += g_S


class Problem:
    """The adaptation problem: prior p0, constraints and objective, with the analytic
    Lagrangian and its gradient over theta = (mu, L_tril, gamma) (Eq. 23)."""

    def __init__(self, prior: ProMP, constraints: Sequence, config: AdaptationConfig):
        self.prior = prior
        self.config = config
        n = prior.n_weights
        self.n = n
        self.tril = np.tril_indices(n, -1)
        self.grid = np.linspace(0.0, 1.0, int(config.n_steps))
        self.mu0 = prior.mean_w.copy()
        C0 = prior.cov_w
        L0 = np.linalg.cholesky(C0 + 1e-12 * np.trace(C0) / n * np.eye(n))
        self.L0 = L0
        L0inv = np.linalg.inv(L0)
        self.S0inv = L0inv.T @ L0inv
        self.logdet0 = 2.0 * np.sum(np.log(np.diag(L0)))
        self.blocks = None
        if config.kl_blocks is not None:
            self.blocks = []
            for a, b in config.kl_blocks:
                Cb = C0[a:b, a:b]
                self.blocks.append((a, b, np.linalg.inv(Cb), np.linalg.slogdet(Cb)[1]))
        self.Phi_R = None
        if config.kappa > 0:
            self.Phi_R = prior.smoothness_matrix(joint_weights=config.smoothness_weights)
        groups = {}
        points = {}
        self.bound: List[Optional[_PointMoments]] = []
        self.weight_constraints: List[WeightConstraint] = []
        self.slices = []
        offset = 0
        for c in constraints:
            if isinstance(c, WeightConstraint):
                self.weight_constraints.append(c)
                nv = 1
                self.bound.append(None)
            elif isinstance(c, Constraint):
                times = c.times(self.grid)
                key = times.tobytes()
                if key not in groups:
                    groups[key] = _Group(prior, times)
                pkey = (id(c.point), key)
                if pkey not in points:
                    points[pkey] = _PointMoments(c.point, groups[key], prior.n_dims,
                                                 config.ut_alpha)
                self.bound.append(points[pkey])
                nv = times.size if c.reduce == 'each' else 1
            else:
                raise ValidationError(f'constraints: expected Constraint objects, got '
                                      f'{type(c).__name__}')
            self.slices.append(slice(offset, offset + nv))
            offset += nv
        self.constraints = list(constraints)
        self.groups = list(groups.values())
        self.points = list(points.values())
        self.n_values = offset
        self.alpha = np.concatenate([np.full(s.stop - s.start, c.alpha)
                                     for c, s in zip(self.constraints, self.slices)]) \
            if self.constraints else np.zeros(0)
        self.n_evaluations = 0

    # --------------------------------------------------------------- parameters
    def initial_theta(self) -> NDArray:
        if self.config.whiten:
            return np.zeros(2 * self.n + self.tril[0].size)
        L0 = self.L0
        return np.concatenate([self.mu0, L0[self.tril], np.log(np.diag(L0))])

    def bounds(self):
        """L-BFGS-B box on gamma only: the diagonal of L stays within [e^-25, e^5] times the
        prior's, which keeps exp(gamma) finite during line searches."""
        n, nt = self.n, self.tril[0].size
        lo = np.full(2 * n + nt, -np.inf)
        hi = np.full(2 * n + nt, np.inf)
        base = 0.0 if self.config.whiten else np.log(np.diag(self.L0))
        lo[n + nt:] = base - 25.0
        hi[n + nt:] = base + 5.0
        return list(zip(lo, hi))

    def _factors(self, theta):
        """First block, lower-triangular matrix and gamma of theta (raw or whitened)."""
        n = self.n
        first = theta[:n]
        T = np.zeros((n, n))
        T[self.tril] = theta[n:n + self.tril[0].size]
        gamma = theta[n + self.tril[0].size:]
        T[np.diag_indices(n)] = np.exp(gamma)
        return first, T, gamma

    def unpack(self, theta):
        """(mu, L, gamma) with Sigma = L L^T in the original coordinates."""
        first, T, gamma = self._factors(theta)
        if self.config.whiten:
            return self.mu0 + self.L0 @ first, self.L0 @ T, gamma
        return first, T, gamma

    # --------------------------------------------------------------- objective
    def kl(self, mu, L, grads=False):
        """KL(N(mu, L L^T) || p0) (or the sum of block marginals), with dKL/dmu and dKL/dL."""
        dmu = mu - self.mu0
        if self.blocks is None:
            SL = self.S0inv @ L
            d = np.diag(L)
            kl = 0.5 * (np.sum(L * SL) + dmu @ self.S0inv @ dmu - self.n + self.logdet0) \
                - np.sum(np.log(d))
            if not grads:
                return kl
            return kl, self.S0inv @ dmu, SL - np.diag(1.0 / d)
        kl = 0.0
        g_mu = np.zeros(self.n)
        g_L = np.zeros((self.n, self.n))
        for a, b, Sinv, logdet in self.blocks:
            Lb = L[a:b]
            Sb = Lb @ Lb.T
            cb = np.linalg.cholesky(Sb)
            Sb_inv = np.linalg.inv(Sb)
            db = dmu[a:b]
            kl += 0.5 * (np.sum(Sinv * Sb) + db @ Sinv @ db - (b - a) + logdet
                         - 2.0 * np.sum(np.log(np.diag(cb))))
            g_mu[a:b] += Sinv @ db
            g_L[a:b] += (Sinv - Sb_inv) @ Lb
        if not grads:
            return kl
        return kl, g_mu, g_L

    def constraint_values(self, mu, L, grads=False):
        """F for every multiplier (n_values,), optionally with the backward closure."""
        for g in self.groups:
            g.forward(mu, L)
        for pm in self.points:
            pm.compute()
        F = np.empty(self.n_values)
        parts = []
        Sigma = None
        for c, b, sl in zip(self.constraints, self.bound, self.slices):
            if b is None:
                if Sigma is None:
                    Sigma = L @ L.T
                Fw, dmu, dS = c.probability_w(mu, Sigma)
                F[sl] = Fw
                parts.append((dmu, dS))
                continue
            Ft, dm, dS = c.probability(b.mx, b.Sx, b.group.times)
            if c.reduce == 'max':
                i = int(np.argmax(Ft))
                F[sl] = Ft[i]
                mask = np.zeros(Ft.size)
                mask[i] = 1.0
                parts.append((mask, dm, dS))
            else:
                F[sl] = Ft
                parts.append((None, dm, dS))
        if not grads:
            return F
        return F, parts

    def lagrangian(self, theta, lam):
        """L(theta, lambda) of Eq. (23) and its gradient w.r.t. theta."""
        self.n_evaluations += 1
        first, T, gamma = self._factors(theta)
        whiten = self.config.whiten
        if whiten:
            mu, L = self.mu0 + self.L0 @ first, self.L0 @ T
        else:
            mu, L = first, T
        value = 0.0
        g_mu = np.zeros(self.n)
        g_L = np.zeros((self.n, self.n))
        if not (whiten and self.blocks is None):
            value, g_mu_kl, g_L_kl = self.kl(mu, L, grads=True)
            g_mu += g_mu_kl
            g_L += g_L_kl
        g_Sigma = None
        if self.Phi_R is not None:
            kappa = self.config.kappa
            Pm = self.Phi_R @ mu
            value += kappa * (mu @ Pm + np.sum(self.Phi_R * (L @ L.T)))
            g_mu += 2.0 * kappa * Pm
            g_Sigma = kappa * self.Phi_R
        if self.n_values:
            F, parts = self.constraint_values(mu, L, grads=True)
            value += np.sum(lam * (self.alpha - F))
            for c, b, sl, part in zip(self.constraints, self.bound, self.slices, parts):
                w = -lam[sl]
                if b is None:
                    dmu, dS = part
                    g_mu += w @ dmu
                    gS = np.tensordot(w, dS, axes=1)
                    g_Sigma = gS if g_Sigma is None else g_Sigma + gS
                    continue
                mask, dm, dS = part
                wt = w[0] * mask if mask is not None else w
                b.g_mx += wt[:, None] * dm
                b.g_Sx += wt[:, None, None] * dS
            for pm in self.points:
                pm.backward()
            for g in self.groups:
                g.backward(g_mu, g_L)
        if g_Sigma is not None:
            g_L += (g_Sigma + g_Sigma.T) @ L
        if whiten:
            g_first = self.L0.T @ g_mu
            g_T = self.L0.T @ g_L
            if self.blocks is None:
                # KL in whitened coordinates: 0.5 (|L~|^2 + |nu|^2 - n) - 1^T gamma~
                value += 0.5 * (np.sum(T * T) + first @ first - self.n) - np.sum(gamma)
                g_first += first
                g_T += T - np.diag(1.0 / np.diag(T))
        else:
            g_first, g_T = g_mu, g_L
        g_theta = np.concatenate([g_first, g_T[self.tril], np.diag(g_T) * np.exp(gamma)])
        return value, g_theta


def adapt(prior: ProMP, constraints: Sequence, config: Optional[AdaptationConfig] = None
          ) -> Tuple[ProMP, AdaptationReport]:
    """Adapt ``prior`` to the constraints (Algorithm 1, paper 003).

    Returns
    -------
    adapted : ProMP
    report : AdaptationReport
        ``converged`` is True only if every constraint holds at its confidence (within
        ``feasibility_tol``) under the approximation.
    """
    config = config or AdaptationConfig()
    t_start = time.perf_counter()
    prob = Problem(prior, constraints, config)
    theta = prob.initial_theta()
    lam = np.concatenate([np.full(s.stop - s.start, c.lambda0 or config.lambda0)
                          for c, s in zip(prob.constraints, prob.slices)]) \
        if prob.constraints else np.zeros(0)
    eta = np.concatenate([np.full(s.stop - s.start, c.eta or config.eta)
                          for c, s in zip(prob.constraints, prob.slices)]) \
        if prob.constraints else np.zeros(0)
    bounds = prob.bounds()
    n_inner = 0
    n_outer = 0
    prev = None
    status = 'max_outer_reached'
    feasible = False
    for n_outer in range(1, int(config.max_outer) + 1):
        res = minimize(prob.lagrangian, theta, args=(lam,), jac=True, method='L-BFGS-B',
                       bounds=bounds,
                       options={'maxiter': int(config.max_inner), 'ftol': config.lbfgs_ftol,
                                'gtol': config.lbfgs_gtol, 'maxcor': config.lbfgs_maxcor})
        if np.all(np.isfinite(res.x)):
            theta = res.x
        n_inner += int(res.nit)
        mu, L, _ = prob.unpack(theta)
        F = prob.constraint_values(mu, L) if prob.n_values else np.zeros(0)
        C = prob.alpha - F
        feasible = bool(np.all(C <= config.feasibility_tol))
        value = float(res.fun)
        if feasible:
            status = 'converged'
            break
        if (not config.relative_step and prev is not None
                and abs(value - prev) < config.objective_tol):
            status = 'stalled_infeasible'
            break
        prev = value
        if config.relative_step:
            step = np.clip(eta * C / (1.0 - prob.alpha), -config.max_log_step,
                           config.max_log_step)
        else:
            step = eta * C
        lam = lam * np.exp(step)    # exponential method of multipliers (Algorithm 1)
    mu, L, gamma = prob.unpack(theta)
    Sigma = L @ L.T
    adapted = prior.copy(mu, 0.5 * (Sigma + Sigma.T))
    kl = float(prob.kl(mu, L))
    F = prob.constraint_values(mu, L) if prob.n_values else np.zeros(0)
    reports = []
    for c, sl in zip(prob.constraints, prob.slices):
        p = float(np.min(F[sl]))
        reports.append(ConstraintReport(c.name, c.kind, c.alpha, p,
                                        p >= c.alpha - config.feasibility_tol,
                                        float(np.max(lam[sl]))))
    if not feasible and status == 'max_outer_reached':
        status = 'infeasible_or_unconverged'
    report = AdaptationReport(feasible, status, kl, kl / prior.n_basis, n_outer, n_inner,
                              prob.n_evaluations, time.perf_counter() - t_start, reports)
    return adapted, report


def sample_points(promp: ProMP, c, n_samples: int, rng: np.random.Generator,
                  grid: NDArray, W: Optional[NDArray] = None) -> NDArray:
    """Sampled x_t of constraint ``c`` at its times: (n_samples, n, k)."""
    times = c.times(grid)
    if W is None:
        W = promp.sample_weights(n_samples, rng)
    phi = promp.basis.features(times)
    dofs = list(c.point.dofs)
    W3 = W.reshape(-1, promp.n_dims, promp.n_basis)[:, dofs, :]
    Z = (W3.reshape(-1, promp.n_basis) @ phi.T).reshape(W.shape[0], len(dofs), -1)
    return c.point.forward(np.ascontiguousarray(Z.transpose(0, 2, 1)))


def monte_carlo_satisfaction(promp: ProMP, constraints: Sequence, n_samples: int,
                             rng: np.random.Generator, n_steps: int = 101
                             ) -> Tuple[NDArray, NDArray, float]:
    """Monte-Carlo check of the constraints on trajectories sampled from ``promp``.

    Returns
    -------
    per_time_min : (n_constraints,)
        For each constraint, the worst per-time satisfaction frequency ('each') or the
        frequency of satisfying it somewhere in its support ('max'/weight constraints).
    whole : (n_constraints,)
        Frequency of trajectories satisfying the constraint at every time of its support.
    all_ok : float
        Frequency of trajectories satisfying every constraint (1 - violation rate).
    """
    grid = np.linspace(0.0, 1.0, int(n_steps))
    W = promp.sample_weights(n_samples, rng)
    per_time, whole = [], []
    ok_all = np.ones(n_samples, bool)
    for c in constraints:
        if isinstance(c, WeightConstraint):
            ok = c.satisfied_w(W)
            per_time.append(ok.mean())
        else:
            X = sample_points(promp, c, n_samples, rng, grid, W)
            sat = c.satisfied(X, c.times(grid))
            if sat.ndim == 2:
                per_time.append(sat.mean(axis=0).min())
                ok = sat.all(axis=1)
            else:
                per_time.append(sat.mean())
                ok = sat
        whole.append(ok.mean())
        ok_all &= ok
    return np.array(per_time), np.array(whole), float(ok_all.mean())
