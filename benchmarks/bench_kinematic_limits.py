"""What a real arm's controller would see: the published references against the Panda's limits.

Three parts, each judged on the ``joint_reference`` messages themselves, differenced on their
own header stamps (:func:`cdmp_ros.core.run_metrics.kinematic_report`), against the limits the
nodes run with (the URDF merged with Franka's datasheet, ``config/joint_limits/panda.yaml``):

1. ``demos``: ``cdmp demo`` and ``cdmp demo --kind promp`` at each ``--rates`` (the whole graph,
   its bag, its summary: ticks over each limit and the worst ratio, contacts, the sim's reflex
   errors, obstacle -> first changed reference latency p50/p99);
2. ``storm``: sim, streamer, adapter and learner from ``config/*.yaml`` as processes, then for
   ``--duration`` s a bounded publisher (loopback only) sends valid goals (half inside the
   limits, half up to 0.5 rad beyond them) and spheres that appear next to the arm, jump
   3-15 cm and vanish, one event every 0.3-1.2 s (seeded); every reference is recorded, and
   every contact the sim reports is printed with its links and the events of the 3 s before
   it; ``--streamer-param NAME:=VALUE`` (repeatable) adds streamer parameters;
3. ``tick``: the streamer's tick cost in-process (a 7-joint CDMP reach with the obstacle
   coupling of one sphere next to the hand), with the output stage on and off, for the
   coupling of config/streamer.yaml and for the code's defaults.

``--stage off`` runs parts 1-2 with the streamer's ``output_stage: false`` (the references as
integrated, before this stage existed). Every ROS process runs with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_kinematic_limits.py [--parts demos storm tick]
        [--rates 500 1000] [--duration 45] [--seed 0] [--domain 75] [--stage on|off]
        [--streamer-param NAME:=VALUE ...]
"""
import argparse
import os
import sys
import tempfile
import threading
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_flood import NODES, start_nodes, stop_nodes  # noqa: E402

ORDERS = ('velocity', 'acceleration', 'jerk')
STARTUP = 90.0


def panda_limits_in_force():
    from cdmp_ros.core.joint_limits import shipped_limits
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.ros.robot_model import default_urdf_path
    chain = panda_chain(default_urdf_path())
    return chain, shipped_limits(chain.joint_names, chain.lower, chain.upper,
                                 chain.velocity_limits, 'urdf')


def row(name, rep, extra):
    cells = [name] + [f'{rep[o]["over"]} ({rep[o]["worst_ratio"]:.3f})' for o in ORDERS]
    return '| ' + ' | '.join(cells + [str(rep['position_outside'])] + extra) + ' |'


HEADER = ('| stream | ticks over velocity (worst ratio) | over acceleration (worst) | over jerk '
          '(worst) | positions outside | references | contacts | reflex errors | obstacle -> '
          'reference p50 / p99 [ms] |\n|---|---|---|---|---|---|---|---|---|')


# -- part 1: the demos --------------------------------------------------------------------------
def run_demos(args, limits):
    from cdmp_ros.cli.demo_run import run_demo
    from cdmp_ros.core.run_metrics import kinematic_report
    from cdmp_ros.cli.demo_run import _joint_arrays
    os.environ['ROS_DOMAIN_ID'] = str(args.domain)
    lines = []
    for rate in args.rates:
        for kind in ('cdmp', 'promp'):
            out = os.path.join(args.out, f'demo_{kind}_{rate:g}')
            os.makedirs(out, exist_ok=True)
            t0 = time.monotonic()
            with open(os.path.join(out, 'demo.log'), 'w') as log:
                s = run_demo(out, kind=kind, log=log, streamer_parameters={
                    'rate': float(rate), 'output_stage': args.stage == 'on'})
            S, Q, names = _joint_arrays(os.path.join(out, 'bag'), '/joint_reference',
                                        header_stamps=True)
            rep = kinematic_report(S, Q, limits.subset(names))
            lines.append(row(f'`cdmp demo{" --kind promp" if kind == "promp" else ""}` at '
                             f'{rate:g} Hz', rep,
                             [str(rep['samples']), f'{s["contacts"]:.0f}',
                              f'{s["reflex_errors"]:.0f}',
                              f'{s["latency_ms_p50"]:.2f} / {s["latency_ms_p99"]:.2f}']))
            print(lines[-1], f'({time.monotonic() - t0:.0f} s)', flush=True)
    return lines


