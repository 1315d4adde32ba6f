"""Constrained ProMP adaptation (paper 003, Eq. 5-10, 23): analytic gradients of the
Lagrangian vs finite differences for every constraint type (incl. the unscented transform and
the Gamma approximation), and the optimiser's outcome checked by sampling."""
import numpy as np
import pytest

from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.solver import AdaptationConfig, Problem, monte_carlo_satisfaction
from cdmp_ros.core.adaptation.constraints import (DofPoint, Hyperplane, JointLimit,
                                                  MutualAvoidance, NonConvexCorner, Point,
                                                  Repeller, SmoothnessConstraint, UnboundWaypoint,
                                                  Waypoint)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


class Planar2(Point):
    """Test-local planar 2-link arm end point (independent of cdmp_ros.core.kinematics)."""

    def __init__(self, dofs=(0, 1), lengths=(1.0, 0.8)):
        self.dofs = tuple(dofs)
        self.n_out = 2
        self.l1, self.l2 = lengths

    def forward_and_jacobian(self, Z):
        q1, q2 = Z[..., 0], Z[..., 1]
        x = self.l1 * np.cos(q1) + self.l2 * np.cos(q1 + q2)
        y = self.l1 * np.sin(q1) + self.l2 * np.sin(q1 + q2)
        J = np.empty(Z.shape[:-1] + (2, 2))
        J[..., 0, 0] = -y
        J[..., 0, 1] = -self.l2 * np.sin(q1 + q2)
        J[..., 1, 0] = x
        J[..., 1, 1] = self.l2 * np.cos(q1 + q2)
        return np.stack([x, y], axis=-1), J


def _prior(rng, D=2, M=5):
    A = rng.standard_normal((D * M, D * M))
    return ProMP(D, RbfBasis.uniform(M), 0.3 * rng.standard_normal(D * M),
                 A @ A.T / (D * M) * 0.2 + 0.05 * np.eye(D * M))


def _check_gradient(prob, rng, n_checks=12):
    theta = prob.initial_theta() + 0.05 * rng.standard_normal(prob.initial_theta().size)
    lam = rng.uniform(0.5, 2.0, prob.n_values)
    f, g = prob.lagrangian(theta, lam)
    idx = rng.choice(theta.size, size=min(n_checks, theta.size), replace=False)
    idx = np.unique(np.r_[idx, 0, theta.size - 1])
    h = 1e-6
    for i in idx:
        e = np.zeros_like(theta)
        e[i] = h
        fd = (prob.lagrangian(theta + e, lam)[0] - prob.lagrangian(theta - e, lam)[0]) / (2 * h)
        scale = max(abs(fd), abs(g[i]), 1e-3 * np.linalg.norm(g) / np.sqrt(g.size))
        assert abs(fd - g[i]) / scale <= 1e-5, (i, fd, g[i])
    # directional derivative over all parameters at once
    v = rng.standard_normal(theta.size)
    v /= np.linalg.norm(v)
    fd = (prob.lagrangian(theta + h * v, lam)[0]
          - prob.lagrangian(theta - h * v, lam)[0]) / (2 * h)
    assert abs(fd - g @ v) <= 1e-5 * max(abs(fd), 1e-8)


CART = DofPoint([0, 1])


def _constraint_sets():
    return {
        'repeller': [Repeller(CART, [0.2, 0.1], 0.3)],
        'waypoint': [Waypoint(CART, [0.5, -0.2], 0.2, support=(0.4, 0.5))],
        'unbound_waypoint': [UnboundWaypoint(CART, [0.4, 0.3], 0.1, support=(0.2, 0.9))],
        'hyperplane': [Hyperplane(CART, [1.0, 0.5], [0.3, 0.0])],
        'corner': [NonConvexCorner(CART, [1, 0], [0.1, 0.1], [0, 1], [0.1, 0.1])],
        'joint_limit': [JointLimit(0, -0.5, 0.4), JointLimit(1, upper=lambda t: 0.2 + t,
                                                             support=(0.3, 1.0))],
        'ut_repeller': [Repeller(Planar2(), [1.2, 0.9], 0.3)],
        'ut_hyperplane': [Hyperplane(Planar2(), [0.0, 1.0], [0.0, 1.5])],
        'mutual': [MutualAvoidance(Planar2((0, 1)), Planar2((2, 3)), 0.5)],
        # batches of several members: weighed in one product per batch (all 'each'), or per
        # member when a member has one multiplier for its whole support ('max')
        'sphere_batch': [Repeller(CART, [0.2, 0.1], 0.3), Repeller(CART, [-0.3, 0.2], 0.2),
                         Waypoint(CART, [0.5, -0.2], 0.2, support=(0.4, 0.5))],
        'sphere_batch_max': [Repeller(CART, [0.2, 0.1], 0.3),
                             UnboundWaypoint(CART, [0.4, 0.3], 0.1, support=(0.2, 0.9))],
    }


