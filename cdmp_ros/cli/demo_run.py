"""``cdmp demo``: the node graph end to end, and its summary read back from the recorded bag.

1. start ``config/graphs/demo.yaml`` (sim, streamer at 500 Hz, adapter, learner fitting a CDMP
   from ``bags/panda_reach``, recorder) as processes; ``--kind dual``:
   ``config/graphs/dual_demo.yaml`` (two Pandas, a ProMP of both arms from ``bags/dual_panda``,
   the adapter keeping the arms ``arm_clearance`` apart);
2. run the scripted user :mod:`cdmp_ros.ros.demo_driver` (an obstacle dropped into the path
   mid-motion, then a goal change, then a sim snapshot);
3. stop the graph, read the bag, and write ``summary.json``, ``summary.md``, ``joints.png``,
   ``ee_path.png`` (and the snapshot PNG) to ``--out``.

Figures and where they come from:

- ``min_obstacle_distance_m``: the sim's ``min_obstacle_distance_since_start_m`` (pybullet
  closest points between every robot link and the obstacle), from its last diagnostics, and
  ``closest_pair`` the ``link/obstacle`` it was measured on; of two arms,
  ``min_robot_distance_m`` the sim's ``min_robot_distance_since_start_m`` (closest points
  between the links of the two arms) and ``min_hand_distance_m`` the least distance between
  the hands (tool centre points) at the measured ``joint_states``;
- ``max_limit_usage``: max over joints and samples of ``|q - centre| / half_range`` of the
  measured ``joint_states`` in the bag (``reference_limit_usage``: same for
  ``joint_reference``); above 1 is outside a limit. ``limit_violations``: the sim's count of
  physics steps with a joint further than its ``limit_tolerance`` (1e-4 rad) outside a limit,
  and ``max_limit_excess_rad`` the largest measured excess beyond a limit (0 when inside):
  when the streamer holds a joint close to its limit, the tracking controller may overshoot
  the reference by some 1e-5 rad, which reads as a usage of 1.00002 but is no violation;
- ``latency_ms_p50/p99``: the streamer's obstacle-message-stamp to first-reference latency over
  the dropped obstacle's messages (its diagnostics);
- ``tracking_error_rad``: largest |reference - measured| joint error at the ``joint_states``
  samples (reference = the latest one before each sample), from the bag;
- ``messages_recorded``: messages in the bag (verified, every CRC);
- ``kinematic_limits``: the ``joint_reference`` stream as the robot's controller sees it,
  differenced on its header stamps (:func:`cdmp_ros.core.run_metrics.kinematic_report`):
  per order (velocity, acceleration, jerk) the references over the Panda's limits by more
  than 2 % and the worst ratio to the limit; ``reflex_errors``: the sim's count of received
  references that broke a limit (what would stop a real Panda).
"""
import json
import os
import signal
import subprocess
import sys
import time
from typing import Dict, List

import numpy as np

from cdmp_ros.bag import BagReader, bag_info
from cdmp_ros.bag.cdr import decode_joint_state
from cdmp_ros.cli.cmd_bringup import (Bringup, Terminated, load_graph, package_config_dir,
                                      signal_flag)
from cdmp_ros.core.errors import CdmpError
from cdmp_ros.core.joint_limits import shipped_limits
from cdmp_ros.core.run_metrics import kinematic_report, tracking_error
from cdmp_ros.core.dmp.dmp import limit_usage
from cdmp_ros.core.topics import DIAGNOSTICS_TOPIC

#: What the learner fits: ``cdmp`` (obstacle drop and goal change) or ``promp`` (constrained
#: adaptation on every obstacle message).
KINDS = ('cdmp', 'promp', 'dual')
#: The robot, graph and learner of each kind.
ROBOT = {'cdmp': 'panda', 'promp': 'panda', 'dual': 'dual_panda'}
GRAPH = {'cdmp': 'demo.yaml', 'promp': 'demo.yaml', 'dual': 'dual_demo.yaml'}
LEARNER = {'cdmp': 'cdmp', 'promp': 'promp', 'dual': 'promp'}
#: Topics the demo records.
RECORDED = ['/joint_reference', '/joint_states', '/obstacles', '/goal', '/primitive',
            '/adapted_primitive', '/ee_pose', DIAGNOSTICS_TOPIC, '/visualization']


