"""`cdmp reproduce promp-tables` (paper 003 Tables II-IV) with a tiny number of problems, and
the protocol's problem generators (../shared/promp_benchmark_protocol.md)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cdmp_ros.experiments.promp_problems import make_problem


def test_problem_generators_follow_the_protocol(rng):
    for K in (1, 2, 3):
        p2 = make_problem('table2', K, rng)
        assert len(p2.constraints) == K and p2.config.n_steps == 101
        assert p2.prior.n_basis == 10 and p2.config.lambda0 == 20.0
        assert np.allclose(p2.prior.mean([0.0, 1.0]), [p2.start, p2.end], atol=0.05)
        for c in p2.constraints:
            assert 0.3 <= c.radius <= 0.6 and c.alpha == 0.999
        p3 = make_problem('table3', K, rng)
        assert p3.config.n_steps == 40 and p3.prior.n_basis == 20
        xs = [c.center[0] for c in p3.constraints]
        assert np.all(np.diff(xs) > 0)          # not adjacent, ordered left to right
        p4 = make_problem('table4', K, rng)
        assert p4.config.n_steps == 20 and p4.config.lambda0 == 40.0
        for c in p4.constraints:                # start and end are allowed by every wall
            assert c.normal @ (p4.start - c.offset) <= 0
            assert c.normal @ (p4.end - c.offset) <= 0


def test_reproduce_promp_tables_tiny(tmp_path, repo_root):
    out = tmp_path / 'tables'
    cmd = [sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'promp-tables', '--out',
           str(out), '--n-problems', '1', '--seed', '3', '--n-samples', '2000', '--no-progress']
    proc = subprocess.run(cmd, cwd=repo_root, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.load(open(out / 'results.json'))
    rows = {r['name']: r for r in res['rows']}
    for table, label in (('table2', 'obstacles'), ('table3', 'waypoints'), ('table4', 'walls')):
        for K in (1, 2, 3):
            for metric in ('failed_pct', 'violation_pct', 'kl', 'solve_s_median'):
                assert f'{table}.{label}_{K}.{metric}' in rows
            assert rows[f'{table}.{label}_{K}.failed_pct']['paper'] is not None
            assert rows[f'{table}.{label}_{K}.failed_pct']['ours'] == 0.0
        assert os.path.exists(out / f'{table}_examples.png')
    assert (out / 'results.md').exists()


@pytest.mark.benchmark
def test_reproduce_promp_tables_full(tmp_path, repo_root):
    out = tmp_path / 'tables_full'
    cmd = [sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'promp-tables', '--out',
           str(out), '--no-progress']
    proc = subprocess.run(cmd, cwd=repo_root, capture_output=True, text=True, timeout=7200)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {r['name']: r for r in json.load(open(out / 'results.json'))['rows']}
    for K in (1, 2, 3):
        assert rows[f'table2.obstacles_{K}.failed_pct']['ours'] <= 2.0
        assert rows[f'table3.waypoints_{K}.failed_pct']['ours'] <= 1.0
        assert rows[f'table4.walls_{K}.failed_pct']['ours'] <= 1.0


def test_confidence_margin_enforces_the_stricter_level(rng):
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.experiments.exp_promp_tables import parse_margins
    p = make_problem('table2', 2, rng, relative_step=True, confidence_margin=0.2)
    assert p.config.confidence_margin == 0.2
    q, rep = adapt(p.prior, p.constraints, p.config)
    assert rep.converged and rep.status == 'converged', rep.to_text()
    for c in rep.constraints:      # approximate violation <= 0.2 (1 - alpha) (within tol)
        assert 1.0 - c.probability <= 0.2 * (1.0 - c.alpha) * (1.0 + 0.1) + 1e-12
    assert parse_margins('0.5') == {'table2': 0.5, 'table3': 0.5, 'table4': 0.5}
    assert parse_margins('table2=0.2') == {'table2': 0.2, 'table3': 1.0, 'table4': 1.0}
    for bad in ('table5=0.2', '0', '1.5'):
        with pytest.raises(SystemExit):
            parse_margins(bad)
