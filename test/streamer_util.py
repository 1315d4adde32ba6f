"""Shared helpers of the streamer tests: a Panda reach primitive, limits, process control."""
import os
import signal
import subprocess
import sys

import numpy as np

from conftest import REPO_ROOT, ros_env, wait_for  # noqa: F401 -- wait_for for the tests

PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
# Panda limits of pybullet_data's panda.urdf (checked against the URDF in test_core_streaming)
LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
VMAX = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
Q_START = np.array([0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.7])
Q_GOAL = np.array([0.8, 0.2, 0.3, -1.2, 0.2, 2.0, 0.3])


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


def start_streamer(domain_id, params=(), log_path=None, params_file=None):
    """Start ``python -m cdmp_ros.nodes.streamer`` with ``-p`` parameters (name:=value)."""
    cmd = [sys.executable, '-m', 'cdmp_ros.nodes.streamer', '--ros-args']
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
