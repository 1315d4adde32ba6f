"""Configuration of the simulated robot behind the ``sim`` node (no ROS here).

:class:`SimConfig` is mirrored 1:1 by the ROS parameters of :mod:`cdmp_ros.ros.sim_node` (the
field metadata carries the description, the range and ``read_only`` used for the parameter
descriptors), except ``initial_positions``, a float array that the node declares itself
(its length depends on ``robot``).
"""
from dataclasses import dataclass, field
from typing import Optional, Tuple

from cdmp_ros.core.config_fields import (accept_unstamped_param, check_fields, max_obstacles_param,
                                         obstacle_distance_param, obstacle_size_param,
                                         param as _param, robot_description_timeout_param,
                                         stamp_age_param, stamp_lead_param)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.reflex import DEFAULT_TOLERANCE, MODES as REFLEX_MODES
from cdmp_ros.core.validation import as_array

#: Robots the sim node can load (see :func:`cdmp_ros.sim.live.build_robots`).
ROBOTS = ('panda', 'dual_panda', 'planar4')
#: Control laws: pybullet position motors, computed torque (Eq. 2, paper 000), the
#: joint-limit-avoiding law in exogenous coordinates (Eq. 4-5, paper 000).
CONTROL_MODES = ('position', 'computed_torque', 'exogenous')


