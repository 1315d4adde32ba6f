#!/usr/bin/env python3
"""Trace which source files of cdmp_ros run on the path of an obstacle message.

    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=44 \\
        .venv/bin/python scripts/obstacle_path.py [--functions] [--sphere X Y Z R]
        [--marker sphere|cube] [--config FILE ...] [--primitive FILE] [--tick-thread]

The path is measured, not read off the code: from the moment the streamer node's ``obstacles``
subscription callback receives the serialized ``MarkerArray`` until the node publishes the
first ``joint_reference`` computed with that obstacle set. The figure is the number of files of
the package ``cdmp_ros`` with code that runs on that path (docs/architecture.md, "An obstacle
message, to the next joint reference", lists them; test/test_architecture_obstacle_path.py
compares the two).

How (everything in this process):

1. a :class:`cdmp_ros.ros.streamer_node.StreamerNode` in its own rclpy context, with the
   parameters of ``--config`` (default ``config/streamer.yaml``) but ``tick_thread: false``
   and ``joint_states_timeout: 0`` (open loop); its executor is never spun, so no timer fires
   and no message arrives on its own: the tick is called here (``_locked_tick``, the timer's
   callback);
2. a reach primitive (or ``--primitive``) goes in through the ``primitive`` subscription's
   raw callback; once the primitive worker has prepared it, ticks until the stream runs and
   references are published (``pub.publish`` is wrapped to see them);
3. a baseline: one tick without obstacles, traced up to its reference (the files marked ``*``
   run on every tick, obstacle or not);
4. the trace: ``sys.setprofile`` records the code object of every Python call; the
   ``obstacles`` subscription's callback gets the serialized MarkerArray (one SPHERE, or CUBE,
   marker in the base frame, stamped now) exactly as rclpy's executor hands it over, then the
   node ticks until the wrapped ``publish`` is called with the first reference computed with
   it (the first tick: a tick integrates at least one slot). Recording stops at that call:
   what the tick does after the publication (counters, the obstacle latency, the tick's
   timing) is not on the path.

``--tick-thread`` keeps the node's tick thread instead (``tick_thread: true``, a node
process's default; ``realtime_priority: 0`` here): the profiler is installed for the threads
the node starts (``threading.setprofile``), the obstacle is delivered from the calling thread
as by the executor, and the tick thread is recorded from the moment the obstacle set is in the
streamer (the node's ``_latency_pending_ns``, set with it under the tick's lock and cleared by
the first reference computed with it) until that reference is published; with
``obstacle_wakeup`` the obstacle wakes the tick thread (``DeadlineSleeper.wake``).

Kept: code objects whose file lies in the package directory, by file and function
(``co_qualname``). Left out and reported apart: module bodies (``<module>``: a module
imported lazily on this first message, not a step of the path), and kernels generated at run
time outside the package (the coupling kernel of a configuration without a checked-in one:
a module in the kernel cache, ``cdmp_ros.core.generated.cache_dir()``, or a ``<generated
...>`` pseudo file). Code without a file that runs with a cdmp_ros module's globals (the
``__init__`` that ``dataclasses`` generates) counts as that module's file. The garbage
collector is off during the trace (no finalizer of unrelated objects runs in it); the
primitive worker thread is idle and not recorded. The measurement checks that the obstacle
acted: the first reference after it was computed with the coupling applied
(``StreamFlags.COUPLED``), the node took the obstacle latency on it, and nothing was rejected.
"""
import argparse
import gc
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Set

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_CONFIG = os.path.join(REPO_ROOT, 'config', 'streamer.yaml')
#: The sphere (centre x, y, z and radius [m], base frame) near the Panda's tool centre point at
#: the start of the reach below (about (0.386, 0.0, 0.547)): its surface 0.1 m from it, inside
#: the repeller's influence distance (0.2 m in config/streamer.yaml), not touching.
DEFAULT_SPHERE = (0.5, 0.0, 0.45, 0.05)
#: A Panda reach (as the streamer tests' ``reach_cdmp``); another robot gets a reach from 35 %
#: to 65 % of each joint's range.
PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
PANDA_START = (0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7)
PANDA_GOAL = (0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3)
#: Bound of every wait on a condition [s]; a pass never waits it out.
WAIT_S = 60.0
#: Ticks after the switch-in before the obstacle (references published without obstacles).
WARM_TICKS = 5


