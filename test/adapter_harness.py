"""The adapter tests' own part (also used by the adapter benchmark): ProMP and CDMP reach
primitives, the adapter process, and a test-side node (:class:`Harness`, a
:class:`node_harness.NodeHarness`) with publishers for every input topic and a recorder of
``adapted_primitive``, ``visualization`` and ``diagnostics``.
"""
import hashlib
import json
import os
import time

import numpy as np

from node_harness import (PANDA_JOINTS, Q_GOAL, Q_START, NodeHarness, start_node,  # noqa: F401
                          stop_process)


def panda_urdf():
    import pybullet_data
    return os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf')


def reach_promp(n_basis=6, n_demos=6, seed=0, y0=Q_START, y1=Q_GOAL, joint_names=PANDA_JOINTS):
    """A 7-DoF ProMP learned from noisy minimum-jerk reaches y0 -> y1."""
    from cdmp_ros.core.promp.promp import ProMP, RbfBasis
    rng = np.random.default_rng(seed)
    T = np.linspace(0.0, 2.0, 50)
    s = T / 2.0
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    demos = []
    for _ in range(n_demos):
        a = np.asarray(y0) + 0.02 * rng.standard_normal(7)
        b = np.asarray(y1) + 0.02 * rng.standard_normal(7)
        bump = 0.05 * rng.standard_normal(7)
        demos.append((T, a + np.outer(s, b - a) + np.outer(np.sin(np.pi * s), bump)))
    return ProMP.fit(demos, RbfBasis.uniform(n_basis), prior_strength=2.0,
                     joint_names=joint_names)


def reach_cdmp(y0=Q_START, y1=Q_GOAL, duration=2.0):
    from cdmp_ros.core.dmp.dmp import CDMP
    from cdmp_ros.core.kinematics import panda_chain
    chain = panda_chain(panda_urdf())
    T = np.linspace(0.0, duration, 201)
    s = T / duration
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    Y = np.asarray(y0) + s[:, None] * (np.asarray(y1) - np.asarray(y0))
    return CDMP(chain.lower, chain.upper, joint_names=PANDA_JOINTS).fit(T, Y)


def start_adapter(domain_id, params=(), log_path=None, params_file='config/adapter.yaml',
                  remaps=()):
    """Start ``python -m cdmp_ros.nodes.adapter`` with ``-p`` parameters (name:=value) and
    ``-r`` remappings (from:=to)."""
    return start_node('adapter', params, domain_id, params_file, remaps, log_path)


class Harness(NodeHarness):
    target = 'adapter'

    def __init__(self, domain_id: int):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String
        from visualization_msgs.msg import MarkerArray

        from cdmp_ros.ros import qos

        # qos.LATCHED (reliable, transient local) with a deep queue: matches the adapter's
        # publisher, gets its latched message, and keeps every answer published after it
        answers = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        super().__init__('adapter_test', domain_id, spin=False)
        self.adapted = []        # (receive time, dict)
        self.viz = []            # (receive time, MarkerArray)
        self.input_publishers('primitive', 'goal', 'goal_point', 'constraints', 'joint_states',
                              'obstacles')
        # every answer, not the latest only: a warm answer and its refinement, published in
        # quick succession, would otherwise replace each other in a keep-last-1 queue before
        # the spin thread takes the first (the tests match answers by their trigger stamp)
        self.subscribe(String, 'adapted_primitive', self._on_adapted, answers)
        self.subscribe(MarkerArray, 'visualization', self._on_viz, qos.LATCHED)
        self.robot_q = None      # published on joint_states at 20 Hz while not None
        self.node.create_timer(0.05, self._robot)
        self.start()

    def _on_adapted(self, msg):
        t = time.monotonic()
        with self.lock:
            self.adapted.append((t, json.loads(msg.data)))

    def _on_viz(self, msg):
        with self.lock:
            self.viz.append((time.monotonic(), msg))

    def _robot(self):
        q = self.robot_q
        if q is not None:
            self.publish('joint_states', self.joint_state(q))

    # -- helpers -----------------------------------------------------------------------------
    def n_adapted(self):
        with self.lock:
            return len(self.adapted)

    def last_adapted(self):
        with self.lock:
            return self.adapted[-1][1] if self.adapted else None

    def history(self, n: int = 6) -> list:
        """The last ``n`` adapted primitives in brief, for a failing assertion's message:
        (request id, trigger, continues, start, start note, status)."""
        with self.lock:
            out = []
            for _, d in self.adapted[-n:]:
                meta = d.get('metadata', {})
                a, r = meta.get('adapter', {}), meta.get('adaptation', {})
                out.append((a.get('request_id'), a.get('trigger'), a.get('continues'),
                            r.get('start'), r.get('start_note'), r.get('status')))
            return out

    def wait_adapted(self, n0, timeout=30.0, trigger=None, source=None, pred=None):
        """Wait for an adapted primitive after the first ``n0`` (caused by ``trigger``,
        adapted from the primitive JSON text ``source``, with ``pred(dict)`` true, if given);
        returns its dict or None."""
        sha = None if source is None else hashlib.sha1(source.encode()).hexdigest()

        def match():
            with self.lock:
                for _, d in self.adapted[n0:]:
                    meta = d.get('metadata', {}).get('adapter', {})
                    if ((trigger is None or meta.get('trigger') == trigger)
                            and (sha is None or meta.get('source_sha1') == sha)
                            and (pred is None or pred(d))):
                        return d
            return None
        if self.wait(lambda: match() is not None, timeout):
            return match()
        return None

    states_since = NodeHarness.statuses_since

    def wait_state(self, pred, since, timeout=30.0):
        """Wait for an adapter state status after ``since`` with pred(message, level, kv)."""
        out = []

        def found():
            for st in self.statuses_since(since):
                if pred(*st):
                    out.append(st)
                    return True
            return False
        return out[0] if self.wait(found, timeout) else None

    def last_viz(self):
        with self.lock:
            return self.viz[-1][1] if self.viz else None

    def make_point(self, xyz, frame='panda_link0', stamp_offset=0.0):
        from geometry_msgs.msg import PointStamped
        from node_harness import set_stamp
        msg = PointStamped()
        msg.header.frame_id = frame
        set_stamp(msg.header, self.now_ns() + int(stamp_offset * 1e9))
        msg.point.x, msg.point.y, msg.point.z = (float(v) for v in xyz)
        return msg

    def sphere(self, center, radius, mid=1, ns='test'):
        """A SPHERE marker of ``radius`` [m] at ``center``, stamped now."""
        from markers import marker
        m = marker(ns=ns, id=mid, position=center, size=2.0 * radius)
        m.header.stamp = self.node.get_clock().now().to_msg()
        return m
