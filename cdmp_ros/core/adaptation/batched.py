"""Batched evaluation of the Lagrangian of :class:`~cdmp_ros.core.adaptation.problem.Problem`
(paper 003, Eq. 23) and its analytic gradient.

The reference evaluation (:meth:`Problem.lagrangian_reference`) walks the problem's structure
object by object: one call per constraint, per member of a batch, per joint of the forward
kinematics, per column of a Cholesky factor, about 580 numpy calls per evaluation of the Panda
problem of ``benchmarks/bench_adapter.py``. This module evaluates the same function with the
per-row work of every stage stacked into array operations over all rows at once, and everything
that depends only on the problem prepared at construction:

- the parameters: the whitened KL and its gradient from theta's entries directly (no dense
  ``T - diag(1 / diag T)``), one reused buffer for the Cholesky factor;
- the constraints of one batch (one ``batch_kind``): their moments gathered from the points'
  moments by one flat index, their gradients scattered back by one ``bincount``, with only the
  rows whose gradient is not zero (the "live" rows: a repeller row far from its sphere has
  F = 1 and a gradient below 1e-30);
- the unscented transform through a kinematic chain (ChainPoint, StackedChainPoints): the sigma
  points of every time step in one array with the batch axis innermost, the frame recursion of
  :class:`~cdmp_ros.core.kinematics.chain.Chain` (one BLAS product and one complex product per
  joint), and the backward pass through the kinematics by the adjoint of the Jacobian,
  ``dL/dq_j = z_j . (sum_p x_p x g_p - o_j x sum_p g_p)`` over the points p beyond joint j,
  so the Jacobians (n_points x 3 x n_dofs per sigma point) are never formed;
- the Gamma tail of the quadratic forms (repellers, waypoints on unscented points): the CDF on
  every row, its derivatives (two more incomplete gamma functions for the shape) on the live
  rows only.

Anything else (single constraints that override ``probability``, weight constraints, linear
maps, other non-linear points, other batch kinds) is evaluated by the reference code of the
problem, so every problem the reference handles is handled. The reference stays the test
oracle: test/test_core_lagrangian_batched.py compares both on the Panda problem, a Table II
problem and random problems of every constraint kind.

The gain is modest (``benchmarks/bench_lagrangian.py``): the reference was batched by
constraint kind already, and what remains is vectorised numerical work (BLAS products of the
70 x 70 factors and of the group marginals, LAPACK on 50 small matrices, the kinematics of 700
sigma points, the incomplete gamma function; on Table II the saddle-point tail), not Python
overhead. It is the default (:data:`~cdmp_ros.core.adaptation.problem.DEFAULT_EVALUATOR`):
1.26-1.36x per evaluation on the Panda problems.
"""
from typing import List, Optional, Tuple

import numpy as np
from numpy.typing import NDArray
from scipy import special

from cdmp_ros.core.adaptation.constraints.points import ChainPoint, StackedChainPoints
from cdmp_ros.core.adaptation.constraints.limits import JointLimit
from cdmp_ros.core.adaptation.constraints.spheres import _Sphere
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.chain import Chain
from cdmp_ros.core.promp.gaussian import batched_cholesky, cholesky_backward, normal_pdf
from cdmp_ros.core.promp.quadratic_tail import quadratic_form_cdf

#: Rows of a joint-limit batch farther than this many standard deviations from both bounds are
#: not live: the normal density there is below 1e-31.
LIMIT_Z = 12.0

#: Rows of a Gamma-tail batch whose CDF is at most this are not live: their derivatives are
#: below ~1e-30 (the left tail of the Gamma law), so the gradient skips them.
GAMMA_DEAD = 1e-30


