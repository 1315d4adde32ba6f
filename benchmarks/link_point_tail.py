"""Why the ProMP demo's adapted distribution comes closer to the sphere than alpha allows
(issue 29 item 4): the Gamma tail, the unscented transform's Gaussian, the phases between the
solver's steps, or sampling noise.

For the last adapted primitive of each ``cdmp demo --kind promp`` output directory given, with
the sphere of the demo (its last position, radius + the adapter's 2 cm margin) and the
adapter's points (``--points``: the end effector and the adapter's default ``avoid_links``) at
its 50 steps, per point:

- ``sampled``: the per-step violation frequency of ``--samples`` trajectories sampled from the
  primitive and put through the kinematics (the truth), its largest value over the 50 steps
  and that step, with the one-sided 95 % Clopper-Pearson bound of that step's count; ``fine``:
  the same over 500 phases (``--samples`` / 4 trajectories);
- at that step, the solver's laws of the violation probability: ``gamma`` (paper 003's moment
  match of |x - c|^2, what ``tail: auto`` uses for link points), ``saddle`` (the saddle-point
  law of the same Gaussian), and ``UT Gaussian``: the frequency of 200,000 draws of the
  unscented transform's Gaussian of the point (its exact law, up to noise), and
  ``importance-sampled``: the estimate of the solver's sampled check
  (:func:`cdmp_ros.core.adaptation.tail_sampling.sphere_violation`, 1,024 draws) with its
  standard error.

gamma << UT Gaussian ~ sampled: the tail; UT Gaussian << sampled: the Gaussian; fine >> sampled:
the phases.

Run: .venv/bin/python benchmarks/link_point_tail.py out/demo_promp [more demo dirs] \
         [--samples 1000000] [--points ee panda_link4 panda_hand]
"""
import argparse
import json
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from cdmp_ros.cli.demo_promp import _primitives, _promp  # noqa: E402
from cdmp_ros.core.adaptation.config import AdaptationConfig, AdaptRequestConfig  # noqa: E402
from cdmp_ros.core.adaptation.tail_sampling import sphere_violation  # noqa: E402
from cdmp_ros.core.adaptation.verification import clopper_pearson_upper  # noqa: E402
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
    ap.add_argument('--points', nargs='+', default=['ee', *AdaptRequestConfig().avoid_links],
                    help="points of interest ('ee' or link names; default: the adapter's, "
                         '%(default)s)')
    args = ap.parse_args(argv)
    points = tuple(args.points)
    chain = panda_chain(panda_urdf_path())
    rng = np.random.default_rng(11)
    grid = np.linspace(0.0, 1.0, N_STEPS)
    print(f'alpha {ALPHA}: allowed per-step violation {1 - ALPHA:.4f} per point; '
          f'{args.samples} trajectories\n')
    print('| run | point | sampled max (step) | its 95 % bound | gamma | saddle | UT Gaussian | '
          'importance-sampled (+- se) | fine max |')
    print('|---|---|---|---|---|---|---|---|---|')
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
                         name=p) for p in points]
        laws = {}
        for tail in ('gamma', 'saddlepoint'):
            prob = Problem(promp, cons, AdaptationConfig(n_steps=N_STEPS, tail=tail))
            F = prob.constraint_values(mu, L)
            laws[tail] = [1.0 - F[sl] for sl in prob.slices]
        S = sampled(promp, chain, center, radius, grid, args.samples, rng, points)
        fine = sampled(promp, chain, center, radius, np.linspace(0.0, 1.0, 500),
                       args.samples // 4, rng, points)
        normals = np.random.default_rng(7).standard_normal((1024, promp.n_dims))
        for j, name in enumerate(points):
            t = int(np.argmax(S[:, j]))
            prob = Problem(promp, [cons[j]], AdaptationConfig(n_steps=N_STEPS))
            prob.constraint_values(mu, L)
            m, Sx = prob._moments_of(0)
            Z = rng.multivariate_normal(m[t], Sx[t], size=200_000)
            ut = float(np.mean(np.linalg.norm(Z - center, axis=1) < radius))
            s_t = grid[t:t + 1]
            est = sphere_violation(cons[j].point, promp.mean(s_t), promp.cov(s_t), center[None],
                                   np.array([radius ** 2]), np.zeros(1, bool), normals)
            bound = float(clopper_pearson_upper(np.round(S[t, j] * args.samples), args.samples))
            print(f'| {os.path.basename(out.rstrip("/"))} | {name} | {S[t, j]:.5f} ({t}) | '
                  f'{bound:.5f} | {laws["gamma"][j][t]:.5f} | {laws["saddlepoint"][j][t]:.5f} | '
                  f'{ut:.5f} | {est.p[0]:.5f} +- {est.se[0]:.5f} | {fine[:, j].max():.5f} |',
                  flush=True)


if __name__ == '__main__':
    main()
