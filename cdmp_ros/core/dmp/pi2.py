"""PI2 (Policy Improvement with Path Integrals) for DMP/CDMP shape and goal (paper 000, III-C).

Ask/tell interface::

    pi2 = Pi2(prim, Pi2Config(), rng=np.random.default_rng(0), dt=0.01)
    for update in range(n_updates):
        trials = pi2.ask()                       # K exploratory rollouts
        costs = [cost_fn(t.trajectory) for t in trials]   # (n_steps,) each
        pi2.tell(costs)                          # Eq. 34-39 update of prim

Exploration happens on the internal parameters: for a CDMP the shape weights and the goal live
in the exogenous space, so every exploratory rollout respects the joint limits (Eq. 32-33).

Costs: ``cost_fn`` returns the immediate cost ``r_t`` per time step with the terminal cost
``phi_N`` added to the last entry. The control cost of Eq. 34,
``0.5 (theta + M_t eps_t)^T R (theta + M_t eps_t)`` with ``R = control_cost * I``, is added
here. The temperature ``lambda`` is set from the cost range per time step:
``P_i,k = exp(-h (S_i,k - min_k S_i,k) / (max_k S_i,k - min_k S_i,k))`` normalised over k.
"""
from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.dmp.dmp import Trajectory
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_positive


@dataclass(frozen=True)
class Pi2Config:
    """Settings of PI2.

    Attributes
    ----------
    n_rollouts : int
        Trials per update (K).
    shape_std : float
        Standard deviation of the exploration noise on the shape weights (internal units).
    goal_std : float
        Standard deviation of the goal exploration noise (internal units); 0 disables goal
        learning.
    h : float
        Sharpness of the cost-to-probability map (lambda from the cost range).
    control_cost : float
        R = control_cost * I in Eq. 34.
    noise_decay : float
        Factor applied to both standard deviations after every update (1 = constant).
    noise_per_step : bool
        Draw a new shape noise at every time step (Eq. 32 literally) instead of once per trial
        (the common practice: smoother exploratory trajectories; the projection M_t is applied
        per time step either way).
    n_reuse : int
        Importance sampling by re-using the ``n_reuse`` lowest-cost trials of earlier updates
        (Theodorou et al., JMLR 2010, the PI2 paper's "re-use of the best roll-outs"): every
        update then averages over the K new trials plus these, whose noise is re-expressed
        relative to the current parameters and whose costs are kept (the rollouts must be
        deterministic functions of the parameters). 0 (default) is plain PI2.
    """

    n_rollouts: int = 5
    shape_std: float = 20.0
    goal_std: float = 0.05
    h: float = 10.0
    control_cost: float = 1e-6
    noise_decay: float = 0.98
    noise_per_step: bool = False
    n_reuse: int = 0

    def __post_init__(self):
        if not isinstance(self.n_rollouts, (int, np.integer)) or self.n_rollouts < 2:
            raise ValidationError(f'n_rollouts: expected an integer >= 2, got '
                                  f'{self.n_rollouts!r}')
        if (isinstance(self.n_reuse, bool) or not isinstance(self.n_reuse, (int, np.integer))
                or self.n_reuse < 0):
            raise ValidationError(f'n_reuse: expected an integer >= 0, got {self.n_reuse!r}')
        check_positive('shape_std', self.shape_std, allow_zero=True)
        check_positive('goal_std', self.goal_std, allow_zero=True)
        check_positive('h', self.h)
        check_positive('control_cost', self.control_cost, allow_zero=True)
        if not (0.0 < self.noise_decay <= 1.0):
            raise ValidationError(f'noise_decay: expected 0 < noise_decay <= 1, got '
                                  f'{self.noise_decay!r}')


@dataclass
class Trial:
    """One exploratory rollout: its noise and the resulting trajectory."""

    shape_noise: NDArray[np.float64]  # (n_steps, n_dims, n_weights)
    goal_noise: NDArray[np.float64]   # (n_dims,) internal units
    trajectory: Trajectory


