"""The linearised KL projection (cdmp_ros.core.adaptation.linearised), the optimiser's start
(AdaptationConfig.start = 'linearised'): its equations against independent computations (a
scalar minimisation, the KL of the full Gaussians, Monte Carlo), the projection on linear and
kinematic problems, and the solve that starts from it."""
import dataclasses

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.special import ndtri

from cdmp_ros.core.adaptation.config import AdaptationConfig
from cdmp_ros.core.adaptation.constraints import (ChainPoint, DofPoint, Hyperplane, JointLimit,
                                                  Repeller, UnboundWaypoint, Waypoint)
from cdmp_ros.core.adaptation.linearised import (linearised_projection, one_dimensional_ratio,
                                                 project_marginals, supported)
from cdmp_ros.core.adaptation.problem import Problem
from cdmp_ros.core.adaptation.solver import adapt, solve_levels
from cdmp_ros.core.adaptation.verification import verify
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PointOfInterest, planar_chain
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


def gaussian_kl(m1, S1, m0, S0):
    """KL(N(m1, S1) || N(m0, S0)) by the textbook formula (an independent computation)."""
    S0i = np.linalg.inv(S0)
    d = m1 - m0
    return 0.5 * (np.trace(S0i @ S1) + d @ S0i @ d - m0.size
                  + np.linalg.slogdet(S0)[1] - np.linalg.slogdet(S1)[1])


def random_prior(rng, D=3, M=6, scale=0.02):
    A = rng.normal(0.0, 1.0, (D * M, D * M))
    mean = np.r_[np.linspace(0.0, 1.2, M), np.linspace(0.3, 0.9, M), np.zeros(M)][:D * M]
    return ProMP(D, RbfBasis.uniform(M), mean, scale * A @ A.T / (D * M) + 1e-4 * np.eye(D * M))


def planar_problem(rng):
    """A 3-link planar arm whose mean end-effector path runs through two spheres, a wall and
    close to a joint limit."""
    chain = planar_chain([1.0, 0.8, 0.5])
    p = random_prior(rng)
    ee = ChainPoint(chain, PointOfInterest('ee'), axes=(0, 1))
    elbow = ChainPoint(chain, PointOfInterest('link2'), axes=(0, 1))
    x = ee.forward(p.mean([0.35, 0.65]))
    xe = elbow.forward(p.mean([0.5]))[0]
    top = ee.forward(p.mean(np.linspace(0.0, 1.0, 31)))[:, 1].max()
    cons = [Repeller(ee, x[0] + [0.03, 0.0], 0.12, alpha=0.99, name='ball'),
            Repeller(ee, x[1], 0.08, support=(0.4, 0.9), alpha=0.999, name='small'),
            Repeller(elbow, xe, 0.06, alpha=0.99, name='elbow'),
            Hyperplane(ee, [0.0, 1.0], [0.0, top - 0.02], alpha=0.99, name='wall'),
            JointLimit(2, -0.15, 0.15, alpha=0.99, name='limit')]
    return p, cons


def test_one_dimensional_ratio_minimises_the_scalar_kl():
    """r = s'/s minimises KL(N(beta + z r, r^2) || N(0, 1)) over r (delta = beta)."""
    for z in (1.0, 3.09, 4.0):
        for delta in (-5.0, -1.0, 0.0, 0.7, 3.0):
            def kl(r):
                m = delta + z * r
                return -np.log(r) + 0.5 * (r * r + m * m) - 0.5
            best = minimize_scalar(kl, bounds=(1e-6, 5.0), method='bounded',
                                   options={'xatol': 1e-10})
            assert one_dimensional_ratio(delta, z) == pytest.approx(best.x, rel=1e-5)


