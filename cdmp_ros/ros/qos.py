"""QoS of cdmp_ros: the profiles of its topics, rclpy <-> rosbag2 metadata dicts, and the
recorder's adaptive choice.

Topic profiles (design.md, Topics):

- ``joint_reference``: :data:`REFERENCE`, reliable, volatile, keep last 10: matches reliable
  and best-effort controller subscriptions; never replays stale references.
- ``joint_states`` (subscribed): :data:`SENSOR`, best effort, keep last 5: matches any
  publisher; only the newest sample matters.
- ``goal``, ``obstacles``, ``/diagnostics``: :data:`COMMAND`, reliable, volatile, keep last 10
  (as ``ros2 topic pub`` and ``diagnostic_updater``).
- ``primitive``, ``adapted_primitive``: :data:`LATCHED`, reliable, transient local, keep last
  1: a late subscriber (a restarted streamer) still gets the current primitive.
  ``robot_description`` (subscribed) too, as robot_state_publisher publishes it.

The recorder subscribes like ``ros2 bag record``: reliable only if every publisher offers
reliable, transient-local only if every publisher offers it (so latched topics such as
``primitive`` keep their last message), history keep-last with a deep queue.
"""
from typing import Any, Dict, Iterable, List

from rclpy.duration import Duration
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)

from cdmp_ros.bag.metadata import INFINITE


def _keep_last(depth: int, reliable: bool = True, latched: bool = False) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=(ReliabilityPolicy.RELIABLE if reliable
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


REFERENCE = _keep_last(10)
SENSOR = _keep_last(5, reliable=False)
COMMAND = _keep_last(10)
LATCHED = _keep_last(1, latched=True)
#: The sim's ``joint_states`` and ``ee_pose``: reliable, volatile, keep last 50.
SIM_STATE = _keep_last(50)
#: ``/clock`` of the sim (``publish_clock``): reliable, volatile, keep last 1.
CLOCK = _keep_last(1)

#: Default depth of the recorder's subscription queues (messages per topic).
RECORDER_DEPTH = 10000

_NAMES = {
    'history': {HistoryPolicy.KEEP_LAST: 'keep_last', HistoryPolicy.KEEP_ALL: 'keep_all',
                HistoryPolicy.SYSTEM_DEFAULT: 'system_default'},
    'reliability': {ReliabilityPolicy.RELIABLE: 'reliable',
                    ReliabilityPolicy.BEST_EFFORT: 'best_effort',
                    ReliabilityPolicy.SYSTEM_DEFAULT: 'system_default'},
    'durability': {DurabilityPolicy.VOLATILE: 'volatile',
                   DurabilityPolicy.TRANSIENT_LOCAL: 'transient_local',
                   DurabilityPolicy.SYSTEM_DEFAULT: 'system_default'},
    'liveliness': {LivelinessPolicy.AUTOMATIC: 'automatic',
                   LivelinessPolicy.MANUAL_BY_TOPIC: 'manual_by_topic',
                   LivelinessPolicy.SYSTEM_DEFAULT: 'system_default'},
}
_INF_NS = INFINITE['sec'] * 10 ** 9 + INFINITE['nsec']


def _duration_dict(d: Duration) -> Dict[str, int]:
    ns = d.nanoseconds
    if ns <= 0 or ns >= _INF_NS:
        return dict(INFINITE)
    return {'sec': ns // 10 ** 9, 'nsec': ns % 10 ** 9}


def profile_to_dict(qos: QoSProfile) -> Dict[str, Any]:
    """An rclpy QoS profile in the rosbag2 metadata (version 9) layout."""
    return {'history': _NAMES['history'].get(qos.history, 'unknown'),
            'depth': int(qos.depth),
            'reliability': _NAMES['reliability'].get(qos.reliability, 'unknown'),
            'durability': _NAMES['durability'].get(qos.durability, 'unknown'),
            'deadline': _duration_dict(qos.deadline),
            'lifespan': _duration_dict(qos.lifespan),
            'liveliness': _NAMES['liveliness'].get(qos.liveliness, 'unknown'),
            'liveliness_lease_duration': _duration_dict(qos.liveliness_lease_duration),
            'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions)}


def _policy(kind: str, value: Any, default):
    if isinstance(value, int):
        try:
            return type(default)(value)
        except ValueError:
            return default
    for enum, name in _NAMES[kind].items():
        if name == str(value).lower():
            return enum
    return default


def dict_to_profile(d: Dict[str, Any], depth: int = 0) -> QoSProfile:
    """A publisher profile for replaying a topic recorded with QoS ``d``.

    Deadline, lifespan and liveliness lease are not replayed (as ``ros2 bag play``).
    """
    history = _policy('history', d.get('history'), HistoryPolicy.KEEP_LAST)
    if history == HistoryPolicy.SYSTEM_DEFAULT:
        history = HistoryPolicy.KEEP_LAST
    return QoSProfile(
        history=history,
        depth=max(int(d.get('depth') or 0), depth, 1),
        reliability=_policy('reliability', d.get('reliability'), ReliabilityPolicy.RELIABLE),
        durability=_policy('durability', d.get('durability'), DurabilityPolicy.VOLATILE))


def playback_profile(profiles: List[Dict[str, Any]], depth: int = 100) -> QoSProfile:
    """Publisher QoS for replay: the first recorded offer, reliable by default."""
    if profiles:
        return dict_to_profile(profiles[0], depth)
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def adapted_subscription_profile(offered: Iterable[QoSProfile],
                                 depth: int = RECORDER_DEPTH) -> QoSProfile:
    """Subscription QoS compatible with every offered publisher profile (rosbag2's rule)."""
    offered = list(offered)
    reliable = bool(offered) and all(
        q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(
        q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
