"""The learner as a real process (``python -m cdmp_ros.nodes.learner``), driven over DDS.

One learner process serves the module (its own private domain, localhost only), started from
config/learner.yaml with narrow explicit limits around the sample demonstrations (so that
exploration noise would leave them for a plain DMP). The test process publishes
demonstrations, calls ``~/refit``, ``~/save`` and ``~/improve``, and reads ``primitive`` and
``diagnostics``. Each bad-input case publishes its input and waits for the matching
``diagnostics`` entry; the node must stay up (and exit 0 on SIGINT at the end).
"""
import os
import shutil
import time

import numpy as np
import pytest

from conftest import REPO_ROOT, module_domain
from learner_harness import PANDA_JOINTS, LearnerHarness, start_learner
from node_harness import (GOAL_CASES, assert_clean_stop, bad_joint_state, config_file_parameters,
                          expect_startup_failures, parameter_defaults, running, stop_process)

pytestmark = pytest.mark.ros
DOMAIN = module_domain(4)
STARTUP = 30.0  # s; interpreter + rclpy start-up on a loaded 2-core machine
TIMEOUT = 30.0  # s; bounds a failing wait only
BAGS = os.path.join(REPO_ROOT, 'bags', 'panda_reach')


def bag_demos():
    from cdmp_ros.bag import read_demonstrations
    return read_demonstrations(BAGS)


def narrow_limits():
    """Demonstrated range +- 0.1 rad (rounded): inside the Panda's, tight for exploration."""
    Ys = np.vstack([Y for _, Y, _ in bag_demos()])
    return np.round(Ys.min(0) - 0.1, 2), np.round(Ys.max(0) + 0.1, 2)


def _list(v):
    return '[' + ', '.join(f'{x:.2f}' for x in v) + ']'


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log = tmp_path_factory.mktemp('learner') / 'learner.log'
    lo, hi = narrow_limits()
    t_start = time.monotonic()
    proc = start_learner(DOMAIN, ['diagnostics_period:=0.2', 'max_input_rate:=1000.0',
                                  'demonstration_gap:=1.0', f'limits.lower:={_list(lo)}',
                                  f'limits.upper:={_list(hi)}', 'improve.shape_std:=100.0',
                                  'improve.updates:=30', 'improve.rollouts_per_update:=8'],
                         log_path=str(log), params_file='config/learner.yaml')
    h = LearnerHarness(DOMAIN)
    with running(proc, h, log, lambda: h.n_primitives() > 0, STARTUP, 'learner'):
        h.first_primitive_s = h.primitives[0][0] - t_start
        h.limits = (lo, hi)
        yield h, proc, log


def alive(h, proc):
    assert proc.poll() is None, 'learner died'
    assert h.call('refit').success  # still serving (and fitting)


# -- normal operation --------------------------------------------------------------------------
def test_publishes_the_bag_primitive_at_start(graph):
    from cdmp_ros.core.primitive_io import primitive_from_dict
    h, proc, log = graph
    d = h.last_primitive()
    print(f'process start -> first primitive received: {h.first_primitive_s:.2f} s')
    assert d['kind'] == 'cdmp' and d['joint_names'] == list(PANDA_JOINTS)
    assert d['metadata']['demonstrations']['from_bags'] == 5
    assert d['limits']['lower'] == pytest.approx(h.limits[0].tolist(), abs=1e-12)
    goals = np.array([Y[-1] for _, Y, _ in bag_demos()])
    assert np.allclose(d['dmp']['goal'], goals.mean(axis=0), atol=1e-12)
    prim = primitive_from_dict(d)
    Y = prim.rollout(dt=0.01).Y
    assert np.abs(Y[-1] - goals.mean(axis=0)).max() < 0.02
    text = 'cdmp from 5 demonstration(s) (5 from bags, 0 from the topic)'
    assert h.wait(lambda: text in log.read_text(), TIMEOUT), log.read_text()


def test_topic_demonstration_with_shuffled_names_is_mapped_and_refitted(graph):
    h, proc, _ = graph
    T, Y, _ = bag_demos()[2]
    Y = Y + np.linspace(0.0, 0.05, 7)  # a distinct goal, still inside the limits
    perm = [6, 2, 0, 5, 1, 3, 4]
    _, kv0 = h.last_state()
    n0 = int(kv0.get('topic_demonstrations', 0))
    h.publish_demo(T, Y, order=perm, period=0.002)
    assert h.wait(lambda: int(h.last_state()[1].get('topic_demonstrations', 0)) == n0 + 1,
                  TIMEOUT)
    k = h.n_primitives()
    r = h.call('refit')
    assert r.success and f'{n0 + 1} from the topic' in r.message, r.message
    assert h.wait(lambda: h.n_primitives() > k, TIMEOUT)
    d = h.last_primitive()
    goals = [y[-1] for _, y, _ in bag_demos()] + [Y[-1]] * (n0 + 1)
    assert d['metadata']['demonstrations']['from_topic'] == n0 + 1
    assert np.allclose(d['dmp']['goal'], np.mean(goals, axis=0), atol=1e-9)


