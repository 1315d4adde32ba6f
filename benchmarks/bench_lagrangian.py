"""Cost of one evaluation of the adaptation Lagrangian (value and analytic gradient), issue 29.

Two problems:

- ``panda``: the adapter's problem of ``bench_adapter.py`` as ``bench_adaptation_solve.py``
  builds an obstacle event (7-DoF Panda ProMP, 10 basis functions per joint, two-sided joint
  limits, three sphere repellers on the end effector and panda_link4 through the unscented
  transform, 50 steps, Gamma tail);
- ``table2``: a paper 003 Table II problem (``--obstacles`` repellers on a 2-D ProMP, 101
  steps, saddle-point tail; ``cdmp_ros.experiments.promp_problems.make_problem``);
- ``demo``: the first obstacle request of a ``cdmp demo --kind promp`` run (``--demo-dir``,
  an output directory of ``benchmarks/bench_demo_promp.py``): the learner's primitive and the
  dropped sphere, built as the adapter builds it (end effector, panda_link4 and panda_hand,
  50 steps, Gamma tail with the importance-sampled check).

Each problem is solved cold once with the reference evaluation, recording the (theta, lambda)
of every evaluation the solver makes; each evaluation (``Problem(evaluator=...)``) then replays
that sequence ``--repeats`` times (after one warm-up replay). Per evaluation: the median and
90th percentile of the wall-clock time of single calls, the Python-level function calls
(cProfile's total over one replay / evaluations), and the largest difference to the
reference over the sequence (value: relative; gradient: |g - g_ref| over |g_KL| +
|g_ref - g_KL|, the scale of the two parts that cancel near an optimum).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_lagrangian.py [--problems
        panda,table2,demo] [--seed 0] [--obstacles 3] [--repeats 5]
        [--demo-dir /tmp/bench_demo_promp/run1]
"""
import argparse
import cProfile
import functools
import os
import pstats
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'benchmarks'))

import numpy as np  # noqa: E402


def panda_problem(seed):
    """(prior, constraints, config) of one obstacle event of bench_adaptation_solve."""
    import cdmp_ros.core.adaptation.requests as requests
    from bench_adaptation_solve import events
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    chain, reqs = events(1, seed, 3)
    built = requests.build_problem(reqs[0], chain, AdaptRequestConfig())
    return built.prior, built.constraints, built.config


def table2_problem(seed, obstacles):
    from cdmp_ros.experiments.promp_problems import make_problem
    p = make_problem('table2', obstacles, np.random.default_rng(seed))
    return p.prior, p.constraints, p.config


def demo_problem(out):
    """(prior, constraints, config) of the first obstacle request of the demo run in ``out``."""
    import json
    import cdmp_ros.core.adaptation.requests as requests
    from cdmp_ros.cli.demo_promp import _primitives, _promp
    from cdmp_ros.core.adaptation.config import AdaptRequestConfig
    from cdmp_ros.core.kinematics import Sphere, panda_chain
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    chain = panda_chain(panda_urdf_path())
    with open(os.path.join(out, 'driver.json')) as f:
        obs = json.load(f)['obstacle']
    prior = _promp(_primitives(os.path.join(out, 'bag'), '/primitive')[0][1], chain)
    req = requests.AdaptRequest(prior, (Sphere(tuple(obs['center']), float(obs['radius'])),),
                                continues=True)
    built = requests.build_problem(req, chain, AdaptRequestConfig())
    return built.prior, built.constraints, built.config


def record(prior, cons, config):
    """(theta, lambda) of every evaluation of a cold reference solve, and its report."""
    from cdmp_ros.core.adaptation import solver
    from cdmp_ros.core.adaptation.problem import Problem
    seen = []
    real = Problem.lagrangian_reference

    def rec(self, theta, lam):
        seen.append((theta.copy(), lam.copy()))
        return real(self, theta, lam)
    orig = solver.Problem
    try:
        solver.Problem = functools.partial(Problem, evaluator='reference')
        Problem.lagrangian_reference = rec
        _, rep = solver.solve_levels(prior, cons, config)
    finally:
        Problem.lagrangian_reference = real
        solver.Problem = orig
    return seen, rep


