"""PI2 (paper 000, Eq. 32-39): projections, averaging, learning, and the limit guarantee."""
import numpy as np
import pytest

from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig, limit_usage
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.dmp.pi2 import Pi2, Pi2Config


def straight(n_dims=1, lo=-1.0, hi=1.0, n_w=8):
    T = np.linspace(0, 1, 101)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    Y = np.outer(s, np.linspace(0.5, 0.2, n_dims))
    cfg = DmpConfig(n_weights_per_dim=n_w)
    return T, Y, CDMP(np.full(n_dims, lo), np.full(n_dims, hi), cfg).fit(T, Y)


def test_projection_matches_explicit_matrix():
    """M_t = R^-1 g g^T / (g^T R^-1 g) with R = r I, applied per time step."""
    _, _, prim = straight(2)
    pi2 = Pi2(prim, Pi2Config(), rng=np.random.default_rng(0), dt=0.05)
    eps = np.random.default_rng(1).normal(size=(pi2.n_steps, 2, 8))
    got = pi2.projected_noise(eps)
    for t in (0, 5, pi2.n_steps - 1):
        g = pi2._G[t]
        M = np.outer(g, g) / (g @ g)
        for d in range(2):
            np.testing.assert_allclose(got[t, d], M @ eps[t, d], rtol=1e-10, atol=1e-14)


def test_update_matches_loop_implementation():
    """Eq. (34)-(39) by explicit loops over trials and time steps."""
    _, _, prim = straight(1)
    cfg = Pi2Config(n_rollouts=4, noise_per_step=True, control_cost=1e-3, noise_decay=1.0)
    pi2 = Pi2(prim, cfg, rng=np.random.default_rng(2), dt=0.05)
    trials = pi2.ask()
    rng = np.random.default_rng(3)
    costs = rng.uniform(0, 1, (4, pi2.n_steps))
    w_before = prim.weights_.copy()
    g_before = prim.to_internal(prim.goal_y_)
    pi2.tell(costs)
    K, N, W = 4, pi2.n_steps, 8
    S = np.zeros((K, N))
    Me = np.zeros((K, N, W))
    for k in range(K):
        for t in range(N):
            g = pi2._G[t]
            Me[k, t] = np.outer(g, g) @ trials[k].shape_noise[t, 0] / (g @ g)
    for k in range(K):
        for i in range(N):
            S[k, i] = costs[k, i:].sum()
            for j in range(i + 1, N):
                th = w_before[0] + Me[k, j]
                S[k, i] += 0.5 * 1e-3 * th @ th
    P = np.zeros((K, N))
    for i in range(N):
        e = np.exp(-10 * (S[:, i] - S[:, i].min()) / (S[:, i].max() - S[:, i].min()))
        P[:, i] = e / e.sum()
    dth_t = np.einsum('kt,ktw->tw', P, Me)
    num = np.zeros(W)
    den = np.zeros(W)
    for i in range(N):
        psi = pi2._psi[i]
        num += (N - i) * psi * dth_t[i]
        den += (N - i) * psi
    np.testing.assert_allclose(prim.weights_[0], w_before[0] + num / den, rtol=1e-9)
    d_goal = sum(P[k, 0] * trials[k].goal_noise for k in range(K))
    np.testing.assert_allclose(prim.to_internal(prim.goal_y_), g_before + d_goal, rtol=1e-9,
                               atol=1e-12)


def test_learning_reduces_cost_via_point_and_goal():
    """Pass through a via point at t = 0.5 and end at a new goal: cost falls by > 80 %."""
    _, _, prim = straight(1, n_w=10)
    target_mid, target_end = 0.6, 0.35

    def cost(tr):
        c = np.zeros(len(tr.T))
        c[len(tr.T) // 2] = 1e3 * (tr.Y[len(tr.T) // 2, 0] - target_mid) ** 2
        c[-1] = 1e3 * (tr.Y[-1, 0] - target_end) ** 2
        c += 1e-5 * tr.Ydd[:, 0] ** 2
        return c

    pi2 = Pi2(prim, Pi2Config(n_rollouts=8, shape_std=100.0, goal_std=0.2, noise_decay=0.97),
              rng=np.random.default_rng(4), dt=0.02)
    first = cost(prim.rollout(dt=0.02)).sum()
    for _ in range(60):
        pi2.tell([cost(t.trajectory) for t in pi2.ask()])
    last = cost(prim.rollout(dt=0.02)).sum()
    assert last < 0.2 * first, (first, last)


def test_exploration_never_leaves_limits_for_cdmp_but_does_for_dmp():
    T, Y, cdmp = straight(3, lo=-0.6, hi=0.7)
    dmp = DMP(3, cdmp.config).fit(T, Y)
    cfg = Pi2Config(n_rollouts=10, shape_std=400.0, goal_std=1.0, noise_per_step=True)
    viol = {}
    for name, prim in (('cdmp', cdmp), ('dmp', dmp)):
        pi2 = Pi2(prim, cfg, rng=np.random.default_rng(5), dt=0.01)
        viol[name] = 0
        for _ in range(5):
            trials = pi2.ask()
            viol[name] += sum(limit_usage(t.trajectory.Y, cdmp.y_min, cdmp.y_max) >= 1.0
                              for t in trials)
            pi2.tell([np.abs(t.trajectory.Y).sum(axis=1) for t in trials])
    assert viol['cdmp'] == 0
    assert viol['dmp'] > 10


def test_config_and_usage_errors():
    with pytest.raises(ValidationError, match='n_rollouts'):
        Pi2Config(n_rollouts=1)
    with pytest.raises(ValidationError, match='noise_decay'):
        Pi2Config(noise_decay=0.0)
    _, _, prim = straight(1)
    with pytest.raises(ValidationError, match='rng'):
        Pi2(prim)
    pi2 = Pi2(prim, rng=np.random.default_rng(0))
    with pytest.raises(ValidationError, match='ask'):
        pi2.tell([])
    pi2.ask()
    with pytest.raises(ValidationError, match='costs'):
        pi2.tell(np.zeros((3, 2)))
