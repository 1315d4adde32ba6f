"""ROS glue of the bag layer: the recorder and player nodes (the executables are thin).

:class:`RecorderNode` subscribes with serialized (``raw=True``) subscriptions and hands the
CDR bytes untouched to :class:`cdmp_ros.bag.BagWriter`; :class:`PlayerNode` verifies a whole
bag (every CRC) before it publishes anything, waits (bounded) for a subscriber on every topic
it plays, then publishes the stored bytes with the original timing and, before it ends, waits
(bounded) for the reliable subscribers' acknowledgements.  The decisions of those waits are
the ROS-free functions :func:`poll_until_done`, :func:`without_subscriber` and
:func:`player_state`.  Parameters are declared with descriptors; topic remapping is the standard
``--ros-args -r from:=to``.
"""
import importlib
import threading
import time
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Tuple

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

from cdmp_ros.bag import BagError, BagReader, BagWriter
from cdmp_ros.bag.cdr import encode_clock
from cdmp_ros.bag.schemas import normalize_type
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from cdmp_ros.ros.diagnostics import OK, WARN, DiagnosticsReporter
from cdmp_ros.ros.qos import (COMMAND, RECORDER_DEPTH, adapted_subscription_profile,
                              playback_profile, profile_to_dict)
from cdmp_ros.common.realtime import check_priority
from cdmp_ros.ros.recorder_take import (TakeThread, ThreadTakenGroup, drain_subscription,
                                        never_called, write_taken)

#: Topics left out when recording "all" topics (rclpy's own plumbing).
HIDDEN_TOPICS = ('/rosout', '/parameter_events')


def message_class(type_name: str):
    """The Python message class of ``pkg/msg/Type``.

    Raises
    ------
    BagError
        If the message package is not installed.
    """
    pkg, ns, name = normalize_type(type_name).split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.{ns}'), name)
    except (ImportError, AttributeError):
        raise BagError(f'type {type_name}: message package {pkg} is not installed') from None


def _describe(node: Node, name: str, default, description: str, **ranges):
    desc = ParameterDescriptor(description=description, **ranges)
    if isinstance(default, list) and not default:
        return node.declare_parameter(name, Parameter.Type.STRING_ARRAY, desc).value or []
    return node.declare_parameter(name, default, desc).value


