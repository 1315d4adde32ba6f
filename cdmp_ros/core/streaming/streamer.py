"""Online streaming of the active primitive: the logic of the streamer node, without ROS.

:class:`ReferenceStreamer` owns the joint reference ``(y, yd)`` that the streamer publishes.
Every tick it advances the active primitive's :class:`~cdmp_ros.core.dmp.stepper.DmpStepper` with
the obstacle coupling term of the current reference (paper 000, Eq. 7/12 mapped into the
exogenous space, Eq. 21), and guarantees what the node promises:

- *No jump on a switch*: a new primitive, and a resumption after a stop, restart the stepper
  from the current reference position **and velocity** at phase 0; an adaptation that
  ``continues`` the running motion (obstacles, constraints) starts at the running phase
  instead (:meth:`ReferenceStreamer.activate`); a new goal only moves the goal target
  ``g_0``, which the goal state follows smoothly (Eq. 14/22). The acceleration of the new
  stepper at its restart differs from the reference's (another forcing term at phase 0), so a
  primitive switched in while streaming gets, over ``switch_blend_time``, an extra joint
  acceleration that starts at exactly that difference and fades out with a quintic weight
  (:class:`SwitchBlend`): the acceleration is continuous and changes by at most about
  ``1.9 |difference| dt / switch_blend_time`` per step. It is added to the obstacle
  coupling's joint acceleration and enters the stepper like it (mapped into the exogenous
  space by ``DmpStepper.set_joint_coupling``, Eq. 21), so the limit guarantee holds during
  the blend.
- *Smooth stop on stale inputs*: without fresh ``joint_states`` (``joint_states_timeout``)
  or without a primitive, the reference decelerates to rest along the closed-form profile of
  :class:`SmoothStop` (velocity continuous, zero acceleration at both ends), in the exogenous
  space of the active CDMP's limits (the tighter of the primitive's and the robot's; else the
  robot's), so the stop itself cannot leave them; then it holds.
- *Never outside the limits, never NaN, never the wrong size*: the output lists have a fixed
  length and every published position is checked against ``[lower, upper]`` (a last guard for
  plain DMPs, whose integration has no limits; flagged ``CLAMPED``).

Times (``now``) are seconds of a steady clock supplied by the caller, so the class is
deterministic and testable without ROS.
"""
import dataclasses
import enum
import math
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.coupling.arms import ArmsCoupling
from cdmp_ros.core.coupling.contract import Coupling
from cdmp_ros.core.coupling.obstacle import CouplingConfig, DampingConfig, ObstacleCoupling
from cdmp_ros.core.coupling.potential_fields import BoardField, ConstantField, RepellerField
from cdmp_ros.core.kinematics import Chain
from cdmp_ros.core.kinematics.arms import Arms, split_by_arm
from cdmp_ros.core.kinematics.capsules import Capsule
from cdmp_ros.core.dmp.stepper import CouplingResult
from cdmp_ros.core.streaming.primitives import PreparedPrimitive
from cdmp_ros.core.streaming.config import StreamerConfig
from cdmp_ros.core.streaming.output_stage import OutputStage
from cdmp_ros.core.joint_limits import KinematicLimits
from cdmp_ros.core.dmp.transform import SAT_MARGIN, XI_SAT, TanhTransform
from cdmp_ros.core.validation import as_array, check_limits


#: Skipped periods the output stage runs through at most in one call of
#: :meth:`ReferenceStreamer.advance` (2,000: 2 s at 1 kHz, 4 s at 500 Hz; a longer stall of the
#: tick is a failure of its own, beyond any controller's communication timeout).
MAX_SKIPPED_STAGE_STEPS = 2000
#: Distance [rad or m] the output stage keeps from the position limits.
STAGE_MARGIN = 1e-6


#: The sections of the streamer's parameters (``<section>.<name>``; ``''``: StreamerConfig) and
#: the config class of each: the node declares them, graph files and tools read them.
PARAMETER_SECTIONS = (('', StreamerConfig), ('coupling', CouplingConfig),
                      ('damping', DampingConfig), ('repeller', RepellerField),
                      ('box_field', ConstantField), ('board_field', BoardField))