# -- part 2: the storm --------------------------------------------------------------------------
class Recorder:
    """joint_reference (stamp, positions) and the latest diagnostics of every node."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC
        from sensor_msgs.msg import JointState
        from cdmp_ros.ros import qos
        self.lock = threading.Lock()
        self.status = {}
        self.stamps, self.Q = [], []
        #: (time.monotonic(), the sim's status message) whenever it names a contact
        self.contact_log = []
        node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._diag, 200)
        node.create_subscription(JointState, 'joint_reference', self._ref, qos.REFERENCE)

    def _diag(self, msg):
        with self.lock:
            for s in msg.status:
                kv = {x.key: x.value for x in s.values}
                kv['_message'] = s.message
                self.status[s.name] = kv
                if s.name == 'sim: state' and '; contact ' in s.message:
                    self.contact_log.append((time.monotonic(), s.message.split('; contact ')[1]))

    def _ref(self, msg):
        with self.lock:
            self.stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            self.Q.append(list(msg.position))

    def get(self, name, key, default=None):
        with self.lock:
            return self.status.get(name, {}).get(key, default)

    def recent_q(self):
        """The last reference and its velocity (difference of the last two)."""
        with self.lock:
            if len(self.Q) < 2:
                return np.array(self.Q[-1]), np.zeros(len(self.Q[-1]))
            dt = max((self.stamps[-1] - self.stamps[-2]) * 1e-9, 1e-4)
            return np.array(self.Q[-1]), (np.array(self.Q[-1]) - np.array(self.Q[-2])) / dt

    def last_q(self):
        with self.lock:
            return np.array(self.Q[-1]) if self.Q else None


#: Points along the Panda from the shoulder to the fingertips whose braking distances a new
#: sphere respects, and the radius [m] around them that the arm's links fill (the largest
#: collision capsule: 10.9 cm at the hand), for the first guess of a place only.
ARM_POINTS = ('panda_link2', 'panda_link3', 'panda_link4', 'panda_link5', 'panda_link6',
              'panda_link7', 'panda_hand', 'ee')
ARM_RADIUS = 0.11
#: Extra distance [m] a new sphere keeps beyond what the arm needs to stop.
CLEARANCE = 0.03


def arm_capsules():
    """The arm as the demo driver sees it: capsules fitted to the collision geometry of its
    links, and the fingers' capsule."""
    from cdmp_ros.core.demo_robot import DemoRobot
    from cdmp_ros.ros.robot_model import default_urdf_path
    return DemoRobot('panda', default_urdf_path()).capsules[0]


def place_sphere(rng, arm, state, limits, radius, near=None, tries=50):
    """A sphere next to the arm that the arm can still avoid within its limits: its surface
    at least the braking distance of every arm point (at the arm's current motion,
    :func:`cdmp_ros.core.coupling.braking.braking_distance`) plus ``CLEARANCE`` away from
    the capsules around the arm's links and fingers (``arm``, :func:`arm_capsules`), and at
    most 20 cm beyond that; ``near``: a jump of 3-15 cm from there. None if no place is found
    in ``tries`` draws."""
    from cdmp_ros.core.coupling.braking import braking_distance
    from cdmp_ros.core.kinematics import PointOfInterest
    pts = [PointOfInterest(p) for p in ARM_POINTS]
    q, qd = state
    X = arm.chain.forward(q[None], pts)[0]
    need = float(np.max(braking_distance(arm.chain, q, qd, limits.acceleration, limits.jerk,
                                         pts))) + CLEARANCE
    for _ in range(tries):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        if near is None:
            c = X[int(rng.integers(len(X)))] + d * (need + ARM_RADIUS + radius
                                                    + rng.uniform(0.0, 0.2))
        else:
            c = near + d * rng.uniform(0.03, 0.15)
        gap = arm.sphere_clearance(q, c, radius)
        if need <= gap <= need + 0.2 and c[2] > 0.05:
            return c
    return None


