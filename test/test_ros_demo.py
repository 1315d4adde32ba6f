"""The README's main command, end to end: ``cdmp demo`` (graph of five node processes, the
scripted sphere drop and goal change, the recorded bag read back) exits 0 and writes every
output it promises. Localhost discovery, a private domain id; bounded by --timeout."""
import json
import os
import subprocess
import sys

import pytest

from conftest import ros_env, module_domain

pytestmark = pytest.mark.ros
DOMAIN = module_domain(2)
KEYS = ('min_obstacle_distance_m', 'max_limit_usage', 'latency_ms_p50', 'latency_ms_p99',
        'tracking_error_rad', 'messages_recorded', 'bag', 'plots', 'snapshot')


def test_cdmp_demo_runs_end_to_end(tmp_path):
    out = tmp_path / 'demo'
    cdmp = os.path.join(os.path.dirname(sys.executable), 'cdmp')
    r = subprocess.run([cdmp, 'demo', '--out', str(out), '--timeout', '90'],
                       env=ros_env(DOMAIN), capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    s = json.loads((out / 'summary.json').read_text())
    for k in KEYS:
        assert k in s, k
    assert s['min_obstacle_distance_m'] > 0.0 and s['contacts'] == 0
    assert 0.0 < s['reference_limit_usage'] < 1.0  # the streamer's guarantee
    assert s['limit_violations'] == 0 and s['max_limit_excess_rad'] <= 1e-4
    assert s['max_limit_usage'] < 1.0 + 1e-4
    assert 0.0 < s['latency_ms_p50'] <= s['latency_ms_p99']
    assert s['latency_samples'] >= 1
    assert s['messages_recorded'] > 1000
    assert s['messages_by_topic']['/joint_reference'] > 1000
    assert s['messages_by_topic']['/goal'] == 1
    for p in s['plots'] + [s['snapshot']]:
        assert os.path.getsize(p) > 1000, p
    assert os.path.isfile(os.path.join(s['bag'], 'metadata.yaml'))
    assert (out / 'summary.md').read_text().count('|') > 10
    assert 'minimum robot-obstacle distance' in r.stdout
