"""Conversions between ROS messages and arrays, with validation that names the bad field.

- ``sensor_msgs/JointState`` <-> joint arrays in a fixed joint order (:class:`JointStateMapper`,
  :class:`JointStateWriter`): names are mapped (any order is accepted), duplicates, missing and
  unknown names, wrong lengths and non-finite values are rejected.
- Reference -> ros2_control controller commands in the controller's joint order
  (:class:`ForwardCommandWriter`: ``std_msgs/Float64MultiArray``; :class:`JointTrajectoryWriter`:
  ``trajectory_msgs/JointTrajectory`` with one point).
- Header stamps: :func:`check_stamp` rejects stamps far in the future or the past.
- ``visualization_msgs/MarkerArray`` -> an obstacle set (:class:`ObstacleSet`): SPHERE = a
  repeller of radius ``scale.x / 2``, CUBE = a box (:class:`Box` when axis-aligned,
  :class:`OrientedBox` when rotated); ADD/MODIFY, DELETE and DELETEALL honoured per
  ``(ns, id)``; marker ``lifetime`` honoured; positions in the robot base frame.

Every rejection raises (or returns) :class:`~cdmp_ros.core.errors.ValidationError` with a
message naming the field, the expectation and the received value.
"""
import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.closest import Box, OrientedBox, Sphere
from cdmp_ros.core.validation import name_permutation

# visualization_msgs/Marker constants (kept here so that the core needs no message package).
MARKER_TYPES = {0: 'ARROW', 1: 'CUBE', 2: 'SPHERE', 3: 'CYLINDER', 4: 'LINE_STRIP',
                5: 'LINE_LIST', 6: 'CUBE_LIST', 7: 'SPHERE_LIST', 8: 'POINTS',
                9: 'TEXT_VIEW_FACING', 10: 'MESH_RESOURCE', 11: 'TRIANGLE_LIST',
                12: 'ARROW_STRIP'}
CUBE, SPHERE = 1, 2
#: A CUBE whose rotation matrix is within this of the identity is an axis-aligned Box.
AXIS_ALIGNED_TOL = 1e-9
ADD, DELETE, DELETEALL = 0, 2, 3


def stamp_to_ns(stamp) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def check_stamp(name: str, stamp, now_ns: int, max_age: float, max_lead: float,
                accept_zero: bool = True) -> None:
    """Reject a header stamp more than ``max_age`` s in the past or ``max_lead`` s ahead.

    A zero stamp means "unstamped" and is accepted when ``accept_zero``.
    """
    t = stamp_to_ns(stamp)
    if t == 0:
        if accept_zero:
            return
        raise ValidationError(f'{name}: expected a stamp, got zero (unstamped)')
    dt = (t - now_ns) * 1e-9
    if dt > max_lead:
        raise ValidationError(f'{name}: stamp {dt:.3f} s in the future (accepted up to '
                              f'{max_lead} s)')
    if -dt > max_age:
        raise ValidationError(f'{name}: stamp {-dt:.3f} s in the past (accepted up to '
                              f'{max_age} s)')


