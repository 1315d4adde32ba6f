"""Importance sampling of a sphere's per-step violation (core/adaptation/tail_sampling.py) and
the check of the Gamma-matched rows that uses it (AdaptationConfig.check_law 'sampled', the
default): each estimate against plain Monte Carlo with many more draws (a linear point, whose
law is a 3-D Gaussian, and points through the Panda's kinematics), the standard error against
the spread of independent estimates, and a solve whose link rows the sampled check corrected,
against 200,000 trajectories put through the kinematics."""
import dataclasses

import numpy as np
import pytest

from cdmp_ros.core.adaptation.config import SAMPLED_CHECK_FRACTION, SAMPLED_CHECK_LAW, \
    AdaptationConfig
from cdmp_ros.core.adaptation.constraints import ChainPoint, DofPoint
from cdmp_ros.core.adaptation.problem import Problem
from cdmp_ros.core.adaptation.solver import monte_carlo_satisfaction, solve_levels
from cdmp_ros.core.adaptation.tail_sampling import (NOMINAL_FRACTION, RAY_BITS, centre_points,
                                                    ray_points, sphere_violation)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain
from cdmp_ros.core.promp.gaussian import batched_cholesky
from cdmp_ros.experiments.promp_problems import panda_problem
from cdmp_ros.sim.robot_specs import panda_urdf_path


@pytest.fixture(scope='module')
def chain():
    return panda_chain(panda_urdf_path())


def _gaussian(rng, k):
    A = rng.standard_normal((k, k))
    return rng.standard_normal(k), 0.02 * (A @ A.T + k * np.eye(k))


def _plain(point, m, S, center, r, inside, n, rng):
    """Plain Monte Carlo: the violation frequency of ``n`` draws and its standard error."""
    Z = rng.multivariate_normal(m, S, size=n)
    d = np.linalg.norm(point.forward(Z) - center, axis=-1)
    p = float(np.mean(d > r if inside else d < r))
    return p, np.sqrt(max(p, 1.0 / n) * (1.0 - p) / n)


def _linear_case(rng, inside):
    """A 3-D linear point, and a ball around which the violation is ~1e-3."""
    m, S = _gaussian(rng, 3)
    point = DofPoint((0, 1, 2))
    Z = rng.multivariate_normal(m, S, size=200_000)  # only to place the ball
    if inside:   # a waypoint ball around the mean: violated outside
        return point, m, S, m, float(np.quantile(np.linalg.norm(Z - m, axis=1), 0.999))
    e = rng.standard_normal(3)
    c = m + 1.5 * np.sqrt(np.trace(S)) * e / np.linalg.norm(e)
    return point, m, S, c, float(np.quantile(np.linalg.norm(Z - c, axis=1), 1e-3))


@pytest.mark.parametrize('inside', [False, True], ids=['repeller', 'waypoint'])
def test_a_linear_points_estimate_agrees_with_plain_sampling(rng, inside):
    point, m, S, c, r = _linear_case(rng, inside)
    est = sphere_violation(point, m[None], S[None], c[None], np.array([r * r]),
                           np.array([inside]), rng.standard_normal((2048, 3)))
    p, se = _plain(point, m, S, c, r, inside, 4_000_000, rng)
    assert 5e-4 < p < 2e-3
    assert abs(est.p[0] - p) <= 4.0 * np.hypot(est.se[0], se), (est, p, se)
    if not inside:
        # importance sampling earns its keep: 2,048 draws, a standard error plain sampling
        # needs ten times as many draws for (a waypoint violated all around its mean gains
        # nothing from one shifted proposal: the check samples repeller rows only)
        assert est.se[0] < np.sqrt(p * (1.0 - p) / 20_480)


def test_the_standard_error_matches_the_spread_of_independent_estimates(rng):
    point, m, S, c, r = _linear_case(rng, False)
    p, se_plain = _plain(point, m, S, c, r, False, 4_000_000, rng)
    draws = [sphere_violation(point, m[None], S[None], c[None], np.array([r * r]),
                              np.array([False]), rng.standard_normal((1024, 3)))
             for _ in range(200)]
    ps = np.array([d.p[0] for d in draws])
    ses = np.array([d.se[0] for d in draws])
    # the spread of the estimates is what their standard errors say (mean of 200: +-10 %)
    ratio = ps.std(ddof=1) / np.sqrt(np.mean(ses ** 2))
    assert 0.8 < ratio < 1.25, ratio
    # and they centre on the truth (the mean of 200 estimates: its own error + the oracle's)
    assert abs(ps.mean() - p) <= 4.0 * np.hypot(ps.std(ddof=1) / np.sqrt(ps.size), se_plain)