class RecorderNode(Node):
    """Record topics into a rosbag2 bag (MCAP).

    Parameters (ROS)
    ----------------
    output : str
        Bag directory to create (default ``rosbag2_<YYYY_mm_dd-HH_MM_SS>``).
    topics : string array
        Topics to record; empty records every discovered topic except /rosout and
        /parameter_events.
    discovery_period : float
        Seconds between graph polls for new topics / publishers.
    flush_period : float
        Maximum age of an open chunk (crash-loss bound, see cdmp_ros/bag/writer.py).
    chunk_size : int
        Maximum uncompressed chunk size in bytes.
    compression : str
        ``zstd``, ``lz4`` or ``none``.
    queue_depth : int
        Subscription queue depth per topic.
    take_period : float
        Seconds between two drains of the subscriptions by the take thread
        (:mod:`cdmp_ros.ros.recorder_take`); 0 = executor callbacks (one wake-up per arrival).
    realtime_priority : int
        SCHED_FIFO priority of the take thread (needs CAP_SYS_NICE or an rtprio limit;
        refused = warning); 0 = normal scheduling.
    realtime_dds : bool
        With ``realtime_priority``: the Fast DDS receive threads get it too.
    """

    def __init__(self, **kwargs):
        super().__init__('recorder', **kwargs)
        default_out = time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S')
        out = _describe(self, 'output', default_out, 'bag directory to create')
        self.wanted = [self.resolve_topic_name(t) for t in
                       _describe(self, 'topics', [], 'topics to record; empty = all')]
        period = _describe(self, 'discovery_period', 0.2, 'graph poll period (s)',
                           floating_point_range=[FloatingPointRange(
                               from_value=0.01, to_value=10.0)])
        flush = _describe(self, 'flush_period', 0.1, 'max age of an open chunk (s)',
                          floating_point_range=[FloatingPointRange(
                              from_value=0.0, to_value=10.0)])
        chunk = _describe(self, 'chunk_size', 1024 * 1024, 'max chunk size (bytes)',
                          integer_range=[IntegerRange(from_value=4096, to_value=2 ** 30)])
        comp = _describe(self, 'compression', 'zstd', 'chunk compression: zstd, lz4, none')
        self.depth = _describe(self, 'queue_depth', RECORDER_DEPTH, 'subscription queue depth',
                               integer_range=[IntegerRange(from_value=1, to_value=100000)])
        self.take_period = _describe(
            self, 'take_period', 0.005, 'seconds between drains of the take thread; '
            '0 = executor callbacks', floating_point_range=[FloatingPointRange(
                from_value=0.0, to_value=1.0)])
        self.rt_priority = check_priority('realtime_priority', _describe(
            self, 'realtime_priority', 0, 'SCHED_FIFO priority of the receive path; 0 = off',
            integer_range=[IntegerRange(from_value=0, to_value=99)]))
        rt_dds = _describe(self, 'realtime_dds', True,
                           'with realtime_priority: DDS receive threads under SCHED_FIFO too')
        self.writer = BagWriter(out, compression=comp, chunk_size=chunk, flush_period=flush)
        self._subs: Dict[str, object] = {}
        self._closed = False
        self._taker = None
        if self.take_period > 0:
            self._group = ThreadTakenGroup()
            self._taker = TakeThread(self.writer, self.take_period, self.rt_priority, rt_dds,
                                     lambda level, text: getattr(self.get_logger(), level)(text))
        elif self.rt_priority:
            self.get_logger().warning('realtime_priority needs take_period > 0; ignored')
        self._discover()
        self.create_timer(period, self._discover)
        if self._taker is not None:
            self._taker.start()
        elif flush > 0:
            self.create_timer(flush, self.writer.flush)
        self.get_logger().info(f'recording to {out} '
                               f'({", ".join(self.wanted) if self.wanted else "all topics"})')

    # -- discovery -------------------------------------------------------------------------
    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs:
                continue
            if self.wanted and topic not in self.wanted:
                continue
            if not self.wanted and topic in HIDDEN_TOPICS:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue  # only subscribers so far: nothing to record yet
            if len(types) != 1:
                self.get_logger().warning(f'{topic}: several types {types}, not recorded')
                self._subs[topic] = None
                continue
            self._subscribe(topic, types[0], infos)

    def _subscribe(self, topic: str, type_name: str, infos) -> None:
        try:
            cls = message_class(type_name)
        except BagError as exc:
            self.get_logger().warning(f'{topic}: {exc}; not recorded')
            self._subs[topic] = None
            return
        offered = [i.qos_profile for i in infos]
        thash = str(infos[0].topic_type_hash) if infos else ''
        self.writer.add_topic(topic, type_name, [profile_to_dict(q) for q in offered],
                              type_description_hash=thash if thash.startswith('RIHS') else None)
        qos = adapted_subscription_profile(offered, self.depth)
        if self._taker is not None:
            sub = self.create_subscription(cls, topic, never_called, qos,
                                           callback_group=self._group, raw=True)
            self._taker.add(topic, sub)
            self._subs[topic] = sub
            self.get_logger().info(f'subscribed to {topic} [{type_name}]')
            return
        holder: List = []

        def on_message(data: bytes, info: dict) -> None:
            write_taken(self.writer.write, topic, data, info)
            # drain what else is queued: one executor round per batch
            drain_subscription(topic, holder[0], self.writer.write)

        sub = self.create_subscription(cls, topic, on_message, qos, raw=True)
        holder.append(sub)
        self._subs[topic] = sub
        self.get_logger().info(f'subscribed to {topic} [{type_name}]')

    # -- shutdown --------------------------------------------------------------------------
    def close(self) -> None:
        """Take every message still queued, then close the bag (summary + metadata.yaml)."""
        if self._closed:
            return
        self._closed = True
        drain = True
        if self._taker is not None:
            drain = self._taker.stop()
            if self._taker.error is not None:
                print(f'[recorder] take thread stopped: {self._taker.error!r}', flush=True)
            if not drain:
                print('[recorder] take thread still running after 10 s: closing the bag '
                      'without the final drain', flush=True)
        for topic, sub in (self._subs.items() if drain else ()):
            if sub is None:
                continue
            try:
                drain_subscription(topic, sub, self.writer.write)
            except Exception:  # context already down: nothing more can be taken
                pass
        meta = self.writer.close()
        print(f'[recorder] closed {self.writer.bag_dir}: {meta.message_count} messages on '
              f'{len(meta.topics)} topics', flush=True)


