"""Benchmark of the simulation layer: real-time factor of the Panda at 1 kHz.

Target (issue 4): the Panda at 1 kHz under torque control (computed torque, Eq. 2 of paper
000, with pybullet's inverse dynamics) runs >= 5x faster than real time. Each run simulates
``--duration`` seconds tracking a moving joint reference (a new reference every step, as the
streamer sends it); the real-time factor is simulated time / wall time, median over ``--runs``.
The other control laws and a bare ``stepSimulation`` loop are measured for comparison.
Then real-time pacing (``WorldConfig(real_time=True)``): wall time of ``--duration`` simulated
seconds, and how far it lags behind (the tests only check it never runs ahead).

Run: .venv/bin/python benchmarks/bench_sim.py
"""
import argparse
import os
import platform
import time

import numpy as np

from cdmp_ros.sim import make_controller, panda_spec, World, WorldConfig
from cdmp_ros.sim.control import inertia_scaled_gains

DT = 1e-3


def run_once(mode, duration, with_obstacles=False):
    """Simulate ``duration`` s; return the wall time [s] of the stepping loop."""
    with World(WorldConfig(time_step=DT)) as world:
        robot = world.add_robot(panda_spec())
        q0 = np.array(robot.spec.home)
        if mode == 'pd':
            kp, kd = inertia_scaled_gains(robot, 100.0, 20.0)
            robot.set_controller(make_controller('pd', kp=kp, kd=kd))
        elif mode == 'joint_limit':
            kp, kd = inertia_scaled_gains(robot, 100.0, 20.0)
            robot.set_controller(make_controller('joint_limit', kp=kp, kd=kd))
        elif mode != 'bare':
            robot.set_controller(make_controller(mode))
        if with_obstacles:
            world.obstacles.add_sphere('s1', (0.5, 0.2, 0.4), 0.05, collide=False)
            world.obstacles.add_sphere('s2', (0.4, -0.3, 0.6), 0.05, collide=False)
            world.obstacles.add_box('board', (0.3, 0.5, 0.4), (0.2, 0.01, 0.2), collide=False)
        n = int(round(duration / DT))
        w = 2 * np.pi * 0.5
        T = np.arange(n) * DT
        Q = q0 + 0.3 * np.sin(w * T)[:, None]
        QD = 0.3 * w * np.cos(w * T)[:, None] * np.ones(7)
        QDD = -0.3 * w * w * np.sin(w * T)[:, None] * np.ones(7)
        start = time.perf_counter()
        if mode == 'bare':
            import pybullet
            cid = world.client_id
            for _ in range(n):
                pybullet.stepSimulation(physicsClientId=cid)
        else:
            for k in range(n):
                robot.set_reference(Q[k], QD[k], QDD[k])
                world.step()
                if with_obstacles:
                    world.obstacles.distances(robot, max_distance=0.3)
        wall = time.perf_counter() - start
        err = np.abs(robot.q - Q[-1]).max() if mode != 'bare' else float('nan')
    return wall, err


def pacing(duration):
    """Wall time [s] of ``duration`` simulated seconds with real-time pacing."""
    with World(WorldConfig(time_step=DT, real_time=True)) as world:
        robot = world.add_robot(panda_spec())
        robot.set_controller(make_controller('computed_torque'))
        start = time.perf_counter()
        world.run(duration)
        return time.perf_counter() - start


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--runs', type=int, default=7, help='runs per measurement (median)')
    ap.add_argument('--duration', type=float, default=2.0, help='simulated seconds per run')
    args = ap.parse_args()
    rows = [('computed_torque', False, 'Panda, computed torque (Eq. 2)', '>= 5'),
            ('joint_limit', False, 'Panda, Eq. 4 joint-limit law', ''),
            ('pd', False, 'Panda, PD + gravity', ''),
            ('position', False, 'Panda, pybullet position control', ''),
            ('computed_torque', True,
             'Panda, computed torque + distances to 3 obstacles every step', ''),
            ('bare', False, 'Panda, bare stepSimulation (no control)', '')]
    run_once('computed_torque', 0.2)  # warm-up (URDF cache, imports)
    print(f'Python {platform.python_version()}, load average '
          f'{os.getloadavg()[0]:.2f}, {args.runs} runs x {args.duration} s simulated at 1 kHz\n')
    print('| measurement | real-time factor (median) | min | us per step (median) | '
          'final tracking error (rad) | target |')
    print('|---|---|---|---|---|---|')
    for mode, obstacles, label, target in rows:
        results = [run_once(mode, args.duration, obstacles) for _ in range(args.runs)]
        walls = np.array([r[0] for r in results])
        rtf = args.duration / walls
        err = np.median([r[1] for r in results])
        err_text = '' if np.isnan(err) else f'{err:.1e}'
        print(f'| {label} | {np.median(rtf):.1f}x | {rtf.min():.1f}x | '
              f'{np.median(walls) / args.duration * 1e3 * 1e3 * DT:.0f} | {err_text} | '
              f'{target} |')
    walls = np.array([pacing(args.duration) for _ in range(min(args.runs, 3))])
    lag = (walls - (args.duration - DT)) * 1e3  # the first step anchors the pacing
    print(f'\nreal-time pacing, {args.duration} s simulated: wall {np.median(walls):.3f} s '
          f'(median of {len(walls)}), lag behind the wall clock median {np.median(lag):.1f} ms, '
          f'max {lag.max():.1f} ms')


if __name__ == '__main__':
    main()
