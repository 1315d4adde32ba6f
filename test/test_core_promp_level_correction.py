"""The saddle point's check of the Gamma-matched link-point rows (AdaptationConfig.tail 'auto',
max_level_corrections): the check is the saddle-point law of the same moments, the corrected
levels follow their closed form, and a solve whose Gamma rows violate under the saddle point
ends with every checked row within its level under both laws, confirmed by sampling."""
import dataclasses

import numpy as np
import pytest

from cdmp_ros.core.adaptation.config import CHECKED_LAW, AdaptationConfig
from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.problem import Problem
from cdmp_ros.core.adaptation.solver import (MAX_LEVEL_RATIO, corrected_levels,
                                             monte_carlo_satisfaction, solve_levels)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import panda_chain
from cdmp_ros.experiments.promp_problems import panda_problem
from cdmp_ros.sim.robot_specs import panda_urdf_path


@pytest.fixture(scope='module')
def chain():
    return panda_chain(panda_urdf_path())


def _problem(chain, seed=1, n_spheres=3):
    return panda_problem(chain, np.random.default_rng(seed), n_spheres=n_spheres)


def test_corrected_levels_closed_form():
    cfg = AdaptationConfig()
    asked = np.full(4, 0.999)
    alpha = asked.copy()
    # Gamma violations at the solution; the saddle point's: 3x, equal, 1.5x below allowed, 100x
    F = 1.0 - np.array([1e-3, 8e-4, 5e-4, 1e-3])
    F_check = 1.0 - np.array([3e-3, 8e-4, 7.5e-4, 0.1])
    checked = np.array([True, True, True, True])
    new = corrected_levels(alpha, asked, F, F_check, checked, cfg)
    v = 1.0 - new
    k = 1.0 + cfg.feasibility_tol / 1e-3                    # the stopping rule's tolerance
    assert v[0] == pytest.approx(1e-3 * 1e-3 / (3e-3 * k))  # (1 - alpha) v_g / (v_s k)
    assert v[1] == pytest.approx(1e-3) and v[2] == pytest.approx(1e-3)   # within the level
    assert v[3] == pytest.approx(1e-3 / MAX_LEVEL_RATIO)     # the floor
    # an unchecked row is never corrected, however far its check
    assert corrected_levels(alpha, asked, F, F_check, np.zeros(4, bool), cfg) is None
    # never looser: at levels already at or below the target, nothing to do
    assert corrected_levels(new, asked, F, F_check, checked, cfg) is None
    # the next check: row 0's ratio of the two laws grew (3 -> 3.6): tightened again
    F1 = F.copy()
    F1[0] = 1.0 - v[0]
    F1c = F_check.copy()
    F1c[0] = 1.0 - 1.2e-3
    v1 = 1.0 - corrected_levels(new, asked, F1, F1c, checked, cfg)
    assert v1[0] == pytest.approx(1e-3 * v[0] / (1.2e-3 * k)) and np.all(v1[1:] == v[1:])
    tight = 1.0 - np.array([1e-4, 1e-3, 1e-3, 1e-3 / MAX_LEVEL_RATIO])
    # a row just above its level is corrected (the stopping rule's tolerance is no excuse)
    just = corrected_levels(alpha, asked, 1.0 - np.full(4, 1e-3), 1.0 - np.full(4, 1.01e-3),
                            checked, cfg)
    assert 1.0 - just == pytest.approx(np.full(4, 1e-3 / (1.01 * k)))
    assert corrected_levels(tight, asked, F, F_check, checked, cfg) is None
    # the margin: confidence_margin 0.5 allows half the violation
    half = dataclasses.replace(cfg, confidence_margin=0.5)
    F2 = 1.0 - np.array([5e-4, 4e-4, 4e-4, 4e-4])
    F2c = 1.0 - np.array([6e-4, 4e-4, 4e-4, 4e-4])
    v2 = 1.0 - corrected_levels(alpha, asked, F2, F2c, checked, half)
    assert v2[0] == pytest.approx(1e-3 * 5e-4 / (6e-4 * k))
    assert np.all(v2[1:] == pytest.approx(1e-3))