@dataclass
class PathTrace:
    """What :func:`measure` found.

    Attributes
    ----------
    files : dict
        'cdmp_ros/...' file (relative to the repository root) -> names (``co_qualname``) of
        the functions of it that ran on the path.
    imported : set
        Files whose module body ran during the trace (imported lazily): not in ``files``.
    runtime_code : dict
        Kernels that cdmp_ros generated at run time, outside the package (a file of the
        kernel cache, or a ``<generated ...>`` pseudo file name) -> functions that ran.
    baseline : dict or None
        The same for one tick without obstacles, up to its first reference (what runs on
        every tick anyway); None with the tick thread.
    coupled : bool
        The first reference after the obstacle was computed with the coupling applied
        (``StreamFlags.COUPLED`` of that tick's coupling evaluation).
    coupled_ticks : int
        Ticks that applied the coupling from the obstacle on (the node's ``coupled`` count,
        after minus before; with the tick thread, more ticks than the traced one).
    published : int
        References published from the obstacle to the first one computed with it (1 unless
        ticks published before the obstacle set was in).
    ticks : int
        Ticks in the same span (counted by the node).
    latency_taken : bool
        The node took the obstacle latency on a reference published during the trace.
    rejected : int
        Inputs the node rejected during the trace (0: the marker was accepted).
    min_distance : float
        The coupling's smallest obstacle distance at its last evaluation [m].
    coupling_joint : list
        The coupling's joint acceleration handed to the stepper [rad/s^2].
    """

    files: Dict[str, Set[str]] = field(default_factory=dict)
    imported: Set[str] = field(default_factory=set)
    runtime_code: Dict[str, Set[str]] = field(default_factory=dict)
    baseline: Optional[Dict[str, Set[str]]] = None
    coupled: bool = False
    coupled_ticks: int = 0
    published: int = 0
    ticks: int = 0
    latency_taken: bool = False
    rejected: int = 0
    min_distance: float = float('inf')
    coupling_joint: List[float] = field(default_factory=list)

    @property
    def acted(self) -> bool:
        """The obstacle reached the first reference: accepted, coupling applied, timed."""
        return self.coupled and self.published > 0 and self.latency_taken \
            and self.rejected == 0


def _wait(pred, timeout: float, what: str):
    """Poll ``pred()`` until true (returned) or raise after ``timeout`` [s]."""
    end = time.monotonic() + timeout
    while True:
        result = pred()
        if result:
            return result
        if time.monotonic() >= end:
            raise RuntimeError(f'timed out after {timeout:g} s waiting for {what}')
        time.sleep(0.01)


def reach_primitive(joint_names: Sequence[str], lower, upper, duration: float = 2.0) -> str:
    """JSON text of a reach CDMP of the robot (see :data:`PANDA_START`)."""
    import numpy as np

    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.primitive_io import dumps_primitive
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if tuple(joint_names) == PANDA_JOINTS:
        y0, y1 = np.array(PANDA_START), np.array(PANDA_GOAL)
    else:
        y0, y1 = lower + 0.35 * (upper - lower), lower + 0.65 * (upper - lower)
    T = np.linspace(0.0, duration, 401)
    s = T / duration
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    Y = y0 + s[:, None] * (y1 - y0)
    return dumps_primitive(CDMP(lower, upper, joint_names=list(joint_names)).fit(T, Y))


def obstacle_message(frame: str, sphere: Sequence[float], marker: str = 'sphere',
                     stamp=None):
    """A MarkerArray of one ADD marker: a SPHERE of radius r at (x, y, z) = ``sphere``, or
    (``marker`` 'cube') an axis-aligned CUBE of edge 2 r there."""
    from visualization_msgs.msg import Marker, MarkerArray
    x, y, z, r = map(float, sphere)
    m = Marker(ns='obstacle_path', id=1, action=Marker.ADD,
               type=Marker.CUBE if marker == 'cube' else Marker.SPHERE)
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, z
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 2.0 * r
    return MarkerArray(markers=[m])


def _subscription(node, topic: str):
    name = node.resolve_topic_name(topic)
    for sub in node.subscriptions:
        if sub.topic_name == name:
            return sub
    raise RuntimeError(f'the node has no subscription on {name}')


def _deliver(sub, data: bytes) -> None:
    """Call ``sub``'s callback with serialized ``data`` as rclpy's executor does for a raw
    subscription (the message, and its info when the callback takes two arguments)."""
    from rclpy.subscription import Subscription
    assert sub.raw, f'{sub.topic_name}: not a serialized (raw) subscription'
    if sub._callback_type is Subscription.CallbackType.MessageOnly:
        sub.callback(data)
    else:
        sub.callback(data, {'source_timestamp': 0, 'received_timestamp': time.time_ns()})


