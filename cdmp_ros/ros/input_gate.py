"""Input admission shared by every node: one gate in front of every user-input subscription.

Every subscription made through :meth:`InputGate.subscribe` is a serialized (``raw=True``)
subscription, so that nothing is done for a message before it is admitted. In order:

1. **rate limit** (:class:`~cdmp_ros.common.rate_limit.RateLimiter`, per topic): the excess is
   dropped before anything else, every drop counted (reason ``flooding``);
2. **constant-time size checks** on the CDR bytes, before deserialisation: the message size,
   and the element count read from the CDR header (:mod:`cdmp_ros.bag.cdr`; markers of a
   ``MarkerArray``, names of a ``JointState``, bytes of a ``std_msgs/String``); see
   :func:`marker_count`, :func:`json_bytes` and :func:`description_bytes` (both
   :func:`string_bytes`), :func:`joint_names`, :func:`message_bytes`;
3. **deserialisation** (a ``MarkerArray`` by :mod:`cdmp_ros.bag.cdr`, the rest by
   rclpy), then the header stamp (:func:`~cdmp_ros.ros.convert.check_stamp`);
4. the node's callback, which runs the per-element validation (:mod:`cdmp_ros.ros.convert`)
   and reports its own rejections through :meth:`InputGate.reject`.

Every rejection is counted by topic and reason category (:data:`REASONS`) and reported on
``/diagnostics`` (:class:`~cdmp_ros.ros.diagnostics.DiagnosticsReporter`): the status
``<node>: input <topic>`` carries ``rejected_total``, ``last_reason`` and
``rejected_<category>``; :meth:`InputGate.values` gives ``rejected_total`` and
``rejected_<category>`` over all topics for the node's state status.

Why before deserialisation: turning a 5,000-marker ``MarkerArray`` into Python objects costs
about 0.2 s on these machines, whatever the node does with it next.
"""
import threading
import time
from typing import Callable, Dict, Optional

import numpy as np
from rclpy.serialization import deserialize_message
from visualization_msgs.msg import MarkerArray

from cdmp_ros.bag.cdr import (UnsupportedEncoding, cdr_first_count, cdr_joint_state_names,
                              decode_marker_array)
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.common.rate_limit import RateLimiter
from cdmp_ros.ros.convert import check_stamp, stamp_to_ns
from cdmp_ros.ros.recorder_take import (ThreadTakenGroup, never_called, take_newest,
                                        to_monotonic)

#: Reason categories counted on diagnostics as ``rejected_<category>``: first match wins.
REASONS = (('flooding', ('flooding',)),
           ('oversize', ('rejected unparsed',)),
           ('stamp', ('in the future', 'in the past', 'unstamped')),
           ('non_finite', ('finite value', 'finite values')),
           ('joint_names', ('unknown joints', 'missing joints', 'duplicate joint')),
           ('length', ('values (one per name)', 'expected 0 or')),
           ('limits', ('outside the limits', 'velocity limit')),
           ('frame', ('frame_id',)), ('marker_scale', ('scale.',)),
           ('marker_type', ('.type:',)), ('marker_action', ('.action:', 'DELETE of unknown')),
           ('too_many', ('obstacle limit',)), ('marker_pose', ('pose.',)),
           ('malformed', ('not valid JSON', 'cannot be deserialized')),
           ('superseded', ('superseded by',)))

#: Serialized bytes allowed per marker of a MarkerArray (a SPHERE / CUBE marker with short
#: frame and namespace strings is about 220 bytes; points, colors, text, meshes and textures
#: are not used by obstacles).
MARKER_BYTES = 4096
#: Serialized bytes allowed per joint of a JointState (name up to 256 characters, position,
#: velocity and effort) and for its header.
JOINT_BYTES = 256 + 4 + 3 * 8
HEADER_BYTES = 512
#: Names allowed in ``joint_states`` beyond the robot's joints (gripper joints and the like).
EXTRA_JOINTS = 64
#: A PointStamped (or any other fixed-size message with a header) is at most this long.
SMALL_MESSAGE_BYTES = 1024
#: Largest accepted ``robot_description`` (URDF XML) payload [bytes]: about ten times the
#: expanded xacro of a large robot (a PR2 is about 0.4 MB, a Panda 11-30 kB). Parsing takes
#: about 0.2 s per MB here.
ROBOT_DESCRIPTION_BYTES = 4_000_000