class JointStateMapper:
    """Maps ``JointState`` messages into arrays ordered as ``joint_names``.

    Parameters
    ----------
    joint_names : sequence of str
        The expected joints, in the output order.
    allow_extra : bool
        Ignore joints not in ``joint_names`` (e.g. gripper joints in ``joint_states``)
        instead of rejecting them.
    """

    def __init__(self, joint_names: Sequence[str], allow_extra: bool = False):
        self.joint_names = list(joint_names)
        self.n_dims = len(self.joint_names)
        self.allow_extra = allow_extra
        self._index = {n: i for i, n in enumerate(self.joint_names)}
        self._cache: Dict[Tuple[str, ...], List[int]] = {}

    def _order(self, name: str, names: Sequence[str]) -> List[int]:
        """For each output joint, its index in the message's arrays."""
        key = tuple(names)
        order = self._cache.get(key)
        if order is not None:
            return order
        seen = set()
        for i, n in enumerate(names):
            if n in seen:
                raise ValidationError(f'{name}.name: duplicate joint name {n!r} (at index {i})')
            seen.add(n)
        unknown = [n for n in names if n not in self._index]
        if unknown and not self.allow_extra:
            raise ValidationError(f'{name}.name: unknown joints {unknown}; expected '
                                  f'{self.joint_names}')
        missing = [n for n in self.joint_names if n not in seen]
        if missing:
            raise ValidationError(f'{name}.name: missing joints {missing}; got {list(names)}')
        order = [list(names).index(n) for n in self.joint_names]
        if len(self._cache) < 16:
            self._cache[key] = order
        return order

    def to_arrays(self, msg, name: str = 'joint_states', need_velocity: bool = False
                  ) -> Tuple[NDArray[np.float64], Optional[NDArray[np.float64]]]:
        """Positions (n_dims,) and velocities (n_dims,) or None (when the message has none).

        Raises
        ------
        ValidationError
            Duplicate, missing or (unless ``allow_extra``) unknown names; ``position`` or
            ``velocity`` of a length other than ``len(name)``; non-finite values of the mapped
            joints; no velocity when ``need_velocity``.
        """
        names = msg.name
        order = self._order(name, names)
        n_names = len(names)
        pos = msg.position
        if len(pos) != n_names:
            raise ValidationError(f'{name}.position: expected {n_names} values (one per name), '
                                  f'got {len(pos)}')
        vel = msg.velocity
        if len(vel) not in (0, n_names):
            raise ValidationError(f'{name}.velocity: expected 0 or {n_names} values, got '
                                  f'{len(vel)}')
        if need_velocity and len(vel) == 0:
            raise ValidationError(f'{name}.velocity: expected {n_names} values, got none')
        q = np.fromiter((pos[i] for i in order), dtype=np.float64, count=self.n_dims)
        self._check_finite(name, 'position', q)
        qd = None
        if len(vel):
            qd = np.fromiter((vel[i] for i in order), dtype=np.float64, count=self.n_dims)
            self._check_finite(name, 'velocity', qd)
        return q, qd

    def _check_finite(self, name: str, field: str, v: NDArray[np.float64]) -> None:
        if not np.all(np.isfinite(v)):
            j = int(np.flatnonzero(~np.isfinite(v))[0])
            raise ValidationError(f'{name}.{field} of {self.joint_names[j]!r}: expected a '
                                  f'finite value, got {v[j]}')


class JointStateWriter:
    """Fills one reused ``JointState`` message (names set once, arrays updated in place)."""

    def __init__(self, msg, joint_names: Sequence[str], frame_id: str = ''):
        self.msg = msg
        n = len(joint_names)
        msg.name = list(joint_names)
        msg.position = [0.0] * n
        msg.velocity = [0.0] * n
        msg.effort = []
        msg.header.frame_id = frame_id
        self.n_dims = n

    def fill(self, stamp_ns: int, y: Sequence[float], yd: Sequence[float],
             ydd: Sequence[float] = ()):
        """Write the stamp, positions and velocities; returns the message."""
        msg = self.msg
        st = msg.header.stamp
        st.sec = stamp_ns // 1_000_000_000
        st.nanosec = stamp_ns % 1_000_000_000
        pos, vel = msg.position, msg.velocity
        for i in range(self.n_dims):
            pos[i] = y[i]
            vel[i] = yd[i]
        return msg


def controller_order(joint_names: Sequence[str], controller_joints: Sequence[str]
                     ) -> List[int]:
    """For each of ``controller_joints``, its index in ``joint_names`` (the reference order).

    Raises
    ------
    ValidationError
        ``controller_joints`` is not a permutation of ``joint_names`` (names the missing and
        unknown joints).
    """
    name_permutation(joint_names, controller_joints, 'controller_joints: expected a '
                     'permutation of')
    return [list(joint_names).index(n) for n in controller_joints]


class ForwardCommandWriter:
    """Fills one reused ``std_msgs/Float64MultiArray`` for a ros2_control
    ``forward_command_controller`` (position interface): the reference positions in the
    controller's joint order. The message has no stamp; ``fill`` takes one for the common
    interface of the writers and ignores it.

    Parameters
    ----------
    msg : std_msgs.msg.Float64MultiArray
    joint_names : sequence of str
        The order of the reference (``y``).
    controller_joints : sequence of str
        The controller's order (a permutation of ``joint_names``).
    """

    def __init__(self, msg, joint_names: Sequence[str], controller_joints: Sequence[str]):
        self.msg = msg
        self.order = controller_order(joint_names, controller_joints)
        msg.data = [0.0] * len(self.order)

    def fill(self, stamp_ns: int, y: Sequence[float], yd: Sequence[float],
             ydd: Sequence[float] = ()):
        """Write the positions in the controller's order; returns the message."""
        data = self.msg.data
        for i, j in enumerate(self.order):
            data[i] = y[j]
        return self.msg


