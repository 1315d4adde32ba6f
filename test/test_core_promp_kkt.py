"""The outer loop's KKT stopping rule (AdaptationConfig.stop_rule='kkt') and the KKT residuals
of every report: the duality gap against an independent computation, complementary slackness
on Table II problems (the binding constraint sits at its level, checked by sampling), and KL
that falls when alpha is relaxed."""
import dataclasses

import numpy as np
import pytest

from cdmp_ros.core.adaptation.config import AdaptationConfig
from cdmp_ros.core.adaptation.solver import duality_gap, solve_levels
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.experiments.promp_problems import make_problem, sampled_violations


def table2(alpha, seed=1000, K=1, **config):
    pr = make_problem('table2', K, np.random.default_rng(seed), relative_step=True,
                      alpha=alpha)
    pr.config = dataclasses.replace(pr.config, max_outer=40, **config)
    return pr


def test_the_duality_gap_counts_only_slack_above_the_aim():
    lam = np.array([2.0, 0.5, 3.0, 0.0])
    F = np.array([0.999, 0.9, 0.95, 1.0])
    aim = np.array([0.99, 0.99, 0.95, 0.99])
    # by hand: 2 * 0.009 + 0 (below the aim: no slack) + 3 * 0 + 0 * 0.01
    assert duality_gap(lam, F, aim) == pytest.approx(0.018, abs=1e-15)
    assert duality_gap(np.zeros(0), np.zeros(0), np.zeros(0)) == 0.0


def test_config_refuses_an_unknown_stop_rule_and_a_bad_tolerance():
    with pytest.raises(ValidationError, match='stop_rule'):
        AdaptationConfig(stop_rule='optimal')
    with pytest.raises(ValidationError, match='kkt_tol'):
        AdaptationConfig(kkt_tol=0.0)
    with pytest.raises(ValidationError, match='kkt_log_decrease'):
        AdaptationConfig(kkt_log_decrease=-1.0)


def test_the_feasible_rule_stops_with_slack_the_kkt_rule_at_the_level():
    pr = table2(0.99)
    _, first = solve_levels(pr.prior, pr.constraints, pr.config)
    adapted, kkt = solve_levels(pr.prior, pr.constraints,
                                dataclasses.replace(pr.config, stop_rule='kkt'))
    assert first.converged and kkt.converged
    # the paper's rule stops at the first feasible iterate, far inside the level and with the
    # multipliers it started with paying for it
    assert not first.kkt.reached and first.kkt.gap_relative > 1.0
    assert first.kkt.binding[0] < 0.3
    # the KKT rule: complementary slackness within its tolerance, the constraint at about
    # violation_target of its allowed violation, and a lower KL
    assert kkt.kkt.reached and kkt.kkt.gap_relative <= pr.config.kkt_tol
    assert 0.5 <= kkt.kkt.binding[0] <= 1.0
    assert kkt.kl < 0.9 * first.kl
    assert kkt.kkt.feasibility == 0.0 and np.isfinite(kkt.kkt.stationarity)
    # the residuals reported are those of the returned multipliers and values
    lam = dict(kkt.state.multipliers)[pr.constraints[0].name]
    assert kkt.constraints[0].lagrange_max == pytest.approx(lam.max())
    # sampled: the per-step violation sits between 0.5 and 1.0 times 1 - alpha (200,000
    # trajectories: the worst step's estimate has a standard error of ~3 % of the level)
    per_step, _, _ = sampled_violations(adapted, pr, np.random.default_rng(5), 200_000)
    assert 0.5 * 0.01 <= per_step[0] <= 1.0 * 0.01, per_step


def test_relaxing_alpha_lowers_the_kl_under_the_kkt_rule():
    kls = []
    for alpha in (0.999, 0.99, 0.95):
        pr = table2(alpha, stop_rule='kkt')
        _, rep = solve_levels(pr.prior, pr.constraints, pr.config)
        assert rep.converged and rep.kkt.reached, (alpha, rep.status, rep.kkt)
        kls.append(rep.kl)
    assert kls[0] > kls[1] > kls[2], kls


def test_the_report_carries_the_residuals():
    pr = table2(0.99, stop_rule='kkt')
    _, rep = solve_levels(pr.prior, pr.constraints, pr.config)
    d = rep.as_dict()['kkt']
    assert set(d) == {'gap', 'gap_relative', 'stationarity', 'feasibility', 'binding',
                      'reached'}
    assert d['reached'] is True and len(d['binding']) == 1


def test_the_cli_offers_the_stop_rules_of_the_config():
    from cdmp_ros.cli import cmd_adapt
    from cdmp_ros.core.adaptation.config import STOP_RULES
    assert cmd_adapt.STOP_RULES == STOP_RULES
