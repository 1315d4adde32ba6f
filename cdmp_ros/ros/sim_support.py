"""Support of the sim node: QoS of its outputs (its input admission and rejection categories
are those of every node, :mod:`cdmp_ros.ros.input_gate`)."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

STATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
# the rejection categories live with the input gate (re-exported for existing callers)
from cdmp_ros.ros.input_gate import reason_category, REASONS  # noqa: E402,F401
