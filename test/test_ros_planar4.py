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

from cdmp_ros.cli.cmd_bringup import Bringup, load_graph
from conftest import REPO_ROOT, module_domain, ros_env
from node_harness import NodeHarness, graph_running, stamp_ns

pytestmark = pytest.mark.ros
DOMAIN = module_domain(57)
STARTUP = 120.0  # s; four interpreters with rclpy and pybullet on a loaded 2-core machine
TIMEOUT = 30.0   # s; bounds a failing wait only
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


class Listener(NodeHarness):
    """Records every joint_reference and the violations of the planar4 contract."""

    def __init__(self):
        from sensor_msgs.msg import JointState
        from cdmp_ros.ros import qos
        super().__init__('planar4_test', DOMAIN, spin=False)
        self.refs = []        # (stamp ns, positions, velocities)
        self.violations = []
        self.input_publishers('obstacles')
        self.subscribe(JointState, 'joint_reference', self._on_ref, qos.REFERENCE)
        self.start()

    def _on_ref(self, msg):
        q, qd = np.array(msg.position), np.array(msg.velocity)
        bad = []
        if list(msg.name) != JOINTS:
            bad.append(f'names {list(msg.name)}')
        elif q.shape != (4,) or qd.shape != (4,) or not np.all(np.isfinite(q)) or \
                not np.all(np.isfinite(qd)):
            bad.append(f'positions {q}, velocities {qd}')
        elif np.any(q <= LOWER) or np.any(q >= UPPER):
            bad.append(f'outside the position limits {q}')
        elif np.any(np.abs(qd) > VMAX):
            bad.append(f'above the velocity limits {qd}')
        with self.lock:
            if bad:
                self.violations.append('; '.join(bad))
            else:
                self.refs.append((stamp_ns(msg.header.stamp), q, qd))

    def n_refs(self):
        with self.lock:
            return len(self.refs)

    def last_q(self):
        with self.lock:
            return self.refs[-1][1]

    def state(self, prefix):
        """The newest diagnostics values of the node's state status."""
        with self.lock:
            for d in reversed(self.diag_messages):
                if d.name.startswith(prefix) and d.name.endswith(': state'):
                    return d.values
        return {}


def rests(h, near=None):
    """The reference rests (every joint velocity of the newest reference below 1e-3 rad/s),
    within 0.2 rad of ``near`` if given."""
    def resting():
        with h.lock:
            if not h.refs:
                return False
            _, q, qd = h.refs[-1]
        return np.abs(qd).max() < 1e-3 and (near is None or np.abs(q - near).max() < 0.2)
    return h.wait(resting, TIMEOUT)


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    log_path = tmp_path_factory.mktemp('planar4') / 'graph.log'
    log = open(log_path, 'w')
    b = Bringup(load_graph(os.path.join(REPO_ROOT, 'config', 'graphs', 'planar4.yaml')),
                log=log, extra_env=ros_env(DOMAIN))
    h = Listener()
    b.start()
    with graph_running(b, h, log):
        why = b.wait_ready(STARTUP)
        assert why is None, f'not ready ({why}): {b.not_ready()}\n' + \
            log_path.read_text()[-3000:]
        yield h, b, log_path


def test_every_node_gets_ready_and_the_sim_receives_the_planar_references(graph):
    h, b, log_path = graph
    assert set(b.ready) == {'sim', 'streamer', 'adapter', 'learner'}
    # the sim counts the references it accepted (a reference of other joints is rejected)
    assert h.wait(lambda: int(h.state('sim').get('references_received', 0)) > 100, TIMEOUT), \
        h.state('sim')
    sim = h.state('sim')
    assert sim['robot'] == 'planar4' and sim['rejected_total'] == '0', sim
    # (this node's subscription may match the streamer later than the sim's did)
    assert h.wait(lambda: h.n_refs() > 0, TIMEOUT)
    assert not h.violations, h.violations[:5]
    # one robot model: the sim and the streamer, adapter and learner read the same file
    for node in ('sim', 'streamer', 'adapter'):
        assert h.wait(lambda: h.state(node).get('limits_source'), TIMEOUT), node
        assert os.path.samefile(h.state(node)['limits_source'], URDF), (node, h.state(node))
    assert h.wait(lambda: h.state('learner').get('limits_source'), TIMEOUT)
    assert os.path.samefile(h.state('learner')['limits_source'], URDF)
    assert h.wait(lambda: h.state('learner').get('kind') == 'cdmp', TIMEOUT), h.state('learner')


def test_the_references_stay_within_the_planar4_limits(graph):
    """The reach from the sim's initial pose (the demonstrations' start) to the demonstrated
    goal: every reference inside the position and velocity limits (checked on arrival), their
    accelerations differenced on the stamps within the acceleration limit, and the sim's
    reflex (position, velocity, acceleration, jerk of every reference it received, on its
    stamps) counted no error."""
    h, _, _ = graph
    assert rests(h, near=GOAL), h.refs[-1]
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
    from visualization_msgs.msg import Marker, MarkerArray
    h, _, _ = graph
    assert rests(h)
    q0 = h.last_q()
    ee = ee_position(q0)
    centre = ee + np.array([0.0, 0.15, 0.0])   # 15 cm beside the end of the arm, in its plane
    m = Marker(ns='test', id=1, type=Marker.SPHERE, action=Marker.ADD)
    m.header.frame_id = 'base'
    m.header.stamp = h.node.get_clock().now().to_msg()
    m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, centre)
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 0.08
    n0 = h.n_refs()
    h.publish('obstacles', MarkerArray(markers=[m]))
    try:
        assert h.wait(lambda: np.linalg.norm(ee_position(h.last_q()) - ee) > 0.01, TIMEOUT), \
            (ee, ee_position(h.last_q()), h.state('streamer'))
        assert np.linalg.norm(ee_position(h.last_q()) - centre) > np.linalg.norm(ee - centre)
        assert h.wait(lambda: h.state('sim').get('obstacles') == '1', TIMEOUT)
        assert h.wait(lambda: int(h.state('streamer').get('coupled', 0)) > 0, TIMEOUT), \
            h.state('streamer')
    finally:  # the next tests start without the sphere even when this one fails
        h.publish('obstacles', MarkerArray(markers=[Marker(ns='test', action=Marker.DELETEALL)]))
    assert h.n_refs() > n0 and not h.violations, h.violations[:5]
    assert h.wait(lambda: h.state('sim').get('obstacles') == '0', TIMEOUT)
    assert h.state('sim')['reflex_errors'] == '0', h.state('sim')