class JointTrajectoryWriter:
    """Fills one reused ``trajectory_msgs/JointTrajectory`` for a ros2_control
    ``joint_trajectory_controller``: one point per tick, ``time_from_start`` one period,
    positions, velocities and accelerations (those the published positions imply) in the
    controller's joint order, the header stamp of the reference.

    Parameters
    ----------
    msg : trajectory_msgs.msg.JointTrajectory
    point : trajectory_msgs.msg.JointTrajectoryPoint
    joint_names : sequence of str
        The order of the reference (``y``, ``yd``).
    controller_joints : sequence of str
        The controller's order (a permutation of ``joint_names``).
    period : float
        The streaming period [s] (``time_from_start`` of the point).
    frame_id : str
    """

    def __init__(self, msg, point, joint_names: Sequence[str],
                 controller_joints: Sequence[str], period: float, frame_id: str = ''):
        self.msg = msg
        self.order = controller_order(joint_names, controller_joints)
        n = len(self.order)
        msg.joint_names = list(controller_joints)
        msg.header.frame_id = frame_id
        point.positions = [0.0] * n
        point.velocities = [0.0] * n
        point.accelerations = [0.0] * n
        ns = int(round(period * 1e9))
        point.time_from_start.sec = ns // 1_000_000_000
        point.time_from_start.nanosec = ns % 1_000_000_000
        msg.points = [point]
        self.point = msg.points[0]

    def fill(self, stamp_ns: int, y: Sequence[float], yd: Sequence[float],
             ydd: Sequence[float] = ()):
        """Write the stamp, positions and velocities; returns the message."""
        msg = self.msg
        st = msg.header.stamp
        st.sec = stamp_ns // 1_000_000_000
        st.nanosec = stamp_ns % 1_000_000_000
        pos, vel, acc = self.point.positions, self.point.velocities, self.point.accelerations
        for i, j in enumerate(self.order):
            pos[i] = y[j]
            vel[i] = yd[j]
        if ydd:
            for i, j in enumerate(self.order):
                acc[i] = ydd[j]
        return msg


# -- obstacles ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Obstacles:
    """An immutable snapshot of the obstacle set, in the robot base frame.

    Attributes
    ----------
    items : tuple of Sphere, Box or OrientedBox
        The obstacles (:mod:`cdmp_ros.core.kinematics.closest`), ordered by ``(ns, id)``.
    keys : tuple of (ns, id)
        The marker key of each item.
    """

    items: Tuple[Union[Sphere, Box, OrientedBox], ...]
    keys: Tuple[Tuple[str, int], ...]

    def __len__(self) -> int:
        return len(self.items)


EMPTY_OBSTACLES = Obstacles((), ())


def _finite(name: str, values: Sequence[float]) -> None:
    for axis, v in zip('xyzw', values):
        if not math.isfinite(v):
            raise ValidationError(f'{name}.{axis}: expected a finite value, got {v}')


def _rotation(name: str, q) -> NDArray[np.float64]:
    x, y, z, w = q.x, q.y, q.z, q.w
    _finite(name, (x, y, z, w))
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not 0.9 < norm < 1.1:
        raise ValidationError(f'{name}: expected a unit quaternion, got norm {norm:.4g}')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


