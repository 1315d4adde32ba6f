"""Configuration of the adapter (the slow path of the node graph), without ROS.

Two frozen dataclasses, mirrored 1:1 by the ROS parameters of the ``adapter`` node
(:mod:`cdmp_ros.ros.adapter_node`): :class:`AdapterConfig` (inputs, validation, visualisation;
top-level parameters) and :class:`AdaptRequestConfig` (how obstacles, goals and the current
state become a constrained ProMP adaptation problem, paper 003; parameters ``adaptation.*``).
Ranges and descriptions live in the field metadata (used for the parameter descriptors).
"""
from dataclasses import dataclass
from typing import Tuple

from cdmp_ros.core.config_fields import (accept_unstamped_param, check_fields, check_names,
                                         max_json_bytes_param, max_obstacles_param,
                                         obstacle_distance_param,
                                         obstacle_size_param, param as _param,
                                         robot_description_param,
                                         stamp_age_param, stamp_lead_param)
from cdmp_ros.core.kinematics.builders import PANDA_JOINTS


@dataclass(frozen=True)
class AdapterConfig:
    """Parameters of the adapter node (top level); see the field descriptions."""

    joint_names: Tuple[str, ...] = _param(
        PANDA_JOINTS, 'Joints of the robot, in the order of the published primitives.',
        read_only=True)
    urdf_path: str = _param(
        '', 'Robot URDF (limits, kinematics of the points of interest and of the IK). Empty: '
        'the Panda of pybullet_data.', read_only=True)
    robot_description: str = robot_description_param()
    base_frame: str = _param(
        'panda_link0', 'Robot base frame: obstacles and goal_point must be given in it (or '
        'with an empty frame_id).', read_only=True)
    max_stamp_age: float = stamp_age_param()
    max_stamp_lead: float = stamp_lead_param()
    accept_unstamped: bool = accept_unstamped_param()
    max_input_rate: float = _param(
        20.0, 'Messages per second accepted on each of primitive, obstacles, goal, goal_point '
        'and constraints; the excess is dropped and reported (flooding).', 0.1, 10000.0)
    max_joint_states_rate: float = _param(
        2000.0, 'Messages per second accepted on joint_states; the excess is dropped.',
        1.0, 100000.0)
    max_json_bytes: int = max_json_bytes_param()
    max_obstacles: int = max_obstacles_param()
    max_obstacle_size: float = obstacle_size_param()
    max_obstacle_distance: float = obstacle_distance_param()
    goal_margin: float = _param(
        1e-3, 'Goals outside the limits are clipped to centre +- (1 - goal_margin) * half '
        'range (the CDMP margin).', 1e-9, 0.5)
    joint_states_tolerance: float = _param(
        0.05, 'joint_states further than this [rad] outside the limits are rejected.',
        0.0, 1.0)
    joint_states_timeout: float = _param(
        1.0, 'joint_states older than this [s] are not used as the start of an adaptation '
        '(the ProMP is then not conditioned on the current state).', 0.001, 3600.0)
    ik_tolerance: float = _param(
        1e-3, 'A goal_point is reachable when the IK leaves at most this position error [m].',
        1e-6, 0.1)
    ik_max_iter: int = _param(200, 'Iterations of the damped least-squares IK per seed.',
                              1, 10000)
    retarget_dmp_on_goal: bool = _param(
        True, 'With a DMP / CDMP primitive, publish an adapted primitive with the new goal for '
        'goal messages too (goal_point always is). False leaves joint goals to the streamer, '
        'which subscribes goal itself and moves the goal without restarting the movement.')
    diagnostics_period: float = _param(0.5, 'Period of the diagnostics messages [s].',
                                       0.01, 60.0)
    path_points: int = _param(
        50, 'Points of the planned end-effector path (LINE_STRIP on visualization).', 2, 1000)
    band_points: int = _param(
        10, 'Uncertainty spheres of a ProMP on visualization (0 = none).', 0, 200)
    band_sigma: float = _param(
        2.0, 'Radius of the uncertainty spheres in standard deviations of the end effector.',
        0.1, 10.0)

    def __post_init__(self):
        check_fields(self)
        check_names('joint_names', self.joint_names)


@dataclass(frozen=True)
class AdaptRequestConfig:
    """How the adapter builds the constrained ProMP problem (paper 003); ``adaptation.*``."""

    alpha: float = _param(
        0.999, 'Confidence of the obstacle and joint-limit constraints (required satisfaction '
        'probability at every time step).', 0.5, 0.999999)
    obstacle_margin: float = _param(
        0.02, 'Clearance added to every obstacle (sphere radius, box faces) [m].', 0.0, 1.0)
    influence_distance: float = _param(
        0.3, 'Obstacles farther than this [m] from the prior mean path of every point of '
        'interest are left out of the problem.', 0.0, 100.0)
    avoid_links: Tuple[str, ...] = _param(
        ('panda_link4',), 'Links whose frame origin gets the obstacle constraints besides the '
        'end effector (the Panda elbow by default).')
    joint_limits: bool = _param(
        True, 'Constrain every joint to the robot limits (paper 003 Eq. 12).')
    condition_start: bool = _param(
        True, 'Condition the ProMP on the current joint_states at phase 0 (when available).')
    start_var: float = _param(
        1e-4, 'Observation variance of the start conditioning [rad^2].', 1e-10, 1.0)
    goal_var: float = _param(
        1e-4, 'Observation variance of the goal conditioning at phase 1 [rad^2].', 1e-10, 1.0)
    n_steps: int = _param(
        50, 'Time steps on which the path constraints are imposed.', 2, 1000)
    max_outer: int = _param(10, 'Multiplier (outer) updates of the optimiser at most.', 1, 100)
    max_inner: int = _param(300, 'L-BFGS iterations per inner loop at most.', 1, 10000)
    lambda0: float = _param(20.0, 'Initial Lagrange multiplier.', 1e-6, 1e6)

    def __post_init__(self):
        check_fields(self)
        check_names('avoid_links', self.avoid_links, allow_empty=True)