@pytest.mark.parametrize('whiten', [True, False])
@pytest.mark.parametrize('name', sorted(_constraint_sets()))
def test_lagrangian_gradient_matches_finite_differences(name, whiten, rng):
    cons = _constraint_sets()[name]
    D = 4 if name == 'mutual' else 2
    prior = _prior(rng, D=D)
    cfg = AdaptationConfig(n_steps=15, whiten=whiten,
                           kl_blocks=((0, 10), (10, 20)) if name == 'mutual' else None)
    _check_gradient(Problem(prior, cons, cfg), rng)


@pytest.mark.parametrize('ut_alpha', [0.8, 1.5])
def test_gradient_with_unscented_centre_point(ut_alpha, rng):
    cons = [Repeller(Planar2(), [1.2, 0.9], 0.3), Hyperplane(Planar2(), [0.0, 1.0], [0.0, 1.5])]
    cfg = AdaptationConfig(n_steps=9, ut_alpha=ut_alpha)
    _check_gradient(Problem(_prior(rng), cons, cfg), rng)


def test_gradient_with_smoothness_regulariser_and_constraint(rng):
    prior = _prior(rng)
    Phi = prior.smoothness_matrix(joint_weights=[2.0, 0.1])
    bound = float(prior.mean_w @ Phi @ prior.mean_w + np.trace(Phi @ prior.cov_w))
    cons = [SmoothnessConstraint(Phi, bound), Repeller(CART, [0.0, 0.0], 0.2)]
    cfg = AdaptationConfig(n_steps=11, kappa=0.01, smoothness_weights=(2.0, 0.1))
    _check_gradient(Problem(prior, cons, cfg), rng)


def test_batched_constraint_evaluation_matches_one_problem_per_constraint(rng):
    """Constraints of one kind are evaluated in one vectorised call (limits on several joints,
    repellers and waypoints on one point, walls through two non-linear points, contiguous
    DofPoints read from the marginals directly): same F as one Problem per constraint, and
    the gradient of the whole Lagrangian still matches finite differences."""
    prior = _prior(rng, D=4)
    cons = [JointLimit(0, -0.5, 0.4), JointLimit(3, upper=lambda t: 0.2 + t, support=(0.3, 1)),
            Repeller(CART, [0.2, 0.1], 0.3), Waypoint(CART, [0.5, -0.2], 0.4, support=(0.4, 0.5)),
            UnboundWaypoint(CART, [0.4, 0.3], 0.1, support=(0.2, 0.9)),
            Repeller(DofPoint([2, 3]), [0.0, 0.1], 0.2), Repeller(DofPoint([3, 1]), [0, 0], 0.3),
            Hyperplane(Planar2(), [0.0, 1.0], [0.0, 1.5]),
            Hyperplane(Planar2((2, 3)), [1.0, 0.0], [1.0, 0.0], support=(0.5, 1.0)),
            NonConvexCorner(CART, [1, 0], [0.1, 0.1], [0, 1], [0.1, 0.1])]
    cfg = AdaptationConfig(n_steps=15)
    prob = Problem(prior, cons, cfg)
    assert len(prob.batches) < len(cons)
    theta = prob.initial_theta() + 0.05 * rng.standard_normal(prob.initial_theta().size)
    mu, L, _ = prob.unpack(theta)
    F = prob.constraint_values(mu, L)
    for c, sl in zip(cons, prob.slices):
        F1 = Problem(prior, [c], cfg).constraint_values(mu, L)
        times = c.times(prob.grid)
        m = prior.basis.features(times) @ mu.reshape(4, -1).T
        assert np.allclose(F[sl], F1, rtol=0, atol=1e-13), c.name
        if isinstance(c.point, DofPoint):          # and the per-constraint API agrees
            Phi = np.kron(np.eye(4), prior.basis.features(times))      # (4n, 4M) by dims
            S = (Phi @ L @ L.T @ Phi.T).reshape(4, times.size, 4, times.size)
            S = np.einsum('itjt->tij', S)
            d = list(c.point.dofs)
            Fc = c.probability(m[:, d], S[:, d][:, :, d], times)[0]
            Fc = Fc.max(keepdims=True) if c.reduce == 'max' else Fc
            assert np.allclose(F[sl], Fc, rtol=0, atol=1e-12), c.name
    _check_gradient(prob, rng, n_checks=20)


