"""The Lagrangian of the constrained ProMP adaptation (paper 003, Eq. 10 and 23) and its
analytic gradient: KL objective, smoothness regulariser, and the constraints through the
marginals of z_t, the points of interest (linear maps or the unscented transform through the
kinematics) and the Cholesky parameterisation Sigma = L L^T, L = L_tril + diag(exp(gamma)).
"""
from typing import List, Optional, Sequence

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.adaptation.batched import BatchedLagrangian
from cdmp_ros.core.adaptation.config import (CHECKED_LAW, SAMPLED_CHECK_FRACTION,
                                             SAMPLED_CHECK_LAW, AdaptationConfig)
from cdmp_ros.core.adaptation.constraints.base import Constraint, WeightConstraint
from cdmp_ros.core.adaptation.constraints.points import (ChainPoint, DifferencePoint, DofPoint,
                                                         StackedChainPoints,
                                                         StackedDifferencePoints)
from cdmp_ros.core.adaptation.tail_sampling import sphere_violation
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.gaussian import UnscentedTransform
from cdmp_ros.core.promp.promp import ProMP

#: Seed of the 'sampled' check's draws (plus the number of joints of the point).
CHECK_SEED = 20261207


def _contiguous_dofs(point):
    """The slice of z_t a plain DofPoint selects, if its dofs are contiguous and increasing."""
    if type(point) is not DofPoint:
        return None
    d = list(point.dofs)
    if d != list(range(d[0], d[0] + len(d))):
        return None
    return slice(d[0], d[0] + len(d))


def _stack_key(point, times_key):
    """The key of the points evaluated together with ``point`` (one forward-kinematics call
    per chain and one unscented transform): chain points of one chain, dofs and axes
    (StackedChainPoints), or differences of chain points over the same dofs and axes
    (StackedDifferencePoints); None for any other point. Exact classes only: subclasses may
    override the kinematics."""
    if type(point) is ChainPoint:
        return ('chain', id(point.chain), point.dofs, point.axes, times_key)
    if (type(point) is DifferencePoint and type(point.a) is ChainPoint
            and type(point.b) is ChainPoint and point.a.axes == point.b.axes):
        return ('difference', point.dofs, point.a.axes, times_key)
    return None


class _Group:
    """Marginals of z_t at one set of times, shared by the constraints using them."""

    def __init__(self, promp: ProMP, times: NDArray):
        self.times = times
        self.phi = promp.basis.features(times)          # (n, M)
        self.D, self.M = promp.n_dims, promp.n_basis

    def forward(self, mu, L):
        D, M = self.D, self.M
        nw = L.shape[1]
        self.m = self.phi @ mu.reshape(D, M).T          # (n, D)
        # one GEMM: B[t, d] = phi_t^T L[d-th block]  (n, D, nw)
        Lm = L.reshape(D, M, nw).transpose(1, 0, 2).reshape(M, D * nw)
        self.B = (self.phi @ Lm).reshape(-1, D, nw)
        self.S = np.matmul(self.B, np.swapaxes(self.B, 1, 2))   # (n, D, D)
        self.g_m = np.zeros_like(self.m)
        self.g_S = np.zeros_like(self.S)

    def backward(self, g_mu, g_L):
        D, M = self.D, self.M
        nw = g_L.shape[1]
        g_mu += (self.phi.T @ self.g_m).T.ravel()
        g_B = np.matmul(self.g_S + np.swapaxes(self.g_S, 1, 2), self.B)   # (n, D, nw)
        g_Lm = self.phi.T @ g_B.reshape(-1, D * nw)                       # (M, D nw)
        g_L += g_Lm.reshape(M, D, nw).transpose(1, 0, 2).reshape(D * M, nw)


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

    def add_gradient(self, xs, dm, dS):
        """Add ``dm``, ``dS`` (gradients w.r.t. the mean and covariance of the coordinates
        ``xs`` of the point, all of them when None) to ``g_mx``, ``g_Sx``."""
        if xs is None:
            self.g_mx += dm
            self.g_Sx += dS
        else:
            self.g_mx[:, xs] += dm
            self.g_Sx[:, xs, xs] += dS

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
        g.g_m[:, self.dofs] += g_m           # dofs are unique: no lost updates
        g.g_S[:, self.dofs[:, None], self.dofs[None, :]] += g_S


