"""The streamer node: ROS glue around :class:`cdmp_ros.core.streaming.streamer.ReferenceStreamer`.

Publishes ``joint_reference`` at ``rate`` and, with ``controller_output``, the same references
for a ros2_control controller in its joint order; subscribes ``primitive`` /
``adapted_primitive``, ``goal``, ``joint_states``, ``obstacles`` and ``robot_description``;
reports on ``/diagnostics`` (topics, types and QoS: docs/nodes.md; diagnostics keys:
docs/nodes.md). Every input passes :class:`cdmp_ros.ros.input_gate.InputGate` and the
per-element validation.

Primitive messages are parsed and prepared in a worker thread (the latest one wins), so a
large primitive never delays a tick; the tick only switches the prepared stepper in, as
:class:`cdmp_ros.core.streaming.selection.AdaptationSelector` decides (only the newest
adaptation of the current ``primitive``, in any arrival order).

The tick runs in a dedicated thread (``tick_thread``, default) that sleeps to the absolute
deadlines of the steady clock (:class:`cdmp_ros.core.streaming.schedule.TickSchedule`,
:class:`cdmp_ros.common.realtime.DeadlineSleeper`), optionally under SCHED_FIFO
(``realtime_priority``) and pinned (``tick_cpu``), so a slow callback of the executor delays
a tick by the GIL and one short lock at most, not by a whole callback queue. One lock
(``_lock``) serialises the tick and the callbacks that change the streamer's state.
Start-up objects are frozen out of the garbage collector so a full collection does not stall
the tick. With ``obstacle_wakeup`` an obstacle message wakes the tick thread to publish the
next slot of the fixed grid at once. ``tick_thread: false`` falls back to an executor timer.

The robot model (limits, kinematics of the coupling terms) is chosen once at start-up
(:class:`cdmp_ros.ros.robot_model.RobotModelSelector`) and never swapped under a running
stream: a later ``robot_description`` is only compared with it.
"""
import gc
import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import MarkerArray

from cdmp_ros.core.coupling.braking import influence_warning, primitive_braking_distance
from cdmp_ros.core.config_fields import chain_tips
from cdmp_ros.core.errors import CdmpError
from cdmp_ros.core.joint_limits import describe_mismatches
from cdmp_ros.core.coupling.obstacle import ObstacleCoupling
from cdmp_ros.core.streaming.latency import LatencyRing
from cdmp_ros.core.streaming.primitives import prepare_primitive
from cdmp_ros.core.streaming.selection import AdaptationSelector, read_provenance
from cdmp_ros.core.streaming.config import DEFAULT_CONTROLLER_TOPICS
from cdmp_ros.core.streaming.schedule import ClockOffset, TickSchedule, clock_offset_ns
from cdmp_ros.core.streaming.streamer import (PARAMETER_SECTIONS, ReferenceStreamer,
                                              StreamerConfig, StreamFlags, StreamState,
                                              coupling_of)
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from cdmp_ros.ros import qos
from cdmp_ros.ros.convert import (ForwardCommandWriter, JointStateMapper, JointStateWriter,
                                  JointTrajectoryWriter, ObstacleSet)
from cdmp_ros.ros.diagnostics import OK, WARN, DiagnosticsReporter
from cdmp_ros.ros.input_gate import (EXTRA_JOINTS, InputGate, joint_names, json_bytes,
                                     marker_count)
from cdmp_ros.common.latest_worker import LatestWorker
from cdmp_ros.ros.limits_params import robot_limits
from cdmp_ros.ros.params import ConfigParameters
from cdmp_ros.ros.readiness_probe import ReadinessProbe, has_publishers, has_subscribers
from cdmp_ros.common.realtime import DeadlineSleeper, configure_thread, report_scheduling
from cdmp_ros.ros.robot_description import RobotDescriptionInput
from cdmp_ros.ros.robot_model import RobotModelSelector

PRIMITIVE_TOPICS = ('primitive', 'adapted_primitive')
#: GIL switch interval of the streamer process, as a fraction of the tick period: a thread
#: holding the GIL (executor callback, primitive worker) hands it to the waiting tick thread
#: after at most this long (CPython's default is 5 ms, five periods at 1 kHz).
SWITCH_INTERVAL_PERIODS = 0.1


