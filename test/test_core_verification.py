"""Sampled verification of adapted ProMPs and the trajectory-level guarantee (issue 12 items 3
and 4): verify() against closed forms and independent Monte Carlo computations, the decision
rules, the report and ``converged``, and trajectory mode against per-step mode."""
import dataclasses

import numpy as np
import pytest
from scipy.stats import norm

from cdmp_ros.core.adaptation.config import AdaptationConfig, AdaptRequestConfig
from cdmp_ros.core.adaptation.constraints import (ChainPoint, DofPoint, Hyperplane, JointLimit,
                                                  NonConvexCorner, Repeller, UnboundWaypoint,
                                                  Waypoint)
from cdmp_ros.core.adaptation.guarantee import default_samples
from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.verification import (clopper_pearson_upper, critical_count,
                                                   detectable_violation,
                                                   trajectory_accepted, verify)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PointOfInterest, chain_from_urdf, panda_chain, planar_chain
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


def _promp_1d(M=8, var=0.5):
    return ProMP(1, RbfBasis.uniform(M), np.zeros(M), var * np.eye(M))


def _binomial_tol(p, n, k=5.0):
    return k * np.sqrt(max(p * (1 - p), 1e-6) / n)


def test_clopper_pearson_and_critical_count_closed_forms():
    n = 1000
    # k = 0: the upper bound solves (1 - p)^n = 0.05
    assert clopper_pearson_upper([0], n)[0] == pytest.approx(1 - 0.05 ** (1 / n), rel=1e-9)
    # k = n - 1: P(Bin(n, p) <= n - 1) = 1 - p^n = 0.05
    assert clopper_pearson_upper([n - 1], n)[0] == pytest.approx(0.95 ** (1 / n), rel=1e-9)
    assert clopper_pearson_upper([n], n)[0] == 1.0
    # critical count: the smallest c with P(Bin > c) <= level, checked by summing the pmf
    from scipy.stats import binom
    c = critical_count(20000, 1e-3, 1e-4)
    assert binom.sf(c, 20000, 1e-3) <= 1e-4 < binom.sf(c - 1, 20000, 1e-3)


