"""Experiment scenes built on the simulation layer.

Reaching with link obstacle avoidance (paper 000, IV-B), transposed from the iCub to the Panda:
the end effector reaches a Cartesian goal; a board (thin box) is placed so that it intersects a
link (default the upper-arm link ``panda_link3``, as the iCub's upper arm in the paper) at the
final configuration of the unmodified motion, by a chosen depth (paper: -1.37 cm). The
board is a non-colliding (ghost) obstacle, so a motion that ignores it passes through it and
the penetration is measured, not prevented by the physics.

Typical use by the reaching experiment::

    with World() as world:
        scene = build_reaching_scene(world)             # robot at q_start, board placed
        # ... roll out a CDMP from scene.q_start to scene.q_goal, with or without coupling ...
        d = scene.board_distances(Y)                     # (n_steps,) min link-board distance
        snapshot(world, 'before.png', scene.camera)
"""
from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
import pybullet

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.validation import as_array, check_positive
from cdmp_ros.sim.camera import CameraConfig
from cdmp_ros.sim.obstacles import ObstacleInfo
from cdmp_ros.sim.robot_specs import PANDA_HOME, panda_spec

# Hand pointing down (rotation by pi about x), quaternion (x, y, z, w).
HAND_DOWN = (1.0, 0.0, 0.0, 0.0)


def _pose_error(robot, ee: int, target: NDArray, orn: Optional[NDArray]) -> NDArray:
    st = pybullet.getLinkState(robot.body_id, ee, computeForwardKinematics=True,
                               physicsClientId=robot.world.client_id)
    R = np.array(pybullet.getMatrixFromQuaternion(st[5])).reshape(3, 3)
    err = target - (np.array(st[4]) + R @ np.asarray(robot.spec.ee_offset))
    if orn is None:
        return err
    Rd = np.array(pybullet.getMatrixFromQuaternion(orn.tolist())).reshape(3, 3)
    return np.concatenate([err, 0.5 * np.cross(R, Rd, axis=0).sum(axis=1)])


def _refine_ik(robot, ee: int, q: NDArray, target: NDArray, orn: Optional[NDArray],
               n_iterations: int = 100, damping: float = 1e-3) -> NDArray:
    """Damped least-squares Newton steps on the pose error (pybullet Jacobians)."""
    cid = robot.world.client_id
    st = pybullet.getLinkState(robot.body_id, ee, physicsClientId=cid)
    # calculateJacobian takes the point in the link's inertial frame: the end-effector point
    inv_pos, inv_orn = pybullet.invertTransform(st[2], st[3])
    local = pybullet.multiplyTransforms(inv_pos, inv_orn, list(robot.spec.ee_offset),
                                        [0.0, 0.0, 0.0, 1.0])[0]
    zeros = [0.0] * robot.n_dofs
    for _ in range(n_iterations):
        robot.reset(q)
        e = _pose_error(robot, ee, target, orn)
        if np.linalg.norm(e[:3]) < 1e-7 and (orn is None or np.linalg.norm(e[3:]) < 1e-6):
            break
        lin, ang = pybullet.calculateJacobian(robot.body_id, ee, local, q.tolist(), zeros,
                                              zeros, physicsClientId=cid)
        J = np.array(lin) if orn is None else np.vstack([lin, ang])
        dq = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(len(e)), e)
        q = np.clip(q + dq, robot.lower + 1e-6, robot.upper - 1e-6)
    return q