def _package_dir() -> str:
    import cdmp_ros
    return os.path.dirname(os.path.realpath(cdmp_ros.__file__))


def _kernel_dirs() -> Set[str]:
    """Where cdmp_ros writes the kernels it generates at run time (outside the package)."""
    try:
        from cdmp_ros.core.generated import cache_dir, fallback_dir
    except ImportError:  # a version without a kernel cache
        return set()
    return {os.path.realpath(d) for d in (cache_dir(), fallback_dir())}


def _classify(calls, trace: PathTrace) -> None:
    """Sort the ``(co_filename, name, module)`` triples of ``calls`` into ``trace``.

    ``module`` is the ``__name__`` of the frame's globals for code without a file (``<...>``):
    the ``__init__`` that ``dataclasses`` generates for a class of a cdmp_ros module runs
    with that module's globals and is counted as code of its file (``name (generated)``)."""
    pkg = _package_dir()
    top = os.path.dirname(pkg)
    kernels = _kernel_dirs()
    for filename, name, module in calls:
        if filename.startswith('<'):
            mod = sys.modules.get(module or '')
            path = getattr(mod, '__file__', None)
            if path and module.startswith('cdmp_ros.'):
                filename, name = path, f'{name} (generated)'
            elif filename.startswith('<generated') or (module or '').startswith('cdmp_ros'):
                trace.runtime_code.setdefault(filename, set()).add(name)
                continue
            else:
                continue
        real = os.path.realpath(filename)
        if os.path.dirname(real) in kernels:
            trace.runtime_code.setdefault(real, set()).add(name)
            continue
        if not real.startswith(pkg + os.sep):
            continue
        rel = os.path.relpath(real, top).replace(os.sep, '/')
        if name == '<module>':
            trace.imported.add(rel)
        else:
            trace.files.setdefault(rel, set()).add(name)


class _Window:
    """The recording window of a trace, and the profile function that records in it.

    Recorded: the 'call' events of the calling thread from :meth:`open` until the first
    reference published after it (:meth:`on_publish`), and, with ``obstacle``, those of the
    node's tick thread from the moment the obstacle set is in the streamer (the node's
    ``_latency_pending_ns`` is set, under the tick's lock, together with the obstacle set, and
    cleared by the first reference computed with it) until that reference is published.
    """

    def __init__(self, node=None):
        from cdmp_ros.core.streaming.streamer import StreamFlags
        self.COUPLED = int(StreamFlags.COUPLED)
        self.node = node
        self.main = threading.get_ident()
        self.tick = None
        self.on = self.done = False
        #: the calling thread is delivering the obstacle: recorded to the end of the delivery
        #: even if the tick thread published meanwhile (it may wake at its deadline and take
        #: the obstacle before the delivery has woken it)
        self.delivering = False
        self.obstacle = True
        self.calls = set()
        self.coupled = False   # the coupling flag of the reference that closed the window

    def open(self, obstacle: bool) -> None:
        self.calls = set()
        self.obstacle = obstacle
        self.done = False
        self.on = True

    def close(self) -> None:
        self.on = False

    def _pending(self) -> bool:
        return bool(self.node._latency_pending_ns)

    def profile(self, frame, event, arg):
        if event != 'call' or not self.on:
            return
        ident = threading.get_ident()
        if ident == self.main:
            if self.done and not self.delivering:
                return
        elif ident != self.tick or self.done or not self._pending():
            return
        code = frame.f_code
        filename = code.co_filename
        name = getattr(code, 'co_qualname', code.co_name)
        module = None
        if filename.startswith('<'):  # no file: the module of its globals, the class
            module = frame.f_globals.get('__name__')
            obj = frame.f_locals.get('self')
            if obj is not None and code.co_name == '__init__':
                name = f'{type(obj).__qualname__}.__init__'
        self.calls.add((filename, name, module))

    def on_publish(self) -> None:
        """Called by the wrapped ``publish`` before the message goes out."""
        if self.on and not self.done and (not self.obstacle or self._pending()):
            self.coupled = bool(self.node.streamer._coupling_flags & self.COUPLED)
            self.done = True


