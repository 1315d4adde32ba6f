"""PI2 options beyond paper 000's Eq. 32-39: re-use of the best earlier trials (n_reuse)."""
import numpy as np
import pytest

from cdmp_ros.core.dmp.dmp import CDMP, DmpConfig
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.dmp.pi2 import Pi2, Pi2Config


def straight(n_dims=2, n_w=6):
    T = np.linspace(0, 1, 101)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    Y = np.outer(s, np.linspace(0.5, 0.2, n_dims))
    cfg = DmpConfig(n_weights_per_dim=n_w)
    return CDMP(np.full(n_dims, -1.0), np.full(n_dims, 1.0), cfg).fit(T, Y)


def plain_update(pi2, w, g_int, eps, g_eps, R, h=10.0):
    """Independent Eq. (34)-(39) over an explicit set of trials (control cost 0)."""
    K, N = R.shape
    S = np.flip(np.cumsum(np.flip(R, 1), 1), 1)
    P = np.exp(-h * (S - S.min(0)) / (S.max(0) - S.min(0)))
    P /= P.sum(0)
    G = pi2._G
    gg = np.einsum('tw,tw->t', G, G)[None, :, None, None]
    Me = np.einsum('tw,tv,ktdv->ktdw', G, G, eps) / gg
    dth_t = np.einsum('kt,ktdw->tdw', P, Me)
    wt = (N - np.arange(N))[:, None] * pi2._psi
    dth = np.einsum('tw,tdw->dw', wt, dth_t) / wt.sum(0)
    return w + dth, g_int + P[:, 0] @ g_eps


def test_default_is_plain_pi2():
    assert Pi2Config().n_reuse == 0
    runs = []
    for cfg in (Pi2Config(n_rollouts=3), Pi2Config(n_rollouts=3, n_reuse=0)):
        prim = straight()
        pi2 = Pi2(prim, cfg, rng=np.random.default_rng(4), dt=0.05)
        for u in range(3):
            pi2.ask()
            pi2.tell(np.random.default_rng(u).uniform(0, 1, (3, pi2.n_steps)))
        runs.append((prim.weights_.copy(), prim.goal_y_.copy()))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


@pytest.mark.parametrize('bad', [-1, 1.5, True, '2'])
def test_n_reuse_validated(bad):
    with pytest.raises(ValidationError, match='n_reuse'):
        Pi2Config(n_reuse=bad)


def test_reused_trials_enter_the_next_update_relative_to_the_new_mean():
    """Update 2 = plain PI2 over its K new trials plus the n_reuse best of update 1, whose
    absolute parameters and costs are kept and whose noise is taken from the updated mean."""
    K, n_reuse = 4, 2
    prim = straight()
    cfg = Pi2Config(n_rollouts=K, n_reuse=n_reuse, control_cost=0.0, noise_decay=1.0,
                    goal_std=0.1, shape_std=5.0)
    pi2 = Pi2(prim, cfg, rng=np.random.default_rng(7), dt=0.05)
    rng = np.random.default_rng(8)
    N = pi2.n_steps
    # update 1: reference computation on the K trials alone
    w0, g0 = prim.weights_.copy(), prim.to_internal(prim.goal_y_)
    t1 = pi2.ask()
    R1 = rng.uniform(0, 1, (K, N))
    eps1 = np.stack([t.shape_noise for t in t1])
    geps1 = np.stack([t.goal_noise for t in t1])
    w1, g1 = plain_update(pi2, w0, g0, eps1, geps1, R1)
    pi2.tell(R1)
    np.testing.assert_allclose(prim.weights_, w1, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(prim.to_internal(prim.goal_y_), g1, rtol=1e-9, atol=1e-12)
    best = np.argsort(R1.sum(1))[:n_reuse]
    # update 2: K new trials + the 2 best of update 1 (absolute parameters, stored costs)
    t2 = pi2.ask()
    assert len(t2) == K  # still K new rollouts per update
    R2 = rng.uniform(0, 1, (K, N))
    eps2 = np.concatenate([np.stack([t.shape_noise for t in t2]), w0 + eps1[best] - w1])
    geps2 = np.concatenate([np.stack([t.goal_noise for t in t2]), g0 + geps1[best] - g1])
    w2, g2 = plain_update(pi2, w1, g1, eps2, geps2, np.concatenate([R2, R1[best]]))
    pi2.tell(R2)
    np.testing.assert_allclose(prim.weights_, w2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(prim.to_internal(prim.goal_y_), g2, rtol=1e-9, atol=1e-12)


def test_a_rare_success_is_kept_when_the_next_trials_all_fail():
    """A binary task (final position inside a narrow window): once one trial succeeds, the
    re-used success keeps the mean inside the window; plain PI2 drifts out again."""
    def finals(n_reuse, seed):
        prim = straight(1)
        cfg = Pi2Config(n_rollouts=5, n_reuse=n_reuse, shape_std=0.0, goal_std=0.25,
                        noise_decay=1.0, control_cost=0.0)
        pi2 = Pi2(prim, cfg, rng=np.random.default_rng(seed), dt=0.05)
        inside, found = [], []
        for _ in range(15):
            trials = pi2.ask()
            costs = []
            for t in trials:
                c = np.zeros(pi2.n_steps)
                y = t.trajectory.Y[-1, 0]
                # a weak pull away from the window plus a miss indicator
                c[-1] = 0.1 * y + 100.0 * (not 0.40 < y < 0.46)
                costs.append(c)
                found.append(c[-1] < 50.0)
            pi2.tell(costs)
            mean_end = prim.rollout(dt=0.05).Y[-1, 0]
            inside.append((any(found), 0.40 < mean_end < 0.46))
        return inside
    kept = [finals(2, s) for s in range(8)]
    plain = [finals(0, s) for s in range(8)]
    # with re-use, after the first successful trial the mean stays inside the window
    for run in kept:
        assert all(ok for found, ok in run if found), run
    assert sum(r[-1][1] for r in kept) >= 6
    assert sum(r[-1][1] for r in kept) > sum(r[-1][1] for r in plain)
