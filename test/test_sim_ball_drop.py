"""Ball-drop scene and `cdmp reproduce ball-drop` (a short run; the full one is on request)."""
import json
import subprocess
import sys

import numpy as np
import pytest

from cdmp_ros.experiments import exp_ball_drop as E
from cdmp_ros.experiments.results import rows_by_name
from cdmp_ros.sim.ball_drop import BallDropScene, CupSpec


def test_ball_lands_in_cup_only_when_released_above_it():
    setup = E.make_setup()
    from cdmp_ros.core.kinematics.ik import solve_position_ik
    outcomes = []
    for offset in ([0.0, 0.0, 0.0], [-0.12, 0.0, 0.0]):
        target = np.asarray(CupSpec().position) + offset + [0.0, 0.0, E.RELEASE_HEIGHT]
        ik = solve_position_ik(setup.chain, setup.ee, target, E.Q_START, setup.lower,
                               setup.upper, margin=0.02)
        assert ik.converged
        T = np.linspace(0, 1.0, 501)
        s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
        Q = E.Q_START + np.outer(s, ik.q - E.Q_START)
        Qd = np.gradient(Q, T, axis=0)
        with BallDropScene(board=None) as scene:
            res = scene.execute(Q, Qd)
        np.testing.assert_allclose(res.release_position, target, atol=0.01)
        outcomes.append(res.success)
    assert outcomes == [True, False]


def test_coupling_keeps_hand_off_the_board():
    setup = E.make_setup()
    from cdmp_ros.sim.ball_drop import BoardSpec
    board = BoardSpec()
    prim = E.initial_policy(setup)
    free = prim.rollout(dt=0.004, duration=E.HORIZON)
    coupled = prim.rollout(dt=0.004, duration=E.HORIZON, **E.ee_board_coupling(setup, board))
    with BallDropScene(board=board, time_step=0.004) as scene:
        assert scene.execute(free.Y, free.Yd, free.Ydd).board_contact
        res = scene.execute(coupled.Y, coupled.Yd, coupled.Ydd)
        assert not res.board_contact
        assert not res.success  # the initial policy aims at the wrong cup position
    assert np.all(coupled.Y > setup.lower) and np.all(coupled.Y < setup.upper)


def test_initial_policy_leans_the_bounded_joint_across_its_range():
    """Joint 2 goes from -0.25 rad (leaning back) to near its upper bound 0.32 rad."""
    setup = E.make_setup()
    assert E.Q_START[E.BOUNDED_JOINT] == pytest.approx(-0.25)
    assert 0.25 < setup.q_goal_est[E.BOUNDED_JOINT] <= E.BOUND[1] - 0.02 + 1e-9
    est = setup.chain.forward(setup.q_goal_est, [setup.ee])[0]
    real = np.asarray(CupSpec().position) + [0.0, 0.0, E.RELEASE_HEIGHT]
    np.testing.assert_allclose(est - real, E.CUP_ERROR, atol=1e-3)


def test_lifting_field_takes_exploratory_rollouts_over_the_board():
    """With a purely normal repulsion some exploratory rollouts end held against the board on
    the start side (y > 0); with the lifted field every one crosses to the cup side."""
    from cdmp_ros.core.dmp.pi2 import Pi2
    from cdmp_ros.sim.ball_drop import BoardSpec
    setup = E.make_setup()
    prim = E.initial_policy(setup)
    pi2 = Pi2(prim, E.pi2_config(5), rng=np.random.default_rng(1), dt=0.004,
              duration=E.HORIZON)
    flat = E.ee_board_coupling(setup, BoardSpec(), lift=False)
    lifted = E.ee_board_coupling(setup, BoardSpec())
    held = 0
    for _ in range(2):
        for t in pi2.ask():
            ends = []
            for coupling in (flat, lifted):
                tr = prim.rollout(dt=0.004, duration=E.HORIZON, **coupling,
                                  weight_noise=t.shape_noise, goal_noise=t.goal_noise)
                ends.append(setup.chain.forward(tr.Y[-1], [setup.ee])[0])
            held += ends[0][1] > 0.0
            assert ends[1][1] < -0.05
    assert held >= 1


@pytest.mark.parametrize('runs, updates', [(1, 2)])
def test_reproduce_ball_drop_short(tmp_path, runs, updates):
    out = tmp_path / 'bd'
    proc = subprocess.run([sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'ball-drop',
                           '--out', str(out), '--runs', str(runs), '--updates', str(updates),
                           '--rollouts', '3'], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = rows_by_name(json.loads((out / 'results.json').read_text()))
    for name in ('first_success_trial', 'final_success_rate', 'limit_violations',
                 'bounded_joint.min_rad', 'bounded_joint.max_rad', 'runs_with_a_success',
                 'dmp_baseline.rollouts_leaving_limits', 'wall_time'):
        assert name in rows
    assert rows['limit_violations']['ours'] == 0
    assert E.BOUND[0] < rows['bounded_joint.min_rad']['ours'] <= rows[
        'bounded_joint.max_rad']['ours'] < E.BOUND[1]
    for png in ('cost_curve.png', 'bounded_joint.png', 'before.png', 'after.png'):
        assert (out / png).stat().st_size > 5000


@pytest.mark.benchmark
def test_reproduce_ball_drop_full(tmp_path):
    """The paper's protocol: 10 runs; every run learns to drop the ball, no violation."""
    out = tmp_path / 'bd'
    proc = subprocess.run([sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'ball-drop',
                           '--out', str(out)], capture_output=True, text=True, timeout=3600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = rows_by_name(json.loads((out / 'results.json').read_text()))
    assert rows['final_success_rate']['ours'] == 1.0
    assert rows['runs_with_a_success']['ours'] == 10
    assert rows['limit_violations']['ours'] == 0