# ----------------------------------------------------------------------------- small helpers
def _cross(a0, a1, a2, b0, b1, b2):
    """Components of a x b from components (any equal shapes)."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


# ----------------------------------------------------------------------------- chains
def fast_chain_point(point) -> bool:
    """Whether the batched unscented transform through the kinematics applies to ``point``:
    a ChainPoint or StackedChainPoints (exactly those classes: subclasses may override the
    kinematics) of a :class:`Chain` whose forward kinematics is the class's own."""
    if type(point) not in (ChainPoint, StackedChainPoints):
        return False
    chain = point.chain
    return (isinstance(chain, Chain)
            and type(chain).forward_and_jacobian is Chain.forward_and_jacobian
            and type(chain)._frames is Chain._frames)


class ChainUT:
    """The unscented transform of a point of interest through a kinematic chain, batched over
    time steps and sigma points, forward (moments) and backward (gradients of the input
    moments). Same sigma points, kinematics and moments as
    :class:`~cdmp_ros.core.promp.gaussian.UnscentedTransform` with ``point.
    forward_and_jacobian``.

    Parameters
    ----------
    point : ChainPoint or StackedChainPoints
    ut : UnscentedTransform
        Of ``len(point.dofs)`` dimensions.
    """

    def __init__(self, point, ut):
        chain = point.chain
        pois = [point.point] if type(point) is ChainPoint else [p.point for p in point.points]
        frames, coords = chain.resolve(pois)
        self.frames = [int(f) for f in frames]
        self.coords4 = [np.r_[c, 1.0] for c in coords]
        self.n_points = len(self.frames)
        self.kmax = max(self.frames)
        self.B = chain.B
        self.base = np.ascontiguousarray(chain.base_transform[:3])
        self.M1 = self.base @ chain.B[0]                     # frame 1 before its joint
        self.prismatic = [bool(v) for v in chain.prismatic]
        self.k = chain.n_dofs
        self.axes = tuple(point.axes)
        self.full_axes = self.axes == (0, 1, 2)
        self.ut = ut
        self.scale = ut.scale
        self.c = ut.n_centre
        self.p = ut.n_centre + 2 * self.k
        self.w = ut.weights
        self.uniform = bool(np.all(self.w == self.w[-1]))
        # mask[j, i]: point i lies beyond joint j (its Jacobian column j is not zero)
        self.mask = np.array([[1.0 if f > j else 0.0 for f in self.frames]
                              for j in range(self.kmax)])

    def forward(self, m: NDArray, S: NDArray) -> Tuple[NDArray, NDArray]:
        """Moments (n, n_out) and (n, n_out, n_out) of x_t from those of z_t (n, k) and
        (n, k, k); keeps what :meth:`backward` needs."""
        n, k, c, p = m.shape[0], self.k, self.c, self.p
        N = n * p
        A = batched_cholesky(S)
        sA = (self.scale * A).transpose(1, 0, 2)             # (k, n, k): scale A[t, i, j]
        Zt = np.empty((k, n, p))                             # Zt[i, t, s]: sigma point s, dof i
        mT = m.T[:, :, None]
        if c:
            Zt[:, :, :c] = mT
        np.add(mT, sA, out=Zt[:, :, c:c + k])
        np.subtract(mT, sA, out=Zt[:, :, c + k:])
        Q = Zt.reshape(k, N)
        if not np.isfinite(Q.sum()):
            raise ValidationError('Q: expected finite values')
        # Rz(q) as a complex factor exp(-i q), from t = tan(q / 2) (Chain._frames)
        kmax = self.kmax
        Tq = np.tan(0.5 * Q[:kmax])
        T2 = Tq * Tq
        den = 1.0 + T2
        E = np.empty((kmax, N), dtype=np.complex128)
        E.real = (1.0 - T2) / den
        E.imag = (-2.0 * Tq) / den
        F = np.empty((kmax + 1, 3, N, 4))
        for j in range(kmax):
            M = F[j + 1]
            if j == 0:   # frame 0 is the constant base: frame 1 by broadcasting
                M[...] = self.M1[:, None, :]
            else:
                np.dot(F[j].reshape(3 * N, 4), self.B[j], out=M.reshape(3 * N, 4))
            if self.prismatic[j]:
                M[:, :, 3] += M[:, :, 2] * Q[j]
            else:
                M.view(np.complex128)[:, :, 0] *= E[j]
        X = np.empty((self.n_points, 3, N))
        for i, (f, c4) in enumerate(zip(self.frames, self.coords4)):
            if f == 0:
                X[i] = (self.base @ c4)[:, None]
            else:
                np.dot(F[f].reshape(3 * N, 4), c4, out=X[i].reshape(3 * N))
        Xq = (X if self.full_axes else X[:, list(self.axes)]).reshape(-1, n, p)  # (Q, n, p)
        mxT = Xq @ self.w                                    # (Q, n)
        D = Xq - mxT[:, :, None]
        Dt = D.transpose(1, 0, 2)                            # (n, Q, p)
        if self.uniform:
            Sx = np.matmul(Dt, Dt.transpose(0, 2, 1))
            Sx *= self.w[-1]
        else:
            Sx = np.matmul(Dt * self.w, Dt.transpose(0, 2, 1))
        self._cache = (A, F, X, Dt, n)
        return mxT.T, Sx

    def backward(self, g_mx: NDArray, g_Sx: NDArray, rows: Optional[NDArray] = None
                 ) -> Tuple[NDArray, NDArray]:
        """Gradients w.r.t. the input moments, (n, k) and (n, k, k), from those w.r.t. the
        output moments, (n, n_out) and (n, n_out, n_out); with ``rows`` (time steps of the
        last :meth:`forward`) only at those steps, ``g_mx`` and ``g_Sx`` given there."""
        A, F, X, Dt, n = self._cache
        k, c, p, kmax = self.k, self.c, self.p, self.kmax
        if rows is not None:
            cols = (rows[:, None] * p + np.arange(p)).ravel()
            A, Dt, n = A[rows], Dt[rows], rows.size
            X = X[:, :, cols]
            ZO = np.moveaxis(F[1:, :, cols, 2:], 3, 0).copy()
        else:
            ZO = np.moveaxis(F[1:, :, :, 2:], 3, 0).copy()   # contiguous planes
        N = n * p
        g_Ss = g_Sx + np.swapaxes(g_Sx, 1, 2)
        GX = np.matmul(g_Ss, Dt)                             # (n, Q, p)
        GX += g_mx[:, :, None]
        GX *= self.w
        GX = GX.transpose(1, 0, 2).reshape(-1, 3 if self.full_axes else len(self.axes), N)
        if not self.full_axes:
            G = np.zeros((self.n_points, 3, N))
            G[:, list(self.axes)] = GX
        else:
            G = GX                                           # (P, 3, N)
        # adjoint of the Jacobians: g_q_j = z_j . (a_j - o_j x b_j) (module docstring)
        cp = np.stack(_cross(X[:, 0], X[:, 1], X[:, 2], G[:, 0], G[:, 1], G[:, 2]), axis=1)
        a = (self.mask @ cp.reshape(self.n_points, 3 * N)).reshape(kmax, 3, N)
        b = (self.mask @ G.reshape(self.n_points, 3 * N)).reshape(kmax, 3, N)
        Zax, Org = ZO[0], ZO[1]                              # (kmax, 3, N) axes, origins
        ob = _cross(Org[:, 0], Org[:, 1], Org[:, 2], b[:, 0], b[:, 1], b[:, 2])
        gq = np.zeros((k, N))
        gq[:kmax] = (Zax[:, 0] * (a[:, 0] - ob[0]) + Zax[:, 1] * (a[:, 1] - ob[1])
                     + Zax[:, 2] * (a[:, 2] - ob[2]))
        for j in range(kmax):
            if self.prismatic[j]:
                gq[j] = np.einsum('cn,cn->n', Zax[j], b[j])
        gZ = gq.reshape(k, n, p)
        g_m = gZ.sum(axis=2).T
        g_A = self.scale * (gZ[:, :, c:c + k] - gZ[:, :, c + k:]).transpose(1, 0, 2)
        return g_m, cholesky_backward(A, g_A)


