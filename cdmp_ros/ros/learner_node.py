"""The learner node: fits DMP / CDMP / ProMP primitives from demonstrations and improves them.

- Demonstrations come from bags (``demonstration_bags``, topic ``demonstration_topic``) and
  from the ``demonstration`` topic (sensor_msgs/JointState), segmented as described in
  :mod:`cdmp_ros.core.demonstrations` (a gap of ``demonstration_gap`` seconds, or an empty
  JointState as end marker). Every sample passes :class:`cdmp_ros.ros.input_gate.InputGate`
  (rate limit, then more names than joints rejected before deserialisation) and is validated
  (names mapped in any order, NaN/inf, lengths, unknown/missing/duplicate joints, stamps,
  non-monotonic time, limits); every rejection is logged and counted on ``/diagnostics``; bad
  bags are reported the same way.
- ``primitive`` (std_msgs/String JSON, transient-local): published at start (fit from the
  bags when ``fit_on_start``), after ``~/refit`` and after ``~/improve``.
- Services (std_srvs/Trigger): ``~/refit`` (bags + topic demonstrations so far), ``~/save``
  (writes ``primitive_path``, returns the absolute path), ``~/improve`` (PI2 in a worker
  thread, :mod:`cdmp_ros.ros.learner_improve`; progress on ``/diagnostics``; a second call
  while one runs is refused).
- Readiness (:mod:`cdmp_ros.ros.readiness_probe`): ready when ``primitive`` has a subscriber
  and, with ``fit_on_start``, the primitive was published.

Parameters mirror :class:`~cdmp_ros.core.learning.LearnerConfig` (top level),
:class:`~cdmp_ros.core.dmp.dmp.DmpConfig` (``dmp.*``), :class:`~cdmp_ros.core.learning.
PrompLearnConfig` (``promp.*``), :class:`~cdmp_ros.core.dmp.improve.ImproveConfig`
(``improve.*``) and :class:`~cdmp_ros.core.dmp.improve.CostConfig` (``cost.*``), plus the
read-only ``limits.lower`` / ``limits.upper`` (empty: the limits of the robot).

Joint limits: the robot's come from ``robot_description`` (when non-empty) or ``urdf_path``
(:mod:`cdmp_ros.ros.robot_model`); explicit ``limits.lower`` / ``limits.upper`` are merged with
them, the tighter per joint and bound, never wider (:func:`cdmp_ros.core.joint_limits.
merge_limits`): the demonstrations are checked against, and the primitives fitted within, the
merged limits. Diagnostics keys: docs/nodes.md.
"""
import collections
import os
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from cdmp_ros.core.demonstrations import DemonstrationSegmenter
from cdmp_ros.core.config_fields import chain_tips
from cdmp_ros.core.dmp.dmp import DmpConfig
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.joint_limits import describe_mismatches, merge_limits
from cdmp_ros.core.dmp.improve import CostConfig, ImproveConfig
from cdmp_ros.core.learning import LearnerConfig, PrompLearnConfig, fit_primitive
from cdmp_ros.core.primitive_io import primitive_to_dict, save_primitive
from cdmp_ros.core.validation import check_limits
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
from cdmp_ros.ros import qos
from cdmp_ros.ros.convert import JointStateMapper, stamp_to_ns
from cdmp_ros.ros.diagnostics import ERROR, OK, WARN, DiagnosticsReporter
from cdmp_ros.ros.input_gate import InputGate, joint_names
from cdmp_ros.ros.learner_improve import ImproveWorker, load_bag_demonstrations
from cdmp_ros.ros.params import ConfigParameters
from cdmp_ros.ros.readiness_probe import ReadinessProbe, has_subscribers
from cdmp_ros.ros.robot_model import limits_source, load_chain

#: ``demonstration``: reliable, volatile, keep last 1000 -- a demonstration streamed at up to
#: 1 kHz loses no sample while a refit briefly holds the executor.
DEMONSTRATION_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                               reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE)
POLL_PERIOD = 0.05  # s, segmentation gaps and improve progress