@pytest.mark.parametrize('whiten', [True, False])
def test_kl_is_zero_at_the_prior_and_closed_form(whiten, rng):
    prior = _prior(rng)
    prob = Problem(prior, [], AdaptationConfig(whiten=whiten))
    mu, L, gamma = prob.unpack(prob.initial_theta())
    assert abs(prob.kl(mu, L)) < 1e-9
    assert abs(prob.lagrangian(prob.initial_theta(), np.zeros(0))[0]) < 1e-9
    theta = prob.initial_theta() + 0.1 * rng.standard_normal(prob.initial_theta().size)
    mu, L, gamma = prob.unpack(theta)
    assert np.allclose(L, np.tril(L))          # L stays lower triangular
    S, S0 = L @ L.T, prior.cov_w
    d = mu - prior.mean_w
    ref = 0.5 * (np.trace(np.linalg.solve(S0, S)) + d @ np.linalg.solve(S0, d) - S.shape[0]
                 + np.linalg.slogdet(S0)[1] - np.linalg.slogdet(S)[1])
    assert np.isclose(prob.kl(mu, L), ref, rtol=1e-9)
    assert np.isclose(prob.lagrangian(theta, np.zeros(0))[0], ref, rtol=1e-9)


def _table_prior(rng, M=10):
    p = ProMP(2, RbfBasis.uniform(M), np.r_[np.linspace(-3, 3, M), np.zeros(M)],
              0.64 * np.eye(2 * M))
    return p.condition([0, 1], [[-3, 0.5], [3, -0.5]], var=1e-3)


# Gaussian CDFs (limits, walls, corners up to the product approximation) are exact for a
# Cartesian ProMP; the Gamma approximation of |x - x_bar|^2 (repellers, waypoints) is not: its
# tail error is allowed up to 3 (1 - alpha) (the paper's Table II: 0.3-0.5 % violations).
GAMMA_SLACK = {'repeller': 3.0, 'waypoint': 3.0, 'unbound_waypoint': 3.0}


def _check_by_sampling(q, cons, rng, n_steps):
    per_time, whole, _ = monte_carlo_satisfaction(q, cons, 20000, rng, n_steps=n_steps)
    for c, p in zip(cons, per_time):
        # binomial standard error at alpha = 0.999 with 20000 samples is ~2.2e-4
        slack = GAMMA_SLACK.get(c.kind, 1.0) * (1.0 - c.alpha)
        assert p >= c.alpha - slack - 5e-4, (c.name, p)
    return per_time, whole


@pytest.mark.parametrize('kind', ['repeller', 'hyperplane', 'unbound_waypoint', 'waypoint',
                                  'corner', 'joint_limit', 'time_varying_limit'])
