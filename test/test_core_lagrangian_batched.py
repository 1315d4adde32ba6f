"""The batched Lagrangian (cdmp_ros.core.adaptation.batched, issue 29) against its oracle, the
reference evaluation constraint by constraint (Problem.lagrangian_reference): value, gradient
and constraint values on the Panda problem of benchmarks/bench_adapter.py, a Table II problem
and random problems of every constraint kind and point of interest; the batched gradient
against finite differences; and the solver's solutions with either evaluation."""
import functools

import numpy as np
import pytest

from cdmp_ros.core.adaptation import solver
from cdmp_ros.core.adaptation.constraints import (ChainPoint, DofPoint, Hyperplane, JointLimit,
                                                  MutualAvoidance, NonConvexCorner, Point,
                                                  Repeller, SmoothnessConstraint, UnboundWaypoint,
                                                  Waypoint)
from cdmp_ros.core.adaptation.problem import Problem
from cdmp_ros.core.adaptation.solver import AdaptationConfig
from cdmp_ros.core.kinematics import Chain, PointOfInterest, planar_chain
from cdmp_ros.core.promp.promp import ProMP, RbfBasis

#: value and gradient of the two evaluations agree to this, relative (module docstring of
#: cdmp_ros.core.adaptation.batched; rounding only)
RTOL = 1e-10


class Planar2(Point):
    """A point of interest of the test's own (not a chain): the reference path evaluates it."""

    def __init__(self, dofs=(0, 1)):
        self.dofs = tuple(dofs)
        self.n_out = 2

    def forward_and_jacobian(self, Z):
        q1, q2 = Z[..., 0], Z[..., 1]
        x = np.cos(q1) + 0.8 * np.cos(q1 + q2)
        y = np.sin(q1) + 0.8 * np.sin(q1 + q2)
        J = np.empty(Z.shape[:-1] + (2, 2))
        J[..., 0, 0], J[..., 0, 1] = -y, -0.8 * np.sin(q1 + q2)
        J[..., 1, 0], J[..., 1, 1] = x, 0.8 * np.cos(q1 + q2)
        return np.stack([x, y], axis=-1), J


def _prior(rng, D=2, M=5):
    A = rng.standard_normal((D * M, D * M))
    return ProMP(D, RbfBasis.uniform(M), 0.3 * rng.standard_normal(D * M),
                 A @ A.T / (D * M) * 0.2 + 0.05 * np.eye(D * M))


def _prismatic_chain():
    """A 3-joint planar chain whose middle joint slides along z (the batched kinematics'
    prismatic branch)."""
    p = planar_chain([1.0, 0.8, 0.5])
    return Chain(p.joint_names, [False, True, False], p.B, p.base_transform, p.attachments,
                 p.link_names, p.ee_link, p.ee_offset, p.lower, p.upper, p.velocity_limits)


