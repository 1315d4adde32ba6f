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


def run_demo(tmp_path, name, *args, timeout=300):
    """``cdmp demo ARGS --out tmp_path/name --timeout 90``: its exit must be 0; returns the
    summary, the output directory and the command's stdout."""
    out = tmp_path / name
    cdmp = os.path.join(os.path.dirname(sys.executable), 'cdmp')
    r = subprocess.run([cdmp, 'demo', *args, '--out', str(out), '--timeout', '90'],
                       env=ros_env(DOMAIN), capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    return json.loads((out / 'summary.json').read_text()), out, r.stdout


def test_cdmp_demo_runs_end_to_end(tmp_path):
    s, out, stdout = run_demo(tmp_path, 'demo', timeout=240)
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
    assert 'minimum robot-obstacle distance' in stdout


def test_cdmp_demo_promp_adapts_to_the_obstacle(tmp_path):
    """``cdmp demo --kind promp``: the obstacle triggers constrained adaptations, and the
    adapted distribution keeps the hand and the link away from the sphere far more often than
    the prior (checked by sampling, independently of the adapter)."""
    s, out, stdout = run_demo(tmp_path, 'demo_promp', '--kind', 'promp')
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
    assert 'constrained adaptations after the drop' in stdout


def test_cdmp_demo_promp_moving_obstacle(tmp_path):
    """``cdmp demo --kind promp --motion cross`` (issue 13 item 2): a sphere crossing the path
    at 0.2 m/s, published at 30 Hz. The adapter stays current (its last adaptation answers the
    last obstacle message; the latest request wins, none waits in a queue), the coupling terms
    act as the inner layer, and the simulated robot stays out of contact and inside its
    limits."""
    s, out, stdout = run_demo(tmp_path, 'demo_cross', '--kind', 'promp', '--motion', 'cross')
    p = s['promp']
    assert p['obstacle_messages'] >= 60  # 0.6 m at 0.2 m/s, 30 per second
    assert p['adaptations'] >= 2
    assert p['adapter_current'] is True
    assert 0 <= p['adapter_queued'] <= 1  # at most the request being solved
    assert p['adapter_requests']['requests_received'] >= p['obstacle_messages'] // 2
    assert s['contacts'] == 0 and s['min_obstacle_distance_m'] > 0.0
    assert s['limit_violations'] == 0 and 0.0 < s['reference_limit_usage'] < 1.0
    assert s['latency_samples'] >= 1  # the streamer's coupling saw the obstacle (inner layer)


def test_cdmp_demo_dual_adapts_both_arms_jointly(tmp_path):
    """``cdmp demo --kind dual`` (issue 29 item 5): two Pandas learn a hand-over as one ProMP;
    the sphere lands midway between the hands, and each adaptation avoids it with both arms and
    keeps the arms arm_clearance apart (mutual avoidance). Checked on what the run did: the
    sim's distances (links to the sphere, links of one arm to the other's), the references'
    limits, and by sampling both distributions independently of the adapter."""
    s, out, stdout = run_demo(tmp_path, 'demo_dual', '--kind', 'dual')
    assert s['kind'] == 'dual' and len(s['joint_names']) == 14
    p = s['promp']
    assert p['adaptations'] >= 1 and p['adapter_current'] is True
    assert s['contacts'] == 0 and s['min_obstacle_distance_m'] > 0.0
    assert s['min_robot_distance_m'] > 0.0 and s['min_hand_distance_m'] > 0.0
    assert s['limit_violations'] == 0 and 0.0 < s['reference_limit_usage'] < 1.0
    assert s['reflex_errors'] == 0
    assert all(s['kinematic_limits'][k]['over'] == 0
               for k in ('velocity', 'acceleration', 'jerk'))
    # the sphere and the hand-over are on the prior's way; the adaptation moves both off it
    prior, adapted = p['prior_violation'], p['adapted_violation']
    assert prior['trajectory'] > 0.1
    assert adapted['trajectory_upper95'] < prior['trajectory']
    assert p['arm_clearance_m'] > 0.0
    arms_prior, arms_adapted = p['prior_arm_violation'], p['adapted_arm_violation']
    assert arms_prior['min_arm_distance_mean_path_m'] < p['arm_clearance_m']
    assert arms_adapted['min_arm_distance_mean_path_m'] >= p['arm_clearance_m']
    assert arms_adapted['trajectory_upper95'] < arms_prior['trajectory']
    # one adaptation of both arms: its constraints name points of either arm and their pairs
    names = [n for group in p['adapted_laws'].values() for n in group]
    for prefix in ('obstacle_0_left_', 'obstacle_0_right_', 'arms_left_'):
        assert any(n.startswith(prefix) for n in names), (prefix, names)
    md = (out / 'summary.md').read_text()
    assert 'minimum distance between the arms' in md
    assert (f'P(two points of different arms within {p["arm_clearance_m"] * 100:.0f} cm), '
            'adapted') in md
    for path in s['plots'] + [s['snapshot']]:
        assert os.path.getsize(path) > 1000, path


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
