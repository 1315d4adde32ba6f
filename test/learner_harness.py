"""The learner tests' own part: the learner process and a test-side node
(:class:`LearnerHarness`, a :class:`node_harness.NodeHarness`) that publishes demonstrations,
records every ``primitive`` and ``diagnostics`` message, and calls the learner's Trigger
services and parameter service."""
import json
import os
import time

import numpy as np

from conftest import REPO_ROOT
from node_harness import PANDA_JOINTS, NodeHarness, start_node  # noqa: F401


def start_learner(domain_id, params=(), log_path=None, params_file=None, cwd=REPO_ROOT):
    """Start ``python -m cdmp_ros.nodes.learner`` with ``-p`` parameters (name:=value)."""
    env = {'RCUTILS_LOGGING_BUFFERED_STREAM': '0',  # log lines reach the file at once
           'PYTHONPATH': REPO_ROOT + os.pathsep + os.environ.get('PYTHONPATH', '')}
    return start_node('learner', params, domain_id, params_file, log_path=log_path, env=env,
                      cwd=cwd)


class LearnerHarness(NodeHarness):
    def __init__(self, domain_id: int, node_name: str = 'learner'):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        from cdmp_ros.ros import qos
        from cdmp_ros.ros.learner_node import DEMONSTRATION_QOS

        super().__init__('learner_test', domain_id, diagnostics_depth=100, spin=False)
        n = self.node
        self.primitives = []     # (receive time, dict)
        self.demo_pub = self.publisher(JointState, 'demonstration', DEMONSTRATION_QOS)
        self.subscribe(String, 'primitive', self._on_primitive, qos.LATCHED)
        self.clients = {s: n.create_client(Trigger, f'/{node_name}/{s}')
                        for s in ('refit', 'save', 'improve')}
        self.target = node_name
        self.start()

    def _on_primitive(self, msg):
        with self.lock:
            self.primitives.append((time.monotonic(), json.loads(msg.data)))

    # -- helpers -----------------------------------------------------------------------------
    def n_primitives(self):
        with self.lock:
            return len(self.primitives)

    def last_primitive(self):
        with self.lock:
            return self.primitives[-1][1] if self.primitives else None

    def recent_diag(self, n=5):
        with self.lock:
            return [(d.name, d.message) for d in self.diag_messages[-n:]]

    def call(self, service, timeout=30.0):
        return self.call_trigger(self.clients[service], timeout)

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
                                                   stamp_ns=start + int(t * 1e9)))
            if period:
                time.sleep(period)
        if end:
            self.demo_pub.publish(JointState())