@pytest.mark.parametrize('link', ['ee', 'panda_link4', 'panda_hand'])
def test_a_panda_link_points_estimate_agrees_with_plain_sampling(chain, rng, link):
    prior, _, _ = panda_problem(chain, np.random.default_rng(3), n_spheres=1)
    s = np.array([0.5])
    m, S = prior.mean(s)[0], prior.cov(s)[0]
    point = ChainPoint(chain, PointOfInterest(link))
    # a sphere 2.5 point-standard-deviations off the mean's point, its radius the 2e-3
    # quantile of the distance (placed with draws of their own)
    Z = rng.multivariate_normal(m, S, size=100_000)
    X = point.forward(Z)
    e = rng.standard_normal(3)
    c = X.mean(axis=0) + 2.5 * np.sqrt(np.trace(np.cov(X.T))) * e / np.linalg.norm(e)
    r = float(np.quantile(np.linalg.norm(X - c, axis=1), 2e-3))
    est = sphere_violation(point, m[None], S[None], c[None], np.array([r * r]),
                           np.array([False]), rng.standard_normal((1024, m.size)))
    p, se = _plain(point, m, S, c, r, False, 1_000_000, rng)
    assert 5e-4 < p < 5e-3
    assert abs(est.p[0] - p) <= 4.0 * np.hypot(est.se[0], se), (est, p, se)
    assert est.se[0] < 0.35 * est.p[0]
    # the proposal's centre lies on the ray to the most probable u whose point is c
    uc = centre_points(point, m[None], batched_cholesky(S[None]), c[None])[0]
    cos = est.u[0] @ uc / (np.linalg.norm(est.u[0]) * np.linalg.norm(uc))
    assert cos == pytest.approx(1.0)


def test_the_ray_enters_the_ball_where_the_closed_form_says(rng):
    """A linear point (x = z): the most probable u at the centre is C^-1 (c - m), the ray
    m + t (c - m) enters the ball |x - c| < r at t = 1 - r / |c - m| (closed form). The
    multisection brackets it from inside within 2^-RAY_BITS; rows whose mean is in the ball
    stay at u = 0; several rows at once (different radii and Cholesky factors)."""
    n = 6
    ms, Ss, cs, r2 = [], [], [], []
    for i in range(n):   # nearly isotropic: the centre within MAX_SHIFT standard deviations
        A = 0.1 * rng.standard_normal((3, 3))
        m, S = rng.standard_normal(3), 0.02 * (np.eye(3) + A @ A.T)
        e = rng.standard_normal(3)
        dist = (1.0 + 0.5 * i) * np.sqrt(np.trace(S))
        r = (0.1 + 0.15 * i) * dist if i < n - 1 else 1.5 * dist   # last row: mean inside
        ms.append(m), Ss.append(S), cs.append(m + dist * e / np.linalg.norm(e))
        r2.append(r * r)
    m, S, c, r2 = np.array(ms), np.array(Ss), np.array(cs), np.array(r2)
    C = batched_cholesky(S)
    point = DofPoint((0, 1, 2))
    u = ray_points(point, m, C, c, r2, np.ones(n))
    uc = centre_points(point, m, C, c)
    assert np.allclose(np.einsum('nij,nj->ni', C, uc), c - m, atol=1e-9)
    for i in range(n - 1):
        dist = np.linalg.norm(c[i] - m[i])
        t_entry = 1.0 - np.sqrt(r2[i]) / dist
        t = (u[i] @ uc[i]) / (uc[i] @ uc[i])
        assert t_entry < t <= t_entry + 2.0 ** -RAY_BITS + 1e-12, (i, t, t_entry)
        assert np.allclose(u[i], t * uc[i])
    assert np.all(u[n - 1] == 0.0)


def test_a_mean_inside_the_repeller_is_sampled_without_a_shift(rng):
    point = DofPoint((0, 1, 2))
    m, S = _gaussian(rng, 3)
    r = 1.0 * np.sqrt(np.trace(S))
    est = sphere_violation(point, m[None], S[None], m[None], np.array([r * r]),
                           np.array([False]), rng.standard_normal((4096, 3)))
    assert np.all(est.u == 0.0)
    p, se = _plain(point, m, S, m, r, False, 1_000_000, rng)
    assert abs(est.p[0] - p) <= 4.0 * np.hypot(est.se[0], se)


def test_bad_draws_are_refused(rng):
    point = DofPoint((0, 1))
    m, S = _gaussian(rng, 2)
    for normals in (np.zeros((100, 3)), np.zeros((4, 2)), np.zeros(100)):
        with pytest.raises(ValidationError, match='normals'):
            sphere_violation(point, m[None], S[None], m[None], np.ones(1), np.zeros(1, bool),
                             normals)
    with pytest.raises(ValidationError, match='S: expected'):
        sphere_violation(point, m[None], S, m[None], np.ones(1), np.zeros(1, bool),
                         np.zeros((100, 2)))
    with pytest.raises(ValidationError, match='check_law'):
        AdaptationConfig(check_law='exact')
    for bad in (8, 1 << 20, 10.5, True):
        with pytest.raises(ValidationError, match='check_samples'):
            AdaptationConfig(check_samples=bad)


