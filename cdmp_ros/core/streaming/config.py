"""The streamer's parameters (:class:`StreamerConfig`), mirrored 1:1 by the ROS parameters of
the streamer node; ranges and descriptions live in the field metadata."""
from dataclasses import dataclass
from typing import Tuple

from cdmp_ros.core.config_fields import (accept_unstamped_param, check_chain_fields,
                                         check_fields, check_names, max_json_bytes_param,
                                         max_obstacles_param, obstacle_distance_param,
                                         obstacle_size_param, param as _param,
                                         robot_description_param,
                                         robot_description_timeout_param, stamp_age_param,
                                         stamp_lead_param, tcp_offset_param, tip_link_param,
                                         tip_links_param,
                                         urdf_path_param)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.builders import PANDA_JOINTS

__all__ = ['StreamerConfig', 'CONTROLLER_OUTPUTS', 'DEFAULT_CONTROLLER_TOPICS', 'BOX_FIELDS']

#: Values of ``controller_output``.
CONTROLLER_OUTPUTS = ('none', 'forward_command', 'joint_trajectory')
#: Values of ``box_field_kind``: the potential field of box obstacles.
BOX_FIELDS = ('constant', 'board')
#: The command topic of each ros2_control controller under its usual name.
DEFAULT_CONTROLLER_TOPICS = {'forward_command': 'forward_position_controller/commands',
                             'joint_trajectory': 'joint_trajectory_controller/joint_trajectory'}


