"""Per-step calibration of the constrained ProMP at default settings (issue 12 item 2): on
Table II, III and IV problems (../shared/promp_benchmark_protocol.md), with no margin setting,
the sampled per-step violation of every constraint is <= 1.1 (1 - alpha) in at least 95 % of
the problems; the paper's Gamma tail (``tail='gamma'``) is not when the optimiser aims exactly
at alpha.

Sampling noise: with n samples, a constraint whose true violation is 1.1 (1 - alpha) at every
step shows a count above ``binom.isf(1e-3 / n_steps, n, 1.1 (1 - alpha))`` at some step with
probability <= 1e-3 (one-sided binomial bound, Bonferroni over the steps), so a problem is
counted as calibrated when every constraint's largest per-step count is below that bound.
Everything is seeded: the same problems and samples on every run.
"""
import numpy as np
from scipy import stats

from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.experiments.promp_problems import ALPHA, make_problem, sampled_violations

N_SAMPLES = 200_000


def _bound(n_steps: int) -> float:
    """Largest per-step violation frequency a calibrated constraint shows (see the module)."""
    return stats.binom.isf(1e-3 / n_steps, N_SAMPLES, 1.1 * (1.0 - ALPHA)) / N_SAMPLES


def _solve(table: str, K: int, seed: int, **config):
    """(calibrated by an independent sample, the adaptation report)."""
    import dataclasses
    p = make_problem(table, K, np.random.default_rng(seed), relative_step=True)
    cfg = dataclasses.replace(p.config, **config)
    q, rep = adapt(p.prior, p.constraints, cfg)
    per_step, _, _ = sampled_violations(q, p, np.random.default_rng(seed + 1), N_SAMPLES)
    return bool(np.all(per_step <= _bound(cfg.n_steps))), rep


def _calibrated(table: str, K: int, seed: int, **config) -> bool:
    good, rep = _solve(table, K, seed, **config)
    assert rep.converged, rep.to_text()  # converged includes the report's own sampled check
    return good


def test_per_step_violation_is_calibrated_at_default_settings():
    cases = [(table, 1 + i % 3, 100 + 7 * i) for table in ('table2', 'table3', 'table4')
             for i in range(7)]
    ok = [_calibrated(*case) for case in cases]
    failed = [case for case, good in zip(cases, ok) if not good]
    # at least 95 % of the problems: 1 of these 21 may miss
    assert len(failed) <= int(0.05 * len(cases)), failed


def test_calibrated_when_aiming_exactly_at_alpha_where_the_gamma_tail_is_not():
    """With the multipliers starting low (lambda0 = 1) and aiming exactly at alpha
    (violation_target = 1, no overshoot), the saddle-point tail still passes the check on
    Table II problems and the paper's Gamma moment match fails it (so the check can fail, and
    the tail is what makes it pass)."""
    cases = [('table2', 1 + i % 3, 100 + 7 * i) for i in range(4)]
    exact = dict(violation_target=1.0, lambda0=1.0)
    assert all(_calibrated(*case, **exact) for case in cases)
    gamma = [_solve(*case, tail='gamma', **exact) for case in cases]
    assert sum(not good for good, _ in gamma) >= 2, [good for good, _ in gamma]
    # the report does not claim what the sample refutes: a miscalibrated Gamma solution is
    # reported as verification_failed by the report's own sampled check
    for good, rep in gamma:
        assert good or rep.status == 'verification_failed', rep.to_text()