def test_check_values_are_the_saddle_point_law_of_the_same_moments(chain, rng):
    prior, cons, cfg = _problem(chain)
    auto = Problem(prior, cons, dataclasses.replace(cfg, tail='auto'))
    saddle = Problem(prior, cons, dataclasses.replace(cfg, tail='saddlepoint'))
    gamma = Problem(prior, cons, dataclasses.replace(cfg, tail='gamma'))
    theta = auto.initial_theta() + 0.05 * rng.standard_normal(auto.initial_theta().size)
    F_check, checked = auto.check_values(theta)
    mu, L, _ = auto.unpack(theta)
    F_auto = auto.constraint_values(mu, L)
    F_saddle = saddle.constraint_values(mu, L)
    F_gamma = gamma.constraint_values(mu, L)
    links = np.concatenate([np.full(s.stop - s.start, c.kind != 'joint_limit')
                            for c, s in zip(auto.constraints, auto.slices)])
    assert np.array_equal(checked, links) and checked.any()
    np.testing.assert_allclose(F_check[checked], F_saddle[checked], rtol=0, atol=1e-12)
    np.testing.assert_allclose(F_auto[checked], F_gamma[checked], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(F_check[~checked], F_auto[~checked])
    # the laws differ there (else the check would prove nothing)
    assert np.max(np.abs(F_saddle[checked] - F_gamma[checked])) > 1e-6
    # no check without the Gamma match
    assert not saddle.check_values(theta)[1].any()


def test_a_solve_whose_gamma_rows_violate_under_the_saddle_point_is_corrected(chain):
    prior, cons, cfg = _problem(chain)
    plain, rep0 = solve_levels(prior, cons, dataclasses.replace(cfg, max_level_corrections=0))
    fixed, rep = solve_levels(prior, cons, cfg)
    assert rep0.converged and rep.converged
    assert rep0.n_level_corrections == 0 and rep.n_level_corrections >= 1
    worst0 = max(1.0 - c.probability for c in rep0.constraints if c.checked)
    assert worst0 > 1.0 - 0.999 + cfg.feasibility_tol     # the Gamma match alone: too light
    for c in rep.constraints:
        assert c.satisfied, c
        assert c.checked == (c.kind != 'joint_limit')
    # the reported probability is the lower of the two laws, recomputed independently
    prob = Problem(prior, cons, dataclasses.replace(cfg, tail='saddlepoint'))
    F_saddle = prob.constraint_values(fixed.mean_w, np.linalg.cholesky(fixed.cov_w))
    for c, sl in zip(prob.constraints, prob.slices):
        r = next(x for x in rep.constraints if x.name == c.name)
        if r.checked:
            assert r.probability <= float(np.min(F_saddle[sl])) + 1e-9
            assert float(np.min(F_saddle[sl])) >= 0.999 - cfg.feasibility_tol
    # sampled through the kinematics: the corrected solution's worst link step is within
    # 1 - alpha (200,000 trajectories; the Gamma match alone: 1.6 x on this problem)
    links = [c for c in cons if c.kind != 'joint_limit']
    S0 = monte_carlo_satisfaction(plain, links, 200_000, np.random.default_rng(5), cfg.n_steps)[0]
    S = monte_carlo_satisfaction(fixed, links, 200_000, np.random.default_rng(5), cfg.n_steps)[0]
    assert 1.0 - S.min() <= 1.0 - 0.999 < 1.0 - S0.min()
    assert 'saddle-point checked' in rep.to_text() and 'corrected by the saddle point' in \
        rep.to_text()
    d = rep.as_dict()
    assert d['n_level_corrections'] == rep.n_level_corrections
    assert {c['name']: c['law'] for c in d['constraints']} == {
        c.name: ('gaussian' if c.kind == 'joint_limit' else CHECKED_LAW) for c in cons}
    # the laws of the other settings
    _, rep_s = solve_levels(prior, cons, dataclasses.replace(cfg, tail='saddlepoint'))
    assert {c.law for c in rep_s.constraints} == {'gaussian', 'saddlepoint'}


def test_the_correction_keeps_the_guarantee_of_adapt(chain):
    prior, cons, cfg = _problem(chain)
    _, rep = adapt(prior, cons, cfg)
    assert rep.converged and rep.verification.holds and rep.n_level_corrections >= 1


def test_max_level_corrections_is_checked():
    for bad in (-1, 11, 1.5, True, 'two'):
        with pytest.raises(ValidationError, match='max_level_corrections'):
            AdaptationConfig(max_level_corrections=bad)
    assert AdaptationConfig(max_level_corrections=0).max_level_corrections == 0
