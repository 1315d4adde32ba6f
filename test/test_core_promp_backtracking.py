"""The outer loop's backtracking of an overshooting multiplier step (solver module docstring),
checked on a scripted sequence of inner-loop results: which iterate a backtrack returns to,
with which multipliers, and that a jump the next outer iteration recovers from is kept.

The inner loop (scipy's L-BFGS) and the constraint values at its results are replaced by a
script, so the test does not depend on the rounding of a real solve: the two Panda requests
that showed the behaviour (test_core_adapt_requests.py, CROSSING and RECOVERING) flip between
backtracking and not with the last bit of their inputs, and so with the BLAS of the machine.
"""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from cdmp_ros.core.adaptation import solver
from cdmp_ros.core.adaptation.config import AdaptationConfig
from cdmp_ros.core.adaptation.constraints import JointLimit
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


@pytest.fixture
def problem():
    rng = np.random.default_rng(0)
    T = np.linspace(0.0, 1.0, 30)
    demos = [(T, np.column_stack([np.sin(np.pi * T) + 0.05 * rng.standard_normal(T.size)]))
             for _ in range(6)]
    prior = ProMP.fit(demos, RbfBasis.uniform(5), prior_strength=2.0)
    cons = [JointLimit(0, None, 0.8, alpha=0.999, name='upper')]
    cfg = AdaptationConfig(n_steps=20, stop_rule='feasible', max_level_corrections=0)
    return prior, cons, cfg


def _script(monkeypatch, worst_sequence):
    """Replace the inner loop and the constraint values: the k-th inner loop returns the
    start theta plus k * 1e-3 (a marker) and its iterate has largest violation
    ``worst_sequence[k]`` of the stopping level; returns the list of (theta, multipliers) each
    inner loop started from."""
    calls = []
    worst_of = {}

    def fake_minimize(fun, theta, args=(), **_):
        k = len(calls)
        calls.append((np.array(theta, copy=True), np.array(args[0], copy=True)))
        x = np.asarray(theta, float) + (k + 1) * 1e-3
        worst_of[x.tobytes()] = worst_sequence[min(k, len(worst_sequence) - 1)]
        return SimpleNamespace(x=x, jac=np.zeros_like(x), nit=1, fun=1.0)

    real_values = solver._values

    def fake_values(prob, theta):
        w = worst_of.get(np.asarray(theta, float).tobytes())
        if w is None:      # after the loop: the real values of the final theta
            return real_values(prob, theta)
        cfg = prob.config
        alpha_stop = 1.0 - cfg.confidence_margin * (1.0 - prob.alpha)
        return alpha_stop - w

    monkeypatch.setattr(solver, 'minimize', fake_minimize)
    monkeypatch.setattr(solver, '_values', fake_values)
    return calls


def test_an_overshooting_step_goes_back_to_the_iterate_before_the_jump(problem, monkeypatch):
    prior, cons, cfg = problem
    # 0.05, then a jump to 0.48 (> 2x and +0.05), not recovered (0.45), then feasible
    calls = _script(monkeypatch, [0.05, 0.48, 0.45, 0.0])
    _, rep = solver.solve_levels(prior, cons, cfg)
    assert rep.n_backtracks == 1 and rep.converged
    assert len(calls) == 4
    theta1 = calls[0][0] + 1e-3        # the iterate before the jump (first inner loop's)
    lam0, lam1 = calls[0][1], calls[1][1]   # its multipliers, and the step that made the jump
    assert np.all(lam1 > lam0)
    # the retry: from that iterate, with half the step in log
    np.testing.assert_array_equal(calls[3][0], theta1)
    np.testing.assert_allclose(calls[3][1], np.sqrt(lam0 * lam1), rtol=1e-15)
    assert rep.n_outer == 4


def test_a_jump_the_next_iteration_recovers_from_is_kept(problem, monkeypatch):
    prior, cons, cfg = problem
    calls = _script(monkeypatch, [0.05, 0.48, 0.0])
    _, rep = solver.solve_levels(prior, cons, cfg)
    assert rep.n_backtracks == 0 and rep.converged and len(calls) == 3
    # the third inner loop went on from the jump's iterate, not from the one before it
    np.testing.assert_array_equal(calls[2][0], calls[1][0] + 2e-3)


def test_small_or_proportionate_growth_is_no_jump(problem, monkeypatch):
    prior, cons, cfg = problem
    # doubled but by less than BACKTRACK_MIN; then grown by BACKTRACK_MIN but not 2x
    for seq in ([0.01, 0.03, 0.05, 0.0], [0.1, 0.16, 0.2, 0.0]):
        _script(monkeypatch, seq)
        _, rep = solver.solve_levels(prior, cons, cfg)
        assert rep.n_backtracks == 0 and rep.converged, seq


def test_backtracks_are_bounded(problem, monkeypatch):
    prior, cons, cfg = problem
    # every retry jumps again: at most MAX_BACKTRACKS, then the solve goes on
    seq = [0.05] + [0.48, 0.45] * (solver.MAX_BACKTRACKS + 2) + [0.0]
    _script(monkeypatch, seq)
    _, rep = solver.solve_levels(prior, cons, dataclasses.replace(cfg, max_outer=40))
    assert rep.n_backtracks == solver.MAX_BACKTRACKS
