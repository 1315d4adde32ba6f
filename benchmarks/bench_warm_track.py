"""In-process cost of the adapter's solves for obstacles tracked at constant velocity (issue 13).

The Panda problem of ``bench_adaptation_solve.py`` (7-DoF ProMP, limits, three spheres on the
end effector and panda_link4; ``--seed``): the spheres of its first event move, each along its
own horizontal heading, by ``--speed / --rate`` per request (default 0.2 m/s at 30 Hz:
6.7 mm), as an obstacle tracker reports them, and every request is solved by the adapter's
``run_request`` with one :class:`~cdmp_ros.core.adaptation.warm.WarmStarts` (the adapter's
solver thread, every request answered). For each heading seed (``--headings``) the same
stream is solved with and without the predictor (``adaptation.warm_start_predict``), and
the table gives per setting the evaluations of the Lagrangian (all solves, and p50 / p90 of
the warm solves), the CPU time per warm solve (solver thread plus the sampled verification's
worker threads), the starts and the mean KL.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_warm_track.py [--n 40]
        [--seed 3] [--headings 1 2 3] [--speed 0.2] [--rate 30]
"""
import argparse
import os
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'benchmarks'))

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from bench_adaptation_solve import events  # noqa: E402
from cdmp_ros.core.adaptation.config import AdaptRequestConfig  # noqa: E402
from cdmp_ros.core.adaptation.requests import AdaptRequest, run_request  # noqa: E402
from cdmp_ros.core.adaptation.verification import worker_cpu_seconds  # noqa: E402
from cdmp_ros.core.adaptation.warm import WarmStarts  # noqa: E402
from cdmp_ros.core.kinematics import Sphere  # noqa: E402


def stream(base, n, heading_seed, step):
    """The obstacle sets of ``n`` requests: the spheres of ``base`` moving ``step`` per request
    along random horizontal headings, through their places at the middle request."""
    rng = np.random.default_rng(heading_seed)
    heading = rng.uniform(0.0, 2 * np.pi, len(base.obstacles))
    direction = np.stack([np.cos(heading), np.sin(heading), 0.0 * heading], axis=1)
    c0 = np.array([ob.center for ob in base.obstacles]) - direction * step * n / 2
    return [tuple(Sphere(tuple(c0[i] + direction[i] * step * k), ob.radius)
                  for i, ob in enumerate(base.obstacles)) for k in range(n)]


def run(chain, base, obstacles, cfg, bar):
    """Solve the stream with one WarmStarts; per solve (start, evaluations, CPU [ms], KL)."""
    ws = WarmStarts()
    rows = []
    for k, obs in enumerate(obstacles):
        req = AdaptRequest(base.prior, obs, start_y=base.start_y, continues=k > 0)
        c0 = time.thread_time() + worker_cpu_seconds()
        rep = run_request(req, chain, cfg, warm=ws).report
        rows.append((rep.start, rep.n_evaluations,
                     (time.thread_time() + worker_cpu_seconds() - c0) * 1e3, rep.kl))
        bar.update()
    return rows, ws.counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--n', type=int, default=40, help='requests per stream')
    ap.add_argument('--seed', type=int, default=3, help='problem of bench_adaptation_solve')
    ap.add_argument('--headings', type=int, nargs='+', default=[1, 2, 3],
                    help="seeds of the spheres' headings (one stream each)")
    ap.add_argument('--speed', type=float, default=0.2, help='m/s')
    ap.add_argument('--rate', type=float, default=30.0, help='requests per second')
    args = ap.parse_args(argv)
    chain, reqs = events(1, args.seed, 3)
    base = reqs[0]
    step = args.speed / args.rate
    print(f'Panda problem of bench_adaptation_solve seed {args.seed}: {len(base.obstacles)} '
          f'spheres moving {step * 1e3:.1f} mm per request, {args.n} requests per stream\n')
    print('| headings | predictor | evaluations, all solves | warm solves | warm evaluations '
          'p50 / p90 | warm CPU p50 / p90 [ms] | starts | mean KL |')
    print('|---|---|---|---|---|---|---|---|')
    with tqdm(total=2 * args.n * len(args.headings), file=sys.stderr, leave=False) as bar:
        for h in args.headings:
            obstacles = stream(base, args.n, h, step)
            for predict in (False, True):
                cfg = AdaptRequestConfig(warm_start_predict=predict)
                rows, counts = run(chain, base, obstacles, cfg, bar)
                warm = [r for r in rows if r[0] == 'warm']
                ev = np.array([r[1] for r in warm] or [0])
                cpu = np.array([r[2] for r in warm] or [0.0])
                starts = ', '.join(f'{k} {v}' for k, v in counts.items()
                                   if v and k not in ('refined', 'refine_kept_warm'))
                tqdm.write(
                    f'| {h} | {"on" if predict else "off"} | {sum(r[1] for r in rows)} | '
                    f'{len(warm)} | {np.median(ev):.0f} / {np.percentile(ev, 90):.0f} | '
                    f'{np.median(cpu):.0f} / {np.percentile(cpu, 90):.0f} | {starts} | '
                    f'{np.mean([r[3] for r in rows]):.2f} |', file=sys.stdout)
    return 0


if __name__ == '__main__':
    sys.exit(main())
