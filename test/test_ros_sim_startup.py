"""The sim node as a real process: start-up failures (exit code 2 with the reason), other
configurations (the planar arm as fast as possible, publishing /clock), and the streamer
driving the sim (the topic contract between two real nodes).

Domain 131, as test_ros_sim.py, whose module-scoped sim has ended before this module runs.
"""
import os

import numpy as np
import pytest
import yaml

from sim_harness import SimHarness, start_sim, stop_process
from node_harness import assert_clean_stop
from conftest import module_domain

pytestmark = pytest.mark.ros
DOMAIN = module_domain(6)
STARTUP = 30.0   # s; interpreter + rclpy + pybullet start-up on a loaded 2-core machine
TIMEOUT = 30.0   # s; bounds a failing wait only


def test_config_file_mirrors_every_parameter(repo_root):
    from cdmp_ros.ros.params import parameter_fields
    from cdmp_ros.sim.node_config import SimConfig
    with open(os.path.join(repo_root, 'config', 'sim.yaml')) as f:
        params = yaml.safe_load(f)['/**']['ros__parameters']
    fields = {f.name: default for f, _, default in parameter_fields(SimConfig)}
    assert set(params) == set(fields) | {'initial_positions'}
    for name, default in fields.items():  # the file states the defaults
        assert params[name] == default, name
    assert np.allclose(params['initial_positions'], [0.0, -np.pi / 4, 0.0, -3 * np.pi / 4,
                                                     0.0, np.pi / 2, np.pi / 4])
    SimConfig(**{k: v for k, v in params.items()})  # and they are valid


STARTUP_CASES = [('control:=velocity', 'control: expected one of'),
                 ('robot:=ur5', 'robot: expected one of'),
                 ('publish_rate:=300.0', 'publish_rate: expected physics_rate (1000)'),
                 ('physics_rate:=50.0', 'physics_rate'),
                 ('initial_positions:=[0.0,0.0,0.0,1.0,0.0,1.0,0.0]', 'initial_positions[3]'),
                 ("initial_positions:=['a','b']", 'initial_positions')]


def test_bad_startup_parameters_exit_nonzero_with_a_reason(tmp_path):
    bad_file = tmp_path / 'bad.yaml'
    bad_file.write_text('/**:\n  ros__parameters:\n    reference_timeout: -3.0\n')
    cases = STARTUP_CASES + [(None, 'reference_timeout')]
    procs = []
    for i, (param, text) in enumerate(cases):  # in parallel: start-up is slow
        log = str(tmp_path / f'{i}.log')
        proc = (start_sim(DOMAIN, [param], log_path=log) if param else
                start_sim(DOMAIN, log_path=log, params_file=str(bad_file)))
        procs.append((proc, text, i))
    try:
        for proc, text, i in procs:
            code = proc.wait(STARTUP)
            log = (tmp_path / f'{i}.log').read_text()
            assert code == 2 and text in log, log
    finally:
        for proc, _, _ in procs:
            stop_process(proc)