def test_the_sampled_check_reads_the_estimate_plus_its_error_near_the_level(chain, rng):
    prior, cons, cfg = panda_problem(chain, np.random.default_rng(1), n_spheres=3)
    assert cfg.check_law == 'sampled'
    prob = Problem(prior, cons, cfg)
    saddle = Problem(prior, cons, dataclasses.replace(cfg, check_law='saddlepoint'))
    theta = prob.initial_theta() + 0.05 * rng.standard_normal(prob.initial_theta().size)
    F, checked = prob.check_values(theta)
    F_s, checked_s = saddle.check_values(theta)
    assert np.array_equal(checked, checked_s) and checked.any()
    assert np.array_equal(F, prob.check_values(theta)[0])       # the same draws every time
    mu, L, _ = prob.unpack(theta)
    n_sampled = 0
    for i, (c, sl) in enumerate(zip(prob.constraints, prob.slices)):
        if c.kind == 'joint_limit':
            assert np.array_equal(F[sl], F_s[sl])
            continue
        times = prob.bound[i][0].group.times
        near = ((1.0 - F_s[sl]) >= SAMPLED_CHECK_FRACTION * (1.0 - c.alpha)) & \
            ~c.rows(times)['inside']
        assert np.array_equal(F[sl][~near], F_s[sl][~near])      # far rows: the saddle point
        if not near.any():
            continue
        # near repeller rows: recomputed from the ProMP's own marginals and the constraint
        times = times[near]
        adapted = prior.copy(mu, L @ L.T)
        rows = c.rows(times)
        est = sphere_violation(c.point, adapted.mean(times), adapted.cov(times),
                               rows['center'], rows['r2'], rows['inside'],
                               prob._check_normals(len(c.point.dofs)))
        np.testing.assert_allclose(F[sl][near], 1.0 - np.minimum(est.p + est.se, 1.0),
                                   rtol=0, atol=1e-9)
        n_sampled += int(near.sum())
    assert n_sampled > 0


def test_a_solve_with_the_sampled_check_keeps_every_link_step_within_its_level(chain):
    prior, cons, cfg = panda_problem(chain, np.random.default_rng(1), n_spheres=3)
    plain, rep0 = solve_levels(prior, cons, dataclasses.replace(cfg, max_level_corrections=0))
    fixed, rep = solve_levels(prior, cons, cfg)
    assert rep.converged and rep.n_level_corrections >= 1
    assert {c.law for c in rep.constraints if c.kind != 'joint_limit'} == {SAMPLED_CHECK_LAW}
    assert all(c.checked and c.satisfied for c in rep.constraints if c.kind != 'joint_limit')
    assert 'corrected by importance sampling' in rep.to_text()
    links = [c for c in cons if c.kind != 'joint_limit']
    S0 = monte_carlo_satisfaction(plain, links, 200_000, np.random.default_rng(5), cfg.n_steps)[0]
    S = monte_carlo_satisfaction(fixed, links, 200_000, np.random.default_rng(5), cfg.n_steps)[0]
    # the Gamma match alone: too light; corrected by the sampled check: within 1 - alpha
    assert 1.0 - S.min() <= 1.0 - 0.999 < 1.0 - S0.min()
    # and not far below it: the binding step sits at 0.5-1.0 of its level
    assert 1.0 - S.min() >= 0.5 * (1.0 - 0.999)


def test_the_check_draws_have_the_configured_size(chain):
    prior, cons, cfg = panda_problem(chain, np.random.default_rng(1), n_spheres=1)
    prob = Problem(prior, cons, dataclasses.replace(cfg, check_samples=64))
    draws = prob._check_normals(7)
    assert draws.shape == (64, 7) and prob._check_normals(7) is draws
    assert int(round(NOMINAL_FRACTION * 64)) == 16


def test_a_solve_left_over_its_level_by_the_check_is_not_converged(chain):
    """A warm solve whose evaluation budget leaves no re-solve for the check's correction
    (the adapter's warm starts run with one) ends ``level_check_failed``, not converged, and
    the constraint the check found over its level is reported violated; with the check off
    (``max_level_corrections`` 0) the same point is an answer of the Gamma match."""
    prior, cons, cfg = panda_problem(chain, np.random.default_rng(1), n_spheres=3)
    _, rep0 = solve_levels(prior, cons, dataclasses.replace(cfg, max_level_corrections=0))
    assert rep0.converged and rep0.status == 'converged'
    start = dataclasses.replace(rep0.state, levels=())
    _, rep = solve_levels(prior, cons, dataclasses.replace(cfg, max_evaluations=1), start=start)
    assert not rep.converged and rep.status == 'level_check_failed'
    assert rep.n_level_corrections == 0
    over = [c for c in rep.constraints if c.checked and not c.satisfied]
    assert over and all(c.kind == 'repeller' for c in over)
    assert 'VIOLATED' in rep.to_text()
