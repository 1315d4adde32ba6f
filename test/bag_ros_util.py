"""Helpers of the recorder/player tests: node processes and an in-process rclpy peer.

Every process gets ``ros_env()`` (localhost discovery, the test's private domain id).
"""
import os
import signal
import subprocess
import sys
import threading
import time

from conftest import ros_env, wait_for  # noqa: F401 (re-exported to the bag tests)

#: Bound of every wait on a condition [s]: it only bounds a failure, a pass never waits it out.
WAIT_S = 30.0


def start_node(node, params, remaps=(), domain_id=None, log_path=None, extra=()):
    """Start ``cdmp_ros.nodes.<node>`` with ``-p k:=v`` parameters; returns the Popen.

    ``extra`` ROS arguments (e.g. ``--params-file``) come first: later assignments win.
    """
    cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{node}', '--ros-args', *extra]
    for k, v in params.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        elif isinstance(v, (list, tuple)):
            v = '[' + ', '.join(f"'{x}'" for x in v) + ']'
        cmd += ['-p', f'{k}:={v}']
    for r in remaps:
        cmd += ['-r', r]
    out = open(log_path, 'w') if log_path else subprocess.DEVNULL
    return subprocess.Popen(cmd, env=ros_env(domain_id), stdout=out, stderr=subprocess.STDOUT)


def stop(proc, sig=signal.SIGINT, timeout=WAIT_S):
    """Signal a process we started and wait for it; kill it if it hangs. Returns rc."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


class Lines:
    """The lines of a child's text stream, read by a background thread as they come."""

    def __init__(self, stream):
        self.lines = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in iter(stream.readline, ''):
            self.lines.append(line)

    def seen(self, *needles):
        """True when every needle occurs in some line read so far."""
        return all(any(n in x for x in list(self.lines)) for n in needles)

    def text(self, timeout=WAIT_S):
        """Everything read; waits (bounded) for the end of the stream first."""
        self._thread.join(timeout)
        return ''.join(self.lines)


class Peer:
    """An rclpy context + node in this process, spun by a background thread."""

    def __init__(self, name='test_peer', domain_id=None):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.context = Context()
        if domain_id is None:
            domain_id = int(os.environ['ROS_DOMAIN_ID'])
        rclpy.init(context=self.context, domain_id=int(domain_id))
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while not self._stop and self.context.ok():
            self.executor.spin_once(timeout_sec=0.02)

    def collect(self, msg_type, topic, qos=None, raw=True):
        """Subscribe; returns a list that fills with (monotonic time, message)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        got = []
        qos = qos or QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(msg_type, topic,
                                      lambda m: got.append((time.monotonic(), m)), qos,
                                      raw=raw)
        return got

    def publisher(self, msg_type, topic, depth=1000):
        """A reliable keep-last publisher; ``depth`` at least the number of messages a test
        publishes means no sample is ever replaced before every reader acknowledged it."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        return self.node.create_publisher(
            msg_type, topic, QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE))

    def close(self):
        self._stop = True
        self._thread.join(timeout=WAIT_S)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def wait_matched(pub, n=1, timeout=WAIT_S):
    """Wait until ``pub`` matched ``n`` subscriptions.

    A reliable volatile writer delivers every sample written after it matched a reader, even
    when the reader side completes its own match later (the reader asks for what it missed),
    so no sleep is needed after this.
    """
    return wait_for(lambda: pub.get_subscription_count() >= n, timeout)


def wait_acked(pub, timeout=WAIT_S):
    """Wait until every matched reader acknowledged every sample of ``pub`` (reliable)."""
    from rclpy.duration import Duration
    return pub.wait_for_all_acked(Duration(seconds=float(timeout)))


def recoverable_count(bag, probe_dir):
    """Messages already safe on disk in the bag a recorder is still writing: what
    ``recover_bag`` would keep now, rebuilt into ``probe_dir`` (the bag itself is untouched).

    The recorder only appends, so the count never decreases; 0 while there is no file yet.
    """
    import shutil
    from cdmp_ros.bag import BagError, recover_bag
    shutil.rmtree(probe_dir, ignore_errors=True)
    try:
        return recover_bag(bag, output=probe_dir).message_count
    except (BagError, OSError):
        return 0