def coupling_of(chain: Chain, configs, capsules: Sequence[Capsule] = ()) -> Coupling:
    """:func:`streamer_coupling` from the configs of every :data:`PARAMETER_SECTIONS`
    (``configs[section]``)."""
    return streamer_coupling(chain, configs[''], configs['coupling'], configs['damping'],
                             configs['repeller'], configs['box_field'], configs['board_field'],
                             capsules)


def streamer_coupling(chain: Chain, config: StreamerConfig,
                      coupling: CouplingConfig = CouplingConfig(),
                      damping: DampingConfig = DampingConfig(),
                      repeller: RepellerField = RepellerField(),
                      box_field: ConstantField = ConstantField(),
                      board_field: BoardField = BoardField(),
                      capsules: Sequence[Capsule] = ()) -> Coupling:
    """The streamer's obstacle coupling from its parameters (the ``coupling.*``,
    ``damping.*``, ``repeller.*``, ``box_field.*`` and ``board_field.*`` sections):
    Eq. (7) on the tool centre point ``config.tcp_offset``, Eq. (12) on
    ``config.coupling_links`` (joint-axis segments, radius ``coupling.link_radius``) and on
    ``capsules`` (their own radius: those of ``config.coupling_capsule_links``, fitted by
    :func:`~cdmp_ros.core.kinematics.capsules.collision_capsules`); spheres get
    ``repeller``, boxes ``box_field`` (IV-B) or, with ``config.box_field_kind == 'board'``,
    ``board_field`` (Eq. 30-31).

    ``chain`` an :class:`~cdmp_ros.core.kinematics.arms.Arms`: an
    :class:`~cdmp_ros.core.coupling.arms.ArmsCoupling`, each arm's coupling on the links of
    ``coupling_links`` and ``capsules`` that are of that arm, Eq. (7) on each arm's tool
    centre point.

    Raises
    ------
    ValidationError
        Unknown link names.
    """
    boxes = board_field if config.box_field_kind == 'board' else box_field
    coupling = dataclasses.replace(coupling, damping=damping)
    if not isinstance(chain, Arms):
        return ObstacleCoupling(chain, list(config.coupling_links) + list(capsules),
                                sphere_field=repeller, box_field=boxes, config=coupling,
                                tcp_offset=config.tcp_offset)
    # several arms: each its own coupling on the links and capsules that are of that arm
    links = split_by_arm(chain, config.coupling_links, 'coupling_links')
    by_link = {c.link: c for c in capsules}
    caps = split_by_arm(chain, list(by_link), 'coupling_capsule_links')
    return ArmsCoupling(chain, [
        ObstacleCoupling(arm, links[k] + [by_link[n] for n in caps[k]], sphere_field=repeller,
                         box_field=boxes, config=coupling, tcp_offset=config.tcp_offset)
        for k, arm in enumerate(chain.chains)])


def bound_into(dq_dd, limit: float, out: List[float]) -> float:
    """Copy a joint acceleration ``dq_dd`` into ``out`` as floats, scaled so that
    ``max_d |out_d| <= limit``; returns the peak ``max_d |dq_dd_d|`` before scaling.

    The one bound of a coupling's magnitude (``coupling_max_acceleration``): potential fields
    grow without bound as an obstacle approaches (a FIRAS repeller like ``1/d^3``), and an
    obstacle that appears inside or next to a link can ask for an acceleration that moves the
    reference from mid-range onto the joint limits in one tick.

    One factor for all joints, so the direction of the coupling (the avoidance direction, the
    null-space structure of Eq. 12) is kept and only its magnitude is bounded. ``limit <= 0``
    copies without a bound. Returns -1.0, with ``out`` unspecified, when ``dq_dd`` is not
    ``len(out)`` finite numbers (the caller rejects it, as
    :meth:`~cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling` would). Never raises;
    allocation-free (the streaming tick).
    """
    n = len(out)
    peak = 0.0
    i = 0
    try:
        for v in dq_dd:
            if i == n:
                return -1.0
            f = float(v)
            if not -math.inf < f < math.inf:
                return -1.0
            out[i] = f
            i += 1
            if f > peak:
                peak = f
            elif -f > peak:
                peak = -f
    except (TypeError, ValueError, OverflowError):
        return -1.0
    if i != n:
        return -1.0
    if 0.0 < limit < peak:
        factor = limit / peak
        for d in range(n):
            out[d] *= factor
    return peak