def measure(sphere: Sequence[float] = DEFAULT_SPHERE, marker: str = 'sphere',
            configs: Sequence[str] = (DEFAULT_CONFIG,), primitive: Optional[str] = None,
            domain_id: Optional[int] = None, timeout: float = WAIT_S,
            tick_thread: bool = False) -> PathTrace:
    """Trace the obstacle path (module docstring) of a streamer node with the parameter files
    ``configs``; ``primitive`` is the JSON text to stream (default :func:`reach_primitive`).

    ``tick_thread``: keep the node's tick thread (as a node process runs by default; its
    ``realtime_priority`` set to 0) instead of ticking from here: the obstacle is delivered
    here as by the executor, the tick thread publishes (woken by the obstacle with
    ``obstacle_wakeup``), and both threads are traced. ``baseline`` is then not measured.

    ``domain_id`` is the rclpy context's (default: ``ROS_DOMAIN_ID``); the environment's
    ``ROS_AUTOMATIC_DISCOVERY_RANGE`` applies (the caller sets LOCALHOST)."""
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from cdmp_ros.core.streaming.streamer import StreamState
    from cdmp_ros.ros.streamer_node import StreamerNode

    cli = ['--ros-args']
    for path in configs:
        cli += ['--params-file', os.path.abspath(path)]
    overrides = [Parameter('joint_states_timeout', value=0.0),
                 Parameter('tick_thread', value=bool(tick_thread))]
    if tick_thread:
        overrides.append(Parameter('realtime_priority', value=0))
    ctx = rclpy.Context()
    init = {} if domain_id is None else {'domain_id': int(domain_id)}
    rclpy.init(context=ctx, **init)
    window = _Window()
    node = None
    gc_was_enabled = gc.isenabled()
    switch_interval = sys.getswitchinterval()  # the node shortens it with the tick thread
    try:
        if tick_thread:  # the tick thread starts in the constructor, with the profiler
            threading.setprofile(window.profile)
        node = StreamerNode(context=ctx, cli_args=cli, parameter_overrides=overrides)
        threading.setprofile(None)
        window.node = node
        window.tick = node.tick_thread.ident if node.tick_thread is not None else None
        st = node.streamer
        published = []   # stamps [ns] of the references
        first = []       # index in published of the first reference after the obstacle
        publish = node.pub.publish

        def recording_publish(msg):
            done = window.done
            window.on_publish()
            if window.done and not done and window.obstacle:
                first.append(len(published))
            published.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            publish(msg)

        node.pub.publish = recording_publish

        def tick_until(pred, what):
            """Tick here (or let the tick thread tick) until ``pred()``."""
            def ticked():
                if not tick_thread:
                    node._locked_tick()
                return pred()
            _wait(ticked, timeout, what)

        # -- streaming, without obstacles ----------------------------------------------------
        text = primitive if primitive is not None else reach_primitive(
            st.joint_names, st.lower, st.upper)
        _deliver(_subscription(node, 'primitive'), serialize_message(String(data=text)))
        # running, not merely active: the tick thread sets ``active`` before it starts the
        # stepper (a soak run read the state in between: "holding: waiting for a primitive")
        try:
            tick_until(lambda: st.active is not None and st.state is StreamState.RUNNING,
                       'the primitive to be prepared and switched in')
        except RuntimeError as exc:
            raise RuntimeError(f'{exc}; the streamer is {st.state.value}: {st.reason}') from None
        n0 = len(published)
        tick_until(lambda: len(published) >= n0 + WARM_TICKS, 'references without obstacles')
        if node.counts['coupled'] or len(node.obstacles) or node._latency_pending_ns:
            raise RuntimeError('coupled, or an obstacle latency pending, before the obstacle')

        trace = PathTrace()
        gc.collect()
        gc.disable()  # no finalizer of unrelated objects in the trace
        # -- a tick without obstacles, the baseline ------------------------------------------
        if not tick_thread:
            window.open(obstacle=False)
            sys.setprofile(window.profile)
            try:
                node._locked_tick()
            finally:
                sys.setprofile(None)
                window.close()
            base = PathTrace()
            _classify(window.calls, base)
            trace.baseline = base.files

        # -- the trace -----------------------------------------------------------------------
        data = serialize_message(obstacle_message(
            node.config.base_frame, sphere, marker, node.get_clock().now().to_msg()))
        obstacles = _subscription(node, 'obstacles')
        before = dict(node.counts)
        rejected = node.gate.values()['rejected_total']
        n_published = len(published)
        latencies = node._obstacle_latency.n
        ticks = node.counts['ticks']
        window.open(obstacle=True)
        sys.setprofile(window.profile)
        try:
            window.delivering = True
            try:
                _deliver(obstacles, data)
            finally:
                window.delivering = False
            tick_until(lambda: window.done, 'the first reference after the obstacle')
        finally:
            sys.setprofile(None)
            window.close()
            if gc_was_enabled:
                gc.enable()
        with node._lock:  # the tick that published it held the lock: it has ended now
            _classify(window.calls, trace)
            trace.ticks = node.counts['ticks'] - ticks
            trace.published = first[0] + 1 - n_published
            trace.coupled = window.coupled
            trace.coupled_ticks = node.counts['coupled'] - before['coupled']
            trace.rejected = node.gate.values()['rejected_total'] - rejected
            trace.latency_taken = node._obstacle_latency.n > latencies
            trace.min_distance = st.min_distance
            trace.coupling_joint = list(st._coupling_joint)
        return trace
    finally:
        threading.setprofile(None)
        sys.setprofile(None)
        if gc_was_enabled:
            gc.enable()
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        # undo the node's process-wide settings (a test process goes on)
        sys.setswitchinterval(switch_interval)
        gc.unfreeze()