def test_a_gap_ends_a_demonstration_and_auto_refit_publishes(graph):
    h, proc, _ = graph
    T, Y, _ = bag_demos()[0]
    n0 = int(h.last_state()[1].get('topic_demonstrations', 0))
    k = h.n_primitives()
    assert h.set_parameter('auto_refit', True).successful
    try:
        h.publish_demo(T[:40], Y[:40], end=False, period=0.002)  # no end marker: a gap ends it
        assert h.wait(lambda: int(h.last_state()[1].get('topic_demonstrations', 0)) == n0 + 1,
                      TIMEOUT)
        assert h.wait(lambda: h.n_primitives() > k, TIMEOUT)
        assert h.last_primitive()['metadata']['demonstrations']['from_topic'] == n0 + 1
    finally:
        assert h.set_parameter('auto_refit', False).successful


# -- bad input on demonstration: one test per case --------------------------------------------
def _bad(h, case):
    from sensor_msgs.msg import JointState
    q = bag_demos()[0][1][0]
    now = h.now_ns()
    if case == 'non_monotonic':
        return [h.joint_state(q, stamp_ns=now), h.joint_state(q, stamp_ns=now - 10 ** 8)]
    if case == 'too_short':
        return [h.joint_state(q, stamp_ns=now + i * 10 ** 7) for i in range(3)] + [JointState()]
    msg = bad_joint_state(lambda dt: h.joint_state(q, stamp_ns=now + int(dt * 10 ** 9)), case,
                          inf=float('inf'))
    if case == 'outside_limits':
        msg.position[1] = float(h.limits[1][1] + 0.5)
    return [msg]


BAD_CASES = dict(  # case -> expected text in the diagnostics reason
    GOAL_CASES, nan="position of 'panda_joint3': expected a finite value, got nan",
    inf="position of 'panda_joint5': expected a finite value, got inf",
    outside_limits="of 'panda_joint2': ", non_monotonic='non-monotonic time',
    too_short='expected at least min_samples=10')


@pytest.mark.parametrize('case', sorted(BAD_CASES))
def test_bad_demonstration_samples_are_rejected(graph, case):
    from sensor_msgs.msg import JointState
    h, proc, _ = graph
    h.reject('demonstration', lambda: _bad(h, case), BAD_CASES[case])
    assert proc.poll() is None
    h.demo_pub.publish(JointState())  # discard what a case left pending, before the next one
    t1 = time.monotonic()
    assert h.wait(lambda: h.last_state()[1].get('pending_samples') == '0'
                  and h.diag_messages[-1][0] > t1, TIMEOUT)


def test_flooding_is_dropped_and_reported(graph):
    from sensor_msgs.msg import JointState
    h, proc, _ = graph
    assert h.set_parameter('max_input_rate', 100.0).successful
    try:
        t0 = time.monotonic()

        def burst():  # end markers, harmless when admitted, until the node reports drops
            for _ in range(200):
                h.demo_pub.publish(JointState())
            return h.wait_diag('flooding: more than 100 messages/s', t0, timeout=0.0,
                               name='input demonstration')
        assert h.wait(burst, TIMEOUT), h.recent_diag()
    finally:
        assert h.set_parameter('max_input_rate', 1000.0).successful
    alive(h, proc)


