"""Demonstrations in bags: the sample sets of ``bags/`` and the learner's reader.

Convention (bags/README.md): a demonstration is a sequence of ``sensor_msgs/msg/JointState``
messages (names, position, velocity) on topic ``demonstration``.  A *set* of demonstrations is
either a directory holding one bag directory per demonstration (read in sorted name order),
or one bag in which a new demonstration starts whenever ``header.stamp`` goes backwards (what
recording a publisher that replays several demonstrations gives).  ``T`` is the header stamp
relative to the first message of its demonstration, in seconds.
"""
import os
import shutil
from typing import List, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.bag.cdr import decode_joint_state, encode_joint_state
from cdmp_ros.bag.errors import BagError
from cdmp_ros.bag.metadata import METADATA_FILE, qos_dict
from cdmp_ros.bag.reader import BagReader
from cdmp_ros.bag.writer import BagWriter
from cdmp_ros.core.errors import ValidationError

Demonstration = Tuple[NDArray[np.float64], NDArray[np.float64], List[str]]

DEMO_TOPIC = '/demonstration'
PANDA_JOINTS = [f'panda_joint{i}' for i in range(1, 8)]
#: Franka Panda joint limits (rad), from the Franka datasheet.
PANDA_Y_MIN = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
PANDA_Y_MAX = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
PANDA_READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
#: Goal of the single-arm reach (well inside the limits).
PANDA_REACH_GOAL = np.array([0.6, 0.25, -0.3, -1.9, 0.1, 2.1, 1.2])
#: Two-arm crossing reach: each arm reaches across the shared workspace.
DUAL_LEFT_GOAL = np.array([-0.7, 0.45, 0.2, -1.8, -0.1, 2.2, 0.6])
DUAL_RIGHT_GOAL = np.array([0.7, 0.45, -0.2, -1.8, 0.1, 2.2, 0.9])
#: The planar 4-link arm (the sim's robot ``planar4``, limits +-2.8 rad): a sweep of the end
#: effector from (2.49, 1.93) m to (3.34, 1.31) m in the base frame.
PLANAR4_JOINTS = [f'joint{i}' for i in range(1, 5)]
PLANAR4_START = np.array([-0.3, 0.7, 0.6, 0.5])
PLANAR4_GOAL = np.array([1.0, -0.4, -0.5, -0.3])
#: Start time (ns since epoch) of the first sample demonstration; fixed for determinism.
EPOCH_NS = 1_700_000_000 * 10 ** 9


