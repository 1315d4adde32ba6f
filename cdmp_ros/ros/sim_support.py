"""Support of the sim node: QoS of its outputs and rejection categories (its input rate
limiting is :class:`cdmp_ros.core.rate_limit.RateLimiter`, which imports neither numpy nor
scipy)."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

STATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
#: Reason categories counted on diagnostics as ``rejected_<category>``: first match wins.
REASONS = (('flooding', ('flooding',)), ('stamp', ('in the future', 'in the past', 'unstamped')),
           ('non_finite', ('finite value', 'finite values')),
           ('joint_names', ('unknown joints', 'missing joints', 'duplicate joint')),
           ('length', ('values (one per name)', 'expected 0 or')),
           ('limits', ('outside the limits', 'velocity limit')),
           ('frame', ('frame_id',)), ('marker_scale', ('scale.',)),
           ('marker_type', ('.type:',)), ('marker_action', ('.action:', 'DELETE of unknown')),
           ('too_many', ('obstacle limit',)), ('marker_pose', ('pose.',)))


def reason_category(reason: str) -> str:
    """The :data:`REASONS` category of a rejection message ('other' if none matches)."""
    for cat, texts in REASONS:
        if any(t in reason for t in texts):
            return cat
    return 'other'