def test_projected_marginals_meet_their_bounds_and_the_kl_chain_rule():
    """The rows' marginals N(m, V) meet m - z sqrt(diag V) >= beta; the full Gaussian built
    from them (prior conditioned as in the module docstring) has exactly the rows' marginal,
    and its KL to the prior equals the k-dimensional KL (the chain rule)."""
    rng = np.random.default_rng(3)
    n, k = 12, 4
    B = rng.normal(size=(n, n))
    S0 = B @ B.T / n + 0.1 * np.eye(n)
    mu0 = rng.normal(size=n)
    H = rng.normal(size=(k, n))
    A = H @ S0 @ H.T
    a0 = H @ mu0
    beta = a0 + rng.uniform(-1.0, 2.0, k) * np.sqrt(np.diag(A))
    z = np.full(k, 3.09)
    m, V, nu = project_marginals(A, a0, beta, z)
    assert np.all(m - z * np.sqrt(np.diag(V)) >= beta - 1e-8)
    assert np.all(nu >= 0.0)
    np.testing.assert_allclose(m, a0 + A @ nu, atol=1e-10)
    K = np.linalg.solve(A, H @ S0).T
    mu = mu0 + K @ (m - a0)
    S = S0 - K @ (A - V) @ K.T
    np.testing.assert_allclose(H @ mu, m, atol=1e-9)
    np.testing.assert_allclose(H @ S @ H.T, V, atol=1e-9)
    assert gaussian_kl(mu, S, mu0, S0) == pytest.approx(gaussian_kl(m, V, a0, A), rel=1e-6)
    # one row: the one-dimensional optimum exactly
    m1, V1, _ = project_marginals(A[:1, :1], a0[:1], beta[:1], z[:1])
    s = np.sqrt(A[0, 0])
    r = min(one_dimensional_ratio((beta[0] - a0[0]) / s, z[0]), 1.0)
    assert np.sqrt(V1[0, 0]) == pytest.approx(r * s, rel=1e-4)   # the fixed point: 1e-5
    assert m1[0] == pytest.approx(max(a0[0], beta[0] + z[0] * r * s), rel=1e-4)


def test_joint_limits_alone_are_met_exactly_and_the_sample_confirms_it():
    """Joint limits are linear in the weights: the projection's margins are exact, every
    step holds at z, and sampled trajectories violate no step more often than 1 - alpha."""
    rng = np.random.default_rng(1)
    p = random_prior(rng, scale=0.05)
    grid = np.linspace(0.0, 1.0, 31)
    cons = [JointLimit(0, 0.1, 1.0, alpha=0.99, name='j0'),
            JointLimit(2, None, 0.05, alpha=0.999, name='j2')]
    assert not verify(p, cons, 20000, np.random.default_rng(2), n_steps=31).holds
    res = linearised_projection(p, cons, grid, z_margin=0.0, tolerance=1e-6)
    assert res.converged and res.rows >= 1
    m, C = res.promp.mean(grid), res.promp.cov(grid)
    sd0, sd2 = np.sqrt(C[:, 0, 0]), np.sqrt(C[:, 2, 2])
    assert np.all(m[:, 0] - ndtri(0.99) * sd0 >= 0.1 - 1e-6 * sd0)
    assert np.all(m[:, 0] + ndtri(0.99) * sd0 <= 1.0 + 1e-6 * sd0)
    assert np.all(m[:, 2] + ndtri(0.999) * sd2 <= 0.05 + 1e-6 * sd2)
    v = verify(res.promp, cons, 20000, np.random.default_rng(2), n_steps=31)
    assert v.holds, v.to_text()
    # the KL is what the full Gaussians give
    kl = gaussian_kl(res.promp.mean_w, res.promp.cov_w, p.mean_w, p.cov_w)
    prob = Problem(p, cons, AdaptationConfig(n_steps=31))
    L = np.linalg.cholesky(res.promp.cov_w)
    assert prob.kl(res.promp.mean_w, L) == pytest.approx(kl, rel=1e-7)


