"""The ProMP demo's adaptation re-solved offline with each probability law of the quadratic
forms (``AdaptationConfig.tail``), each result sampled through the kinematics.

From a ``cdmp demo --kind promp`` output directory: the learner's primitive (the first on
``/primitive``), the sphere's last position, the adapter's default request settings
(``AdaptRequestConfig``, ``avoid_links`` panda_link4, the request continues the motion); per
law: converged, KL, evaluations, wall time and the per-step maximum of the sampled violation
(``--samples`` trajectories, 50 steps) of the end effector and panda_link4 (allowed 1 - alpha),
with the one-sided 95 % Clopper-Pearson bound of that step's count.
The 'auto' law is solved twice: without the saddle point's correction of the Gamma levels
(``max_level_corrections`` 0) and with the default.

Run: .venv/bin/python benchmarks/link_point_resolve.py out/demo_promp \
         --tails auto gamma conservative saddlepoint
"""
import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'benchmarks'))

from cdmp_ros.cli.demo_promp import _primitives, _promp  # noqa: E402
from cdmp_ros.core.adaptation.config import TAILS, AdaptRequestConfig  # noqa: E402
from cdmp_ros.core.adaptation.requests import AdaptRequest, build_problem  # noqa: E402
from cdmp_ros.core.adaptation.solver import solve_levels  # noqa: E402
from cdmp_ros.core.adaptation.verification import clopper_pearson_upper  # noqa: E402
from cdmp_ros.core.kinematics import panda_chain  # noqa: E402
from cdmp_ros.core.kinematics.closest import Sphere  # noqa: E402
from cdmp_ros.sim.robot_specs import panda_urdf_path  # noqa: E402
from link_point_tail import MARGIN, N_STEPS, sampled  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('out', help='output directory of cdmp demo --kind promp')
    ap.add_argument('--tails', nargs='+',
                    default=['auto', 'gamma', 'conservative', 'saddlepoint'],
                    choices=TAILS)
    ap.add_argument('--samples', type=int, default=200_000)
    args = ap.parse_args(argv)
    chain = panda_chain(panda_urdf_path())
    with open(os.path.join(args.out, 'driver.json')) as f:
        driver = json.load(f)
    obs = driver['obstacle']
    center = np.asarray(driver['crossing'][-1] if driver.get('crossing') else obs['center'],
                        float)
    prior = _promp(_primitives(os.path.join(args.out, 'bag'), '/primitive')[0][1], chain)
    cfg = AdaptRequestConfig(avoid_links=('panda_link4',))
    req = AdaptRequest(prior, (Sphere(tuple(center), float(obs['radius'])),), continues=True)
    rng = np.random.default_rng(3)
    print('| law | converged | KL | evaluations | level corrections | wall [ms] | '
          'end effector per-step max (95 % bound) | panda_link4 (95 % bound) |')
    print('|---|---|---|---|---|---|---|---|')
    built = build_problem(req, chain, cfg)
    rows = []
    for tail in args.tails:
        if tail == 'auto':
            rows.append(('auto, no correction',
                         dataclasses.replace(built.config, tail=tail, max_level_corrections=0)))
        rows.append((tail, dataclasses.replace(built.config, tail=tail)))
    for name, config in rows:
        built = build_problem(req, chain, cfg)
        t = time.perf_counter()
        adapted, rep = solve_levels(built.prior, built.constraints, config)
        wall = time.perf_counter() - t
        S = sampled(adapted, chain, center, float(obs['radius']) + MARGIN,
                    np.linspace(0.0, 1.0, N_STEPS), args.samples, rng)
        worst = S.max(axis=0)
        bound = clopper_pearson_upper(np.round(worst * args.samples), args.samples)
        print(f'| {name} | {rep.converged} | {rep.kl:.3f} | {rep.n_evaluations} | '
              f'{rep.n_level_corrections} | {wall * 1e3:.0f} | {worst[0]:.5f} ({bound[0]:.5f}) | '
              f'{worst[1]:.5f} ({bound[1]:.5f}) |', flush=True)


if __name__ == '__main__':
    main()