def _joint_arrays(bag: str, topic: str, header_stamps: bool = False):
    """Times [s] (receipt, or with ``header_stamps`` the messages' own stamps [ns]),
    positions and joint names of a JointState topic, in time order."""
    T, Q, names = [], [], None
    for m in BagReader(bag).messages([topic]):
        js = decode_joint_state(m.data)
        if js.position.size == 0:
            continue
        if names is None:
            names = js.name
        if js.name != names:  # reorder by name (a recorded robot need not use our order)
            idx = [js.name.index(n) for n in names]
            pos = js.position[idx]
        else:
            pos = js.position
        T.append(js.stamp_ns if header_stamps else m.log_time * 1e-9)
        Q.append(pos)
    if not T:
        raise CdmpError(f'{bag}: no {topic} messages were recorded')
    order = np.argsort(np.asarray(T), kind='stable')
    return np.asarray(T)[order], np.asarray(Q)[order], list(names)


def _float(values: Dict[str, str], key: str) -> float:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return float('nan')


def _status(diag: Dict, prefix: str) -> Dict[str, str]:
    for name, st in diag.items():
        if name.split(':')[0].strip().lstrip('/').startswith(prefix):
            return st['values']
    return {}


def summarise(out: str, bag: str, driver: Dict, limits, robot=None) -> Dict:
    """The summary dict (see the module docstring); ``limits`` the robot's
    :class:`~cdmp_ros.core.joint_limits.KinematicLimits`; ``robot`` its
    :class:`~cdmp_ros.core.demo_robot.DemoRobot` (two arms: the distances between them)."""
    lower, upper = limits.lower, limits.upper
    info = bag_info(bag)
    T_ref, Q_ref, _ = _joint_arrays(bag, '/joint_reference')
    T, Q, names = _joint_arrays(bag, '/joint_states')
    track = tracking_error(T_ref, Q_ref, T, Q)
    sim = _status(driver.get('diagnostics', {}), 'sim')
    streamer = _status(driver.get('diagnostics', {}), 'streamer')
    counts = {t['name']: t['count'] for t in info['topics']}
    # the references as the robot's controller sees them: differenced on their own stamps
    S_ref, Q_stamped, ref_names = _joint_arrays(bag, '/joint_reference', header_stamps=True)
    kin = kinematic_report(S_ref, Q_stamped, limits.subset(ref_names))
    arms = {}
    if robot is not None and robot.n_arms > 1:
        H = robot.hands(_in_order(Q, names, robot.joint_names))
        arms = {'min_robot_distance_m': _float(sim, 'min_robot_distance_since_start_m'),
                'min_hand_distance_m': float(np.linalg.norm(H[:, 0] - H[:, 1], axis=-1).min())}
    return {
        **arms,
        'kinematic_limits': kin,
        'reflex_errors': _float(sim, 'reflex_errors'),
        'min_obstacle_distance_m': _float(sim, 'min_obstacle_distance_since_start_m'),
        'closest_pair': sim.get('closest_pair_since_start', ''),
        'contacts': _float(sim, 'contacts_since_start'),
        'max_limit_usage': limit_usage(Q, lower, upper),
        'reference_limit_usage': limit_usage(Q_ref, lower, upper),
        'limit_violations': _float(sim, 'limit_violations'),
        'max_limit_excess_rad': float(max(0.0, np.max(np.asarray(lower) - Q),
                                          np.max(Q - np.asarray(upper)))),
        'latency_ms_p50': _float(streamer, 'obstacle_latency_ms_p50'),
        'latency_ms_p99': _float(streamer, 'obstacle_latency_ms_p99'),
        'latency_samples': _float(streamer, 'obstacle_latency_n'),
        'tracking_error_rad': track['max_rad'],
        'tracking_error_rms_rad': track['rms_rad'],
        'messages_recorded': info['message_count'],
        'messages_by_topic': counts,
        'reference_rate_hz': (len(T_ref) - 1) / (T_ref[-1] - T_ref[0]) if len(T_ref) > 1
        else 0.0,
        'bag': os.path.abspath(bag),
        'snapshot': driver.get('snapshot'),
        'events_s': {k: (v - info['starting_time_ns']) * 1e-9
                     for k, v in driver.get('events_ns', {}).items() if isinstance(v, int)},
        'joint_names': names,
        'plots': [os.path.join(out, 'joints.png'), os.path.join(out, 'ee_path.png')],
    }