def solve_ik(robot, position: ArrayLike, orientation: Optional[Sequence[float]] = None,
             q_rest: Optional[ArrayLike] = None, tol: float = 1e-4) -> NDArray[np.float64]:
    """Joint configuration ``(n_dofs,)`` placing the end-effector point
    (:meth:`Robot.ee_position`) at ``position`` (3,) and, if given, the ``ee_link`` frame at
    the quaternion ``orientation``.

    pybullet's null-space IK (joint limits, rest pose ``q_rest`` for the redundancy, default
    the robot's home) gives the branch; damped least-squares steps with pybullet's Jacobians
    then make it exact. The robot's state is restored afterwards.

    Raises
    ------
    CdmpError
        If no configuration within the limits reaches the target within ``tol`` [m].
    """
    target = as_array('position', position, (3,))
    orn = None if orientation is None else as_array('orientation', orientation, (4,))
    if orn is not None:
        orn = orn / np.linalg.norm(orn)
    if q_rest is None:
        rest = np.array(robot.spec.home)
    else:
        rest = as_array('q_rest', q_rest, (robot.n_dofs,))
    if robot.spec.held_joints:
        raise ValidationError('robot: expected a robot without held joints for solve_ik')
    cid = robot.world.client_id
    ee = robot.link_index(robot.ee_link)
    saved_q, saved_qd = robot.joint_state()
    saved_ref = robot.reference
    try:
        robot.reset(rest)
        kwargs = dict(lowerLimits=robot.lower.tolist(), upperLimits=robot.upper.tolist(),
                      jointRanges=(robot.upper - robot.lower).tolist(), restPoses=rest.tolist(),
                      maxNumIterations=200, residualThreshold=1e-6, physicsClientId=cid)
        if orn is not None:
            kwargs['targetOrientation'] = orn.tolist()
        sol = pybullet.calculateInverseKinematics(robot.body_id, ee, target.tolist(), **kwargs)
        q = np.clip(np.array(sol[:robot.n_dofs]), robot.lower + 1e-6, robot.upper - 1e-6)
        q = _refine_ik(robot, ee, q, target, orn)
        robot.reset(q)
        err = float(np.linalg.norm(robot.ee_position() - target))
    finally:
        robot.reset(saved_q, saved_qd)
        robot.reference = saved_ref
    if err < tol:
        return q
    raise CdmpError(f'solve_ik: no configuration within the limits reaches {target.tolist()} '
                    f'(best position error {err:.4g} m > tol {tol})')


def _quaternion_from_matrix(R: NDArray) -> NDArray[np.float64]:
    """Quaternion (x, y, z, w) of a rotation matrix (3, 3) (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = s / 4
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q)


def elbow_directions(robot, q: ArrayLike, shoulder: str = 'panda_link2',
                     elbow: str = 'panda_link4', wrist: str = 'panda_link6'
                     ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Outward and self-motion directions of the elbow at ``q``, unit vectors (3,) each.

    ``outward`` points from the shoulder-wrist line to the elbow; ``tangent`` = axis x outward
    is the direction in which the Panda's null-space (self-) motion, a rotation of the elbow
    about the shoulder-wrist axis, moves the elbow first. The robot's state is restored.
    """
    saved_q, saved_qd = robot.joint_state()
    saved_ref = robot.reference
    try:
        robot.reset(q)
        s, e, w = (robot.link_pose(n)[0] for n in (shoulder, elbow, wrist))
    finally:
        robot.reset(saved_q, saved_qd)
        robot.reference = saved_ref
    u = (w - s) / np.linalg.norm(w - s)
    v = (e - s) - np.dot(e - s, u) * u
    norm = np.linalg.norm(v)
    if norm < 1e-6:
        raise CdmpError('elbow_directions: the arm is stretched (elbow on the shoulder-wrist '
                        'line)')
    v = v / norm
    return v, np.cross(u, v)


def place_board_on_link(world, robot, q: ArrayLike, link: str, penetration: float,
                        normal: ArrayLike, half_extents: Sequence[float] = (0.15, 0.15, 0.005),
                        name: str = 'board', collide: bool = False,
                        along: Optional[ArrayLike] = None) -> ObstacleInfo:
    """Add a board (thin box) that overlaps ``link`` by ``penetration`` [m] at configuration ``q``.

    The board's thin axis (its local z) is ``normal`` (3,), pointing from the link towards the
    board; its local x axis is ``along`` (projected perpendicular to ``normal``; default any).
    The board is centred on the link's closest point and translated along ``normal`` until the
    closest-point distance is ``-penetration`` (three corrections; a face contact is linear in
    the translation). The robot's state is restored afterwards.
    """
    depth = check_positive('penetration', penetration, allow_zero=True)
    n = as_array('normal', normal, (3,))
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0.0, 0.0]) if along is None else as_array('along', along, (3,))
    a = a - np.dot(a, n) * n
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(n, [0.0, 1.0, 0.0])
    a = a / np.linalg.norm(a)
    R = np.column_stack([a, np.cross(n, a), n])
    orn = _quaternion_from_matrix(R)
    he = as_array('half_extents', half_extents, (3,))
    saved_q, saved_qd = robot.joint_state()
    saved_ref = robot.reference
    try:
        robot.reset(q)
        centre = robot.link_pose(link)[0] + n * (he[2] + 0.2)
        world.obstacles.add_box(name, centre, he, orn, collide=collide, replace=True)
        for _ in range(3):
            report = world.obstacles.distances(robot, max_distance=2.0, obstacles=[name])
            pair = report.pairs.get((link, name))
            if pair is None:
                raise CdmpError(f'place_board_on_link: {link} has no collision geometry')
            # re-centre laterally on the closest point, then correct the offset along n
            lateral = pair.point_on_link - np.dot(pair.point_on_link - centre, n) * n - centre
            centre = centre + lateral - (pair.distance + depth) * n
            world.obstacles.move(name, centre, orn)
    finally:
        robot.reset(saved_q, saved_qd)
        robot.reference = saved_ref
    return world.obstacles.get(name)