class StreamState(enum.Enum):
    WAITING = 'waiting'    #: no reference yet (no joint_states, or no primitive in open loop)
    RUNNING = 'running'    #: integrating the active primitive
    STOPPING = 'stopping'  #: smooth stop in progress
    HOLDING = 'holding'    #: at rest, waiting for fresh inputs or a primitive


class StreamFlags(enum.IntFlag):
    NONE = 0
    CLAMPED = 1           #: a position was outside [lower, upper] and was clamped (plain DMP)
    COUPLED = 2           #: a non-zero obstacle coupling term was applied
    SATURATED = 4         #: the exogenous state saturated (stepper)
    VELOCITY_LIMITED = 8  #: the phase was slowed to respect velocity limits (stepper)
    COUPLING_REJECTED = 16  #: the coupling term was non-finite or failed and was dropped
    COUPLING_BOUNDED = 32   #: the coupling term was scaled down to coupling_max_acceleration
    LIMITED = 64          #: the output stage bent the reference to keep the limits


def _h(s: float) -> float:
    """Velocity profile of the stop: 1 - 3 s^2 + 2 s^3 (1 at s=0, 0 at s=1, flat ends)."""
    return 1.0 - s * s * (3.0 - 2.0 * s)


def _H(s: float) -> float:
    """Integral of :func:`_h` from 0 to s (H(1) = 1/2)."""
    s2 = s * s
    return s - s2 * s + 0.5 * s2 * s2


class SmoothStop:
    """Closed-form stop from ``(y0, yd0)`` within ``duration`` [s], in the exogenous space.

    ``xi(t) = xi0 + xid0 * T * H(t / T)``, ``xid(t) = xid0 * h(t / T)`` with
    ``h(s) = 1 - 3 s^2 + 2 s^3``: velocity continuous at the start, zero at the end, zero
    acceleration at both ends, peak deceleration ``1.5 |xid0| / T``. Positions follow from
    ``y = y_delta tanh(xi) + y_o`` (Eq. 19), so they stay inside the limits of ``transform``,
    and ``xi`` is held within the transform's clipping margin (``|xi| <= atanh(1 - margin)``).
    """

    def __init__(self, transform: TanhTransform, y0: ArrayLike, yd0: ArrayLike,
                 duration: float):
        # the exact exogenous state (no margin clip: a reference inside the margin band does
        # not jump on the first stop tick), saturated like the stepper's
        u = (np.asarray(y0, dtype=float) - transform.y_o) / transform.y_delta
        xi0 = np.clip(np.arctanh(np.clip(u, -1.0, 1.0)), -XI_SAT, XI_SAT)
        self.xi0 = xi0.tolist()
        self.xid0 = (np.asarray(yd0, dtype=float) / np.maximum(transform.jacobian(xi0),
                                                               1e-300)).tolist()
        self.yo = transform.y_o.tolist()
        self.ydel = transform.y_delta.tolist()
        self.duration = float(duration)
        self.t = 0.0
        # it ends no closer to a limit than the transform's own clipping margin (or where it
        # started, if closer): a stepper restarted from the stopped reference then starts
        # exactly there (no clip, no jump)
        edge = math.atanh(1.0 - transform.margin)
        self.xi_max = [min(XI_SAT, max(edge, abs(x))) for x in self.xi0]

    def advance(self, dt: float, y: List[float], yd: List[float], ydd: List[float]) -> bool:
        """Advance by dt and write the state into y, yd, ydd; True once at rest."""
        self.t += dt
        T = self.duration
        s = min(self.t / T, 1.0)
        H, h, hp = _H(s), _h(s), 6.0 * s * (s - 1.0)
        for d, (xi0, v0, xi_max) in enumerate(zip(self.xi0, self.xid0, self.xi_max)):
            xi = xi0 + v0 * T * H
            if -xi_max <= xi <= xi_max:
                xid = v0 * h
                xidd = v0 * hp / T
            else:  # held at the edge: at rest there
                xi = xi_max if xi > 0.0 else -xi_max
                xid = xidd = 0.0
            t = math.tanh(xi)
            de = self.ydel[d]
            sech2 = 1.0 - t * t
            y[d] = de * t + self.yo[d]  # Eq. (27)
            yd[d] = de * sech2 * xid  # Eq. (28)
            ydd[d] = de * sech2 * (xidd - 2.0 * t * xid * xid)  # Eq. (29)
        return s >= 1.0


