"""The sim tests' own part: the sim process and a test-side node (:class:`SimHarness`, a
:class:`node_harness.NodeHarness`) that publishes references and obstacles, records everything
the sim publishes and calls its services.
"""
import time

import numpy as np

from node_harness import (LOWER, PANDA_JOINTS, UPPER, NodeHarness, start_node,  # noqa: F401
                          stamp_ns, stop_process)

PANDA_HOME = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])


def start_sim(domain_id, params=(), log_path=None, params_file=None):
    """Start ``python -m cdmp_ros.nodes.sim`` with ``-p`` parameters (name:=value)."""
    return start_node('sim', params, domain_id, params_file, log_path=log_path)


class SimHarness(NodeHarness):
    target = 'sim'

    def __init__(self, domain_id: int, clock: bool = False):
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger

        super().__init__('sim_test', domain_id, spin=False)
        n = self.node
        self.states = []         # (receive time, stamp ns, names, q, qd, effort)
        self.poses = []          # (receive time, stamp ns, frame, position (3,), quat (4,))
        self.clocks = []         # (receive time, clock ns)
        self.input_publishers('joint_reference', 'obstacles')
        self.subscribe(JointState, 'joint_states', self._on_js)   # reliable, depth 1000
        self.subscribe(PoseStamped, 'ee_pose', self._on_pose)
        if clock:
            from rosgraph_msgs.msg import Clock
            self.subscribe(Clock, '/clock', self._on_clock, 10)
        self.clients = {name: n.create_client(Trigger, f'/sim/{name}')
                        for name in ('snapshot', 'reset')}
        self.start()

    # -- background --------------------------------------------------------------------------
    def _on_js(self, msg):
        rec = (time.monotonic(), stamp_ns(msg.header.stamp), list(msg.name),
               np.array(msg.position), np.array(msg.velocity), np.array(msg.effort))
        with self.lock:
            self.states.append(rec)

    def _on_pose(self, msg):
        p, o = msg.pose.position, msg.pose.orientation
        rec = (time.monotonic(), stamp_ns(msg.header.stamp), msg.header.frame_id,
               np.array([p.x, p.y, p.z]), np.array([o.x, o.y, o.z, o.w]))
        with self.lock:
            self.poses.append(rec)

    def _on_clock(self, msg):
        with self.lock:
            self.clocks.append((time.monotonic(), stamp_ns(msg.clock)))

    def _is_state(self, name):
        return name == 'sim: state'

    # -- helpers -----------------------------------------------------------------------------
    def n_states(self):
        with self.lock:
            return len(self.states)

    def states_since(self, t):
        """The joint_states received after ``t`` (not diagnostics)."""
        with self.lock:
            return [s for s in self.states if s[0] >= t]

    def q(self):
        with self.lock:
            return self.states[-1][3].copy() if self.states else None

    def state_after(self, since):
        """The values of the first 'sim: state' status received after ``since`` (or None)."""
        with self.lock:
            for d in self.diag_messages:
                if d.t >= since and d.name == 'sim: state':
                    return d.message, d.values
        return None

    def wait_state(self, pred, timeout=30.0):
        """Wait for a 'sim: state' status whose (message, values) satisfy ``pred``."""
        def found():
            m, kv = self.last_state()
            return m is not None and pred(m, kv)
        return self.wait(found, timeout)

    def reference(self, positions, velocities=None, names=PANDA_JOINTS, stamp_offset=0.0,
                  zero=False):
        return self.joint_state(positions, names, velocities, stamp_offset, zero)

    def ramp(self, q0, q1, duration, rate=100.0):
        """Publish a minimum-jerk reference from q0 to q1 (with velocities), in real time."""
        q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
        n = int(duration * rate)
        t0 = time.monotonic()
        for k in range(n + 1):
            s = k / n
            pos = q0 + (10 * s ** 3 - 15 * s ** 4 + 6 * s ** 5) * (q1 - q0)
            vel = (30 * s ** 2 - 60 * s ** 3 + 30 * s ** 4) / duration * (q1 - q0)
            self.publish('joint_reference', self.reference(pos, vel))
            time.sleep(max(0.0, t0 + (k + 1) / rate - time.monotonic()))

    def call(self, service, timeout=30.0):
        return self.call_trigger(self.clients[service], timeout)