#: Topic of the player's clock (rosgraph_msgs/Clock), absolute as every ROS 2 tool expects.
CLOCK_TOPIC = '/clock'
#: Default of ``wait_subscribers`` and ``ack_timeout`` [s].
DEFAULT_WAIT_S = 10.0
#: Upper bound of ``wait_subscribers`` and ``ack_timeout`` [s] (cmd_bag checks the same).
MAX_WAIT_S = 86400.0
#: Poll period of the player's waits [s]: a stop request is honoured within it.
WAIT_PERIOD = 0.01
#: Period of the player's diagnostics [s] (also published at each change of its state).
PLAYER_DIAGNOSTICS_PERIOD = 1.0


def without_subscriber(counts: Iterable[Tuple[str, int]]) -> List[str]:
    """The topics (sorted, once each) of ``counts`` (pairs topic, matched subscriptions of one
    publisher; two bag topics remapped to one name give two pairs) that lack a subscriber."""
    return sorted({t for t, n in counts if n < 1})


def topic_list(topics: Iterable[str]) -> str:
    """``'/a, /clock'``: topics as the player's log and diagnostics name them."""
    return ', '.join(topics)


def poll_until_done(pending: Callable[[], Iterable[str]], timeout: float, stop,
                    on_change: Optional[Callable[[List[str]], None]] = None,
                    period: float = WAIT_PERIOD,
                    clock: Callable[[], float] = time.monotonic) -> List[str]:
    """Poll ``pending()`` (what is still awaited) until it is empty, ``timeout`` seconds have
    passed or ``stop`` (a :class:`threading.Event`) is set; return what is still pending
    (sorted; empty = done).

    ``pending`` is called at least once, also with ``timeout`` 0; ``on_change`` gets every
    new pending list after the first one (a topic got its subscriber, or lost it).
    """
    deadline = clock() + timeout
    last = None
    while True:
        now = sorted(pending())
        if last is not None and now != last and on_change is not None:
            on_change(now)
        last = now
        if not now or stop.is_set():
            return now
        left = deadline - clock()
        if left <= 0:
            return now
        stop.wait(min(period, left))


def player_state(no_subscriber: Sequence[str], not_acknowledged: Optional[Sequence[str]],
                 finished: bool) -> Tuple[bool, str]:
    """``(ok, message)`` of the player's diagnostics state (after the subscriber wait).

    Parameters
    ----------
    no_subscriber : sequence of str
        Those still without a subscriber when the wait ended (played anyway).
    not_acknowledged : sequence of str or None
        Reliable topics whose subscribers did not acknowledge every message within the
        acknowledgement timeout (None: not checked yet, or not at all).
    finished : bool
        The bag has been played (and the acknowledgement wait is over).
    """
    parts = ['finished' if finished else 'playing']
    if no_subscriber:
        parts.append(f'played without subscriber on {topic_list(no_subscriber)}')
    if not_acknowledged:
        parts.append(f'not acknowledged on {topic_list(not_acknowledged)}')
    return not (no_subscriber or not_acknowledged), '; '.join(parts)