# ----------------------------------------------------------------------------- row kernels
def sphere_gamma_rows(m: NDArray, S: NDArray, params: dict):
    """:meth:`_Sphere.probability_rows` with the Gamma tail, derivatives on the live rows.

    Returns
    -------
    F : (N,); live : (n_live,) row indices; dF_dm : (n_live, k); dF_dS : (n_live, k, k)
    """
    N, k = m.shape
    d = m - params['center']
    Sd = np.matmul(S, d[:, :, None])[:, :, 0]
    Sf = S.reshape(N, k * k)
    ones, diag = _row_ops(k)
    # Eq. (15) moments of |x - c|^2: E = |d|^2 + tr S, V = 4 d^T S d + 2 tr(S S^T)
    E = np.maximum((d * d) @ ones + Sf @ diag, 1e-300)
    V = np.maximum(4.0 * ((d * Sd) @ ones)
                   + 2.0 * ((Sf * np.swapaxes(S, 1, 2).reshape(N, k * k)) @ _row_ops(k * k)[0]),
                   1e-300)
    x = params['r2']
    kk = E * E / V
    u = (E / V) * x
    P = special.gammainc(kk, u)
    live = np.flatnonzero(P > GAMMA_DEAD)
    F = np.where(params['inside'], P, 1.0 - P)
    if not live.size:
        return F, live, np.zeros((0, k)), np.zeros((0, k, k))
    sign = params['sign']                     # +1 inside rows (waypoints), -1 repellers
    if live.size < N:
        E, V, kk, u, x, Pl = E[live], V[live], kk[live], u[live], x[live], P[live]
        d, Sd, S, sg = d[live], Sd[live], S[live], sign[live]
    else:
        Pl, sg = P, sign
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        log_dens = (kk - 1.0) * np.log(np.maximum(u, 1e-300)) - u - special.gammaln(kk)
        dP_du = np.where(u > 0, np.exp(log_dens), 0.0)
    # dP/dk: the central difference of gamma_cdf (the one scalar numerical derivative)
    h = 1e-5 * (1.0 + kk)
    lk = Pl < 1.0 - 1e-16
    if lk.all():
        dP_dk = (special.gammainc(kk + h, u) - special.gammainc(kk - h, u)) / (2.0 * h)
    else:
        dP_dk = np.zeros(kk.shape)
        if lk.any():
            dP_dk[lk] = (special.gammainc(kk[lk] + h[lk], u[lk])
                         - special.gammainc(kk[lk] - h[lk], u[lk])) / (2.0 * h[lk])
    sV = sg / V
    dE = sV * (dP_dk * (2.0 * E) + dP_du * x)
    dV = sV * (dP_dk * -kk - dP_du * u)
    # dE/dm = 2 d, dV/dm = 8 S d; dE/dS = I, dV/dS = 4 (d d^T + S^T)
    dm = (2.0 * dE)[:, None] * d + (8.0 * dV)[:, None] * Sd
    dS = d[:, :, None] * d[:, None, :]
    dS += np.swapaxes(S, 1, 2)
    dS *= (4.0 * dV)[:, None, None]
    dS.reshape(-1, k * k)[:, ::k + 1] += dE[:, None]
    return F, live, dm, dS


