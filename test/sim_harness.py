"""A test-side ROS node for the sim tests: publishes references and obstacles, records
everything the sim publishes, calls its services.

Runs in its own rclpy context on a private domain id, spun by a background thread.
"""
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np

from conftest import REPO_ROOT, ros_env, wait_for

PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
PANDA_HOME = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])
# Panda limits of pybullet_data's panda.urdf
LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])


def start_sim(domain_id, params=(), log_path=None, params_file=None):
    """Start ``python -m cdmp_ros.nodes.sim`` with ``-p`` parameters (name:=value)."""
    cmd = [sys.executable, '-m', 'cdmp_ros.nodes.sim', '--ros-args']
    if params_file:
        cmd += ['--params-file', params_file]
    for p in params:
        cmd += ['-p', p]
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


def stamp_ns(stamp):
    return stamp.sec * 1_000_000_000 + stamp.nanosec


class SimHarness:
    def __init__(self, domain_id: int, clock: bool = False):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger
        from visualization_msgs.msg import MarkerArray

        from cdmp_ros.ros import qos

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('sim_test', context=self.context)
        n = self.node
        self.lock = threading.Lock()
        self.states = []         # (receive time, stamp ns, names, q, qd, effort)
        self.poses = []          # (receive time, stamp ns, frame, position (3,), quat (4,))
        self.clocks = []         # (receive time, clock ns)
        self.diag_messages = []  # (time, status name, message, {key: value})
        self.pub = {
            'joint_reference': n.create_publisher(JointState, 'joint_reference',
                                                  qos.REFERENCE),
            'obstacles': n.create_publisher(MarkerArray, 'obstacles', qos.COMMAND),
        }
        ref = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)  # lose nothing
        n.create_subscription(JointState, 'joint_states', self._on_js, ref)
        n.create_subscription(PoseStamped, 'ee_pose', self._on_pose, ref)
        n.create_subscription(DiagnosticArray, 'diagnostics', self._on_diag, 50)
        if clock:
            from rosgraph_msgs.msg import Clock
            n.create_subscription(Clock, '/clock', self._on_clock, 10)
        self.clients = {name: n.create_client(Trigger, f'/sim/{name}')
                        for name in ('snapshot', 'reset')}
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

    def _on_diag(self, msg):
        t = time.monotonic()
        with self.lock:
            for s in msg.status:
                self.diag_messages.append((t, s.name, s.message,
                                           {kv.key: kv.value for kv in s.values}))

    # -- helpers -----------------------------------------------------------------------------
    def n_states(self):
        with self.lock:
            return len(self.states)

    def states_since(self, t):
        with self.lock:
            return [s for s in self.states if s[0] >= t]

    def q(self):
        with self.lock:
            return self.states[-1][3].copy() if self.states else None

    def wait(self, pred, timeout):
        return wait_for(pred, timeout)

    def wait_diag(self, text, since, timeout=30.0, name=None):
        """Wait for a diagnostics status (after ``since``) whose message contains ``text``."""
        def found():
            with self.lock:
                return any(t >= since and text in m and (name is None or name in nm)
                           for t, nm, m, _ in self.diag_messages)
        return self.wait(found, timeout)

    def state_after(self, since):
        """The values of the first 'sim: state' status received after ``since`` (or None)."""
        with self.lock:
            for t, nm, m, kv in self.diag_messages:
                if t >= since and nm == 'sim: state':
                    return m, kv
        return None

    def wait_state(self, pred, timeout=30.0):
        """Wait for a 'sim: state' status whose (message, values) satisfy ``pred``."""
        def found():
            m, kv = self.last_state()
            return m is not None and pred(m, kv)
        return self.wait(found, timeout)

    def last_state(self):
        with self.lock:
            for t, nm, m, kv in reversed(self.diag_messages):
                if nm == 'sim: state':
                    return m, kv
        return None, {}

    def reference(self, positions, velocities=None, names=PANDA_JOINTS, stamp_offset=0.0,
                  zero=False):
        from sensor_msgs.msg import JointState
        msg = JointState()
        if not zero:
            t = self.node.get_clock().now().nanoseconds + int(stamp_offset * 1e9)
            msg.header.stamp.sec = t // 1_000_000_000
            msg.header.stamp.nanosec = t % 1_000_000_000
        msg.name = list(names)
        msg.position = [float(v) for v in positions]
        if velocities is not None:
            msg.velocity = [float(v) for v in velocities]
        return msg

    def publish(self, topic, msg):
        self.pub[topic].publish(msg)

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
        from std_srvs.srv import Trigger
        client = self.clients[service]
        assert client.wait_for_service(timeout_sec=timeout), f'no service {service}'
        fut = client.call_async(Trigger.Request())
        assert self.wait(fut.done, timeout), f'{service}: no answer'
        return fut.result()

    def set_parameter(self, name, value, timeout=10.0):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        client = self.node.create_client(SetParameters, '/sim/set_parameters')
        try:
            assert client.wait_for_service(timeout_sec=timeout)
            req = SetParameters.Request(
                parameters=[Parameter(name, value=value).to_parameter_msg()])
            fut = client.call_async(req)
            assert self.wait(fut.done, timeout)
            return fut.result().results[0]
        finally:
            self.node.destroy_client(client)

    def close(self):
        self._stop.set()
        self.thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