class PlayerNode(Node):
    """Replay a bag with its original timing.

    Before the first message the player waits until every topic it plays (remapped names),
    and ``/clock`` with ``clock``, has at least one matched subscription, at most
    ``wait_subscribers`` seconds; then it plays anyway and names the topics that had none
    (log and ``/diagnostics``). After the last message (not looping) it waits, at most
    ``ack_timeout`` seconds, until every reliable subscriber acknowledged every message,
    names the topics not acknowledged, and ends. A stop signal ends every wait at once.

    Parameters (ROS)
    ----------------
    bag : str
        Bag directory (or ``.mcap`` file) to play.
    rate : float
        Playback rate factor (2.0 = twice as fast).
    loop : bool
        Start over at the end.
    topics : string array
        Topics to play (as recorded); empty = all.
    clock : bool
        Publish ``/clock`` (rosgraph_msgs/Clock) with the bag time before every message.
    wait_subscribers : float
        Longest wait for a subscriber on every played topic and ``/clock`` (s); 0 = play
        at once.
    ack_timeout : float
        Longest wait after the last message for the reliable subscribers to acknowledge
        every message, all topics together (s); 0 = end at once.
    start_delay : float
        Seconds to wait before the first message, after the subscriber wait.

    The former parameters ``wait_for_subscribers`` and ``wait_timeout`` are no longer used:
    set, they give a warning that names their replacement.
    """

    def __init__(self, **kwargs):
        super().__init__('player', **kwargs)
        self.bag = _describe(self, 'bag', '', 'bag directory or .mcap file to play')
        self.rate = _describe(self, 'rate', 1.0, 'playback rate factor',
                              floating_point_range=[FloatingPointRange(
                                  from_value=0.001, to_value=1000.0)])
        self.loop = _describe(self, 'loop', False, 'loop the bag')
        selected = _describe(self, 'topics', [], 'topics to play; empty = all')
        self.clock = _describe(self, 'clock', False, 'publish /clock')
        seconds = [FloatingPointRange(from_value=0.0, to_value=MAX_WAIT_S)]
        self.wait_subscribers = _describe(
            self, 'wait_subscribers', DEFAULT_WAIT_S, 'longest wait before playing for a '
            'subscriber on every played topic and /clock (s); 0 = play at once',
            floating_point_range=seconds)
        self.ack_timeout = _describe(
            self, 'ack_timeout', DEFAULT_WAIT_S, 'longest wait after the last message for '
            'the reliable subscribers to acknowledge every message (s); 0 = end at once',
            floating_point_range=seconds)
        self.start_delay = _describe(self, 'start_delay', 0.0, 'delay before playing (s)')
        for old, new in (('wait_for_subscribers', 'wait_subscribers (seconds)'),
                         ('wait_timeout', 'wait_subscribers and ack_timeout')):
            desc = ParameterDescriptor(description=f'no longer used: see {new}',
                                       dynamic_typing=True)
            if self.declare_parameter(old, None, desc).value is not None:
                self.get_logger().warning(f'parameter {old} is no longer used (ignored): the '
                                          f'player now takes {new}')
        self.exit_code = 0
        self._done = False
        self._closed = False
        self._thread = None
        if not self.bag:
            raise BagError('parameter bag: expected a bag directory, got an empty string')
        # Refuse corrupted or truncated input before anything is published.
        self.reader = BagReader(self.bag)
        topics = self.reader.verify()
        self.selected = {t for t in topics if not selected or t in selected
                         or t.lstrip('/') in selected}
        missing = [t for t in selected if t not in topics and '/' + t.lstrip('/') not in topics]
        if missing:
            self.get_logger().warning(f'topics not in the bag: {missing}')
        self.pubs = {}
        for name in sorted(self.selected):
            info = topics[name]
            try:
                cls = message_class(info.type)
            except BagError as exc:
                self.get_logger().warning(f'{name}: {exc}; not played')
                continue
            profiles = info.offered_qos_profiles
            if self.reader.metadata is not None:
                for t in self.reader.metadata.topics:
                    if t.name == name and t.offered_qos_profiles:
                        profiles = t.offered_qos_profiles
            self.pubs[name] = self.create_publisher(cls, name, playback_profile(profiles))
        self.clock_pub = None
        if self.clock:
            from rosgraph_msgs.msg import Clock
            self.clock_pub = self.create_publisher(Clock, CLOCK_TOPIC, QoSProfile(depth=10))
        # (name on the wire (remapped), publisher), /clock included: what subscribers see
        self.outputs = [(p.topic_name, p) for p in [*self.pubs.values(), self.clock_pub]
                        if p is not None]
        self.published = 0
        self.waited: List[str] = []
        self.no_subscriber: List[str] = []
        self.not_acknowledged: Optional[List[str]] = None
        self._diag_lock = threading.Lock()
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, COMMAND)
        self.reporter = DiagnosticsReporter(self, self.diag_pub)
        self.reporter.set_state(OK, 'starting', bag=self.bag,
                                wait_subscribers=self.wait_subscribers,
                                ack_timeout=self.ack_timeout)
        self.create_timer(PLAYER_DIAGNOSTICS_PERIOD, self._publish_diagnostics)
        self._stop = threading.Event()
        self.get_logger().info(f'playing {self.bag}: {sorted(self.pubs)} at rate {self.rate}')
        self._thread = threading.Thread(target=self._run, name='player', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        """Playback thread: publishing needs no executor; shutdown is checked between
        messages and during every wait."""
        try:
            self._wait_for_subscribers()
            if self._stop.is_set() or self._stop.wait(self.start_delay):
                return
            self._report(False)
            while True:
                self._play_once()
                if not self.loop or self._stop.is_set():
                    break
            if self._stop.is_set():
                return
            self._wait_acked()
            self._report(True, flush=True)
        except BagError as exc:
            self.get_logger().error(f'playback stopped: {exc}')
            self.exit_code = 1
        except Exception as exc:  # context shut down under us: stop quietly
            if not self._stop.is_set():
                self.get_logger().error(f'playback failed: {exc!r}')
                self.exit_code = 1
        finally:
            self._done = True

    def _wait_for_subscribers(self) -> None:
        """Wait (at most ``wait_subscribers`` s) for a subscriber on every output topic."""
        if self.wait_subscribers <= 0 or not self.outputs:
            return
        self.waited = sorted({t for t, _ in self.outputs})
        log = self.get_logger()
        log.info(f'waiting up to {self.wait_subscribers:g} s for a subscriber on '
                 f'{topic_list(self.waited)}')
        with self._diag_lock:
            self.reporter.set_state(OK, f'waiting for a subscriber on '
                                    f'{topic_list(self.waited)}')
        self._publish_diagnostics()

        def still_waiting(now: List[str]) -> None:
            if now:
                log.info(f'still waiting for a subscriber on {topic_list(now)}')
        missing = poll_until_done(
            lambda: without_subscriber((t, p.get_subscription_count())
                                       for t, p in self.outputs),
            self.wait_subscribers, self._stop, still_waiting)
        if self._stop.is_set():
            return
        self.no_subscriber = missing
        if missing:
            log.warning(f'no subscriber on {topic_list(missing)} after '
                        f'{self.wait_subscribers:g} s; playing anyway')
        else:
            log.info('every topic has a subscriber')

    def _wait_acked(self) -> None:
        """Before the node ends: every reliable subscriber has acknowledged every message (a
        destroyed writer drops what a slow reader has not received yet), all topics together
        waiting at most ``ack_timeout``."""
        from rclpy.duration import Duration
        from rclpy.qos import ReliabilityPolicy
        if self.ack_timeout <= 0:
            return
        reliable = [(t, p) for t, p in self.outputs
                    if p.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                    and p.get_subscription_count() > 0]
        if not reliable:  # no reliable subscriber: nothing to wait for
            self.not_acknowledged = []
            return
        now = Duration(seconds=0)
        left = poll_until_done(
            lambda: {t for t, p in reliable if not p.wait_for_all_acked(now)},
            self.ack_timeout, self._stop)
        if self._stop.is_set():
            return
        self.not_acknowledged = left
        if left:
            self.get_logger().warning(
                f'not acknowledged within {self.ack_timeout:g} s on {topic_list(left)}: a '
                'reliable subscriber may have missed messages')
        else:
            self.get_logger().info('every reliable subscriber acknowledged every message on '
                                   f'{topic_list(sorted({t for t, _ in reliable}))}')

    def _report(self, finished: bool, flush: bool = False) -> None:
        """Set and publish the diagnostics state; with ``flush``, wait (bounded) until the
        diagnostics subscribers acknowledged it (the node is about to end)."""
        ok, text = player_state(self.no_subscriber, self.not_acknowledged, finished)
        values = {'no_subscriber': topic_list(self.no_subscriber),
                  'waited_for': topic_list(self.waited)}
        if self.not_acknowledged is not None:
            values['not_acknowledged'] = topic_list(self.not_acknowledged)
        with self._diag_lock:
            self.reporter.set_state(OK if ok else WARN, text, **values)
        self._publish_diagnostics()
        if flush and self.ack_timeout > 0:
            from rclpy.duration import Duration
            poll_until_done(lambda: [] if self.diag_pub.wait_for_all_acked(
                Duration(seconds=0)) else [DIAGNOSTICS_TOPIC], min(self.ack_timeout, 1.0),
                self._stop)

    def _publish_diagnostics(self) -> None:
        with self._diag_lock:
            self.reporter.values['published'] = str(self.published)
            self.reporter.publish(self.get_clock().now().to_msg())

    def _play_once(self) -> None:
        t0_bag: Optional[int] = None
        t0_wall = time.monotonic()
        for m in self.reader.messages(self.pubs.keys()):
            if t0_bag is None:
                t0_bag = m.log_time
            due = t0_wall + (m.log_time - t0_bag) / 1e9 / self.rate
            wait = due - time.monotonic()
            if (wait > 0 and self._stop.wait(wait)) or self._stop.is_set():
                return
            if self.clock_pub is not None:
                self.clock_pub.publish(encode_clock(m.log_time))
            self.pubs[m.topic].publish(m.data)
            self.published += 1

    def done(self) -> bool:
        """True when the bag has been played (and not looping)."""
        return self._done

    def close(self) -> None:
        """Stop the playback thread and report."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._thread.join(timeout=5.0)
        print(f'[player] published {self.published} messages from {self.bag}', flush=True)
