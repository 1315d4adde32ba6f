"""Cost of the dual-arm adaptation of ``cdmp reproduce dual-arm`` (paper 003, III-C; issue 29
item 5: <= 1 s).

The problem of :func:`cdmp_ros.experiments.exp_dual_arm.solve`: the joint ProMP of both
Pandas learned from ``bags/dual_panda`` (8 basis functions per joint), the paper's five
mutual-avoidance pairs, the table and the joint limits on 50 steps, the sum-of-marginal-KLs
objective. Prints the p50 of ``--calls`` evaluations of the Lagrangian (value and gradient) at
the prior, then the wall time of ``--solves`` cold adaptations (``adapt``, its sampled
verification included), their evaluations, KL and status.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_dual_arm.py [--calls 20]
        [--solves 2]
"""
import argparse
import os
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--calls', type=int, default=20, help='timed Lagrangian evaluations')
    ap.add_argument('--solves', type=int, default=2, help='timed cold adaptations')
    args = ap.parse_args(argv)
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.core.adaptation.problem import Problem
    from cdmp_ros.experiments import exp_dual_arm as E
    prior = E.learn_prior(E.load_demonstrations(None), 8)
    groups = E.constraints(E.cell_chains(), E.CLEARANCE, True)
    constraints = [c for g in groups.values() for c in g]
    config = E.adaptation_config(8, 50)
    problem = Problem(prior, constraints, config)
    theta = problem.initial_theta()
    lam = np.full(problem.n_values, config.lambda0)
    problem.lagrangian(theta, lam)                         # warm-up
    times = []
    for _ in range(args.calls):
        t = time.perf_counter()
        problem.lagrangian(theta, lam)
        times.append(time.perf_counter() - t)
    print(f'machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; '
          f'{len(constraints)} constraints, {problem.n_values} multipliers, '
          f'{len(problem.points)} points of interest')
    print('\n| measurement | value |\n|---|---|')
    print(f'| Lagrangian evaluation p50 [ms] | {1e3 * np.median(times):.2f} |')
    for i in range(args.solves):
        t = time.perf_counter()
        _, report = adapt(prior, constraints, config)
        wall = time.perf_counter() - t
        print(f'| adapt {i + 1} [s] (evaluations, KL, status) | {wall:.2f} '
              f'({report.n_evaluations}, {report.kl:.3f}, {report.status}) |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