_ROW_OPS = {}


def _row_ops(k: int):
    """(ones(k), flattened identity (k*k,)): row sums and traces as matrix-vector products."""
    r = _ROW_OPS.get(k)
    if r is None:
        r = _ROW_OPS[k] = (np.ones(k), np.eye(k).ravel())
    return r


def limit_rows(m: NDArray, S: NDArray, params: dict):
    """:meth:`JointLimit.probability_rows` (Eq. 13) with the derivatives on the live rows:
    those within :data:`LIMIT_Z` standard deviations of a bound."""
    a, b = params['a'], params['b']
    mu = m[:, 0]
    sd = np.sqrt(np.maximum(S[:, 0, 0], 1e-300))
    with np.errstate(invalid='ignore'):
        zb, za = (b - mu) / sd, (a - mu) / sd          # +-inf for infinite bounds
    F = special.ndtr(zb) - special.ndtr(za)
    live = np.flatnonzero((za > -LIMIT_Z) | (zb < LIMIT_Z))
    if not live.size:
        return F, live, np.zeros((0, 1)), np.zeros((0, 1, 1))
    zb, za, sdl = zb[live], za[live], sd[live]
    fb, fa = np.isfinite(zb), np.isfinite(za)
    zb0 = np.where(fb, zb, 0.0)
    za0 = np.where(fa, za, 0.0)
    pb = np.where(fb, normal_pdf(zb0), 0.0)
    pa = np.where(fa, normal_pdf(za0), 0.0)
    dF_dvar = (-pb * zb0 + pa * za0) / (2.0 * sdl * sdl)
    return F, live, ((pa - pb) / sdl)[:, None], dF_dvar[:, None, None]