@dataclass(frozen=True)
class ReachingSceneConfig:
    """The reaching scene of paper 000, IV-B, on the Panda.

    Attributes
    ----------
    ee_goal : tuple of float
        Goal of the end-effector point (the tool centre point, :meth:`Robot.ee_position`) in
        the robot base frame [m]. The paper's iCub goal
        (0.350, 0.091, 0.853) m is in the iCub's frame and not reachable by the Panda; this
        default is a comparable reach forward-left, well inside the workspace.
    ee_orientation : tuple of float or None
        Hand orientation at the goal (default pointing down); None leaves it free.
    q_start : tuple of float
        Start configuration (default the Panda's ready pose).
    link : str
        Link the board intersects at the final configuration (the upper arm).
    penetration : float
        Overlap of board and link at the final configuration [m] (paper: 1.37 cm).
    board_half_extents : tuple of float
        Half extents of the board: its local x (along the upper arm), y, and the thin z.
    """

    ee_goal: Tuple[float, float, float] = (0.40, 0.30, 0.20)
    ee_orientation: Optional[Tuple[float, float, float, float]] = HAND_DOWN
    q_start: Tuple[float, ...] = PANDA_HOME
    link: str = 'panda_link3'
    penetration: float = 0.0137
    board_half_extents: Tuple[float, float, float] = (0.10, 0.06, 0.005)

    def __post_init__(self):
        object.__setattr__(self, 'ee_goal', tuple(
            float(v) for v in as_array('ee_goal', self.ee_goal, (3,))))
        if self.ee_orientation is not None:
            object.__setattr__(self, 'ee_orientation', tuple(
                float(v) for v in as_array('ee_orientation', self.ee_orientation, (4,))))
        object.__setattr__(self, 'q_start', tuple(
            float(v) for v in as_array('q_start', self.q_start, (7,))))
        check_positive('penetration', self.penetration, allow_zero=True)
        he = as_array('board_half_extents', self.board_half_extents, (3,))
        if np.any(he <= 0):
            raise ValidationError(f'board_half_extents: expected positive values, got {he}')
        object.__setattr__(self, 'board_half_extents', tuple(float(v) for v in he))


@dataclass
class ReachingScene:
    """A built reaching scene (see :func:`build_reaching_scene`).

    Attributes
    ----------
    world : World
    robot : Robot
        The Panda, at ``q_start``.
    config : ReachingSceneConfig
    q_start, q_goal : (7,) ndarray
        Start configuration and the IK solution for ``config.ee_goal`` (the final
        configuration of the unmodified motion).
    ee_goal : (3,) ndarray
    board : ObstacleInfo
        The board (ghost obstacle named ``'board'``).
    board_normal : (3,) ndarray
        Unit normal of the board, pointing from the link into the board.
    camera : CameraConfig
        A view of the arm and the board for before/after snapshots.
    """

    world: object
    robot: object
    config: ReachingSceneConfig
    q_start: NDArray[np.float64]
    q_goal: NDArray[np.float64]
    ee_goal: NDArray[np.float64]
    board: ObstacleInfo
    board_normal: NDArray[np.float64]
    camera: CameraConfig = field(default_factory=CameraConfig)

    def board_distances(self, Y: ArrayLike, links: Optional[Sequence[str]] = None
                        ) -> NDArray[np.float64]:
        """Minimum distance between the board and ``links`` (default every link) along a joint
        trajectory ``Y`` (n_steps, 7), evaluated kinematically (the robot is teleported to
        each row, then restored) [m]; negative = penetration."""
        Y = as_array('Y', Y, (None, self.robot.n_dofs))
        robot = self.robot
        names = robot.link_names if links is None else tuple(links)
        rows = [robot.link_index(n) + 1 for n in names]   # report rows: base first
        saved_q, saved_qd = robot.joint_state()
        saved_ref = robot.reference
        out = np.empty(len(Y))
        try:
            for k, q in enumerate(Y):
                robot.reset(np.clip(q, robot.lower, robot.upper))
                report = self.world.obstacles.distances(robot, max_distance=1.0,
                                                        obstacles=[self.board.name])
                out[k] = report.distance[rows, 0].min()
        finally:
            robot.reset(saved_q, saved_qd)
            robot.reference = saved_ref
        return out

    def ee_error(self, q: ArrayLike) -> float:
        """Distance between the end effector at ``q`` (7,) and ``ee_goal`` [m]."""
        robot = self.robot
        saved_q, saved_qd = robot.joint_state()
        saved_ref = robot.reference
        try:
            robot.reset(q)
            return float(np.linalg.norm(robot.ee_position() - self.ee_goal))
        finally:
            robot.reset(saved_q, saved_qd)
            robot.reference = saved_ref


