"""The adapter node: the slow path of the graph (design.md, Data flow). ROS glue around
:class:`~cdmp_ros.core.adaptation.session.AdaptationSession` (the request policy) and
:class:`~cdmp_ros.core.adaptation.jobs.SolveWorker` (the solver thread).

Subscribes ``primitive``, ``obstacles``, ``goal``, ``goal_point``, ``constraints``,
``joint_states`` and ``robot_description``; publishes ``adapted_primitive``,
``visualization`` and ``/diagnostics`` (types and QoS: docs/nodes.md; diagnostics keys:
docs/nodes.md).

- DMP / CDMP primitives: a goal (``goal``, or ``goal_point`` through the IK) gives at once an
  adapted primitive with the new goal and the same weights (``retarget_dmp_on_goal`` false:
  only ``goal_point``); obstacles are left to the streamer's coupling terms and only shown on
  ``visualization``.
- ProMPs: every change of the primitive, the obstacles, the goal or the constraint set submits
  an adaptation request to the solver thread (latest request wins). Only converged
  adaptations are published; otherwise the last good primitive stays latched. Warm starts
  and their cold refinements: :mod:`cdmp_ros.core.adaptation.warm`. A new ``primitive``
  clears the goal (a new task); obstacles and constraints are kept.
- A primitive is adapted within the tighter of its own limits and the robot's, per joint and
  bound (:func:`cdmp_ros.ros.adapter_inputs.primitive_limits`). The robot model is chosen once
  at start-up (:class:`cdmp_ros.ros.robot_model.RobotModelSelector`); a later
  ``robot_description`` is only compared with it.
- Every published primitive carries its provenance in ``metadata.adapter``
  (:class:`cdmp_ros.core.streaming.selection.Provenance`), so the streamer streams only the
  newest adaptation of its current primitive; an adaptation to ``obstacles`` or
  ``constraints`` continues the running motion, one to a new ``primitive`` or goal restarts it
  from the current state.

Every input passes :class:`cdmp_ros.ros.input_gate.InputGate` and the per-element validation.
``joint_states`` is polled, not subscribed with a callback: served by the executor, each
message of a 1 kHz robot would cost Python time taken from the solver thread. QoS: the
primitives and ``visualization`` are latched, so a restarted node or a late RViz gets the
current one.
"""
import json
import math
import sys
import time
from typing import Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from cdmp_ros.core.adaptation.requests import link_balls, rollout_path, solve_goal_point
from cdmp_ros.core.adaptation.config import AdaptRequestConfig, AdapterConfig
from cdmp_ros.core.adaptation.warm import WarmStarts
from cdmp_ros.core.config_fields import chain_tips
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.joint_limits import describe_mismatches
from cdmp_ros.core.primitive_io import primitive_from_dict
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from cdmp_ros.ros import qos
from cdmp_ros.ros.adapter_inputs import (goal_point_target, parse_constraints, parse_primitive,
                                         primitive_goal, primitive_limits)
from cdmp_ros.ros.adapter_viz import build_markers
from cdmp_ros.core.adaptation.jobs import Job, JobResult, SolveWorker, solve_job
from cdmp_ros.core.adaptation import session as policy
from cdmp_ros.core.adaptation.session import AdaptationSession, ResultAction
from cdmp_ros.ros.convert import JointStateMapper, ObstacleSet, stamp_to_ns
from cdmp_ros.ros.diagnostics import ERROR, OK, WARN, DiagnosticsReporter
from cdmp_ros.ros.input_gate import (EXTRA_JOINTS, SMALL_MESSAGE_BYTES, InputGate, joint_names,
                                     json_bytes, marker_count, message_bytes)
from cdmp_ros.ros.params import ConfigParameters
from cdmp_ros.ros.readiness_probe import ReadinessProbe, has_publishers, has_subscribers
from cdmp_ros.ros.robot_description import RobotDescriptionInput
from cdmp_ros.ros.robot_model import RobotModelSelector, load_collision_capsules

INPUT_TOPICS = ('primitive', 'obstacles', 'goal', 'goal_point', 'constraints')
#: [s] Python's GIL switch interval in the adapter process (default 5 ms): the executor takes a
#: new request, and the solver thread sees it, within about 1 ms while the other thread runs
#: Python code (a refinement, a callback); with the default, that wait adds tens of ms to
#: the latency from an obstacle to its solve.
SWITCH_INTERVAL = 0.001
#: The session's state levels (:mod:`cdmp_ros.core.adaptation.session`) as diagnostics levels.
LEVELS = {policy.OK: OK, policy.WARN: WARN, policy.ERROR: ERROR}
#: Diagnostics keys describing the last result (replaced as a whole by the next one).
RESULT_KEYS = ('outcome', 'solve_time_ms', 'solve_cpu_ms', 'trigger', 'request_id', 'stale',
               'kl', 'iterations', 'outer_iterations', 'backtracks', 'evaluations', 'start',
               'start_note', 'obstacles_used', 'obstacles_ignored', 'latency_ms')


