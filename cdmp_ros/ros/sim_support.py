"""Support of the sim node: QoS of its outputs, input rate limiting, rejection categories."""
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


class RateLimiter:
    """Token bucket: at most ``rate`` events per second on average, bursts of ``burst``.

    The semantics of :class:`cdmp_ros.core.streaming.RateLimiter`, repeated here because
    importing that module pulls in scipy.signal and scipy.stats (about 1.5 s of start-up CPU
    that the sim does not otherwise need).
    """

    def __init__(self, rate: float, burst=None):
        self.rate = float(rate)
        self.burst = float(burst if burst is not None else max(10.0, 0.1 * rate))
        self.tokens = self.burst
        self.last = None
        self.dropped = 0

    def allow(self, now: float) -> bool:
        if self.last is not None:
            self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        self.dropped += 1
        return False


def reason_category(reason: str) -> str:
    """The :data:`REASONS` category of a rejection message ('other' if none matches)."""
    for cat, texts in REASONS:
        if any(t in reason for t in texts):
            return cat
    return 'other'