def reason_category(reason: str) -> str:
    """The :data:`REASONS` category of a rejection message ('other' if none matches)."""
    for cat, texts in REASONS:
        if any(t in reason for t in texts):
            return cat
    return 'other'


# -- constant-time size checks: (topic, serialized bytes) -> reason or None ------------------
def message_bytes(limit: Callable[[], int]):
    """Reject a message longer than ``limit()`` bytes."""
    def check(topic: str, data: bytes) -> Optional[str]:
        lim = limit()
        if len(data) > lim:
            return f'{topic}: message of {len(data)} bytes exceeds {lim} bytes; rejected unparsed'
        return None
    return check


def marker_count(max_obstacles: Callable[[], int]):
    """Reject a MarkerArray of more than ``max_obstacles() + 1`` markers (room for a leading
    DELETEALL) or more than :data:`MARKER_BYTES` per allowed marker."""
    def check(topic: str, data: bytes) -> Optional[str]:
        lim = max_obstacles() + 1
        n = cdr_first_count(data)
        if n is not None and n > lim:
            return (f'{topic}.markers: {n} markers exceed max_obstacles + 1 = {lim}; rejected '
                    'unparsed')
        if len(data) > lim * MARKER_BYTES + HEADER_BYTES:
            return (f'{topic}: message of {len(data)} bytes exceeds {MARKER_BYTES} bytes per '
                    f'marker for {lim} markers; rejected unparsed')
        return None
    return check


def string_bytes(max_bytes: Callable[[], int], limit_name: str):
    """Reject a ``std_msgs/String`` whose payload is longer than ``max_bytes()`` (UTF-8);
    the reason names the limit ``limit_name``."""
    def check(topic: str, data: bytes) -> Optional[str]:
        lim = max_bytes()
        n = cdr_first_count(data)
        size = (n - 1) if n else len(data)
        if size > lim:
            return (f'{topic}: payload of {size} bytes exceeds {limit_name} = {lim}; '
                    'rejected unparsed')
        return None
    return check


def json_bytes(max_bytes: Callable[[], int]):
    """Reject a ``std_msgs/String`` whose payload is longer than ``max_bytes()`` (UTF-8)."""
    return string_bytes(max_bytes, 'max_json_bytes')


def description_bytes():
    """Reject a ``robot_description`` longer than :data:`ROBOT_DESCRIPTION_BYTES`."""
    return string_bytes(lambda: ROBOT_DESCRIPTION_BYTES, 'ROBOT_DESCRIPTION_BYTES')


def read_raw(msg_type, topic: str, data: bytes, size=None):
    """The size check (``size``, one of the checks above, or None) and the deserialisation of
    one serialized message: ``(message, None, None)``, or ``(None, reason, category)``."""
    if size is not None:
        reason = size(topic, data)
        if reason is not None:
            return None, reason, 'oversize'
    try:
        return deserialize(data, msg_type), None, None
    except Exception as exc:  # noqa: BLE001 -- a bad payload must not end the node
        return None, f'{topic}: cannot be deserialized ({exc})', 'malformed'


def deserialize(data: bytes, msg_type):
    """The message of ``data``: a ``MarkerArray`` as
    :class:`~cdmp_ros.bag.cdr.WireMarkerArray` records (rclpy's message if its
    encapsulation is not plain CDR), any other type by rclpy."""
    if msg_type is MarkerArray:
        try:
            return decode_marker_array(data)
        except UnsupportedEncoding:
            pass
    return deserialize_message(data, msg_type)


