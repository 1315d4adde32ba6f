"""Probabilistic movement primitives (paper 003, Section II-A, Eq. 1-4).

A ProMP over ``n_dims`` degrees of freedom uses ``n_basis`` normalised Gaussian radial basis
functions of the phase s in [0, 1] per degree of freedom. The weight matrix w (n_dims x n_basis)
is stacked by rows: ``w = [w_1, ..., w_D]`` with w_d the weights of dimension d, so
``y_t[d] = phi(s_t) . w[d * M:(d + 1) * M]`` (Eq. 1). ``p(w) = N(mean_w, cov_w)``.

Times passed to the methods are phases s = t / duration in [0, 1].
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_positive


@dataclass(frozen=True)
class RbfBasis:
    """Normalised Gaussian RBFs in phase.

    b_i(s) = exp(-(s - c_i)^2 / (2 width^2)),  phi_i(s) = b_i(s) / sum_j b_j(s).

    Parameters
    ----------
    centers : tuple of float
        Centres c_i in phase units.
    width : float
        Standard deviation of every kernel in phase units.
    """
    centers: Tuple[float, ...]
    width: float

    def __post_init__(self):
        c = as_array('centers', self.centers, (None,))
        if c.size < 1:
            raise ValidationError('centers: expected at least one centre, got 0')
        object.__setattr__(self, 'centers', tuple(float(v) for v in c))
        check_positive('width', self.width)

    @classmethod
    def uniform(cls, n_basis: int, extension: float = 0.1) -> 'RbfBasis':
        """``n_basis`` centres evenly spaced over [-extension, 1 + extension], width = spacing
        (the basis of the paper's benchmark, see promp_benchmark_protocol.md)."""
        if int(n_basis) < 2:
            raise ValidationError(f'n_basis: expected an integer >= 2, got {n_basis!r}')
        c = np.linspace(-extension, 1.0 + extension, int(n_basis))
        return cls(tuple(c), float(c[1] - c[0]))

    @property
    def n_basis(self) -> int:
        return len(self.centers)

    def features(self, s: ArrayLike, derivative: int = 0) -> NDArray[np.float64]:
        """Normalised features or their phase derivatives.

        Parameters
        ----------
        s : array-like, shape (n,)
            Phases.
        derivative : {0, 1, 2}
            Order of the derivative d^k phi / ds^k.

        Returns
        -------
        ndarray, shape (n, n_basis)
        """
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        c = np.asarray(self.centers)
        h = self.width ** 2
        diff = s[:, None] - c[None, :]
        # shift the exponent for numerical safety (cancels in the normalisation)
        e = -0.5 * diff ** 2 / h
        b = np.exp(e - e.max(axis=1, keepdims=True))
        S0 = b.sum(axis=1, keepdims=True)
        phi = b / S0
        if derivative == 0:
            return phi
        r = -diff / h
        b1 = r * b
        S1 = b1.sum(axis=1, keepdims=True)
        phi1 = b1 / S0 - b * S1 / S0 ** 2
        if derivative == 1:
            return phi1
        if derivative == 2:
            b2 = (r * r - 1.0 / h) * b
            S2 = b2.sum(axis=1, keepdims=True)
            return (b2 / S0 - 2.0 * b1 * S1 / S0 ** 2 - b * S2 / S0 ** 2
                    + 2.0 * b * S1 ** 2 / S0 ** 3)
        raise ValidationError(f'derivative: expected 0, 1 or 2, got {derivative!r}')


class ProMP:
    """A ProMP p(w) = N(mean_w, cov_w) with observation noise variances ``sigma_y`` (Eq. 1-3).

    Parameters
    ----------
    n_dims : int
        Degrees of freedom D.
    basis : RbfBasis
        Basis shared by all dimensions (M functions).
    mean_w : array-like, shape (D * M,), optional
        Weight mean, stacked by rows (default zeros).
    cov_w : array-like, shape (D * M, D * M), optional
        Weight covariance (default identity).
    sigma_y : array-like, shape (D,), optional
        Observation noise variance per dimension (Sigma_y = diag(sigma_y), default 1e-6).
    duration : float
        Nominal duration [s] (phase s = t / duration).
    joint_names : sequence of str, optional
        One name per dimension (default ``dim0``, ``dim1``, ...).
    """
    kind = 'promp'

    def __init__(self, n_dims: int, basis: RbfBasis, mean_w: Optional[ArrayLike] = None,
                 cov_w: Optional[ArrayLike] = None, sigma_y: Optional[ArrayLike] = None,
                 duration: float = 1.0, joint_names: Optional[Sequence[str]] = None):
        if int(n_dims) < 1:
            raise ValidationError(f'n_dims: expected an integer >= 1, got {n_dims!r}')
        self.n_dims = int(n_dims)
        self.basis = basis
        n = self.n_weights
        self.mean_w = (np.zeros(n) if mean_w is None
                       else as_array('mean_w', mean_w, (n,)).copy())
        self.cov_w = (np.eye(n) if cov_w is None
                      else as_array('cov_w', cov_w, (n, n)).copy())
        if not np.allclose(self.cov_w, self.cov_w.T, rtol=1e-9, atol=1e-12):
            raise ValidationError('cov_w: expected a symmetric matrix, got an asymmetric one')
        self.cov_w = 0.5 * (self.cov_w + self.cov_w.T)
        self.sigma_y = (np.full(self.n_dims, 1e-6) if sigma_y is None
                        else as_array('sigma_y', sigma_y, (self.n_dims,)).copy())
        if np.any(self.sigma_y < 0):
            raise ValidationError(f'sigma_y: expected non-negative variances, got {self.sigma_y}')
        self.duration = check_positive('duration', duration)
        names = ([f'dim{i}' for i in range(self.n_dims)] if joint_names is None
                 else [str(n) for n in joint_names])
        if len(names) != self.n_dims or len(set(names)) != self.n_dims:
            raise ValidationError(f'joint_names: expected {self.n_dims} unique names, '
                                  f'got {names}')
        self.joint_names = names
        self.metadata = {}

    # ------------------------------------------------------------------ structure
    @property
    def n_basis(self) -> int:
        return self.basis.n_basis

    @property
    def n_weights(self) -> int:
        return self.n_dims * self.basis.n_basis

    def copy(self, mean_w: Optional[ArrayLike] = None,
             cov_w: Optional[ArrayLike] = None) -> 'ProMP':
        """A ProMP with the same basis and the given (or the same) weight distribution."""
        return ProMP(self.n_dims, self.basis,
                     self.mean_w if mean_w is None else mean_w,
                     self.cov_w if cov_w is None else cov_w, self.sigma_y, self.duration,
                     self.joint_names)

    def design(self, s: ArrayLike, derivative: int = 0) -> NDArray[np.float64]:
        """Block design matrices Psi_t with z_t = Psi_t w.

        Returns
        -------
        ndarray, shape (n, D, D * M)
        """
        phi = self.basis.features(s, derivative)
        n, M, D = phi.shape[0], self.n_basis, self.n_dims
        Psi = np.zeros((n, D, D * M))
        for d in range(D):
            Psi[:, d, d * M:(d + 1) * M] = phi
        return Psi

    # ------------------------------------------------------------------ moments
    def mean(self, s: ArrayLike, derivative: int = 0) -> NDArray[np.float64]:
        """Mean trajectory E[z_t] = mu_w phi_t, shape (n, D)."""
        phi = self.basis.features(s, derivative)
        return phi @ self.mean_w.reshape(self.n_dims, self.n_basis).T

    def cov(self, s: ArrayLike, derivative: int = 0) -> NDArray[np.float64]:
        """Marginal covariances Cov[z_t], shape (n, D, D) (without observation noise)."""
        Psi = self.design(s, derivative)
        return Psi @ self.cov_w @ np.swapaxes(Psi, 1, 2)

    def joint_cov(self, s: ArrayLike, derivative: int = 0) -> NDArray[np.float64]:
        """Full covariance of (z_{t_1}, ..., z_{t_n}) including cross-time and cross-joint
        terms, shape (n * D, n * D), index t * D + d."""
        Psi = self.design(s, derivative).reshape(-1, self.n_weights)
        return Psi @ self.cov_w @ Psi.T

    def sample_weights(self, n_samples: int, rng: np.random.Generator) -> NDArray[np.float64]:
        """Weight samples, shape (n_samples, D * M)."""
        A = _psd_sqrt(self.cov_w)
        return self.mean_w + rng.standard_normal((int(n_samples), self.n_weights)) @ A.T

    def sample_trajectories(self, s: ArrayLike, n_samples: int, rng: np.random.Generator,
                            noise: bool = False) -> NDArray[np.float64]:
        """Trajectory samples, shape (n_samples, n, D); ``noise`` adds Sigma_y (Eq. 1)."""
        phi = self.basis.features(s)
        W = self.sample_weights(n_samples, rng).reshape(-1, self.n_dims, self.n_basis)
        Y = np.einsum('tm,kdm->ktd', phi, W)
        if noise:
            Y = Y + rng.standard_normal(Y.shape) * np.sqrt(self.sigma_y)
        return Y

    # ------------------------------------------------------------------ conditioning
    def condition(self, s: ArrayLike, y: ArrayLike, var: ArrayLike = 1e-6,
                  yd: Optional[ArrayLike] = None, var_yd: ArrayLike = 1e-6) -> 'ProMP':
        """Condition on via-points (Gaussian conditioning in weight space) -> new ProMP.

        Parameters
        ----------
        s : array-like, shape (n,)
            Phases of the via-points.
        y : array-like, shape (n, D)
            Positions; NaN entries are not observed.
        var : float or array-like broadcastable to (n, D)
            Observation variances of the positions.
        yd : array-like, shape (n, D), optional
            Velocities [unit/s] (dy/dt = dy/ds / duration); NaN entries are not observed.
        var_yd : float or array-like broadcastable to (n, D)
            Observation variances of the velocities.
        """
        s = as_array('s', np.atleast_1d(s), (None,))
        y = as_array('y', np.atleast_2d(y), (s.size, self.n_dims), finite=False)
        rows = [self.design(s).reshape(-1, self.n_weights)]
        obs = [y.ravel()]
        variances = [np.broadcast_to(np.asarray(var, dtype=float), y.shape).ravel()]
        if yd is not None:
            yd = as_array('yd', np.atleast_2d(yd), (s.size, self.n_dims), finite=False)
            rows.append(self.design(s, 1).reshape(-1, self.n_weights) / self.duration)
            obs.append(yd.ravel())
            variances.append(np.broadcast_to(np.asarray(var_yd, dtype=float), yd.shape).ravel())
        H = np.concatenate(rows)
        o = np.concatenate(obs)
        r = np.concatenate(variances)
        keep = np.isfinite(o)
        H, o, r = H[keep], o[keep], r[keep]
        if np.any(r < 0):
            raise ValidationError('var: expected non-negative observation variances')
        PHt = self.cov_w @ H.T
        G = H @ PHt + np.diag(r)
        K = np.linalg.solve(G, PHt.T).T
        mean_w = self.mean_w + K @ (o - H @ self.mean_w)
        cov_w = self.cov_w - K @ PHt.T
        return self.copy(mean_w, 0.5 * (cov_w + cov_w.T))

    # ------------------------------------------------------------------ smoothness
    def smoothness_matrix(self, support: Tuple[float, float] = (0.0, 1.0),
                          joint_weights: Optional[ArrayLike] = None,
                          n_grid: int = 201) -> NDArray[np.float64]:
        """Matrix Phi_R of R(w) = w^T Phi_R w = sum_d kappa_d / |T| int_T |z_d''|^2 ds
        (Eq. 14, paper 003; second derivative in phase, trapezoidal integration).

        Returns
        -------
        ndarray, shape (D * M, D * M), block diagonal.
        """
        t0, t1 = float(support[0]), float(support[1])
        if not t1 > t0:
            raise ValidationError(f'support: expected t0 < t1, got {support}')
        kw = (np.ones(self.n_dims) if joint_weights is None
              else as_array('joint_weights', joint_weights, (self.n_dims,)))
        s = np.linspace(t0, t1, int(n_grid))
        phi2 = self.basis.features(s, 2)
        q = np.full(s.size, (t1 - t0) / (s.size - 1))
        q[[0, -1]] *= 0.5
        block = (phi2 * q[:, None]).T @ phi2 / (t1 - t0)
        return np.kron(np.diag(kw), block)

    # ------------------------------------------------------------------ learning
    @classmethod
    def fit(cls, demonstrations: Sequence[Tuple[ArrayLike, ArrayLike]], basis: RbfBasis,
            duration: Optional[float] = None, prior_cov: Optional[ArrayLike] = None,
            prior_strength: float = 1.0, noise_prior: Tuple[float, float] = (1.0, 1e-6),
            n_iter: int = 100, tol: float = 1e-6,
            joint_names: Optional[Sequence[str]] = None) -> 'ProMP':
        """Learn a ProMP from demonstrations by EM with MAP priors (Eq. 4 and its text).

        Each demonstration (T_i, Y_i) is phase-normalised, s = (T - T[0]) / (T[-1] - T[0]),
        so demonstrations may have different lengths and durations.

        Priors: Sigma_w ~ inverse-Wishart with mode ``prior_cov`` and ``prior_strength``
        pseudo-observations nu_0, which gives the M-step
        Sigma_w = (nu_0 prior_cov + sum_i [(m_i - mu)(m_i - mu)^T + C_i]) / (nu_0 + n);
        flat prior on mu_w; inverse-gamma (a0, b0) = ``noise_prior`` on each sigma_y[d]:
        sigma_y[d] = (b0 + 0.5 E[sum residual^2]) / (a0 + 1 + 0.5 n_obs). The prior keeps
        Sigma_w positive definite with fewer demonstrations than weights.

        Parameters
        ----------
        demonstrations : sequence of (T (n_i,), Y (n_i, D))
        basis : RbfBasis
        duration : float, optional
            Nominal duration (default: mean demonstration duration).
        prior_cov : array-like, shape (D * M, D * M), optional
            Mode of the inverse-Wishart prior (default: per-dimension data variance times I).
        """
        demos = []
        for i, (T, Y) in enumerate(demonstrations):
            T = as_array(f'demonstrations[{i}].T', T, (None,))
            Y = np.asarray(Y, dtype=float)
            Y = as_array(f'demonstrations[{i}].Y', Y.reshape(T.size, -1), (T.size, None))
            if T.size < 2 or not np.all(np.diff(T) > 0):
                raise ValidationError(f'demonstrations[{i}].T: expected >= 2 strictly '
                                      f'increasing times, got {T.size} samples')
            demos.append((T, Y))
        if not demos:
            raise ValidationError('demonstrations: expected at least one, got 0')
        D = demos[0][1].shape[1]
        for i, (_, Y) in enumerate(demos):
            if Y.shape[1] != D:
                raise ValidationError(f'demonstrations[{i}].Y: expected {D} columns, '
                                      f'got {Y.shape[1]}')
        M = basis.n_basis
        n = D * M
        stats = []
        for T, Y in demos:
            s = (T - T[0]) / (T[-1] - T[0])
            phi = basis.features(s)
            stats.append((phi.T @ phi, phi.T @ Y, np.sum(Y * Y, axis=0), T.size))
        if duration is None:
            duration = float(np.mean([T[-1] - T[0] for T, _ in demos]))
        all_Y = np.concatenate([Y for _, Y in demos])
        data_var = np.var(all_Y, axis=0) + 1e-6
        if prior_cov is None:
            prior_cov = np.kron(np.diag(data_var), np.eye(M))
        prior_cov = as_array('prior_cov', prior_cov, (n, n))
        nu0 = check_positive('prior_strength', prior_strength, allow_zero=True)
        a0, b0 = (float(v) for v in noise_prior)
        # initialisation: ridge regression per demonstration
        ridge = 1e-6 * np.eye(M)
        W0 = np.array([np.linalg.solve(PtP + ridge, PtY).T.ravel() for PtP, PtY, _, _ in stats])
        mu = W0.mean(axis=0)
        Sigma = prior_cov.copy()
        sig = 1e-2 * data_var
        prev = None
        for _ in range(int(n_iter)):
            Sinv = np.linalg.inv(Sigma)
            means, covs = [], []
            res = np.zeros(D)
            for PtP, PtY, yy, n_obs in stats:
                P = Sinv + np.kron(np.diag(1.0 / sig), PtP)
                C = np.linalg.inv(P)
                C = 0.5 * (C + C.T)
                m = C @ (Sinv @ mu + (PtY / sig).T.ravel())
                Wm = m.reshape(D, M)
                for d in range(D):
                    Cdd = C[d * M:(d + 1) * M, d * M:(d + 1) * M]
                    res[d] += (yy[d] - 2.0 * Wm[d] @ PtY[:, d] + Wm[d] @ PtP @ Wm[d]
                               + np.sum(PtP * Cdd))
                means.append(m)
                covs.append(C)
            means = np.array(means)
            mu = means.mean(axis=0)
            dev = means - mu
            scatter = dev.T @ dev + np.sum(covs, axis=0)
            Sigma = (nu0 * prior_cov + scatter) / (nu0 + len(stats))
            Sigma = 0.5 * (Sigma + Sigma.T)
            n_total = sum(st[3] for st in stats)
            sig = (b0 + 0.5 * res) / (a0 + 1.0 + 0.5 * n_total)
            cur = np.concatenate([mu, Sigma.ravel(), sig])
            if prev is not None and np.max(np.abs(cur - prev)) < tol * (1 + np.max(np.abs(cur))):
                break
            prev = cur
        return cls(D, basis, mu, Sigma, sig, duration, joint_names)


def _psd_sqrt(C: NDArray[np.float64]) -> NDArray[np.float64]:
    """A with A A^T = C for a symmetric PSD matrix (Cholesky, eigen-decomposition fallback)."""
    try:
        return np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        vals, vecs = np.linalg.eigh(C)
        return vecs * np.sqrt(np.clip(vals, 0.0, None))