class ObstacleSet:
    """Obstacles kept per ``(ns, id)`` from ``MarkerArray`` messages.

    Parameters
    ----------
    base_frame : str
        Markers must be in this frame (or have an empty ``frame_id``).
    max_obstacles : int
        Additions beyond this number are rejected.
    max_size : float
        Largest sphere diameter / box edge [m].
    max_distance : float
        Largest distance of a marker position from the base [m].
    """

    def __init__(self, base_frame: str = 'panda_link0', max_obstacles: int = 64,
                 max_size: float = 10.0, max_distance: float = 100.0):
        self.base_frame = base_frame
        self.max_obstacles = int(max_obstacles)
        self.max_size = float(max_size)
        self.max_distance = float(max_distance)
        # (ns, id) -> (Sphere or Box, expiry time or None)
        self._items: Dict[Tuple[str, int], tuple] = {}
        self.snapshot = EMPTY_OBSTACLES

    def __len__(self) -> int:
        return len(self._items)

    def apply(self, markers: Sequence, now: float = 0.0, name: str = 'obstacles'
              ) -> List[ValidationError]:
        """Apply the markers in order; returns the rejections (valid markers still apply).

        ``now`` [s, steady clock] is used for marker lifetimes.
        """
        errors = []
        changed = False
        for i, m in enumerate(markers):
            try:
                changed |= self._apply_one(m, now, f'{name}.markers[{i}]')
            except ValidationError as exc:
                errors.append(exc)
        if changed:
            self._rebuild()
        return errors

    def expire(self, now: float) -> bool:
        """Remove markers whose lifetime ended; True if the set changed."""
        dead = [k for k, v in self._items.items() if v[1] is not None and v[1] <= now]
        for k in dead:
            del self._items[k]
        if dead:
            self._rebuild()
        return bool(dead)

    def _apply_one(self, m, now: float, name: str) -> bool:
        action, key = m.action, (m.ns, m.id)
        if action == DELETEALL:
            if m.ns:
                keys = [k for k in self._items if k[0] == m.ns]
            else:
                keys = list(self._items)
            for k in keys:
                del self._items[k]
            return bool(keys)
        if action == DELETE:
            if key not in self._items:
                raise ValidationError(f'{name}: DELETE of unknown obstacle (ns={m.ns!r}, '
                                      f'id={m.id})')
            del self._items[key]
            return True
        if action != ADD:
            raise ValidationError(f'{name}.action: expected ADD/MODIFY (0), DELETE (2) or '
                                  f'DELETEALL (3), got {action}')
        frame = m.header.frame_id
        if frame and frame.lstrip('/') != self.base_frame:
            raise ValidationError(f'{name}.header.frame_id: expected the robot base frame '
                                  f'{self.base_frame!r} (or empty), got {frame!r}')
        if m.type not in (SPHERE, CUBE):
            tname = MARKER_TYPES.get(m.type, 'unknown')
            raise ValidationError(f'{name}.type: expected SPHERE (2) or CUBE (1), got '
                                  f'{m.type} ({tname})')
        p = m.pose.position
        center = np.array([p.x, p.y, p.z])
        _finite(f'{name}.pose.position', center)
        dist = float(np.linalg.norm(center))
        if dist > self.max_distance:
            raise ValidationError(f'{name}.pose.position: expected within {self.max_distance} m '
                                  f'of the base, got {dist:.4g} m')
        s = m.scale
        if m.type == SPHERE:
            self._check_scale(f'{name}.scale.x', s.x)
            item = Sphere(tuple(center), 0.5 * s.x)
        else:
            for axis, v in zip('xyz', (s.x, s.y, s.z)):
                self._check_scale(f'{name}.scale.{axis}', v)
            R = _rotation(f'{name}.pose.orientation', m.pose.orientation)
            size = np.array([s.x, s.y, s.z])
            if np.abs(R - np.eye(3)).max() <= AXIS_ALIGNED_TOL:
                item = Box(tuple(center - 0.5 * size), tuple(center + 0.5 * size))
            else:
                item = OrientedBox(tuple(center), tuple(size), tuple(map(tuple, R.tolist())))
        if key not in self._items and len(self._items) >= self.max_obstacles:
            raise ValidationError(f'{name}: obstacle limit reached ({self.max_obstacles}); '
                                  f'(ns={m.ns!r}, id={m.id}) not added')
        life = stamp_to_ns(m.lifetime) * 1e-9
        self._items[key] = (item, (now + life) if life > 0 else None)
        return True

    def _check_scale(self, name: str, v: float) -> None:
        if not math.isfinite(v) or v <= 0.0:
            raise ValidationError(f'{name}: expected a finite positive size [m], got {v}')
        if v > self.max_size:
            raise ValidationError(f'{name}: expected at most {self.max_size} m, got {v}')

    def _rebuild(self) -> None:
        keys = tuple(sorted(self._items))
        self.snapshot = Obstacles(tuple(self._items[k][0] for k in keys), keys)