class AdapterNode(Node):
    """See the module docstring; parameters mirror :class:`AdapterConfig` (top level) and
    :class:`AdaptRequestConfig` (``adaptation.*``)."""

    def __init__(self, **kwargs):
        super().__init__('adapter', **kwargs)
        self.params = ConfigParameters(self, [('', AdapterConfig),
                                              ('adaptation', AdaptRequestConfig)],
                                       on_change=self._on_params)
        cfg: AdapterConfig = self.params['']
        # the limits and kinematics of the robot: the robot_description parameter, else the
        # robot_description topic (robot_description_timeout), else urdf_path
        self.robot = RobotDescriptionInput(self, RobotModelSelector(
            cfg.urdf_path, cfg.joint_names, cfg.robot_description,
            cfg.robot_description_timeout, tip_link=chain_tips(cfg), tcp_offset=cfg.tcp_offset))
        model = self.robot.load(self.create_subscription(
            String, 'robot_description', self.robot.on_raw, qos.LATCHED, raw=True))
        self.urdf_path = model.source
        self.chain = model.chain
        self.model = model
        self._check_links(self.params['adaptation'])
        balls = self._link_balls(self.params['adaptation'])
        self.joint_names = list(cfg.joint_names)
        self.js_mapper = JointStateMapper(cfg.joint_names, allow_extra=True)
        self.goal_mapper = JointStateMapper(cfg.joint_names, allow_extra=False)
        self.obstacles = ObstacleSet(cfg.base_frame, cfg.max_obstacles, cfg.max_obstacle_size,
                                     cfg.max_obstacle_distance)
        self.session = AdaptationSession(self.joint_names)
        self.session.link_balls = balls
        self.q: Optional[np.ndarray] = None
        self.q_time = -math.inf
        self._obstacle_items = ()

        self.pub = self.create_publisher(String, 'adapted_primitive', qos.LATCHED)
        self.viz_pub = self.create_publisher(MarkerArray, 'visualization', qos.LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                              qos.COMMAND)
        self.reporter = DiagnosticsReporter(self, self.diag_pub)
        self.reporter.set_state(OK, 'waiting for a primitive', outcome='none',
                                limits_source=self.urdf_path, limit_mismatch='none')
        self.gate = InputGate(self, self.reporter, lambda: self.config)
        self.robot.attach(self.gate, self.reporter)
        self._set_rates(cfg)
        gate, n = self.gate, len(self.joint_names)
        json_size = json_bytes(lambda: self.config.max_json_bytes)
        gate.subscribe(String, 'primitive', self._on_primitive, qos.LATCHED,
                       size=json_size)
        gate.subscribe(MarkerArray, 'obstacles', self._on_obstacles, qos.COMMAND,
                       size=marker_count(lambda: self.config.max_obstacles))
        gate.subscribe(JointState, 'goal', self._on_goal, qos.COMMAND,
                       size=joint_names(lambda: n), stamped=True)
        gate.subscribe(PointStamped, 'goal_point', self._on_goal_point, qos.COMMAND,
                       size=message_bytes(lambda: SMALL_MESSAGE_BYTES), stamped=True)
        gate.subscribe(String, 'constraints', self._on_constraints, qos.COMMAND,
                       size=json_size)
        # read when a request is formed and at every diagnostics period, never per message
        self._poll_joint_states = gate.subscribe_polled(
            JointState, 'joint_states', self._on_joint_states, qos.SENSOR,
            size=joint_names(lambda: n + EXTRA_JOINTS), stamped=True)
        self._results_ready = self.create_guard_condition(self._on_results)
        # used by the solver thread only; its counters are read for diagnostics
        self.warm = WarmStarts()
        sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
        self.worker = SolveWorker(self._solve, self._results_ready.trigger)
        self.worker.start()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.readiness = ReadinessProbe(self, {
            'primitive': ('a primitive received', lambda: self.session.primitive is not None),
            'consumer': ('a subscriber on adapted_primitive',
                         has_subscribers(self, 'adapted_primitive')),
            'joint_states': ('a publisher on joint_states (the start of an adaptation)',
                             has_publishers(self, 'joint_states'))})
        self.diag_timer = self.create_timer(cfg.diagnostics_period, self._publish_diagnostics,
                                            clock=self._steady)
        self.get_logger().info(
            f'adapting primitives from {self.resolve_topic_name("primitive")} to '
            f'{self.resolve_topic_name("adapted_primitive")}; robot {self.urdf_path}')

    # -- setup -------------------------------------------------------------------------------
    def _check_links(self, acfg: AdaptRequestConfig) -> None:
        bad = [n for n in acfg.avoid_links if n not in self.chain.link_names]
        if bad:
            raise ValidationError(f'adaptation.avoid_links: {bad} are not links of the robot '
                                  f'{list(self.chain.link_names)}')

    def _link_balls(self, acfg: AdaptRequestConfig):
        """The balls covering the collision geometry of ``acfg.avoid_links`` (None without
        ``link_geometry``); ValidationError naming a link without collision geometry."""
        if not acfg.link_geometry or not acfg.avoid_links:
            return None
        return link_balls(load_collision_capsules(
            self.config.urdf_path, list(acfg.avoid_links), self.model.text or '', self.chain,
            what='adaptation.avoid_links (adaptation.link_geometry true)'))

    def _set_rates(self, cfg: AdapterConfig) -> None:
        self.gate.set_rates({t: cfg.max_input_rate for t in INPUT_TOPICS})

    def _on_params(self, configs) -> None:
        """Validate a parameter change as a whole (raises ValidationError to refuse it)."""
        cfg: AdapterConfig = configs['']
        acfg, old = configs['adaptation'], self.params['adaptation']
        self._check_links(acfg)
        if (acfg.avoid_links, acfg.link_geometry) != (old.avoid_links, old.link_geometry):
            self.session.link_balls = self._link_balls(acfg)  # reads the URDF and its meshes
        self.obstacles.max_obstacles = cfg.max_obstacles
        self.obstacles.max_size = cfg.max_obstacle_size
        self.obstacles.max_distance = cfg.max_obstacle_distance
        self._set_rates(cfg)
        if abs(cfg.diagnostics_period - self.diag_timer.timer_period_ns * 1e-9) > 1e-9:
            self.diag_timer.cancel()
            self.destroy_timer(self.diag_timer)
            self.diag_timer = self.create_timer(cfg.diagnostics_period,
                                                self._publish_diagnostics, clock=self._steady)

    @property
    def config(self) -> AdapterConfig:
        return self.params['']

    # -- subscriptions -----------------------------------------------------------------------
    def _on_joint_states(self, msg: JointState, received: float) -> None:
        arrays = self.gate.joint_arrays(self.js_mapper, msg, 'joint_states')
        if arrays is None:
            return
        q = arrays[0]
        lo, hi = self.chain.lower, self.chain.upper
        if not self.gate.within_limits('joint_states', q, lo, hi,
                                       self.config.joint_states_tolerance, self.joint_names):
            return
        self.q = np.clip(q, lo, hi)
        self.q_time = received

    def _current_q(self) -> Optional[np.ndarray]:
        """The newest accepted joint_states position (None before any); polls the reader."""
        self._poll_joint_states()
        return self.q

    def _on_primitive(self, msg: String) -> None:
        try:
            prim = parse_primitive(msg.data, self.joint_names, self.config.max_json_bytes)
            lo, hi, mismatches = primitive_limits(prim, self.chain)
        except CdmpError as exc:
            self.gate.reject('primitive', str(exc))
            return
        prim['limits'] = (lo, hi)
        self.session.set_primitive(prim)
        self.reporter.values['limit_mismatch'] = describe_mismatches(mismatches)
        self.get_logger().info(f'new {prim["kind"]} primitive ({len(msg.data)} bytes)')
        if mismatches:
            self.get_logger().warning(
                f'the primitive limits differ from the robot ({self.urdf_path}) on '
                f'{len(mismatches)} bounds, the tighter are used: '
                f'{describe_mismatches(mismatches)}')
        self._trigger('primitive', 0)

    def _on_constraints(self, msg: String) -> None:
        p = self.session.primitive
        try:
            doc = parse_constraints(msg.data, p['prim'] if p and p['kind'] == 'promp' else None,
                                    self.chain, self.config.max_json_bytes)
        except CdmpError as exc:
            self.gate.reject('constraints', str(exc))
            return
        self.session.set_constraints(doc)
        self.get_logger().info(f'constraint set with '
                               f'{len(doc["constraints"]) if doc else 0} constraints')
        self._trigger('constraints', 0)

    def _on_goal(self, msg: JointState) -> None:
        arrays = self.gate.joint_arrays(self.goal_mapper, msg, 'goal')
        if arrays is None:
            return
        self._set_goal('goal', arrays[0], None, stamp_to_ns(msg.header.stamp))

    def _on_goal_point(self, msg: PointStamped) -> None:
        cfg = self.config
        try:
            target = goal_point_target(msg, cfg.base_frame)
            res = solve_goal_point(self.chain, target, self._ik_seeds(), cfg.ik_tolerance,
                                   cfg.ik_max_iter, margin=cfg.goal_margin)
        except ValidationError as exc:
            self.gate.reject('goal_point', str(exc))
            return
        self._set_goal('goal_point', res.q, target, stamp_to_ns(msg.header.stamp))

    def _ik_seeds(self):
        """IK seeds: the current joint state, the primitive's goal, the middle of the limits."""
        g = primitive_goal(self.session.primitive)
        mid = 0.5 * (self.chain.lower + self.chain.upper)
        return [q for q in (self._current_q(), g, mid) if q is not None]

    def _set_goal(self, topic: str, g: np.ndarray, point, stamp_ns: int) -> None:
        clipped = self.session.set_goal(g, point, self.chain.lower, self.chain.upper,
                                        self.config.goal_margin)
        gc = self.session.goal_y
        if clipped:
            changes = ', '.join(f'{self.joint_names[j]} {g[j]:.4g} -> {gc[j]:.4g}'
                                for j in clipped)
            self.gate.reject(topic, f'{topic} outside the limits, clipped with the CDMP margin: '
                                    f'{changes}')
        self.get_logger().info(f'new goal from {topic}: {np.round(gc, 4).tolist()}',
                               throttle_duration_sec=1.0)
        self._trigger(topic, stamp_ns)

    def _on_obstacles(self, msg: MarkerArray) -> None:
        good, stamp_ns = self.gate.markers('obstacles', msg)
        self.gate.reject_all('obstacles', self.obstacles.apply(good, time.monotonic()))
        self._obstacles_changed('obstacles', stamp_ns)

    def _obstacles_changed(self, topic: str, stamp_ns: int) -> None:
        items = self.obstacles.snapshot.items
        if items == self._obstacle_items:
            return
        self._obstacle_items = items
        if self.session.is_promp:
            self._trigger(topic, stamp_ns)
        else:  # DMP / CDMP: the streamer's coupling handles obstacles
            self._publish_dmp_visualization()

    # -- requests ----------------------------------------------------------------------------
    def _trigger(self, topic: str, stamp_ns: int) -> None:
        cfg = self.config
        start = None
        if self.session.is_promp:
            q = self._current_q()
            start = q if time.monotonic() - self.q_time <= cfg.joint_states_timeout else None
        t = self.session.trigger(topic, stamp_ns, self.obstacles.snapshot.items, start,
                                 self.params['adaptation'], cfg,
                                 self.get_clock().now().nanoseconds, time.monotonic())
        if t.action == 'solve':
            self.session.replaced(self.worker.submit(t.job))
        elif t.action == 'retarget':
            self._retarget_dmp(topic, stamp_ns)
        else:
            self.reporter.set_state(OK, t.message)
            if t.action == 'wait' or t.retargeted is not None:
                self._publish_dmp_visualization(t.retargeted)

    def _solve(self, job: Job) -> JobResult:
        """Solve ``job`` (in the solver thread); a refinement gives way to any newer request."""
        worker = self.worker
        if job.refine_kl is None:
            return solve_job(job, self.chain, worker.stopping, self.warm)
        return solve_job(job, self.chain,
                         lambda: worker.stopping() or worker.has_pending(), self.warm)

    def _refine(self, res: JobResult) -> None:
        """A refinement of a published warm solve, if the session asks for one."""
        job = self.session.refinement(
            res, not (self.worker.busy or self.worker.has_pending()),
            self.get_clock().now().nanoseconds, time.monotonic())
        if job is not None:
            self.worker.submit(job)

    def _retarget_dmp(self, topic: str, stamp_ns: int = 0) -> None:
        """DMP / CDMP: publish the primitive with the new goal (same weights)."""
        d, clipped = self.session.retarget(topic, stamp_ns, self.config.goal_margin,
                                           self.get_clock().now().nanoseconds)
        if d is None:
            self._publish_dmp_visualization()
            return
        if clipped:
            self.gate.reject(topic, f'{topic} outside the primitive limits, clipped: '
                                    + ', '.join(self.joint_names[j] for j in clipped))
        self.pub.publish(String(data=json.dumps(d)))
        self._clear_result_values()
        self.reporter.set_state(OK, f'{self.session.primitive["kind"]} retargeted to the goal '
                                    f'from {topic}', outcome='retargeted', trigger=topic)
        self._publish_dmp_visualization(d)

    def _publish_dmp_visualization(self, d=None) -> None:
        """Obstacles and (with a DMP/CDMP primitive) its rollout from the current state."""
        path = None
        p = self.session.primitive
        if p is not None and p['kind'] != 'promp':
            try:
                prim = primitive_from_dict(d) if d is not None else p['prim']
                path = rollout_path(prim, p['perm'], self.chain, self._current_q(),
                                    self.config.path_points)
            except (CdmpError, ValueError) as exc:  # a primitive that cannot be rolled out
                self.get_logger().warning(f'visualization: {exc}', throttle_duration_sec=5.0)
        self._publish_markers(path, None)

    def _publish_markers(self, path, band) -> None:
        self.viz_pub.publish(build_markers(self.config.base_frame,
                                           self.get_clock().now().to_msg(), path, band,
                                           self.obstacles.snapshot.items,
                                           self.session.goal_point))

    # -- results -----------------------------------------------------------------------------
    def _on_results(self) -> None:
        for res in self.worker.take():
            self._handle_result(res)

    def _handle_result(self, res: JobResult) -> None:
        act: ResultAction = self.session.result(res, time.monotonic())
        for name, seconds in act.timings:
            self.reporter.timing(name, seconds)
        if act.level is not None:
            self._clear_result_values()
        if act.reject is not None:
            self.gate.reject(*act.reject)
        if act.publish is not None:
            self.pub.publish(String(data=act.publish))
            self._publish_markers(*act.markers)
        if act.level is not None:
            self.reporter.set_state(LEVELS[act.level], act.message, **act.values)
        if act.warning is not None:
            self.get_logger().warning(act.warning)
        if act.refine:
            self._refine(res)
        if act.report:
            self._publish_now()

    # -- diagnostics -------------------------------------------------------------------------
    def _clear_result_values(self) -> None:
        """Forget the key/values of the previous result (p.*, v.*, verification.*, kl, ...)."""
        self.reporter.values = {k: v for k, v in self.reporter.values.items()
                                if not (k.startswith(('p.', 'v.', 'verification.'))
                                        or k in RESULT_KEYS)}

    def _publish_now(self) -> None:
        counts = dict(self.warm.counts)   # (refinements: the node's own counters)
        starts = {f'starts_{k}': counts[k] for k in ('warm', 'predicted', 'continued', 'cold',
                                                     'warm_then_cold', 'cold_then_warm',
                                                     'over_guard')}
        self.reporter.set_state(self.reporter.level, self.reporter.message,
                                **self.worker.summary(), **self.session.counts, **starts,
                                **self.readiness.values(), **self.gate.values())
        self.reporter.publish(self.get_clock().now().to_msg())

    def _publish_diagnostics(self) -> None:
        if self.obstacles.expire(time.monotonic()):
            self._obstacles_changed('obstacles', 0)
        p, session = self.session.primitive, self.session
        self._poll_joint_states()
        age = time.monotonic() - self.q_time
        self.reporter.set_state(self.reporter.level, self.reporter.message,
                                primitive=p['kind'] if p else 'none',
                                robot_state=('none' if math.isinf(age) else 'fresh'
                                             if age <= self.config.joint_states_timeout
                                             else 'stale'),
                                obstacles=len(self.obstacles),
                                constraints=(len(session.constraint_doc['constraints'])
                                             if session.constraint_doc else 0),
                                goal=('none' if session.goal_y is None
                                      else np.round(session.goal_y, 4).tolist()))
        self._publish_now()

    def close(self) -> None:
        """Stop the solver thread; a running solve is cancelled within one evaluation of the
        Lagrangian, but a problem being built or a sampled verification runs to its end (under
        a second of CPU; the join allows 10 s for a loaded machine)."""
        self.worker.stop()
        self.worker.join(timeout=10.0)
        if self.worker.is_alive():  # stuck: a daemon thread, left behind
            print('[adapter] solver thread still busy at shutdown', flush=True)
