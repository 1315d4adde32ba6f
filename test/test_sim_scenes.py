"""The reaching scene of paper 000, IV-B on the Panda (cdmp_ros.sim.scenes)."""
import numpy as np
import pybullet
import pytest

from cdmp_ros.core.errors import CdmpError
from cdmp_ros.sim import panda_spec, snapshot, World
from cdmp_ros.sim.scenes import (build_reaching_scene, HAND_DOWN, nominal_path,
                                 ReachingSceneConfig, solve_ik)


@pytest.fixture(scope='module')
def scene():
    with World() as world:
        yield build_reaching_scene(world)


def test_goal_configuration_reaches_the_cartesian_goal(scene):
    robot = scene.robot
    assert scene.ee_error(scene.q_goal) < 1e-4
    assert robot.limit_usage(scene.q_goal).max() < 0.9
    np.testing.assert_allclose(robot.q, scene.q_start)       # state restored after building
    # the hand points down at the goal (z axis of panda_hand along -z of the world)
    robot.reset(scene.q_goal)
    R = np.array(pybullet.getMatrixFromQuaternion(robot.link_pose('panda_hand')[1])).reshape(3, 3)
    robot.reset(scene.q_start)
    assert R[:, 2] @ [0, 0, -1] > 1 - 1e-6


def test_board_intersects_the_link_only_at_the_end_of_the_nominal_motion(scene):
    d = scene.board_distances(nominal_path(scene.q_start, scene.q_goal))
    assert d[0] > 0.0                                           # starts free
    assert d[-1] == pytest.approx(-scene.config.penetration, abs=1e-4)   # paper: -1.37 cm
    assert d.min() == pytest.approx(d[-1], abs=1e-4)            # deepest at the end
    link_only = scene.board_distances(scene.q_goal[None], links=[scene.config.link])
    assert link_only[0] == pytest.approx(-scene.config.penetration, abs=1e-4)
    assert scene.board.collide is False and scene.board.name == 'board'


def test_null_space_motion_can_clear_the_board(scene):
    """The board sits on the self-motion side of the upper arm: a null-space gradient walk
    (end-effector position held by J^+, the link pushed along -normal) clears it while the
    end effector stays on the goal. This is the avoidance the coupling of Eq. (12) performs."""
    robot = scene.robot
    cid = scene.world.client_id
    ee = robot.link_index(robot.ee_link)
    link = robot.link_index(scene.config.link)
    q = scene.q_goal.copy()
    zeros = [0.0] * 7
    try:
        for _ in range(200):
            robot.reset(q)
            J = np.array(pybullet.calculateJacobian(robot.body_id, ee, [0, 0, 0], q.tolist(),
                                                    zeros, zeros, physicsClientId=cid)[0])
            # Jacobian of the link's closest point to the board (in the link's inertial frame)
            pair = scene.world.obstacles.distances(robot, 1.0, ['board']).pairs[
                (scene.config.link, 'board')]
            com = pybullet.getLinkState(robot.body_id, link, physicsClientId=cid)
            inv = pybullet.invertTransform(com[0], com[1])
            local = pybullet.multiplyTransforms(inv[0], inv[1], pair.point_on_link.tolist(),
                                                [0, 0, 0, 1])[0]
            Jo = np.array(pybullet.calculateJacobian(robot.body_id, link, local, q.tolist(),
                                                     zeros, zeros, physicsClientId=cid)[0])
            Jp = np.linalg.pinv(J)
            N = np.eye(7) - Jp @ J
            e = scene.ee_goal - robot.ee_position()
            q = q + Jp @ e + N @ (0.5 * Jo.T @ -scene.board_normal)
            q = np.clip(q, robot.lower, robot.upper)
            if scene.board_distances(q[None])[0] > 0.01:
                break
        assert scene.board_distances(q[None])[0] > 0.01
        assert scene.ee_error(q) < 2e-3
    finally:
        robot.reset(scene.q_start)


def test_solve_ik_reports_unreachable_targets():
    with World() as world:
        robot = world.add_robot(panda_spec())
        with pytest.raises(CdmpError, match='solve_ik'):
            solve_ik(robot, (2.0, 0.0, 0.5), HAND_DOWN)
        q = solve_ik(robot, (0.4, -0.2, 0.4))
        robot.reset(q)
        np.testing.assert_allclose(robot.ee_position(), (0.4, -0.2, 0.4), atol=1e-4)


def test_scene_snapshots(scene, tmp_path):
    robot = scene.robot
    before = snapshot(scene.world, str(tmp_path / 'start.png'), scene.camera)
    robot.reset(scene.q_goal)
    after = snapshot(scene.world, str(tmp_path / 'goal.png'), scene.camera)
    robot.reset(scene.q_start)
    assert np.mean(np.any(before != after, axis=2)) > 0.01


def test_config_validation():
    with pytest.raises(ValueError, match='ee_goal'):
        ReachingSceneConfig(ee_goal=(1.0, 2.0))
