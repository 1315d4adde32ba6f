"""The ``sim`` rollout cost of the learner's ``~/improve``: rollouts tracked in pybullet.

Every rollout's joint reference ``(Y, Yd, Ydd)`` is tracked by the Franka Panda of
``pybullet_data`` in a private headless (DIRECT) world with computed-torque control (paper
000, Eq. 2), one physics step per rollout step. The per-step cost is the scripted cost
(:class:`cdmp_ros.core.dmp.improve.ScriptedCost`: jerk, end-effector clearance from the obstacle,
final joint error) evaluated on the **measured** joint positions, plus
``torque_weight * |tau_t|^2 dt`` on the commanded torques.

Use from one thread only (pybullet clients are not shared between threads); :meth:`close`
(or the context manager) disconnects the world.
"""
from typing import Optional

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.dmp.dmp import Trajectory
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.dmp.improve import ScriptedCost
from cdmp_ros.sim.control import ComputedTorqueController
from cdmp_ros.sim.robot_specs import panda_spec
from cdmp_ros.sim.world import World, WorldConfig, WorldOwner


class SimRolloutCost(WorldOwner):
    """Per-step rollout costs measured in pybullet (see the module docstring).

    Parameters
    ----------
    scripted : ScriptedCost
        Cost terms on the measured joints; its ``dt`` is the physics step.
    torque_weight : float
        Weight of the squared commanded torques [1/(N^2 m^2 s)].
    joint_names : sequence of str, optional
        The primitive's joints; must be the Panda's, in its order.
    """

    def __init__(self, scripted: ScriptedCost, torque_weight: float = 1e-5,
                 joint_names: Optional[tuple] = None):
        spec = panda_spec()
        if joint_names is not None and tuple(joint_names) != tuple(spec.joint_names):
            raise ValidationError(f'joint_names: the sim cost needs the Panda joints '
                                  f'{list(spec.joint_names)}, got {list(joint_names)}')
        self.scripted = scripted
        self.torque_weight = float(torque_weight)
        self.dt = scripted.dt
        self.world = World(WorldConfig(time_step=self.dt))
        self.robot = self.world.add_robot(spec)
        self.robot.set_controller(ComputedTorqueController())
        self.last_q: Optional[NDArray[np.float64]] = None
        self.last_torques: Optional[NDArray[np.float64]] = None

    def execute(self, traj: Trajectory):
        """Track ``traj`` from its start state; measured joints and torques (n_steps, 7)."""
        Y, Yd, Ydd = traj.Y, traj.Yd, traj.Ydd
        robot, world = self.robot, self.world
        n = Y.shape[0]
        q = np.empty_like(Y)
        tau = np.zeros_like(Y)
        robot.reset(Y[0], Yd[0])
        q[0] = robot.q
        for k in range(1, n):
            robot.set_reference(Y[k], Yd[k], Ydd[k])
            world.step()
            q[k] = robot.q
            if robot.last_command is not None:
                tau[k] = robot.last_command
        return q, tau

    def __call__(self, traj: Trajectory) -> NDArray[np.float64]:
        q, tau = self.execute(traj)
        self.last_q, self.last_torques = q, tau
        r = self.scripted.per_step(q)
        return r + self.torque_weight * np.einsum('ij,ij->i', tau, tau) * self.dt
