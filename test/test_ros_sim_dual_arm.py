"""The sim node (a real process, ``-p robot:=dual_panda``) runs the result of paper 003 III-C
(cdmp reproduce dual-arm): the adapted mean of the joint ProMP of both arms, published as
``joint_reference`` with the sim's ``left_`` / ``right_`` joint names, is followed (checked on
``joint_states``) without any contact between the two robots or with the table (a CUBE
obstacle), as the sim reports on ``diagnostics``; the original mean, streamed the same way
after a reset, makes the robots collide (so the check can fail).
"""
import time

import numpy as np
import pytest

from conftest import module_domain, wait_for
from node_harness import running
from sim_harness import SimHarness, start_sim

pytestmark = pytest.mark.ros
DOMAIN = module_domain(34)
STARTUP = 30.0   # s; interpreter + rclpy + pybullet start-up on a loaded 2-core machine
TIMEOUT = 30.0   # s; bounds a failing wait only
DURATION = 4.0   # s of streaming per trajectory (the demonstrations last 2 s)
RATE = 100.0     # Hz of the published reference
PATH_TOL = 0.03  # rad; every measured state lies this close to the reference path
GOAL_TOL = 0.01  # rad; settled at the end of the reference


@pytest.fixture(scope='module')
def primitives():
    """The original and the adapted ProMP of the experiment, at a reduced size."""
    from cdmp_ros.core.adaptation.guarantee import adapt
    from cdmp_ros.experiments import exp_dual_arm as exp
    prior = exp.learn_prior(exp.load_demonstrations(), n_basis=5)
    groups = exp.constraints(exp.cell_chains())
    adapted, report = adapt(prior, [c for g in groups.values() for c in g],
                            exp.adaptation_config(5, 20))
    assert report.converged, report.to_text()
    return prior, adapted


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log = tmp_path_factory.mktemp('sim_dual_arm') / 'sim.log'
    proc = start_sim(DOMAIN, ['robot:=dual_panda', 'control:=computed_torque',
                              'diagnostics_period:=0.2'], log_path=str(log))
    h = SimHarness(DOMAIN)
    with running(proc, h, log, lambda: h.n_states() > 10, STARTUP, 'sim'):
        # the sim's joint_reference subscription is matched before anything is streamed
        assert h.wait(lambda: h.pub['joint_reference'].get_subscription_count() > 0, TIMEOUT)
        yield h, proc, log


def _table(h):
    """The table under both robots as a CUBE marker (top 1 cm below the bases, world frame)."""
    from visualization_msgs.msg import Marker, MarkerArray
    m = Marker(ns='table', id=0, type=Marker.CUBE, action=Marker.ADD)
    m.header.frame_id = 'world'
    m.pose.position.x, m.pose.position.y, m.pose.position.z = 0.565, 0.0, -0.025
    m.pose.orientation.w = 1.0
    m.scale.x, m.scale.y, m.scale.z = 1.8, 1.2, 0.03
    h.publish('obstacles', MarkerArray(markers=[m]))


def _stream(h, promp, names):
    """Publish the mean of ``promp`` (positions and velocities) over DURATION at RATE, from
    a minimum-jerk ramp to its start; returns the reference path (n, 14)."""
    q_now = h.q()
    s = np.linspace(0.0, 1.0, int(DURATION * RATE) + 1)
    Y = promp.mean(s)
    Yd = promp.mean(s, derivative=1) / DURATION
    _ramp(h, q_now, Y[0], 1.0, names)
    _paced(h, list(zip(Y, Yd)), names)
    return Y


def _ramp(h, q0, q1, duration, names):
    n = int(duration * RATE)
    msgs = []
    for k in range(n + 1):
        s = k / n
        pos = q0 + (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5) * (q1 - q0)
        vel = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration * (q1 - q0)
        msgs.append((pos, vel))
    _paced(h, msgs, names)


def _paced(h, points, names):
    """Publish ``points`` (position, velocity) as joint_reference (stamped when sent), point k
    once the sim's own clock (the stamps of its joint_states) has advanced k / RATE s: paced
    by a condition on the simulated time, not by sleeping on the wall clock."""
    def stamp():
        with h.lock:
            return h.states[-1][1]
    t0 = stamp()
    for k, (pos, vel) in enumerate(points):
        due = t0 + round(k * 1e9 / RATE)
        assert wait_for(lambda: stamp() >= due, TIMEOUT, period=0.002), (k, stamp() - due)
        h.publish('joint_reference', h.reference(pos, vel, names=names))


def _path_error(states, Y):
    """Largest distance (max over joints) of a measured state to the nearest path sample."""
    Q = np.array([s[3] for s in states])
    return float(np.abs(Q[:, None, :] - Y[None, :, :]).max(axis=2).min(axis=1).max())


def test_sim_follows_the_adapted_mean_without_contact(graph, primitives):
    h, proc, _ = graph
    prior, adapted = primitives
    names = adapted.joint_names
    assert names[0] == 'left_panda_joint1' and names[7] == 'right_panda_joint1'
    with h.lock:
        assert h.states[-1][2] == list(names)     # the sim's joint order is the ProMP's
    _table(h)
    assert h.wait_state(lambda m, kv: kv.get('obstacles') == '1'
                        and np.isfinite(float(kv['min_obstacle_distance_m']))), h.last_state()
    Y = _stream(h, adapted, names)
    t_end = time.monotonic()
    # follows: settles at the end of the reference, and never strays from its path
    assert h.wait(lambda: np.abs(h.q() - Y[-1]).max() < GOAL_TOL, TIMEOUT), h.q() - Y[-1]
    assert np.abs(Y[-1] - Y[0]).max() > 0.5          # the arms did move
    err = _path_error(h.states_since(t_end - DURATION), Y)
    assert err < PATH_TOL, err
    # no contact: a state report after the end, with the robot-robot and table distances
    # monitored (finite), never at or below zero since the start
    assert h.wait_state(lambda m, kv: h.state_after(t_end) is not None), h.last_state()
    _, kv = h.state_after(t_end)
    assert kv['contacts_since_start'] == '0', kv
    assert 0.0 < float(kv['min_robot_distance_since_start_m']) < 1.0, kv
    assert 0.0 < float(kv['min_obstacle_distance_since_start_m']) < 1.0, kv
    assert kv['limit_violations'] == '0', kv
    assert proc.poll() is None


def test_original_mean_makes_the_robots_collide(graph, primitives):
    # the same check on the unadapted primitives: the sim reports the contact
    h, proc, _ = graph
    prior, _ = primitives
    assert h.call('reset').success
    _stream(h, prior, prior.joint_names)
    assert h.wait_state(lambda m, kv: int(kv['contacts_since_start']) > 0
                        and float(kv['min_robot_distance_since_start_m']) <= 0.0), \
        h.last_state()
    assert proc.poll() is None
