"""``diagnostic_msgs/DiagnosticArray`` reporting shared by the nodes.

Every node publishes on the absolute topic ``/diagnostics``
(:data:`cdmp_ros.core.topics.DIAGNOSTICS_TOPIC`; design.md, Topics), where
diagnostic_aggregator and rqt_robot_monitor read it, whatever the node's namespace; the status
names tell the nodes apart by their fully qualified name (``streamer: state`` in the root
namespace, ``arm/streamer: state`` under ``-r __ns:=/arm``).

:class:`DiagnosticsReporter` collects, between two publications:

- rejected inputs per topic (count since start, count since the last report, the last reason),
  each also logged (throttled, so that a flood of bad messages does not flood the log);
- timings (``timing(name, seconds)``): count, mean, p99 and max over a ring buffer of the last
  ``window`` samples (allocation-free when recording);
- the node's state: level (OK/WARN/ERROR), a message and key/values set by the node;
- standing conditions (``set_condition``): a problem that holds until the node clears it
  (a robot model that differs from the ``robot_description`` topic), whatever state the
  node sets meanwhile: the state status is at least the condition's level and its message
  ends with the condition's text.

``publish(now)`` sends one ``DiagnosticArray`` with a status ``<node>: state`` (``<node>``: the
node's fully qualified name without the leading slash), one
``<node>: input <topic>`` per topic that ever had a rejection (``rejected_total``,
``rejected_since_last_report``, ``last_reason`` and ``rejected_<category>`` per reason
category given) and one ``<node>: timing``.
``publish_if_due`` also publishes early (at most every ``min_interval``) when something was
rejected, so a rejection shows on ``/diagnostics`` promptly but a flood is summarised.
"""
import math
import time
from typing import Dict, List, Optional, Tuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR


def _rank(level) -> int:
    """A DiagnosticStatus level (bytes, as the message module defines them, or int) as int."""
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


class _Timing:
    __slots__ = ('buf', 'n', 'i', 'total', 'max')

    def __init__(self, window: int):
        self.buf = [0.0] * window
        self.n = 0
        self.i = 0
        self.total = 0
        self.max = 0.0

    def add(self, v: float) -> None:
        self.buf[self.i] = v
        self.i = (self.i + 1) % len(self.buf)
        if self.n < len(self.buf):
            self.n += 1
        self.total += 1
        if v > self.max:
            self.max = v

    def stats(self) -> Tuple[float, float, float]:
        vals = sorted(self.buf[:self.n])
        if not vals:
            return 0.0, 0.0, 0.0
        p99 = vals[min(len(vals) - 1, int(math.ceil(0.99 * len(vals))) - 1)]
        return sum(vals) / len(vals), p99, max(vals)


def node_prefix(node) -> str:
    """The status-name prefix of ``node``: its fully qualified name without the leading slash."""
    return node.get_fully_qualified_name().lstrip('/')


