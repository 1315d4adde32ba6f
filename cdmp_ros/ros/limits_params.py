"""The ``joint_limits.<joint>.*`` parameters (MoveIt's and ros2_control's ``joint_limits.yaml``
convention) and the limits a node runs with: the URDF's position and velocity merged
tighter-of-two with them (:class:`~cdmp_ros.core.joint_limits.KinematicLimits`)."""
from typing import Any, Dict, Sequence

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.joint_limits import (USED_KEYS, KinematicLimits, default_joint_limits,
                                        shipped_limits)

_DESCRIPTIONS = {
    'has_position_limits': 'Use min_position/max_position (tighter-of-two with the URDF).',
    'min_position': 'Lower position limit [rad or m].',
    'max_position': 'Upper position limit [rad or m].',
    'has_velocity_limits': 'Use max_velocity (tighter-of-two with the URDF).',
    'max_velocity': 'Velocity limit [rad/s or m/s].',
    'has_acceleration_limits': 'Use max_acceleration.',
    'max_acceleration': 'Acceleration limit [rad/s^2 or m/s^2].',
    'has_jerk_limits': 'Use max_jerk.',
    'max_jerk': 'Jerk limit [rad/s^3 or m/s^3].',
}


def declare_joint_limits(node, joint_names: Sequence[str]) -> Dict[str, Dict[str, Any]]:
    """Declare ``joint_limits.<joint>.<key>`` (read-only; defaults: the shipped limits of
    :func:`~cdmp_ros.core.joint_limits.default_joint_limits`) and return the entries.

    Raises
    ------
    ValidationError
        A value of the wrong type (naming the parameter).
    """
    defaults = default_joint_limits(joint_names)
    entries = {}
    for joint in joint_names:
        entry = {}
        for key in USED_KEYS:
            name = f'joint_limits.{joint}.{key}'
            flag = key.startswith('has_')
            default = defaults.get(joint, {}).get(key, False if flag else 0.0)
            desc = ParameterDescriptor(description=_DESCRIPTIONS[key], read_only=True,
                                       dynamic_typing=not flag)  # 7500 as well as 7500.0
            try:
                value = node.declare_parameter(name, default, desc).value
            except (ParameterException, TypeError, ValueError) as exc:
                raise ValidationError(f'parameter {name}: {exc}') from None
            entry[key] = float(value) if isinstance(value, int) and not flag else value
        entries[joint] = entry
    return entries


def robot_limits(node, joint_names: Sequence[str], lower, upper, velocity,
                 source: str) -> KinematicLimits:
    """The limits in force: the URDF's position and velocity (arrays in the order of
    ``joint_names``; the model named ``source``) merged tighter-of-two with the
    ``joint_limits.*`` parameters (declared here).

    Raises
    ------
    ValidationError
        A parameter of the wrong type or value, naming it.
    """
    return shipped_limits(joint_names, lower, upper, velocity, f'urdf {source}',
                          declare_joint_limits(node, joint_names))