class LearnerNode(Node):
    """See the module docstring."""

    def __init__(self, **kwargs):
        super().__init__('learner', **kwargs)
        self.params = ConfigParameters(
            self, [('', LearnerConfig), ('dmp', DmpConfig), ('promp', PrompLearnConfig),
                   ('improve', ImproveConfig), ('cost', CostConfig)],
            on_change=self._on_params)
        cfg: LearnerConfig = self.params['']
        self.chain, self.lower, self.upper = self._limits(cfg)
        self.mapper = JointStateMapper(cfg.joint_names, allow_extra=False)
        self.segmenter = DemonstrationSegmenter(cfg.joint_names, self.lower, self.upper,
                                                cfg.demonstration_gap, cfg.min_samples,
                                                cfg.max_samples, cfg.limit_tolerance)
        self.topic_demos = collections.deque(maxlen=cfg.max_demonstrations)
        self.pub = self.create_publisher(String, 'primitive', qos.LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                              qos.COMMAND)
        self.reporter = DiagnosticsReporter(self, self.diag_pub)
        self.gate = InputGate(self, self.reporter, lambda: self.config)
        self.gate.set_rates({'demonstration': cfg.max_input_rate})
        n = len(cfg.joint_names)
        self.gate.subscribe(JointState, 'demonstration', self._on_demonstration,
                            DEMONSTRATION_QOS, size=joint_names(lambda: n))
        self.create_service(Trigger, '~/refit', self._srv_refit)
        self.create_service(Trigger, '~/save', self._srv_save)
        self.create_service(Trigger, '~/improve', self._srv_improve)
        self.primitive = None
        self.source = 'none'
        self.worker = None
        self.counts = {'published': 0, 'samples': 0, 'bag_demonstrations': 0,
                       'improvements': 0}
        self.improve_values = {}
        ready = {'consumer': ('a subscriber on primitive', has_subscribers(self, 'primitive'))}
        if cfg.fit_on_start:
            ready['primitive'] = ('a primitive fitted and published at start',
                                  lambda: self.primitive is not None)
        self.readiness = ReadinessProbe(self, ready)
        self.poll_timer = self.create_timer(POLL_PERIOD, self._poll)
        self.diag_timer = self.create_timer(cfg.diagnostics_period, self._publish_diagnostics)
        self.reporter.set_state(WARN, 'no primitive yet',
                                limits_source=('limits.lower/upper' if self.chain is None
                                               else self.limits_source),
                                limit_mismatch=describe_mismatches(self.limit_mismatches))
        if cfg.fit_on_start:
            ok, text = self.refit('start')
            (self.get_logger().info if ok else self.get_logger().warning)(text)
        self._publish_diagnostics()

    # -- setup -------------------------------------------------------------------------------
    def _declare_limits(self):
        out = []
        for key in ('lower', 'upper'):
            desc = ParameterDescriptor(
                name=f'limits.{key}', type=ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=True,
                description=f'{key.capitalize()} joint limits [rad] in the order of '
                            'joint_names; merged with the robot limits (robot_description or '
                            'urdf_path), the tighter used; empty: the robot limits.')
            try:
                p = self.declare_parameter(f'limits.{key}', Parameter.Type.DOUBLE_ARRAY, desc)
            except (ParameterException, TypeError, ValueError) as exc:
                raise ValidationError(f'parameter limits.{key}: {exc}') from None
            out.append(list(p.value or []))
        return out

    def _limits(self, cfg: LearnerConfig):
        """(chain or None, lower, upper): the robot's limits, tightened by the explicit ones
        (never widened; the differences in ``self.limit_mismatches``)."""
        lower, upper = self._declare_limits()
        self.limit_mismatches = []
        # the robot model: robot_description, else urdf_path (as the streamer and adapter)
        path = self.limits_source = cfg.urdf_path
        chain, chain_error = None, None
        try:
            path = self.limits_source = limits_source(cfg.urdf_path, cfg.robot_description)
            chain = load_chain(cfg.urdf_path, cfg.joint_names, chain_tips(cfg), cfg.tcp_offset,
                               cfg.robot_description)
        except CdmpError as exc:
            chain, chain_error = None, f'cannot use {path!r}: {exc}'
        n = len(cfg.joint_names)
        if lower or upper:
            if len(lower) != n or len(upper) != n:
                raise ValidationError(f'limits.lower/upper: expected {n} values each (one per '
                                      f'joint), got {len(lower)} and {len(upper)}')
            lo, hi = check_limits(lower, upper, n)
            if chain is not None:  # the tighter of the parameters and the robot
                try:
                    lo, hi, self.limit_mismatches = merge_limits(
                        cfg.joint_names, chain.lower, chain.upper, lo, hi)
                except ValidationError as exc:
                    raise ValidationError(f'limits.lower/upper and the robot limits of '
                                          f'{path!r}: {exc}') from None
            if self.limit_mismatches:
                self.get_logger().warning(
                    f'limits.lower/upper differ from the robot ({path}) on '
                    f'{len(self.limit_mismatches)} bounds, the tighter are used: '
                    f'{describe_mismatches(self.limit_mismatches)}')
        elif chain is not None:
            lo, hi = chain.lower.copy(), chain.upper.copy()
        else:
            raise ValidationError(f'limits: empty limits.lower/upper need the URDF; '
                                  f'{chain_error}')
        if chain is None:
            self.get_logger().warning(f'{chain_error}; ~/improve is not available')
        return chain, lo, hi

    def _on_params(self, configs) -> None:
        """Apply an accepted change (the dataclasses validated it already)."""
        cfg: LearnerConfig = configs['']
        self.segmenter.configure(cfg.demonstration_gap, cfg.min_samples, cfg.max_samples,
                                 cfg.limit_tolerance)
        if cfg.max_demonstrations != self.topic_demos.maxlen:
            self.topic_demos = collections.deque(self.topic_demos,
                                                 maxlen=cfg.max_demonstrations)
        if cfg.max_input_rate != self.gate.limiters['demonstration'].rate:
            self.gate.set_rates({'demonstration': cfg.max_input_rate})
        if abs(cfg.diagnostics_period - self.diag_timer.timer_period_ns * 1e-9) > 1e-9:
            self.destroy_timer(self.diag_timer)
            self.diag_timer = self.create_timer(cfg.diagnostics_period,
                                                self._publish_diagnostics)

    @property
    def config(self) -> LearnerConfig:
        return self.params['']

    # -- demonstrations ----------------------------------------------------------------------
    def _on_demonstration(self, msg: JointState) -> None:
        now = time.monotonic()
        if len(msg.name) == 0 and len(msg.position) == 0:
            self._handle(self.segmenter.end('end marker (empty JointState)'))
            return
        if not self.gate.stamp_ok('demonstration', 'demonstration.header.stamp',
                                  msg.header.stamp):
            return
        now_ns = self.get_clock().now().nanoseconds
        try:
            q, _ = self.mapper.to_arrays(msg, 'demonstration')
            stamp_ns = stamp_to_ns(msg.header.stamp) or now_ns
            events = self.segmenter.add(stamp_ns * 1e-9, q, now)
        except ValidationError as exc:
            self.gate.reject('demonstration', str(exc))
            return
        self.counts['samples'] += 1
        self._handle(events)

    def _handle(self, events) -> None:
        for ev in events:
            if ev.demo is None:
                self.gate.reject('demonstration', ev.message)
                continue
            self.topic_demos.append(ev.demo)
            self.get_logger().info(f'{ev.message}; {len(self.topic_demos)} topic '
                                   'demonstration(s) kept')
            if self.config.auto_refit:
                ok, text = self.refit('demonstration')
                (self.get_logger().info if ok else self.get_logger().warning)(text)

    # -- fitting -----------------------------------------------------------------------------
    def refit(self, reason: str):
        """Fit from the bags and the topic demonstrations; publish. Returns (ok, message)."""
        if self.worker is not None:
            return False, 'refit refused: an improvement is running (wait for it to finish)'
        t0 = time.perf_counter()
        cfg = self.config
        demos, used, errors = load_bag_demonstrations(
            cfg.demonstration_bags, cfg.demonstration_topic, cfg.joint_names, self.lower,
            self.upper, cfg.min_samples, cfg.limit_tolerance)
        if errors:  # one entry, every reason (the reporter keeps the last reason only)
            self.gate.reject('demonstration_bags', f'{len(errors)} of '
                                                   f'{len(cfg.demonstration_bags)} entries '
                                                   f'rejected: ' + '; '.join(errors))
        self.counts['bag_demonstrations'] = len(demos)
        n_bag = len(demos)
        demos = demos + list(self.topic_demos)
        if not demos:
            self.reporter.set_state(WARN if self.primitive is not None else ERROR,
                                    'no demonstrations to fit')
            return False, (f'refit ({reason}): no demonstrations (bags: {errors or "none"}; '
                           'topic: none)')
        try:
            prim = fit_primitive(cfg.kind, demos, cfg.joint_names, self.lower, self.upper,
                                 self.params['dmp'], self.params['promp'])
            prim.metadata['demonstrations'] = {'bags': used, 'from_bags': n_bag,
                                               'from_topic': len(demos) - n_bag}
            text = self._publish(prim, f'fit ({reason})')
        except (CdmpError, ValueError, np.linalg.LinAlgError) as exc:
            self.gate.reject('demonstration', f'fit failed: {exc}')
            return False, f'refit ({reason}) failed: {exc}'
        dt = time.perf_counter() - t0
        self.reporter.timing('fit', dt)
        return True, (f'{text}: {cfg.kind} from {len(demos)} demonstration(s) ({n_bag} from '
                      f'bags, {len(demos) - n_bag} from the topic), rms error '
                      f'{prim.metadata["fit_rms_error"]:.4g} rad, {dt * 1e3:.0f} ms')

    def _publish(self, prim, source: str) -> str:
        import json
        text = json.dumps(primitive_to_dict(prim))  # validates against the schema
        self.pub.publish(String(data=text))
        self.primitive, self.source = prim, source
        self.counts['published'] += 1
        self.reporter.set_state(OK, f'primitive published ({source})')
        return f'published {self.resolve_topic_name("primitive")}'

    # -- services ----------------------------------------------------------------------------
    def _srv_refit(self, request, response):
        response.success, response.message = self.refit('~/refit')
        return response

    def _srv_save(self, request, response):
        if self.primitive is None:
            response.success, response.message = False, 'no primitive to save yet'
            return response
        path = os.path.abspath(os.path.expanduser(self.config.primitive_path))
        try:
            save_primitive(self.primitive, path)
        except (OSError, CdmpError) as exc:
            response.success, response.message = False, f'cannot write {path}: {exc}'
            return response
        self.get_logger().info(f'saved the primitive ({self.source}) to {path}')
        response.success, response.message = True, path
        return response

    def _srv_improve(self, request, response):
        if self.worker is not None:
            rep, _ = self.worker.progress()
            at = f'update {rep.update}/{rep.n_updates}' if rep else 'starting'
            response.success = False
            response.message = f'refused: an improvement is already running ({at})'
            return response
        if self.primitive is None:
            response.success, response.message = False, 'refused: no primitive to improve'
            return response
        cfg: ImproveConfig = self.params['improve']
        try:
            worker = ImproveWorker(self.primitive, cfg, self.params['cost'], self.chain,
                                   self.lower, self.upper)
        except (CdmpError, ValueError) as exc:
            response.success, response.message = False, f'refused: {exc}'
            return response
        self.worker = worker
        self.improve_values = {'improve': f'running 0/{cfg.updates}'}
        worker.start()
        response.success = True
        response.message = (f'improving: {cfg.updates} PI2 updates of {cfg.rollouts_per_update} '
                            f'rollouts, cost {cfg.cost!r}; progress on diagnostics')
        self.get_logger().info(response.message)
        return response

    # -- periodic ----------------------------------------------------------------------------
    def _poll(self) -> None:
        self._handle(self.segmenter.poll(time.monotonic()))
        w = self.worker
        if w is None:
            return
        rep, new = w.progress()
        if new:
            self.improve_values = {
                'improve': f'running {rep.update}/{rep.n_updates}',
                'improve_cost_mean': f'{rep.mean_cost:.6g}',
                'improve_cost_min': f'{rep.min_cost:.6g}',
                'improve_rollouts_outside_limits': str(w.improver.outside),
                'improve_max_limit_usage': f'{w.improver.max_usage:.6f}'}
            self.reporter.set_state(OK, f'improving: update {rep.update}/{rep.n_updates}, '
                                        f'cost mean {rep.mean_cost:.4g} min {rep.min_cost:.4g}')
            self._publish_diagnostics()
        result, error = w.outcome()
        if result is None and error is None:
            return
        self.worker = None
        if error is not None:
            self.improve_values = {'improve': f'failed: {error}'}
            self.gate.reject('improve', f'improvement failed: {error}')
        else:
            self._finish_improve(result, w.elapsed)
        self._publish_diagnostics()

    def _finish_improve(self, result, elapsed: float) -> None:
        text = self._publish(result.primitive, f'PI2 {result.updates} updates')
        self.counts['improvements'] += 1
        self.improve_values = {
            'improve': f'done {result.updates} updates', 'improve_cost_before':
            f'{result.cost_before:.6g}', 'improve_cost_after': f'{result.cost_after:.6g}',
            'improve_rollouts': str(result.rollouts),
            'improve_rollouts_outside_limits': str(result.rollouts_outside_limits),
            'improve_max_limit_usage': f'{result.max_limit_usage:.6f}',
            'improve_time_s': f'{elapsed:.3f}'}
        self.get_logger().info(
            f'improvement done: {result.updates} updates, {result.rollouts} rollouts '
            f'({result.rollouts_outside_limits} outside the limits), cost '
            f'{result.cost_before:.4g} -> {result.cost_after:.4g} in {elapsed:.2f} s; {text}')

    def _publish_diagnostics(self) -> None:
        values = dict(self.improve_values)
        prim = self.primitive
        if prim is not None:
            values['fit_rms_error'] = f'{prim.metadata.get("fit_rms_error", float("nan")):.6g}'
        self.reporter.set_state(
            self.reporter.level, self.reporter.message, kind=self.config.kind,
            primitive=(f'{prim.kind} ({self.source})' if prim is not None else 'none'),
            topic_demonstrations=len(self.topic_demos),
            pending_samples=self.segmenter.n_pending, **self.counts, **values,
            **self.readiness.values(), **self.gate.values())
        self.reporter.publish(self.get_clock().now().to_msg())

    def close(self) -> None:
        w = self.worker
        if w is not None:  # a running ~/improve ends before its next rollout cost
            w.stop_event.set()
            w.join(timeout=1.0)
