"""Integration: the node graph (sim, streamer, adapter, learner) as real processes over DDS.

One graph serves the module (localhost discovery, a private domain id), started with
:class:`cdmp_ros.cli.cmd_bringup.Bringup` like ``cdmp bringup``. The test process is the user: it
publishes obstacles and goals, listens to ``joint_reference`` (every message checked: names,
size, finite, inside the limits) and to every node's ``diagnostics``. Every wait is on a
condition, bounded by a generous timeout; no check depends on wall-clock durations or rates
(benchmarks/bench_streamer.py --graph sim,adapter measures the stream's timing).
"""
import os
import signal
import time

import numpy as np
import pytest

from cdmp_ros.cli.cmd_bringup import Bringup, parse_graph
from conftest import ros_env, module_domain
from node_harness import graph_running, wait_matched
from streamer_harness import LOWER, PANDA_JOINTS, UPPER, Harness, max_acceleration

pytestmark = pytest.mark.ros
DOMAIN = module_domain(3)
STARTUP = 60.0   # s; five interpreters with rclpy and pybullet on a loaded 2-core machine
TIMEOUT = 30.0   # s; bounds a failing wait only
MAX_ACC = 100.0  # rad/s^2 between consecutive references at 500 Hz: no jump


def _graph():
    return parse_graph({'stop_timeout': 10.0, 'nodes': [
        {'name': 'sim', 'executable': 'sim', 'params_file': 'sim.yaml',
         'parameters': {'control': 'position', 'diagnostics_period': 0.25}},
        {'name': 'streamer', 'executable': 'streamer', 'params_file': 'streamer.yaml',
         'parameters': {'rate': 500.0, 'diagnostics_period': 0.25,
                        'coupling_links': ['panda_link4', 'panda_link6', 'panda_link7'],
                        'coupling.link_radius': 0.06,
                        # the demo's field: a sphere 20 cm away moves the hand by ~3 cm
                        'repeller.gain': 0.03, 'repeller.influence_distance': 0.25}},
        {'name': 'adapter', 'executable': 'adapter', 'params_file': 'adapter.yaml',
         'parameters': {'diagnostics_period': 0.25}},
        {'name': 'learner', 'executable': 'learner', 'params_file': 'learner.yaml'},
    ]})


def status(h, prefix, key=None, since=None):
    """The newest diagnostics values of the status named ``prefix``... (a node's state),
    received after ``since`` if given."""
    with h.lock:
        for t, name, msg, _, kv in reversed(h.diag_messages):
            if since is not None and t < since:
                break
            if name.startswith(prefix) and name.endswith(': state'):
                return kv if key is None else kv.get(key)
    return {} if key is None else None


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log_path = tmp_path_factory.mktemp('graph') / 'graph.log'
    log = open(log_path, 'w')
    b = Bringup(_graph(), log=log, extra_env=ros_env(DOMAIN))
    b.start()
    h = Harness(DOMAIN)
    h.robot_on = False  # the sim is the robot
    with graph_running(b, h, log):
        # evidence from every node, not this node's view of the graph: DDS discovery between
        # two other nodes (learner -> adapter) can lag by seconds on a loaded machine, and a
        # primitive reaching the adapter after the goal would clear that goal
        ok = h.wait(lambda: status(h, 'sim', 'state') is not None and h.n_refs() > 100
                    and 'cdmp' in (status(h, 'streamer', 'primitive') or '')
                    and status(h, 'adapter', 'primitive') == 'cdmp'
                    or b.exited(), STARTUP)
        assert ok and not b.exited(), log_path.read_text()[-3000:]
        # this node's commands reach their subscribers: goal (streamer, adapter), obstacles
        # (streamer, adapter, sim)
        assert wait_matched(h.pub['goal'], 2, STARTUP) and \
            wait_matched(h.pub['obstacles'], 3, STARTUP), log_path.read_text()[-3000:]
        yield h, b, log_path
    assert not h.violations, h.violations[:5]


def _rest(h, timeout=TIMEOUT):
    """Wait until the reference rests (every joint velocity < 1e-3 rad/s)."""
    return h.wait(lambda: np.abs(h.last_ref()[3]).max() < 1e-3, timeout)


def test_the_learned_primitive_is_streamed_to_the_sim(graph):
    h, b, _ = graph
    assert _rest(h)
    q_ref = h.last_ref()[2]
    assert np.all(q_ref > LOWER) and np.all(q_ref < UPPER)
    # the sim follows the reference (position control)
    assert h.wait(lambda: float(status(h, 'sim', 'tracking_error_rad') or 1.0) < 0.02,
                  TIMEOUT), status(h, 'sim')
    # the learner reports what it published (its diagnostics come at their own period)
    assert h.wait(lambda: status(h, 'learner', 'kind') is not None, TIMEOUT), h.diag_messages[-5:]
    assert status(h, 'learner', 'kind') == 'cdmp', status(h, 'learner')


