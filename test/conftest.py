"""Shared fixtures. ROS processes started by tests obey the network rule: localhost-only
discovery and a private ROS_DOMAIN_ID (see ../shared/design.md, Environment facts)."""
import atexit
import os
import random
import shutil
import sys
import tempfile
import time
import uuid

import pytest
from hypothesis import settings

# Property tests draw the same examples on every run (a CI run never fails on a draw that the
# previous one did not make), keep no example database between runs, and have no per-example
# deadline (a loaded machine is slow, not wrong).
settings.register_profile('cdmp', derandomize=True, database=None, deadline=None)
settings.load_profile('cdmp')

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# The network rule holds for everything this test session starts, including rclpy in-process.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(random.Random(os.getpid()).randint(100, 199)))
os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)
os.environ.setdefault('MPLBACKEND', 'Agg')
# The caches (cdmp_ros.core.cache: kernels generated at run time, fitted capsules) go into a
# directory of this session, inherited by the node processes, removed at its end: the user's
# ~/.cache stays untouched.
if 'CDMP_ROS_CACHE' not in os.environ:
    os.environ['CDMP_ROS_CACHE'] = tempfile.mkdtemp(prefix='cdmp_ros_cache_')
    atexit.register(shutil.rmtree, os.environ['CDMP_ROS_CACHE'], True)
os.environ.pop('CDMP_ROS_KERNEL_CACHE', None)  # a kernel cache of the user's is not used


def load_script(name: str):
    """The module of ``scripts/<name>.py`` (scripts are not a package), executed once per
    call."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        name, os.path.join(REPO_ROOT, 'scripts', name + '.py'))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def module_domain(offset: int) -> int:
    """A private domain id for one test module: the session's ``ROS_DOMAIN_ID`` plus ``offset``.

    Modules that keep processes running get their own offset so that a process left over from
    one module never talks to the next; sessions started with different ``ROS_DOMAIN_ID`` values
    (parallel checkouts, soak runs) never share a domain as long as their ids are 10 apart.
    """
    return (int(os.environ['ROS_DOMAIN_ID']) + int(offset)) % 233


def ros_env(domain_id=None) -> dict:
    """Environment for a ROS child process: localhost discovery, private domain id."""
    env = dict(os.environ)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None else os.environ['ROS_DOMAIN_ID'])
    env['AMENT_PREFIX_PATH'] = sys.prefix
    env['PYTHONUNBUFFERED'] = '1'
    return env


def wait_for(pred, timeout, period=0.02):
    """Poll ``pred()`` until it is true or ``timeout`` [s] has passed; returns the last result.

    The one wait of the test suite: tests wait on a condition, never on a duration. The
    timeout only bounds a failure, so it is generous (tens of seconds on a loaded machine).
    """
    end = time.monotonic() + timeout
    while True:
        result = pred()
        if result or time.monotonic() >= end:
            return result
        time.sleep(period)


# -- evidence on diagnostics -----------------------------------------------------------------
# The test harnesses record every diagnostics status as a tuple (receive time, status name,
# message, ..., {key: value}); a node reports rejected input on '<node>: input <topic>' with
# the keys rejected_total and last_reason (cdmp_ros.ros.diagnostics).
def rejected_total(h, topic):
    """``rejected_total`` of the newest '<node>: input <topic>' status ``h`` received (0)."""
    with h.lock:
        for entry in reversed(h.diag_messages):
            if entry[1].endswith(f': input {topic}'):
                return int(entry[-1]['rejected_total'])
    return 0


def reject_token(h, topic, send, timeout=30.0, resend_after=None):
    """Send (``send(token)``) one message the node must reject with a reason naming a fresh
    ``token``, and wait until its diagnostics report that rejection.

    Returns ``(rejected_total, sends)``: the topic's rejection count that includes this
    rejection, and how many messages were sent (more than one only on a best-effort topic, after
    ``resend_after`` seconds without a report).
    """
    token = f'evidence_{uuid.uuid4().hex[:10]}'
    sends = [0, 0.0]

    def seen():
        with h.lock:
            for entry in reversed(h.diag_messages):
                if (entry[1].endswith(f': input {topic}')
                        and token in entry[-1].get('last_reason', '')):
                    return int(entry[-1]['rejected_total'])
        now = time.monotonic()
        if sends[0] == 0 or (resend_after is not None and now - sends[1] > resend_after):
            send(token)
            sends[0] += 1
            sends[1] = now
        return None

    total = wait_for(seen, timeout)
    assert total, f'the rejection of {token} on {topic} was never reported'
    return total, sends[0]


def assert_not_rejected(h, topic, send_rejected, action, timeout=30.0, resend_after=None):
    """Run ``action()`` (which publishes on ``topic``) between two messages the node rejects
    (``send_rejected(token)``: a message whose rejection reason names ``token``), and assert
    on the evidence of the node's own counter that nothing ``action`` sent was rejected: the
    two rejections are counted exactly one apart. Messages of one publisher are processed in
    order, so the second rejection is reported only after everything before it was handled.
    Returns what ``action`` returned."""
    before, n1 = reject_token(h, topic, send_rejected, timeout, resend_after)
    result = action()
    after, n2 = reject_token(h, topic, send_rejected, timeout, resend_after)
    # a resent (best-effort) rejection message may have been counted more than once
    assert after - before - 1 <= (n1 - 1) + (n2 - 1), \
        f'{after - before - 1} message(s) on {topic} rejected: {last_reason(h, topic)}'
    return result


def last_reason(h, topic):
    with h.lock:
        for entry in reversed(h.diag_messages):
            if entry[1].endswith(f': input {topic}'):
                return entry[-1].get('last_reason')
    return None


def joint_state_rejected(h, publish, joint_names, stamp_ns):
    """``send_rejected`` for a JointState topic: the joint names with the last two replaced by
    a duplicated ``token`` (rejected as 'duplicate joint name <token>' before anything else is
    checked; as many names as joints, so the input gate's constant-time name count, which
    rejects more names than the robot has joints unparsed, lets it through to that check)."""
    from sensor_msgs.msg import JointState

    def send(token):
        msg = JointState()
        t = stamp_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
        msg.name = list(joint_names)[:-2] + [token, token]
        msg.position = [0.0] * len(msg.name)
        publish(msg)
    return send


def marker_rejected(h, publish, stamp=None):
    """``send_rejected`` for an obstacles topic: a SPHERE in the frame ``token``."""
    from visualization_msgs.msg import MarkerArray

    from markers import marker

    def send(token):
        m = marker(ns='evidence', id=0, position=(2.0, 0.0, 0.0), frame=token)
        if stamp is not None:
            m.header.stamp = stamp()
        publish(MarkerArray(markers=[m]))
    return send


@pytest.fixture
def repo_root():
    return REPO_ROOT


@pytest.fixture
def rng():
    import numpy as np
    return np.random.default_rng(12345)


@pytest.fixture(scope='session')
def chain():
    """The Panda's kinematic chain (pybullet_data's URDF); a module may define its own."""
    from adapter_harness import panda_urdf
    from cdmp_ros.core.kinematics import panda_chain
    return panda_chain(panda_urdf())


@pytest.fixture(scope='session')
def prior():
    """A 7-DoF reach ProMP of 5 basis functions (adapter_harness.reach_promp)."""
    from adapter_harness import reach_promp
    return reach_promp(n_basis=5)