def sphere_saddle_rows(m: NDArray, S: NDArray, params: dict):
    """:meth:`_Sphere.probability_rows` with the saddle-point tail, restricted to the rows
    whose gradient is not zero (the rows quadratic_form_cdf does not skip)."""
    G, dG_dm, dG_dS = quadratic_form_cdf(m, S, params['center'], params['r2'],
                                         params.get('state'))
    inside = params['inside']
    F = np.where(inside, G, 1.0 - G)
    live = np.flatnonzero(np.any(dG_dm != 0.0, axis=1) | np.any(dG_dS != 0.0, axis=(1, 2)))
    sg = params['sign'][live]
    return F, live, sg[:, None] * dG_dm[live], sg[:, None, None] * dG_dS[live]


# ----------------------------------------------------------------------------- batches
class _Batch:
    """One batch of the problem (constraints of one ``batch_kind``): gather of the rows'
    moments, the row kernel, the multipliers of the rows and the scatter of the gradients."""

    def __init__(self, prob, fn, members, offsets, params, guide, rows):
        self.members = members
        self.offsets = offsets
        self.params = dict(params)
        self.fn = fn
        self.rows = rows
        cons = [prob.constraints[i] for i in members]
        self.guide = guide
        self.has_guide = guide is not None and bool(np.any(params.get('inside', False)))
        self.kernel = None
        tail = params.get('tail', 'saddlepoint')
        if (issubclass(type(cons[0]), _Sphere) and fn is _Sphere.probability_rows
                and tail in ('gamma', 'saddlepoint')):   # 'conservative': the reference
            ins = np.asarray(params['inside'], bool)
            self.params['sign'] = np.where(ins, 1.0, -1.0)
            self.kernel = sphere_gamma_rows if tail == 'gamma' else sphere_saddle_rows
        elif issubclass(type(cons[0]), JointLimit) and fn is JointLimit.probability_rows:
            self.kernel = limit_rows
        # the points' moments this batch reads, and flat indices of its rows into them
        self.pms: List = []
        for i in members:
            pm = prob.bound[i][0]
            if all(pm is not q for q in self.pms):
                self.pms.append(pm)
        sizes = [pm.group.times.size * pm.point.n_out for pm in self.pms]
        self.m_sizes = sizes
        self.S_sizes = [pm.group.times.size * pm.point.n_out ** 2 for pm in self.pms]
        m_off = np.cumsum([0] + sizes)
        S_off = np.cumsum([0] + self.S_sizes)
        im, iS = [], []
        for i in members:
            pm, xs = prob.bound[i]
            q = pm.point.n_out
            cols = np.arange(q)[xs] if xs is not None else np.arange(q)
            j = next(a for a, b in enumerate(self.pms) if b is pm)
            t = np.arange(pm.group.times.size)[:, None]
            im.append(m_off[j] + t * q + cols[None, :])
            iS.append(S_off[j] + t[:, :, None] * q * q + cols[None, :, None] * q
                      + cols[None, None, :])
        self.im = np.concatenate(im)
        self.iS = np.concatenate(iS)
        self.k = self.im.shape[1]
        self.m_total = int(m_off[-1])
        self.S_total = int(S_off[-1])
        self.each = [prob.constraints[i].reduce != 'max' for i in members]
        self.slices = [prob.slices[i] for i in members]
        self.n_rows = self.im.shape[0]

    def gather(self):
        if len(self.pms) == 1:
            pm = self.pms[0]
            mflat, Sflat = pm.mx.reshape(-1), pm.Sx.reshape(-1)
        else:
            mflat = np.concatenate([pm.mx.reshape(-1) for pm in self.pms])
            Sflat = np.concatenate([pm.Sx.reshape(-1) for pm in self.pms])
        return mflat[self.im], Sflat[self.iS]

    def evaluate(self, F, F_true, lam):
        """Fill F (guided) and F_true, return the gradient rows: (live, dm, dS) weighted by
        the multipliers (-lambda), or None if nothing is live."""
        m, S = self.gather()
        params = self.params
        if self.kernel is not None:
            Fr, live, dm, dS = self.kernel(m, S, params)
        else:
            Fr, dm, dS = self.fn(m, S, params)
            live = None
        rows = self.rows
        if rows is not None:
            F_true[rows] = Fr
        else:
            for (a, b), sl, each in zip(self.offsets, self.slices, self.each):
                Ft = Fr[a:b]
                F_true[sl] = Ft if each else Ft.max()
        if self.has_guide:
            if live is not None:                # the guide needs every row's gradient
                dm, dS = self._expand(live, dm, dS)
                live = None
            G, dG_dm, dG_dS = self.guide(m, S, params)
            if np.any(G):
                Fr, dm, dS = Fr + G, dm + dG_dm, dS + dG_dS
        # per-row weights -lambda (a 'max' member: its multiplier at its best row only)
        if rows is not None:
            F[rows] = Fr
            w = -lam[rows]
        else:
            w = np.zeros(self.n_rows)
            for (a, b), sl, each in zip(self.offsets, self.slices, self.each):
                Ft = Fr[a:b]
                if each:
                    F[sl] = Ft
                    w[a:b] = -lam[sl]
                else:
                    j = int(np.argmax(Ft))
                    F[sl] = Ft[j]
                    w[a + j] = -lam[sl][0]
        if live is None:
            return None, w[:, None] * dm, w[:, None, None] * dS
        if not live.size:
            return None
        wl = w[live]
        return live, wl[:, None] * dm, wl[:, None, None] * dS

    def _expand(self, live, dm, dS):
        n, k = self.n_rows, self.k
        fm = np.zeros((n, k))
        fS = np.zeros((n, k, k))
        fm[live] = dm
        fS[live] = dS
        return fm, fS

    def scatter(self, grad):
        """Add the weighted gradient rows of :meth:`evaluate` to the points' g_mx, g_Sx."""
        if grad is None:
            return
        live, wdm, wdS = grad
        im, iS = (self.im, self.iS) if live is None else (self.im[live], self.iS[live])
        gm = np.bincount(im.ravel(), weights=wdm.ravel(), minlength=self.m_total)
        gS = np.bincount(iS.ravel(), weights=wdS.ravel(), minlength=self.S_total)
        a = b = 0
        for pm, sm, sS in zip(self.pms, self.m_sizes, self.S_sizes):
            pm.g_mx += gm[a:a + sm].reshape(pm.g_mx.shape)
            pm.g_Sx += gS[b:b + sS].reshape(pm.g_Sx.shape)
            a += sm
            b += sS