def test_an_obstacle_changes_the_reference_and_the_sim_reports_no_contact(graph):
    from visualization_msgs.msg import Marker, MarkerArray
    from cdmp_ros.core.demo_robot import DemoRobot
    from cdmp_ros.core.kinematics import PointOfInterest
    from cdmp_ros.ros.robot_model import default_urdf_path
    h, b, _ = graph
    assert _rest(h)
    arm = DemoRobot('panda', default_urdf_path())
    chain = arm.model
    q0 = h.last_ref()[2]
    ee = chain.forward(q0, [PointOfInterest('ee')])[0]
    m = Marker(ns='test', id=1, type=Marker.SPHERE, action=Marker.ADD)
    m.header.frame_id = 'panda_link0'
    m.header.stamp = h.node.get_clock().now().to_msg()
    m.pose.position.x, m.pose.position.y, m.pose.position.z = (
        float(ee[0]), float(ee[1]) + 0.2, float(ee[2]))  # 20 cm beside the hand
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 0.08
    contacts0 = int(status(h, 'sim', 'contacts_since_start') or 0)
    h.publish('obstacles', MarkerArray(markers=[m]))
    try:
        # the reference moves away from the sphere
        assert h.wait(lambda: np.linalg.norm(chain.forward(h.last_ref()[2], [PointOfInterest(
            'ee')])[0] - ee) > 0.01, TIMEOUT)
        assert h.wait(lambda: status(h, 'sim', 'obstacles') == '1', TIMEOUT)
        # a sim state reported after 1 s more of simulated time (250 joint_states at 250 Hz)
        # with the sphere covers the avoiding motion
        moved = time.monotonic()
        assert h.wait(lambda: status(h, 'sim', since=moved), TIMEOUT)
        n_js = int(status(h, 'sim', 'joint_states_published', since=moved))
        assert h.wait(lambda: int(status(h, 'sim', 'joint_states_published') or 0)
                      >= n_js + 250, TIMEOUT), status(h, 'sim')
        sim = status(h, 'sim')
        assert int(sim['contacts_since_start']) == contacts0, sim
        assert float(sim['min_obstacle_distance_m']) > 0.0, sim
        # the arm as the coupling sees it (capsules from the elbow to the fingers) moved away
        # from the sphere; the hand alone need not (the links' repellers act too: a soak run
        # ended with the hand 18.3 cm from the sphere, 20 cm before)
        c = [m.pose.position.x, m.pose.position.y, m.pose.position.z]
        assert arm.clearance(h.last_ref()[2], c, 0.04) > arm.clearance(q0, c, 0.04)
    finally:  # the next tests start without the sphere even when this one fails
        h.publish('obstacles', MarkerArray(markers=[Marker(ns='test', action=Marker.DELETEALL)]))
    assert h.wait(lambda: status(h, 'sim', 'obstacles') == '0', TIMEOUT)


def test_a_goal_change_is_followed_without_a_jump(graph):
    h, b, _ = graph
    assert _rest(h)
    goal = h.last_ref()[2] + np.array([0.3, -0.2, 0.2, 0.2, 0.0, -0.2, 0.3])
    i0 = h.n_refs()
    h.publish('goal', h.joint_state(goal))
    assert h.wait(lambda: np.abs(h.last_ref()[2] - goal).max() < 0.02, TIMEOUT)
    refs = h.refs_since(i0)
    assert max_acceleration(refs) < MAX_ACC
    # the adapter retargeted the primitive too (the streamer switched to it without a jump)
    assert h.wait(lambda: status(h, 'adapter', 'outcome') == 'retargeted', TIMEOUT), \
        status(h, 'adapter')


def test_a_killed_adapter_does_not_interrupt_the_stream_and_recovers_the_primitive(graph):
    import subprocess
    h, b, log_path = graph
    proc = b.procs['adapter']
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    # the stream goes on without the adapter: 500 more references (1 s of stream at 500 Hz)
    n0 = h.n_refs()
    assert h.wait(lambda: h.n_refs() >= n0 + 500 or b.procs['streamer'].poll() is not None,
                  TIMEOUT), h.n_refs() - n0
    assert b.procs['streamer'].poll() is None
    # restart it (as a supervisor would); it gets the learner's latched primitive again
    spec = next(s for s in b.graph.nodes if s.name == 'adapter')
    since = time.monotonic()
    new = subprocess.Popen(spec.command(), env=b.env, stdout=open(log_path, 'a'),
                           stderr=subprocess.STDOUT, start_new_session=True)
    b.procs['adapter'] = new

    def recovered():
        with h.lock:
            return any(t >= since and name.startswith('adapter') and kv.get('primitive') ==
                       'cdmp' for t, name, _, _, kv in h.diag_messages)
    assert h.wait(recovered, STARTUP), log_path.read_text()[-2000:]
    assert new.poll() is None
    assert h.last_ref()[2].shape == (len(PANDA_JOINTS),)