class StreamerNode(Node):
    """See the module docstring; parameters mirror :class:`StreamerConfig` and the coupling
    configs (``coupling.*``, ``damping.*``, ``repeller.*``, ``box_field.*``,
    ``board_field.*``)."""

    def __init__(self, **kwargs):
        super().__init__('streamer', **kwargs)
        self.params = ConfigParameters(self, list(PARAMETER_SECTIONS),
                                       on_change=self._on_params)
        cfg: StreamerConfig = self.params['']
        # the limits, kinematics and capsules of the robot: the robot_description parameter,
        # else the robot_description topic (robot_description_timeout), else urdf_path
        self.robot = RobotDescriptionInput(self, RobotModelSelector(
            cfg.urdf_path, cfg.joint_names, cfg.robot_description,
            cfg.robot_description_timeout, cfg.coupling_capsule_links, chain_tips(cfg),
            cfg.tcp_offset))
        model = self.robot.load(self.create_subscription(
            String, 'robot_description', self.robot.on_raw, qos.LATCHED, raw=True))
        self.urdf_path = model.source
        self.chain = model.chain
        self.capsules = list(model.capsules)
        self.coupling = self._make_coupling(self.params.configs)
        # position and velocity from the URDF, tighter-of-two with joint_limits.* parameters
        self.limits = robot_limits(self, cfg.joint_names, self.chain.lower, self.chain.upper,
                                   self.chain.velocity_limits, self.urdf_path)
        self.streamer = ReferenceStreamer(
            self.chain.lower, self.chain.upper, cfg,
            coupling=self.coupling if cfg.coupling_enabled else None, limits=self.limits)
        self.js_mapper = JointStateMapper(cfg.joint_names, allow_extra=True)
        self.goal_mapper = JointStateMapper(cfg.joint_names, allow_extra=False)
        self.obstacles = ObstacleSet(cfg.base_frame, cfg.max_obstacles, cfg.max_obstacle_size,
                                     cfg.max_obstacle_distance)

        self.pub = self.create_publisher(JointState, 'joint_reference', qos.REFERENCE)
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                              qos.COMMAND)
        self.reporter = DiagnosticsReporter(self, self.diag_pub)
        self.reporter.values['limits_source'] = self.urdf_path
        self.reporter.values['limits'] = self.limits.describe()
        self.reporter.values['limits_sources'] = '; '.join(self.limits.sources)
        # the reporter's own lock: building and publishing diagnostics (milliseconds on a
        # loaded machine) must not hold the tick's lock; the tick's timings are ring-buffer
        # writes without a lock
        self._report_lock = threading.Lock()
        self.gate = InputGate(self, self.reporter, lambda: self.config, lock=self._report_lock)
        self.robot.attach(self.gate, self.reporter)
        self._set_rates(cfg)
        self.writer = JointStateWriter(JointState(), cfg.joint_names, cfg.base_frame)
        self.controller_pub, self.controller_writer = self._controller_output(cfg)
        n = len(cfg.joint_names)
        cfg_now = lambda: self.config  # noqa: E731
        for topic in PRIMITIVE_TOPICS:
            self.gate.subscribe(String, topic, lambda m, t=topic: self._on_primitive(t, m),
                                qos.LATCHED,
                                size=json_bytes(lambda: cfg_now().max_json_bytes))
        self.gate.subscribe(JointState, 'goal', self._on_goal, qos.COMMAND,
                            size=joint_names(lambda: n), stamped=True)
        self.gate.subscribe(JointState, 'joint_states', self._on_joint_states,
                            qos.SENSOR, size=joint_names(lambda: n + EXTRA_JOINTS),
                            stamped=True)
        self.gate.subscribe(MarkerArray, 'obstacles', self._on_obstacles, qos.COMMAND,
                            size=marker_count(lambda: cfg_now().max_obstacles))

        # primitive messages are parsed and prepared off the executor and tick threads
        # primitive and adapted_primitive in separate slots: a restarted streamer receives both
        # latched messages at once and needs both (core/streaming/selection.py)
        self.worker = LatestWorker(self._prepare, _prepare_failed, name='primitive-worker',
                                   key=lambda request: request[0])
        self.worker.start()
        self.counts = {'ticks': 0, 'published': 0, 'clamped': 0, 'coupling_rejected': 0,
                       'coupled': 0, 'coupling_bounded': 0, 'output_limited': 0}
        self.active_text = None
        # which primitive is streamed (the deterministic-restart rule) and the latency from
        # an adaptation's trigger stamp to the first reference computed from it
        self.selection = AdaptationSelector(cfg.stream_unadapted)
        self._adapt_latency = LatencyRing('adaptation_latency')
        self._adapt_pending = None  # the switched-in adaptation awaiting its first reference
        self._adapt_first = {}
        self._timed_trigger_ns = 0  # trigger stamp of the last adaptation timed
        # obstacle message stamp -> publication of the first reference computed with it
        self._obstacle_latency = LatencyRing('obstacle_latency', 4096, (50, 99))
        self._latency_pending_ns = 0
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._dt = cfg.dt
        self._lock = threading.RLock()  # the tick reports rejections while holding it
        self._tick_errors = 0
        # deadlines, catch-up and stamps: slot j is stamped stamp0 + j / rate exactly (ROS
        # clock = steady clock + an offset measured at start and with every diagnostics message)
        self.schedule = TickSchedule(cfg.rate, time.monotonic(), *self._clock_offset(25))
        self._pub_slot0 = 0
        self.timer = None
        self.tick_thread = None
        self.realtime_status = None
        self._stopping = threading.Event()
        self._sleeper = DeadlineSleeper(spin=cfg.tick_spin)
        # Everything built so far lives as long as the node: moved out of the collector's
        # generations, a full collection no longer walks the objects of rclpy, numpy, scipy and
        # the node, which would stall the tick.
        gc.collect()
        gc.freeze()
        if cfg.tick_thread:
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_PERIODS * cfg.dt))
            self._configured = threading.Event()
            self.tick_thread = threading.Thread(target=self._tick_loop, name='streamer-tick',
                                                daemon=True)
            self.tick_thread.start()
            self._configured.wait(5.0)
            self._report_scheduling(cfg)
        else:
            self.timer = self.create_timer(cfg.dt, self._locked_tick, clock=self._steady)
        self.readiness = ReadinessProbe(self, self._readiness_conditions(cfg))
        self.diag_timer = self.create_timer(cfg.diagnostics_period, self._publish_diagnostics,
                                            clock=self._steady)
        self.get_logger().info(
            f'streaming {len(cfg.joint_names)} joints at {cfg.rate:g} Hz on '
            f'{self.resolve_topic_name("joint_reference")}; robot {self.urdf_path}')

    # -- setup -------------------------------------------------------------------------------
    def _readiness_conditions(self, cfg: StreamerConfig):
        """Ready: a primitive in force, a consumer of the references and, closed loop, a
        publisher of joint_states."""
        consumers = ('joint_reference',) + ((self.controller_pub.topic_name,)
                                            if self.controller_pub is not None else ())
        out = {'primitive': ('a primitive received and in force',
                             lambda: self.streamer.active is not None),
               'consumer': (f'a subscriber on {" or ".join(consumers)}',
                            has_subscribers(self, *consumers))}
        if cfg.joint_states_timeout > 0.0:
            out['joint_states'] = ('a publisher on joint_states (closed loop)',
                                   has_publishers(self, 'joint_states'))
        return out

    def _make_coupling(self, configs) -> ObstacleCoupling:
        return coupling_of(self.chain, configs, self.capsules)

    def _controller_output(self, cfg: StreamerConfig):
        """The publisher and writer of ``controller_output`` (None, None for 'none'); the
        reorder index into the controller's joint order is computed here, once."""
        joints = cfg.controller_joint_names
        # the topic from a parameter: listed as <controller_topic> in the table of docs/nodes.md
        self.controller_topic = (cfg.controller_topic
                                 or DEFAULT_CONTROLLER_TOPICS.get(cfg.controller_output, ''))
        if cfg.controller_output == 'forward_command':
            writer = ForwardCommandWriter(Float64MultiArray(), cfg.joint_names, joints)
            pub = self.create_publisher(Float64MultiArray, self.controller_topic,
                                        qos.COMMAND)
        elif cfg.controller_output == 'joint_trajectory':
            writer = JointTrajectoryWriter(JointTrajectory(), JointTrajectoryPoint(),
                                           cfg.joint_names, joints, cfg.dt, cfg.base_frame)
            pub = self.create_publisher(JointTrajectory, self.controller_topic,
                                        qos.COMMAND)
        else:
            return None, None
        self.get_logger().info(f'{cfg.controller_output} controller output on '
                               f'{pub.topic_name}, joints {list(joints)}')
        return pub, writer

    def _set_rates(self, cfg: StreamerConfig) -> None:
        rates = {t: cfg.max_input_rate for t in PRIMITIVE_TOPICS + ('goal', 'obstacles')}
        self.gate.set_rates(dict(rates, joint_states=cfg.max_joint_states_rate))

    def _on_params(self, configs) -> None:
        """Validate a parameter change as a whole (raises ValidationError to refuse it)."""
        cfg: StreamerConfig = configs['']
        coupling = self._make_coupling(configs)  # raises on bad link names / gains
        with self._lock:
            self._apply_params(cfg, coupling)
        if abs(cfg.diagnostics_period - self.diag_timer.timer_period_ns * 1e-9) > 1e-9:
            self.diag_timer.cancel()
            self.destroy_timer(self.diag_timer)
            self.diag_timer = self.create_timer(cfg.diagnostics_period,
                                                self._publish_diagnostics, clock=self._steady)

    def _apply_params(self, cfg: StreamerConfig, coupling: ObstacleCoupling) -> None:
        self.streamer.set_config(cfg)
        self.coupling = coupling
        self.streamer.coupling = coupling if cfg.coupling_enabled else None
        self.obstacles.max_obstacles = cfg.max_obstacles
        self.obstacles.max_size = cfg.max_obstacle_size
        self.obstacles.max_distance = cfg.max_obstacle_distance
        self._set_rates(cfg)

    @property
    def config(self) -> StreamerConfig:
        """The configuration in force (the streamer's: applied under the tick's lock)."""
        return self.streamer.config

    # -- inputs ------------------------------------------------------------------------------
    def _on_joint_states(self, msg: JointState) -> None:
        arrays = self.gate.joint_arrays(self.js_mapper, msg, 'joint_states')
        if arrays is None:
            return
        q = arrays[0]
        if not self.gate.within_limits('joint_states', q, self.streamer.lower,
                                       self.streamer.upper, 0.05,  # measured noise tolerance
                                       self.streamer.joint_names):
            return
        with self._lock:
            self.streamer.note_joint_states(q, time.monotonic())

    def _on_goal(self, msg: JointState) -> None:
        arrays = self.gate.joint_arrays(self.goal_mapper, msg, 'goal')
        if arrays is None:
            return
        g = arrays[0]
        with self._lock:
            clipped = self.streamer.set_goal(g)
        if clipped:
            gc = self.streamer.goal_override
            names = self.streamer.joint_names
            changes = ', '.join(f'{names[j]} {g[j]:.4g} -> {gc[j]:.4g}' for j in clipped)
            self.gate.reject('goal', f'goal.position outside the limits, clipped with the '
                                     f'CDMP margin: {changes}')
        self.get_logger().info(f'new goal {np.round(self.streamer.goal_override, 4).tolist()}',
                               throttle_duration_sec=1.0)

    def _on_obstacles(self, msg: MarkerArray) -> None:
        now = time.monotonic()
        good, newest = self.gate.markers('obstacles', msg)
        with self._lock:
            errors = self.obstacles.apply(good, now)
            self.streamer.obstacles = self.obstacles.snapshot.items
            # the latency is counted from the publisher's stamp (same host clock), or from the
            # arrival when the markers are unstamped
            self._latency_pending_ns = newest or self.get_clock().now().nanoseconds
        if self.tick_thread is not None and self.config.obstacle_wakeup:
            self._sleeper.wake()
        self.gate.reject_all('obstacles', errors)

    def _on_primitive(self, topic: str, msg: String) -> None:
        replaced = self.worker.submit((topic, msg.data))
        if replaced is not None:  # dropped unparsed: counted, so that nothing goes unreported
            old = replaced[0]
            self.gate.reject(old, f'{old}: superseded by a newer {topic} before it was parsed',
                             'superseded')

    def _prepare(self, request):
        """Worker thread: parse and prepare ``(topic, text)`` (no ROS calls, no shared
        state); returns ``(topic, prepared, None)``."""
        topic, text = request
        chain = self.chain
        prepared = prepare_primitive(text, self.streamer.joint_names, self._dt, chain.lower,
                                     chain.upper, chain.velocity_limits, source=topic)
        if topic != 'primitive':
            prepared.provenance = read_provenance(prepared.metadata)
        lim = self.streamer.limits
        prepared.braking_m = primitive_braking_distance(prepared.prim, chain,
                                                        lim.acceleration, lim.jerk)
        return topic, prepared, None

    # -- the tick ----------------------------------------------------------------------------
    def _tick_loop(self) -> None:
        """The tick thread: sleep to the next slot's deadline (or an obstacle wake-up), tick."""
        cfg = self.config
        st = configure_thread(cfg.realtime_priority,
                              (cfg.tick_cpu,) if cfg.tick_cpu >= 0 else ())
        if st.realtime:
            self._sleeper.spin = 0.0  # never spin under SCHED_FIFO
        self.realtime_status = st
        self._configured.set()
        sched, sleeper, lock, stopping = self.schedule, self._sleeper, self._lock, \
            self._stopping
        clock = time.monotonic
        timing = self.reporter.timing
        while not stopping.is_set():
            woken = sleeper.sleep_until(sched.deadline())
            if stopping.is_set():
                return
            if woken and sched.is_ahead(clock()):
                continue  # already one slot ahead: wait for the schedule
            try:
                with lock:
                    late = sched.woke(clock(), woken)
                    if not woken:  # deadline -> tick running (sleep, GIL and lock)
                        timing('tick_wake_late', late)
                    self._tick()
            except Exception as exc:  # noqa: BLE001 -- the stream must go on
                self._tick_errors += 1
                if not stopping.is_set() and (self._tick_errors == 1
                                              or self._tick_errors % 1000 == 0):
                    self.get_logger().error(f'tick failed ({self._tick_errors} so far): '
                                            f'{exc!r}')

    def _report_scheduling(self, cfg: StreamerConfig) -> None:
        """Log the tick thread's scheduling; lift the other threads (``realtime_threads``).

        Runs in the constructor's thread (the executor thread), so threads it creates later
        (executor, middleware) inherit its policy."""
        report_scheduling(self.get_logger(), self.realtime_status, cfg.realtime_threads,
                          self.tick_thread, self.worker, self._sleeper.spin)

    def _locked_tick(self) -> None:
        with self._lock:
            self._tick()

    def _tick(self) -> None:
        t_start = time.perf_counter()
        now = time.monotonic()
        for topic, prepared, error in self.worker.take():
            if prepared is None:
                self.gate.reject(topic, error)
            else:
                self._switch_in(topic, prepared, now)
        first, steps, skipped = self.schedule.advance(now, self.config.max_catch_up)
        st = self.streamer
        if st.state is not StreamState.WAITING:
            # every integrated slot is published with its own stamp (a late tick catches up);
            # the output stage also runs through the skipped slots (stamps stay consistent)
            self._pub_slot0 = first
            flags = st.advance(steps, now, self._publish_step, skipped)
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
            if flags & StreamFlags.COUPLING_BOUNDED:
                c['coupling_bounded'] += 1
            if flags & StreamFlags.LIMITED:
                c['output_limited'] += 1
        self.reporter.timing('tick', time.perf_counter() - t_start)

    def _switch_in(self, topic: str, prepared, now: float) -> None:
        """Tick thread: switch in what :class:`AdaptationSelector` selects."""
        dec = self.selection.offer(topic, prepared)
        # one call site per severity: rclpy refuses a call site whose severity changes
        for counter, message in dec.ignored:
            if counter in ('adapted_held', 'primitive_awaiting_adaptation'):
                self.get_logger().info(message)
            else:
                self.get_logger().warning(message)
        chosen = dec.activate
        if chosen is None:
            return
        text = self.streamer.activate(chosen, now, dec.continues)
        advice = influence_warning(chosen.braking_m,
                                   self.params['repeller'].influence_distance)
        if advice:
            self.get_logger().warning(advice)
        if dec.provenance is not None:
            text += f' (generation {dec.provenance.generation}, {dec.provenance.trigger_topic})'
        text += '; ' + '; '.join(chosen.notes) if chosen.notes else ''
        if chosen.limit_mismatches:
            self.get_logger().warning(text)
        else:
            self.get_logger().info(text)
        prov = dec.provenance
        # timed only when triggered while this streamer runs (not a latched adaptation from
        # before a restart), and once per trigger: the adapter's refinement of a warm solve
        # answers the same obstacle message again
        started = self.schedule.stamp0_ns
        self._adapt_pending = ((chosen, prov) if prov and prov.trigger_stamp_ns > started
                               and prov.trigger_stamp_ns != self._timed_trigger_ns else None)

    def _note_adapted_reference(self, stamp: int) -> None:
        """The first reference computed from a switched-in adaptation: trigger -> stamp."""
        prepared, prov = self._adapt_pending
        if self.streamer.active is not prepared:
            self._adapt_pending = None  # replaced before it produced a reference
            return
        if self.streamer.state is not StreamState.RUNNING:
            return  # stored while the inputs are stale: its first reference comes later
        self._adapt_pending = None
        self._timed_trigger_ns = prov.trigger_stamp_ns
        self._adapt_latency.add((stamp - prov.trigger_stamp_ns) * 1e-6)
        self._adapt_first = {'adapted_reference_stamp_ns': stamp,
                             'adapted_trigger_stamp_ns': prov.trigger_stamp_ns,
                             'adapted_reference_generation': prov.generation}

    def _publish_step(self, i: int) -> None:
        st = self.streamer
        stamp = self.schedule.stamp_ns(self._pub_slot0 + i)
        if self._adapt_pending is not None:
            self._note_adapted_reference(stamp)
        self.pub.publish(self.writer.fill(stamp, st.out_y, st.out_yd))
        if self.controller_pub is not None:  # the same reference, the controller's order
            self.controller_pub.publish(self.controller_writer.fill(stamp, st.out_y, st.out_yd,
                                                                    st.out_ydd))
        self.counts['published'] += 1
        if self._latency_pending_ns:
            lat = (self.get_clock().now().nanoseconds - self._latency_pending_ns) * 1e-6
            self._latency_pending_ns = 0
            self._obstacle_latency.add(lat)

    def _clock_offset(self, readings: int = 5) -> ClockOffset:
        """ROS clock - steady clock [ns], with its uncertainty."""
        clock = self.get_clock()
        return clock_offset_ns(lambda: clock.now().nanoseconds, readings=readings)

    def _publish_diagnostics(self) -> None:
        # follow a step of the ROS clock (NTP step, sim time); otherwise the grid stays exact
        self.schedule.anchor(self._clock_offset())
        st = self.streamer
        with self._lock:
            self.obstacles.expire(time.monotonic())
            self.streamer.obstacles = self.obstacles.snapshot.items
            latency = self._obstacle_latency.values()
            counts = dict(self.counts, **self.schedule.counts,
                          output_clamped=st.stage.clamped)
            state, reason, active = st.state, st.reason, st.active
            n_obstacles = len(self.obstacles)
            # the largest coupling asked for beyond the bound in this period (0: none)
            peak, st.coupling_peak = st.coupling_peak, 0.0
            adaptation = dict(self.selection.values(), **self._adapt_latency.values(),
                              **self._adapt_first)
        level = OK if state is StreamState.RUNNING else WARN
        # the active primitive's limits against the robot's (the tighter ones are used)
        mismatches = active.limit_mismatches if active is not None else ()
        if mismatches:
            reason += (f'; the primitive limits differ from the robot ({self.urdf_path}) on '
                       f'{len(mismatches)} bounds: the tighter are used')
        extra_limits = {'limit_mismatch': describe_mismatches(mismatches),
                        'braking_distance_m': f'{active.braking_m if active else 0.0:.4f}',
                        'repeller_influence_distance_m':
                            f'{self.params["repeller"].influence_distance:.4f}'}
        extra = {'tick_errors': self._tick_errors} if self._tick_errors else {}
        if self.controller_pub is not None:
            extra['controller_output'] = (f'{self.config.controller_output} on '
                                          f'{self.controller_pub.topic_name}')
        if self.realtime_status is not None:
            extra['tick_scheduling'] = (f'SCHED_FIFO {self.realtime_status.priority}'
                                        if self.realtime_status.realtime else 'normal')
        with self._report_lock:
            self.reporter.set_state(
                level, f'{state.value}: {reason}', state=state.value,
                primitive=(f'{active.kind} from {active.source}' if active else 'none'),
                obstacles=n_obstacles,
                min_obstacle_distance_m=f'{self.streamer.min_distance:.4f}',
                coupling_peak_rad_s2=f'{peak:.4g}',
                rate_hz=f'{self.config.rate:g}', **latency, **adaptation,
                **extra,
                **extra_limits, **self.readiness.values(),
                **counts, **self.gate.values())
            self.reporter.publish(self.get_clock().now().to_msg())

    def close(self) -> None:
        """Stop the tick thread (before the node is destroyed) and the primitive worker."""
        self._stopping.set()
        self._sleeper.wake()
        if self.tick_thread is not None:
            self.tick_thread.join(timeout=2.0)
        self.worker.stop()
        self.worker.join(timeout=2.0)


def _prepare_failed(request, exc: Exception):
    """``(topic, None, reason)`` of a primitive message that cannot be prepared."""
    topic = request[0]
    if isinstance(exc, CdmpError):
        return topic, None, str(exc)
    return topic, None, f'{topic}: cannot be prepared: {exc!r}'
