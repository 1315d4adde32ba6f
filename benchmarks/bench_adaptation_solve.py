"""In-process cost of the adapter's solve for sets of obstacle events (issue 13, latency).

The problem of bench_adaptation_latency without the processes: the 7-DoF Panda ProMP of
bench_adapter, ``--spheres`` spheres (default 3: the first ones near the prior mean
end-effector path, the last one near the elbow path, radius 5-10 cm) and ``--n`` events, each
moving every sphere N(0, 2 cm) around its place and conditioning on a start state on the
prior mean at a random phase in [0, 0.1] (the robot has just started). Every event is built
and solved exactly as the adapter does (``run_request`` with ``config/adapter.yaml``'s
``adaptation`` defaults: limits, repellers on the end effector and panda_link4, 50 steps,
sampled verification), one after the other on this thread.

Prints per event (unless ``-q``) the outcome, the CPU time (``time.thread_time`` of this
thread plus that of the verification's worker threads), outer and
inner iterations and Lagrangian evaluations; then the outcome counts, the median KL and the
50th / 95th percentiles of evaluations and CPU time of the converged events, and the median
CPU split into build / optimiser / sampled verification / JSON message.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_adaptation_solve.py [--n 40]
        [--seed 0] [--spheres 3] [--opt max_log_decrease=3.0 ...] [-q]

``--opt NAME=VALUE`` overrides an AdaptationConfig field (Python literal), e.g. the EMM's
``max_log_decrease=3.0`` (the symmetric clip used before 2026-11-24).
"""
import argparse
import ast
import collections
import os
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'benchmarks'))

import numpy as np  # noqa: E402

from bench_adapter import panda_prior  # noqa: E402


def events(n, seed, spheres):
    """(chain, [AdaptRequest]) of ``n`` obstacle events (module docstring)."""
    from cdmp_ros.core.adaptation.requests import AdaptRequest, ee_path
    from cdmp_ros.core.kinematics import PointOfInterest
    from cdmp_ros.core.kinematics.closest import Sphere
    rng = np.random.default_rng(seed)
    prior, chain = panda_prior(rng)
    elbow = PointOfInterest('panda_link4')
    centres, radii = [], []
    for k in range(spheres):
        q = prior.mean([rng.uniform(0.3, 0.7)])
        x = (ee_path(chain, q)[0] if k < spheres - 1 or spheres == 1
             else chain.forward(q, [elbow])[0, 0])
        centres.append(x + rng.normal(0.0, 0.04, 3))
        radii.append(rng.uniform(0.05, 0.1))
    base = np.array(centres)
    reqs = []
    for _ in range(n):
        c = base + rng.normal(0.0, 0.02, base.shape)
        start = prior.mean([rng.uniform(0.0, 0.1)])[0]
        reqs.append(AdaptRequest(prior, tuple(Sphere(ci, float(r)) for ci, r in zip(c, radii)),
                                 start_y=start))
    return chain, reqs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--n', type=int, default=40, help='obstacle events (default 40)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--spheres', type=int, default=3)
    ap.add_argument('--opt', nargs='*', default=[], metavar='NAME=VALUE',
                    help='AdaptationConfig overrides')
    ap.add_argument('-q', action='store_true', help='summary only')
    args = ap.parse_args()
    import cdmp_ros.core.adaptation.requests as requests
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.adaptation.guarantee import attach_verification
    from cdmp_ros.core.adaptation.solver import solve_levels
    from cdmp_ros.core.adaptation.verification import worker_cpu_seconds

    def cpu():  # this thread's CPU time and that of the verification's worker threads
        return time.thread_time() + worker_cpu_seconds()
    over = {}
    for o in args.opt:
        name, _, value = o.partition('=')
        over[name] = ast.literal_eval(value)
    config_cls = requests.AdaptationConfig
    chain, reqs = events(args.n, args.seed, args.spheres)
    cfg = AdaptRequestConfig()
    rows = []
    for req in reqs:
        t0 = cpu()
        built = requests.build_problem(req, chain, cfg)
        config = config_cls(**{**built.config.__dict__, **over})
        if built.infeasible:
            rows.append(('infeasible', None))
            if not args.q:
                print('infeasible (known at build time: ' + built.infeasible[0] + ')')
            continue
        t1 = cpu()
        adapted, rep = solve_levels(built.prior, built.constraints, config)
        t2 = cpu()
        attach_verification(rep, adapted, built.constraints, config,
                            np.random.default_rng(0), 0.0)
        t3 = cpu()
        requests.promp_message(adapted)
        t4 = cpu()
        outcome = requests.classify(rep)
        split = (t1 - t0, t2 - t1, t3 - t2, t4 - t3)
        rows.append((outcome, (rep.n_outer, rep.n_inner, rep.n_evaluations, rep.kl) + split))
        if not args.q:
            print(f'{outcome:12s} CPU {sum(split) * 1e3:7.1f} ms  outer {rep.n_outer:2d} '
                  f'inner {rep.n_inner:4d} evaluations {rep.n_evaluations:4d} '
                  f'({rep.status})')
    counts = collections.Counter(o for o, _ in rows)
    conv = np.array([r for o, r in rows if o == 'converged'])
    print(f'events {args.n} (seed {args.seed}, {args.spheres} spheres, overrides {over}): '
          + ', '.join(f'{k} {v}' for k, v in sorted(counts.items())))
    if conv.size:
        cpu = conv[:, 4:8].sum(axis=1) * 1e3
        ev = conv[:, 2]
        med = np.median(conv[:, 4:8], axis=0) * 1e3
        print(f'converged: evaluations p50 {np.percentile(ev, 50):.0f} / p95 '
              f'{np.percentile(ev, 95):.0f}; CPU p50 {np.percentile(cpu, 50):.1f} / p95 '
              f'{np.percentile(cpu, 95):.1f} ms; median KL {np.median(conv[:, 3]):.1f}; '
              f'median CPU split build {med[0]:.1f} / optimiser {med[1]:.1f} / verification '
              f'{med[2]:.1f} / message {med[3]:.1f} ms; per evaluation '
              f'{np.median(conv[:, 5] / conv[:, 2]) * 1e3:.3f} ms')


if __name__ == '__main__':
    main()