def run_storm(args, rate, chain, limits):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import Marker, MarkerArray
    from cdmp_ros.core.run_metrics import kinematic_report
    from cdmp_ros.ros import qos

    rng = np.random.default_rng(args.seed)
    arm = arm_capsules()
    logdir = tempfile.mkdtemp(prefix='bench_kinematic_limits_')
    streamer = {'rate': float(rate), 'output_stage': str(args.stage == 'on').lower(),
                'diagnostics_period': 0.5}
    streamer.update(kv.split(':=', 1) for kv in args.streamer_param)
    procs = start_nodes(args.domain, REPO, logdir, {'streamer': streamer})
    rclpy.init(domain_id=args.domain)
    node = rclpy.create_node('kinematic_storm')
    rec = Recorder(node)
    goal_pub = node.create_publisher(JointState, 'goal', qos.COMMAND)
    obs_pub = node.create_publisher(MarkerArray, 'obstacles', qos.COMMAND)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    stop = threading.Event()
    spinner = threading.Thread(target=lambda: [executor.spin_once(timeout_sec=0.05)
                                               for _ in iter(stop.is_set, True)], daemon=True)
    spinner.start()
    counts = {'goal inside': 0, 'goal beyond': 0, 'sphere appears': 0, 'sphere jumps': 0,
              'spheres cleared': 0, 'no room': 0}
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < STARTUP and (
                rec.get('streamer: state', 'primitive', 'none') == 'none'
                or rec.last_q() is None):
            if any(p.poll() is not None for p in procs.values()):
                raise SystemExit(f'a node exited during start-up; logs in {logdir}')
            time.sleep(0.2)
        if rec.last_q() is None:
            raise SystemExit(f'no joint_reference within {STARTUP:g} s; logs in {logdir}')
        n0 = len(rec.Q)
        base = {k: float(rec.get('sim: state', k, '0') or 0)
                for k in ('contacts_since_start', 'reflex_errors')}
        print(f'storm at {rate:g} Hz for {args.duration:g} s (seed {args.seed})', flush=True)
        t_start = time.monotonic()
        end = t_start + args.duration
        sphere = None
        events = []
        while time.monotonic() < end:
            time.sleep(float(rng.uniform(0.3, 1.2)))
            u = rng.random()
            if u < 0.4:
                beyond = rng.random() < 0.5
                if beyond:
                    g = np.where(rng.random(7) < 0.5, chain.lower - rng.uniform(0, 0.5, 7),
                                 chain.upper + rng.uniform(0, 0.5, 7))
                else:
                    g = rng.uniform(chain.lower + 0.2 * (chain.upper - chain.lower),
                                    chain.upper - 0.2 * (chain.upper - chain.lower))
                goal_pub.publish(JointState(name=list(chain.joint_names),
                                            position=[float(v) for v in g]))
                counts['goal beyond' if beyond else 'goal inside'] += 1
                events.append((time.monotonic(), 'goal beyond' if beyond else 'goal inside'))
                continue
            arr = MarkerArray()
            if u < 0.9 or sphere is None:
                radius = float(rng.uniform(0.03, 0.07))
                jump = sphere is not None and u >= 0.6
                new = place_sphere(rng, arm, rec.recent_q(), limits, radius,
                                   sphere if jump else None)
                if new is None:
                    counts['no room'] += 1
                    continue
                sphere = new
                counts['sphere jumps' if jump else 'sphere appears'] += 1
                events.append((time.monotonic(), f'sphere r={radius:.3f} at '
                               f'({sphere[0]:.2f}, {sphere[1]:.2f}, {sphere[2]:.2f})'
                               + (' (jump)' if jump else '')))
                m = Marker(type=Marker.SPHERE, action=Marker.ADD, id=1, ns='storm')
                m.header.frame_id = 'panda_link0'
                m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, sphere)
                m.pose.orientation.w = 1.0
                m.scale.x = m.scale.y = m.scale.z = 2.0 * radius
                arr.markers.append(m)
            else:
                arr.markers.append(Marker(action=Marker.DELETEALL))
                sphere = None
                counts['spheres cleared'] += 1
            t = time.time_ns()
            for m in arr.markers:
                m.header.stamp.sec, m.header.stamp.nanosec = t // 10**9, t % 10**9
            obs_pub.publish(arr)
        time.sleep(2.0)
        alive = {n: procs[n].poll() is None for n in NODES}
    finally:
        stop.set()
        spinner.join(timeout=5)
        stop_nodes(procs)
        node.destroy_node()
        rclpy.shutdown()
    with rec.lock:
        S, Q = np.array(rec.stamps[n0:]), np.array(rec.Q[n0:])
    order = np.argsort(S, kind='stable')
    S, Q = S[order], Q[order]
    keep = np.concatenate([[True], np.diff(S) > 0])
    rep = kinematic_report(S[keep], Q[keep], limits)
    contacts = float(rec.get('sim: state', 'contacts_since_start', 'nan') or 'nan') - \
        base['contacts_since_start']
    reflex = float(rec.get('sim: state', 'reflex_errors', 'nan') or 'nan') - \
        base['reflex_errors']
    lat = (rec.get('streamer: state', 'obstacle_latency_ms_p50', 'nan'),
           rec.get('streamer: state', 'obstacle_latency_ms_p99', 'nan'))
    line = row(f'storm, {args.duration:g} s at {rate:g} Hz', rep,
               [str(rep['samples']), f'{contacts:.0f}', f'{reflex:.0f}',
                f'{float(lat[0]):.2f} / {float(lat[1]):.2f}'])
    print(line, flush=True)
    for t, pairs in rec.contact_log:
        before = [f'{e - t_start:.2f} s {what}' for e, what in events if t - 3.0 < e <= t]
        print(f'  contact at {t - t_start:6.2f} s: {pairs}; events of the 3 s before: '
              f'{before}', flush=True)
    print(f'  events: {counts}; alive at the end: {alive}; references missed by the '
          f'recording: {int(np.sum(np.diff(S) > round(1e9 / rate)))}; logs {logdir}',
          flush=True)
    return [line]


