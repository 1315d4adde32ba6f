"""A shipped robot's graph started with ``cdmp bringup`` (config/graphs/<robot>.yaml) and a
listener of its ``joint_reference``: the harness of test_ros_planar4.py and
test_ros_dual_panda.py."""
import os
from typing import Sequence

import numpy as np
import pytest

from conftest import REPO_ROOT, ros_env
from node_harness import NodeHarness, graph_running, stamp_ns

STARTUP = 120.0  # s; four interpreters with rclpy and pybullet on a loaded 2-core machine
TIMEOUT = 30.0   # s; bounds a failing wait only


class ReferenceListener(NodeHarness):
    """Records every joint_reference and the violations of the robot's contract: the joint
    names, finite positions and velocities, strictly inside the position limits, within the
    velocity limits (limits given by the test, read from the robot's files)."""

    def __init__(self, name: str, domain: int, joints: Sequence[str], lower, upper, vmax):
        from sensor_msgs.msg import JointState
        from cdmp_ros.ros import qos
        super().__init__(name, domain, spin=False)
        self.joints = list(joints)
        self.lower, self.upper, self.vmax = (np.asarray(v, float) for v in (lower, upper, vmax))
        self.refs = []        # (stamp ns, positions, velocities)
        self.violations = []
        self.input_publishers('obstacles')
        self.subscribe(JointState, 'joint_reference', self._on_ref, qos.REFERENCE)
        self.start()

    def _on_ref(self, msg):
        q, qd = np.array(msg.position), np.array(msg.velocity)
        n = len(self.joints)
        bad = []
        if list(msg.name) != self.joints:
            bad.append(f'names {list(msg.name)}')
        elif q.shape != (n,) or qd.shape != (n,) or not np.all(np.isfinite(q)) or \
                not np.all(np.isfinite(qd)):
            bad.append(f'positions {q}, velocities {qd}')
        elif np.any(q <= self.lower) or np.any(q >= self.upper):
            bad.append(f'outside the position limits {q}')
        elif np.any(np.abs(qd) > self.vmax):
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

    def publish_sphere(self, frame: str, centre, diameter: float) -> None:
        """One sphere marker on ``obstacles``, stamped now."""
        from visualization_msgs.msg import Marker, MarkerArray
        m = Marker(ns='test', id=1, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = frame
        m.header.stamp = self.node.get_clock().now().to_msg()
        m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, centre)
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = float(diameter)
        self.publish('obstacles', MarkerArray(markers=[m]))

    def clear_obstacles(self) -> bool:
        """Remove every obstacle; True once the streamer and the sim report none (False after
        the wait's timeout: callers in ``finally`` blocks do not mask the test's own failure).
        Waiting keeps a late removal from reaching the next test's nodes."""
        from visualization_msgs.msg import Marker, MarkerArray
        self.publish('obstacles', MarkerArray(markers=[Marker(ns='test',
                                                              action=Marker.DELETEALL)]))
        return self.wait(lambda: all(self.state(n).get('obstacles') == '0'
                                     for n in ('streamer', 'sim')))

    def rests(self, near=None):
        """The reference rests (every joint velocity of the newest reference below 1e-3
        rad/s), within 0.2 rad of ``near`` if given."""
        def resting():
            with self.lock:
                if not self.refs:
                    return False
                _, q, qd = self.refs[-1]
            return np.abs(qd).max() < 1e-3 and (near is None or np.abs(q - near).max() < 0.2)
        return self.wait(resting, TIMEOUT)


def graph_fixture(robot: str, domain: int, joints: Sequence[str], lower, upper, vmax):
    """A module fixture: config/graphs/<robot>.yaml started with every node ready, and a
    :class:`ReferenceListener` of the robot's contract; yields ``(listener, bringup, log
    path)`` and stops the graph after the module."""
    @pytest.fixture(scope='module')
    def graph(tmp_path_factory):
        from cdmp_ros.cli.cmd_bringup import Bringup, load_graph
        log_path = tmp_path_factory.mktemp(robot) / 'graph.log'
        log = open(log_path, 'w')
        b = Bringup(load_graph(os.path.join(REPO_ROOT, 'config', 'graphs', f'{robot}.yaml')),
                    log=log, extra_env=ros_env(domain))
        h = ReferenceListener(f'{robot}_test', domain, joints, lower, upper, vmax)
        b.start()
        with graph_running(b, h, log):
            why = b.wait_ready(STARTUP)
            assert why is None, f'not ready ({why}): {b.not_ready()}\n' + \
                log_path.read_text()[-3000:]
            yield h, b, log_path
    return graph


def assert_ready_on_one_model(graph, robot: str, urdf: str, model_nodes: Sequence[str]):
    """Every node of the graph is ready, the sim (``robot``) accepts the streamer's references
    (a reference of other joints would be rejected), every reference received so far keeps the
    contract, the ``model_nodes`` report ``urdf`` as their ``limits_source`` (one robot model),
    and the learner published a CDMP."""
    h, b, _ = graph
    assert set(b.ready) == {'sim', 'streamer', 'adapter', 'learner'}
    assert h.wait(lambda: int(h.state('sim').get('references_received', 0)) > 100, TIMEOUT), \
        h.state('sim')
    sim = h.state('sim')
    assert sim['robot'] == robot and sim['rejected_total'] == '0', sim
    # (this node's subscription may match the streamer later than the sim's did)
    assert h.wait(lambda: h.n_refs() > 0, TIMEOUT)
    assert not h.violations, h.violations[:5]
    for node in model_nodes:
        assert h.wait(lambda: h.state(node).get('limits_source'), TIMEOUT), node
        assert os.path.samefile(h.state(node)['limits_source'], urdf), (node, h.state(node))
    assert h.wait(lambda: h.state('learner').get('kind') == 'cdmp', TIMEOUT), h.state('learner')