@dataclass(frozen=True)
class SimConfig:
    """Parameters of the simulated robot; mirrored 1:1 by the sim node's ROS parameters.

    Ranges, choices and descriptions live in the field metadata.
    """

    robot: str = _param(
        'panda', 'Robot to simulate: panda (Franka Panda of pybullet_data), dual_panda (two '
        'Pandas 1.13 m apart, joints prefixed left_/right_), planar4 (planar 4-link arm of '
        'paper 003).', read_only=True, choices=ROBOTS)
    urdf_path: str = _param(
        '', 'Robot URDF whose joint limits (position, velocity) the simulated robot holds: '
        'the tighter of these and the limits of its pybullet model (robot panda only; the '
        'pybullet body stays the model of robot). Empty: the Panda of pybullet_data.',
        read_only=True)
    robot_description: str = _param(
        '', 'The robot URDF as XML text, as a ROS system passes it to its nodes; when '
        'non-empty it takes precedence over the robot_description topic and urdf_path for '
        'the joint limits (robot panda only; diagnostics: limits_source).', read_only=True)
    robot_description_timeout: float = robot_description_timeout_param(
        'the joint limits (robot panda only; ignored for the others)')
    control: str = _param(
        'position', 'Tracking law: position (pybullet position motors), computed_torque '
        '(Eq. 2, paper 000), exogenous (joint-limit-avoiding law in tanh coordinates, Eq. 4, '
        'paper 000).', choices=CONTROL_MODES)
    physics_rate: float = _param(
        1000.0, 'Physics step rate [Hz] (fixed step 1/physics_rate).', 100.0, 10000.0,
        read_only=True)
    publish_rate: float = _param(
        250.0, 'Rate of joint_states, ee_pose (and /clock) in simulated time [Hz]; '
        'physics_rate / publish_rate must be an integer.', 1.0, 1000.0, read_only=True)
    monitor_rate: float = _param(
        100.0, 'Rate of the obstacle distance and contact queries in simulated time [Hz] '
        '(rounded to whole publish periods; only while there are obstacles or, dual_panda, two '
        'robots).', 1.0, 1000.0)
    real_time: bool = _param(
        True, 'true: simulated time follows the wall clock (steady clock, with catch-up); '
        'false: step as fast as the CPU allows (in slices that keep callbacks responsive).')
    realtime_priority: int = _param(
        0, 'SCHED_FIFO priority (1-99) of every thread of the sim node (executor and '
        'middleware), set at start: the simulated robot stands for hardware whose controller '
        'runs in real time on its own computer, and must not be starved by a planner on the '
        'same machine (on 2 cores an adaptation solve held the simulation at 0.14 times real '
        'time while a sphere fell onto the frozen arm). 0: normal scheduling. Refused without '
        'CAP_SYS_NICE / an rtprio limit: logged, normal scheduling. Needs real_time true.',
        0, 99, read_only=True)
    max_catch_up: float = _param(
        0.1, 'Largest simulated time [s] stepped in one late tick; beyond it the simulation '
        'slips behind the wall clock (counted as slipped_steps).', 0.001, 10.0)
    publish_clock: bool = _param(
        False, 'Publish rosgraph_msgs/Clock on /clock (simulated time from 0) for '
        'use_sim_time; published stamps are then simulated time and input stamps are '
        'checked against it.', read_only=True)
    reference_timeout: float = _param(
        0.5, 'A joint_reference older than this [s] is stale: the last position is held with '
        'zero velocity. 0 disables the check.', 0.0, 3600.0)
    snapshot_path: str = _param(
        '', 'PNG written by the ~/snapshot service; empty: a new file in the temporary '
        'directory per call.')
    diagnostics_period: float = _param(0.5, 'Period of the diagnostics messages [s].',
                                       0.01, 60.0)
    base_frame: str = _param(
        '', 'Frame of ee_pose and of the obstacle markers (markers with another non-empty '
        'frame_id are rejected). Empty: the robot base link (panda_link0, base, world for '
        'dual_panda).', read_only=True)
    kp: float = _param(
        400.0, 'Position gain [1/s^2] of computed_torque; for exogenous, scaled by the joint '
        'inertias M_ii at the initial pose [N m per unit of xi].', 0.0, 1e6)
    kd: float = _param(
        40.0, 'Velocity gain [1/s] of computed_torque; for exogenous, scaled by M_ii '
        '[N m s/rad].', 0.0, 1e4)
    exogenous_margin: float = _param(
        0.01, 'exogenous: fraction of each half range kept free when the set point is mapped '
        'to xi_d (Eq. 5, paper 000).', 1e-6, 0.5)
    position_gain: float = _param(
        0.1, 'position: pybullet positionGains of the motors.', 1e-6, 1.0)
    velocity_gain: float = _param(
        1.0, 'position: pybullet velocityGains of the motors.', 0.0, 10.0)
    obstacles_collide: bool = _param(
        True, 'Obstacles are physical bodies the robot bumps into (false: ghosts seen only by '
        'the distance and contact queries).')
    contact_threshold: float = _param(
        0.0, 'A link-obstacle pair (dual_panda: also a link pair of the two robots) at a '
        'distance <= this [m] is a contact.', 0.0, 0.1)
    distance_range: float = _param(
        5.0, 'Link-obstacle distances beyond this [m] are not computed (reported as inf).',
        0.01, 100.0)
    limit_tolerance: float = _param(
        1e-4, 'A physics step counts as a limit violation when a measured joint is more '
        'than this [rad or m] outside its URDF limits (after the end stops acted).', 0.0, 0.1)
    reflex: str = _param(
        'count', 'What the sim does with a joint_reference that breaks the limits in force '
        '(joint_limits.* with the URDF, as the streamer keeps them): a position outside them, '
        'or a velocity, acceleration or jerk of the references differenced on their header '
        'stamps above its limit by more than reflex_tolerance. count: counted as '
        'reflex_errors on diagnostics, applied (clipped into the position limits). stop: the '
        'robot halts at its measured position and refuses every reference until ~/reset, as '
        'a Franka Panda does after a reflex.', choices=REFLEX_MODES)
    reflex_tolerance: float = _param(
        DEFAULT_TOLERANCE, 'Relative slack of the reflex check of velocity, acceleration and '
        'jerk (stamps are rounded to the nanosecond): a difference counts when above '
        '(1 + reflex_tolerance) times its limit.', 0.0, 0.5)
    max_stamp_age: float = stamp_age_param()
    max_stamp_lead: float = stamp_lead_param()
    accept_unstamped: bool = accept_unstamped_param()
    max_reference_rate: float = _param(
        2000.0, 'joint_reference messages per second accepted; the excess is dropped and '
        'reported (flooding).', 1.0, 100000.0)
    max_input_rate: float = _param(
        100.0, 'obstacles messages per second accepted; the excess is dropped and reported.',
        1.0, 100000.0)
    max_obstacles: int = max_obstacles_param()
    max_obstacle_size: float = obstacle_size_param()
    max_obstacle_distance: float = obstacle_distance_param()
    initial_positions: Optional[Tuple[float, ...]] = field(
        default=None, metadata={'description': 'Initial joint positions (and the pose of '
                                '~/reset), in joint_states order; default: the robot home.'})

    def __post_init__(self):
        check_fields(self)
        if self.realtime_priority and not self.real_time:
            raise ValidationError(f'real_time: expected true with realtime_priority '
                                  f'{self.realtime_priority} (stepping as fast as possible '
                                  f'under SCHED_FIFO would starve the machine)')
        if self.robot != 'panda' and (self.urdf_path or self.robot_description.strip()):
            raise ValidationError(f'urdf_path / robot_description: expected empty values for '
                                  f'robot {self.robot!r} (they give the limits of a panda)')
        ratio = self.physics_rate / self.publish_rate
        if ratio < 1.0 - 1e-9 or abs(ratio - round(ratio)) > 1e-6 * ratio:
            raise ValidationError(f'publish_rate: expected physics_rate ({self.physics_rate:g})'
                                  f' / publish_rate to be an integer >= 1, got '
                                  f'{self.publish_rate:g} (ratio {ratio:.6g})')
        if self.initial_positions is not None:
            q = as_array('initial_positions', self.initial_positions, (None,))
            object.__setattr__(self, 'initial_positions', tuple(float(v) for v in q))

    @property
    def physics_dt(self) -> float:
        """Physics time step [s]."""
        return 1.0 / self.physics_rate

    @property
    def monitor_decimation(self) -> int:
        """Published messages per obstacle distance / contact query."""
        return max(1, int(round(self.publish_rate / self.monitor_rate)))

    @property
    def publish_decimation(self) -> int:
        """Physics steps per published joint_states message."""
        return int(round(self.physics_rate / self.publish_rate))
