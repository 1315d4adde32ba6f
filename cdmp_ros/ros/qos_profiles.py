"""QoS profiles of the cdmp_ros topics (design.md, Topics).

- ``joint_reference``: :data:`REFERENCE`, reliable, volatile, keep last 10: matches reliable
  and best-effort controller subscriptions; never replays stale references.
- ``joint_states`` (subscribed): :data:`SENSOR`, best effort, keep last 5: matches any
  publisher; only the newest sample matters.
- ``goal``, ``obstacles``, ``diagnostics``: :data:`COMMAND`, reliable, volatile, keep last 10
  (as ``ros2 topic pub`` and ``diagnostic_updater``).
- ``primitive``, ``adapted_primitive``: :data:`LATCHED`, reliable, transient local, keep last
  1: a late subscriber (a restarted streamer) still gets the current primitive.
"""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

REFERENCE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
SENSOR = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                    reliability=ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.VOLATILE)
COMMAND = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.VOLATILE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
