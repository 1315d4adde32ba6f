"""Paper 000, IV-B: the reaching experiment with link avoidance (cdmp reproduce reaching)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cdmp_ros.core.coupling.terms import end_effector_term, link_term
from cdmp_ros.core.coupling.potential_fields import ConstantField
from cdmp_ros.core.kinematics import panda_chain, PointOfInterest
from cdmp_ros.core.kinematics.closest import segment_box
from cdmp_ros.experiments.reaching_coupling import (BoardLinkCoupling, HoldGains,
                                                    PANDA_LINK_RADIUS, PANDA_SEGMENTS,
                                                    point_box_distance, quaternion_matrix,
                                                    segment_box_distance, world_to_frame)
from cdmp_ros.experiments.results import rows_by_name
from cdmp_ros.sim import World
from cdmp_ros.sim.scenes import build_reaching_scene, nominal_path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope='module')
def scene():
    with World() as world:
        yield build_reaching_scene(world)


def test_segment_box_distance_matches_the_exact_closest_point():
    rng = np.random.default_rng(3)
    h = np.array([0.1, 0.06, 0.005])
    for _ in range(200):
        a, b = rng.uniform(-0.2, 0.2, (2, 3))
        t, d, n = segment_box_distance(a.tolist(), b.tolist(), h.tolist())
        t_ref, d_ref, _, _ = segment_box(a, b, -h, h)
        assert d == pytest.approx(float(d_ref), abs=1e-6)
        # the normal is a unit direction along which the signed distance grows at rate 1
        p = a + t * (b - a)
        assert np.linalg.norm(n) == pytest.approx(1.0)
        eps = 1e-7
        rate = (point_box_distance(p + eps * np.asarray(n), h)[0] - point_box_distance(p, h)[0])
        assert rate / eps == pytest.approx(1.0, abs=1e-3)
        assert 0.0 <= t <= 1.0 and 0.0 <= float(t_ref) <= 1.0


def test_world_to_frame_inverts_the_board_pose():
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    R = quaternion_matrix(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    c = rng.normal(size=3)
    T = world_to_frame(c, q)
    x_local = rng.normal(size=3)
    x_world = R @ x_local + c
    np.testing.assert_allclose(T[:3, :3] @ x_world + T[:3, 3], x_local, atol=1e-12)


def test_capsules_are_conservative_against_pybullet_meshes(scene):
    """The link capsules of the coupling report at most the mesh distance + 5 mm (they are
    conservative where it matters: up to 4 mm closer than the pybullet meshes), on the nominal
    motion and around the final configuration."""
    chain = panda_chain(scene.robot.spec.urdf_path,
                        base_transform=world_to_frame(scene.board.position,
                                                      scene.board.orientation))
    coupling = BoardLinkCoupling(chain, scene.board.size, ConstantField(1.0, 0.1, (0, 0, -1)))
    rng = np.random.default_rng(1)
    Q = list(nominal_path(scene.q_start, scene.q_goal, 21)[8:])
    Q += [scene.q_goal + rng.normal(0.0, 0.15, 7) for _ in range(8)]
    links = [s[0] for s in PANDA_SEGMENTS]
    for q in Q:
        coupling.joint_acceleration(0, q.tolist(), [0.0] * 7)
        mesh = [scene.board_distances(q[None], links=[link])[0] for link in links]
        for capsule, d in zip(coupling.last_distances, mesh):
            assert capsule <= d + 5e-3
    # the final configuration of the unmodified motion penetrates in both models
    coupling.joint_acceleration(0, scene.q_goal.tolist(), [0.0] * 7)
    assert coupling.last_distances[0] < -0.01
    assert PANDA_LINK_RADIUS > 0.0


def test_board_frame_coupling_equals_the_world_frame_equations(scene):
    """Eq. (12) + Eq. (7) computed in the board frame on floats equal the numpy reference in the
    world frame (rotation invariance of the pseudo-inverses)."""
    R = quaternion_matrix(scene.board.orientation)
    chain_b = panda_chain(scene.robot.spec.urdf_path,
                          base_transform=world_to_frame(scene.board.position,
                                                        scene.board.orientation))
    chain_w = panda_chain(scene.robot.spec.urdf_path)
    q = scene.q_goal + np.array([0.05, -0.03, 0.02, 0.04, -0.02, 0.03, 0.01])
    qd = np.linspace(-0.2, 0.2, 7)
    x_ref_b = chain_b.forward(scene.q_goal, [PointOfInterest('ee')])
    hold = HoldGains(100.0, 20.0)
    coupling = BoardLinkCoupling(chain_b, scene.board.size, ConstantField(2.0, 0.2, (0, 0, -1)),
                                 hold=hold, ee_ref=x_ref_b)
    dq = np.array(coupling.joint_acceleration(0, q.tolist(), qd.tolist()))
    # reference: world frame, numpy, one term per active segment
    X, J = chain_w.forward_and_jacobian(q, [PointOfInterest('ee')])
    x_ref_w = R @ x_ref_b[0] + np.asarray(scene.board.position)
    expected = end_effector_term(J[0], hold.kp * (x_ref_w - X[0]) - hold.kd * J[0] @ qd)
    n_active = 0
    for (link, a, b), d in zip(PANDA_SEGMENTS, coupling.last_distances):
        if d >= 0.2:
            continue
        ends_b = chain_b.forward(q, [PointOfInterest(link, a), PointOfInterest(link, b)])
        t, _, _ = segment_box_distance(ends_b[0].tolist(), ends_b[1].tolist(),
                                       scene.board.size)
        point = PointOfInterest(link, tuple(np.asarray(a) + t * (np.subtract(b, a))))
        _, J_o = chain_w.forward_and_jacobian(q, [point])
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