def test_kinematic_problem_converges_and_verifies():
    """Spheres on the end effector and a link, a wall and a limit on a planar arm: the
    projection converges under the linearisation, and the sampled verification holds."""
    for seed in (0, 1, 2, 3):
        p, cons = planar_problem(np.random.default_rng(seed))
        grid = np.linspace(0.0, 1.0, 31)
        before = verify(p, cons, 4000, np.random.default_rng(0), n_steps=31)
        assert not before.holds                     # the prior violates them
        res = linearised_projection(p, cons, grid)
        assert res.converged and res.worst_margin >= -0.05 and res.rows >= 5, seed
        v = verify(res.promp, cons, 4000, np.random.default_rng(0), n_steps=31)
        assert v.holds, (seed, v.to_text())
        lam = res.multipliers
        assert lam.shape == (Problem(p, cons, AdaptationConfig(n_steps=31)).n_values,)
        assert np.all(lam >= 20.0)


def test_solve_from_the_projection_converges_in_fewer_evaluations():
    """The full solve started at the projection converges and verifies, in fewer Lagrangian
    evaluations than from the prior; the report says where it started. (The problem is not
    convex: on this arm the projection leads to a different local optimum than the prior,
    with a larger KL; that is measured, not asserted.) A projection that does not converge
    is not used as the start."""
    used = 0
    for seed in (0, 1, 2):
        p, cons = planar_problem(np.random.default_rng(seed))
        config = AdaptationConfig(n_steps=31)
        _, cold = solve_levels(p, cons, config)
        _, warm = solve_levels(p, cons, dataclasses.replace(config, start='linearised'))
        assert cold.converged and warm.converged
        assert cold.start == 'prior'
        projected = linearised_projection(p, cons, np.linspace(0.0, 1.0, 31), config.lambda0)
        if not projected.converged:
            assert warm.start == 'prior' and warm.n_evaluations == cold.n_evaluations
            continue
        used += 1
        assert warm.start == 'linearised' and warm.start_passes == projected.passes
        assert warm.n_evaluations < cold.n_evaluations, (seed, warm.n_evaluations,
                                                         cold.n_evaluations)
        _, rep = adapt(p, cons, dataclasses.replace(config, start='linearised'))
        assert rep.converged and rep.verification.holds
        assert rep.as_dict()['start'] == 'linearised'
    assert used >= 2


def test_unsupported_constraints_start_at_the_prior_and_bad_settings_are_refused():
    p, cons = planar_problem(np.random.default_rng(0))
    ee = cons[0].point
    for extra in (Waypoint(ee, [1.0, 1.0], 0.3, support=(0.5, 0.5), name='via'),
                  UnboundWaypoint(ee, [1.0, 1.0], 0.3, name='any')):
        assert not supported(cons + [extra])
        _, rep = solve_levels(p, cons + [extra], AdaptationConfig(n_steps=21, start='linearised'))
        assert rep.start == 'prior'
    assert supported([Hyperplane(DofPoint([0]), [1.0], [2.0])])
    # contradictory limits: the projection cannot converge and the solve starts at the prior
    clash = cons + [JointLimit(2, 0.3, None, alpha=0.99, name='clash')]
    res = linearised_projection(p, clash, np.linspace(0.0, 1.0, 21))
    assert not res.converged and res.worst_margin < -0.05 and res.passes == 12
    _, rep = solve_levels(p, clash, AdaptationConfig(n_steps=21, start='linearised',
                                                     max_outer=2))
    assert rep.start == 'prior' and not rep.converged
    with pytest.raises(ValidationError, match='start'):
        AdaptationConfig(start='posterior')


def test_theta_of_is_the_inverse_of_unpack():
    p, cons = planar_problem(np.random.default_rng(4))
    for whiten in (True, False):
        prob = Problem(p, cons, AdaptationConfig(n_steps=11, whiten=whiten))
        rng = np.random.default_rng(5)
        B = rng.normal(size=(p.n_weights, p.n_weights))
        S = B @ B.T / p.n_weights + 0.01 * np.eye(p.n_weights)
        mu = rng.normal(size=p.n_weights)
        m, L, _ = prob.unpack(prob.theta_of(mu, S))
        np.testing.assert_allclose(m, mu, atol=1e-9)
        np.testing.assert_allclose(L @ L.T, S, atol=1e-8)