@pytest.mark.parametrize('n', [1, 2, 10, 100, 1000, 2000, 10000, 20000])
def test_the_bounds_equal_scipy_stats(n):
    """The three binomial quantities come from scipy.special (the adapter does not import
    scipy.stats at its start); scipy.stats is their oracle, on a grid of counts and levels."""
    from scipy.stats import beta, binom
    k = np.unique(np.linspace(0, n, 12).astype(int))
    for conf in (0.5, 0.95, 0.99):
        np.testing.assert_allclose(clopper_pearson_upper(k, n, conf), np.where(
            k < n, beta.ppf(conf, k + 1.0, np.maximum(n - k, 1)), 1.0), rtol=1e-10)
    for p in (0.0, 1e-5, 1e-3, 0.05, 0.5, 1.0):
        for level in (1e-6, 1e-4, 0.01, 0.05, 0.5, 0.999):
            critical_count.cache_clear()
            c, ref = critical_count(n, p, level), int(binom.isf(level, n, p))
            # equal, or one apart where P(Bin > the smaller) equals the level to rounding
            assert c == ref or (abs(c - ref) == 1 and binom.sf(min(c, ref), n, p)
                                == pytest.approx(level, rel=1e-12)), (p, level, c, ref)
    for accepted in {0, n // 3, n - 1}:
        kk = accepted + 1
        assert detectable_violation(n, accepted, 0.9) == pytest.approx(
            beta.ppf(0.9, kk, n - kk + 1), rel=1e-10)


def test_single_step_matches_the_gaussian_closed_form():
    """1-D, one time step: the violation probability is 1 - Phi((b - m) / s)."""
    p = _promp_1d()
    t, b = 0.4, 0.9
    m, s = p.mean([t])[0, 0], np.sqrt(p.cov([t])[0, 0, 0])
    exact = 1.0 - norm.cdf((b - m) / s)
    n = 40000
    c = JointLimit(0, upper=b, support=(t, t), alpha=0.9, name='upper')
    v = verify(p, [c], n, np.random.default_rng(1), n_steps=11)
    cv = v.constraints[0]
    assert cv.steps == 1
    assert cv.per_step_max == cv.trajectory == v.trajectory_violation
    assert abs(cv.trajectory - exact) < _binomial_tol(exact, n), (cv.trajectory, exact)
    assert cv.upper95 >= cv.trajectory
    assert v.holds == (exact <= 0.1)


def test_trajectory_level_matches_an_independent_monte_carlo():
    """Whole support, several constraints: per-step maxima, per-constraint and union
    trajectory-level violations against a direct computation on sampled trajectories."""
    p = _promp_1d()
    grid = np.linspace(0.0, 1.0, 21)
    cons = [JointLimit(0, upper=1.2, alpha=0.99, name='up'),
            JointLimit(0, lower=-1.0, support=(0.3, 0.7), alpha=0.99, name='low')]
    n = 30000
    v = verify(p, cons, n, np.random.default_rng(2), n_steps=21)
    Y = p.sample_trajectories(grid, 200000, np.random.default_rng(3))[..., 0]
    up = Y > 1.2
    sel = (grid >= 0.3 - 1e-9) & (grid <= 0.7 + 1e-9)
    low = Y[:, sel] <= -1.0
    refs = [(up.mean(0).max(), up.any(1).mean()), (low.mean(0).max(), low.any(1).mean())]
    for cv, (step_ref, traj_ref) in zip(v.constraints, refs):
        assert abs(cv.trajectory - traj_ref) < _binomial_tol(traj_ref, n)
        assert abs(cv.per_step_max - step_ref) < _binomial_tol(step_ref, n)
    union = (up.any(1) | low.any(1)).mean()
    assert abs(v.trajectory_violation - union) < _binomial_tol(union, n)
    assert v.trajectory_violation >= max(cv.trajectory for cv in v.constraints)
    assert v.constraints[1].steps == int(sel.sum())


def test_known_violations_link_points_and_unbound_waypoints():
    """A nearly deterministic planar arm whose end effector passes through one sphere and far
    from another; an unbound waypoint on its path and one far away."""
    chain = planar_chain([1.0] * 2)
    M = 6
    mean = np.r_[np.linspace(0.0, 1.0, M), np.zeros(M)]
    p = ProMP(2, RbfBasis.uniform(M), mean, 1e-10 * np.eye(2 * M))
    ee = ChainPoint(chain, PointOfInterest('ee'), axes=(0, 1))
    x_mid = ee.forward(p.mean([0.5]))[0]
    cons = [Repeller(ee, x_mid, 0.05, alpha=0.99, name='hit'),
            Repeller(ee, [10.0, 10.0], 0.5, alpha=0.99, name='far'),
            UnboundWaypoint(ee, x_mid, 0.05, alpha=0.99, name='via'),
            UnboundWaypoint(ee, [10.0, 10.0], 0.5, alpha=0.99, name='never'),
            Hyperplane(DofPoint([1]), [1.0], [0.5], alpha=0.99, name='wall')]
    v = verify(p, cons, 500, np.random.default_rng(4), n_steps=41)
    got = {c.name: (c.per_step_max, c.trajectory) for c in v.constraints}
    assert got['hit'] == (1.0, 1.0) and got['far'] == (0.0, 0.0)
    assert got['via'] == (0.0, 0.0) and got['never'] == (1.0, 1.0)
    assert got['wall'] == (0.0, 0.0)
    assert v.trajectory_violation == 1.0 and not v.holds
    assert [c.holds for c in v.constraints] == [False, True, True, False, True]


def test_screen_bound_holds_for_revolute_and_prismatic_joints(tmp_path):
    """The screen's lemma (verification._KinematicGroup): |x(q) - x(r)| <= sum_j
    |J_j(r)| |q_j - r_j|, J_j the Jacobian column of joint j at the reference r; against
    forward kinematics for random pairs with small and large moves, on the Panda and on a
    chain with a prismatic joint. Single-joint moves of 1e-4 reach the bound (it is tight)."""
    import pybullet_data
    from test_core_kinematics import CUSTOM_URDF
    urdf = tmp_path / 'mixed.urdf'
    urdf.write_text(CUSTOM_URDF)
    chains = [(panda_chain(pybullet_data.getDataPath() + '/franka_panda/panda.urdf'),
               [PointOfInterest('ee'), PointOfInterest('panda_link4'),
                PointOfInterest('panda_link6', (0.05, -0.1, 0.02))]),
              (chain_from_urdf(str(urdf), 'tool'),
               [PointOfInterest('ee'), PointOfInterest('l3', (0.1, 0.2, 0.3))])]
    rng = np.random.default_rng(11)
    for chain, points in chains:
        lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
        hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
        for scale in (1e-3, 0.1, 1.0, 3.0):
            R = rng.uniform(lo, hi, (4000, chain.n_dofs))
            Q = R + rng.normal(0.0, scale, R.shape)
            Xr, J = chain.forward_and_jacobian(R, points)
            bound = np.einsum('bj,bpj->bp', np.abs(Q - R), np.linalg.norm(J, axis=2))
            moved = np.linalg.norm(chain.forward(Q, points) - Xr, axis=-1)
            assert np.all(moved <= bound * (1 + 1e-9) + 1e-12), np.max(moved - bound)
        R = rng.uniform(lo, hi, (200, chain.n_dofs))
        Xr, J = chain.forward_and_jacobian(R, points)
        rho = np.linalg.norm(J, axis=2)
        for j in range(chain.n_dofs):
            Q = R.copy()
            Q[:, j] += 1e-4
            moved = np.linalg.norm(chain.forward(Q, points) - Xr, axis=-1)
            np.testing.assert_allclose(moved, 1e-4 * rho[:, :, j], rtol=1e-3, atol=1e-12)


def test_curvature_bound_holds_and_is_not_vacuous(tmp_path):
    """Chain.curvature_bound (the first-order screen's lemma): |x(q) - x(r) - J(r)(q - r)| <=
    1/2 sum_jk M_jk |q_j - r_j| |q_k - r_k| against forward kinematics for random pairs with
    small and large moves, on the Panda (points on the hand, a link and off a link's axis) and
    on a planar arm; the worst remainder reaches more than half the bound; a chain with a
    prismatic joint has none."""
    import pybullet_data
    from test_core_kinematics import CUSTOM_URDF
    chains = [(panda_chain(pybullet_data.getDataPath() + '/franka_panda/panda.urdf'),
               [PointOfInterest('ee'), PointOfInterest('panda_link4'),
                PointOfInterest('panda_link6', (0.05, -0.1, 0.02))]),
              (planar_chain([1.0, 0.8, 0.5]), [PointOfInterest('ee'),
                                               PointOfInterest('link2', (0.1, 0.2, 0.0))])]
    rng = np.random.default_rng(12)
    for chain, points in chains:
        M = chain.curvature_bound(points)
        assert M.shape == (len(points), chain.n_dofs, chain.n_dofs)
        np.testing.assert_array_equal(M, M.transpose(0, 2, 1))
        lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
        hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
        worst = 0.0
        for scale in (1e-3, 0.05, 0.3, 1.0, 3.0):
            R = rng.uniform(lo, hi, (4000, chain.n_dofs))
            Q = R + rng.normal(0.0, scale, R.shape)
            Xr, J = chain.forward_and_jacobian(R, points)
            rem = np.linalg.norm(chain.forward(Q, points) - Xr
                                 - np.einsum('bpkj,bj->bpk', J, Q - R), axis=-1)
            a = np.abs(Q - R)
            bound = 0.5 * np.einsum('bj,pjk,bk->bp', a, M, a)
            assert np.all(rem <= bound * (1 + 1e-9) + 1e-12), np.max(rem - bound)
            worst = max(worst, float(np.max(rem / np.maximum(bound, 1e-300))))
        assert worst > 0.5, worst    # nearly tight (0.98 and 1.0 when written)
    urdf = tmp_path / 'mixed.urdf'
    urdf.write_text(CUSTOM_URDF)
    assert chain_from_urdf(str(urdf), 'tool').curvature_bound([PointOfInterest('ee')]) is None


def test_screen_gives_the_verdicts_of_the_full_kinematics(monkeypatch):
    """verify() with the screen (kinematics only where a ball around the mean's points, or
    around their first-order prediction, leaves a verdict open) reports exactly what it reports
    without it, with either screen, on a planar arm whose sampled paths
    cross spheres, a wall and the limits (so that all three cases occur: certainly
    satisfied, certainly violated, open); and it did skip work. A point with a constraint
    that has no screen (a corner) makes its group evaluated in full. The chunks evaluated on
    two threads give the reports of one thread."""
    import cdmp_ros.core.adaptation.verification as verification
    monkeypatch.setattr(verification, 'THREADS', 2)
    chain = planar_chain([1.0, 0.8, 0.5])
    M = 6
    rng = np.random.default_rng(5)
    mean = np.r_[np.linspace(0.0, 1.2, M), np.linspace(0.3, 0.9, M), np.zeros(M)]
    A = rng.normal(0.0, 1.0, (3 * M, 3 * M))
    p = ProMP(3, RbfBasis.uniform(M), mean, 0.0005 * A @ A.T + 1e-4 * np.eye(3 * M))
    ee = ChainPoint(chain, PointOfInterest('ee'), axes=(0, 1))
    elbow = ChainPoint(chain, PointOfInterest('link2'), axes=(0, 1))
    x = ee.forward(p.mean([0.2, 0.5, 0.8]))
    xe = elbow.forward(p.mean([0.5]))[0]
    top = ee.forward(p.mean(np.linspace(0.0, 1.0, 41)))[:, 1].max()
    cons = [Repeller(ee, x[1], 0.15, alpha=0.99, name='hit'),
            Waypoint(ee, x[2], 0.3, support=(0.7, 0.9), alpha=0.9, name='near'),
            UnboundWaypoint(ee, x[0], 0.05, alpha=0.9, name='via'),
            Hyperplane(ee, [0.0, 1.0], [0.0, top + 0.03], alpha=0.99, name='wall'),
            Repeller(elbow, xe + [0.05, 0.0], 0.1, alpha=0.99, name='elbow'),
            JointLimit(2, -0.2, 0.2, alpha=0.99, name='limit')]
    for seed in range(3):
        screened = verify(p, cons, 3000, np.random.default_rng(seed), n_steps=41)
        full = verify(p, cons, 3000, np.random.default_rng(seed), n_steps=41, screen=False)
        one = verify(p, cons, 3000, np.random.default_rng(seed), n_steps=41, threads=1)
        assert screened.constraints == full.constraints == one.constraints
        assert screened.kinematics_fraction == one.kinematics_fraction
        assert screened.trajectory_violation == full.trajectory_violation
        assert 0.0 < screened.kinematics_fraction < 0.9, screened.kinematics_fraction
        assert full.kinematics_fraction == 1.0
    # without the unbound waypoint every group holds per step: its constraints are evaluated
    # on the undecided (sample, step) pairs only (_KinematicGroup.violations)
    # a sphere that moves along the elbow's mean path: each pair is evaluated at its own time
    moving = Repeller(elbow, lambda t: elbow.forward(p.mean(t)) + [0.04, 0.0], 0.06,
                      alpha=0.99, name='moving')
    per_step = [c for c in cons if c.name != 'via'] + [moving]
    groups = verification._kinematic_groups(p, per_step, np.linspace(0.0, 1.0, 41), True)
    assert groups and all(g.pairs for g in groups)
    assert not all(g.pairs for g in verification._kinematic_groups(
        p, cons, np.linspace(0.0, 1.0, 41), True))
    for seed in range(2):
        pairs = verify(p, per_step, 3000, np.random.default_rng(seed), n_steps=41)
        full = verify(p, per_step, 3000, np.random.default_rng(seed), n_steps=41, screen=False)
        assert pairs.constraints == full.constraints
        assert pairs.trajectory_violation == full.trajectory_violation
        assert 0.0 < pairs.kinematics_fraction < 0.9, pairs.kinematics_fraction
        assert 0.0 < pairs.constraints[-1].per_step_max < 1.0, pairs.constraints[-1]
    got = {c.name: c for c in screened.constraints}
    # the cases the screen must keep apart all occur: steps violated by some samples only
    for name in ('hit', 'near', 'elbow', 'limit', 'via'):
        assert 0.0 < got[name].per_step_max < 1.0, (name, got[name])
    assert 0.0 < got['wall'].trajectory < 1.0, got['wall']
    # the zeroth-order screen (a chain with a prismatic joint has no curvature bound): the
    # same reports, with more pairs left to the kinematics
    monkeypatch.setattr(type(chain), 'curvature_bound', lambda self, points: None)
    zeroth = verify(p, cons, 3000, np.random.default_rng(0), n_steps=41)
    monkeypatch.undo()
    monkeypatch.setattr(verification, 'THREADS', 2)
    first = verify(p, cons, 3000, np.random.default_rng(0), n_steps=41)
    assert zeroth.constraints == first.constraints
    assert zeroth.trajectory_violation == first.trajectory_violation
    assert first.kinematics_fraction < 0.5 * zeroth.kinematics_fraction, (
        first.kinematics_fraction, zeroth.kinematics_fraction)
    assert zeroth.kinematics_fraction < 0.9
    corner = NonConvexCorner(ee, [1.0, 0.0], [5.0, 0.0], [0.0, 1.0], [0.0, 5.0], alpha=0.99,
                             name='corner')
    v = verify(p, cons + [corner], 500, np.random.default_rng(0), n_steps=41)
    ref = verify(p, cons + [corner], 500, np.random.default_rng(0), n_steps=41, screen=False)
    assert v.constraints == ref.constraints
    # the end effector's group runs in full; 'near', on its own time grid, is still screened
    assert screened.kinematics_fraction < v.kinematics_fraction < 1.0


def test_per_step_rule_passes_a_calibrated_solution_and_fails_twice_the_level():
    """One step at exactly its level passes; at twice the level it fails (20,000 samples)."""
    p = _promp_1d()
    t = 0.5
    m, s = p.mean([t])[0, 0], np.sqrt(p.cov([t])[0, 0, 0])
    eps = 0.002
    at_level = JointLimit(0, upper=m + s * norm.isf(eps), support=(t, t), alpha=1 - eps)
    twice = JointLimit(0, upper=m + s * norm.isf(2 * eps), support=(t, t), alpha=1 - eps)
    passed = [verify(p, [at_level], 20000, np.random.default_rng(k), 11).holds
              for k in range(20)]
    assert sum(passed) >= 19, passed      # the rule's family-wise level is 1 %
    failed = [not verify(p, [twice], 20000, np.random.default_rng(k), 11).holds
              for k in range(20)]
    assert sum(failed) >= 19, failed


@pytest.mark.parametrize('n, accepted', [(1000, 0), (1000, 3), (2000, 12), (20000, 70)])
def test_detectable_violation_has_95_percent_power_by_sampling(n, accepted):
    """At the reported p the rule 'reject when count > accepted' rejects 95 % of 400,000
    sampled binomial counts; at 0.9 p clearly less (the smallest such p)."""
    p = detectable_violation(n, accepted)
    rng = np.random.default_rng(n + accepted)
    power = np.mean(rng.binomial(n, p, 400_000) > accepted)
    assert abs(power - 0.95) < 0.003, (p, power)
    assert np.mean(rng.binomial(n, 0.9 * p, 400_000) > accepted) < 0.94
    assert detectable_violation(n, n) == 1.0


@pytest.mark.parametrize('n, level', [(1000, 0.01), (2000, 0.05), (10000, 0.001), (50, 0.01)])
def test_trajectory_accepted_is_the_largest_count_the_upper_bound_passes(n, level):
    ks = np.arange(n + 1)
    passing = ks[clopper_pearson_upper(ks, n) <= level]
    assert trajectory_accepted(n, level) == (passing.max() if passing.size else -1)


def test_verification_reports_what_its_test_detects_and_catches_it():
    """A one-step constraint violated exactly at the reported detectable probability fails
    the sampled verification in about 95 % of 300 seeds; the report states it as a multiple
    of the asked level, with the per-step rule (Bonferroni over the tested steps) and the
    conservative trajectory rule (below 1)."""
    p = _promp_1d()
    t = 0.5
    m, s = p.mean([t])[0, 0], np.sqrt(p.cov([t])[0, 0, 0])
    eps, n = 0.01, 2000
    asked = JointLimit(0, upper=m + s * norm.isf(eps), support=(t, t), alpha=1 - eps)
    rep = verify(p, [asked], n, np.random.default_rng(0), 11)
    c = rep.constraints[0]
    assert c.detectable == detectable_violation(n, critical_count(n, eps, 0.01 / c.steps))
    assert c.detectable_excess == pytest.approx(c.detectable / eps)
    assert 1.0 < c.detectable_excess < 3.0 and rep.detectable_excess == c.detectable_excess
    assert 'detects' in rep.to_text()
    at_detectable = JointLimit(0, upper=m + s * norm.isf(c.detectable), support=(t, t),
                               alpha=1 - eps)
    caught = np.mean([not verify(p, [at_detectable], n, np.random.default_rng(k), 11).holds
                      for k in range(300)])
    assert 0.91 <= caught <= 0.99, caught
    # more tested steps: a harder Bonferroni level, a larger detectable excess
    wide = JointLimit(0, upper=m + s * norm.isf(eps), support=(0.0, 1.0), alpha=1 - eps)
    assert verify(p, [wide], n, np.random.default_rng(0), 101).constraints[0]. \
        detectable_excess > c.detectable_excess
    traj = verify(p, [asked], n, np.random.default_rng(0), 11, guarantee='trajectory')
    tc = traj.constraints[0]
    assert tc.detectable == detectable_violation(n, trajectory_accepted(n, eps))
    assert tc.detectable_excess < 1.0


class _OptimisticLimit(JointLimit):
    """The optimiser sees a bound 1 higher than the samples are checked against."""

    def rows(self, times):
        r = super().rows(times)
        r['b'] = r['b'] + 1.0
        return r


def test_report_carries_the_verification_and_converged_requires_it():
    p = _promp_1d()
    ok = JointLimit(0, upper=0.8, alpha=0.99, name='honest')
    adapted, rep = adapt(p, [ok], AdaptationConfig(n_steps=21))
    assert rep.converged and rep.status == 'converged'
    d = rep.as_dict()['verification']
    assert d['n_samples'] == default_samples([ok], 21) == 10000
    assert set(d) >= {'n_samples', 'trajectory_violation', 'trajectory_violation_upper95',
                      'constraints'}
    assert set(d['constraints'][0]) >= {'name', 'per_step_max', 'trajectory', 'upper95'}
    assert d['constraints'][0]['name'] == 'honest'
    assert 'sampled verification' in rep.to_text()
    # the approximation is satisfied, the samples are not
    bad = _OptimisticLimit(0, upper=0.3, alpha=0.99, name='optimistic')
    adapted, rep = adapt(p, [bad], AdaptationConfig(n_steps=21))
    assert all(c.satisfied for c in rep.constraints)
    assert not rep.converged and rep.status == 'verification_failed'
    assert not rep.verification.constraints[0].holds
    # reproducible by default, another rng gives another sample
    _, r1 = adapt(p, [ok], AdaptationConfig(n_steps=21))
    _, r2 = adapt(p, [ok], AdaptationConfig(n_steps=21))
    assert r1.verification.as_dict()['constraints'] == r2.verification.as_dict()['constraints']


def test_trajectory_guarantee_meets_the_bound_where_per_step_does_not():
    """A 1-D ProMP under an upper limit over the whole movement (exact Gaussian CDFs): per-step
    mode holds each step at alpha but a trajectory crosses the limit at some step more often
    than 1 - alpha; trajectory mode brings the whole-trajectory violation below 1 - alpha, by
    an independent Monte Carlo check, at a larger KL."""
    p = _promp_1d()
    c = JointLimit(0, upper=0.5, alpha=0.99, name='upper')
    base = AdaptationConfig(n_steps=51, lambda0=0.01, max_outer=30)
    grid = np.linspace(0.0, 1.0, 51)
    results = {}
    for mode in ('per_step', 'trajectory'):
        q, rep = adapt(p, [c], dataclasses.replace(base, guarantee=mode))
        Y = q.sample_trajectories(grid, 200000, np.random.default_rng(11))[..., 0]
        results[mode] = (rep, float((Y > 0.5).any(axis=1).mean()), float((Y > 0.5).mean(0).max()))
    rep_s, traj_s, step_s = results['per_step']
    rep_t, traj_t, step_t = results['trajectory']
    assert rep_s.converged and rep_t.converged, (rep_s.to_text(), rep_t.to_text())
    assert step_s <= 0.01 and traj_s > 0.01, (step_s, traj_s)
    assert traj_t <= 0.01, traj_t
    assert rep_t.verification.guarantee == 'trajectory' and rep_t.verification.holds
    assert rep_t.verification.trajectory_violation_upper95 <= 0.01
    assert rep_t.n_solves >= 2 and rep_t.levels[0] < 0.01
    assert rep_t.constraints[0].alpha == 0.99          # the user's level is reported
    assert rep_t.kl > rep_s.kl


def test_trajectory_mode_rechecks_the_returned_solution_on_fresh_samples(monkeypatch):
    """The loop's checks select the solution; one more check on new samples of the returned
    distribution is the report's verification (and decides converged)."""
    from cdmp_ros.core.adaptation import guarantee
    calls = []

    def recording(promp, *args, **kw):
        ver = verify(promp, *args, **kw)
        calls.append((promp, ver))
        return ver
    monkeypatch.setattr(guarantee, 'verify', recording)
    p = _promp_1d()
    c = JointLimit(0, upper=0.5, alpha=0.99, name='upper')
    q, rep = adapt(p, [c], AdaptationConfig(n_steps=51, lambda0=0.01, max_outer=30,
                                            guarantee='trajectory'))
    assert len(calls) == rep.n_solves + 1
    assert calls[-1] == (q, rep.verification)
    chosen = [ver for promp, ver in calls[:-1] if promp is q]
    assert chosen == [rep.selection_verification]
    # other samples: the counts of the two checks of the same distribution differ
    a, b = rep.verification.constraints[0], rep.selection_verification.constraints[0]
    assert (a.per_step_max, a.trajectory) != (b.per_step_max, b.trajectory), (a, b)
    assert rep.converged == rep.verification.holds
    d = rep.as_dict()
    assert d['selection_verification']['n_samples'] == d['verification']['n_samples']
    assert 're-checked on fresh samples' in rep.to_text()


def test_guarantee_and_sample_settings_are_validated():
    with pytest.raises(ValidationError, match='guarantee'):
        AdaptationConfig(guarantee='always')
    with pytest.raises(ValidationError, match='verification_samples'):
        AdaptationConfig(verification_samples=0)
    with pytest.raises(ValidationError, match='max_refinements'):
        AdaptationConfig(max_refinements=-1)
    with pytest.raises(ValidationError, match='guarantee'):
        AdaptRequestConfig(guarantee='whole')
    assert AdaptRequestConfig(guarantee='trajectory').guarantee == 'trajectory'
    p = _promp_1d()
    c = JointLimit(0, upper=1.0)
    with pytest.raises(ValidationError, match='n_samples'):
        verify(p, [c], 0, np.random.default_rng(0))
    with pytest.raises(ValidationError, match='guarantee'):
        verify(p, [c], 10, np.random.default_rng(0), guarantee='sometimes')


def test_default_sample_count_follows_the_kinematics_cost():
    chain = planar_chain([1.0] * 4)
    ee = ChainPoint(chain, PointOfInterest('ee'), axes=(0, 1))
    elbow = ChainPoint(chain, PointOfInterest('link2'), axes=(0, 1))
    lin = [Repeller(DofPoint([0, 1]), [0, 0], 1.0, alpha=0.99)]
    assert default_samples(lin, 101) == 10000
    # without kinematics: enough samples to catch twice the asked level (the Table II setting)
    rng = np.random.default_rng(1)
    lin3 = [Repeller(DofPoint([0, 1]), rng.normal(size=2), 0.5, alpha=0.999) for _ in range(3)]
    n = default_samples(lin3, 101)
    assert n == 60000
    p = _promp_1d()
    grid_c = [JointLimit(0, upper=9.0, alpha=0.999, name=f'l{k}') for k in range(3)]
    assert default_samples(grid_c, 101) == 60000
    ver = verify(p, grid_c, n, np.random.default_rng(0), 101)
    assert 1.5 < ver.detectable_excess <= 2.0
    assert verify(p, grid_c, 40000, np.random.default_rng(0), 101).detectable_excess > 2.0
    # two link points of one chain share the forward kinematics: 100 FK evaluations / sample
    kin = [Repeller(ee, [0, 0], 1.0), Repeller(elbow, [0, 0], 1.0)]
    assert default_samples(kin, 100) == 1000
    assert default_samples(kin, 20) == 5000


def test_experiment_rows_report_the_verification():
    from cdmp_ros.experiments import exp_promp_tables
    from cdmp_ros.experiments.results import verification_rows
    rng = np.random.default_rng(0)
    recs = exp_promp_tables.solve_row('table2', 1, 2, rng, n_samples=2000, relative_step=True,
                                      guarantee='per_step')
    rows = {r['name']: r['ours'] for r in exp_promp_tables.summarise('table2', 1, recs)}
    for key in ('verified_per_step_max_pct_median', 'verified_trajectory_pct',
                'verified_trajectory_upper95_pct', 'verified_pct', 'verification_s_median'):
        assert rows[f'table2.obstacles_1.{key}'] is not None, key
    assert 0.0 <= rows['table2.obstacles_1.verified_trajectory_pct'] <= \
        rows['table2.obstacles_1.verified_trajectory_upper95_pct'] <= 100.0
    rep = recs[0]
    _, report = adapt(rep['problem'].prior, rep['problem'].constraints, rep['problem'].config)
    names = [r['name'] for r in verification_rows('x', report)]
    assert names == ['x.verified_per_step_max_pct', 'x.verified_trajectory_pct',
                     'x.verified_trajectory_upper95_pct', 'x.verified']


def test_mutual_avoidance_pairs_share_the_kinematics_of_their_points(monkeypatch):
    """The differences of chain points (mutual avoidance of two arms) are checked on positions
    computed once per arm for all the pairs' points: the same reports as each pair's own
    kinematics, with violations that occur (pairs near each other)."""
    import pybullet_data
    import cdmp_ros.core.adaptation.verification as verification
    from cdmp_ros.core.adaptation.constraints import MutualAvoidance
    from cdmp_ros.core.kinematics import dual_panda_chains
    chains = dual_panda_chains(pybullet_data.getDataPath() + '/franka_panda/panda.urdf',
                               distance=0.9)
    pts = [[ChainPoint(c, PointOfInterest(link), range(7 * a, 7 * a + 7))
            for link in ('ee', 'panda_hand', 'panda_link4')] for a, c in enumerate(chains)]
    M = 4
    rng = np.random.default_rng(3)
    A = rng.normal(0.0, 1.0, (14 * M, 14 * M))
    reach = np.r_[0.0, 0.6, 0.0, -1.2, 0.0, 1.8, 0.8]
    p = ProMP(14, RbfBasis.uniform(M), np.tile(reach, 2).repeat(M),
              0.002 * A @ A.T + 1e-3 * np.eye(14 * M))
    cons = [MutualAvoidance(pts[0][i], pts[1][j], 0.25, alpha=0.99, name=f'pair_{i}{j}')
            for i, j in ((0, 0), (0, 1), (1, 0), (2, 2))]
    cons.append(Hyperplane(pts[0][0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.1], alpha=0.99))
    # a constraint that keeps the screened group of pts[0][0] out of the per-step path: its
    # positions there are the screen's centres where it decided, valid for its own
    # constraints only (the pairs must not use them)
    tcp = pts[0][0].forward(p.mean(np.linspace(0.0, 1.0, 20))[:, :7])
    cons.append(UnboundWaypoint(pts[0][0], tcp[10], 0.05, alpha=0.9, name='via'))
    shared = verify(p, cons, 400, np.random.default_rng(0), n_steps=20, threads=1)
    full = verify(p, cons, 400, np.random.default_rng(0), n_steps=20, threads=1, screen=False)
    monkeypatch.setattr(verification, '_difference_ends', lambda *a: {})
    apart = verify(p, cons, 400, np.random.default_rng(0), n_steps=20, threads=1)
    assert shared.constraints == apart.constraints == full.constraints
    assert shared.trajectory_violation == apart.trajectory_violation
    assert any(0.0 < c.per_step_max for c in shared.constraints[:4]), shared.constraints
    assert 0.0 < shared.kinematics_fraction < 1.0, shared.kinematics_fraction
