"""Test-side ROS node for the learner tests: publishes demonstrations, records every
``primitive`` and ``diagnostics`` message, calls the learner's Trigger services and
parameter service. Own rclpy context on a private domain id, spun by a background thread."""
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np

from conftest import REPO_ROOT, ros_env, wait_for

PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))


def start_learner(domain_id, params=(), log_path=None, params_file=None, cwd=REPO_ROOT):
    """Start ``python -m cdmp_ros.nodes.learner`` with ``-p`` parameters (name:=value)."""
    cmd = [sys.executable, '-m', 'cdmp_ros.nodes.learner', '--ros-args']
    if params_file:
        cmd += ['--params-file', params_file]
    for p in params:
        cmd += ['-p', p]
    out = open(log_path, 'w') if log_path else subprocess.DEVNULL
    env = ros_env(domain_id)
    env['RCUTILS_LOGGING_BUFFERED_STREAM'] = '0'  # log lines reach the file at once
    env['PYTHONPATH'] = REPO_ROOT + os.pathsep + env.get('PYTHONPATH', '')
    return subprocess.Popen(cmd, env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                            start_new_session=True)


class LearnerHarness:
    def __init__(self, domain_id: int, node_name: str = 'learner'):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        from cdmp_ros.ros import qos
        from cdmp_ros.ros.learner_node import DEMONSTRATION_QOS

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('learner_test', context=self.context)
        n = self.node
        self.lock = threading.Lock()
        self.primitives = []     # (receive time, dict)
        self.diag_messages = []  # (time, status name, message, {key: value})
        self.demo_pub = n.create_publisher(JointState, 'demonstration', DEMONSTRATION_QOS)
        n.create_subscription(String, 'primitive', self._on_primitive, qos.LATCHED)
        n.create_subscription(DiagnosticArray, 'diagnostics', self._on_diag, 100)
        self.clients = {s: n.create_client(Trigger, f'/{node_name}/{s}')
                        for s in ('refit', 'save', 'improve')}
        self.node_name = node_name
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

    def _on_primitive(self, msg):
        with self.lock:
            self.primitives.append((time.monotonic(), json.loads(msg.data)))

    def _on_diag(self, msg):
        t = time.monotonic()
        with self.lock:
            for s in msg.status:
                self.diag_messages.append((t, s.name, s.message,
                                           {kv.key: kv.value for kv in s.values}))

    # -- helpers -----------------------------------------------------------------------------
    def wait(self, pred, timeout):
        return wait_for(pred, timeout)

    def n_primitives(self):
        with self.lock:
            return len(self.primitives)

    def last_primitive(self):
        with self.lock:
            return self.primitives[-1][1] if self.primitives else None

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

    def recent_diag(self, n=5):
        with self.lock:
            return [(nm, m) for _, nm, m, _ in self.diag_messages[-n:]]

    def call(self, service, timeout=30.0):
        from std_srvs.srv import Trigger
        client = self.clients[service]
        assert client.wait_for_service(timeout_sec=timeout), f'no service {service}'
        fut = client.call_async(Trigger.Request())
        assert self.wait(fut.done, timeout), f'{service}: no response'
        return fut.result()

    def set_parameter(self, name, value, timeout=10.0):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        client = self.node.create_client(SetParameters, f'/{self.node_name}/set_parameters')
        try:
            assert client.wait_for_service(timeout_sec=timeout)
            req = SetParameters.Request(parameters=[Parameter(name,
                                                              value=value).to_parameter_msg()])
            fut = client.call_async(req)
            assert self.wait(fut.done, timeout)
            return fut.result().results[0]
        finally:
            self.node.destroy_client(client)

    def joint_state(self, positions, names=PANDA_JOINTS, stamp_ns=None):
        from sensor_msgs.msg import JointState
        msg = JointState()
        if stamp_ns is not None:
            msg.header.stamp.sec = int(stamp_ns // 1_000_000_000)
            msg.header.stamp.nanosec = int(stamp_ns % 1_000_000_000)
        msg.name = list(names)
        msg.position = [float(v) for v in positions]
        return msg

    def now_ns(self):
        return self.node.get_clock().now().nanoseconds

    def publish_demo(self, T, Y, names=PANDA_JOINTS, order=None, end=True, period=0.0,
                     start_ns=None):
        """Publish a demonstration (stamps = start + T, default ending now) and, with ``end``,
        the empty end marker."""
        from sensor_msgs.msg import JointState
        T = np.asarray(T)
        start = start_ns if start_ns is not None else self.now_ns() - int(T[-1] * 1e9) - 10**8
        order = list(range(len(names))) if order is None else list(order)
        for t, y in zip(T, Y):
            self.demo_pub.publish(self.joint_state(np.asarray(y)[order],
                                                   [names[i] for i in order],
                                                   start + int(t * 1e9)))
            if period:
                time.sleep(period)
        if end:
            self.demo_pub.publish(JointState())

    def close(self):
        self._stop.set()
        self.thread.join(timeout=5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)