class Pi2:
    """PI2 on a fitted :class:`~cdmp_ros.core.dmp.dmp.DMP` or ``CDMP`` (updated in place).

    Parameters
    ----------
    prim : DMP or CDMP
        Fitted primitive; its weights and goal are improved by :meth:`tell`.
    config : Pi2Config
    rng : numpy.random.Generator
    dt : float
        Rollout step [s].
    duration : float, optional
        Rollout duration (default the primitive's tau).
    rollout_kwargs : dict, optional
        Extra arguments of :meth:`DMP.rollout` (start_y, coupling, ...).
    """

    def __init__(self, prim, config: Optional[Pi2Config] = None,
                 rng: Optional[np.random.Generator] = None, dt: float = 0.01,
                 duration: Optional[float] = None, rollout_kwargs: Optional[dict] = None):
        prim._check_fitted()
        if rng is None:
            raise ValidationError('rng: expected a numpy.random.Generator (explicit seeding)')
        self.prim = prim
        self.config = config if config is not None else Pi2Config()
        self.rng = rng
        self.dt = check_positive('dt', dt)
        self.duration = prim.tau_ if duration is None else check_positive('duration', duration)
        self.rollout_kwargs = dict(rollout_kwargs or {})
        self.n_steps = int(round(self.duration / self.dt)) + 1
        u = np.arange(self.n_steps) * self.dt / prim.tau_
        self._G = prim.basis.features(u)  # g_t up to a per-dim scalar, (n_steps, n_w)
        s = prim.basis.phase(u)[:, None]
        self._psi = np.exp(-0.5 * prim.basis.widths * (s - prim.basis.centers) ** 2)
        self.shape_std = self.config.shape_std
        self.goal_std = self.config.goal_std
        self._trials: Optional[List[Trial]] = None
        self.n_updates = 0
        # re-used trials (n_reuse > 0): absolute shape parameters (n, N, D, W), absolute
        # internal goals (n, D) and per-step costs (n, N)
        self._elite: Optional[tuple] = None

    # -- exploration ---------------------------------------------------------------------------
    def ask(self) -> List[Trial]:
        """Draw K noisy parameter sets and roll them out (Eq. 32-33)."""
        cfg, prim = self.config, self.prim
        K, N, D, W = cfg.n_rollouts, self.n_steps, prim.n_dims, prim.weights_.shape[1]
        if cfg.noise_per_step:
            eps = self.rng.normal(0.0, self.shape_std, (K, N, D, W))
        else:
            eps = np.broadcast_to(self.rng.normal(0.0, self.shape_std, (K, 1, D, W)),
                                  (K, N, D, W)).copy()
        g_eps = self.rng.normal(0.0, self.goal_std, (K, D)) if self.goal_std > 0 else \
            np.zeros((K, D))
        trials = []
        for k in range(K):
            tr = prim.rollout(dt=self.dt, duration=self.duration, weight_noise=eps[k],
                              goal_noise=g_eps[k], **self.rollout_kwargs)
            trials.append(Trial(eps[k], g_eps[k], tr))
        self._trials = trials
        return trials

    def projected_noise(self, eps: ArrayLike) -> NDArray[np.float64]:
        """``M_t eps_t`` with ``M_t = R^-1 g_t g_t^T / (g_t^T R^-1 g_t)``, R = r I (Eq. 34).

        eps : (..., n_steps, n_dims, n_weights) -> same shape.
        """
        G = self._G
        gg = np.maximum(np.einsum('tw,tw->t', G, G), 1e-300)
        proj = np.einsum('tw,...tdw->...td', G, np.asarray(eps)) / gg[:, None]
        return proj[..., None] * G[:, None, :]

    # -- update --------------------------------------------------------------------------------
    def tell(self, costs: Sequence[ArrayLike]) -> dict:
        """Update the primitive from the per-step costs of the last :meth:`ask` (Eq. 34-39).

        Returns a summary: mean and min total cost of the trials, and the update norms.
        """
        if self._trials is None:
            raise ValidationError('tell: call ask() first')
        cfg, prim = self.config, self.prim
        K, N = cfg.n_rollouts, self.n_steps
        R = as_array('costs', costs, (K, N))
        eps = np.stack([t.shape_noise for t in self._trials])   # (K, N, D, W)
        g_eps = np.stack([t.goal_noise for t in self._trials])  # (K, D)
        g_now = prim.to_internal(prim.goal_y_)
        if self._elite is not None:  # importance sampling: noise relative to the current mean
            e_theta, e_goal, e_cost = self._elite
            eps = np.concatenate([eps, e_theta - prim.weights_[None, None]])
            g_eps = np.concatenate([g_eps, e_goal - g_now[None]])
            R = np.concatenate([R, e_cost])
        Meps = self.projected_noise(eps)                         # (K, N, D, W)
        theta = prim.weights_[None, None] + Meps
        control = 0.5 * cfg.control_cost * np.einsum('ktdw,ktdw->kt', theta, theta)
        # Eq. (34): cost-to-go S_i = sum_{j>=i} r_j + phi_N + 0.5 sum_{j>i} (..)^T R (..)
        S = np.flip(np.cumsum(np.flip(R, 1), 1), 1)
        ctrl_to_go = np.flip(np.cumsum(np.flip(control, 1), 1), 1)
        S = S + ctrl_to_go - control
        P = self.probabilities(S)                                # (K, N)
        if cfg.n_reuse > 0:
            best = np.argsort(S[:, 0], kind='stable')[:cfg.n_reuse]
            self._elite = (prim.weights_[None, None] + eps[best], g_now[None] + g_eps[best],
                           R[best].copy())
        # Eq. (35): dtheta_i = sum_k P_ik M_ik eps_ik
        d_theta_t = np.einsum('kt,ktdw->tdw', P, Meps)
        # Eq. (36): time-weighted average with (N - i) psi_j(t_i)
        weights = (N - np.arange(N))[:, None] * self._psi         # (N, W)
        d_theta = np.einsum('tw,tdw->dw', weights, d_theta_t) / np.maximum(
            weights.sum(axis=0), 1e-300)
        prim.weights_ = prim.weights_ + d_theta                   # Eq. (37)
        # Eq. (38)-(39): goal update with the probabilities at the start
        d_goal = P[:, 0] @ g_eps
        if self.goal_std > 0:
            g_int = prim.to_internal(prim.goal_y_) + d_goal
            prim.goal_y_ = prim.from_internal(g_int, np.zeros_like(g_int),
                                              np.zeros_like(g_int))[0]
        self.shape_std *= cfg.noise_decay
        self.goal_std *= cfg.noise_decay
        self.n_updates += 1
        self._trials = None
        totals = S[:K, 0]
        return {'mean_cost': float(np.mean(totals)), 'min_cost': float(np.min(totals)),
                'd_theta_norm': float(np.linalg.norm(d_theta)),
                'd_goal_norm': float(np.linalg.norm(d_goal))}

    def probabilities(self, S: ArrayLike) -> NDArray[np.float64]:
        """``P(tau_i,k)``: softmax over trials of ``-h`` times the range-normalised cost."""
        S = np.asarray(S, dtype=np.float64)
        lo = S.min(axis=0, keepdims=True)
        rng = np.maximum(S.max(axis=0, keepdims=True) - lo, 1e-12)
        E = np.exp(-self.config.h * (S - lo) / rng)
        return E / E.sum(axis=0, keepdims=True)
