"""Benchmark of the constrained ProMP adaptation (issue 3).

Targets: a 2-D Table II problem with one obstacle (paper 003 III-B, protocol settings): median
solve <= 50 ms; a 7-DoF Panda joint-space ProMP (10 basis functions per joint, 100 time steps)
with two-sided joint limits and 3 sphere repellers on the end effector and the elbow: median
<= 200 ms, p95 <= 1 s.

Run: .venv/bin/python benchmarks/bench_promp.py [--n-table2 50] [--n-panda 5] [--seed 0]
(single-threaded BLAS: OPENBLAS_NUM_THREADS=1 is set below, before numpy is imported).
"""
import argparse
import os
import platform
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from cdmp_ros.core.adaptation import adapt  # noqa: E402
from cdmp_ros.experiments.promp_problems import make_problem, panda_problem  # noqa: E402


def _stats(times):
    t = np.asarray(times) * 1e3
    return np.median(t), np.percentile(t, 90), np.percentile(t, 95), t.max()


def bench_table2(n, rng, relative_step=True):
    times, iters, conv = [], [], []
    problems = [make_problem('table2', 1, rng, relative_step=relative_step) for _ in range(n)]
    adapt(problems[0].prior, problems[0].constraints, problems[0].config)   # warm-up
    for p in problems:
        t0 = time.perf_counter()
        _, rep = adapt(p.prior, p.constraints, p.config)
        times.append(time.perf_counter() - t0)
        iters.append(rep.n_inner)
        conv.append(rep.converged)
    return times, iters, conv


def bench_panda(n, rng):
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.sim.robots import panda_urdf_path
    chain = panda_chain(panda_urdf_path())
    times, iters, conv = [], [], []
    for _ in range(n):
        prior, cons, cfg = panda_problem(chain, rng)
        t0 = time.perf_counter()
        _, rep = adapt(prior, cons, cfg)
        times.append(time.perf_counter() - t0)
        iters.append(rep.n_inner)
        conv.append(rep.converged)
    return times, iters, conv


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n-table2', type=int, default=50)
    ap.add_argument('--n-panda', type=int, default=5)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    print(f'machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, '
          f'load average {os.getloadavg()[0]:.1f}')
    print()
    print('| case | n | median [ms] | p90 [ms] | p95 [ms] | max [ms] | median L-BFGS its '
          '| converged | target |')
    print('|---|---|---|---|---|---|---|---|---|')
    rows = []
    if args.n_table2:
        rows.append(('Table II, 1 obstacle (2-D, 10 basis/dim, 101 steps)',
                     bench_table2(args.n_table2, rng), 'median <= 50 ms'))
    if args.n_panda:
        rows.append(('Panda 7-DoF, 10 basis/joint, 100 steps, limits + 3 spheres x (ee, elbow)',
                     bench_panda(args.n_panda, rng), 'median <= 200 ms, p95 <= 1 s'))
    for name, (times, iters, conv), target in rows:
        med, p90, p95, mx = _stats(times)
        print(f'| {name} | {len(times)} | {med:.1f} | {p90:.1f} | {p95:.1f} | {mx:.1f} | '
              f'{np.median(iters):.0f} | {np.mean(conv) * 100:.0f} % | {target} |')


if __name__ == '__main__':
    main()