def _cases():
    cart = DofPoint([0, 1])
    arm = planar_chain([1.0, 0.8])
    tip = ChainPoint(arm, PointOfInterest('ee'), axes=(0, 1))
    elbow = ChainPoint(arm, PointOfInterest('link2'), axes=(0, 1))
    arm3 = planar_chain([1.0, 0.8, 0.5])
    tip3 = ChainPoint(arm3, PointOfInterest('ee'))                      # all three axes
    mid3 = ChainPoint(arm3, PointOfInterest('link3'))
    sub = ChainPoint(arm, PointOfInterest('ee'), dofs=(2, 1), axes=(1, 0))   # dofs of D = 3
    pri = ChainPoint(_prismatic_chain(), PointOfInterest('ee'))
    return {
        # (constraints, n_dims, config overrides)
        'repeller': ([Repeller(cart, [0.2, 0.1], 0.3)], 2, {}),
        'waypoint': ([Waypoint(cart, [0.5, -0.2], 0.2, support=(0.4, 0.5))], 2, {}),
        'far_waypoint': ([Waypoint(cart, [4.0, 3.0], 0.1, support=(0.5, 0.5))], 2, {}),
        'unbound_waypoint': ([UnboundWaypoint(cart, [0.4, 0.3], 0.1, support=(0.2, 0.9))], 2,
                             {}),
        'hyperplane': ([Hyperplane(cart, [1.0, 0.5], [0.3, 0.0])], 2, {}),
        'corner': ([NonConvexCorner(cart, [1, 0], [0.1, 0.1], [0, 1], [0.1, 0.1])], 2, {}),
        'joint_limit': ([JointLimit(0, -0.5, 0.4),
                         JointLimit(1, upper=lambda t: 0.2 + t, support=(0.3, 1.0)),
                         JointLimit(0, lower=-0.1, support=(0.5, 0.5))], 2, {}),
        'gamma_tail': ([Repeller(cart, [0.2, 0.1], 0.3), Waypoint(cart, [0.5, -0.2], 0.2)], 2,
                       {'tail': 'gamma'}),
        'sphere_batch_max': ([Repeller(cart, [0.2, 0.1], 0.3), Repeller(cart, [-0.3, 0.2], 0.2),
                              UnboundWaypoint(cart, [0.4, 0.3], 0.1, support=(0.2, 0.9))], 2,
                             {}),
        'custom_point': ([Repeller(Planar2(), [1.2, 0.9], 0.3),
                          Hyperplane(Planar2(), [0.0, 1.0], [0.0, 1.5])], 2, {}),
        'mutual': ([MutualAvoidance(Planar2((0, 1)), Planar2((2, 3)), 0.5)], 4,
                   {'kl_blocks': ((0, 5), (5, 10))}),
        'smoothness': (['smoothness', JointLimit(0, -0.5, 0.4)], 2, {'kappa': 0.1}),
        'chain': ([Repeller(tip, [1.2, 0.9], 0.3), Repeller(elbow, [0.6, 0.5], 0.2),
                   JointLimit(0, -0.5, 0.4)], 2, {}),
        'chain_saddle_tail': ([Repeller(tip, [1.2, 0.9], 0.3), Waypoint(elbow, [0.9, 0.3], 0.2)],
                              2, {'tail': 'saddlepoint'}),
        'chain_centre_point': ([Repeller(tip, [1.2, 0.9], 0.3),
                                Hyperplane(tip, [0.0, 1.0], [0.0, 1.5])], 2, {'ut_alpha': 0.8}),
        'chain_3d_stacked': ([Repeller(tip3, [1.5, 1.0, 0.0], 0.3),
                              Repeller(mid3, [1.0, 0.8, 0.0], 0.2),
                              Repeller(tip3, [0.5, 1.5, 0.0], 0.3, support=(0.2, 0.6))], 3, {}),
        'chain_dof_subset': ([Repeller(sub, [0.9, 1.2], 0.3), JointLimit(0, -0.5, 0.4)], 3, {}),
        'chain_prismatic': ([Repeller(pri, [1.5, 1.0, 0.3], 0.3),
                             Waypoint(pri, [1.2, 1.2, 0.0], 0.4, support=(0.6, 0.7))], 3, {}),
    }


def _problem(name, whiten, rng):
    cons, D, over = _cases()[name]
    prior = _prior(rng, D=D)
    cons = [SmoothnessConstraint(prior.smoothness_matrix(), 50.0) if c == 'smoothness' else c
            for c in cons]
    cfg = AdaptationConfig(n_steps=15, whiten=whiten, **over)
    return prior, cons, cfg


def _compare(prior, cons, cfg, rng, n_points=3, spread=0.05, thetas=None, rtol=RTOL):
    """Value, gradient and constraint values of both evaluations at random (theta, lambda)
    or at ``thetas``."""
    ref = Problem(prior, cons, cfg, evaluator='reference')
    new = Problem(prior, cons, cfg, evaluator='batched')
    assert new.evaluator == 'batched' and ref.evaluator == 'reference'
    size = ref.initial_theta().size
    if thetas is None:
        thetas = [(ref.initial_theta() + spread * rng.standard_normal(size),
                   rng.uniform(0.5, 50.0, ref.n_values)) for _ in range(n_points)]
    for theta, lam in thetas:
        v0, g0 = ref.lagrangian(theta, lam)
        v1, g1 = new.lagrangian(theta, lam)
        # the gradient's scale: its KL part and its constraint part (they cancel near an
        # optimum, so |g| alone would measure rounding of the parts against their difference)
        gk = ref.lagrangian(theta, np.zeros_like(lam))[1]
        scale = np.linalg.norm(gk) + np.linalg.norm(g0 - gk)
        assert abs(v1 - v0) <= rtol * max(abs(v0), 1.0), (v0, v1)
        assert np.linalg.norm(g1 - g0) <= rtol * scale, (np.linalg.norm(g1 - g0), scale)
        if ref.n_values:
            F0 = ref.cached_values(theta)
            F1 = new.cached_values(theta)
            assert np.allclose(F1, F0, rtol=0.0, atol=1e-12)
    assert new.n_evaluations == ref.n_evaluations - len(thetas)


