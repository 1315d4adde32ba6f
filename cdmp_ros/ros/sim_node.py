"""The sim node: ROS glue around :class:`cdmp_ros.sim.live.LiveSim` (pybullet, DIRECT mode).

Subscribes ``joint_reference``, ``obstacles`` and, with ``robot`` panda,
``robot_description``; publishes ``joint_states`` and ``ee_pose`` at ``publish_rate`` of
simulated time, ``/diagnostics`` and, with ``publish_clock``, ``/clock``; services
``~/snapshot`` and ``~/reset`` (topics, types and QoS: docs/nodes.md; diagnostics keys:
docs/nodes.md). ``joint_states`` is kept 50 deep (:data:`~cdmp_ros.ros.qos.SIM_STATE`) so the
burst of one late tick reaches a reliable subscriber whole.

Stepping: one steady-clock timer. With ``real_time`` it steps the physics up to the wall clock
(at most ``max_catch_up`` s; beyond that the simulation slips); without it, each tick steps
for a short slice of CPU, so subscriptions and services are served between slices. Each
publish period of simulated time gets its own message.

Every input passes :class:`cdmp_ros.ros.input_gate.InputGate` and the per-element validation.
A reference outside the joint limits, or faster than the URDF velocity limit, is clipped;
whatever it receives, the simulated joints never pass their limits (the end stops of
:class:`~cdmp_ros.sim.live.LiveSim`). Every accepted reference also passes a
:class:`cdmp_ros.core.reflex.ReflexMonitor`, as a Franka Panda's reflex: ``reflex: count``
counts an error and applies the reference, ``reflex: stop`` halts the robot at its measured
position and refuses every reference until ``~/reset``.

Joint limits (``robot`` panda): the tighter of the pybullet model's and those of the robot
model chosen once at start-up (:class:`cdmp_ros.ros.robot_model.RobotModelSelector`, as in the
streamer and the adapter). The pybullet body itself stays the model of ``robot``: a
robot_description refers to its meshes by ``package://`` URIs that only a ROS installation
resolves, so only the limits come from it. For ``dual_panda`` and ``planar4`` the limits are
those of the URDF files pybullet loads.
"""
import math
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.joint_limits import LimitMismatch
from cdmp_ros.core.reflex import REFUSED, STOP, VIOLATION, ReflexMonitor
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from cdmp_ros.ros import qos
from cdmp_ros.ros.convert import JointStateMapper, ObstacleSet, stamp_to_ns
from cdmp_ros.ros.diagnostics import ERROR, OK, WARN, DiagnosticsReporter
from cdmp_ros.ros.input_gate import InputGate, joint_names, marker_count
from cdmp_ros.ros.limits_params import robot_limits
from cdmp_ros.ros.params import ConfigParameters
from cdmp_ros.ros.readiness_probe import ReadinessProbe, has_publishers
from cdmp_ros.common.realtime import process_thread_ids, set_threads_fifo
from cdmp_ros.ros.robot_description import RobotDescriptionInput
from cdmp_ros.ros.robot_model import RobotModelSelector
from cdmp_ros.sim.live import limit_clip, LiveSim
from cdmp_ros.sim.node_config import SimConfig
from cdmp_ros.sim.robot_specs import PANDA_JOINTS


#: Timer period and stepping slice [s] when ``real_time`` is false.
FAST_PERIOD, FAST_SLICE = 0.002, 0.0015


def describe_sim_mismatch(m: LimitMismatch) -> str:
    """One differing bound: the pybullet model's value, the robot's, the one used."""
    return (f'{m.joint} {m.bound}: pybullet {m.primitive:.6g}, robot {m.robot:.6g} -> '
            f'{m.used:.6g}')


