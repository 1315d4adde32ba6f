"""Paper 003 III-A on the planar 4-link arm (cdmp reproduce planar): the original ProMPs, one
adaptation through the kinematics checked by sampling, and (benchmark) the whole experiment."""
import json
import subprocess
import sys

import numpy as np
import pytest

from cdmp_ros.core.adaptation.guarantee import adapt
from cdmp_ros.core.adaptation.solver import AdaptationConfig, monte_carlo_satisfaction
from cdmp_ros.core.kinematics import PointOfInterest, planar_chain
from cdmp_ros.experiments import exp_planar


def test_original_promp_reaches_the_end_point(rng):
    chain = planar_chain([1.0] * 4)
    p, end = exp_planar.original_promp(chain, exp_planar.START_A, rng)
    assert np.allclose(chain.forward(end, [PointOfInterest('ee')])[0, :2], exp_planar.END_XY,
                       atol=1e-6)
    assert np.allclose(p.mean([1.0])[0], end, atol=0.05)
    assert np.allclose(p.mean([0.0])[0], exp_planar.START_A, atol=0.1)


def test_planar_repeller_with_start_and_end_constraints_holds_by_sampling(rng):
    chain = planar_chain([1.0] * 4)
    ee, tasks = exp_planar.tasks(chain)
    start, end_guess, cons = tasks['repeller']
    p, _ = exp_planar.original_promp(chain, start, rng, n_basis=5, end_guess=end_guess)
    allc = exp_planar.base_constraints(chain, start, ee) + cons
    before = monte_carlo_satisfaction(p, cons, 3000, rng, 15)[0]
    q, rep = adapt(p, allc, AdaptationConfig(n_steps=15))
    assert rep.converged, rep.to_text()
    per_time = monte_carlo_satisfaction(q, allc, 20000, rng, 15)[0]
    assert before[0] < 0.99
    # unscented transform + Gamma approximation: within 5 (1 - alpha) of the confidence
    assert np.all(per_time >= 1 - 5e-3), per_time


@pytest.mark.benchmark
def test_reproduce_planar_full(tmp_path, repo_root):
    out = tmp_path / 'planar'
    proc = subprocess.run([sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'planar',
                           '--out', str(out)], cwd=repo_root, capture_output=True, text=True,
                          timeout=3600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {r['name']: r for r in json.load(open(out / 'results.json'))['rows']}
    for name in ('waypoint', 'repeller', 'corner', 'hyperplane'):
        for obj in ('kl', 'smooth'):
            assert rows[f'{name}.{obj}.violation_pct']['ours'] < 5.0
    assert (out / 'fig3_planar.png').exists() and (out / 'fig4_mutual.png').exists()
