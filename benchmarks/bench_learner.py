"""Learner figures: fitting from the sample bags, start-up to the first primitive, ~/improve.

1. In process (the code the node runs): read ``bags/panda_reach`` (5 demonstrations) and fit
   + serialise a cdmp, dmp and promp primitive; median over ``--repeat`` runs.
2. Across processes: start ``python -m cdmp_ros.nodes.learner`` and measure the wall time
   until a subscriber in this process receives ``primitive`` (interpreter + rclpy start-up
   included), and the node's own "read bags + fit + publish" time from its log line.
3. ``~/improve`` (in process, :class:`cdmp_ros.core.dmp.improve.Improver`, default
   ``improve.*`` / ``cost.*`` parameters): cost of the noiseless rollout before and after,
   updates, rollouts, rollouts outside the limits, wall time; scripted and sim cost.

OpenBLAS is single-threaded as in the learner process (``OPENBLAS_NUM_THREADS=1`` unless set;
see cdmp_ros/nodes/learner.py).

Every ROS process runs with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private domain id.

    .venv/bin/python benchmarks/bench_learner.py [--repeat 5] [--domain 179]
"""
import argparse
import os
import re
import statistics
import subprocess
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # as the learner node (before numpy)


def fit_figures(repeat):
    import pybullet_data
    from cdmp_ros.bag import read_demonstrations
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.learning import fit_primitive
    from cdmp_ros.core.primitive_io import dumps_primitive
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda',
                                     'panda.urdf'))
    rows = []
    for kind in ('cdmp', 'dmp', 'promp'):
        times, read_times = [], []
        for _ in range(repeat):
            t0 = time.perf_counter()
            demos = read_demonstrations(os.path.join(REPO, 'bags', 'panda_reach'))
            t1 = time.perf_counter()
            prim = fit_primitive(kind, [(T, Y) for T, Y, _ in demos], chain.joint_names,
                                 chain.lower, chain.upper)
            dumps_primitive(prim)
            times.append(time.perf_counter() - t0)
            read_times.append(t1 - t0)
        rows.append((kind, statistics.median(read_times), statistics.median(times),
                     prim.metadata['fit_rms_error']))
    return chain, rows


def startup_figures(domain):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String
    from cdmp_ros.ros import qos
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(domain), AMENT_PREFIX_PATH=sys.prefix, PYTHONUNBUFFERED='1')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node('bench_learner', context=ctx)
    got = []
    node.create_subscription(String, 'primitive', lambda m: got.append(time.monotonic()),
                             qos.LATCHED)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, '-m', 'cdmp_ros.nodes.learner'], cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    try:
        while not got and time.monotonic() - t0 < 60 and proc.poll() is None:
            ex.spin_once(timeout_sec=0.05)
    finally:
        proc.send_signal(2)
        out = proc.communicate(timeout=20)[0]
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    m = re.search(r'rms error [0-9.e-]+ rad, (\d+) ms', out)
    return (got[0] - t0) if got else float('nan'), (int(m.group(1)) if m else None)


def improve_figures(chain):
    from cdmp_ros.bag import read_demonstrations
    from cdmp_ros.core.dmp.improve import CostConfig, ImproveConfig, Improver, ScriptedCost
    from cdmp_ros.core.learning import fit_primitive
    from cdmp_ros.sim.rollout_cost import SimRolloutCost
    demos = read_demonstrations(os.path.join(REPO, 'bags', 'panda_reach'))
    prim = fit_primitive('cdmp', [(T, Y) for T, Y, _ in demos], chain.joint_names,
                         chain.lower, chain.upper)
    rows = []
    for cost_name, updates in (('scripted', 10), ('scripted', 30), ('sim', 10)):
        cfg = ImproveConfig(updates=updates, cost=cost_name)
        scripted = ScriptedCost(chain, CostConfig(), prim.goal_y_, cfg.dt)
        t0 = time.perf_counter()
        if cost_name == 'sim':
            with SimRolloutCost(scripted, joint_names=chain.joint_names) as sim:
                res = Improver(prim, cfg, sim, chain.lower, chain.upper).run()
        else:
            res = Improver(prim, cfg, scripted, chain.lower, chain.upper).run()
        dt = time.perf_counter() - t0
        rows.append((cost_name, res.updates, res.rollouts, res.cost_before, res.cost_after,
                     res.rollouts_outside_limits, res.max_limit_usage, dt))
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--repeat', type=int, default=5)
    ap.add_argument('--domain', type=int, default=179)
    args = ap.parse_args()
    print(f'OPENBLAS_NUM_THREADS={os.environ["OPENBLAS_NUM_THREADS"]}, load average '
          f'{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores')
    chain, fits = fit_figures(args.repeat)
    print('| kind | read 5 bags [ms] | read + fit + JSON [ms] | fit rms error [rad] |')
    print('|---|---|---|---|')
    for kind, r, t, e in fits:
        print(f'| {kind} | {r * 1e3:.0f} | {t * 1e3:.0f} | {e:.4f} |')
    wall, node_ms = startup_figures(args.domain)
    print()
    print('| learner process start -> primitive received [s] | in-node bags + fit + publish '
          '[ms] |')
    print('|---|---|')
    print(f'| {wall:.2f} | {node_ms} |')
    print()
    print('| cost | updates | rollouts | cost before | cost after | rollouts outside limits | '
          'max limit usage | time [s] |')
    print('|---|---|---|---|---|---|---|---|')
    for c, u, n, b, a, o, m, t in improve_figures(chain):
        print(f'| {c} | {u} | {n} | {b:.3f} | {a:.3f} | {o} | {m:.3f} | {t:.2f} |')


if __name__ == '__main__':
    main()