#: Evaluations of the Lagrangian (:class:`Problem`'s ``evaluator``): the batched one
#: (:mod:`cdmp_ros.core.adaptation.batched`) or the reference (its test oracle).
EVALUATORS = ('batched', 'reference')
#: The evaluation a Problem uses unless told otherwise: the batched one, 1.26-1.36x faster per
#: evaluation on the Panda problems (the demo's first obstacle request 1.40 -> 1.11 ms;
#: ``benchmarks/bench_lagrangian.py``), values equal to 1e-13 and gradients to 1e-10 of the
#: reference's; the reference stays its test oracle.
DEFAULT_EVALUATOR = 'batched'


class Problem:
    """The adaptation problem: prior p0, constraints and objective, with the analytic
    Lagrangian and its gradient over theta = (mu, L_tril, gamma) (Eq. 23).

    ``evaluator``: ``'batched'`` or ``'reference'`` (:data:`EVALUATORS`; default
    :data:`DEFAULT_EVALUATOR`)."""

    def __init__(self, prior: ProMP, constraints: Sequence, config: AdaptationConfig,
                 evaluator: Optional[str] = None):
        evaluator = DEFAULT_EVALUATOR if evaluator is None else evaluator
        if evaluator not in EVALUATORS:
            raise ValidationError(f'evaluator: expected one of {list(EVALUATORS)}, got '
                                  f'{evaluator!r}')
        self.prior = prior
        self.config = config
        n = prior.n_weights
        self.n = n
        self.tril = np.tril_indices(n, -1)
        self._tril_flat = np.ravel_multi_index(self.tril, (n, n))
        self._diag_flat = np.arange(n) * (n + 1)
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
        keys = []
        stacks = {}
        for c in constraints:
            if isinstance(c, Constraint):
                times = c.times(self.grid)
                key = times.tobytes()
                if key not in groups:
                    groups[key] = _Group(prior, times)
                keys.append(key)
                skey = _stack_key(c.point, key)
                if skey is not None:
                    members = stacks.setdefault(skey, [])
                    if all(m is not c.point for m in members):
                        members.append(c.point)
            else:
                keys.append(None)
        points = {}
        where = {}        # (id(point), times key) -> (_PointMoments, slice or None)
        for skey, members in stacks.items():
            if len(members) > 1:
                stacked = (StackedChainPoints(members) if skey[0] == 'chain'
                           else StackedDifferencePoints(members))
                pm = _PointMoments(stacked, groups[skey[-1]], prior.n_dims, config.ut_alpha)
                points[('stack',) + skey] = pm
                for i, m in enumerate(members):
                    where[(id(m), skey[-1])] = (pm, slice(i * stacked.q, (i + 1) * stacked.q))
        self.bound: List = []
        self.weight_constraints: List[WeightConstraint] = []
        self.slices = []
        offset = 0
        for c, key in zip(constraints, keys):
            if isinstance(c, WeightConstraint):
                self.weight_constraints.append(c)
                nv = 1
                self.bound.append(None)
            elif isinstance(c, Constraint):
                pkey = (id(c.point), key)
                if pkey not in where:
                    sel = _contiguous_dofs(c.point)
                    if sel is not None:
                        # a selection of contiguous dimensions: a view of the group's marginals
                        ikey = ('identity', key)
                        if ikey not in points:
                            points[ikey] = _PointMoments(DofPoint(range(prior.n_dims)),
                                                         groups[key], prior.n_dims,
                                                         config.ut_alpha)
                        where[pkey] = (points[ikey], sel)
                    else:
                        pm = _PointMoments(c.point, groups[key], prior.n_dims, config.ut_alpha)
                        points[pkey] = pm
                        where[pkey] = (pm, None)
                self.bound.append(where[pkey])
                nv = groups[key].times.size if c.reduce == 'each' else 1
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
        self._build_batches()
        self._glo, self._ghi = self.gamma_limits()
        self._normals = {}   # k -> the 'sampled' check's standard normal draws
        self._last = None
        self.n_evaluations = 0
        self.evaluator = evaluator
        self._batched = None
        if evaluator == 'batched':
            self._batched = BatchedLagrangian(self)

    def _build_batches(self):
        """Constraints of one ``batch_kind`` and output size, evaluated in one call."""
        batches = {}
        self.single = []
        self.fused = []
        self.check_params = []
        # per constraint, the law of its probability (ConstraintReport.law)
        self.laws = [self.config.resolved_tail(True) if b is None else 'custom'
                     for b in self.bound]
        for i, (c, b) in enumerate(zip(self.constraints, self.bound)):
            if b is None:
                continue
            kind = getattr(c, 'batch_kind', None)
            if kind is None or type(c).probability is not Constraint.probability:
                self.single.append(i)
                continue
            k = c.point.n_out
            # linear and unscented points apart: AdaptationConfig.tail = 'auto' treats them
            # differently
            batches.setdefault((kind, k, bool(self.bound[i][0].linear)), []).append(i)
        self.batches = []
        for (_, _, linear), members in batches.items():
            rows, offsets, n = [], [], 0
            for i in members:
                r = self.constraints[i].rows(self.bound[i][0].group.times)
                size = self.bound[i][0].group.times.size
                rows.append(r)
                offsets.append((n, n + size))
                n += size
            params = {key: np.concatenate([r[key] for r in rows]) for key in rows[0]}
            # the tail approximation of quadratic forms, and a scratch space kept between
            # evaluations (warm starts of the saddle points)
            params['tail'] = self.config.resolved_tail(linear)
            params['state'] = {}
            cls = type(self.constraints[members[0]])
            # the far-waypoint guide of the Lagrangian (spheres; a robust objective)
            self.batches.append((cls.probability_rows, members, offsets, params,
                                 getattr(cls, 'guide_rows', None)))
            # the saddle point's check of the Gamma match (AdaptationConfig.tail 'auto'):
            # the same moments, another law, a scratch space of its own
            self.check_params.append(
                dict(params, tail='saddlepoint', state={})
                if self.config.tail == 'auto' and params['tail'] == 'gamma' else None)
            checked_law = (SAMPLED_CHECK_LAW if self.config.check_law == 'sampled'
                           else CHECKED_LAW)
            law = ('gaussian' if cls.batch_kind != 'sphere' else
                   checked_law if self.check_params[-1] is not None else params['tail'])
            for i in members:
                self.laws[i] = law
            # members with one multiplier per row: their rows' multipliers in batch order,
            # so the Lagrangian weighs the batch's gradients in one product (see lagrangian)
            fused = all(self.constraints[i].reduce == 'each' for i in members)
            self.fused.append(np.concatenate([np.arange(self.slices[i].start,
                                                        self.slices[i].stop)
                                              for i in members]) if fused else None)

    def _moments_of(self, i):
        pm, xs = self.bound[i]
        if xs is None:
            return pm.mx, pm.Sx
        return pm.mx[:, xs], pm.Sx[:, xs, xs]

    # --------------------------------------------------------------- parameters
    def initial_theta(self) -> NDArray:
        if self.config.whiten:
            return np.zeros(2 * self.n + self.tril[0].size)
        L0 = self.L0
        return np.concatenate([self.mu0, L0[self.tril], np.log(np.diag(L0))])

    def gamma_limits(self):
        """Box on gamma: the diagonal of L stays within [e^-25, e^5] times the prior's, which
        keeps exp(gamma) finite during line searches. Returns (lo, hi), each (n,)."""
        base = 0.0 if self.config.whiten else np.log(np.diag(self.L0))
        return (np.broadcast_to(base - 25.0, (self.n,)).copy(),
                np.broadcast_to(base + 5.0, (self.n,)).copy())

    def bounds(self):
        """The box of :meth:`gamma_limits` on the whole theta as scipy Bounds (the optimiser
        itself clips gamma inside the Lagrangian instead: scipy's L-BFGS-B converts bounds
        with a Python loop over every parameter on each call)."""
        from scipy.optimize import Bounds
        n, nt = self.n, self.tril[0].size
        lo = np.full(2 * n + nt, -np.inf)
        hi = np.full(2 * n + nt, np.inf)
        lo[n + nt:], hi[n + nt:] = self.gamma_limits()
        return Bounds(lo, hi)

    def _factors(self, theta):
        """First block, lower-triangular matrix and gamma of theta (raw or whitened); gamma
        is clipped to :meth:`gamma_limits` (its gradient is zero outside)."""
        n = self.n
        first = theta[:n]
        T = np.zeros((n, n))
        T.flat[self._tril_flat] = theta[n:n + self.tril[0].size]
        gamma = np.clip(theta[n + self.tril[0].size:], self._glo, self._ghi)
        T.flat[self._diag_flat] = np.exp(gamma)
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

    def constraint_values(self, mu, L, grads=False, guided=False):
        """F for every multiplier (n_values,), optionally with the backward closure.

        ``guided`` (the Lagrangian): the batches' ``guide_rows`` are added to the rows'
        probabilities and gradients, and the unguided F is returned as a third value (what
        the multiplier updates and the report use)."""
        for g in self.groups:
            g.forward(mu, L)
        for pm in self.points:
            pm.compute()
        F = np.empty(self.n_values)
        parts = [None] * len(self.constraints)
        Sigma = None
        for i, (c, b, sl) in enumerate(zip(self.constraints, self.bound, self.slices)):
            if b is None:
                if Sigma is None:
                    Sigma = L @ L.T
                Fw, dmu, dS = c.probability_w(mu, Sigma, tail=self.config.resolved_tail(True))
                F[sl] = Fw
                parts[i] = (dmu, dS)
        for i in self.single:
            m, S = self._moments_of(i)
            self._store(i, *self.constraints[i].probability(m, S, self.bound[i][0].group.times),
                        F, parts)
        F_true = F.copy() if guided else None
        batch_grads = []
        for (fn, members, offsets, params, guide), rows in zip(self.batches, self.fused):
            if len(members) == 1:
                m, S = self._moments_of(members[0])
            else:
                ms = [self._moments_of(i) for i in members]
                m = np.concatenate([v[0] for v in ms])
                S = np.concatenate([v[1] for v in ms])
            Fr, dm, dS = fn(m, S, params)
            if guided:
                for i, (a, b) in zip(members, offsets):
                    sl, Ft = self.slices[i], Fr[a:b]
                    F_true[sl] = Ft.max() if self.constraints[i].reduce == 'max' else Ft
                if guide is not None:
                    G, dG_dm, dG_dS = guide(m, S, params)
                    if np.any(G):
                        Fr, dm, dS = Fr + G, dm + dG_dm, dS + dG_dS
            if grads and rows is not None:   # fused: weighed per batch in lagrangian
                F[rows] = Fr
                batch_grads.append((members, offsets, rows, dm, dS))
                continue
            for i, (a, b) in zip(members, offsets):
                self._store(i, Fr[a:b], dm[a:b], dS[a:b], F, parts)
        if grads:
            # parts: per constraint (None for the members of a fused batch), then the fused
            # batches as (members, offsets, multiplier rows, dF/dm, dF/dS)
            parts = (parts, batch_grads)
        if guided:  # (weight and single constraints have no guide: F_true holds them)
            if not grads:
                return F, F_true
            return F, parts, F_true
        if not grads:
            return F
        return F, parts

    def cached_values(self, theta):
        """F of the last Lagrangian evaluation if it was at ``theta``, else None."""
        if not self.n_values:
            return np.zeros(0)
        last = self._last
        if last is not None and np.array_equal(last[0], theta):
            return last[1]
        return None

    def check_values(self, theta):
        """The saddle point's check of the Gamma-matched rows at ``theta``: ``(F_check,
        checked)``, F of every multiplier under the saddle-point law for the rows of points
        through the unscented transform that ``AdaptationConfig.tail`` 'auto' solves with the
        Gamma match (``checked`` True), F of :meth:`constraint_values` elsewhere.

        The Gamma match keeps the optimiser from inflating the joint variance (its gradients
        penalise a wide distribution), but its tail can be several times too light; the
        solver corrects those rows' levels by this check
        (:func:`~cdmp_ros.core.adaptation.solver.corrected_levels`)."""
        mu, L, _ = self.unpack(theta)
        F = self.cached_values(theta)
        if F is None:
            F = self.constraint_values(mu, L) if self.n_values else np.zeros(0)
        checked = np.zeros(F.size, dtype=bool)
        if not any(p is not None for p in self.check_params):
            return F, checked
        for g in self.groups:            # the moments at theta (the cache may hold others)
            g.forward(mu, L)
        for pm in self.points:
            pm.compute()
        F = F.copy()
        for (fn, members, offsets, _, _), check in zip(self.batches, self.check_params):
            if check is None:
                continue
            ms = [self._moments_of(i) for i in members]
            Fs = fn(np.concatenate([v[0] for v in ms]), np.concatenate([v[1] for v in ms]),
                    check)[0]
            sphere = getattr(self.constraints[members[0]], 'batch_kind', None) == 'sphere'
            for i, (a, b) in zip(members, offsets):
                sl, Ft = self.slices[i], Fs[a:b]
                if self.config.check_law == 'sampled' and sphere:
                    Ft = self._sampled_check(i, Ft, check, a, b)
                F[sl] = Ft.max() if self.constraints[i].reduce == 'max' else Ft
                checked[sl] = True
        return F, checked

    def _sampled_check(self, i, Ft, check, a, b):
        """The 'sampled' check of constraint ``i``'s rows (``AdaptationConfig.check_law``):
        at the repeller rows where the saddle point's satisfaction ``Ft`` leaves a violation
        of at least SAMPLED_CHECK_FRACTION (1 - alpha), one minus the importance-sampled
        violation of the point's true law plus one standard error; ``Ft`` elsewhere.
        ``check[a:b]``: the rows' centres, squared radii and sides."""
        c = self.constraints[i]
        # repeller rows (the proposal's shift covers a ball to be avoided, not the outside
        # of a ball to be reached, which surrounds the mean)
        near = ((1.0 - Ft) >= SAMPLED_CHECK_FRACTION * (1.0 - c.alpha)) & \
            ~np.asarray(check['inside'][a:b], bool)
        if not near.any():
            return Ft
        pm, _ = self.bound[i]
        rows = np.flatnonzero(near)
        dofs = np.asarray(c.point.dofs)
        g = pm.group
        at = a + rows   # the rows in the batch's parameters
        est = sphere_violation(c.point, g.m[np.ix_(rows, dofs)],
                               g.S[np.ix_(rows, dofs, dofs)], check['center'][at],
                               check['r2'][at], check['inside'][at],
                               self._check_normals(dofs.size))
        out = Ft.copy()
        out[rows] = 1.0 - np.minimum(est.p + est.se, 1.0)
        return out

    def _check_normals(self, k):
        """The standard normal draws of the 'sampled' check for points of ``k`` joints: the
        same at every check of this problem (the check is a function of theta)."""
        draws = self._normals.get(k)
        if draws is None:
            rng = np.random.default_rng(CHECK_SEED + k)
            draws = self._normals[k] = rng.standard_normal((self.config.check_samples, k))
        return draws

    def _store(self, i, Ft, dm, dS, F, parts):
        sl = self.slices[i]
        if self.constraints[i].reduce == 'max':
            j = int(np.argmax(Ft))
            F[sl] = Ft[j]
            mask = np.zeros(Ft.size)
            mask[j] = 1.0
            parts[i] = (mask, dm, dS)
        else:
            F[sl] = Ft
            parts[i] = (None, dm, dS)

    def prior_terms(self, first, T):
        """The terms of L(theta, lambda) (Eq. 23) other than the constraints, shared by
        :meth:`lagrangian_reference` and the batched evaluator: ``(mu, L, value, g_mu, g_L,
        g_Sigma)``, the moments in the original coordinates from the factors of theta
        (:meth:`_factors`), the KL and the smoothness regulariser kappa * E[R(w)] (Eq. 14-15)
        with their gradients w.r.t. mu, L and Sigma (``g_Sigma`` None without the
        regulariser). Whitened without blocks the KL is left out (value 0): the callers add
        it in whitened coordinates."""
        if self.config.whiten:
            mu, L = self.mu0 + self.L0 @ first, self.L0 @ T
        else:
            mu, L = first, T
        value = 0.0
        g_mu = np.zeros(self.n)
        g_L = np.zeros((self.n, self.n))
        if not (self.config.whiten and self.blocks is None):
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
        return mu, L, value, g_mu, g_L, g_Sigma

    def lagrangian(self, theta, lam):
        """L(theta, lambda) of Eq. (23) and its gradient w.r.t. theta (batched:
        :class:`~cdmp_ros.core.adaptation.batched.BatchedLagrangian`; the reference
        :meth:`lagrangian_reference` with ``evaluator='reference'``)."""
        if self._batched is None:
            return self.lagrangian_reference(theta, lam)
        self.n_evaluations += 1
        value, grad, F_true = self._batched.evaluate(theta, lam)
        if F_true is not None:
            self._last = (theta.copy(), F_true)
        return value, grad

    def lagrangian_reference(self, theta, lam):
        """L(theta, lambda) of Eq. (23) and its gradient w.r.t. theta, evaluated constraint
        by constraint: the test oracle of the batched :meth:`lagrangian`."""
        self.n_evaluations += 1
        first, T, gamma = self._factors(theta)
        whiten = self.config.whiten
        mu, L, value, g_mu, g_L, g_Sigma = self.prior_terms(first, T)
        if self.n_values:
            F, (parts, batch_grads), F_true = self.constraint_values(mu, L, grads=True,
                                                                     guided=True)
            self._last = (theta.copy(), F_true)
            value += np.sum(lam * (self.alpha - F))
            for members, offsets, rows, dm, dS in batch_grads:
                w = -lam[rows]
                wdm = w[:, None] * dm
                wdS = w[:, None, None] * dS
                for i, (a, b) in zip(members, offsets):
                    pm, xs = self.bound[i]
                    pm.add_gradient(xs, wdm[a:b], wdS[a:b])
            for c, b, sl, part in zip(self.constraints, self.bound, self.slices, parts):
                if part is None:
                    continue
                w = -lam[sl]
                if b is None:
                    dmu, dS = part
                    g_mu += w @ dmu
                    gS = np.tensordot(w, dS, axes=1)
                    g_Sigma = gS if g_Sigma is None else g_Sigma + gS
                    continue
                mask, dm, dS = part
                wt = w[0] * mask if mask is not None else w
                pm, xs = b
                pm.add_gradient(xs, wt[:, None] * dm, wt[:, None, None] * dS)
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
        g_gamma = np.diag(g_T) * np.exp(gamma)
        g_gamma[theta[-self.n:] != gamma] = 0.0          # clipped: flat outside the box
        g_theta = np.concatenate([g_first, g_T.flat[self._tril_flat], g_gamma])
        return value, g_theta