@pytest.mark.parametrize('whiten', [True, False])
@pytest.mark.parametrize('name', sorted(_cases()))
def test_batched_lagrangian_matches_the_reference(name, whiten, rng):
    prior, cons, cfg = _problem(name, whiten, rng)
    _compare(prior, cons, cfg, rng)


@pytest.mark.parametrize('name', ['chain', 'chain_3d_stacked', 'chain_prismatic',
                                  'chain_dof_subset', 'chain_centre_point', 'joint_limit',
                                  'gamma_tail'])
def test_batched_gradient_matches_finite_differences(name, rng):
    prior, cons, cfg = _problem(name, True, rng)
    from test_core_adaptation import _check_gradient
    _check_gradient(Problem(prior, cons, cfg, evaluator='batched'), rng)


@pytest.fixture(scope='module')
def panda():
    """The adapter's problem of benchmarks/bench_adapter.py: the Panda ProMP, joint limits and
    repellers on the end effector and panda_link4 (three spheres, as
    benchmarks/bench_adaptation_solve.py builds an obstacle event)."""
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.adaptation.requests import AdaptRequest, build_problem, ee_path
    from cdmp_ros.core.kinematics import Sphere, panda_chain
    from cdmp_ros.experiments.promp_problems import panda_problem
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    rng = np.random.default_rng(0)
    chain = panda_chain(panda_urdf_path())
    prior, _, _ = panda_problem(chain, rng, n_spheres=1)
    prior.joint_names = list(chain.joint_names)
    elbow = PointOfInterest('panda_link4')
    spheres = []
    for k in range(3):
        q = prior.mean([rng.uniform(0.3, 0.7)])
        x = ee_path(chain, q)[0] if k < 2 else chain.forward(q, [elbow])[0, 0]
        spheres.append(Sphere(x + rng.normal(0.0, 0.04, 3), float(rng.uniform(0.05, 0.1))))
    req = AdaptRequest(prior, tuple(spheres), start_y=prior.mean([0.05])[0])
    built = build_problem(req, chain, AdaptRequestConfig())
    assert any(type(c.point) is ChainPoint for c in built.constraints
               if hasattr(c, 'point'))
    return built.prior, built.constraints, built.config


def _iterates(prior, cons, cfg, n):
    """(theta, lambda) of the first ``n`` evaluations of a reference solve (where the solver
    evaluates the Lagrangian) and of its last ones."""
    seen = []
    real = Problem.lagrangian_reference

    def record(self, theta, lam):
        seen.append((theta.copy(), lam.copy()))
        return real(self, theta, lam)
    prob_cls = functools.partial(Problem, evaluator='reference')
    orig = solver.Problem
    try:
        solver.Problem = prob_cls
        Problem.lagrangian_reference = record
        solver.solve_levels(prior, cons, cfg)
    finally:
        Problem.lagrangian_reference = real
        solver.Problem = orig
    return seen[:n] + seen[-n:]


def test_panda_problem_matches_the_reference(panda, rng):
    # 3e-10: the Cholesky factors of the steps pinned by the start and goal conditioning
    # (variance 1e-4) amplify rounding; over a whole solve the largest difference measured is
    # 1.2e-10 (benchmarks/RESULTS.md, "Lagrangian evaluation batched")
    prior, cons, cfg = panda
    _compare(prior, cons, cfg, rng, thetas=_iterates(prior, cons, cfg, 3), rtol=3e-10)
    _compare(prior, cons, cfg, rng, n_points=2, spread=0.1, rtol=3e-10)


