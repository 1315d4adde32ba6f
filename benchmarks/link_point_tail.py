"""Why the ProMP demo's adapted distribution comes closer to the sphere than alpha allows
(issue 29 item 4): the Gamma tail, the unscented transform's Gaussian, the phases between the
solver's steps, or sampling noise.

For the last adapted primitive of each ``cdmp demo --kind promp`` output directory given, with
the sphere of the demo (its last position, radius + the adapter's 2 cm margin) and the
adapter's points (end effector, panda_link4) at its 50 steps, per point:

- ``sampled``: the per-step violation frequency of ``--samples`` trajectories sampled from the
  primitive and put through the kinematics (the truth), its largest value over the 50 steps
  and that step; ``fine``: the same over 500 phases (``--samples`` / 4 trajectories);
- at that step, the solver's laws of the violation probability: ``gamma`` (paper 003's moment
  match of |x - c|^2, what ``tail: auto`` uses for link points), ``saddle`` (the saddle-point
  law of the same Gaussian), and ``UT Gaussian``: the frequency of 200,000 draws of the
  unscented transform's Gaussian of the point (its exact law, up to noise).

gamma << UT Gaussian ~ sampled: the tail; UT Gaussian << sampled: the Gaussian; fine >> sampled:
the phases.

Run: .venv/bin/python benchmarks/link_point_tail.py out/demo_promp [more demo dirs]
"""
import argparse
import json
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from cdmp_ros.cli.demo_promp import _primitives, _promp  # noqa: E402
from cdmp_ros.core.adaptation.config import AdaptationConfig  # noqa: E402
from cdmp_ros.core.adaptation.constraints import ChainPoint, Repeller  # noqa: E402
from cdmp_ros.core.adaptation.problem import Problem  # noqa: E402
from cdmp_ros.core.kinematics import PointOfInterest, panda_chain  # noqa: E402
from cdmp_ros.sim.robot_specs import panda_urdf_path  # noqa: E402

POINTS = ('ee', 'panda_link4')
ALPHA = 0.999
N_STEPS = 50
MARGIN = 0.02


def sampled(promp, chain, center, radius, phases, n, rng, points=POINTS, chunk=20_000):
    """Per-phase violation frequency of each of ``points`` (link names, 'ee'),
    (len(phases), len(points))."""
    pois = [PointOfInterest(p) for p in points]
    cnt = np.zeros((len(phases), len(points)))
    done = 0
    while done < n:
        k = min(chunk, n - done)
        Y = promp.sample_trajectories(phases, k, rng)
        X = chain.forward(Y.reshape(-1, Y.shape[-1]), pois)
        d = np.linalg.norm(X - center, axis=-1).reshape(k, len(phases), len(points))
        cnt += (d < radius).sum(axis=0)
        done += k
    return cnt / n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('outs', nargs='+', help='output directories of cdmp demo --kind promp')
    ap.add_argument('--samples', type=int, default=200_000)
    args = ap.parse_args(argv)
    chain = panda_chain(panda_urdf_path())
    rng = np.random.default_rng(11)
    grid = np.linspace(0.0, 1.0, N_STEPS)
    print(f'alpha {ALPHA}: allowed per-step violation {1 - ALPHA:.4f} per point; '
          f'{args.samples} trajectories\n')
    print('| run | point | sampled max (step) | gamma | saddle | UT Gaussian | fine max |')
    print('|---|---|---|---|---|---|---|')
    for out in args.outs:
        driver = json.load(open(os.path.join(out, 'driver.json')))
        obs = driver['obstacle']
        center = np.asarray(driver['crossing'][-1] if driver.get('crossing')
                            else obs['center'], float)
        radius = float(obs['radius']) + MARGIN
        promp = _promp(_primitives(os.path.join(out, 'bag'), '/adapted_primitive')[-1][1],
                       chain)
        mu = promp.mean_w
        L = np.linalg.cholesky(promp.cov_w + 1e-12 * np.eye(mu.size))
        cons = [Repeller(ChainPoint(chain, PointOfInterest(p)), center, radius, alpha=ALPHA,
                         name=p) for p in POINTS]
        laws = {}
        for tail in ('gamma', 'saddlepoint'):
            prob = Problem(promp, cons, AdaptationConfig(n_steps=N_STEPS, tail=tail))
            F = prob.constraint_values(mu, L)
            laws[tail] = [1.0 - F[sl] for sl in prob.slices]
        S = sampled(promp, chain, center, radius, grid, args.samples, rng)
        fine = sampled(promp, chain, center, radius, np.linspace(0.0, 1.0, 500),
                       args.samples // 4, rng)
        for j, name in enumerate(POINTS):
            t = int(np.argmax(S[:, j]))
            prob = Problem(promp, [cons[j]], AdaptationConfig(n_steps=N_STEPS))
            prob.constraint_values(mu, L)
            m, Sx = prob._moments_of(0)
            Z = rng.multivariate_normal(m[t], Sx[t], size=200_000)
            ut = float(np.mean(np.linalg.norm(Z - center, axis=1) < radius))
            print(f'| {os.path.basename(out.rstrip("/"))} | {name} | {S[t, j]:.5f} ({t}) | '
                  f'{laws["gamma"][j][t]:.5f} | {laws["saddlepoint"][j][t]:.5f} | {ut:.5f} | '
                  f'{fine[:, j].max():.5f} |', flush=True)


if __name__ == '__main__':
    main()
