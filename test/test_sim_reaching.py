"""Paper 000, IV-B: the reaching experiment with link avoidance (cdmp reproduce reaching)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from coupling_oracle import end_effector_term, link_term
from cdmp_ros.core.kinematics import panda_chain, PointOfInterest
from cdmp_ros.experiments.reaching_coupling import (HoldGains, PANDA_LINK_RADIUS,
                                                    PANDA_SEGMENTS, ReachingCoupling,
                                                    board_field, board_obstacle)
from cdmp_ros.experiments.results import rows_by_name
from cdmp_ros.sim import World
from cdmp_ros.sim.scenes import build_reaching_scene, nominal_path
from closest_oracle import segment_obstacle

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope='module')
def scene():
    with World() as world:
        yield build_reaching_scene(world)


def test_board_obstacle_is_the_pybullet_board(scene):
    """The OrientedBox of the board has the pybullet board body's pose and extents."""
    import pybullet as p
    board = board_obstacle(scene.board)
    cid = scene.robot.world.client_id
    pos, orn = p.getBasePositionAndOrientation(scene.board.body_id, physicsClientId=cid)
    np.testing.assert_allclose(board.center, pos, atol=1e-9)
    np.testing.assert_allclose(np.array(board.rotation).ravel(),
                               p.getMatrixFromQuaternion(orn), atol=1e-9)
    np.testing.assert_allclose(board.half, scene.board.size, atol=1e-12)
    assert min(board.half) < 0.01 < max(board.half)          # a thin board, not a cube


def test_capsules_are_conservative_against_pybullet_meshes(scene):
    """The link capsules of the coupling report at most the mesh distance + 5 mm (they are
    conservative where it matters: up to 4 mm closer than the pybullet meshes), on the nominal
    motion and around the final configuration."""
    chain = panda_chain(scene.robot.spec.urdf_path)
    board = board_obstacle(scene.board)
    coupling = ReachingCoupling(chain, board_field(board, 1.0, 0.1))
    rng = np.random.default_rng(1)
    Q = list(nominal_path(scene.q_start, scene.q_goal, 21)[8:])
    Q += [scene.q_goal + rng.normal(0.0, 0.15, 7) for _ in range(8)]
    links = [s[0] for s in PANDA_SEGMENTS]
    for q in Q:
        coupling.joint_acceleration(q.tolist(), [0.0] * 7, (board,))
        mesh = [scene.board_distances(q[None], links=[link])[0] for link in links]
        for capsule, d in zip(coupling.last_distances, mesh):
            assert capsule <= d + 5e-3
    # the final configuration of the unmodified motion penetrates in both models
    coupling.joint_acceleration(scene.q_goal.tolist(), [0.0] * 7, (board,))
    assert coupling.last_distances[0] < -0.01
    assert PANDA_LINK_RADIUS > 0.0


def test_reaching_coupling_equals_the_numpy_equations(scene):
    """Eq. (12) + Eq. (7) of the reaching coupling (the common ObstacleCoupling on the board's
    OrientedBox, plus the hold) equal the numpy reference: one term per active segment, its
    closest point from the numpy closest-point routine."""
    chain = panda_chain(scene.robot.spec.urdf_path)
    board = board_obstacle(scene.board)
    R = np.array(board.rotation)
    q = scene.q_goal + np.array([0.05, -0.03, 0.02, 0.04, -0.02, 0.03, 0.01])
    qd = np.linspace(-0.2, 0.2, 7)
    x_ref = chain.forward(scene.q_goal, [PointOfInterest('ee')])
    hold = HoldGains(100.0, 20.0)
    coupling = ReachingCoupling(chain, board_field(board, 2.0, 0.2), hold=hold, ee_ref=x_ref,
                                limits=None)
    coupling.tick = 5
    dq = np.array(coupling.joint_acceleration(q.tolist(), qd.tolist(), (board,)))
    X, J = chain.forward_and_jacobian(q, [PointOfInterest('ee')])
    expected = end_effector_term(J[0], hold.kp * (x_ref[0] - X[0]) - hold.kd * J[0] @ qd)
    n_active = 0
    for (link, a, b), d in zip(PANDA_SEGMENTS, coupling.last_distances):
        ends = chain.forward(q, [PointOfInterest(link, a), PointOfInterest(link, b)])
        t, d_ref, _, _ = segment_obstacle(ends[0], ends[1], board, PANDA_LINK_RADIUS)
        assert d == pytest.approx(float(d_ref), abs=1e-6)
        if d >= 0.2:
            continue
        point = PointOfInterest(link, tuple(np.asarray(a) + float(t) * (np.subtract(b, a))))
        _, J_o = chain.forward_and_jacobian(q, [point])
        expected += link_term(J[0], J_o[0], R @ [0.0, 0.0, -2.0])
        n_active += 1
    assert n_active >= 1
    np.testing.assert_allclose(dq, expected, rtol=1e-8, atol=1e-8)


def test_cli_reproduces_the_reaching_experiment(tmp_path):
    out = tmp_path / 'reaching'
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get('PYTHONPATH', ''))
    proc = subprocess.run([sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'reaching',
                           '--out', str(out), '--distance-every', '20'],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    results = json.loads((out / 'results.json').read_text())
    rows = rows_by_name(results)
    for name in ('link_distance_cm.without_coupling', 'link_distance_cm.with_coupling',
                 'ee_error_cm', 'strong_field.cdmp_limit_usage',
                 'strong_field.dmp_limit_usage'):
        assert set(rows[name]) == {'name', 'ours', 'paper', 'unit'}
    assert rows['link_distance_cm.without_coupling']['ours'] < 0.0       # collision
    assert rows['link_distance_cm.without_coupling']['ours'] == pytest.approx(-1.37, abs=0.1)
    assert rows['link_distance_cm.with_coupling']['ours'] > 0.0          # avoided
    assert rows['ee_error_cm']['ours'] < 2.0                              # paper: about 1 cm
    assert rows['limit_usage.with_coupling']['ours'] < 1.0
    assert rows['strong_field.cdmp_limit_usage']['ours'] < 1.0
    assert rows['strong_field.dmp_limit_usage']['ours'] > 1.0
    assert rows['strong_field.cdmp_limit_margin_rad']['ours'] > 0.0
    assert rows['strong_field.dmp_limit_margin_rad']['ours'] < 0.0
    assert rows['real_time_factor.without_coupling']['ours'] > 0.0
    for png in ('before.png', 'after.png', 'joints.png'):
        assert (out / png).stat().st_size > 1000
    assert 'link_distance_cm.with_coupling' in (out / 'results.md').read_text()