def test_planar_arm_as_fast_as_possible_with_clock(tmp_path):
    log = tmp_path / 'planar.log'
    proc = start_sim(DOMAIN, ['robot:=planar4', 'real_time:=false', 'publish_clock:=true',
                              'control:=computed_torque', 'diagnostics_period:=0.2',
                              'max_stamp_age:=60.0'],  # this process may receive /clock late
                     log_path=str(log))
    h = SimHarness(DOMAIN, clock=True)
    try:
        ok = h.wait(lambda: len(h.clocks) > 50 or proc.poll() is not None, STARTUP)
        assert ok and proc.poll() is None, log.read_text()
        # stepping (how much faster than the wall clock is benchmarks/bench_sim_node.py's
        # figure: a real-time factor of 2-8 on an idle machine)
        assert h.wait_state(lambda m, kv: kv.get('robot') == 'planar4'
                            and float(kv.get('real_time_factor', 'nan')) > 0.0, TIMEOUT), \
            h.last_state()
        with h.lock:
            clocks = list(h.clocks)
        # this process may lag behind the joint_states burst: let it catch up with the clock
        assert h.wait(lambda: h.states_since(0.0)[-1][1] >= clocks[-1][1], TIMEOUT)
        with h.lock:
            states = list(h.states)
        assert np.all(np.diff([c for _, c in clocks]) > 0)
        assert np.all(np.array([c for _, c in clocks]) % 4_000_000 == 0)  # whole 4 ms slots
        assert states[-1][2] == ['joint1', 'joint2', 'joint3', 'joint4']
        # the stamps are simulated time, as /clock: whole 4 ms slots (a wall-clock stamp
        # would not be), the same values (this process may drop some of the burst)
        stamps = {s[1] for s in states}
        assert all(st % 4_000_000 == 0 for st in stamps), sorted(stamps)[:8]
        common = [c for _, c in clocks if min(stamps) <= c <= max(stamps)]
        assert any(c in stamps for c in common), (sorted(stamps)[:8], sorted(stamps)[-8:],
                                                  common[:8])
        # a reference stamped in simulated time is accepted and tracked
        goal = np.array([0.5, -0.4, 0.3, 0.2])
        ref = h.reference(goal, names=['joint1', 'joint2', 'joint3', 'joint4'], zero=True)
        c = h.clocks[-1][1]
        ref.header.stamp.sec, ref.header.stamp.nanosec = divmod(c, 1_000_000_000)
        h.publish('joint_reference', ref)
        assert h.wait(lambda: np.abs(h.q() - goal).max() < 1e-3, TIMEOUT), \
            (h.q(), h.last_state())
        _, kv = h.last_state()
        assert kv.get('rejected_total', '0') == '0', kv
    finally:
        h.close()
        code = stop_process(proc)
    assert_clean_stop(code, log.read_text(), 'sim')


def test_streamer_drives_the_sim(tmp_path):
    """The contract of design.md between two real nodes: the streamer's joint_reference
    (reliable) reaches the sim, the sim's joint_states (reliable, 250 Hz) satisfy the
    streamer's best-effort subscription, and the robot follows the streamed reach."""
    from std_msgs.msg import String

    from cdmp_ros.core.primitive_io import dumps_primitive
    from cdmp_ros.ros import qos
    from streamer_harness import Q_GOAL, Q_START, reach_cdmp, start_streamer
    sim = start_sim(DOMAIN, [f'initial_positions:={[float(v) for v in Q_START]}',
                             'diagnostics_period:=0.2'],
                    log_path=str(tmp_path / 'sim.log'), params_file='config/sim.yaml')
    streamer = start_streamer(DOMAIN, [], log_path=str(tmp_path / 'streamer.log'),
                              params_file='config/streamer.yaml')
    h = SimHarness(DOMAIN)
    try:
        pub = h.node.create_publisher(String, 'primitive', qos.LATCHED)
        # the sim took references, and this process has the sim's joint_states (its own
        # subscription may match later than the streamer's on a loaded machine)
        ok = h.wait(lambda: (h.wait_state(lambda m, kv: int(kv.get('references_received', 0))
                                          > 50, 0.1) and h.q() is not None)
                    or sim.poll() is not None or streamer.poll() is not None, STARTUP)
        assert ok and sim.poll() is None and streamer.poll() is None, (
            (tmp_path / 'sim.log').read_text() + (tmp_path / 'streamer.log').read_text())
        assert np.abs(h.q() - Q_START).max() < 0.01  # the streamer holds the measured pose
        pub.publish(String(data=dumps_primitive(reach_cdmp(duration=1.5))))
        assert h.wait(lambda: np.abs(h.q() - Q_GOAL).max() < 0.01, TIMEOUT), h.q() - Q_GOAL
        _, kv = h.last_state()
        assert kv['limit_violations'] == '0' and kv.get('rejected_total', '0') == '0', kv
    finally:
        h.close()
        codes = {'streamer': stop_process(streamer), 'sim': stop_process(sim)}
    for name, code in codes.items():
        assert_clean_stop(code, (tmp_path / f'{name}.log').read_text(), name)
