"""The streamer node: ROS glue around :class:`cdmp_ros.core.streaming.ReferenceStreamer`.

Publishes ``joint_reference`` (sensor_msgs/JointState) from a steady-clock timer at ``rate``;
subscribes ``primitive`` / ``adapted_primitive`` (JSON, latched), ``goal``, ``joint_states``
and ``obstacles``; reports on ``diagnostics``. Primitive messages are parsed and prepared in a
worker thread (the latest one wins), so a large primitive never delays a tick; the tick only
switches the prepared stepper in. Every input is validated (:mod:`cdmp_ros.ros.convert`),
rate-limited against flooding, and each rejection is logged and counted on ``diagnostics``.
"""
import os
import threading
import time
from typing import Optional, Tuple

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from cdmp_ros.core.coupling import DampingConfig
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.fields import ConstantField, RepellerField
from cdmp_ros.core.kinematics import panda_chain
from cdmp_ros.core.obstacle_coupling import CouplingConfig, ObstacleCoupling
from cdmp_ros.core.stream_primitives import prepare_primitive
from cdmp_ros.core.streaming import (CouplingSource, RateLimiter, ReferenceStreamer,
                                     StreamerConfig, StreamFlags, StreamState)
from cdmp_ros.ros import qos_profiles
from cdmp_ros.ros.convert import (JointStateMapper, JointStateWriter, ObstacleSet,
                                  check_stamp)
from cdmp_ros.ros.diagnostics import OK, WARN, DiagnosticsReporter
from cdmp_ros.ros.params import ConfigParameters

PRIMITIVE_TOPICS = ('primitive', 'adapted_primitive')
#: Obstacle-to-reference latencies kept for the diagnostics percentiles (a ring).
LATENCY_SAMPLES = 4096


def default_urdf_path() -> str:
    """The Panda URDF shipped with pybullet_data."""
    import pybullet_data
    return os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf')