def measure(make, seq, repeats):
    """Per-call times (s), calls per evaluation and first-call time of a problem's
    ``lagrangian`` replaying ``seq``."""
    t0 = time.perf_counter()
    prob = make()
    prob.lagrangian(*seq[0])
    first = time.perf_counter() - t0
    for theta, lam in seq:                      # warm-up replay
        prob.lagrangian(theta, lam)
    times = []
    clock = time.perf_counter
    for _ in range(repeats):
        prob = make()
        for theta, lam in seq:
            t = clock()
            prob.lagrangian(theta, lam)
            times.append(clock() - t)
    prob = make()
    prof = cProfile.Profile()
    prof.enable()
    for theta, lam in seq:
        prob.lagrangian(theta, lam)
    prof.disable()
    calls = pstats.Stats(prof).total_calls / len(seq)
    return np.array(times), calls, first


def agreement(make, seq):
    """Largest relative value difference and scaled gradient difference to the reference."""
    from cdmp_ros.core.adaptation.problem import Problem
    prob = make()
    ref = Problem(prob.prior, prob.constraints, prob.config, evaluator='reference')
    dv = dg = 0.0
    for theta, lam in seq:
        v0, g0 = ref.lagrangian(theta, lam)
        v1, g1 = prob.lagrangian(theta, lam)
        gk = ref.lagrangian(theta, np.zeros_like(lam))[1]
        scale = np.linalg.norm(gk) + np.linalg.norm(g0 - gk)
        dv = max(dv, abs(v1 - v0) / max(abs(v0), 1e-300))
        dg = max(dg, np.linalg.norm(g1 - g0) / scale)
    return dv, dg


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--problems', default='panda,table2',
                    help='comma-separated subset of panda,table2,demo (default panda,table2)')
    ap.add_argument('--demo-dir', default='/tmp/bench_demo_promp/run1',
                    help='the demo run of the demo problem (default %(default)s)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--obstacles', type=int, default=3, help='Table II repellers (1-3)')
    ap.add_argument('--repeats', type=int, default=5, help='timed replays of the sequence')
    args = ap.parse_args()
    from cdmp_ros.core.adaptation.problem import Problem
    problems = []
    for name in [p.strip() for p in args.problems.split(',') if p.strip()]:
        if name == 'panda':
            problems.append(('Panda (bench_adapter event, 3 spheres)', panda_problem(args.seed)))
        elif name == 'table2':
            problems.append((f'Table II ({args.obstacles} obstacles)',
                             table2_problem(args.seed, args.obstacles)))
        elif name == 'demo':
            if not os.path.isfile(os.path.join(args.demo_dir, 'driver.json')):
                ap.error(f'--demo-dir: no driver.json in {args.demo_dir!r} (an output '
                         'directory of benchmarks/bench_demo_promp.py)')
            problems.append((f'demo ({os.path.basename(args.demo_dir)}, first obstacle)',
                             demo_problem(args.demo_dir)))
        else:
            ap.error(f'--problems: unknown problem {name!r}')
    print(f'machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}, '
          f'OPENBLAS_NUM_THREADS={os.environ.get("OPENBLAS_NUM_THREADS")}; seed {args.seed}, '
          f'{args.repeats} replays')
    rows = []
    for label, (prior, cons, config) in problems:
        seq, rep = record(prior, cons, config)
        print(f'{label}: {len(seq)} evaluations in the cold solve (KL {rep.kl:.4g}, '
              f'{rep.status}), {prior.n_weights} weights, theta of {seq[0][0].size}',
              file=sys.stderr)
        variants = [('reference', functools.partial(Problem, prior, cons, config,
                                                    evaluator='reference')),
                    ('batched', functools.partial(Problem, prior, cons, config,
                                                  evaluator='batched'))]
        base = None
        for name, make in variants:
            times, calls, first = measure(make, seq, args.repeats)
            diff = agreement(make, seq) if name != 'reference' else (0.0, 0.0)
            med = float(np.median(times))
            base = med if base is None else base
            rows.append((label, name, len(seq), med, float(np.percentile(times, 90)), calls,
                         base / med, diff, first))
    print()
    print('| problem | evaluation | evaluations | per evaluation p50 [us] | p90 [us] | '
          'Python calls / evaluation | speed-up (p50) | max rel. diff value / gradient | '
          'first call [ms] |')
    print('|---|---|---|---|---|---|---|---|---|')
    for label, name, n, med, p90, calls, speed, (dv, dg), first in rows:
        print(f'| {label} | {name} | {n} | {med * 1e6:.0f} | {p90 * 1e6:.0f} | {calls:.0f} | '
              f'{speed:.2f}x | {dv:.1e} / {dg:.1e} | {first * 1e3:.0f} |')


if __name__ == '__main__':
    main()