class DiagnosticsReporter:
    """Builds and publishes the node's ``DiagnosticArray`` (see the module docstring).

    Parameters
    ----------
    node : rclpy.node.Node
    publisher : rclpy publisher of DiagnosticArray
    name : str, optional
        Prefix of the status names; default the node's fully qualified name without the
        leading slash (``streamer``, ``arm/streamer``, or the name given by ``-r __node:=``),
        which tells apart the nodes that share ``/diagnostics``.
    window : int
        Number of samples kept per timing.
    log_period : float
        Minimum time [s] between two log lines for rejections on the same topic.
    """

    def __init__(self, node, publisher, name: Optional[str] = None, window: int = 2000,
                 log_period: float = 1.0):
        self.node = node
        self.publisher = publisher
        self.name = node_prefix(node) if name is None else name
        self.window = window
        self.log_period = log_period
        self.level = OK
        self.message = 'starting'
        self.values: Dict[str, str] = {}
        self._rejected: Dict[str, List] = {}  # topic -> [total, since_report, reason, last_log]
        self._categories: Dict[str, Dict[str, int]] = {}  # topic -> {category: count}
        self._timings: Dict[str, _Timing] = {}
        self._conditions: Dict[str, Tuple[object, str]] = {}  # name -> (level, text)
        self._dirty = False
        self._last_publish = -math.inf
        self.published = 0

    def set_state(self, level: int, message: str, **values) -> None:
        """The node's summary status; ``values`` are added as key/values (str())."""
        self.level = level
        self.message = message
        for k, v in values.items():
            self.values[k] = str(v)

    def set_condition(self, name: str, level, text: Optional[str]) -> None:
        """A standing condition ``name`` of the node, shown in the state status until it is
        cleared (``text`` None): the level is at least ``level``, the message ends with
        ``text``."""
        if text is None:
            self._conditions.pop(name, None)
        else:
            self._conditions[name] = (level, text)

    def reject(self, topic: str, reason: str, category: Optional[str] = None) -> None:
        """Record (and log, throttled) a rejected or sanitised input on ``topic``; with a
        ``category``, also counted as ``rejected_<category>`` of the topic."""
        if category is not None:
            cats = self._categories.setdefault(topic, {})
            cats[category] = cats.get(category, 0) + 1
        entry = self._rejected.get(topic)
        now = time.monotonic()
        if entry is None:
            entry = self._rejected[topic] = [0, 0, '', -math.inf]
        entry[0] += 1
        entry[1] += 1
        entry[2] = reason
        if now - entry[3] >= self.log_period:
            extra = f' ({entry[1]} since last report)' if entry[1] > 1 else ''
            self.node.get_logger().warning(f'{topic}: {reason}{extra}')
            entry[3] = now
        self._dirty = True

    def rejected_count(self, topic: str) -> int:
        entry = self._rejected.get(topic)
        return entry[0] if entry else 0

    def timing(self, name: str, seconds: float) -> None:
        t = self._timings.get(name)
        if t is None:
            t = self._timings[name] = _Timing(self.window)
        t.add(seconds)

    def build(self, stamp) -> DiagnosticArray:
        """The DiagnosticArray of the current state (``stamp``: builtin_interfaces/Time)."""
        arr = DiagnosticArray()
        arr.header.stamp = stamp
        hw = self.node.get_fully_qualified_name()
        level = self.level
        recent = [t for t, e in self._rejected.items() if e[1]]
        if recent and level == OK:
            level = WARN
        msg = self.message
        for c_level, text in self._conditions.values():
            if _rank(c_level) > _rank(level):
                level = c_level
            msg += '; ' + text
        if recent:
            msg += '; rejected input on ' + ', '.join(sorted(recent))
        arr.status.append(DiagnosticStatus(
            level=level, name=f'{self.name}: state', message=msg, hardware_id=hw,
            values=[KeyValue(key=k, value=v) for k, v in sorted(self.values.items())]))
        for topic, (total, since, reason, _) in sorted(self._rejected.items()):
            arr.status.append(DiagnosticStatus(
                level=WARN if since else OK, name=f'{self.name}: input {topic}',
                message=f'rejected: {reason}' if since else 'ok', hardware_id=hw,
                values=[KeyValue(key='rejected_total', value=str(total)),
                        KeyValue(key='rejected_since_last_report', value=str(since)),
                        KeyValue(key='last_reason', value=reason)]
                + [KeyValue(key=f'rejected_{c}', value=str(n))
                   for c, n in sorted(self._categories.get(topic, {}).items())]))
        if self._timings:
            values = []
            for name, t in sorted(self._timings.items()):
                mean, p99, mx = t.stats()
                values += [KeyValue(key=f'{name}_mean_ms', value=f'{mean * 1e3:.4f}'),
                           KeyValue(key=f'{name}_p99_ms', value=f'{p99 * 1e3:.4f}'),
                           KeyValue(key=f'{name}_max_ms', value=f'{mx * 1e3:.4f}'),
                           KeyValue(key=f'{name}_count', value=str(t.total))]
            arr.status.append(DiagnosticStatus(level=OK, name=f'{self.name}: timing',
                                               message='timings', hardware_id=hw,
                                               values=values))
        return arr

    def publish(self, stamp) -> None:
        self.publisher.publish(self.build(stamp))
        for entry in self._rejected.values():
            entry[1] = 0
        self._dirty = False
        self._last_publish = time.monotonic()
        self.published += 1

    def publish_if_due(self, stamp, min_interval: float = 0.1) -> bool:
        """Publish now if a rejection is pending and ``min_interval`` has passed."""
        if self._dirty and time.monotonic() - self._last_publish >= min_interval:
            self.publish(stamp)
            return True
        return False