# -- part 3: the tick ---------------------------------------------------------------------------
def tick_cost(args, chain, limits, n_ticks=5000):
    import dataclasses
    import itertools
    from cdmp_ros.cli.cmd_bringup import NodeSpec, spec_streamer_configs
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.kinematics import PointOfInterest
    from cdmp_ros.core.coupling.obstacle import Sphere
    from cdmp_ros.core.primitive_io import dumps_primitive
    from cdmp_ros.core.streaming.config import StreamerConfig
    from cdmp_ros.core.streaming.primitives import prepare_primitive
    from cdmp_ros.core.streaming.streamer import (ReferenceStreamer, coupling_of,
                                                  streamer_coupling)
    from cdmp_ros.ros.robot_model import load_collision_capsules
    lines = ['| streamer tick, in-process | coupling | rate [Hz] | mean [us] | p99 [us] | '
             'max [us] |', '|---|---|---|---|---|---|']
    T = np.linspace(0.0, 2.0, 401)
    q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    q1 = np.array([0.8, 0.2, -0.4, -1.6, 0.3, 1.9, 1.2])
    s = 10 * (T / 2) ** 3 - 15 * (T / 2) ** 4 + 6 * (T / 2) ** 5
    prim = CDMP(limits.lower, limits.upper, joint_names=chain.joint_names).fit(
        T, q0 + s[:, None] * (q1 - q0))
    text = dumps_primitive(prim)
    shipped = spec_streamer_configs(NodeSpec('streamer', 'streamer', (
        os.path.join(REPO, 'config', 'streamer.yaml'),)))
    capsules = load_collision_capsules('', shipped[''].coupling_capsule_links, chain=chain)
    for rate, stage, which in itertools.product(args.rates, (True, False),
                                                ('config/streamer.yaml', 'code defaults')):
        if which == 'code defaults':
            cfg = StreamerConfig(rate=float(rate), joint_states_timeout=0.0, output_stage=stage)
            coupling = streamer_coupling(chain, cfg)
        else:
            cfg = dataclasses.replace(shipped[''], rate=float(rate), joint_states_timeout=0.0,
                                      output_stage=stage)
            coupling = coupling_of(chain, {**shipped, '': cfg}, capsules)
        st = ReferenceStreamer(limits.lower, limits.upper, cfg, coupling=coupling,
                               limits=limits)
        prep = prepare_primitive(text, chain.joint_names, cfg.dt, limits.lower,
                                 limits.upper, limits.velocity)
        st.activate(prep, 0.0)
        x = chain.forward(q0[None], [PointOfInterest('ee')])[0, 0]
        st.obstacles = [Sphere(x + np.array([0.1, 0.05, 0.0]), 0.05)]
        times = np.empty(n_ticks)
        for k in range(n_ticks):
            t = time.perf_counter()
            st.advance(1, k * cfg.dt)
            times[k] = time.perf_counter() - t
            if k % 1000 == 999:  # a fresh reach keeps the stage and coupling busy
                st.activate(dataclasses.replace(prep), k * cfg.dt)
        us = times * 1e6
        lines.append(f'| output stage {"on" if stage else "off"} | {which} | {rate:g} | '
                     f'{us.mean():.0f} | {np.percentile(us, 99):.0f} | {us.max():.0f} |')
        print(lines[-1], flush=True)
    return lines


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split('\n', 1)[1])
    ap.add_argument('--parts', nargs='+', default=['demos', 'storm', 'tick'],
                    choices=('demos', 'storm', 'tick'))
    ap.add_argument('--rates', nargs='+', type=float, default=[500.0, 1000.0])
    ap.add_argument('--duration', type=float, default=45.0, help='storm duration [s]')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--domain', type=int, default=75)
    ap.add_argument('--stage', choices=('on', 'off'), default='on',
                    help="the streamer's output_stage in parts demos and storm")
    ap.add_argument('--streamer-param', action='append', default=[], metavar='NAME:=VALUE',
                    help='one more streamer parameter in the storm (repeatable)')
    ap.add_argument('--out', default=os.path.join(tempfile.gettempdir(), 'bench_kinematic'))
    args = ap.parse_args()
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ['ROS_DOMAIN_ID'] = str(args.domain)
    os.environ['AMENT_PREFIX_PATH'] = sys.prefix
    chain, limits = panda_limits_in_force()
    print(f'limits: {limits.describe()}\n', flush=True)
    lines = []
    if 'demos' in args.parts:
        lines += run_demos(args, limits)
    if 'storm' in args.parts:
        for rate in args.rates:
            lines += run_storm(args, rate, chain, limits)
    print(f'\n## kinematic limits, output stage {args.stage}\n')
    if lines:
        print(HEADER)
        print('\n'.join(lines))
    if 'tick' in args.parts:
        print()
        print('\n'.join(tick_cost(args, chain, limits)))


if __name__ == '__main__':
    main()
