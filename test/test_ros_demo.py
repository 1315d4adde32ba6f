"""The README's main command, end to end: ``cdmp demo`` (graph of five node processes, the
scripted sphere drop and goal change, the recorded bag read back) exits 0 and writes every
output it promises. Localhost discovery, a private domain id; bounded by --timeout."""
import json
import os
import subprocess
import sys

import pytest

from cdmp_ros.core.adaptation.config import SAMPLED_CHECK_LAW
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


def test_cdmp_demo_promp_adapts_to_the_obstacle(tmp_path):
    """``cdmp demo --kind promp``: the obstacle triggers constrained adaptations, and the
    adapted distribution keeps the hand and the link away from the sphere far more often than
    the prior (checked by sampling, independently of the adapter)."""
    out = tmp_path / 'demo_promp'
    cdmp = os.path.join(os.path.dirname(sys.executable), 'cdmp')
    r = subprocess.run([cdmp, 'demo', '--kind', 'promp', '--out', str(out), '--timeout', '90'],
                       env=ros_env(DOMAIN), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    s = json.loads((out / 'summary.json').read_text())
    assert s['kind'] == 'promp'
    p = s['promp']
    assert p['adaptations'] >= 1
    assert s['contacts'] == 0 and s['min_obstacle_distance_m'] > 0.0
    assert 0.0 < s['reference_limit_usage'] < 1.0
    prior, adapted = p['prior_violation'], p['adapted_violation']
    assert prior['trajectory'] > 0.1  # the sphere lands on the prior's mean path
    assert adapted['trajectory_upper95'] < prior['trajectory']
    assert s['messages_by_topic'].get('/goal', 0) == 0  # no goal change in this demo
    # which law each constraint used (issue 29 item 4)
    laws = {n: law for law, names in p['adapted_laws'].items() for n in names}
    assert {laws[n] for n in laws if n.startswith('obstacle')} == {SAMPLED_CHECK_LAW}, laws
    assert 'probability laws of the last adaptation' in (out / 'summary.md').read_text()
    for path in s['plots']:
        assert os.path.getsize(path) > 1000, path
    assert 'promp_paths.png' in (out / 'summary.md').read_text()
    assert 'constrained adaptations after the drop' in r.stdout


def test_cdmp_demo_promp_moving_obstacle(tmp_path):
    """``cdmp demo --kind promp --motion cross`` (issue 13 item 2): a sphere crossing the path
    at 0.2 m/s, published at 30 Hz. The adapter stays current (its last adaptation answers the
    last obstacle message; the latest request wins, none waits in a queue), the coupling terms
    act as the inner layer, and the simulated robot stays out of contact and inside its
    limits."""
    out = tmp_path / 'demo_cross'
    cdmp = os.path.join(os.path.dirname(sys.executable), 'cdmp')
    r = subprocess.run([cdmp, 'demo', '--kind', 'promp', '--motion', 'cross', '--out', str(out),
                        '--timeout', '90'],
                       env=ros_env(DOMAIN), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    s = json.loads((out / 'summary.json').read_text())
    p = s['promp']
    assert p['obstacle_messages'] >= 60  # 0.6 m at 0.2 m/s, 30 per second
    assert p['adaptations'] >= 2
    assert p['adapter_current'] is True
    assert 0 <= p['adapter_queued'] <= 1  # at most the request being solved
    assert p['adapter_requests']['requests_received'] >= p['obstacle_messages'] // 2
    assert s['contacts'] == 0 and s['min_obstacle_distance_m'] > 0.0
    assert s['limit_violations'] == 0 and 0.0 < s['reference_limit_usage'] < 1.0
    assert s['latency_samples'] >= 1  # the streamer's coupling saw the obstacle (inner layer)


def test_adaptation_latencies_count_each_answered_obstacle_once(monkeypatch):
    """summary.json's adaptation_latency_ms: one figure per timed adaptation (its first
    reference's stamp), not per generation: a refinement switched in after a warm solve
    carries the same last latency under a new generation."""
    import cdmp_ros.cli.demo_promp as demo_promp
    states = [{'adapted_generation': '1', 'adapted_reference_stamp_ns': '100',
               'adaptation_latency_ms_last': '80.5'},
              {'adapted_generation': '1', 'adapted_reference_stamp_ns': '100',
               'adaptation_latency_ms_last': '80.5'},
              {'adapted_generation': '2', 'adapted_reference_stamp_ns': '100',   # refinement
               'adaptation_latency_ms_last': '80.5'},
              {'adapted_generation': '3', 'adapted_reference_stamp_ns': '300',
               'adaptation_latency_ms_last': '95.0'},
              {'adapted_generation': 'none', 'adaptation_latency_ms_last': 'nan'}]
    monkeypatch.setattr(demo_promp, '_diagnostic_values', lambda bag, prefix: states)
    assert demo_promp.adaptation_latencies('unused.mcap') == [80.5, 95.0]