class SwitchBlend:
    """The fade-out of the acceleration difference at a switch, over ``n_steps`` steps.

    ``corr`` is the joint-space difference (reference acceleration before the switch minus the
    new stepper's at its restart, without the obstacle coupling). Step ``i`` adds
    ``corr * (1 - w(i / n_steps))`` to the coupling's joint acceleration, with
    ``w(s) = 10 s^3 - 15 s^4 + 6 s^5`` (``w' = w'' = 0`` at both ends): the first acceleration
    equals the old one and the correction vanishes smoothly.
    """

    def __init__(self, corr: List[float], n_steps: int):
        self.corr = corr
        self.n_steps = int(n_steps)
        self.i = 0

    def next_weight(self) -> Tuple[float, bool]:
        """The weight ``1 - w`` of the next step's correction, and whether the blend is over
        (the weight is then 0)."""
        self.i += 1
        s = self.i / self.n_steps
        if s >= 1.0:
            return 0.0, True
        return 1.0 - s * s * s * (10.0 - 15.0 * s + 6.0 * s * s), False


class ReferenceStreamer:
    """The streamer's reference generator (see the module docstring).

    Parameters
    ----------
    lower, upper : array-like, shape (n_dims,)
        Robot position limits, in the order of ``config.joint_names``.
    config : StreamerConfig
    coupling : Coupling, optional
        Obstacle coupling (:class:`~cdmp_ros.core.coupling.contract.Coupling`), evaluated at
        the reference state for ``self.obstacles`` (not called while there is none).
    limits : KinematicLimits, optional
        The robot's velocity, acceleration and jerk limits (same joints) that the output stage
        keeps; default none beyond the position limits.

    Attributes
    ----------
    obstacles : sequence
        The current obstacle set (replaced as a whole by the caller).
    min_distance : float
        Smallest of the coupling's ``last_distances`` at its last evaluation (inf without
        obstacles).
    coupling_peak : float
        Largest joint acceleration [rad/s^2] the coupling asked for beyond
        ``config.coupling_max_acceleration`` (before the bound; 0 while it never did). The
        caller may reset it (the node does, every diagnostics period).
    """

    def __init__(self, lower: ArrayLike, upper: ArrayLike, config: StreamerConfig,
                 coupling: Optional[Coupling] = None,
                 limits: Optional[KinematicLimits] = None):
        self.config = config
        self._dt = config.dt
        self.joint_names = list(config.joint_names)
        n = self.n_dims = len(self.joint_names)
        lo, hi = check_limits(lower, upper, n)
        self.lower, self.upper = lo, hi
        self._lo, self._hi = lo.tolist(), hi.tolist()
        self.transform = TanhTransform(lo, hi, margin=SAT_MARGIN)
        self._goal_transform = TanhTransform(lo, hi, margin=config.limit_margin)
        self.coupling = coupling
        self.obstacles: Sequence = ()
        self.min_distance = math.inf
        self.coupling_peak = 0.0
        self.y = [0.0] * n
        self.yd = [0.0] * n
        self.ydd = [0.0] * n
        self.state = StreamState.WAITING
        self.reason = ('waiting for joint_states' if config.joint_states_timeout > 0
                       else 'waiting for a primitive')
        self.active: Optional[PreparedPrimitive] = None
        self.goal_override: Optional[NDArray[np.float64]] = None
        self.last_measure: Optional[float] = None
        self.steps = 0
        self._stop: Optional[SmoothStop] = None
        self._calls = 0
        self._coupling_flags = 0
        self._blend: Optional[SwitchBlend] = None
        self._last: Optional[PreparedPrimitive] = None   # the primitive last started
        self._coupling_joint = [0.0] * n   # the obstacle coupling's joint acceleration
        self._blended = [0.0] * n          # that plus the switch correction
        self._bounded = [0.0] * n          # the coupling as bounded (coupling_max_acceleration)
        self._zeros = (0.0,) * n
        self.measured: Optional[List[float]] = None  # the last measured position
        if limits is None:
            limits = KinematicLimits.unlimited(self.joint_names, lo, hi)
        self.limits = limits.subset(self.joint_names)
        self.active_limits = self.limits  # with the active primitive's own joint_limits
        self.stage = OutputStage(lo, hi, self.limits.velocity, self.limits.acceleration,
                                 self.limits.jerk, config.dt, config.output_bandwidth,
                                 margin=STAGE_MARGIN)
        self._bind_output()

    # -- configuration ------------------------------------------------------------------------
    def set_config(self, config: StreamerConfig) -> None:
        """Apply a new configuration (joint names and limits unchanged); the active stepper
        is rebuilt by the caller when ``rate`` changes."""
        if tuple(config.joint_names) != tuple(self.joint_names):
            raise ValidationError('joint_names: cannot change while streaming')
        self.config = config
        self._dt = config.dt
        self._goal_transform = TanhTransform(self.lower, self.upper,
                                             margin=config.limit_margin)
        self.stage.bandwidth = config.output_bandwidth
        self._bind_output()

    def _bind_output(self) -> None:
        """What is published: the output stage's state, or (``output_stage`` off) the
        primitive's reference itself."""
        if self.config.output_stage:
            if self.out_y is self.y and self.state is not StreamState.WAITING:
                self.stage.reset(self.y, self.yd, self.ydd)  # switched on while streaming
            self.out_y, self.out_yd, self.out_ydd = self.stage.p, self.stage.v, self.stage.a
        else:
            self.out_y, self.out_yd, self.out_ydd = self.y, self.yd, self.ydd

    out_y: List[float] = None  # set by _bind_output

    @property
    def dt(self) -> float:
        return self._dt

    # -- inputs (outside the tick) ------------------------------------------------------------
    def note_joint_states(self, q: ArrayLike, now: float) -> None:
        """A valid measurement arrived (streamer order); the first one sets the reference."""
        self.last_measure = now
        if self.measured is None:
            self.measured = [0.0] * self.n_dims
        m = self.measured
        for d in range(self.n_dims):
            m[d] = float(q[d])
        if self.state is StreamState.WAITING:
            self._set_reference(np.asarray(q, dtype=float), np.zeros(self.n_dims))
            self.stage.reset(self.y)
            self.state = StreamState.HOLDING
            self.reason = 'holding the measured position: no primitive yet'

    def clip_goal(self, goal_y: ArrayLike) -> Tuple[NDArray[np.float64], List[int]]:
        """Clip a goal into the limits with the margin; returns it and the clipped joints."""
        g = as_array('goal.position', goal_y, (self.n_dims,))
        gc = self._goal_transform.clip_position(g)
        return gc, [int(i) for i in np.flatnonzero(gc != g)]

    def set_goal(self, goal_y: ArrayLike) -> List[int]:
        """New joint-space goal (kept for later primitives too); returns the clipped joints.

        The active stepper's goal target changes; the goal state follows through Eq. 14/22,
        so position and velocity stay continuous.
        """
        g, clipped = self.clip_goal(goal_y)
        self.goal_override = g
        if self.active is not None and self.state is StreamState.RUNNING:
            self.active.stepper.set_goal(g)
        return clipped

    def activate(self, prepared: PreparedPrimitive, now: float, continues: bool = False) -> str:
        """Switch to a prepared primitive without a jump; returns a description.

        ``continues``: the primitive reshapes the motion that is running (an adaptation to
        obstacles, :class:`~cdmp_ros.core.streaming.selection.Decision`): while running, its
        stepper starts at the current phase (``DmpStepper.reset(phase_u=...)``) instead of
        restarting the motion at phase 0, which would replay the whole movement from wherever
        the arm is. The forcing term then scales from the new primitive's own start, so that
        from the current state the rest of *its* trajectory (the adapted mean the adapter
        checked) is followed, the difference decaying through the attractor.
        """
        phase = 0.0
        if continues and self.state is StreamState.RUNNING and self._last is not None:
            # the stepper that runs (``active`` may be one stored while inputs were stale);
            # not running (stopping, holding): the motion restarts at phase 0
            phase = float(self._last.stepper.output.u)
        self.active = prepared
        self._apply_limits(prepared)
        if self.state is StreamState.WAITING and self.config.joint_states_timeout == 0:
            self._set_reference(prepared.prim.start_y_, np.zeros(self.n_dims))
            self.stage.reset(self.y)
            self.state = StreamState.HOLDING
        if self.state is StreamState.WAITING:
            return f'{prepared.source}: stored; waiting for joint_states to start'
        if self._fresh(now):
            blend = self.state is StreamState.RUNNING and self._last is not prepared
            jump = self._start_stepper(phase)
            if blend:
                self._begin_blend()
            at = f' at phase {phase:.3f}' if phase > 0.0 else ''
            return (f'{prepared.source}: switched in at the current reference{at}'
                    + (f' (start clipped by {jump:.3g} rad to the primitive limits)'
                       if jump > 1e-9 else ''))
        return f'{prepared.source}: stored; inputs stale ({self.reason})'

    def _apply_limits(self, prepared: PreparedPrimitive) -> None:
        """The output stage keeps the robot's limits, merged with the primitive's own
        ``joint_limits`` while it is the active one (the tighter of the two)."""
        lim = self.limits if prepared.kinematic is None else self.limits.merged(
            prepared.kinematic)
        self.active_limits = lim
        self.stage.set_limits(lim.velocity.tolist(), lim.acceleration.tolist(),
                              lim.jerk.tolist())

    # -- the tick -----------------------------------------------------------------------------
    def advance(self, n_steps: int, now: float,
                on_step: Optional[Callable[[int], None]] = None, skipped: int = 0) -> int:
        """Advance the reference by ``n_steps`` periods; returns :class:`StreamFlags` bits.

        ``on_step(i)``, if given, is called after each step (``i = 0 .. n_steps - 1``) with
        ``out_y, out_yd, out_ydd`` (what is published) already through the output stage (the
        node publishes every step of a catch-up).

        ``skipped``: periods before these ``n_steps`` that are not published (a tick later
        than the catch-up allows, :meth:`TickSchedule.advance`). The output stage runs
        through them toward the reference as it stands (the primitive pauses, a time scaling
        it never notices), at most :data:`MAX_SKIPPED_STAGE_STEPS` of them: the positions
        published after the gap are then a sample of a motion within the velocity,
        acceleration and jerk limits, and their differences on the stamps stay within them
        (without it the stamps jump by the gap while the positions move one period: the
        acceleration spikes by the gap's length).

        Never raises on account of inputs: the stepper does not raise, the coupling callable is
        guarded, the guard keeps every position finite and inside the limits, and the output
        stage keeps what is published inside the position, velocity, acceleration and jerk
        limits.
        """
        state = self.state
        if state is StreamState.WAITING:
            return 0
        fresh = self._fresh(now)
        if state is StreamState.RUNNING and not fresh:
            self._begin_stop(now)
        elif state is not StreamState.RUNNING and fresh and self.active is not None:
            self._start_stepper()
        elif state is StreamState.HOLDING and not fresh:
            self.reason = self._stale_reason(now)
        flags = 0
        dt = self._dt
        stage_on = self.config.output_stage
        if stage_on and skipped > 0:
            target = self.y
            for _ in range(min(int(skipped), MAX_SKIPPED_STAGE_STEPS)):
                if self.stage.update(target):
                    flags |= StreamFlags.LIMITED
        if self.state is StreamState.RUNNING and self.coupling is not None:
            # evaluated once per call (zero-order hold over catch-up steps), every
            # coupling_decimation calls
            self._calls += 1
            if self._calls >= self.config.coupling_decimation:
                self._calls = 0
                self._coupling_flags = self._coupling_into(self.active.stepper)
            flags = self._coupling_flags
        for i in range(max(1, int(n_steps))):
            if self.state is StreamState.RUNNING:
                flags |= self._step_primitive()
            elif self.state is StreamState.STOPPING:
                if self._stop.advance(dt, self.y, self.yd, self.ydd):
                    self._hold()
            self.steps += 1
            flags |= self._guard()
            if stage_on and self.stage.update(self.y):
                flags |= StreamFlags.LIMITED
            if on_step is not None:
                on_step(i)
        return flags

    # -- internals ----------------------------------------------------------------------------
    def _fresh(self, now: float) -> bool:
        if self.active is None:
            return False
        timeout = self.config.joint_states_timeout
        return timeout == 0 or (self.last_measure is not None
                                and now - self.last_measure <= timeout)

    def _stale_reason(self, now: float) -> str:
        if self.active is None:
            return 'no primitive'
        if self.last_measure is None:
            return 'no joint_states received'
        return f'joint_states stale ({now - self.last_measure:.2f} s old)'

    def _set_reference(self, y: ArrayLike, yd: ArrayLike) -> None:
        y = np.clip(np.asarray(y, dtype=float), self.lower, self.upper)
        self.y[:] = y.tolist()
        self.yd[:] = np.asarray(yd, dtype=float).tolist()
        self.ydd[:] = [0.0] * self.n_dims

    def _start_stepper(self, phase_u: float = 0.0) -> float:
        """Restart the active stepper at the current reference (at normalised time
        ``phase_u``, see :meth:`activate`); returns the start clip [rad].

        From rest (``HOLDING``) with a measurement, the reference first moves to the measured
        position: the motion starts where the arm is, not where it was held (the arm may
        have been moved meanwhile); the output stage carries what is published there within
        the limits."""
        prep = self.active
        if self.state is StreamState.HOLDING and self.measured is not None:
            self._set_reference(self.measured, self._zeros)
            self.stage.retarget(self.y)
        prim = prep.prim
        goal = self.goal_override if self.goal_override is not None else prim.goal_y_
        y = np.asarray(self.y)
        prep.stepper.reset(start_y=y, start_yd=np.asarray(self.yd), goal_y=goal,
                           phase_u=phase_u)
        self._calls = self.config.coupling_decimation  # evaluate at the first step
        self._blend = None
        self._last = prep
        # P = 0 until the coupling is evaluated (at the first step); _coupling_joint keeps
        # the last evaluation, which the blend of a switch compares against
        prep.stepper.set_joint_coupling(None)
        self.state = StreamState.RUNNING
        self.reason = f'streaming the {prep.kind} from {prep.source}'
        return float(np.max(np.abs(np.asarray(prep.stepper.output.y) - y)))

    def _begin_blend(self) -> None:
        """After a switch while running: fade the acceleration difference out."""
        n = round(self.config.switch_blend_time / self.config.dt)
        if n < 1:
            return
        stepper = self.active.stepper
        # the new stepper's first step adds the obstacle coupling again: compare without it
        corr = [self.ydd[d] - stepper.output.ydd[d] - self._coupling_joint[d]
                for d in range(self.n_dims)]
        if all(math.isfinite(v) for v in corr):
            self._blend = SwitchBlend(corr, n)

    def _begin_stop(self, now: float) -> None:
        self._blend = None
        self.reason = 'stopping: ' + self._stale_reason(now)
        self._stop = SmoothStop(self._stop_transform(), self.y, self.yd, self.config.stop_time)
        self.state = StreamState.STOPPING

    def _stop_transform(self) -> TanhTransform:
        """The limits a stop keeps: the active CDMP's (the tighter of the primitive's and the
        robot's), else the streamer's. With the robot's, a stop from speed next to a tighter
        primitive limit went past it, and the next start clipped the reference back in one
        tick (0.057 rad seen in a demo)."""
        prim = self.active.prim if self.active is not None else None
        if prim is not None and prim.kind == 'cdmp':
            y = np.asarray(self.y)
            if np.all(y > prim.y_min) and np.all(y < prim.y_max):
                return prim.transform
        return self.transform

    def _hold(self) -> None:
        self.reason = self.reason.replace('stopping: ', 'stopped: ')
        self.yd[:] = [0.0] * self.n_dims
        self.ydd[:] = [0.0] * self.n_dims
        self.state = StreamState.HOLDING
        self._stop = None

    def _step_primitive(self) -> int:
        stepper = self.active.stepper
        blend = self._blend
        if blend is not None:
            f, done = blend.next_weight()
            b, cj, corr = self._blended, self._coupling_joint, blend.corr
            for d in range(self.n_dims):
                b[d] = cj[d] + f * corr[d]
            stepper.set_joint_coupling(b)
            if done:
                self._blend = None
        out, status = stepper.update(stepper.input)
        self.y[:] = out.y
        self.yd[:] = out.yd
        self.ydd[:] = out.ydd
        return (4 if status & 4 else 0) | (8 if status & 16 else 0)

    def _coupling_into(self, stepper) -> int:
        """The coupling at the reference for the current obstacles, bounded to
        ``coupling_max_acceleration`` (:func:`bound_into`;
        finite values beyond the stepper's ``MAX_JOINT_COUPLING`` are then scaled down too,
        not dropped) and handed to the stepper (which maps it into its exogenous space, capped
        near saturation); never raises."""
        obstacles = self.obstacles
        cj = self._coupling_joint
        if not obstacles:
            self.min_distance = math.inf
            stepper.set_joint_coupling(None)
            cj[:] = self._zeros
            return 0
        coupling = self.coupling
        try:
            a = coupling.joint_acceleration(self.y, self.yd, obstacles)
            self.min_distance = min(coupling.last_distances, default=math.inf)
        except Exception:  # noqa: BLE001 -- the tick must not raise; reported as rejected
            a = ()
        bounded = 0
        limit = self.config.coupling_max_acceleration
        buf = self._bounded
        peak = bound_into(a, limit, buf) if a is not None else 0.0  # in place, no new list
        if a is None:  # the Coupling contract's "no coupling"
            result = stepper.set_joint_coupling(None)
        elif peak < 0.0:
            result = stepper.set_joint_coupling(())  # not n finite numbers: rejected
        else:
            if 0.0 < limit < peak:
                if peak > self.coupling_peak:
                    self.coupling_peak = peak
                bounded = int(StreamFlags.COUPLING_BOUNDED)
            result = stepper.set_joint_coupling(buf)
        if result is CouplingResult.APPLIED:
            for d in range(self.n_dims):
                cj[d] = buf[d]
        else:
            cj[:] = self._zeros
        if result is CouplingResult.REJECTED:
            return int(StreamFlags.COUPLING_REJECTED)
        return (int(StreamFlags.COUPLED) | bounded) if result is CouplingResult.APPLIED else 0

    def _guard(self) -> int:
        flags = 0
        y, yd, lo, hi = self.y, self.yd, self._lo, self._hi
        for d in range(self.n_dims):
            v = y[d]
            if not lo[d] <= v <= hi[d]:
                flags = int(StreamFlags.CLAMPED)
                y[d] = hi[d] if v > hi[d] else lo[d]  # NaN -> lower (never produced)
                yd[d] = 0.0
            if not -1e12 < yd[d] < 1e12:
                yd[d] = 0.0
        return flags
