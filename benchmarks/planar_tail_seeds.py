"""The planar 4-link repeller of test_core_promp_planar.py (paper 003 III-A) under each law of
the quadratic forms (``AdaptationConfig.tail``), seeds 0-5: per seed, converged, the sampled
worst per-step violation (20,000 trajectories, 15 steps, every constraint) and the KL.

Run: .venv/bin/python benchmarks/planar_tail_seeds.py gamma conservative saddlepoint
"""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from cdmp_ros.core.adaptation.guarantee import adapt  # noqa: E402
from cdmp_ros.core.adaptation.solver import AdaptationConfig  # noqa: E402
from cdmp_ros.core.adaptation.solver import monte_carlo_satisfaction  # noqa: E402
from cdmp_ros.core.kinematics import planar_chain  # noqa: E402
from cdmp_ros.experiments import exp_planar  # noqa: E402


def main(tails):
    chain = planar_chain([1.0] * 4)
    ee, tasks = exp_planar.tasks(chain)
    start, end_guess, cons = tasks['repeller']
    for tail in tails:
        rows = []
        for seed in range(6):
            p, _ = exp_planar.original_promp(chain, start, np.random.default_rng(seed),
                                             n_basis=5, end_guess=end_guess)
            allc = exp_planar.base_constraints(chain, start, ee) + cons
            q, rep = adapt(p, allc, AdaptationConfig(n_steps=15, tail=tail))
            per_time = monte_carlo_satisfaction(q, allc, 20000,
                                                np.random.default_rng(100 + seed), 15)[0]
            rows.append(f'seed {seed}: converged {rep.converged}, worst step '
                        f'{1.0 - per_time.min():.5f}, KL {rep.kl:.2f}')
        print(f'{tail}: ' + '; '.join(rows), flush=True)


if __name__ == '__main__':
    main(sys.argv[1:] or ['gamma', 'conservative', 'saddlepoint'])