def test_bad_and_corrupted_bags_are_reported_and_the_good_one_used(graph, tmp_path):
    h, proc, _ = graph
    corrupt = tmp_path / 'corrupt'
    shutil.copytree(os.path.join(BAGS, 'demo_00'), corrupt)
    mcap = next(corrupt.glob('*.mcap'))
    data = bytearray(mcap.read_bytes())
    data[2000:6000] = b'\xab' * 4000
    mcap.write_bytes(bytes(data))
    truncated = tmp_path / 'truncated'
    shutil.copytree(os.path.join(BAGS, 'demo_01'), truncated)
    mcap = next(truncated.glob('*.mcap'))
    mcap.write_bytes(mcap.read_bytes()[:10000])
    bags = [str(tmp_path / 'missing'), str(corrupt), str(truncated),
            os.path.join(REPO_ROOT, 'bags', 'dual_panda'), BAGS]
    assert h.set_parameter('demonstration_bags', bags).successful
    try:
        t0 = time.monotonic()
        r = h.call('refit')
        assert r.success and '5 from bags' in r.message, r.message
        for text in ("missing': not found", "corrupt': ", 'the file is truncated',
                     "dual_panda': bag", "missing joints ['panda_joint1'"):
            assert h.wait_diag(text, t0, name='input demonstration_bags'), (text,
                                                                            h.recent_diag())
        assert h.set_parameter('demonstration_bags', bags[:4]).successful
        r = h.call('refit')  # the topic demonstrations alone
        assert r.success and '0 from bags' in r.message, r.message
    finally:
        assert h.set_parameter('demonstration_bags', ['bags/panda_reach']).successful
    alive(h, proc)


def test_save_writes_the_primitive_file(graph, tmp_path):
    from cdmp_ros.core.primitive_io import load_primitive, primitive_to_dict
    h, proc, _ = graph
    path = tmp_path / 'reach.json'
    assert h.set_parameter('primitive_path', str(path)).successful
    r = h.call('save')
    assert r.success and r.message == str(path)
    assert primitive_to_dict(load_primitive(path)) == h.last_primitive()
    assert h.set_parameter('primitive_path', str(tmp_path / 'no' / 'dir.json')).successful
    r = h.call('save')
    assert not r.success and 'cannot write' in r.message
    alive(h, proc)


def test_improve_runs_pi2_in_a_worker_within_the_limits(graph):
    from cdmp_ros.core.dmp.dmp import limit_usage
    from cdmp_ros.core.primitive_io import primitive_from_dict
    h, proc, _ = graph
    t0 = time.monotonic()
    k = h.n_primitives()
    r = h.call('improve')
    assert r.success and '30 PI2 updates of 8 rollouts' in r.message, r.message
    again = h.call('improve')
    assert not again.success and 'already running' in again.message
    refit = h.call('refit')  # the node stays responsive, and refuses to refit meanwhile
    assert not refit.success and 'improvement is running' in refit.message
    assert h.wait_diag('improving: update', t0, timeout=30, name='state')
    assert h.wait(lambda: h.last_state()[1].get('improve', '').startswith('done'), 60)
    kv = h.last_state()[1]
    before, after = float(kv['improve_cost_before']), float(kv['improve_cost_after'])
    print(f'improve: cost {before:.4g} -> {after:.4g}, {kv["improve_rollouts"]} rollouts in '
          f'{kv["improve_time_s"]} s, max limit usage {kv["improve_max_limit_usage"]}')
    assert after < 0.5 * before
    assert kv['improve_rollouts'] == '240' and kv['improve_rollouts_outside_limits'] == '0'
    # exploration went close to the narrow limits (a plain DMP leaves them: test_core_improve)
    assert 0.9 < float(kv['improve_max_limit_usage']) < 1.0
    assert h.wait(lambda: h.n_primitives() > k, TIMEOUT)
    d = h.last_primitive()
    assert d['metadata']['pi2']['updates'] == 30
    prim = primitive_from_dict(d)
    assert limit_usage(prim.rollout(dt=0.005).Y, *h.limits) < 1.0
    alive(h, proc)


def test_improve_against_the_sim(graph):
    h, proc, _ = graph
    for name, value in (('improve.cost', 'sim'), ('improve.updates', 2),
                        ('improve.rollouts_per_update', 3)):
        assert h.set_parameter(name, value).successful
    try:
        t0 = time.monotonic()
        r = h.call('improve')
        assert r.success and "cost 'sim'" in r.message, r.message
        assert h.wait(lambda: h.last_state()[1].get('improve') == 'done 2 updates', 60), \
            h.recent_diag()
        kv = h.last_state()[1]
        assert kv['improve_rollouts'] == '6' and kv['improve_rollouts_outside_limits'] == '0'
        assert float(kv['improve_cost_after']) > 0.0
        # diagnostics arrive in order: a failure would have been received before 'done'
        assert not h.wait_diag('improvement failed', t0, timeout=0.0)
    finally:
        for name, value in (('improve.cost', 'scripted'), ('improve.updates', 30),
                            ('improve.rollouts_per_update', 8)):
            h.set_parameter(name, value)
    alive(h, proc)