def _in_order(Q, names: List[str], order: List[str]):
    """Columns of ``Q`` (named ``names``) in the order ``order``."""
    return np.asarray(Q)[:, [list(names).index(n) for n in order]]


def plot(out: str, bag: str, driver: Dict, lower, upper, robot) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    T_ref, Q_ref, _ = _joint_arrays(bag, '/joint_reference')
    T, Q, names = _joint_arrays(bag, '/joint_states')
    t0 = min(T_ref[0], T[0])
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 1.6 * len(names)), sharex=True)
    for j, ax in enumerate(axes):
        ax.plot(T_ref - t0, Q_ref[:, j], label='joint_reference')
        ax.plot(T - t0, Q[:, j], '--', label='joint_states')
        for lim in (lower[j], upper[j]):
            ax.axhline(lim, color='r', lw=0.8)
        ax.set_ylabel(names[j].replace('panda_', ''), fontsize=8)
        for k, v in driver.get('events_ns', {}).items():
            if isinstance(v, int) and k in ('drop_start', 'goal_change'):
                ax.axvline(v * 1e-9 - t0, color='k', ls=':', lw=0.8)
    axes[0].legend(fontsize=7, loc='upper right')
    axes[-1].set_xlabel('time [s] (dotted: obstacle drop, goal change; red: limits)')
    fig.tight_layout()
    fig.savefig(os.path.join(out, 'joints.png'), dpi=90)
    plt.close(fig)

    H = robot.hands(_in_order(Q, names, robot.joint_names))            # (n, arms, 3)
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection='3d')
    planned = driver.get('planned_hand_paths') or [driver.get('planned_path')]
    for arm in range(robot.n_arms):
        which = f' {arm + 1}' if robot.n_arms > 1 else ''
        ax.plot(*H[:, arm].T, label=f'hand{which} (measured)')
        if arm < len(planned) and planned[arm]:
            ax.plot(*np.asarray(planned[arm]).T, ':', label=f'hand{which} planned (no '
                    'obstacle)')
    obs = driver.get('obstacle', {})
    if obs.get('center'):
        c, r = np.asarray(obs['center']), obs['radius']
        u, v = np.mgrid[0:2 * np.pi:16j, 0:np.pi:8j]
        ax.plot_wireframe(c[0] + r * np.cos(u) * np.sin(v), c[1] + r * np.sin(u) * np.sin(v),
                          c[2] + r * np.cos(v), color='r', lw=0.5)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_zlabel('z [m]')
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(out, 'ee_path.png'), dpi=90)
    plt.close(fig)


