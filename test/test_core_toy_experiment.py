"""`cdmp reproduce toy` writes the common results shape and shows the paper's effect."""
import json
import os
import subprocess
import sys

from cdmp_ros.experiments.results import rows_by_name

REQUIRED = ['goal_adaptation.limit_deg', 'goal_adaptation.dmp_max_deg',
            'goal_adaptation.cdmp_max_deg', 'steep_change.limit_deg',
            'steep_change.dmp_max_deg', 'steep_change.cdmp_max_deg',
            'goal_adaptation.rms_error_deg']


def test_reproduce_toy_cli(tmp_path):
    out = tmp_path / 'toy'
    proc = subprocess.run([sys.executable, '-m', 'cdmp_ros.cli.main', 'reproduce', 'toy',
                           '--out', str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert '| goal_adaptation.dmp_max_deg |' in proc.stdout
    res = json.loads((out / 'results.json').read_text())
    assert set(res) >= {'experiment', 'rows'}
    for r in res['rows']:
        assert set(r) == {'name', 'ours', 'paper', 'unit'}
    rows = rows_by_name(res)
    for name in REQUIRED:
        assert name in rows, name
    for case in ('goal_adaptation', 'steep_change'):
        limit = rows[f'{case}.limit_deg']['ours']
        assert rows[f'{case}.dmp_max_deg']['ours'] > limit
        assert rows[f'{case}.cdmp_max_deg']['ours'] < limit
    assert rows['goal_adaptation.rms_error_deg']['ours'] < 0.5
    assert os.path.getsize(out / 'toy.png') > 10_000
    md = (out / 'results.md').read_text()
    assert '| quantity | ours | paper | unit |' in md
