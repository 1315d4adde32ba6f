"""One robot in a :class:`cdmp_ros.sim.world.World`: state, reference, dynamics, control hook.

Joint vectors ``q``, ``qd``, ``qdd`` and torques ``tau`` are ``(n_dofs,)`` arrays ordered as
``Robot.joint_names`` (the spec's controlled joints). Held joints (Panda fingers) are driven by
pybullet position motors at their fixed positions and never appear in these vectors.
"""
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
import pybullet

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, lookup

# Half-width [rad or m] of the joint stops when a robot is loaded with joint_stops=False.
_WIDE_STOPS = 1e3


class JointReference:
    """The joint reference a controller tracks: ``q``, ``qd``, ``qdd``, each ``(n_dofs,)``."""

    __slots__ = ('q', 'qd', 'qdd')

    def __init__(self, q: NDArray, qd: NDArray, qdd: NDArray):
        self.q, self.qd, self.qdd = q, qd, qdd


class Robot:
    """A robot loaded into a world (create it with :meth:`World.add_robot`).

    Attributes
    ----------
    name : str
    spec : RobotSpec
    body_id : int
        pybullet body unique id.
    joint_names : tuple of str
        Controlled joints, the order of every joint vector.
    n_dofs : int
    lower, upper : (n_dofs,) ndarray
        Joint position limits read from the URDF [rad or m].
    velocity_limits, effort_limits : (n_dofs,) ndarray
        Joint velocity [rad/s] and effort [N m] limits read from the URDF.
    link_names : tuple of str
        Every link, the base first (pybullet link index -1), then by link index.
    ee_link : str
        End-effector link name.
    reference : JointReference
        The reference tracked by the controller (see :meth:`set_reference`).
    controller : object
        The active controller (``cdmp_ros.sim.control``); position control by default.
    last_command : (n_dofs,) ndarray or None
        The last torque command of a torque controller [N m].
    """

    def __init__(self, world, spec, name: str, base_position: Sequence[float],
                 base_orientation: Sequence[float], joint_stops: bool = True):
        from cdmp_ros.sim.control import PositionController
        self.world, self.spec, self.name = world, spec, name
        cid = world.client_id
        self._cid = cid
        pos = as_array('base_position', base_position, (3,))
        orn = as_array('base_orientation', base_orientation, (4,))
        norm = float(np.linalg.norm(orn))
        if not norm > 0.0:
            raise ValidationError(f'base_orientation: expected a non-zero quaternion, got {orn}')
        self.base_position = pos
        self.base_orientation = orn / norm
        self.body_id = pybullet.loadURDF(spec.urdf_path, pos.tolist(),
                                         self.base_orientation.tolist(), useFixedBase=True,
                                         physicsClientId=cid)
        infos = [pybullet.getJointInfo(self.body_id, j, physicsClientId=cid)
                 for j in range(pybullet.getNumJoints(self.body_id, physicsClientId=cid))]
        by_name = {info[1].decode(): info for info in infos}
        base_name = pybullet.getBodyInfo(self.body_id, physicsClientId=cid)[0].decode()
        self.link_names = (base_name,) + tuple(info[12].decode() for info in infos)
        self._link_index = {n: i - 1 for i, n in enumerate(self.link_names)}
        missing = [n for n in spec.joint_names + tuple(h for h, _ in spec.held_joints)
                   if n not in by_name]
        if missing:
            raise ValidationError(f'joint_names: expected joints of {spec.urdf_path}, '
                                  f'got unknown {missing}')
        self.joint_names = spec.joint_names
        self.n_dofs = len(self.joint_names)
        self.ee_link = spec.ee_link
        self.link_index(self.ee_link)  # validates
        arm = [by_name[n] for n in self.joint_names]
        if any(info[2] == pybullet.JOINT_FIXED for info in arm):
            raise ValidationError(f'joint_names: expected movable joints, got fixed ones in '
                                  f'{self.joint_names}')
        self.lower = np.array([info[8] for info in arm])
        self.upper = np.array([info[9] for info in arm])
        if np.any(self.upper <= self.lower):
            raise ValidationError(f'{spec.urdf_path}: expected finite joint limits with '
                                  f'lower < upper, got {self.lower} / {self.upper}')
        self.effort_limits = np.array([info[10] for info in arm])
        self.velocity_limits = np.array([info[11] for info in arm])
        self._arm_idx = [info[0] for info in arm]
        movable = [info[0] for info in infos if info[2] != pybullet.JOINT_FIXED]
        self._movable = movable
        self._arm_slots = np.array([movable.index(j) for j in self._arm_idx])
        held = {by_name[n][0]: v for n, v in spec.held_joints}
        unlisted = [infos[j][1].decode() for j in movable
                    if j not in held and j not in self._arm_idx]
        if unlisted:
            raise ValidationError(f'{spec.name}: movable joints {unlisted} are neither '
                                  'controlled (joint_names) nor held (held_joints)')
        self._full_q0 = np.zeros(len(movable))
        for j, v in held.items():
            self._full_q0[movable.index(j)] = v
        # no held joints and the controlled joints in pybullet's order: skip the scatter
        self._identity = bool(np.array_equal(self._arm_slots, np.arange(len(movable))))

        for link in range(-1, len(infos)):  # the dynamics model is exactly pybullet's
            pybullet.changeDynamics(self.body_id, link, linearDamping=0.0, angularDamping=0.0,
                                    jointDamping=0.0, physicsClientId=cid)
        if not joint_stops:
            for j in self._arm_idx:
                pybullet.changeDynamics(self.body_id, j, jointLowerLimit=-_WIDE_STOPS,
                                        jointUpperLimit=_WIDE_STOPS, physicsClientId=cid)
        for j, v in held.items():
            pybullet.resetJointState(self.body_id, j, v, 0.0, physicsClientId=cid)
            pybullet.setJointMotorControl2(self.body_id, j, pybullet.POSITION_CONTROL,
                                           targetPosition=v, force=infos[j][10] or 100.0,
                                           physicsClientId=cid)
        self._motors_off = False
        self.last_command: Optional[NDArray[np.float64]] = None
        self.controller = PositionController()
        self.reset(spec.home)

    # -- state ----------------------------------------------------------------------------
    def _vector(self, name: str, value: ArrayLike) -> NDArray[np.float64]:
        return as_array(name, value, (self.n_dofs,))

    def reset(self, q: ArrayLike, qd: Optional[ArrayLike] = None) -> None:
        """Teleport the joints to ``q`` (velocities ``qd``, default 0) and hold that pose.

        The reference becomes ``(q, qd, 0)``. ``q`` must lie within the joint limits.
        """
        q = self._vector('q', q)
        qd = np.zeros(self.n_dofs) if qd is None else self._vector('qd', qd)
        bad = np.flatnonzero((q < self.lower) | (q > self.upper))
        if bad.size:
            i = int(bad[0])
            raise ValidationError(f'q[{i}] ({self.joint_names[i]}): expected a value in '
                                  f'[{self.lower[i]}, {self.upper[i]}], got {q[i]}')
        for j, qi, qdi in zip(self._arm_idx, q, qd):
            pybullet.resetJointState(self.body_id, j, float(qi), float(qdi),
                                     physicsClientId=self._cid)
        self.reference = JointReference(q.copy(), qd.copy(), np.zeros(self.n_dofs))

    def joint_state(self) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Measured joint positions and velocities, each ``(n_dofs,)``."""
        states = pybullet.getJointStates(self.body_id, self._arm_idx, physicsClientId=self._cid)
        return (np.array([s[0] for s in states]), np.array([s[1] for s in states]))

    def joint_state_effort(self) -> Tuple[NDArray[np.float64], NDArray[np.float64],
                                          NDArray[np.float64]]:
        """Measured positions, velocities and efforts, each ``(n_dofs,)``, in one query.

        The effort is the torque of the last command of a torque controller, else the motor
        torque pybullet applied in the last step (position motors) [N m or N].
        """
        states = pybullet.getJointStates(self.body_id, self._arm_idx, physicsClientId=self._cid)
        q = np.array([s[0] for s in states])
        qd = np.array([s[1] for s in states])
        if self.last_command is not None:
            return q, qd, np.array(self.last_command, dtype=np.float64)
        return q, qd, np.array([s[3] for s in states])

    @property
    def q(self) -> NDArray[np.float64]:
        """Measured joint positions ``(n_dofs,)``."""
        return self.joint_state()[0]

    @property
    def qd(self) -> NDArray[np.float64]:
        """Measured joint velocities ``(n_dofs,)``."""
        return self.joint_state()[1]

    def limit_usage(self, q: Optional[ArrayLike] = None) -> NDArray[np.float64]:
        """``|q - centre| / half-range`` per joint; above 1 means outside the limits."""
        q = self.q if q is None else self._vector('q', q)
        return np.abs(q - 0.5 * (self.upper + self.lower)) / (0.5 * (self.upper - self.lower))

    # -- links ----------------------------------------------------------------------------
    def link_index(self, link: str) -> int:
        """pybullet link index of ``link`` (-1 for the base)."""
        return lookup('link', self._link_index, link, self.link_names)

    def link_pose(self, link: str) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World position ``(3,)`` and quaternion ``(4,)`` (x, y, z, w) of a link frame (URDF)."""
        idx = self.link_index(link)
        if idx < 0:  # fixed base: the URDF root frame is where it was loaded
            return self.base_position.copy(), self.base_orientation.copy()
        else:
            st = pybullet.getLinkState(self.body_id, idx, computeForwardKinematics=True,
                                       physicsClientId=self._cid)
            pos, orn = st[4], st[5]
        return np.array(pos), np.array(orn)

    def ee_position(self) -> NDArray[np.float64]:
        """World position ``(3,)`` of the end-effector point: ``spec.ee_offset`` in the
        ``ee_link`` frame (the Panda's tool centre point, as ``PointOfInterest('ee')``)."""
        pos, orn = self.link_pose(self.ee_link)
        offset = self.spec.ee_offset
        if offset == (0.0, 0.0, 0.0):
            return pos
        R = np.array(pybullet.getMatrixFromQuaternion(orn.tolist())).reshape(3, 3)
        return pos + R @ np.asarray(offset)

    # -- dynamics (Eq. 1, paper 000) -----------------------------------------------------
    def _full(self, q: NDArray) -> list:
        if self._identity:
            return q.tolist()
        full = self._full_q0.copy()
        full[self._arm_slots] = q
        return full.tolist()

    def _full_zero_held(self, v: NDArray) -> list:
        if self._identity:
            return v.tolist()
        full = np.zeros(len(self._movable))
        full[self._arm_slots] = v
        return full.tolist()

    def mass_matrix(self, q: Optional[ArrayLike] = None) -> NDArray[np.float64]:
        """Joint-space inertia matrix ``M(q)`` ``(n_dofs, n_dofs)`` (pybullet's model)."""
        q = self.q if q is None else self._vector('q', q)
        M = np.array(pybullet.calculateMassMatrix(self.body_id, self._full(q),
                                                  physicsClientId=self._cid))
        return M[np.ix_(self._arm_slots, self._arm_slots)]

    def inverse_dynamics(self, q: ArrayLike, qd: ArrayLike, qdd: ArrayLike
                         ) -> NDArray[np.float64]:
        """``tau = M(q) qdd + C(q, qd) qd + G(q)`` ``(n_dofs,)`` (Eq. 1 without contacts).

        Recursive Newton-Euler of pybullet (``calculateInverseDynamics``); held joints at
        their held positions with zero velocity and acceleration.
        """
        q, qd, qdd = self._vector('q', q), self._vector('qd', qd), self._vector('qdd', qdd)
        return self._inverse_dynamics(q, qd, qdd)

    def _inverse_dynamics(self, q: NDArray, qd: NDArray, qdd: NDArray) -> NDArray:
        tau = pybullet.calculateInverseDynamics(
            self.body_id, self._full(q), self._full_zero_held(qd), self._full_zero_held(qdd),
            physicsClientId=self._cid)
        return np.array(tau) if self._identity else np.array(tau)[self._arm_slots]

    def bias_forces(self, q: ArrayLike, qd: ArrayLike) -> NDArray[np.float64]:
        """``C(q, qd) qd + G(q)`` ``(n_dofs,)``, the bias forces of Eq. 1."""
        return self.inverse_dynamics(q, qd, np.zeros(self.n_dofs))

    def gravity(self, q: ArrayLike) -> NDArray[np.float64]:
        """``G(q)`` ``(n_dofs,)``."""
        zeros = np.zeros(self.n_dofs)
        return self.inverse_dynamics(q, zeros, zeros)

    # -- control --------------------------------------------------------------------------
    def set_controller(self, controller) -> None:
        """Select the control law (:mod:`cdmp_ros.sim.control`) used from the next step on."""
        if not hasattr(controller, 'apply'):
            raise ValidationError(f'controller: expected a cdmp_ros.sim.control controller, '
                                  f'got {type(controller).__name__}')
        self.controller = controller

    def set_reference(self, q: ArrayLike, qd: Optional[ArrayLike] = None,
                      qdd: Optional[ArrayLike] = None) -> None:
        """Set the joint reference tracked from the next step on (``qd``, ``qdd`` default 0)."""
        zeros = np.zeros(self.n_dofs)
        self.reference = JointReference(
            self._vector('q', q), zeros if qd is None else self._vector('qd', qd),
            zeros if qdd is None else self._vector('qdd', qdd))

    def apply_control(self) -> None:
        """Compute and send the controller's command for the current state (called by
        :meth:`World.step` before every physics step)."""
        q, qd = self.joint_state()
        self.controller.apply(self, q, qd, self.reference)

    def send_torque(self, tau: NDArray) -> None:
        """Command joint torques ``(n_dofs,)`` for the next step (velocity motors disabled)."""
        if not self._motors_off:
            pybullet.setJointMotorControlArray(self.body_id, self._arm_idx,
                                               pybullet.VELOCITY_CONTROL,
                                               forces=[0.0] * self.n_dofs,
                                               physicsClientId=self._cid)
            self._motors_off = True
        self.last_command = tau
        pybullet.setJointMotorControlArray(self.body_id, self._arm_idx, pybullet.TORQUE_CONTROL,
                                           forces=tau.tolist(), physicsClientId=self._cid)

    def send_position(self, q: NDArray, qd: NDArray, position_gain: float,
                      velocity_gain: float, force_scale: float) -> None:
        """Command pybullet's position motors towards ``(q, qd)`` for the next step."""
        self._motors_off = False
        self.last_command = None
        n = self.n_dofs
        pybullet.setJointMotorControlArray(
            self.body_id, self._arm_idx, pybullet.POSITION_CONTROL, targetPositions=q.tolist(),
            targetVelocities=qd.tolist(), forces=(self.effort_limits * force_scale).tolist(),
            positionGains=[position_gain] * n, velocityGains=[velocity_gain] * n,
            physicsClientId=self._cid)
