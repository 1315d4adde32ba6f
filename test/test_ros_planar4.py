"""The planar 4-link arm with no file of the user's (issue 31, item 7): the graph
config/graphs/planar4.yaml (``cdmp bringup planar4``, the graph of ``cdmp.launch.py
robot:=planar4``: every node's config/ file with config/robots/planar4/ on top) started as real
processes. Every node gets ready; the sim (robot planar4) receives the streamer's references of
the 4 planar joints and checks them against the same limits (its reflex); the test, listening
to ``joint_reference``, checks every message against the planar4 limits read from the URDF
and config/joint_limits/planar4.yaml; and a sphere published on ``obstacles`` beside the end
effector moves the reference away from it (the coupling on the chain from the URDF). Every wait
is on a condition, bounded by a generous timeout.
"""
import os

import numpy as np
import pytest
import yaml

from conftest import REPO_ROOT, module_domain
from robot_graph import TIMEOUT, assert_ready_on_one_model, graph_fixture

pytestmark = pytest.mark.ros
DOMAIN = module_domain(57)
JOINTS = ['joint1', 'joint2', 'joint3', 'joint4']
URDF = os.path.join(REPO_ROOT, 'urdf', 'planar4.urdf')
#: the start of the demonstrations and the sim's initial pose (config/robots/planar4/sim.yaml),
#: and the goal they reach (each demonstration's goal perturbed by N(0, 0.05^2) per joint)
START = np.array([-0.3, 0.7, 0.6, 0.5])
GOAL = np.array([1.0, -0.4, -0.5, -0.3])


def planar4_limits():
    """(lower, upper, velocity, acceleration, jerk) per joint, read from the URDF and the
    shipped joint_limits file (not from the nodes)."""
    from cdmp_ros.core.kinematics.urdf import parse_urdf
    robot = parse_urdf(URDF)
    joints = {j.name: j for j in robot.joints}
    with open(os.path.join(REPO_ROOT, 'config', 'joint_limits', 'planar4.yaml')) as f:
        entries = yaml.safe_load(f)['/**']['ros__parameters']['joint_limits']
    return (np.array([joints[n].lower for n in JOINTS]),
            np.array([joints[n].upper for n in JOINTS]),
            np.array([joints[n].velocity for n in JOINTS]),
            np.array([entries[n]['max_acceleration'] for n in JOINTS]),
            np.array([entries[n]['max_jerk'] for n in JOINTS]))


LOWER, UPPER, VMAX, AMAX, JMAX = planar4_limits()


def ee_position(q):
    """The end effector of the planar arm (4 links of 1 m): sum_i (cos, sin) of q_1 + ... + q_i,
    computed here, not by the nodes' kinematics."""
    theta = np.cumsum(q)
    return np.array([np.cos(theta).sum(), np.sin(theta).sum(), 0.0])


graph = graph_fixture('planar4', DOMAIN, JOINTS, LOWER, UPPER, VMAX)


def test_every_node_gets_ready_and_the_sim_receives_the_planar_references(graph):
    # one robot model: the sim and the streamer, adapter and learner read the same file
    assert_ready_on_one_model(graph, 'planar4', URDF, ('sim', 'streamer', 'adapter', 'learner'))


def test_the_references_stay_within_the_planar4_limits(graph):
    """The reach from the sim's initial pose (the demonstrations' start) to the demonstrated
    goal: every reference inside the position and velocity limits (checked on arrival), their
    accelerations differenced on the stamps within the acceleration limit, and the sim's
    reflex (position, velocity, acceleration, jerk of every reference it received, on its
    stamps) counted no error."""
    h, _, _ = graph
    assert h.rests(near=GOAL), h.refs[-1]
    with h.lock:
        refs = list(h.refs)
    assert not h.violations, h.violations[:5]
    assert np.abs(refs[-1][1] - START).max() > 1.0, refs[-1][1]
    t = np.array([r[0] for r in refs]) * 1e-9
    V = np.array([r[2] for r in refs])
    dt = np.diff(t)
    assert np.all(dt > 0.0)
    acc = np.abs(np.diff(V, axis=0)) / dt[:, None]
    assert np.all(acc <= AMAX * 1.02), acc.max(axis=0)
    assert h.wait(lambda: 'reflex_errors' in h.state('sim'), TIMEOUT)
    sim = h.state('sim')
    assert sim['reflex_errors'] == '0', sim
    assert (JMAX > 0).all() and (AMAX > 0).all()


def test_a_sphere_beside_the_end_effector_moves_the_reference_away(graph):
    h, _, _ = graph
    assert h.rests()
    q0 = h.last_q()
    ee = ee_position(q0)
    centre = ee + np.array([0.0, 0.15, 0.0])   # 15 cm beside the end of the arm, in its plane
    n0 = h.n_refs()
    h.publish_sphere('base', centre, 0.08)
    try:
        assert h.wait(lambda: np.linalg.norm(ee_position(h.last_q()) - ee) > 0.01, TIMEOUT), \
            (ee, ee_position(h.last_q()), h.state('streamer'))
        assert np.linalg.norm(ee_position(h.last_q()) - centre) > np.linalg.norm(ee - centre)
        assert h.wait(lambda: h.state('sim').get('obstacles') == '1', TIMEOUT)
        assert h.wait(lambda: int(h.state('streamer').get('coupled', 0)) > 0, TIMEOUT), \
            h.state('streamer')
    finally:  # the next tests start without the sphere even when this one fails
        h.clear_obstacles()
    assert h.n_refs() > n0 and not h.violations, h.violations[:5]
    assert h.state('sim').get('obstacles') == '0' == h.state('streamer').get('obstacles')
    assert h.state('sim')['reflex_errors'] == '0', h.state('sim')
