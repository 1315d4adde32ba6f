"""The saddle point's check of the Gamma-matched link-point rows (AdaptationConfig.tail
'auto', max_level_corrections, check_law 'saddlepoint'): the check is the saddle-point law of
the same moments, the corrected levels follow their closed form, and a solve whose Gamma rows
violate under the saddle point ends with every checked row within its level under both laws,
confirmed by sampling; a warm start carries the levels the check implied (SolverState.levels)
and, for a nearby problem, needs no re-solve of its own."""
import dataclasses

import numpy as np
import pytest

from cdmp_ros.core.adaptation.config import CHECKED_LAW, AdaptationConfig
from cdmp_ros.core.adaptation.constraints import Repeller
from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.problem import Problem
from cdmp_ros.core.adaptation.solver import (CARRY_FRACTION, MAX_LEVEL_RATIO, carried_levels,
                                             corrected_levels, implied_levels,
                                             monte_carlo_satisfaction, solve_levels)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import panda_chain
from cdmp_ros.experiments.promp_problems import panda_problem
from cdmp_ros.sim.robot_specs import panda_urdf_path


@pytest.fixture(scope='module')
def chain():
    return panda_chain(panda_urdf_path())


def _problem(chain, seed=1, n_spheres=3):
    """The Panda problem with the saddle point's check (``check_law``; the importance-sampled
    check, the default, has its tests in test_core_tail_sampling.py)."""
    prior, cons, cfg = panda_problem(chain, np.random.default_rng(seed), n_spheres=n_spheres)
    return prior, cons, dataclasses.replace(cfg, check_law='saddlepoint')


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


def test_implied_levels_closed_form():
    cfg = AdaptationConfig()
    asked = np.full(5, 0.999)
    k = 1.0 + cfg.feasibility_tol / 1e-3
    # Gamma and saddle-point violations at a solution: ratio 3; at the level; the saddle point
    # lighter than the Gamma match; far from the level (below CARRY_FRACTION); 100x
    F = 1.0 - np.array([2e-4, 1e-3, 6e-4, 1e-6, 1e-3])
    F_check = 1.0 - np.array([6e-4, 1e-3, 3e-4, 0.5 * CARRY_FRACTION * 1e-3, 0.1])
    checked = np.ones(5, bool)
    v = 1.0 - implied_levels(asked, F, F_check, checked, cfg)
    # the level of corrected_levels, from the ratio at the solution, not from the solve's level
    assert v[0] == pytest.approx(1e-3 * 2e-4 / (6e-4 * k))
    assert v[1] == pytest.approx(1e-3 / k)
    assert v[2] == pytest.approx(1e-3)             # never looser than asked
    assert v[3] == pytest.approx(1e-3)             # far from its level: the asked one
    assert v[4] == pytest.approx(1e-3 / MAX_LEVEL_RATIO)   # the floor
    # unchecked rows keep the asked level
    assert np.array_equal(implied_levels(asked, F, F_check, np.zeros(5, bool), cfg), asked)
    # the same level as corrected_levels where that one tightens (a row over its level); row
    # 0 is within its level, so this solve needs no correction, but a next solve where it binds
    # under the Gamma match would (the ratio 3 stays): it starts at the implied level
    c = corrected_levels(asked, asked, F, F_check, checked, cfg)
    assert 1.0 - c[4] == pytest.approx(v[4]) and c[0] == asked[0]


def test_carried_levels_tighten_by_name_and_size(chain):
    prior, cons, cfg = _problem(chain)
    prob = Problem(prior, cons, cfg)
    c0, sl0 = prob.constraints[-1], prob.slices[-1]
    n = sl0.stop - sl0.start
    tighter = np.full(n, 0.9999)
    looser = np.full(n, 0.9)
    alpha = carried_levels(prob, ((c0.name, tighter), ('no such constraint', tighter)))
    assert np.all(alpha[sl0] == 0.9999)
    np.testing.assert_array_equal(np.delete(alpha, np.arange(sl0.start, sl0.stop)),
                                  np.delete(prob.alpha, np.arange(sl0.start, sl0.stop)))
    # never looser than asked; a size that does not match is ignored
    assert np.array_equal(carried_levels(prob, ((c0.name, looser),)), prob.alpha)
    assert np.array_equal(carried_levels(prob, ((c0.name, tighter[:-1]),)), prob.alpha)
    assert np.array_equal(carried_levels(prob, ()), prob.alpha)


def test_a_warm_start_carries_the_implied_levels(chain):
    """A solve that needed the correction hands its implied levels to the next solve
    (SolverState.levels); a warm start solves those rows at them (the Gamma match then sits
    within the carried level, not the asked one), and, for the obstacles moved by 2 cm, ends
    with every checked row within its level under the saddle point without a re-solve where
    the same warm start without the levels needed one; sampling confirms the level."""
    prior, cons, cfg = _problem(chain, seed=2)
    _, rep = solve_levels(prior, cons, cfg)
    assert rep.converged and rep.n_level_corrections >= 1
    carried = dict(rep.state.levels)
    assert carried and set(carried) <= {c.name for c in cons if c.kind != 'joint_limit'}
    for levels in carried.values():
        assert np.all(levels >= 0.999) and np.any(levels > 0.999)
    # the warm solve honours levels it is handed: here 0.9999 on every sphere row
    strict = dataclasses.replace(rep.state, levels=tuple(
        (c.name, np.full(cfg.n_steps, 0.9999)) for c in cons if c.kind == 'repeller'))
    strict_sol, rep_s = solve_levels(prior, cons, dataclasses.replace(
        cfg, max_level_corrections=0), start=strict)
    prob = Problem(prior, cons, dataclasses.replace(cfg, tail='gamma'))
    F = prob.constraint_values(strict_sol.mean_w, np.linalg.cholesky(strict_sol.cov_w))
    rows = np.concatenate([np.full(s.stop - s.start, c.kind == 'repeller')
                           for c, s in zip(prob.constraints, prob.slices)])
    assert rep_s.converged and np.min(F[rows]) >= 0.9999 - 2 * cfg.feasibility_tol
    # the obstacles moved by 2 cm
    moved = [Repeller(c.point, c.center - 0.02, c.radius, alpha=c.alpha, name=c.name)
             if c.kind == 'repeller' else c for c in cons]
    assert sum(c.kind == 'repeller' for c in moved) == 6
    _, rep_0 = solve_levels(prior, moved, cfg, start=dataclasses.replace(rep.state, levels=()))
    warm, rep_w = solve_levels(prior, moved, cfg, start=rep.state)
    assert rep_w.converged and rep_w.start == 'warm'
    assert rep_0.n_level_corrections >= 1 and rep_w.n_level_corrections == 0
    for c in rep_w.constraints:
        assert c.satisfied, c
    links = [c for c in moved if c.kind != 'joint_limit']
    S = monte_carlo_satisfaction(warm, links, 200_000, np.random.default_rng(6), cfg.n_steps)[0]
    assert 1.0 - S.min() <= 1.0 - 0.999