def test_panda_gradient_matches_finite_differences(panda, rng):
    prior, cons, cfg = panda
    prob = Problem(prior, cons, cfg, evaluator='batched')
    theta, lam = _iterates(prior, cons, cfg, 2)[1]     # early in the solve: a gradient
    f, g = prob.lagrangian(theta, lam)
    h = 1e-6
    for _ in range(3):
        v = rng.standard_normal(theta.size)
        v /= np.linalg.norm(v)
        fd = (prob.lagrangian(theta + h * v, lam)[0]
              - prob.lagrangian(theta - h * v, lam)[0]) / (2 * h)
        assert abs(fd - g @ v) <= 1e-5 * max(abs(fd), 1e-3 * np.linalg.norm(g)), (fd, g @ v)


def test_table2_problem_matches_the_reference(rng):
    from cdmp_ros.experiments.promp_problems import make_problem
    p = make_problem('table2', 3, np.random.default_rng(0))
    _compare(p.prior, p.constraints, p.config, rng,
             thetas=_iterates(p.prior, p.constraints, p.config, 3))


def _solver_problems():
    """The problems of the solver tests of test_core_adaptation.py (a conditioned 2-D prior,
    one constraint of each kind) and Table II / IV problems."""
    from cdmp_ros.experiments.promp_problems import make_problem
    M = 10
    p = ProMP(2, RbfBasis.uniform(M), np.r_[np.linspace(-3, 3, M), np.zeros(M)],
              0.64 * np.eye(2 * M)).condition([0, 1], [[-3, 0.5], [3, -0.5]], var=1e-3)
    cart = DofPoint([0, 1])
    mid = p.mean([0.5])[0]
    cfg = AdaptationConfig(n_steps=41)
    out = {
        'repeller': (p, [Repeller(cart, mid + [0, 0.3], 0.5)], cfg),
        'hyperplane': (p, [Hyperplane(cart, [0.0, 1.0], [0.0, 0.5], support=(0.2, 0.8))], cfg),
        'unbound_waypoint': (p, [UnboundWaypoint(cart, mid + [0.5, 0.8], 0.15)], cfg),
        'waypoint': (p, [Waypoint(cart, mid + [0, 1.0], 0.2, support=(0.45, 0.55))], cfg),
        'corner': (p, [NonConvexCorner(cart, [1, 0], mid - [0.5, 0.5], [0, -1], mid + [0, 0.3],
                                       support=(0.2, 0.8))], cfg),
        'joint_limit': (p, [JointLimit(1, -0.8, 0.6, support=(0.1, 0.9))], cfg),
    }
    for table, K in (('table2', 1), ('table2', 3), ('table4', 2)):
        q = make_problem(table, K, np.random.default_rng(K))
        out[f'{table}_{K}'] = (q.prior, q.constraints, q.config)
    return out


@pytest.mark.parametrize('name', sorted(_solver_problems()))
def test_solver_gives_the_same_solution_with_either_evaluation(name, monkeypatch):
    prior, cons, cfg = _solver_problems()[name]
    monkeypatch.setattr(solver, 'Problem', functools.partial(Problem, evaluator='reference'))
    _, ref = solver.solve_levels(prior, cons, cfg)
    monkeypatch.setattr(solver, 'Problem', functools.partial(Problem, evaluator='batched'))
    _, rep = solver.solve_levels(prior, cons, cfg)
    assert rep.status == ref.status
    assert rep.n_evaluations == ref.n_evaluations
    assert rep.kl == pytest.approx(ref.kl, rel=1e-8)


def test_the_batched_evaluation_is_the_default(rng):
    """The batched evaluation is the default (1.26-1.36x per evaluation on the Panda
    problems); the reference stays the oracle of these tests."""
    assert Problem(_prior(rng), [], AdaptationConfig()).evaluator == 'batched'


def test_unknown_evaluator_is_refused(rng):
    from cdmp_ros.core.errors import ValidationError
    with pytest.raises(ValidationError, match='evaluator'):
        Problem(_prior(rng), [], AdaptationConfig(), evaluator='fast')