def nominal_path(q_start: ArrayLike, q_goal: ArrayLike, n_steps: int = 51
                 ) -> NDArray[np.float64]:
    """Minimum-jerk joint path ``(n_steps, n_dofs)`` from ``q_start`` to ``q_goal``."""
    s = np.linspace(0.0, 1.0, n_steps)
    s = 10 * s**3 - 15 * s**4 + 6 * s**5
    q_start, q_goal = np.asarray(q_start, dtype=float), np.asarray(q_goal, dtype=float)
    return q_start + s[:, None] * (q_goal - q_start)


def build_reaching_scene(world, config: ReachingSceneConfig = ReachingSceneConfig(),
                         robot=None) -> ReachingScene:
    """Build the reaching scene of paper 000, IV-B in ``world``.

    Adds the Panda (unless ``robot`` is given), solves the IK of ``config.ee_goal`` with the
    start configuration as rest pose (base joint turned towards the goal), and places the
    board so that it overlaps ``config.link`` by ``config.penetration`` at that final
    configuration. The board's normal is the elbow's self-motion direction
    (:func:`elbow_directions`), so the null space can move the link out of the board while the
    end effector stays on its goal; its long side runs along the upper arm. Of the two sides,
    the one where the :func:`nominal_path` starts free and is deepest at its end is used.
    """
    if robot is None:
        robot = world.add_robot(panda_spec(home=config.q_start))
    q_start = np.array(config.q_start)
    robot.reset(q_start)
    rest = q_start.copy()   # same posture, base joint turned towards the goal
    rest[0] = np.clip(np.arctan2(config.ee_goal[1], config.ee_goal[0]), robot.lower[0],
                      robot.upper[0])
    q_goal = solve_ik(robot, config.ee_goal, config.ee_orientation, q_rest=rest)
    _, tangent = elbow_directions(robot, q_goal)
    saved = robot.joint_state()
    robot.reset(q_goal)
    along = robot.link_pose('panda_link4')[0] - robot.link_pose('panda_link2')[0]
    robot.reset(*saved)
    # Of the two sides, keep the one where the nominal motion (minimum-jerk in joint space,
    # what a DMP fitted to a straight demonstration produces) starts free and penetrates
    # deepest at its end, as in the paper's Fig. 4a.
    nominal = nominal_path(q_start, q_goal)
    best = None
    for sign in (1.0, -1.0):
        board = place_board_on_link(world, robot, q_goal, config.link, config.penetration,
                                    sign * tangent, config.board_half_extents, name='board',
                                    collide=False, along=along)
        scene = ReachingScene(world, robot, config, q_start, q_goal, np.array(config.ee_goal),
                              board, sign * tangent)
        d = scene.board_distances(nominal)
        score = (d[0] <= 0.0, d[-1] - d.min())
        if best is None or score < best[0]:
            best = (score, sign)
    sign = best[1]
    board = place_board_on_link(world, robot, q_goal, config.link, config.penetration,
                                sign * tangent, config.board_half_extents, name='board',
                                collide=False, along=along)
    normal = sign * tangent
    # a three-quarter view from the board's side: the board face and the arm through it
    target = 0.5 * (np.array(config.ee_goal) + np.array(board.position))
    c, s = np.cos(np.radians(35.0)), np.sin(np.radians(35.0))
    view = np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1], 0.0])
    eye = target + 1.1 * view / np.linalg.norm(view) + np.array([0.0, 0.0, 0.35])
    camera = CameraConfig(target=tuple(target), eye=tuple(eye))
    return ReachingScene(world, robot, config, q_start, q_goal,
                         np.array(config.ee_goal), board, normal, camera)
