"""The ball-dropping scene of paper 000, section IV-C, with the Franka Panda.

The Panda carries a ball (radius 1.2 cm) fixed to its tool centre point, moves along a joint
reference over a board, releases the ball at the end of the reference and the ball falls under
gravity; the drop succeeds when the ball comes to rest inside the cup (an open box of five
static plates). The arm tracks the reference with computed torque (Eq. 2), so the commanded
torques of the cost (Eq. 40) are the controller's.
"""
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import pybullet
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.kinematics import PANDA_EE_OFFSET
from cdmp_ros.core.validation import as_array
from cdmp_ros.sim.control import ComputedTorqueController
from cdmp_ros.sim.robot_specs import panda_spec
from cdmp_ros.sim.world import World, WorldConfig, WorldOwner

BALL_RADIUS = 0.012


@dataclass(frozen=True)
class CupSpec:
    """An open box: inner half width [m], wall height [m], wall/bottom thickness [m]."""

    position: tuple = (0.62, -0.22, 0.10)  # centre of the bottom plate's top face
    inner_half_width: float = 0.045
    wall_height: float = 0.08
    thickness: float = 0.005


@dataclass(frozen=True)
class BoardSpec:
    """A thin static board (box) given by its centre and half extents [m]."""

    center: tuple = (0.55, 0.0, 0.235)
    half_extents: tuple = (0.15, 0.005, 0.135)


@dataclass
class DropResult:
    """Outcome of one executed rollout."""

    success: bool
    torques: NDArray[np.float64]       # (n_steps, 7) commanded joint torques [N m]
    ee_path: NDArray[np.float64]       # (n_steps, 3) measured tool centre point [m]
    q: NDArray[np.float64]             # (n_steps, 7) measured joint positions [rad]
    ball_final: NDArray[np.float64]    # (3,) ball position after settling [m]
    board_contact: bool                # the arm touched the board
    release_position: NDArray[np.float64]  # (3,) TCP at release [m]


