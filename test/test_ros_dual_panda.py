"""The dual-Panda cell with no file of the user's (issue 31 item 7): the graph
config/graphs/dual_panda.yaml (``cdmp bringup dual_panda``, the graph of ``cdmp.launch.py
robot:=dual_panda``: every node's config/ file with config/robots/dual_panda/ on top) started as
real processes. Every node gets ready on the model urdf/dual_panda.urdf (two arms,
``tip_links``); the sim (robot dual_panda) receives the streamer's references of the 14 joints
and checks them against the same limits (its reflex); the test checks every reference against
the Panda's limits; and a sphere beside the hands moves each hand away from it (each arm's
coupling). Hand positions are
computed here from pybullet_data's Panda at each arm's base (not the nodes' URDF). Every wait
is on a condition, bounded by a generous timeout.
"""
import os

import numpy as np
import pytest

from conftest import REPO_ROOT, module_domain
from robot_graph import TIMEOUT, assert_ready_on_one_model, graph_fixture

pytestmark = pytest.mark.ros
DOMAIN = module_domain(67)
ARMS = ('left_', 'right_')
URDF = os.path.join(REPO_ROOT, 'urdf', 'dual_panda.urdf')


def _cell():
    """(chains, joint names, lower, upper, velocity) of the cell, from pybullet_data's Panda."""
    from cdmp_ros.core.kinematics import PANDA_JOINTS, dual_panda_chains
    from cdmp_ros.sim.robot_specs import panda_urdf_path
    chains = dual_panda_chains(panda_urdf_path())
    names = [a + j for a in ARMS for j in PANDA_JOINTS]
    return (chains, names, np.r_[chains[0].lower, chains[1].lower],
            np.r_[chains[0].upper, chains[1].upper],
            np.r_[chains[0].velocity_limits, chains[1].velocity_limits])


CHAINS, JOINTS, LOWER, UPPER, VMAX = _cell()


def hand(arm, q):
    """The tool centre point of arm 0 (left) or 1 (right) at the 14 joint positions ``q``."""
    from cdmp_ros.core.kinematics import PointOfInterest
    return CHAINS[arm].forward(np.asarray(q)[7 * arm:7 * arm + 7], [PointOfInterest('ee')])[0]


graph = graph_fixture('dual_panda', DOMAIN, JOINTS, LOWER, UPPER, VMAX)


def test_every_node_gets_ready_on_the_cells_model(graph):
    # the sim builds the cell from pybullet_data's Panda; the other nodes read its URDF
    assert_ready_on_one_model(graph, 'dual_panda', URDF, ('streamer', 'adapter', 'learner'))


def test_the_references_stay_within_the_limits_and_the_sims_reflex(graph):
    """The demonstrated motion of both arms: every reference inside the position and velocity
    limits (checked on arrival), and the sim's reflex (position, velocity, acceleration and
    jerk of every reference it received, on its stamps) counted no error."""
    h, b, _ = graph
    assert h.rests(), h.refs[-1]
    with h.lock:
        refs = list(h.refs)
    assert not h.violations, h.violations[:5]
    t = np.array([r[0] for r in refs]) * 1e-9
    assert np.all(np.diff(t) > 0.0)
    # both arms moved away from where the sim started them (the demonstrations end 1.2 rad
    # from it): measured from the sim's start, not from this node's first reference, which
    # may come late in the motion (its subscription can match the streamer after the sim's)
    start = [n for n in b.graph.nodes if n.name == 'sim'][0].effective_parameters()[
        'initial_positions']
    moved = np.abs(np.array([r[1] for r in refs]) - np.asarray(start)).max(axis=0)
    assert moved[:7].max() > 0.05 and moved[7:].max() > 0.05, moved
    assert h.wait(lambda: 'reflex_errors' in h.state('sim'), TIMEOUT)
    assert h.state('sim')['reflex_errors'] == '0', h.state('sim')


def test_a_sphere_beside_the_hands_moves_each_hand_away(graph):
    """The demonstrations end in a hand-over (the hands 4-10 cm apart): a sphere 12 cm from the
    left hand, on its side away from the right hand, is within the influence distance of both
    hands, and each arm's coupling moves its hand away from it."""
    h, _, _ = graph
    assert h.rests()
    q0 = h.last_q()
    left, right = hand(0, q0), hand(1, q0)
    away = (left - right) / np.linalg.norm(left - right)
    centre = left + 0.12 * away
    n0 = h.n_refs()
    h.publish_sphere('world', centre, 0.08)
    try:
        assert h.wait(lambda: np.linalg.norm(hand(0, h.last_q()) - left) > 0.01, TIMEOUT), \
            (left, hand(0, h.last_q()), h.state('streamer'))
        assert h.wait(lambda: all(
            np.linalg.norm(hand(a, h.last_q()) - centre) > np.linalg.norm(x - centre) + 1e-3
            for a, x in enumerate((left, right))), TIMEOUT), (left, right, h.last_q())
        assert h.wait(lambda: int(h.state('streamer').get('coupled', 0)) > 0, TIMEOUT), \
            h.state('streamer')
    finally:  # the next tests start without the sphere even when this one fails
        h.clear_obstacles()
    assert h.n_refs() > n0 and not h.violations, h.violations[:5]
    assert h.state('sim').get('obstacles') == '0' == h.state('streamer').get('obstacles')
    assert h.state('sim')['reflex_errors'] == '0', h.state('sim')
