"""A test-side ROS node for the adapter tests and benchmark: publishers for every input topic,
a recorder of ``adapted_primitive``, ``visualization`` and ``diagnostics``.

Runs in its own rclpy context on a private domain id, spun by a background thread.
"""
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from conftest import REPO_ROOT, ros_env, wait_for

PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
Q_START = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
Q_GOAL = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])


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
    cmd = [sys.executable, '-m', 'cdmp_ros.nodes.adapter', '--ros-args']
    if params_file:
        cmd += ['--params-file', params_file]
    for p in params:
        cmd += ['-p', p]
    for r in remaps:
        cmd += ['-r', r]
    out = open(log_path, 'w') if log_path else subprocess.DEVNULL
    return subprocess.Popen(cmd, env=ros_env(domain_id), cwd=REPO_ROOT, stdout=out,
                            stderr=subprocess.STDOUT, start_new_session=True)


def stop_process(proc, timeout=10.0):
    """SIGINT, then SIGKILL if needed; returns the exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            return proc.wait(5)
    return proc.returncode


class Harness:
    def __init__(self, domain_id: int):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from visualization_msgs.msg import MarkerArray

        from cdmp_ros.ros import qos

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('adapter_test', context=self.context)
        n = self.node
        self.lock = threading.Lock()
        self.adapted = []        # (receive time, dict)
        self.viz = []            # (receive time, MarkerArray)
        self.diag_messages = []  # (time, status name, message, level, {key: value})
        self.pub = {
            'primitive': n.create_publisher(String, 'primitive', qos.LATCHED),
            'goal': n.create_publisher(JointState, 'goal', qos.COMMAND),
            'goal_point': n.create_publisher(PointStamped, 'goal_point', qos.COMMAND),
            'constraints': n.create_publisher(String, 'constraints', qos.COMMAND),
            'joint_states': n.create_publisher(JointState, 'joint_states', qos.COMMAND),
            'obstacles': n.create_publisher(MarkerArray, 'obstacles', qos.COMMAND),
        }
        n.create_subscription(String, 'adapted_primitive', self._on_adapted,
                              qos.LATCHED)
        n.create_subscription(MarkerArray, 'visualization', self._on_viz, qos.LATCHED)
        n.create_subscription(DiagnosticArray, 'diagnostics', self._on_diag, 50)
        self.robot_q = None      # published on joint_states at 20 Hz while not None
        n.create_timer(0.05, self._robot)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 -- context shut down at teardown
                if self._stop.is_set():
                    return
                raise

    def _on_adapted(self, msg):
        t = time.monotonic()
        with self.lock:
            self.adapted.append((t, json.loads(msg.data)))

    def _on_viz(self, msg):
        with self.lock:
            self.viz.append((time.monotonic(), msg))

    def _on_diag(self, msg):
        t = time.monotonic()
        with self.lock:
            for s in msg.status:
                self.diag_messages.append((t, s.name, s.message, int.from_bytes(s.level, 'little')
                                           if isinstance(s.level, bytes) else int(s.level),
                                           {kv.key: kv.value for kv in s.values}))

    def _robot(self):
        q = self.robot_q
        if q is not None:
            self.pub['joint_states'].publish(self.make_joint_state(q))

    # -- helpers -----------------------------------------------------------------------------
    def publish(self, topic, msg):
        self.pub[topic].publish(msg)

    def n_adapted(self):
        with self.lock:
            return len(self.adapted)

    def last_adapted(self):
        with self.lock:
            return self.adapted[-1][1] if self.adapted else None

    def wait(self, pred, timeout):
        return wait_for(pred, timeout)

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

    def wait_diag(self, text, since, timeout=30.0, name=None):
        """Wait for a diagnostics status (after ``since``) whose message contains ``text``."""
        def found():
            with self.lock:
                return any(t >= since and text in m and (name is None or name in nm)
                           for t, nm, m, _, _ in self.diag_messages)
        return self.wait(found, timeout)

    def states_since(self, since):
        with self.lock:
            return [(m, lv, kv) for t, nm, m, lv, kv in self.diag_messages
                    if t >= since and nm.endswith(': state')]

    def wait_state(self, pred, since, timeout=30.0):
        """Wait for an adapter state status after ``since`` with pred(message, level, kv)."""
        out = []

        def found():
            for st in self.states_since(since):
                if pred(*st):
                    out.append(st)
                    return True
            return False
        return out[0] if self.wait(found, timeout) else None

    def last_viz(self):
        with self.lock:
            return self.viz[-1][1] if self.viz else None

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

    def make_point(self, xyz, frame='panda_link0', stamp_offset=0.0):
        from geometry_msgs.msg import PointStamped
        msg = PointStamped()
        msg.header.frame_id = frame
        t = self.node.get_clock().now().nanoseconds + int(stamp_offset * 1e9)
        msg.header.stamp.sec = t // 1_000_000_000
        msg.header.stamp.nanosec = t % 1_000_000_000
        msg.point.x, msg.point.y, msg.point.z = (float(v) for v in xyz)
        return msg

    def sphere(self, center, radius, mid=1, ns='test'):
        from visualization_msgs.msg import Marker
        m = Marker(ns=ns, id=mid, type=Marker.SPHERE, action=Marker.ADD)
        m.header.frame_id = 'panda_link0'
        m.header.stamp = self.node.get_clock().now().to_msg()
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in center)
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 2.0 * radius
        return m

    def close(self):
        self._stop.set()
        self.thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