@dataclass(frozen=True)
class StreamerConfig:
    """Parameters of the streamer; mirrored 1:1 by the ROS parameters of the streamer node.

    Ranges and descriptions live in the field metadata (used for the parameter descriptors).
    """

    rate: float = _param(500.0, 'Publishing rate of joint_reference [Hz] (1 kHz supported); '
                         'fixed at start.', 1.0, 2000.0, read_only=True)
    joint_states_timeout: float = _param(
        0.5, 'joint_states older than this [s] are stale: the reference stops smoothly and '
        'holds. 0 disables the check (open loop: the reference starts at the primitive start).',
        0.0, 60.0)
    stop_time: float = _param(0.5, 'Duration of the smooth stop [s].', 0.01, 10.0)
    switch_blend_time: float = _param(
        0.05, 'A primitive switched in while streaming starts with the acceleration of the '
        'reference; the difference fades out over this time [s] (quintic weight, as a coupling '
        'term: limits kept). 0: position and velocity continuous, the acceleration jumps.',
        0.0, 1.0)
    output_stage: bool = _param(
        True, 'Pass every published reference through the output stage: consecutive '
        'positions differ within the velocity, acceleration and jerk limits (joint_limits.*) '
        'and stop in time before the position limits; the published velocity is the '
        "positions' difference. False: publish the primitive's reference as integrated "
        '(for comparison only: a real arm may refuse it).')
    output_bandwidth: float = _param(
        30.0, 'Poles [1/s] of the output stage when it closes a gap to the reference (after '
        'a bounded step, a start or a resume); a reference that keeps the limits is followed '
        'exactly.', 1.0, 500.0)
    max_catch_up: int = _param(
        10, 'Integration steps made at most in one tick after a late timer callback.', 1, 1000)
    limit_margin: float = _param(
        1e-3, 'Goals outside the limits are clipped to centre +- (1 - limit_margin) * half '
        'range (the CDMP margin).', 1e-9, 0.5)
    joint_names: Tuple[str, ...] = _param(
        PANDA_JOINTS, 'Joints of the reference, in the published order.', read_only=True)
    urdf_path: str = urdf_path_param('limits, kinematics for the coupling')
    tip_link: str = tip_link_param()
    tip_links: Tuple[str, ...] = tip_links_param()
    robot_description: str = robot_description_param()
    robot_description_timeout: float = robot_description_timeout_param()
    base_frame: str = _param(
        'panda_link0', 'Robot base frame: obstacles must be given in it (or with an empty '
        'frame_id).', read_only=True)
    max_stamp_age: float = stamp_age_param()
    max_stamp_lead: float = stamp_lead_param()
    accept_unstamped: bool = accept_unstamped_param()
    max_input_rate: float = _param(
        100.0, 'Messages per second accepted on goal, obstacles, primitive and '
        'adapted_primitive; the excess is dropped and reported (flooding).', 1.0, 100000.0)
    max_joint_states_rate: float = _param(
        2000.0, 'Messages per second accepted on joint_states; the excess is dropped.',
        1.0, 100000.0)
    max_json_bytes: int = max_json_bytes_param()
    max_obstacles: int = max_obstacles_param()
    max_obstacle_size: float = obstacle_size_param()
    max_obstacle_distance: float = obstacle_distance_param()
    diagnostics_period: float = _param(0.5, 'Period of the diagnostics messages [s].',
                                       0.01, 60.0)
    stream_unadapted: bool = _param(
        True, "Stream a primitive from 'primitive' as soon as it arrives; false: only record "
        "it as the source and start with its first adaptation from 'adapted_primitive' (with "
        'the adapter: the robot executes only trajectories adapted to the constraints, never '
        'the raw prior).', read_only=True)
    coupling_enabled: bool = _param(
        True, 'Apply the obstacle coupling terms (paper 000, Eq. 7/12) every tick.')
    coupling_max_acceleration: float = _param(
        500.0, 'Bound [rad/s^2] of the obstacle coupling: its joint acceleration is scaled '
        'down (one factor for all joints, direction kept) so that no joint gets more. The '
        'potential fields grow without bound near an obstacle; unbounded, a sphere appearing '
        'next to a link moved the reference from mid-range onto the limits in one tick. The '
        "default keeps the demo's avoidance and changes the velocity by at most 1 rad/s per "
        "2 ms tick; it is not a hardware limit (set the robot's own for a real arm, and expect "
        'weaker avoidance). 0: no bound.',
        0.0, 1e6)
    coupling_decimation: int = _param(
        1, 'Evaluate the coupling every N ticks and hold it in between (box obstacles with '
        'link terms cost milliseconds per evaluation).', 1, 1000)
    tick_thread: bool = _param(
        True, 'Publish from a dedicated tick thread that sleeps to absolute deadlines of the '
        'steady clock (False: an executor timer, sharing the executor thread with the '
        'subscriptions).', read_only=True)
    realtime_priority: int = _param(
        50, 'SCHED_FIFO priority of the tick thread (1-99; 0 = normal scheduling). Refused '
        'without CAP_SYS_NICE / an rtprio limit: logged, normal scheduling. Default 50, as '
        "ros2_control's controller_manager: under a flood of large messages with valid "
        'obstacles and goals on a 2-core machine normal scheduling kept 97.6-98.0 % of the '
        '500 Hz ticks on time, SCHED_FIFO 50 99.35 % (benchmarks/bench_flood.py).', 0, 99,
        read_only=True)
    realtime_threads: str = _param(
        'all', "With realtime_priority > 0: 'all' also puts the node's other threads under "
        'SCHED_FIFO (executor and middleware threads at realtime_priority - 1, the primitive '
        'worker at 1), so no thread the tick waits for (GIL, DDS) is preempted by normal '
        "processes; 'tick' lifts the tick thread only.", read_only=True)
    tick_cpu: int = _param(-1, 'CPU the tick thread is pinned to (-1 = no pinning).',
                           -1, 1023, read_only=True)
    tick_spin: float = _param(
        0.0, 'Seconds before each deadline at which the tick thread stops sleeping and '
        'yields until the deadline (normal scheduling only, never under SCHED_FIFO; costs '
        'CPU).', 0.0, 0.01, read_only=True)
    obstacle_wakeup: bool = _param(
        True, 'An obstacle message wakes the tick thread: the next slot is integrated with '
        'the new obstacles and published at once with its own scheduled stamp (at most one '
        'period early); the schedule is unchanged.')
    controller_output: str = _param(
        'none', "Also publish the references for a ros2_control controller: 'none'; "
        "'forward_command' (std_msgs/Float64MultiArray of positions, for a "
        "forward_command_controller on the position interface); 'joint_trajectory' "
        '(trajectory_msgs/JointTrajectory with one point per tick, time_from_start one '
        'period, positions and velocities, for a joint_trajectory_controller).',
        read_only=True, choices=CONTROLLER_OUTPUTS)
    controller_topic: str = _param(
        '', 'Topic of the controller output; empty: the standard one of the controller '
        "('forward_position_controller/commands' or "
        "'joint_trajectory_controller/joint_trajectory').", read_only=True)
    controller_joints: Tuple[str, ...] = _param(
        (), "The controller's joints in its order (a permutation of joint_names); empty: "
        'joint_names.', read_only=True)
    coupling_links: Tuple[str, ...] = _param(
        ('panda_link3', 'panda_link5'), 'Link segments that get a null-space avoidance term '
        '(Eq. 12); the end effector always gets Eq. 7.', read_only=True)
    coupling_capsule_links: Tuple[str, ...] = _param(
        (), 'Links that get Eq. 12 on one capsule fitted around their URDF collision geometry '
        '(its own radius; it encloses the link, so its distance bounds the true one from '
        'below), next to the joint-axis segments of coupling_links.', read_only=True)
    tcp_offset: Tuple[float, ...] = tcp_offset_param(
        read_only=False, use='on which the end-effector term (Eq. 7) acts, so the tool '
        'itself avoids obstacles (the end-effector point of the chain is its value at the '
        'start)')
    box_field_kind: str = _param(
        'constant', "Potential field of box obstacles: 'constant' (paper 000, IV-B: the "
        "box_field.* parameters) or 'board' (Eq. 30-31, for escaping around a board's edge: "
        'the board_field.* parameters; axis-aligned boxes only, an oriented box makes the '
        'coupling rejected).', choices=BOX_FIELDS)

    def __post_init__(self):
        check_fields(self)
        if self.realtime_threads not in ('all', 'tick'):
            raise ValidationError(f"realtime_threads: expected 'all' or 'tick', got "
                                  f'{self.realtime_threads!r}')
        check_names('joint_names', self.joint_names)
        check_chain_fields(self)
        check_names('controller_joints', self.controller_joints, allow_empty=True)
        if self.controller_joints and sorted(self.controller_joints) != sorted(
                self.joint_names):
            raise ValidationError(f'controller_joints: expected a permutation of joint_names '
                                  f'{list(self.joint_names)}, got {list(self.controller_joints)}')

    @property
    def controller_joint_names(self) -> Tuple[str, ...]:
        """``controller_joints``, or ``joint_names`` when empty."""
        return self.controller_joints or self.joint_names

    @property
    def dt(self) -> float:
        return 1.0 / self.rate