def test_runtime_parameter_changes_are_validated(graph):
    h, proc, _ = graph
    assert "kind: expected one of ['cdmp', 'dmp', 'promp']" in h.refusal('kind', 'spline')
    assert 'alpha_y' in h.refusal('dmp.alpha_y', -1.0)
    assert 'rollouts_per_update' in h.refusal('improve.rollouts_per_update', 1)
    assert 'read-only' in h.refusal('joint_names', ['a', 'b']).lower()
    assert 'read-only' in h.refusal('limits.lower', [0.0] * 7).lower()
    r = h.set_parameter('kind', 'promp')
    assert r.successful, r.reason
    try:
        k = h.n_primitives()
        r = h.call('refit')
        assert r.success and 'promp from' in r.message, r.message
        assert h.wait(lambda: h.n_primitives() > k, TIMEOUT)
        assert h.last_primitive()['kind'] == 'promp'
        r = h.call('improve')
        assert not r.success and 'PI2 improves dmp and cdmp primitives' in r.message
    finally:
        assert h.set_parameter('kind', 'cdmp').successful
    alive(h, proc)


# -- start-up ----------------------------------------------------------------------------------
STARTUP_CASES = [('kind:=spline', 'kind: expected one of'),
                 ('dmp.n_weights_per_dim:=0', 'n_weights_per_dim'),
                 ('limits.lower:=[0.0, 1.0]', 'limits.lower/upper: expected 7 values'),
                 ('improve.cost:=bogus', "cost: expected one of ['scripted', 'sim']")]


def test_bad_startup_parameters_and_files_exit_nonzero_and_bad_bags_do_not(tmp_path):
    logs = [str(tmp_path / f'{i}.log') for i in range(len(STARTUP_CASES))]
    procs = [(start_learner(173 + i, [param], log_path=logs[i]), text, logs[i])
             for i, (param, text) in enumerate(STARTUP_CASES)]  # in parallel: start-up is slow
    broken = tmp_path / 'broken.yaml'
    broken.write_text('/**:\n  ros__parameters:\n    kind: [unclosed\n')
    broken_proc = start_learner(177, [], log_path=str(tmp_path / 'broken.log'),
                                params_file=str(broken))
    bad_bags = start_learner(178, ["demonstration_bags:=['/nonexistent/bag']",
                                   'diagnostics_period:=0.2'],
                             log_path=str(tmp_path / 'bags.log'))
    h = None
    try:
        expect_startup_failures(procs, STARTUP)
        code = broken_proc.wait(STARTUP)  # rclpy refuses the file before the node exists
        log = (tmp_path / 'broken.log').read_text()
        assert code != 0 and "Couldn't parse params file" in log and 'line 3' in log, log
        h = LearnerHarness(178)
        r = h.call('refit')
        assert not r.success and "'/nonexistent/bag': not found" in r.message, r.message
        assert h.wait_diag("'/nonexistent/bag': not found", 0.0, timeout=STARTUP,
                           name='input demonstration_bags'), (tmp_path / 'bags.log').read_text()
        assert bad_bags.poll() is None and h.n_primitives() == 0
        r = h.call('save')
        assert not r.success and 'no primitive' in r.message
    finally:
        if h is not None:
            h.close()
        stop_process(broken_proc)  # expect_startup_failures stopped the others
        assert_clean_stop(stop_process(bad_bags), (tmp_path / 'bags.log').read_text(), 'learner')


# -- files -------------------------------------------------------------------------------------
def test_config_file_mirrors_every_parameter_with_its_default():
    from cdmp_ros.core.dmp.dmp import DmpConfig
    from cdmp_ros.core.dmp.improve import CostConfig, ImproveConfig
    from cdmp_ros.core.learning import LearnerConfig, PrompLearnConfig
    assert config_file_parameters('learner') == parameter_defaults(
        [('', LearnerConfig), ('dmp', DmpConfig), ('promp', PrompLearnConfig),
         ('improve', ImproveConfig), ('cost', CostConfig)])


def test_default_bags_resolve_in_the_source_tree_and_an_install(tmp_path, monkeypatch):
    from cdmp_ros.ros.learner_improve import resolve_bag_path
    monkeypatch.chdir(tmp_path)
    assert resolve_bag_path('bags/panda_reach') == BAGS
    share = tmp_path / 'prefix' / 'share' / 'cdmp_ros' / 'bags' / 'installed_only'
    share.mkdir(parents=True)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path / 'prefix'))
    assert resolve_bag_path('bags/installed_only') == str(share)
    assert resolve_bag_path('bags/nowhere') == 'bags/nowhere'