def test_adapted_promp_satisfies_constraint_at_its_confidence(kind, rng):
    prior = _table_prior(rng)
    mid = prior.mean([0.5])[0]
    cons = {
        'repeller': [Repeller(CART, mid + [0, 0.3], 0.5)],
        'hyperplane': [Hyperplane(CART, [0.0, 1.0], [0.0, 0.5], support=(0.2, 0.8))],
        'unbound_waypoint': [UnboundWaypoint(CART, mid + [0.5, 0.8], 0.15)],
        'waypoint': [Waypoint(CART, mid + [0, 1.0], 0.2, support=(0.45, 0.55))],
        'corner': [NonConvexCorner(CART, [1, 0], mid - [0.5, 0.5], [0, -1], mid + [0, 0.3],
                                   support=(0.2, 0.8))],
        'joint_limit': [JointLimit(1, -0.8, 0.6, support=(0.1, 0.9))],
        'time_varying_limit': [JointLimit(1, lower=-1.5, upper=lambda t: 0.8 - 1.2 * t,
                                          support=(0.2, 0.9))],
    }[kind]
    q, rep = adapt(prior, cons, AdaptationConfig(n_steps=41))
    assert rep.converged, rep.to_text()
    assert rep.kl > 0
    before = monte_carlo_satisfaction(prior, cons, 5000, rng, n_steps=41)[0]
    assert np.all(before < 0.99)          # the prior does not satisfy it already
    _check_by_sampling(q, cons, rng, 41)


def test_infeasible_problem_is_reported_not_returned_as_success(rng):
    prior = _table_prior(rng)
    # the start point is pinned at x = -3 with variance 1e-3; forbid it with a wall at t = 0
    cons = [Hyperplane(CART, [-1.0, 0.0], [-2.0, 0.0], support=(0.0, 0.0))]
    q, rep = adapt(prior, cons, AdaptationConfig(max_outer=3, max_inner=50))
    assert not rep.converged
    assert rep.status != 'converged'
    assert not rep.constraints[0].satisfied


# -- a waypoint far from the prior (issue 13 item 4: a robust objective) ---------------------
def _far_waypoint_problem(n_sd, kind=Waypoint):
    M = 10
    p = ProMP(2, RbfBasis.uniform(M), np.r_[np.linspace(-3, 3, M), np.zeros(M)],
              0.8 ** 2 * np.eye(2 * M)).condition([0, 1], [[-3, 0.0], [3, 0.0]], var=1e-3)
    s = np.array([0.5])
    sd = np.sqrt(np.diag(p.cov(s)[0]))
    target = p.mean(s)[0] + np.array([0.0, n_sd * sd[1]])
    support = (0.5, 0.5) if kind is Waypoint else (0.3, 0.7)
    return p, kind(DofPoint([0, 1]), target, 0.1, support=support, alpha=0.999), target


@pytest.mark.parametrize('kind', [Waypoint, UnboundWaypoint])
@pytest.mark.parametrize('n_sd', [10, 20])
def test_a_waypoint_far_from_the_prior_is_reached(n_sd, kind):
    """10 and 20 prior standard deviations away the probability of the ball and its gradient
    vanish; the guide of the Lagrangian (spheres.guide_rows) still pulls the distribution
    there, and the report (probabilities and the sampled check) is the unguided one."""
    p, c, target = _far_waypoint_problem(n_sd, kind)
    q, rep = adapt(p, [c], AdaptationConfig(n_steps=101))
    assert rep.converged, rep.to_text()
    assert rep.constraints[0].probability >= 0.999
    times = np.linspace(0.0, 1.0, 101)[(np.linspace(0.0, 1.0, 101) >= c.support[0] - 1e-9)
                                       & (np.linspace(0.0, 1.0, 101) <= c.support[1] + 1e-9)]
    assert np.linalg.norm(q.mean(times) - target, axis=1).min() < c.radius


