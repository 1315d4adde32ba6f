"""Benchmark of the (C)DMP core: one streaming step and a full rollout.

Targets (issue 2): one 7-DoF CDMP step with 30 kernels per joint, including the tanh map and
velocity/acceleration outputs, median <= 10 us and p99 <= 50 us; a 1 s rollout at 1 kHz
(1000 steps, 7 DoF) <= 10 ms.

Run: .venv/bin/python benchmarks/bench_dmp.py
"""
import argparse
import platform
import time

import numpy as np

from cdmp_ros.core.dmp.dmp import CDMP, DmpConfig


def make_cdmp(n_dims=7, n_weights=30, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = -np.full(n_dims, 2.5), np.full(n_dims, 2.5)
    T = np.linspace(0.0, 1.0, 1001)
    s = 10 * T ** 3 - 15 * T ** 4 + 6 * T ** 5
    start, goal = rng.uniform(-1, 1, n_dims), rng.uniform(-1, 1, n_dims)
    Y = start + np.outer(s, goal - start) + 0.2 * np.outer(np.sin(2 * np.pi * T), np.ones(n_dims))
    return CDMP(lo, hi, DmpConfig(n_weights_per_dim=n_weights)).fit(T, Y)


def bench_step(prim, dt, n_steps, reps):
    """Per-call latency of stepper.update over whole movements (start, motion, tail)."""
    pc = time.perf_counter_ns
    samples = np.empty(n_steps * reps)
    st = prim.stepper(dt)
    inp = st.input
    upd = st.update
    i = 0
    for _ in range(reps):
        st.reset()
        for _ in range(n_steps):
            t0 = pc()
            upd(inp)
            samples[i] = pc() - t0
            i += 1
    return samples / 1e3


def bench_rollout(prim, reps):
    times = np.empty(reps)
    for i in range(reps):
        t0 = time.perf_counter()
        prim.rollout(dt=0.001, tau=1.0)
        times[i] = time.perf_counter() - t0
    return times * 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--reps', type=int, default=40, help='movements per measurement')
    args = ap.parse_args()
    prim = make_cdmp()
    bench_step(prim, 0.001, 1000, 2)  # warm-up
    step = bench_step(prim, 0.001, 1500, args.reps)
    roll = bench_rollout(prim, max(20, args.reps))
    print(f'machine: {platform.machine()}, {platform.python_implementation()} '
          f'{platform.python_version()}, {len(step)} steps, {len(roll)} rollouts')
    print()
    print('| measurement | median | p99 | target |')
    print('|---|---|---|---|')
    print(f'| CDMP step, 7 DoF, 30 kernels/joint (us) | {np.median(step):.2f} | '
          f'{np.percentile(step, 99):.2f} | median <= 10, p99 <= 50 |')
    print(f'| CDMP rollout 1 s at 1 kHz, 7 DoF (ms) | {np.median(roll):.3f} | '
          f'{np.percentile(roll, 99):.3f} | <= 10 |')


if __name__ == '__main__':
    main()