def joint_names(max_names: Callable[[], int]):
    """Reject a JointState of more than ``max_names()`` names, or longer than
    :data:`JOINT_BYTES` per allowed name (position, velocity and effort arrays included)."""
    def check(topic: str, data: bytes) -> Optional[str]:
        lim = max_names()
        n = cdr_joint_state_names(data)
        if n is not None and n > lim:
            return f'{topic}.name: {n} names exceed the limit of {lim}; rejected unparsed'
        if len(data) > lim * JOINT_BYTES + HEADER_BYTES:
            return (f'{topic}: message of {len(data)} bytes exceeds {JOINT_BYTES} bytes per '
                    f'joint for {lim} joints; rejected unparsed')
        return None
    return check


class InputGate:
    """Rate limits, constant-time size checks and rejection counting of a node's inputs.

    Parameters
    ----------
    node : rclpy.node.Node
    reporter : DiagnosticsReporter
        Where rejections are reported.
    config : callable
        Returns the node's config (``max_stamp_age``, ``max_stamp_lead``,
        ``accept_unstamped``), read at every check (parameter changes apply at once).
    now_ns : callable, optional
        Now in the time base of the stamps (default: the node's ROS clock).
    lock : lock, optional
        Held while the reporter is used (a node that publishes its diagnostics from another
        thread passes the lock it uses there).
    """

    def __init__(self, node, reporter, config: Callable, now_ns: Optional[Callable] = None,
                 lock=None):
        self.node = node
        self.reporter = reporter
        self.config = config
        self.now_ns = now_ns or (lambda: node.get_clock().now().nanoseconds)
        self.lock = lock if lock is not None else threading.Lock()
        self.limiters: Dict[str, RateLimiter] = {}
        self.by_reason: Dict[str, int] = {}
        self.received: Dict[str, int] = {}

    # -- configuration -----------------------------------------------------------------------
    def set_rates(self, rates: Dict[str, float]) -> None:
        """(Re)create the rate limiters of the given topics (messages/s)."""
        for topic, rate in rates.items():
            self.limiters[topic] = RateLimiter(rate)

    def subscribe(self, msg_type, topic: str, callback: Callable, qos, size=None,
                  stamped: bool = False):
        """A serialized subscription of ``topic`` whose messages reach ``callback`` only
        through the gate (rate limit, ``size`` check, deserialisation, header stamp when
        ``stamped``). ``topic`` must have a rate (:meth:`set_rates`)."""
        return self.node.create_subscription(
            msg_type, topic, self.raw_callback(msg_type, topic, callback, size, stamped), qos,
            raw=True)

    def raw_callback(self, msg_type, topic: str, callback: Callable, size=None,
                     stamped: bool = False) -> Callable[[bytes], None]:
        """The callback of a serialized subscription made elsewhere, passing its messages
        through the gate as :meth:`subscribe` does."""
        def on_raw(data: bytes) -> None:
            self.received[topic] = self.received.get(topic, 0) + 1
            if not self.admit(topic):
                return
            msg = self._checked(msg_type, topic, data, size, stamped)
            if msg is not None:
                callback(msg)
        return on_raw

    def subscribe_polled(self, msg_type, topic: str, callback: Callable, qos, size=None,
                         stamped: bool = False) -> Callable[[], None]:
        """A serialized subscription of ``topic`` that no executor waits on; returns
        ``poll()``, which takes what the reader holds (at most the ``qos`` depth, keep-last)
        and passes the newest message through the checks of :meth:`subscribe` (no rate limit:
        the work is bounded by how often the node polls) to ``callback(msg, received)``,
        ``received`` = its receive time in ``time.monotonic()`` seconds.

        For a state the node needs only now and then (the adapter's ``joint_states``, read
        when it forms a request): a subscription served by the executor would wake it for
        every message, about 1 ms of Python per wake-up on these machines, taken from the
        node's other threads through the GIL. Older queued messages are superseded, not
        checked. Call ``poll()`` from one thread at a time."""
        sub = self.node.create_subscription(msg_type, topic, never_called, qos,
                                            callback_group=ThreadTakenGroup(), raw=True)
        max_count = 4 * max(1, int(qos.depth))   # bounded even while messages keep coming

        def poll() -> None:
            newest, n = take_newest(sub, max_count)
            if newest is None:
                return
            self.received[topic] = self.received.get(topic, 0) + n
            data, info = newest
            received = to_monotonic(info.get('received_timestamp') or time.time_ns())
            msg = self._checked(msg_type, topic, data, size, stamped)
            if msg is not None:
                callback(msg, received)

        return poll

    def _checked(self, msg_type, topic: str, data: bytes, size, stamped: bool):
        """The message of ``data`` if it passes the size check, deserialisation and (when
        ``stamped``) the stamp check; else None, the rejection reported."""
        msg, reason, category = read_raw(msg_type, topic, data, size)
        if msg is None:
            self.reject(topic, reason, category)
            return None
        if stamped and not self.stamp_ok(topic, f'{topic}.header.stamp', msg.header.stamp):
            return None
        return msg

    # -- checks ------------------------------------------------------------------------------
    def admit(self, topic: str, now: Optional[float] = None) -> bool:
        """The rate limit of ``topic``: False (and the drop counted) for the excess."""
        lim = self.limiters[topic]
        if lim.allow(time.monotonic() if now is None else now):
            return True
        self.reject(topic, f'flooding: more than {lim.rate:g} messages/s, {lim.dropped} '
                           'dropped so far', 'flooding')
        return False

    def stamp_ok(self, topic: str, name: str, stamp) -> bool:
        """The stamp check of the node's config; a bad stamp is rejected (False)."""
        cfg = self.config()
        try:
            check_stamp(name, stamp, self.now_ns(), cfg.max_stamp_age, cfg.max_stamp_lead,
                        cfg.accept_unstamped)
        except ValidationError as exc:
            self.reject(topic, str(exc), 'stamp')
            return False
        return True

    def markers(self, topic: str, msg):
        """The markers of a MarkerArray whose stamps pass (DELETEALL needs none), and the
        newest stamp [ns] among them (0 if none is stamped)."""
        good, newest = [], 0
        for i, m in enumerate(msg.markers):
            if m.action != 3 and not self.stamp_ok(
                    topic, f'{topic}.markers[{i}].header.stamp', m.header.stamp):
                continue
            newest = max(newest, stamp_to_ns(m.header.stamp))
            good.append(m)
        return good, newest

    # -- counting ----------------------------------------------------------------------------
    def reject(self, topic: str, reason: str, category: Optional[str] = None) -> None:
        """Count and report a rejected (or sanitised) input on ``topic``."""
        cat = category or reason_category(reason)
        with self.lock:
            self.by_reason[cat] = self.by_reason.get(cat, 0) + 1
            self.reporter.reject(topic, reason, cat)
            self.reporter.publish_if_due(self.node.get_clock().now().to_msg())

    def reject_all(self, topic: str, errors) -> None:
        for exc in errors:
            self.reject(topic, str(exc))

    def joint_arrays(self, mapper, msg, topic: str):
        """``mapper.to_arrays(msg, topic)`` (the positions and velocities of a JointState in
        the node's joint order), or None after rejecting ``msg`` on ``topic`` with the
        mapper's error."""
        try:
            return mapper.to_arrays(msg, topic)
        except ValidationError as exc:
            self.reject(topic, str(exc))
            return None

    def within_limits(self, topic: str, q, lower, upper, tolerance: float, names) -> bool:
        """Whether the measured positions ``q`` lie within ``[lower - tolerance, upper +
        tolerance]``; if not, rejects the message on ``topic`` naming the first joint
        outside."""
        out = np.flatnonzero((q < lower - tolerance) | (q > upper + tolerance))
        if out.size:
            j = int(out[0])
            self.reject(topic, f'{topic}.position of {names[j]!r}: {q[j]:.4g} is outside the '
                               f'limits [{lower[j]}, {upper[j]}]')
            return False
        return True

    def values(self) -> Dict[str, int]:
        """``rejected_total`` and ``rejected_<category>`` over every topic, and
        ``received_<topic>`` (messages that reached the gate, before any check)."""
        out = {f'received_{k}': v for k, v in self.received.items()}
        out.update({f'rejected_{k}': v for k, v in self.by_reason.items()})
        out['rejected_total'] = sum(self.by_reason.values())
        return out