def test_the_guide_is_zero_where_the_constraint_can_hold_and_its_gradient_is_exact():
    """G = 0 (with its gradient) for rows within 3 standard scores of the ball, so solutions
    and reports of reachable constraints are unchanged; far away the guided Lagrangian's
    gradient matches central differences and does not vanish."""
    from cdmp_ros.core.adaptation.constraints.spheres import GUIDE_Z, _Sphere
    rng = np.random.default_rng(4)
    m = rng.normal(0.0, 1.0, (50, 2))
    S = np.einsum('nij,nkj->nik', *(2 * [rng.normal(0.0, 0.3, (50, 2, 2))])) + 0.01 * np.eye(2)
    params = {'inside': np.r_[np.ones(40, bool), np.zeros(10, bool)],
              'center': rng.normal(0.0, 3.0, (50, 2)), 'r2': np.full(50, 0.04)}
    G, dm, dS = _Sphere.guide_rows(m, S, params)
    from cdmp_ros.core.promp.gaussian import quadratic_moments
    E, V = quadratic_moments(m, S, params['center'])[:2]
    z = (params['r2'] - E) / np.sqrt(V)
    near = (z >= GUIDE_Z) | ~params['inside']
    assert near.any() and (~near).any()
    assert np.all(G[near] == 0.0) and np.all(dm[near] == 0.0) and np.all(G[~near] < 0.0)
    for n_sd in (2, 10):
        prior, c, _ = _far_waypoint_problem(n_sd)
        prob = Problem(prior, [c], AdaptationConfig(n_steps=101))
        theta = prob.initial_theta() + 0.01 * np.random.default_rng(0).standard_normal(
            prob.initial_theta().size)
        lam = np.array([20.0])
        _, g = prob.lagrangian(theta, lam)
        h = 1e-6
        idx = np.arange(0, theta.size, 7)
        fd = np.array([(prob.lagrangian(theta + h * e, lam)[0]
                        - prob.lagrangian(theta - h * e, lam)[0]) / (2 * h)
                       for e in np.eye(theta.size)[idx]])
        np.testing.assert_allclose(g[idx], fd, rtol=1e-5, atol=1e-7)
        g0 = prob.lagrangian(theta, np.zeros(1))[1]  # the KL alone
        pull = np.abs(g - g0)[:prior.n_weights].max()
        assert pull > 1e-3, pull  # the constraint pulls the mean, even at 10 sd


def test_batches_of_one_multiplier_per_row_are_weighed_together(rng):
    """The fused path (every member 'each') and the per-member path give one Lagrangian."""
    prior = _prior(rng)
    cons = _constraint_sets()['sphere_batch']
    prob = Problem(prior, cons, AdaptationConfig(n_steps=15))
    assert len(prob.batches) == 1 and prob.fused[0] is not None
    theta = 0.05 * rng.standard_normal(prob.initial_theta().size)
    lam = rng.uniform(0.5, 2.0, prob.n_values)
    f, g = prob.lagrangian(theta, lam)
    prob.fused[0] = None                     # force the per-member path
    f1, g1 = prob.lagrangian(theta, lam)
    assert f == pytest.approx(f1, rel=1e-13)
    assert np.allclose(g, g1, rtol=1e-12, atol=1e-14)
    mixed = Problem(prior, _constraint_sets()['sphere_batch_max'], AdaptationConfig(n_steps=15))
    assert mixed.fused == [None]


def test_multiplier_update_clips_increases_and_decreases_separately():
    """Relative EMM step: lambda exp(clip(eta (alpha' - F) / (1 - alpha'),
    -max_log_decrease, max_log_step)); the paper's step lambda exp(eta (alpha' - F))."""
    from cdmp_ros.core.adaptation.solver import multiplier_update
    lam = np.array([20.0, 20.0, 20.0, 20.0])
    aim = np.full(4, 1.0 - 6e-4)
    F = np.array([0.9, 1.0 - 1.2e-3, 1.0 - 6e-4, 1.0])    # far below, 2x, at, above the aim
    eta = np.ones(4)
    cfg = AdaptationConfig()
    assert cfg.max_log_step == 3.0 and cfg.max_log_decrease == 0.3
    new = multiplier_update(lam, F, eta, aim, cfg)
    assert new == pytest.approx(20.0 * np.exp([3.0, 1.0, 0.0, -0.3]), rel=1e-9)
    sym = multiplier_update(lam, F, eta, aim, AdaptationConfig(max_log_decrease=3.0))
    assert sym[3] == pytest.approx(20.0 * np.exp(-1.0), rel=1e-9)   # the unclipped -1
    paper = multiplier_update(lam, F, eta, aim, AdaptationConfig(relative_step=False))
    assert paper == pytest.approx(20.0 * np.exp(aim - F), rel=1e-12)
    with pytest.raises(ValidationError, match='max_log_decrease'):
        AdaptationConfig(max_log_decrease=0.0)