def markdown(s: Dict) -> str:
    rows = [('minimum robot-obstacle distance', f'{s["min_obstacle_distance_m"] * 100:.2f} cm'
             f' ({s.get("closest_pair") or "no obstacle"})'),
            ('contacts', f'{s["contacts"]:.0f}'),
            *([('minimum distance between the arms (links, sim) / hands (measured)',
                f'{s["min_robot_distance_m"] * 100:.2f} / {s["min_hand_distance_m"] * 100:.2f}'
                ' cm')] if 'min_hand_distance_m' in s else []),
            ('largest joint-limit usage (measured)', f'{s["max_limit_usage"]:.3f}'),
            ('largest joint-limit usage (reference)', f'{s["reference_limit_usage"]:.3f}'),
            ('limit violations (sim, beyond 1e-4 rad)', f'{s["limit_violations"]:.0f}'),
            ('obstacle -> reference latency p50 / p99',
             f'{s["latency_ms_p50"]:.2f} / {s["latency_ms_p99"]:.2f} ms '
             f'({s["latency_samples"]:.0f} messages)'),
            ('tracking error max / rms', f'{s["tracking_error_rad"]:.4f} / '
                                         f'{s["tracking_error_rms_rad"]:.4f} rad'),
            ('reference rate', f'{s["reference_rate_hz"]:.1f} Hz'),
            ('worst velocity / acceleration / jerk of the references, to the limit',
             ' / '.join(f'{s["kinematic_limits"][k]["worst_ratio"]:.3f}'
                        for k in ('velocity', 'acceleration', 'jerk'))
             + f' ({s["kinematic_limits"]["samples"]} references, differenced on their '
               'stamps)'),
            ('reflex errors (sim)', f'{s["reflex_errors"]:.0f}'),
            ('messages recorded', f'{s["messages_recorded"]}'),
            ('bag', s['bag'])]
    p = s.get('promp')
    if p:
        lat = p['adaptation_latency_ms']
        rows[-1:-1] = [
            ('constrained adaptations after the drop', f'{p["adaptations"]}'),
            ('obstacle -> first adapted reference', (
                f'{np.median(lat):.1f} ms median, {max(lat):.1f} ms max ({len(lat)} '
                'adaptations switched in)') if lat else 'not reported')]
        for prefix, what, tail in (
                ('', f'P(a hand or an avoided link within '
                 f'{p["violation_margin_m"] * 100:.0f} cm of the sphere)',
                 lambda v: f'{v["n_samples"]} samples'),
                ('arm_', f'P(two points of different arms within '
                 f'{p.get("arm_clearance_m", 0.0) * 100:.0f} cm)',
                 lambda v: f'mean path {v["min_arm_distance_mean_path_m"] * 100:.1f} cm apart')):
            for label in ('prior', 'adapted'):
                v = p.get(f'{label}_{prefix}violation')
                if v:
                    rows[-1:-1] = [(f'{what}, {label}, sampled',
                                    f'trajectory {v["trajectory"]:.4f} (95 % bound '
                                    f'{v["trajectory_upper95"]:.4f}), per step max '
                                    f'{v["per_step_max"]:.4f}; {tail(v)}')]
        laws = p.get('adapted_laws')
        if laws:
            rows[-1:-1] = [('probability laws of the last adaptation', '; '.join(
                f'{law}: {", ".join(names)}' for law, names in laws.items()))]
    lines = ['| quantity | value |', '|---|---|'] + [f'| {a} | {b} |' for a, b in rows]
    return '\n'.join(lines) + '\n'


def demo_environment() -> Dict[str, str]:
    """Localhost discovery and a private domain unless the caller chose them."""
    env = {}
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE',
                                                          'LOCALHOST')
    env['ROS_DOMAIN_ID'] = os.environ.get('ROS_DOMAIN_ID', '73')
    env['AMENT_PREFIX_PATH'] = os.environ.get('AMENT_PREFIX_PATH', sys.prefix)
    return env


