"""A node's readiness, measured on the ROS graph (:class:`cdmp_ros.core.readiness.Readiness`).

Each node names its conditions with a description and a check (a callable returning a bool:
a publisher or subscriber count on the graph, a primitive in force). :class:`ReadinessProbe`
evaluates them on a timer (:data:`CHECK_PERIOD`), logs one INFO line per transition
(``ready 0.84 s after start``, :data:`cdmp_ros.core.readiness.READY_LINE`: what
``cdmp bringup --wait-ready`` and a launch file's ``OnProcessIO`` handler wait for) and gives
the ``ready``, ``waiting_for`` and ``ready_after_s`` values of the node's ``/diagnostics``
state.
"""
import time
from typing import Callable, Dict, Mapping, Tuple

from cdmp_ros.core.readiness import Readiness

#: Seconds between two evaluations of the conditions.
CHECK_PERIOD = 0.1


def has_publishers(node, topic: str) -> Callable[[], bool]:
    """A check: at least one publisher on ``topic`` (resolved in the node's namespace)."""
    return lambda: node.count_publishers(topic) > 0


def has_subscribers(node, *topics: str) -> Callable[[], bool]:
    """A check: at least one subscriber on one of ``topics``."""
    return lambda: any(node.count_subscribers(t) > 0 for t in topics)


class ReadinessProbe:
    """Evaluate ``conditions`` (name -> (description, check)) every :data:`CHECK_PERIOD`.

    A check that raises counts as not holding (the node keeps running; the exception is in
    ``waiting_for`` only as the condition's name). The timer runs in the node's executor.
    """

    def __init__(self, node, conditions: Mapping[str, Tuple[str, Callable[[], bool]]]):
        self.node = node
        self.checks: Dict[str, Callable[[], bool]] = {k: c for k, (_, c) in conditions.items()}
        self.readiness = Readiness({k: d for k, (d, _) in conditions.items()},
                                   time.monotonic())
        self.timer = node.create_timer(CHECK_PERIOD, self.check)

    def check(self) -> None:
        states = {}
        for name, fn in self.checks.items():
            try:
                states[name] = bool(fn())
            except Exception:  # noqa: BLE001 -- a graph query during shutdown: not ready
                states[name] = False
        message = self.readiness.update(time.monotonic(), **states)
        if message is not None:
            self.node.get_logger().info(message)

    @property
    def ready(self) -> bool:
        return self.readiness.ready

    def values(self) -> Dict[str, str]:
        return self.readiness.values()