# ----------------------------------------------------------------------------- the evaluator
class BatchedLagrangian:
    """L(theta, lambda) of a :class:`Problem` and its gradient, batched (module docstring).

    Parameters
    ----------
    prob : Problem
        Its groups, points and batches are used (and their moment buffers written).
    """

    def __init__(self, prob):
        self.prob = prob
        n = prob.n
        self.n = n
        self.nt = prob.tril[0].size
        self.T = np.zeros((n, n))
        self.L0T = np.ascontiguousarray(prob.L0.T)
        self.whiten = bool(prob.config.whiten)
        self.groups = []
        for g in prob.groups:
            self.groups.append((g, np.ascontiguousarray(g.phi.T)))
        # points: identity views of a group, chains (batched UT) or the reference code
        self.identity, self.chains, self.other = [], [], []
        for pm in prob.points:
            if pm.identity:
                self.identity.append(pm)
            elif not pm.linear and fast_chain_point(pm.point):
                self.chains.append((pm, ChainUT(pm.point, pm.ut)))
            else:
                self.other.append(pm)
        self.batches = [_Batch(prob, fn, members, offsets, params, guide, rows)
                        for (fn, members, offsets, params, guide), rows
                        in zip(prob.batches, prob.fused)]
        self.weights = [i for i, b in enumerate(prob.bound) if b is None]

    # ------------------------------------------------------------------ stages
    def _group_forward(self, mu, L):
        for g, _ in self.groups:
            D, M = g.D, g.M
            nw = L.shape[1]
            g.m = g.phi @ mu.reshape(D, M).T
            Lm = L.reshape(D, M, nw).transpose(1, 0, 2).reshape(M, D * nw)
            g.B = (g.phi @ Lm).reshape(-1, D, nw)
            g.S = np.matmul(g.B, np.swapaxes(g.B, 1, 2))
            g.g_m = np.zeros_like(g.m)
            g.g_S = np.zeros_like(g.S)

    def _group_backward(self, g_mu, g_L):
        for g, phiT in self.groups:
            D, M = g.D, g.M
            nw = g_L.shape[1]
            g_mu += (phiT @ g.g_m).T.reshape(-1)
            g_B = np.matmul(g.g_S + np.swapaxes(g.g_S, 1, 2), g.B)
            g_Lm = phiT @ g_B.reshape(-1, D * nw)
            g_L += g_Lm.reshape(M, D, nw).transpose(1, 0, 2).reshape(D * M, nw)

    def _points_forward(self):
        for pm in self.identity:
            pm.mx, pm.Sx = pm.group.m, pm.group.S
            pm.g_mx = pm.group.g_m          # the group's accumulators themselves
            pm.g_Sx = pm.group.g_S
        for pm, cut in self.chains:
            g = pm.group
            d = pm.dofs
            if d.size == g.D and np.array_equal(d, np.arange(g.D)):
                m, S = g.m, g.S
            else:
                m, S = g.m[:, d], g.S[:, d][:, :, d]
            pm.mx, pm.Sx = cut.forward(m, S)
            pm.g_mx = np.zeros_like(pm.mx)
            pm.g_Sx = np.zeros_like(pm.Sx)
        for pm in self.other:
            pm.compute()

    def _points_backward(self):
        for pm, cut in self.chains:
            # only the time steps with a gradient (the others: every row dead)
            n = pm.g_mx.shape[0]
            rows = np.flatnonzero((pm.g_mx != 0.0).any(axis=1)
                                  | (pm.g_Sx.reshape(n, -1) != 0.0).any(axis=1))
            if not rows.size:
                continue
            if 2 * rows.size > n:      # gathering most steps costs more than it saves
                g_m, g_S = cut.backward(pm.g_mx, pm.g_Sx)
                rows = slice(None)
            else:
                g_m, g_S = cut.backward(pm.g_mx[rows], pm.g_Sx[rows], rows)
            g = pm.group
            d = pm.dofs
            if d.size == g.D and np.array_equal(d, np.arange(g.D)):
                g.g_m[rows] += g_m
                g.g_S[rows] += g_S
            else:
                r = np.arange(n)[rows]
                g.g_m[r[:, None], d[None, :]] += g_m
                g.g_S[r[:, None, None], d[None, :, None], d[None, None, :]] += g_S
        for pm in self.other:
            pm.backward()
        # identity points accumulate into their group directly

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, theta: NDArray, lam: NDArray
                 ) -> Tuple[float, NDArray, Optional[NDArray]]:
        """(L, dL/dtheta, F) at theta with multipliers lam; F (unguided) per multiplier,
        None without constraints."""
        prob = self.prob
        n, nt = self.n, self.nt
        first = theta[:n]
        tv = theta[n:n + nt]
        graw = theta[n + nt:]
        gamma = np.clip(graw, prob._glo, prob._ghi)
        eg = np.exp(gamma)
        T = self.T
        T.flat[prob._tril_flat] = tv
        T.flat[prob._diag_flat] = eg
        mu, L, value, g_mu, g_L, g_Sigma = prob.prior_terms(first, T)
        fast_kl = self.whiten and prob.blocks is None
        F_true = None
        if prob.n_values:
            F = np.empty(prob.n_values)
            F_true = np.empty(prob.n_values)
            self._group_forward(mu, L)
            self._points_forward()
            # weight constraints and single constraints: the reference code
            parts = []
            if self.weights:
                Sigma = L @ L.T
                tail = prob.config.resolved_tail(True)
                for i in self.weights:
                    sl = prob.slices[i]
                    Fw, dmu, dS = prob.constraints[i].probability_w(mu, Sigma, tail=tail)
                    F[sl] = F_true[sl] = Fw
                    w = -lam[sl]
                    g_mu += w @ dmu
                    gS = np.tensordot(w, dS, axes=1)
                    g_Sigma = gS if g_Sigma is None else g_Sigma + gS
            for i in prob.single:
                m, S = prob._moments_of(i)
                c = prob.constraints[i]
                Ft, dm, dS = c.probability(m, S, prob.bound[i][0].group.times)
                sl = prob.slices[i]
                if c.reduce == 'max':
                    j = int(np.argmax(Ft))
                    F[sl] = F_true[sl] = Ft[j]
                    wt = np.zeros(Ft.size)
                    wt[j] = -lam[sl][0]
                else:
                    F[sl] = F_true[sl] = Ft
                    wt = -lam[sl]
                parts.append((prob.bound[i], wt, dm, dS))
            grads = [b.evaluate(F, F_true, lam) for b in self.batches]
            value += float(np.dot(lam, prob.alpha - F))
            for b, gr in zip(self.batches, grads):
                b.scatter(gr)
            for (pm, xs), wt, dm, dS in parts:
                pm.add_gradient(xs, wt[:, None] * dm, wt[:, None, None] * dS)
            self._points_backward()
            self._group_backward(g_mu, g_L)
        if g_Sigma is not None:
            g_L += (g_Sigma + g_Sigma.T) @ L
        tril, diag = prob._tril_flat, prob._diag_flat
        g_theta = np.empty(theta.size)
        if self.whiten:
            g_first = self.L0T @ g_mu
            g_T = self.L0T @ g_L
            if fast_kl:
                # 0.5 (|T|^2 + |nu|^2 - n) - sum(gamma), T's entries from theta directly
                value += 0.5 * (tv @ tv + eg @ eg + first @ first - n) - np.sum(gamma)
                g_first += first
                g_theta[n:n + nt] = g_T.flat[tril] + tv
                g_gamma = (g_T.flat[diag] + eg - 1.0 / eg) * eg
            else:
                g_theta[n:n + nt] = g_T.flat[tril]
                g_gamma = g_T.flat[diag] * eg
        else:
            g_first, g_T = g_mu, g_L
            g_theta[n:n + nt] = g_T.flat[tril]
            g_gamma = g_T.flat[diag] * eg
        g_gamma[graw != gamma] = 0.0                 # clipped: flat outside the box
        g_theta[:n] = g_first
        g_theta[n + nt:] = g_gamma
        return value, g_theta, F_true
