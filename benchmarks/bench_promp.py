"""Benchmark of the constrained ProMP adaptation (issue 3).

Targets: a 2-D Table II problem with one obstacle (paper 003 III-B, protocol settings): median
solve <= 50 ms; a 7-DoF Panda joint-space ProMP (10 basis functions per joint, 100 time steps)
with two-sided joint limits and 3 sphere repellers on the end effector and the elbow: median
<= 200 ms, p95 <= 1 s.

Both include the sampled verification of every report (issue 12: 10,000 trajectories for
Table II, 1,000 for the Panda at 100 steps, the defaults); its cost alone is the
"verification" columns. A third Table II row solves with the trajectory-level guarantee.

Run: .venv/bin/python benchmarks/bench_promp.py [--n-table2 50] [--n-panda 5] [--seed 0]
[--compare-tails] (the same problems again with tail 'saddlepoint' and 'gamma'; the default
'auto' is the saddle point on Table II's linear points and the Gamma match on the Panda's
link points, see AdaptationConfig.tail)
(single-threaded BLAS: OPENBLAS_NUM_THREADS=1 is set below, before numpy is imported).
"""
import argparse
import dataclasses
import os
import platform
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from cdmp_ros.core.adaptation.guarantee import adapt  # noqa: E402
from cdmp_ros.experiments.promp_problems import make_problem, panda_problem  # noqa: E402


def _stats(times):
    t = np.asarray(times) * 1e3
    return np.median(t), np.percentile(t, 90), np.percentile(t, 95), t.max()


class _Runs:
    """Wall-clock and CPU (process) time, L-BFGS iterations, Lagrangian evaluations."""

    def __init__(self):
        self.wall, self.cpu, self.iters, self.evals, self.conv = [], [], [], [], []
        self.verify, self.samples = [], []

    def solve(self, prior, cons, cfg):
        t0, c0 = time.perf_counter(), time.process_time()
        _, rep = adapt(prior, cons, cfg)
        self.wall.append(time.perf_counter() - t0)
        self.cpu.append(time.process_time() - c0)
        self.iters.append(rep.n_inner)
        self.evals.append(rep.n_evaluations)
        self.conv.append(rep.converged)
        self.verify.append(rep.verification.time_s)
        self.samples.append(rep.verification.n_samples)


def bench_table2(n, rng, tail='auto', guarantee='per_step'):
    runs = _Runs()
    problems = [make_problem('table2', 1, rng, relative_step=True) for _ in range(n)]
    configs = [dataclasses.replace(p.config, tail=tail, guarantee=guarantee) for p in problems]
    adapt(problems[0].prior, problems[0].constraints, configs[0])   # warm-up
    for p, cfg in zip(problems, configs):
        runs.solve(p.prior, p.constraints, cfg)
    return runs


def bench_panda(n, rng, tail='auto'):
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    chain = panda_chain(panda_urdf_path())
    runs = _Runs()
    for _ in range(n):
        prior, cons, cfg = panda_problem(chain, rng)
        runs.solve(prior, cons, dataclasses.replace(cfg, tail=tail))
    return runs


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n-table2', type=int, default=50)
    ap.add_argument('--n-panda', type=int, default=5)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--compare-tails', action='store_true',
                    help="also run every case with tail='saddlepoint' and tail='gamma' (the "
                         "paper's moment match) on the same problems, for comparison")
    args = ap.parse_args()
    print(f'machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, '
          f'load average {os.getloadavg()[0]:.1f} at the start')
    print()
    print('| case | n | median [ms] | p90 [ms] | p95 [ms] | max [ms] | CPU median / p95 [ms] '
          '| median L-BFGS its / evaluations | converged | target |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    rows = []
    tails = ('auto', 'saddlepoint', 'gamma') if args.compare_tails else ('auto',)
    for tail in tails:
        # the same problems for every tail
        if args.n_table2:
            rows.append((f'Table II, 1 obstacle (2-D, 10 basis/dim, 101 steps), tail {tail}',
                         bench_table2(args.n_table2, np.random.default_rng(args.seed), tail),
                         'median <= 50 ms' if tail == 'auto' else '-'))
        if args.n_panda:
            rows.append(('Panda 7-DoF, 10 basis/joint, 100 steps, limits + 3 spheres x (ee, '
                         f'elbow), tail {tail}',
                         bench_panda(args.n_panda, np.random.default_rng(args.seed + 1), tail),
                         'median <= 200 ms, p95 <= 1 s' if tail == 'auto' else '-'))
    if args.n_table2:
        rows.append(('Table II, 1 obstacle, guarantee trajectory',
                     bench_table2(args.n_table2, np.random.default_rng(args.seed),
                                  guarantee='trajectory'), '-'))
    for name, r, target in rows:
        med, p90, p95, mx = _stats(r.wall)
        cmed, _, cp95, _ = _stats(r.cpu)
        print(f'| {name} | {len(r.wall)} | {med:.1f} | {p90:.1f} | {p95:.1f} | {mx:.1f} | '
              f'{cmed:.1f} / {cp95:.1f} | {np.median(r.iters):.0f} / {np.median(r.evals):.0f} '
              f'| {np.mean(r.conv) * 100:.0f} % | {target} |')
    print()
    print('Sampled verification alone (included above):')
    print()
    print('| case | samples (median) | median [ms] | p95 [ms] | max [ms] |')
    print('|---|---|---|---|---|')
    for name, r, _ in rows:
        med, _, p95, mx = _stats(r.verify)
        print(f'| {name} | {np.median(r.samples):.0f} | {med:.1f} | {p95:.1f} | {mx:.1f} |')
    print()
    print(f'load average {os.getloadavg()[0]:.1f} at the end')


if __name__ == '__main__':
    main()
