"""The streamer tests' own part: Panda reach primitives, the streamer process, and a test-side
node (:class:`Harness`, a :class:`node_harness.NodeHarness`) that is a fake robot and a
checking listener.

The node publishes ``joint_states`` (echoing the last reference, like a perfect robot) at
100 Hz while ``robot_on`` is set (joints ``robot_names``, by default the arm's in order),
offers publishers for every input topic, and checks EVERY received ``joint_reference``
message: 7 names in order, finite, inside the limits (violations are collected, never
silently dropped).
"""
import math
import time

import numpy as np

from conftest import wait_for  # noqa: F401 -- re-exported to the streamer tests
from node_harness import (LOWER, PANDA_JOINTS, Q_GOAL, Q_START, UPPER, NodeHarness,  # noqa: F401
                          start_node, stop_process)

VMAX = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
FINGER_POSITION = 0.02  # m, the fake robot's finger joints (when listed in robot_names)


# -- primitives ---------------------------------------------------------------------------------
def reach_demo(y0=Q_START, y1=Q_GOAL, duration=2.0, n=401):
    """A minimum-jerk-like joint reach (T, Y)."""
    T = np.linspace(0.0, duration, n)
    s = T / duration
    s = 10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5
    return T, np.asarray(y0) + s[:, None] * (np.asarray(y1) - np.asarray(y0))


def reach_cdmp(y0=Q_START, y1=Q_GOAL, duration=2.0, joint_names=PANDA_JOINTS):
    from cdmp_ros.core.dmp.dmp import CDMP
    T, Y = reach_demo(y0, y1, duration)
    return CDMP(LOWER, UPPER, joint_names=joint_names).fit(T, Y)


def reach_dmp(y0=Q_START, y1=Q_GOAL, duration=2.0):
    from cdmp_ros.core.dmp.dmp import DMP
    T, Y = reach_demo(y0, y1, duration)
    return DMP(7, joint_names=PANDA_JOINTS).fit(T, Y)


#: Limits of :func:`wide_narrow_cdmp`: wider than the robot's on panda_joint1, narrower on
#: panda_joint2; and the tighter of these and the robot's.
WIDE_NARROW_LOWER = np.where(np.arange(7) == 0, -3.5, np.where(np.arange(7) == 1, -0.8, LOWER))
WIDE_NARROW_UPPER = np.where(np.arange(7) == 0, 3.5, np.where(np.arange(7) == 1, 0.4, UPPER))
TIGHT_LOWER = np.maximum(LOWER, WIDE_NARROW_LOWER)
TIGHT_UPPER = np.minimum(UPPER, WIDE_NARROW_UPPER)


def wide_narrow_cdmp():
    """A reach CDMP with the limits WIDE_NARROW_* whose goal on panda_joint1 (3.2) is beyond
    the robot's upper limit (2.9671)."""
    from cdmp_ros.core.dmp.dmp import CDMP
    goal = Q_GOAL.copy()
    goal[0] = 3.2
    T, Y = reach_demo(Q_START, goal, 2.0)
    return CDMP(WIDE_NARROW_LOWER, WIDE_NARROW_UPPER, joint_names=PANDA_JOINTS).fit(T, Y)


# -- the streamer process -----------------------------------------------------------------------
def start_streamer(domain_id, params=(), log_path=None, params_file=None):
    """Start ``python -m cdmp_ros.nodes.streamer`` with ``-p`` parameters (name:=value)."""
    return start_node('streamer', params, domain_id, params_file, log_path=log_path)


# -- the test-side node -------------------------------------------------------------------------
class Harness(NodeHarness):
    target = 'streamer'

    def __init__(self, domain_id: int):
        from sensor_msgs.msg import JointState

        from cdmp_ros.ros import qos

        super().__init__('streamer_test', domain_id, spin=False)
        self.refs = []           # (receive time, stamp ns, positions, velocities)
        self.violations = []
        self.robot_on = True
        self.robot_q = Q_START.copy()
        # names of the fake robot's joint_states (any order; names other than the arm's, such
        # as finger joints, are published at FINGER_POSITION)
        self.robot_names = PANDA_JOINTS
        self.input_publishers('primitive', 'adapted_primitive', 'goal', 'joint_states',
                              'obstacles')
        self.subscribe(JointState, 'joint_reference', self._on_ref, qos.REFERENCE)
        self.node.create_timer(0.01, self._robot)
        self.start()

    # -- background --------------------------------------------------------------------------
    def _on_ref(self, msg):
        t = time.monotonic()
        q = np.array(msg.position)
        qd = np.array(msg.velocity)
        bad = []
        if list(msg.name) != list(PANDA_JOINTS):
            bad.append(f'names {list(msg.name)}')
        if q.shape != (7,) or qd.shape != (7,):
            bad.append(f'sizes {q.shape} {qd.shape}')
        elif not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
            bad.append(f'non-finite {q} {qd}')
        elif np.any(q < LOWER) or np.any(q > UPPER):
            bad.append(f'outside the limits {q}')
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with self.lock:
            if bad:
                self.violations.append('; '.join(bad))
            else:
                self.refs.append((t, stamp, q, qd))
                self.robot_q = q

    def _robot(self):
        if not self.robot_on:
            return
        names = list(self.robot_names)
        with self.lock:
            q = dict(zip(PANDA_JOINTS, self.robot_q.tolist()))
        self.publish('joint_states',
                     self.joint_state([q.get(n, FINGER_POSITION) for n in names], names))

    # -- helpers -----------------------------------------------------------------------------
    def n_refs(self):
        with self.lock:
            return len(self.refs)

    def refs_since(self, index):
        with self.lock:
            return list(self.refs[index:])

    def last_ref(self):
        with self.lock:
            return self.refs[-1] if self.refs else None


def max_acceleration(refs):
    """Largest |change of a joint velocity| / (stamp difference) between consecutive
    references [rad/s^2]: a velocity jump of v at 500 Hz shows as 500 v."""
    if len(refs) < 2:
        return 0.0
    V = np.array([r[3] for r in refs])
    dt = np.diff([r[1] for r in refs]) * 1e-9
    return float((np.abs(np.diff(V, axis=0)).max(axis=1) / np.maximum(dt, 1e-4)).max())


def rate_of(refs):
    if len(refs) < 2:
        return 0.0
    return (len(refs) - 1) / (refs[-1][0] - refs[0][0])


def finite(x):
    return all(math.isfinite(v) for v in x)