class _PrimitiveWorker(threading.Thread):
    """Prepares the latest primitive message off the executor thread."""

    def __init__(self, prepare):
        super().__init__(name='primitive-worker', daemon=True)
        self._prepare = prepare
        self._cv = threading.Condition()
        self._pending: Optional[Tuple[str, str]] = None
        self._results = []
        self._stopping = False

    def submit(self, topic: str, text: str) -> None:
        with self._cv:
            self._pending = (topic, text)  # coalesce: only the newest counts
            self._cv.notify()

    def take(self):
        """Results since the last call: list of (topic, prepared or None, error or None)."""
        if not self._results:
            return ()
        with self._cv:
            out, self._results = self._results, []
        return out

    def stop(self) -> None:
        with self._cv:
            self._stopping = True
            self._cv.notify()

    def run(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                topic, text = self._pending
                self._pending = None
            try:
                res = (topic, self._prepare(topic, text), None)
            except CdmpError as exc:
                res = (topic, None, str(exc))
            except Exception as exc:  # noqa: BLE001 -- a worker must survive any payload
                res = (topic, None, f'{topic}: cannot be prepared: {exc!r}')
            with self._cv:
                self._results.append(res)


class StreamerNode(Node):
    """See the module docstring; parameters mirror :class:`StreamerConfig` and the coupling
    configs (``coupling.*``, ``damping.*``, ``repeller.*``, ``box_field.*``)."""

    def __init__(self, **kwargs):
        super().__init__('streamer', **kwargs)
        self.params = ConfigParameters(
            self, [('', StreamerConfig), ('coupling', CouplingConfig),
                   ('damping', DampingConfig), ('repeller', RepellerField),
                   ('box_field', ConstantField)], on_change=self._on_params)
        cfg: StreamerConfig = self.params['']
        self.urdf_path = cfg.urdf_path or default_urdf_path()
        self.chain = self._load_chain(cfg)
        self.coupling_source = CouplingSource(self._make_coupling(self.params.configs))
        self.streamer = ReferenceStreamer(
            self.chain.lower, self.chain.upper, cfg,
            coupling=self.coupling_source if cfg.coupling_enabled else None)
        self.js_mapper = JointStateMapper(cfg.joint_names, allow_extra=True)
        self.goal_mapper = JointStateMapper(cfg.joint_names, allow_extra=False)
        self.obstacles = ObstacleSet(cfg.base_frame, cfg.max_obstacles, cfg.max_obstacle_size,
                                     cfg.max_obstacle_distance)
        self._limiters = {}
        self._make_limiters(cfg)

        self.pub = self.create_publisher(JointState, 'joint_reference', qos_profiles.REFERENCE)
        self.diag_pub = self.create_publisher(DiagnosticArray, 'diagnostics',
                                              qos_profiles.COMMAND)
        self.reporter = DiagnosticsReporter(self, self.diag_pub, 'streamer')
        self.writer = JointStateWriter(JointState(), cfg.joint_names, cfg.base_frame)
        for topic in PRIMITIVE_TOPICS:
            self.create_subscription(String, topic, lambda m, t=topic: self._on_primitive(t, m),
                                     qos_profiles.LATCHED)
        self.create_subscription(JointState, 'goal', self._on_goal, qos_profiles.COMMAND)
        self.create_subscription(JointState, 'joint_states', self._on_joint_states,
                                 qos_profiles.SENSOR)
        self.create_subscription(MarkerArray, 'obstacles', self._on_obstacles,
                                 qos_profiles.COMMAND)

        self.worker = _PrimitiveWorker(self._prepare)
        self.worker.start()
        self.counts = {'ticks': 0, 'published': 0, 'missed_ticks': 0, 'clamped': 0,
                       'coupling_rejected': 0, 'coupled': 0}
        self.active_text = None
        # obstacle message stamp -> publication of the first reference computed with it
        self._latency_ms = np.zeros(LATENCY_SAMPLES)
        self._latency_n = 0
        self._latency_pending_ns = 0
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._dt = cfg.dt
        self._t0 = time.monotonic()
        self._k = 0
        self.timer = self.create_timer(cfg.dt, self._tick, clock=self._steady)
        self.diag_timer = self.create_timer(cfg.diagnostics_period, self._publish_diagnostics,
                                            clock=self._steady)
        self.get_logger().info(
            f'streaming {len(cfg.joint_names)} joints at {cfg.rate:g} Hz on '
            f'{self.resolve_topic_name("joint_reference")}; robot {self.urdf_path}')

    # -- setup -------------------------------------------------------------------------------
    def _load_chain(self, cfg: StreamerConfig):
        """The Panda chain of ``urdf_path`` (limits, velocity limits, kinematics)."""
        try:
            chain = panda_chain(self.urdf_path)
        except (OSError, CdmpError) as exc:
            raise ValidationError(f'urdf_path: cannot load a Panda from {self.urdf_path!r}: '
                                  f'{exc}') from None
        if list(chain.joint_names) != list(cfg.joint_names):
            raise ValidationError(f'joint_names: expected the joints of {self.urdf_path!r} '
                                  f'{chain.joint_names}, got {list(cfg.joint_names)}')
        return chain

    def _make_coupling(self, configs) -> ObstacleCoupling:
        cc = configs['coupling']
        cc = CouplingConfig(damping=configs['damping'], link_radius=cc.link_radius,
                            end_effector=cc.end_effector)
        return ObstacleCoupling(self.chain, configs[''].coupling_links,
                                sphere_field=configs['repeller'],
                                box_field=configs['box_field'], config=cc)

    def _make_limiters(self, cfg: StreamerConfig) -> None:
        for topic in PRIMITIVE_TOPICS + ('goal', 'obstacles'):
            self._limiters[topic] = RateLimiter(cfg.max_input_rate)
        self._limiters['joint_states'] = RateLimiter(cfg.max_joint_states_rate)

    def _on_params(self, configs) -> None:
        """Validate a parameter change as a whole (raises ValidationError to refuse it)."""
        cfg: StreamerConfig = configs['']
        coupling = self._make_coupling(configs)  # raises on bad link names / gains
        self.streamer.set_config(cfg)
        self.coupling_source.coupling = coupling
        self.streamer.coupling = self.coupling_source if cfg.coupling_enabled else None
        self.obstacles.max_obstacles = cfg.max_obstacles
        self.obstacles.max_size = cfg.max_obstacle_size
        self.obstacles.max_distance = cfg.max_obstacle_distance
        self._make_limiters(cfg)
        if abs(cfg.diagnostics_period - self.diag_timer.timer_period_ns * 1e-9) > 1e-9:
            self.diag_timer.cancel()
            self.destroy_timer(self.diag_timer)
            self.diag_timer = self.create_timer(cfg.diagnostics_period,
                                                self._publish_diagnostics, clock=self._steady)

    @property
    def config(self) -> StreamerConfig:
        return self.params['']

    # -- inputs ------------------------------------------------------------------------------
    def _admit(self, topic: str, now: float, stamps=()) -> bool:
        """Flooding and stamp checks shared by the subscriptions."""
        if not self._limiters[topic].allow(now):
            lim = self._limiters[topic]
            if lim.dropped == 1 or lim.dropped % 100 == 0:
                self.reporter.reject(topic, f'flooding: more than {lim.rate:g} messages/s, '
                                            f'{lim.dropped} dropped so far')
            return False
        cfg = self.config
        if stamps:
            now_ns = self.get_clock().now().nanoseconds
            try:
                for name, stamp in stamps:
                    check_stamp(name, stamp, now_ns, cfg.max_stamp_age, cfg.max_stamp_lead,
                                cfg.accept_unstamped)
            except ValidationError as exc:
                self._reject(topic, str(exc))
                return False
        return True

    def _reject(self, topic: str, reason: str) -> None:
        self.reporter.reject(topic, reason)
        self.reporter.publish_if_due(self.get_clock().now().to_msg())

    def _on_joint_states(self, msg: JointState) -> None:
        now = time.monotonic()
        if not self._admit('joint_states', now, [('joint_states.header.stamp',
                                                  msg.header.stamp)]):
            return
        try:
            q, _ = self.js_mapper.to_arrays(msg, 'joint_states')
        except ValidationError as exc:
            self._reject('joint_states', str(exc))
            return
        lo, hi = self.streamer.lower, self.streamer.upper
        if np.any(q < lo - 0.05) or np.any(q > hi + 0.05):  # measured noise tolerance
            j = int(np.flatnonzero((q < lo - 0.05) | (q > hi + 0.05))[0])
            self._reject('joint_states', f'joint_states.position of '
                                         f'{self.streamer.joint_names[j]!r}: {q[j]:.4g} is '
                                         f'outside the limits [{lo[j]}, {hi[j]}]')
            return
        self.streamer.note_joint_states(q, now)

    def _on_goal(self, msg: JointState) -> None:
        now = time.monotonic()
        if not self._admit('goal', now, [('goal.header.stamp', msg.header.stamp)]):
            return
        try:
            g, _ = self.goal_mapper.to_arrays(msg, 'goal')
        except ValidationError as exc:
            self._reject('goal', str(exc))
            return
        clipped = self.streamer.set_goal(g)
        if clipped:
            gc = self.streamer.goal_override
            names = self.streamer.joint_names
            changes = ', '.join(f'{names[j]} {g[j]:.4g} -> {gc[j]:.4g}' for j in clipped)
            self._reject('goal', f'goal.position outside the limits, clipped with the CDMP '
                                 f'margin: {changes}')
        self.get_logger().info(f'new goal {np.round(self.streamer.goal_override, 4).tolist()}',
                               throttle_duration_sec=1.0)

    def _on_obstacles(self, msg: MarkerArray) -> None:
        now = time.monotonic()
        if not self._admit('obstacles', now):
            return
        good = []
        newest = 0
        for i, m in enumerate(msg.markers):
            newest = max(newest, m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
            if m.action == 3:  # DELETEALL needs no stamp
                good.append(m)
                continue
            if self._admit_stamp('obstacles', f'obstacles.markers[{i}].header.stamp',
                                 m.header.stamp):
                good.append(m)
        for exc in self.obstacles.apply(good, now):
            self._reject('obstacles', str(exc))
        self.coupling_source.obstacles = self.obstacles.snapshot.items
        # the latency is counted from the publisher's stamp (same host clock), or from the
        # arrival when the markers are unstamped
        self._latency_pending_ns = newest or self.get_clock().now().nanoseconds

    def _admit_stamp(self, topic, name, stamp) -> bool:
        cfg = self.config
        try:
            check_stamp(name, stamp, self.get_clock().now().nanoseconds, cfg.max_stamp_age,
                        cfg.max_stamp_lead, cfg.accept_unstamped)
        except ValidationError as exc:
            self._reject(topic, str(exc))
            return False
        return True

    def _on_primitive(self, topic: str, msg: String) -> None:
        if not self._admit(topic, time.monotonic()):
            return
        self.worker.submit(topic, msg.data)

    def _prepare(self, topic: str, text: str):
        """Worker thread: parse and prepare (no ROS calls, no shared state)."""
        chain = self.chain
        return prepare_primitive(text, self.streamer.joint_names, self._dt, chain.lower,
                                 chain.upper, chain.velocity_limits, source=topic)

    # -- the tick ----------------------------------------------------------------------------
    def _tick(self) -> None:
        t_start = time.perf_counter()
        now = time.monotonic()
        for topic, prepared, error in self.worker.take():
            if prepared is None:
                self._reject(topic, error)
            else:
                text = self.streamer.activate(prepared, now)
                self.get_logger().info(text + ('; ' + '; '.join(prepared.notes)
                                               if prepared.notes else ''))
        dt = self._dt
        k = int((now - self._t0) / dt)  # the slot that began most recently
        steps = k - self._k
        if steps < 1:
            steps, k = 1, self._k + 1
        cap = self.config.max_catch_up
        if steps > cap:  # too late: skip the oldest slots (they are reported as missed)
            self.counts['missed_ticks'] += steps - cap
            steps = cap
        self._k = k
        st = self.streamer
        if st.state is not StreamState.WAITING:
            # every integrated slot is published with its own stamp (a late tick catches up)
            self._pub_base = (self.get_clock().now().nanoseconds
                              - int((now - (self._t0 + (k - steps + 1) * dt)) * 1e9))
            flags = st.advance(steps, now, self._publish_step)
        else:
            flags = st.advance(steps, now)
        c = self.counts
        c['ticks'] += 1
        if flags:
            if flags & StreamFlags.CLAMPED:
                c['clamped'] += 1
            if flags & StreamFlags.COUPLING_REJECTED:
                c['coupling_rejected'] += 1
            if flags & StreamFlags.COUPLED:
                c['coupled'] += 1
        self.reporter.timing('tick', time.perf_counter() - t_start)

    def _publish_step(self, i: int) -> None:
        st = self.streamer
        self.pub.publish(self.writer.fill(self._pub_base + int(i * self._dt * 1e9), st.y, st.yd))
        self.counts['published'] += 1
        if self._latency_pending_ns:
            lat = (self.get_clock().now().nanoseconds - self._latency_pending_ns) * 1e-6
            self._latency_pending_ns = 0
            self._latency_ms[self._latency_n % LATENCY_SAMPLES] = lat
            self._latency_n += 1

    def _publish_diagnostics(self) -> None:
        st = self.streamer
        self.obstacles.expire(time.monotonic())
        self.coupling_source.obstacles = self.obstacles.snapshot.items
        level = OK if st.state is StreamState.RUNNING else WARN
        active = st.active
        self.reporter.set_state(
            level, f'{st.state.value}: {st.reason}', state=st.state.value,
            primitive=(f'{active.kind} from {active.source}' if active else 'none'),
            obstacles=len(self.obstacles),
            min_obstacle_distance_m=f'{self.coupling_source.min_distance:.4f}',
            rate_hz=f'{self.config.rate:g}', **self._latency_values(), **self.counts)
        self.reporter.publish(self.get_clock().now().to_msg())

    def _latency_values(self) -> dict:
        """Obstacle message stamp -> first joint_reference published with it, over the last
        :data:`LATENCY_SAMPLES` obstacle messages (ms)."""
        n = min(self._latency_n, LATENCY_SAMPLES)
        if n == 0:
            return {'obstacle_latency_n': 0}
        p50, p99, top = np.percentile(self._latency_ms[:n], [50.0, 99.0, 100.0])
        return {'obstacle_latency_n': self._latency_n,
                'obstacle_latency_ms_p50': f'{p50:.3f}', 'obstacle_latency_ms_p99': f'{p99:.3f}',
                'obstacle_latency_ms_max': f'{top:.3f}'}

    def close(self) -> None:
        self.worker.stop()
        self.worker.join(timeout=2.0)