def run_demo(out: str, timeout: float = 45.0, graph_file: str = None,
             driver_args: List[str] = (), log=None, kind: str = 'cdmp',
             streamer_parameters: Dict = None) -> Dict:
    """Run the demo; return the summary (also written to ``out``).

    ``kind``: ``cdmp`` (the learner fits a CDMP; obstacle drop, then a goal change),
    ``promp`` (the learner fits a ProMP, every obstacle message triggers a constrained
    adaptation that the streamer follows; :mod:`cdmp_ros.cli.demo_promp`) or ``dual`` (as
    ``promp`` on two Pandas: the sphere lands between the hands, and each adaptation also
    keeps the arms apart).
    ``streamer_parameters``: more parameters of the streamer (e.g. ``{'rate': 1000.0}``)."""
    if kind not in KINDS:
        raise CdmpError(f'demo: kind: expected one of {list(KINDS)}, got {kind!r}')
    from cdmp_ros.core.demo_robot import DemoRobot
    from cdmp_ros.sim.robot_specs import PANDA_URDF

    log = log if log is not None else sys.stdout
    out = os.path.abspath(out)
    os.makedirs(out, exist_ok=True)
    bag = os.path.join(out, 'bag')
    if os.path.exists(bag):
        import shutil
        shutil.rmtree(bag)
    robot = DemoRobot(ROBOT[kind], PANDA_URDF)
    graph = load_graph(graph_file or os.path.join(package_config_dir(), 'graphs', GRAPH[kind]))
    overrides = {'recorder': {'output': bag, 'topics': RECORDED},
                 'sim': {'snapshot_path': os.path.join(out, 'snapshot.png')},
                 'learner': {'kind': LEARNER[kind]}}
    if kind == 'dual':
        # the sphere lands midway between the hands at 45 % of their path, where both come
        # close to it and to each other; at 65 % (the Panda's) the arms end their motion
        # within the streamer's repeller field, where its coupling may keep them moving
        # (2 of 4 runs did not rest within 40 s; benchmarks/RESULTS.md, "The dual demo")
        driver_args = ['--robot', robot.name, '--lateral', '0', '--obstacle-at', '0.45',
                       *driver_args]
    if LEARNER[kind] == 'promp':
        driver_args = ['--no-goal-change', '--wait-adapter', *driver_args]
        # the robot executes only adapted trajectories: it starts with the adapter's answer
        # to the primitive, not with the raw prior (which ignores the constraints)
        overrides['streamer'] = {'stream_unadapted': False}
    if streamer_parameters:
        overrides['streamer'] = dict(overrides.get('streamer', {}), **streamer_parameters)
    adapter_spec = next((spec for spec in graph.nodes if spec.executable == 'adapter'), None)
    nodes = []
    for spec in graph.nodes:
        extra = overrides.get(spec.executable)
        if extra:
            from dataclasses import replace
            spec = replace(spec, parameters={**spec.parameters, **extra})
        nodes.append(spec)
    from dataclasses import replace
    graph = replace(graph, nodes=nodes)
    env = demo_environment()
    t_start = time.monotonic()
    log.write(f'demo: starting the graph (ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]}, discovery '
              f'{env["ROS_AUTOMATIC_DISCOVERY_RANGE"]}); output in {out}\n')
    b = Bringup(graph, log=log, extra_env=env)
    driver = None
    with signal_flag(signal.SIGTERM) as (terminated, _):  # SIGTERM stops the graph too
        try:
            b.start()
            driver = subprocess.Popen(
                [sys.executable, '-m', 'cdmp_ros.ros.demo_driver', '--out', out,
                 '--timeout', str(timeout), *driver_args], env=b.env, stdout=log
                if hasattr(log, 'fileno') else None, stderr=subprocess.STDOUT)
            end = time.monotonic() + timeout + 30.0
            while driver.poll() is None and time.monotonic() < end:
                if terminated.is_set():
                    raise Terminated('demo: terminated by SIGTERM; the graph was stopped')
                dead = b.exited()
                if dead:
                    raise CdmpError(f'demo: node(s) exited early: {dead}')
                time.sleep(0.1)
            if driver.poll() is None:
                raise CdmpError(f'demo: the driver did not finish within {timeout + 30:.0f} s')
        finally:
            try:
                if driver is not None and driver.poll() is None:
                    driver.terminate()
                    try:
                        driver.wait(timeout=10)
                    except subprocess.TimeoutExpired:
                        driver.kill()
                        driver.wait()
            finally:
                codes = b.stop()  # the graph stops whatever happened to the driver
    log.write(f'demo: graph stopped ({codes}); {time.monotonic() - t_start:.1f} s\n')
    if driver.returncode != 0:
        raise CdmpError(f'demo: the scripted run failed (exit code {driver.returncode}); see '
                        'the log above')
    with open(os.path.join(out, 'driver.json')) as f:
        drv = json.load(f)
    m = robot.model
    limits = shipped_limits(m.joint_names, m.lower, m.upper, m.velocity_limits,
                            f'urdf {os.path.basename(robot.urdf)}')
    summary = summarise(out, bag, drv, limits, robot)
    summary['kind'] = kind
    summary['wall_time_s'] = time.monotonic() - t_start
    summary['node_exit_codes'] = codes
    plot(out, bag, drv, m.lower, m.upper, robot)
    if LEARNER[kind] == 'promp':
        from cdmp_ros.cli.demo_promp import adapter_parameters, plot_promp_paths, promp_summary
        params = adapter_parameters(adapter_spec) if adapter_spec else {}
        summary['promp'] = promp_summary(bag, drv, robot, params)
        summary['plots'].append(os.path.join(out, 'promp_paths.png'))
        plot_promp_paths(summary['plots'][-1], bag, drv, robot)
    with open(os.path.join(out, 'summary.json'), 'w') as f:
        json.dump(summary, f, indent=1, default=float)
    with open(os.path.join(out, 'summary.md'), 'w') as f:
        f.write(f'# cdmp demo --kind {kind}\n\n' + markdown(summary) + '\n' + ' '.join(
            f'![{os.path.basename(p)[:-4]}]({os.path.basename(p)})' for p in
            summary['plots'] + ([summary['snapshot']] if summary['snapshot'] else [])) + '\n')
    return summary