class BallDropScene(WorldOwner):
    """Panda, cup, board and ball in a private pybullet world (close it after use).

    Parameters
    ----------
    cup : CupSpec
    board : BoardSpec, optional
        ``None`` for no board.
    time_step : float
        Physics step [s]; the joint reference is sampled at this step.
    fall_time : float
        Time after the release before the ball is checked [s].
    """

    def __init__(self, cup: CupSpec = CupSpec(), board: Optional[BoardSpec] = BoardSpec(),
                 time_step: float = 0.002, fall_time: float = 0.6):
        self.cup, self.board = cup, board
        self.time_step = float(time_step)
        self.fall_time = float(fall_time)
        self.world = World(WorldConfig(time_step=self.time_step))
        self.robot = self.world.add_robot(panda_spec())
        self.robot.set_controller(ComputedTorqueController())
        self._cid = self.world.client_id
        self._hand = self.robot.link_index('panda_hand')
        self._build_cup()
        if board is not None:
            self.world.obstacles.add_box('board', board.center, board.half_extents)
        col = pybullet.createCollisionShape(pybullet.GEOM_SPHERE, radius=BALL_RADIUS,
                                            physicsClientId=self._cid)
        vis = pybullet.createVisualShape(pybullet.GEOM_SPHERE, radius=BALL_RADIUS,
                                         rgbaColor=[0.9, 0.2, 0.1, 1],
                                         physicsClientId=self._cid)
        self.ball = pybullet.createMultiBody(0.01, col, vis, [0, 0, -5],
                                             physicsClientId=self._cid)
        # the ball must not collide with the hand that carries it
        for link in range(-1, pybullet.getNumJoints(self.robot.body_id,
                                                    physicsClientId=self._cid)):
            pybullet.setCollisionFilterPair(self.robot.body_id, self.ball, link, -1, 0,
                                            physicsClientId=self._cid)
        self._constraint = None

    def _build_cup(self) -> None:
        c = self.cup
        x, y, z = c.position
        w, h, t = c.inner_half_width, c.wall_height, c.thickness
        plates = [((x, y, z - t / 2), (w + t, w + t, t / 2))]
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if dx:
                plates.append(((x + dx * (w + t / 2), y, z + h / 2), (t / 2, w + t, h / 2)))
            else:
                plates.append(((x, y + dy * (w + t / 2), z + h / 2), (w + t, t / 2, h / 2)))
        self.cup_ids = []
        for center, half in plates:
            col = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half,
                                                physicsClientId=self._cid)
            vis = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=half,
                                             rgbaColor=[0.2, 0.4, 0.9, 1],
                                             physicsClientId=self._cid)
            self.cup_ids.append(pybullet.createMultiBody(0.0, col, vis, center,
                                                         physicsClientId=self._cid))

    def tcp(self) -> NDArray[np.float64]:
        """Tool centre point (between the fingertips) in the world frame."""
        pos, orn = self.robot.link_pose('panda_hand')
        R = np.array(pybullet.getMatrixFromQuaternion(orn.tolist())).reshape(3, 3)
        return pos + R @ np.asarray(PANDA_EE_OFFSET)

    def _attach_ball(self) -> None:
        pybullet.resetBasePositionAndOrientation(self.ball, self.tcp().tolist(), [0, 0, 0, 1],
                                                 physicsClientId=self._cid)
        pybullet.resetBaseVelocity(self.ball, [0, 0, 0], [0, 0, 0], physicsClientId=self._cid)
        self._constraint = pybullet.createConstraint(
            self.robot.body_id, self._hand, self.ball, -1, pybullet.JOINT_FIXED, [0, 0, 0],
            list(PANDA_EE_OFFSET), [0, 0, 0], physicsClientId=self._cid)
        pybullet.changeConstraint(self._constraint, maxForce=1e4, physicsClientId=self._cid)

    def _release(self) -> None:
        if self._constraint is not None:
            pybullet.removeConstraint(self._constraint, physicsClientId=self._cid)
            self._constraint = None

    def inside_cup(self, p: ArrayLike) -> bool:
        """Whether a ball centre ``p`` lies inside the cup's inner volume."""
        c = self.cup
        d = np.abs(np.asarray(p)[:2] - np.asarray(c.position[:2]))
        z = float(p[2]) - c.position[2]
        return bool(np.all(d < c.inner_half_width) and 0.0 < z < c.wall_height)

    def execute(self, Q: ArrayLike, Qd: ArrayLike, Qdd: Optional[ArrayLike] = None
                ) -> DropResult:
        """Track the reference ``Q, Qd, Qdd`` (n_steps, 7), sampled at ``time_step``, carrying
        the ball; release it at the last sample and let it fall for ``fall_time``."""
        Q = as_array('Q', Q, (None, 7))
        Qd = as_array('Qd', Qd, Q.shape)
        Qdd = np.zeros_like(Q) if Qdd is None else as_array('Qdd', Qdd, Q.shape)
        robot = self.robot
        self._release()
        robot.reset(Q[0], Qd[0])
        self._attach_ball()
        n = Q.shape[0]
        torques = np.zeros((n, 7))
        qs = np.zeros((n, 7))
        ee = np.zeros((n, 3))
        contact = False
        for k in range(n):
            robot.set_reference(Q[k], Qd[k], Qdd[k])
            self.world.step()
            torques[k] = robot.last_command
            qs[k] = robot.q
            ee[k] = self.tcp()
            if self.board is not None and k % 10 == 0:
                contact = contact or bool(self.world.obstacles.contacts(robot))
        release = self.tcp()
        self._release()
        robot.set_reference(Q[-1], np.zeros(7), np.zeros(7))
        self.world.step(int(round(self.fall_time / self.time_step)))
        ball = np.array(pybullet.getBasePositionAndOrientation(
            self.ball, physicsClientId=self._cid)[0])
        return DropResult(self.inside_cup(ball), torques, ee, qs, ball, contact, release)

    def snapshot(self, path: str, target: Sequence[float] = (0.45, 0.0, 0.3)) -> None:
        """Write a PNG camera snapshot of the scene."""
        from cdmp_ros.sim.camera import CameraConfig, snapshot
        snapshot(self.world, path, CameraConfig(target=tuple(target)))
