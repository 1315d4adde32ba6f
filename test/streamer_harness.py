"""A test-side ROS node for the streamer tests: a fake robot and a checking listener.

Runs in its own rclpy context on a private domain id, spun by a background thread. It
publishes ``joint_states`` (echoing the last reference, like a perfect robot) at 100 Hz while
``robot_on`` is set (joints ``robot_names``, by default the arm's in order), offers publishers
for every input topic, and checks EVERY received ``joint_reference`` message: 7 names in
order, finite, inside the limits (violations are collected, never silently dropped).
"""
import math
import threading
import time

import numpy as np

from conftest import wait_for
from streamer_util import LOWER, PANDA_JOINTS, Q_START, UPPER


FINGER_POSITION = 0.02  # m, the fake robot's finger joints (when listed in robot_names)


class Harness:
    def __init__(self, domain_id: int):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from visualization_msgs.msg import MarkerArray

        from cdmp_ros.ros import qos

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('streamer_test', context=self.context)
        n = self.node
        self.lock = threading.Lock()
        self.refs = []           # (receive time, stamp ns, positions, velocities)
        self.violations = []
        self.diag_messages = []  # (time, status name, message, {key: value})
        self.robot_on = True
        self.robot_q = Q_START.copy()
        # names of the fake robot's joint_states (any order; names other than the arm's, such
        # as finger joints, are published at FINGER_POSITION)
        self.robot_names = PANDA_JOINTS
        self.pub = {
            'primitive': n.create_publisher(String, 'primitive', qos.LATCHED),
            'adapted_primitive': n.create_publisher(String, 'adapted_primitive',
                                                    qos.LATCHED),
            'goal': n.create_publisher(JointState, 'goal', qos.COMMAND),
            'joint_states': n.create_publisher(JointState, 'joint_states', qos.COMMAND),
            'obstacles': n.create_publisher(MarkerArray, 'obstacles', qos.COMMAND),
        }
        n.create_subscription(JointState, 'joint_reference', self._on_ref, qos.REFERENCE)
        n.create_subscription(DiagnosticArray, 'diagnostics', self._on_diag, 50)
        n.create_timer(0.01, self._robot)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    # -- background --------------------------------------------------------------------------
    def _spin(self):
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 -- context shut down at teardown
                if self._stop.is_set():
                    return
                raise

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

    def _on_diag(self, msg):
        t = time.monotonic()
        with self.lock:
            for s in msg.status:
                self.diag_messages.append((t, s.name, s.message,
                                           {kv.key: kv.value for kv in s.values}))

    def _robot(self):
        if not self.robot_on:
            return
        from sensor_msgs.msg import JointState
        msg = JointState()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        names = list(self.robot_names)
        msg.name = names
        with self.lock:
            q = dict(zip(PANDA_JOINTS, self.robot_q.tolist()))
        msg.position = [q.get(n, FINGER_POSITION) for n in names]
        self.pub['joint_states'].publish(msg)

    # -- helpers -----------------------------------------------------------------------------
    def publish(self, topic, msg):
        self.pub[topic].publish(msg)

    def n_refs(self):
        with self.lock:
            return len(self.refs)

    def refs_since(self, index):
        with self.lock:
            return list(self.refs[index:])

    def last_ref(self):
        with self.lock:
            return self.refs[-1] if self.refs else None

    def wait(self, pred, timeout):
        return wait_for(pred, timeout)

    def wait_diag(self, text, since, timeout=30.0, name=None):
        """Wait for a diagnostics status (after ``since``) whose message contains ``text``."""
        def found():
            with self.lock:
                return any(t >= since and text in m and (name is None or name in nm)
                           for t, nm, m, _ in self.diag_messages)
        return self.wait(found, timeout)

    def last_state(self):
        with self.lock:
            for t, nm, m, kv in reversed(self.diag_messages):
                if nm.endswith(': state'):
                    return m, kv
        return None, {}

    def make_joint_state(self, positions, names=PANDA_JOINTS, stamp_offset=0.0, zero=False):
        from sensor_msgs.msg import JointState
        msg = JointState()
        if not zero:
            t = self.node.get_clock().now().nanoseconds + int(stamp_offset * 1e9)
            msg.header.stamp.sec = t // 1_000_000_000
            msg.header.stamp.nanosec = t % 1_000_000_000
        msg.name = list(names)
        msg.position = [float(v) for v in positions]
        return msg

    def close(self):
        self._stop.set()
        self.thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


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