class SimNode(Node):
    """See the module docstring; parameters mirror :class:`SimConfig`."""

    def __init__(self, **kwargs):
        super().__init__('sim', **kwargs)
        self.params = ConfigParameters(self, [('', SimConfig)], on_change=self._on_params)
        cfg: SimConfig = self.params['']
        urdf_limits, self.robot = None, None
        if cfg.robot == 'panda':  # the limits of the robot that runs (see the module docstring):
            # the robot_description parameter, else the robot_description topic
            # (robot_description_timeout), else urdf_path
            self.robot = RobotDescriptionInput(self, RobotModelSelector(
                cfg.urdf_path, PANDA_JOINTS, cfg.robot_description,
                cfg.robot_description_timeout))
            model = self.robot.load(self.create_subscription(
                String, 'robot_description', self.robot.on_raw, qos.LATCHED, raw=True))
            chain = model.chain
            urdf_limits = (chain.lower, chain.upper, chain.velocity_limits)
        self.sim = LiveSim(cfg, urdf_limits)
        self.limits_source = (model.source if urdf_limits is not None
                              else ', '.join(r.spec.urdf_path for r in self.sim.robots))
        try:
            # the limits the reflex checks: the simulated robot's position and velocity limits
            # merged with the joint_limits.* parameters, as in the streamer
            self.limits = robot_limits(self, self.sim.joint_names, self.sim.lower,
                                       self.sim.upper, self.sim.velocity_limits,
                                       self.limits_source)
            self.reflex = ReflexMonitor(self.limits, cfg.reflex_tolerance, cfg.reflex)
            self._declare_initial_positions()
            self._setup(cfg)
        except Exception:
            self.sim.close()
            raise
        self.scheduling = self._go_realtime(cfg.realtime_priority)

    def _go_realtime(self, priority: int) -> str:
        """SCHED_FIFO ``priority`` for every thread of the process (``realtime_priority``);
        returns the scheduling for the diagnostics. A refusal is logged, never raised."""
        if priority == 0:
            return 'normal'
        n, problems = set_threads_fifo(priority, process_thread_ids())
        if problems:
            self.get_logger().warning(f'realtime_priority: {problems}; {n} threads lifted')
            return f'SCHED_FIFO {priority} refused: {problems}' if n == 0 else \
                f'SCHED_FIFO {priority} on {n} threads ({problems})'
        self.get_logger().info(f'SCHED_FIFO priority {priority} on all {n} threads')
        return f'SCHED_FIFO {priority}'

    def _declare_initial_positions(self) -> None:
        desc = ParameterDescriptor(
            name='initial_positions', type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            dynamic_typing=True,
            description=('Initial joint positions [rad or m] in joint_states order (pose of '
                         f'~/reset), inside the limits; {self.sim.n_dofs} values for '
                         f'{self.sim.config.robot}. A change applies at the next ~/reset.'))
        try:
            p = self.declare_parameter('initial_positions', self.sim.initial_positions.tolist(),
                                       desc)
        except (ParameterException, TypeError, ValueError) as exc:
            raise ValidationError(f'parameter initial_positions: {exc}') from None
        self.sim.set_initial_positions(self._positions(p.value))
        self.sim.reset()
        self.add_on_set_parameters_callback(self._on_set_initial)
        self.add_post_set_parameters_callback(self._post_set_initial)

    def _positions(self, value) -> np.ndarray:
        if isinstance(value, (str, bytes)) or not hasattr(value, '__len__') or any(
                isinstance(v, (bool, str)) for v in value):
            raise ValidationError(f'initial_positions: expected a list of numbers, got '
                                  f'{value!r}')
        return self.sim.check_positions('initial_positions',
                                        np.asarray(value, dtype=np.float64))

    def _on_set_initial(self, params) -> SetParametersResult:
        for p in params:
            if p.name == 'initial_positions':
                try:
                    self._positions(p.value)
                except ValidationError as exc:
                    self.get_logger().warning(f'parameter change refused: {exc}')
                    return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _post_set_initial(self, params) -> None:
        for p in params:
            if p.name == 'initial_positions':
                self.sim.set_initial_positions(self._positions(p.value))

    def _setup(self, cfg: SimConfig) -> None:
        sim = self.sim
        self.mapper = JointStateMapper(sim.joint_names, allow_extra=False)
        self.obstacles = ObstacleSet(sim.base_frame, cfg.max_obstacles, cfg.max_obstacle_size,
                                     cfg.max_obstacle_distance)
        self.js_pub = self.create_publisher(JointState, 'joint_states', qos.SIM_STATE)
        self.pose_pub = self.create_publisher(PoseStamped, 'ee_pose', qos.SIM_STATE)
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                              qos.COMMAND)
        self.clock_pub = None
        if cfg.publish_clock:
            from rosgraph_msgs.msg import Clock as ClockMsg
            self._clock_msg = ClockMsg()
            self.clock_pub = self.create_publisher(ClockMsg, '/clock', qos.CLOCK)
        self.reporter = DiagnosticsReporter(self, self.diag_pub)
        mismatch = '; '.join(describe_sim_mismatch(m) for m in sim.limit_mismatches) or 'none'
        self.reporter.set_state(OK, 'starting', limits_source=self.limits_source,
                                limit_mismatch=mismatch, limits=self.limits.describe(),
                                limits_sources='; '.join(self.limits.sources))
        if sim.limit_mismatches:
            self.get_logger().warning(f'the limits of {self.limits_source} differ from the '
                                      f'pybullet model on {len(sim.limit_mismatches)} bounds, '
                                      f'the tighter are used: {mismatch}')
        self.gate = InputGate(self, self.reporter, lambda: self.config, now_ns=self._now_ns)
        if self.robot is not None:
            self.robot.attach(self.gate, self.reporter)
        self._set_rates(cfg)
        self.gate.subscribe(JointState, 'joint_reference', self._on_reference,
                            qos.REFERENCE, size=joint_names(lambda: len(sim.joint_names)),
                            stamped=True)
        self.gate.subscribe(MarkerArray, 'obstacles', self._on_obstacles, qos.COMMAND,
                            size=marker_count(lambda: self.config.max_obstacles))
        self.create_service(Trigger, '~/snapshot', self._on_snapshot)
        self.create_service(Trigger, '~/reset', self._on_reset)

        self._js = JointState()
        self._js.name = list(sim.joint_names)
        self._pose = PoseStamped()
        self._pose.header.frame_id = sim.base_frame
        self.counts = {'references_received': 0, 'joint_states_published': 0,
                       'slipped_steps': 0, 'snapshots': 0, 'resets': 0}
        self._ref_time = None   # steady time of the last accepted reference
        self._holding = False
        self._reflex_log = [-math.inf, 0]  # last log time of a reflex error, errors since
        self._n_published = 0
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._anchor()
        self._rtf = (time.monotonic(), sim.t, float('nan'))
        self.timer = None
        self._make_timer(cfg)
        self.readiness = ReadinessProbe(self, {'references': (
            'a publisher on joint_reference', has_publishers(self, 'joint_reference'))})
        self.diag_timer = self.create_timer(cfg.diagnostics_period, self._publish_diagnostics,
                                            clock=self._steady)
        self.get_logger().info(
            f'simulating {cfg.robot} ({sim.n_dofs} joints, {cfg.control} control) at '
            f'{cfg.physics_rate:g} Hz, {"real time" if cfg.real_time else "as fast as possible"}'
            f'; joint_states at {cfg.publish_rate:g} Hz on '
            f'{self.resolve_topic_name("joint_states")}; base frame {sim.base_frame}')

    # -- configuration -----------------------------------------------------------------------
    @property
    def config(self) -> SimConfig:
        return self.params['']

    def _set_rates(self, cfg: SimConfig) -> None:
        self.gate.set_rates({'joint_reference': cfg.max_reference_rate,
                             'obstacles': cfg.max_input_rate})

    def _make_timer(self, cfg: SimConfig) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.destroy_timer(self.timer)
        period = (1.0 / cfg.publish_rate) if cfg.real_time else FAST_PERIOD
        self.timer = self.create_timer(period, self._tick, clock=self._steady)

    def _anchor(self) -> None:
        """Tie the current simulated step to now (wall, steady and ROS clocks)."""
        self._wall0 = time.monotonic()
        self._k0 = self.sim.n_steps
        self._ros0_ns = self.get_clock().now().nanoseconds

    def _on_params(self, configs) -> None:
        """Validate a parameter change as a whole (raises ValidationError to refuse it)."""
        old, cfg = self.config, configs['']
        self.sim.set_control(cfg)  # raises on bad gains
        self.reflex.set_mode(cfg.reflex)
        self.reflex.set_tolerance(cfg.reflex_tolerance)
        self.obstacles.max_obstacles = cfg.max_obstacles
        self.obstacles.max_size = cfg.max_obstacle_size
        self.obstacles.max_distance = cfg.max_obstacle_distance
        self._set_rates(cfg)
        if cfg.obstacles_collide != old.obstacles_collide:
            self._sync_obstacles()
        if cfg.real_time != old.real_time:
            self._make_timer(cfg)
            self._anchor()
        if cfg.diagnostics_period != old.diagnostics_period:
            self.diag_timer.cancel()
            self.destroy_timer(self.diag_timer)
            self.diag_timer = self.create_timer(cfg.diagnostics_period,
                                                self._publish_diagnostics, clock=self._steady)

    # -- inputs ------------------------------------------------------------------------------
    def _now_ns(self) -> int:
        """Now in the time base of stamps (simulated time with publish_clock)."""
        if self.clock_pub is not None:
            return int(round(self.sim.n_steps * 1e9 / self.config.physics_rate))
        return self.get_clock().now().nanoseconds

    def _on_reference(self, msg: JointState) -> None:
        topic = 'joint_reference'
        arrays = self.gate.joint_arrays(self.mapper, msg, topic)
        if arrays is None:
            return
        q, qd = arrays
        if not self._reflex_check(msg, q):
            return
        sim = self.sim
        names = sim.joint_names
        q, bad = limit_clip(q, sim.lower, sim.upper)
        if bad:
            j = bad[0]
            self.gate.reject(topic, f'joint_reference.position of {names[j]!r} is outside '
                                    f'the limits [{sim.lower[j]}, {sim.upper[j]}], clipped to '
                                    f'{q[j]:.6g} ({len(bad)} joint(s))')
        if qd is not None:
            vmax = sim.velocity_limits
            qd, bad = limit_clip(qd, -vmax, vmax)
            if bad:
                j = bad[0]
                self.gate.reject(topic, f'joint_reference.velocity of {names[j]!r} exceeds '
                                        f'the velocity limit {vmax[j]}, clipped '
                                        f'({len(bad)} joint(s))')
        sim.set_reference(q, qd)
        self.counts['references_received'] += 1
        self._ref_time = time.monotonic()
        self._holding = False

    def _reflex_check(self, msg: JointState, q: np.ndarray) -> bool:
        """The reflex check of one reference (see the module docstring); False: refused."""
        stamp = stamp_to_ns(msg.header.stamp) or self._now_ns()  # unstamped: arrival time
        status, violations = self.reflex.update(stamp, q.tolist())
        if status == REFUSED:
            return False
        log = self.get_logger()
        if status == STOP:
            self.sim.halt()
            log.error(f'reflex: joint_reference breaks the limits ({self.reflex.stop_reason}): '
                      'the robot halts and refuses references until ~/reset')
            self._publish_diagnostics()
            return False
        if status == VIOLATION:
            now = time.monotonic()
            entry = self._reflex_log
            entry[1] += 1
            if now - entry[0] >= 1.0:
                extra = f' ({entry[1]} references since the last report)' if entry[1] > 1 \
                    else ''
                log.warning(f'reflex error: joint_reference breaks the limits '
                            f'({self.reflex.last_error}){extra}; applied (reflex: count)')
                entry[0], entry[1] = now, 0
        return True

    def _on_obstacles(self, msg: MarkerArray) -> None:
        good, _ = self.gate.markers('obstacles', msg)
        self.gate.reject_all('obstacles', self.obstacles.apply(good, time.monotonic()))
        self._sync_obstacles()

    def _sync_obstacles(self) -> None:
        snap = self.obstacles.snapshot
        try:
            self.sim.sync_obstacles({f'{ns}/{i}': item for (ns, i), item in
                                     zip(snap.keys, snap.items)})
        except Exception as exc:  # noqa: BLE001 -- pybullet refused a shape: keep running
            self.gate.reject('obstacles', f'cannot be simulated: {exc}')
        self.sim.monitor()

    # -- services ----------------------------------------------------------------------------
    def _on_snapshot(self, request, response):
        try:
            response.message = self.sim.snapshot(self.config.snapshot_path)
            response.success = True
            self.counts['snapshots'] += 1
            self.get_logger().info(f'snapshot written to {response.message}')
        except Exception as exc:  # noqa: BLE001 -- a failed snapshot must not end the node
            response.success = False
            response.message = f'snapshot failed: {exc}'
            self.get_logger().error(response.message)
        return response

    def _on_reset(self, request, response):
        stopped = self.reflex.stopped
        self.sim.reset()
        self.reflex.reset()
        self._ref_time = None
        self._holding = False
        self.counts['resets'] += 1
        response.success = True
        response.message = ('reset to initial_positions '
                            f'{np.round(self.sim.initial_positions, 6).tolist()}')
        if stopped:
            response.message += '; reflex cleared, references accepted again'
        self.get_logger().info(response.message)
        return response

    # -- stepping ----------------------------------------------------------------------------
    def _tick(self) -> None:
        t_start = time.perf_counter()
        now = time.monotonic()
        cfg = self.config
        if (self._ref_time is not None and not self._holding and cfg.reference_timeout > 0
                and not self.reflex.stopped and now - self._ref_time > cfg.reference_timeout):
            self.sim.hold()
            self._holding = True
            self.get_logger().warning(f'joint_reference stale (none for '
                                      f'{cfg.reference_timeout:g} s): holding the last '
                                      'position')
        if cfg.real_time:
            steps = int((now - self._wall0) * cfg.physics_rate) + self._k0 - self.sim.n_steps
            cap = max(1, int(cfg.max_catch_up * cfg.physics_rate))
            if steps > cap:  # too late: the simulation slips behind the wall clock
                self.counts['slipped_steps'] += steps - cap
                self._k0 -= steps - cap
                steps = cap
            self._advance(steps)
        else:
            end = t_start + FAST_SLICE
            while time.perf_counter() < end:
                self._advance(cfg.publish_decimation)
        self.reporter.timing('tick', time.perf_counter() - t_start)

    def _advance(self, steps: int) -> None:
        """Step ``steps`` physics steps, publishing at every publish slot."""
        sim = self.sim
        dec = self.config.publish_decimation
        while steps > 0:
            n = min(steps, dec - sim.n_steps % dec)
            sim.step(n)
            steps -= n
            if sim.n_steps % dec == 0:
                self._publish_state()

    def _publish_state(self) -> None:
        sim, cfg = self.sim, self.config
        if self.clock_pub is not None:
            stamp_ns = self._now_ns()
        elif cfg.real_time:
            stamp_ns = self._ros0_ns + int((sim.n_steps - self._k0) * 1e9 / cfg.physics_rate)
        else:
            stamp_ns = self.get_clock().now().nanoseconds
        sec, nsec = divmod(stamp_ns, 1_000_000_000)
        q, qd, effort = sim.state()
        js = self._js
        js.header.stamp.sec, js.header.stamp.nanosec = sec, nsec
        js.position, js.velocity, js.effort = q.tolist(), qd.tolist(), effort.tolist()
        self.js_pub.publish(js)
        pos, orn = sim.ee_pose()
        ps = self._pose
        ps.header.stamp.sec, ps.header.stamp.nanosec = sec, nsec
        p, o = ps.pose.position, ps.pose.orientation
        p.x, p.y, p.z = float(pos[0]), float(pos[1]), float(pos[2])
        o.x, o.y, o.z, o.w = float(orn[0]), float(orn[1]), float(orn[2]), float(orn[3])
        self.pose_pub.publish(ps)
        if self.clock_pub is not None:
            c = self._clock_msg.clock
            c.sec, c.nanosec = sec, nsec
            self.clock_pub.publish(self._clock_msg)
        self._n_published += 1
        self.counts['joint_states_published'] = self._n_published
        if self._n_published % cfg.monitor_decimation == 0 and (len(self.obstacles)
                                                                or len(sim.robots) > 1):
            if len(self.obstacles) and self.obstacles.expire(time.monotonic()):
                self._sync_obstacles()
            else:
                sim.monitor()

    # -- diagnostics -------------------------------------------------------------------------
    def _state(self):
        cfg, st = self.config, self.sim.stats
        if self.reflex.stopped:
            level, state = ERROR, 'reflex'
            text = (f'reflex: halted, references refused until ~/reset '
                    f'({self.reflex.stop_reason})')
        elif self._ref_time is None:
            level, text, state = OK, 'waiting: holding initial_positions', 'waiting'
        elif self._holding:
            level, state = WARN, 'holding'
            text = f'holding: joint_reference stale (none for {cfg.reference_timeout:g} s)'
        else:
            level, text, state = OK, 'tracking joint_reference', 'tracking'
        if st.contacts:
            level = max(level, WARN)
            text += '; contact ' + ', '.join(f'{link}-{obs}' for link, obs, _ in
                                             st.contact_pairs[:3])
        return level, text, state

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        sim = self.sim
        t0, s0, rtf = self._rtf
        if now - t0 > 0.0:
            rtf = (sim.t - s0) / (now - t0)
        self._rtf = (now, sim.t, rtf)
        level, text, state = self._state()
        self.reporter.set_state(
            level, text, state=state, robot=self.config.robot, control=self.config.control,
            obstacles=len(self.obstacles), sim_time=f'{sim.t:.3f}', scheduling=self.scheduling,
            real_time_factor=f'{rtf:.3f}' if math.isfinite(rtf) else 'nan',
            **sim.stats.as_values(), **self.counts, **self.reflex.as_values(),
            **self.readiness.values(), **self.gate.values())
        self.reporter.publish(self.get_clock().now().to_msg())

    def close(self) -> None:
        self.sim.close()