def min_jerk(tau: NDArray[np.float64]) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Minimum-jerk profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 and ds/dtau, tau in [0, 1]."""
    s = tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)
    ds = 30 * tau ** 2 * (1 - tau) ** 2
    return s, ds


def noisy_reach(start_y: NDArray[np.float64], goal_y: NDArray[np.float64],
                rng: np.random.Generator, duration: float = 2.0, rate: float = 100.0,
                goal_noise: float = 0.05, shape_noise: float = 0.08
                ) -> Tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """One noisy point-to-point demonstration in joint space.

    A min-jerk profile from ``start_y`` to a perturbed goal plus a smooth random deviation
    ``sum_k a_k sin(k pi tau) * 16 tau^2 (1 - tau)^2`` per joint, which vanishes with its
    velocity at both ends.

    Returns
    -------
    T : ndarray, shape (n_steps,)
    Y, Yd : ndarray, shape (n_steps, n_dims)
        Positions and their exact time derivatives.
    """
    n_steps = int(round(duration * rate)) + 1
    T = np.arange(n_steps) / rate
    tau = T / duration
    goal = goal_y + rng.normal(0.0, goal_noise, size=goal_y.shape)
    s, ds = min_jerk(tau)
    amp = rng.normal(0.0, shape_noise, size=(3, goal_y.size))
    k = np.arange(1, 4)[:, None]
    env = 16 * tau ** 2 * (1 - tau) ** 2
    denv = 32 * tau * (1 - tau) * (1 - 2 * tau)
    sin = np.sin(k * np.pi * tau[None, :])
    dsin = k * np.pi * np.cos(k * np.pi * tau[None, :])
    bump = np.einsum('kn,kd->nd', sin, amp) * env[:, None]
    dbump = (np.einsum('kn,kd->nd', dsin, amp) * env[:, None]
             + np.einsum('kn,kd->nd', sin, amp) * denv[:, None])
    Y = start_y + s[:, None] * (goal - start_y) + bump
    Yd = (ds[:, None] * (goal - start_y) + dbump) / duration
    return T, Y, Yd


def panda_reach_set(rng: np.random.Generator, n_demos: int = 5) -> List[Demonstration]:
    """``n_demos`` noisy Panda reaches from the ready pose (7 joints)."""
    out = []
    for _ in range(n_demos):
        T, Y, Yd = noisy_reach(PANDA_READY, PANDA_REACH_GOAL, rng)
        out.append((T, np.hstack([Y, Yd]), list(PANDA_JOINTS)))
    return out


def dual_panda_set(rng: np.random.Generator, n_demos: int = 3) -> List[Demonstration]:
    """``n_demos`` two-arm crossing reaches (14 joints, ``left_``/``right_`` prefixes)."""
    names = [f'left_{j}' for j in PANDA_JOINTS] + [f'right_{j}' for j in PANDA_JOINTS]
    out = []
    for _ in range(n_demos):
        T, YL, YdL = noisy_reach(PANDA_READY, DUAL_LEFT_GOAL, rng)
        _, YR, YdR = noisy_reach(PANDA_READY, DUAL_RIGHT_GOAL, rng)
        out.append((T, np.hstack([YL, YR, YdL, YdR]), names))
    return out


def planar4_reach_set(rng: np.random.Generator, n_demos: int = 3) -> List[Demonstration]:
    """``n_demos`` noisy reaches of the planar 4-link arm from :data:`PLANAR4_START`
    (4 joints)."""
    out = []
    for _ in range(n_demos):
        T, Y, Yd = noisy_reach(PLANAR4_START, PLANAR4_GOAL, rng)
        out.append((T, np.hstack([Y, Yd]), list(PLANAR4_JOINTS)))
    return out


def write_set(root: str, demos: Sequence[Demonstration]) -> List[str]:
    """Write a set as ``root/demo_00, demo_01, ...`` (one bag per demonstration, the ``i``-th
    starting at ``EPOCH_NS + i * 10 s``), replacing ``root``; returns the bag directories."""
    if os.path.isdir(root):
        shutil.rmtree(root)
    written = []
    for i, (T, YYd, names) in enumerate(demos):
        n = len(names)
        bag = os.path.join(root, f'demo_{i:02d}')
        write_demonstration(bag, T, YYd[:, :n], YYd[:, n:], names,
                            start_ns=EPOCH_NS + i * 10 ** 10)
        written.append(bag)
    return written


def write_demonstration(bag_dir: str, T, Y, Yd, joint_names: Sequence[str],
                        start_ns: int = EPOCH_NS, topic: str = DEMO_TOPIC) -> None:
    """Write one demonstration as a bag (deterministic bytes: no time-based chunking)."""
    T = np.asarray(T, dtype=np.float64)
    with BagWriter(bag_dir, flush_period=0.0, overwrite=True) as w:
        w.add_topic(topic, 'sensor_msgs/msg/JointState', [qos_dict(depth=1000)])
        for t, y, yd in zip(T, Y, Yd):
            stamp = start_ns + int(round(t * 1e9))
            w.write(topic, encode_joint_state(stamp, list(joint_names), y, yd), stamp)


def _bag_dirs(path: str) -> List[str]:
    if os.path.isfile(os.path.join(path, METADATA_FILE)) or os.path.isfile(path):
        return [path]
    if not os.path.isdir(path):
        raise BagError(f'path: {path} is not a bag or a directory of bags')
    subs = sorted(os.path.join(path, d) for d in os.listdir(path)
                  if os.path.isfile(os.path.join(path, d, METADATA_FILE)))
    if not subs:
        raise BagError(f'path: {path} holds no bag directories')
    return subs


def read_demonstrations(path: str, topic: str = DEMO_TOPIC) -> List[Demonstration]:
    """Demonstrations recorded in a bag or a directory of bags, for the learner.

    Parameters
    ----------
    path : str
        A bag directory, an ``.mcap`` file, or a directory holding bag directories.
    topic : str
        JointState topic; a leading ``/`` is optional.

    Returns
    -------
    list of (T, Y, joint_names)
        ``T`` shape (n_steps,) seconds from the demonstration's first stamp, ``Y`` shape
        (n_steps, n_dims) joint positions, ``joint_names`` list of n_dims names.

    Raises
    ------
    BagError
        Missing or unreadable bag, or no message on ``topic``.
    ValidationError
        Messages whose joint names or position lengths are inconsistent.
    """
    wanted = {topic, '/' + topic.lstrip('/'), topic.lstrip('/')}
    demos: List[Demonstration] = []
    for bag in _bag_dirs(path):
        stamps: List[int] = []
        rows: List[np.ndarray] = []
        names = None
        n_before = len(demos)
        for m in BagReader(bag).messages(wanted):
            if m.type != 'sensor_msgs/msg/JointState':
                raise BagError(f'{bag}: topic {m.topic} has type {m.type}, expected '
                               'sensor_msgs/msg/JointState')
            js = decode_joint_state(m.data)
            if stamps and js.stamp_ns < stamps[-1]:
                demos.append(_finish(stamps, rows, names))
                stamps, rows = [], []
            if names is None:
                names = list(js.name)
            if list(js.name) != names or js.position.shape != (len(names),):
                raise ValidationError(
                    f'{bag}: message {len(stamps)}: expected joints {names} with as many '
                    f'positions, got {list(js.name)} with {js.position.shape[0]}')
            stamps.append(js.stamp_ns)
            rows.append(js.position)
        if stamps:
            demos.append(_finish(stamps, rows, names))
        if len(demos) == n_before:
            raise BagError(f'{bag}: no message on topic {topic}')
    return demos


def _finish(stamps, rows, names) -> Demonstration:
    s = np.asarray(stamps, dtype=np.int64)
    return (s - s[0]) / 1e9, np.vstack(rows), list(names)
