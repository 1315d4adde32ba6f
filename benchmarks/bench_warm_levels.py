"""Warm starts and the check of the Gamma rows: a stream of falling-sphere requests.

For each ``cdmp demo --kind promp`` output directory given (``benchmarks/bench_demo_promp.py``
leaves ten): the learner's primitive, the adapter's default request settings
(``AdaptRequestConfig``, ``avoid_links`` of ``--avoid-links``, requests that continue the
motion), one request without obstacles (as the adapter's first), then ``--positions`` requests
for the demo's sphere falling from 12 cm above its last position to it, solved as the adapter
solves them (``run_request`` with the warm starts of one stream, the sampled verification
included). Each stream is solved once per ``--modes`` entry:

- ``sampled``: the default: the Gamma rows checked by importance sampling of the point's true
  law (``AdaptationConfig.check_law`` 'sampled'), warm starts carrying the implied levels;
- ``saddlepoint``: checked by the saddle point of the unscented Gaussian, levels carried;
- ``asked``: the saddle point's check, warm starts at the asked levels (the code before the
  carried levels).

Printed per mode: Lagrangian evaluations per request (p50 / max), re-solves by the level
correction, wall time per request (p50 / max, this process alone), the sum of the KLs, and
for the 4th and the last answer of each stream the sampled per-step violation of the end
effector and every avoided link within the sphere + 2 cm (``--samples`` trajectories, 50
steps; allowed 1 - alpha = 0.1 % per point): the worst, and how many answers exceed 0.1 %.

Run: OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_warm_levels.py \
         /tmp/bench_demo_promp/run* [--avoid-links panda_link4] [--modes sampled saddlepoint]
"""
import argparse
import functools
import json
import os
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'benchmarks'))

from cdmp_ros.cli.demo_promp import _primitives, _promp  # noqa: E402
from cdmp_ros.core.adaptation import requests, solver  # noqa: E402
from cdmp_ros.core.adaptation.config import AdaptRequestConfig  # noqa: E402
from cdmp_ros.core.adaptation.requests import AdaptRequest, run_request  # noqa: E402
from cdmp_ros.core.adaptation.verification import clopper_pearson_upper  # noqa: E402
from cdmp_ros.core.adaptation.warm import WarmStarts  # noqa: E402
from cdmp_ros.core.kinematics import panda_chain  # noqa: E402
from cdmp_ros.core.kinematics.closest import Sphere  # noqa: E402
from cdmp_ros.sim.robot_specs import panda_urdf_path  # noqa: E402
from link_point_tail import MARGIN, N_STEPS, sampled  # noqa: E402

#: --modes: (check_law, levels a warm start carries)
MODES = {'sampled': ('sampled', 'carried'), 'saddlepoint': ('saddlepoint', 'carried'),
         'asked': ('saddlepoint', 'asked')}


def stream(out, chain, positions, samples, avoid_links):
    """The requests of one demo directory: per request (evaluations, level corrections, KL,
    wall [s], converged and verified, sampled end-effector per-step max or None)."""
    with open(os.path.join(out, 'driver.json')) as f:
        driver = json.load(f)
    obs = driver['obstacle']
    end = np.asarray(driver['crossing'][-1] if driver.get('crossing') else obs['center'], float)
    prior = _promp(_primitives(os.path.join(out, 'bag'), '/primitive')[0][1], chain)
    cfg = AdaptRequestConfig(avoid_links=tuple(avoid_links))
    warm = WarmStarts()
    run_request(AdaptRequest(prior, (), continues=False), chain, cfg, warm=warm)
    rows = []
    for i, dz in enumerate(np.linspace(0.12, 0.0, positions)):
        centre = end + np.array([0.0, 0.0, dz])
        req = AdaptRequest(prior, (Sphere(tuple(centre), float(obs['radius'])),),
                           continues=True)
        t = time.perf_counter()
        res = run_request(req, chain, cfg, warm=warm)
        wall = time.perf_counter() - t
        rep = res.report
        worst = None
        if i in (3, positions - 1):
            S = sampled(res.adapted, chain, centre, float(obs['radius']) + MARGIN,
                        np.linspace(0.0, 1.0, N_STEPS), samples, np.random.default_rng(1),
                        ('ee',) + tuple(avoid_links))
            worst = float(S.max())
        rows.append((rep.n_evaluations, rep.n_level_corrections, rep.kl, wall,
                     bool(rep.converged), worst))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('outs', nargs='+', help='output directories of cdmp demo --kind promp')
    ap.add_argument('--positions', type=int, default=8)
    ap.add_argument('--samples', type=int, default=200_000)
    ap.add_argument('--avoid-links', nargs='+', default=list(AdaptRequestConfig().avoid_links),
                    help='links avoiding the sphere besides the end effector (default: the '
                         "adapter's, %(default)s)")
    ap.add_argument('--modes', nargs='+', default=['sampled', 'saddlepoint'], choices=MODES,
                    help='check law of the Gamma rows with carried levels (sampled, '
                         'saddlepoint) or the code before the carried levels (asked)')
    args = ap.parse_args(argv)
    if args.positions < 4:
        ap.error('--positions: expected at least 4')
    chain = panda_chain(panda_urdf_path())
    carried = solver.implied_levels
    build = requests.AdaptationConfig
    print('| check law, levels of a warm start | requests | evaluations p50 / max | '
          'level re-solves | wall p50 / max [ms] | KL sum | converged | sampled per-step max '
          'over the avoiding points, worst (95 % bound) | answers above 0.1 % |')
    print('|---|---|---|---|---|---|---|---|---|')
    for mode in args.modes:
        law, levels = MODES[mode]
        if levels == 'asked':
            solver.implied_levels = lambda alpha_asked, *_: alpha_asked.copy()
        requests.AdaptationConfig = functools.partial(build, check_law=law)
        try:
            rows = [r for out in args.outs
                    for r in stream(out, chain, args.positions, args.samples, args.avoid_links)]
        finally:
            solver.implied_levels = carried
            requests.AdaptationConfig = build
        ev = np.array([r[0] for r in rows])
        ms = np.array([r[3] for r in rows]) * 1e3
        worst = np.array([r[5] for r in rows if r[5] is not None])
        bound = clopper_pearson_upper(np.round(worst.max() * args.samples), args.samples)
        print(f'| {law}, {levels} | {len(rows)} | {np.median(ev):.0f} / {ev.max()} | '
              f'{sum(r[1] for r in rows)} | {np.median(ms):.0f} / {ms.max():.0f} | '
              f'{sum(r[2] for r in rows):.2f} | {sum(r[4] for r in rows)} of {len(rows)} | '
              f'{100 * worst.max():.4f} % ({100 * float(bound):.4f} %) | '
              f'{int(np.sum(worst > 1e-3))} of {worst.size} |', flush=True)


if __name__ == '__main__':
    main()
