"""ROS glue of the bag layer: the recorder and player nodes (the executables are thin).

:class:`RecorderNode` subscribes with serialized (``raw=True``) subscriptions and hands the
CDR bytes untouched to :class:`cdmp_ros.bag.BagWriter`; :class:`PlayerNode` verifies a whole
bag (every CRC) before it publishes anything, then publishes the stored bytes with the
original timing.  Parameters are declared with descriptors; topic remapping is the standard
``--ros-args -r from:=to``.
"""
import importlib
import threading
import time
from typing import Dict, List, Optional

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

from cdmp_ros.bag import BagError, BagReader, BagWriter
from cdmp_ros.bag.cdr import encode_clock
from cdmp_ros.bag.schemas import normalize_type
from cdmp_ros.ros.qos import (RECORDER_DEPTH, adapted_subscription_profile, playback_profile,
                              profile_to_dict)
from cdmp_ros.ros.realtime import check_priority
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


class PlayerNode(Node):
    """Replay a bag with its original timing.

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
    wait_for_subscribers : int
        Before playing, wait until every publisher has at least this many subscribers.
    wait_timeout : float
        Longest wait for those subscribers (s), then play anyway; and, after the last
        message, longest wait (all publishers together) for the reliable subscribers to
        acknowledge every sample.
    start_delay : float
        Seconds to wait before the first message (lets late subscribers match).
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
        self.wait_subs = _describe(self, 'wait_for_subscribers', 0,
                                   'subscribers each publisher waits for')
        self.wait_timeout = _describe(self, 'wait_timeout', 10.0, 'subscriber wait limit, '
                                      'and acknowledgement wait at the end (s)')
        self.start_delay = _describe(self, 'start_delay', 0.0, 'delay before playing (s)')
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
            self.clock_pub = self.create_publisher(Clock, '/clock', QoSProfile(depth=10))
        self.published = 0
        self._stop = threading.Event()
        self.get_logger().info(f'playing {self.bag}: {sorted(self.pubs)} at rate {self.rate}')
        self._thread = threading.Thread(target=self._run, name='player', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        """Playback thread: publishing needs no executor; shutdown is checked between
        messages and during every wait."""
        try:
            self._wait_for_subscribers()
            if self._stop.wait(self.start_delay):
                return
            while True:
                self._play_once()
                if not self.loop or self._stop.is_set():
                    break
            self._wait_acked()
        except BagError as exc:
            self.get_logger().error(f'playback stopped: {exc}')
            self.exit_code = 1
        except Exception as exc:  # context shut down under us: stop quietly
            if not self._stop.is_set():
                self.get_logger().error(f'playback failed: {exc!r}')
                self.exit_code = 1
        finally:
            self._done = True

    def _wait_acked(self) -> None:
        """Before the node ends: every reliable subscriber has acknowledged every sample
        (destroying a writer drops what a slow reader has not received yet), all publishers
        together waiting at most ``wait_timeout``."""
        from rclpy.duration import Duration
        deadline = time.monotonic() + self.wait_timeout
        for name, pub in self.pubs.items():
            # in 0.1 s slices: a stop request (close) is honoured within 0.1 s
            while not pub.wait_for_all_acked(Duration(seconds=0.1)):
                if self._stop.is_set():
                    return
                if time.monotonic() > deadline:
                    self.get_logger().warning(f'{name}: not every sample was acknowledged '
                                              f'within {self.wait_timeout} s')
                    break

    def _wait_for_subscribers(self) -> None:
        if self.wait_subs <= 0:
            return
        deadline = time.monotonic() + self.wait_timeout
        while time.monotonic() < deadline and not self._stop.is_set():
            if all(p.get_subscription_count() >= self.wait_subs for p in self.pubs.values()):
                return
            self._stop.wait(0.01)
        self.get_logger().warning('not every publisher got its subscribers; playing anyway')

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