def trace_obstacle_path(sphere: Sequence[float] = DEFAULT_SPHERE, marker: str = 'sphere',
                        configs: Sequence[str] = (DEFAULT_CONFIG,),
                        primitive: Optional[str] = None, domain_id: Optional[int] = None,
                        timeout: float = WAIT_S) -> Dict[str, Set[str]]:
    """The files of the obstacle path -> their functions that ran (:func:`measure`); raises
    if the obstacle did not act on the first reference (move it closer to the arm)."""
    trace = measure(sphere, marker, configs, primitive, domain_id, timeout)
    if not trace.acted:
        raise RuntimeError(f'the obstacle did not act on the first reference: {trace}')
    return trace.files


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split('\n')[0],
        epilog='ROS: the in-process context uses ROS_DOMAIN_ID (or --domain-id) and discovers '
               'on localhost only (ROS_AUTOMATIC_DISCOVERY_RANGE is set to LOCALHOST unless it '
               'is OFF). Exit code 1 if the obstacle did not act on the first reference.')
    parser.add_argument('--sphere', nargs=4, type=float, metavar=('X', 'Y', 'Z', 'R'),
                        default=DEFAULT_SPHERE,
                        help='obstacle centre and radius [m], base frame (default: '
                             '%(default)s); a cube has edge 2 R')
    parser.add_argument('--marker', choices=('sphere', 'cube'), default='sphere',
                        help='marker type of the obstacle (default: %(default)s)')
    parser.add_argument('--config', nargs='+', default=[DEFAULT_CONFIG], metavar='FILE',
                        help='streamer parameter file(s), in order (default: '
                             'config/streamer.yaml); joint_states_timeout and tick_thread are '
                             'overridden')
    parser.add_argument('--primitive', metavar='FILE',
                        help='primitive file (JSON) to stream (default: a reach CDMP)')
    parser.add_argument('--tick-thread', action='store_true',
                        help="keep the node's tick thread (a node process's default) and "
                             'trace it too, instead of ticking from the calling thread')
    parser.add_argument('--functions', action='store_true',
                        help='list the functions of each file that ran on the path')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS domain id of the context (default: ROS_DOMAIN_ID, else 44)')
    args = parser.parse_args(argv)
    if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'OFF':
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_DOMAIN_ID', '44')      # a private domain, never 0
    os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    primitive = None
    if args.primitive:
        with open(args.primitive) as f:
            primitive = f.read()
    trace = measure(args.sphere, args.marker, args.config, primitive, args.domain_id,
                    tick_thread=args.tick_thread)
    base = trace.baseline or {}
    print(f'{len(trace.files)} files of cdmp_ros on the obstacle -> joint_reference path '
          f'({trace.published} reference(s) published, coupling applied: {trace.coupled}, '
          f'min distance {trace.min_distance:.4f} m); * = also on a tick without obstacles:')
    for path in sorted(trace.files):
        print(f'  {path}{" *" if path in base else ""}')
        if args.functions:
            for name in sorted(trace.files[path]):
                print(f'      {name}{" *" if name in base.get(path, ()) else ""}')
    if trace.imported:
        print('module bodies run (lazy imports, not counted): '
              + ', '.join(sorted(trace.imported)))
    for name, funcs in sorted(trace.runtime_code.items()):
        print(f'kernel generated at run time (not counted): {name}: '
              f'{", ".join(sorted(funcs))}')
    if not trace.acted:
        print(f'the obstacle did not act on the first reference (coupled {trace.coupled}, '
              f'latency taken {trace.latency_taken}, rejected {trace.rejected}): move it '
              'closer to the arm', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
