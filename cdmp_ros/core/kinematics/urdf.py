"""Minimal URDF parser for serial kinematic chains (``xml.etree`` only, no ROS).

Reads ``<link name>`` and ``<joint>`` elements with their ``<origin xyz rpy>``, ``<axis xyz>``,
``<parent link>``, ``<child link>`` and ``<limit lower upper velocity>``. Joint types
``revolute``, ``continuous``, ``prismatic`` and ``fixed`` are supported; ``floating`` and
``planar`` joints are rejected. Every failure raises
:class:`~cdmp_ros.core.errors.ValidationError` naming the joint (or link) and the field.

Conventions (URDF specification): the joint frame is the parent link frame moved by
``origin``; ``rpy`` are fixed-axis roll, pitch, yaw, i.e. ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``;
the child link frame coincides with the joint frame at zero joint position.
"""
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.errors import ValidationError

JOINT_TYPES = ('revolute', 'continuous', 'prismatic', 'fixed')

Vec3 = Tuple[float, float, float]


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint. ``lower``/``upper`` are -inf/+inf for continuous and fixed joints,
    ``velocity`` is +inf when the URDF gives none (fixed joints)."""

    name: str
    type: str
    parent: str
    child: str
    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)
    axis: Vec3 = (1.0, 0.0, 0.0)
    lower: float = -np.inf
    upper: float = np.inf
    velocity: float = np.inf

    @property
    def origin(self) -> NDArray[np.float64]:
        """Homogeneous transform (4, 4) from the parent link frame to the joint frame."""
        T = np.eye(4)
        T[:3, :3] = rpy_to_matrix(self.rpy)
        T[:3, 3] = self.xyz
        return T


@dataclass(frozen=True)
class UrdfRobot:
    """The parsed robot: link names (document order) and joints by name (document order)."""

    name: str
    links: Tuple[str, ...]
    joints: Tuple[UrdfJoint, ...]

    def joint_by_child(self) -> Dict[str, UrdfJoint]:
        """Map child link name -> the joint that moves it."""
        return {j.child: j for j in self.joints}

    def root_link(self) -> str:
        """The unique link that is no joint's child."""
        children = {j.child for j in self.joints}
        roots = [link for link in self.links if link not in children]
        if len(roots) != 1:
            raise ValidationError(f'robot {self.name!r}: expected exactly one root link, '
                                  f'got {roots}')
        return roots[0]

    def path(self, tip_link: str, base_link: Optional[str] = None) -> List[UrdfJoint]:
        """Joints from ``base_link`` (default: the root) down to ``tip_link``, in order."""
        if tip_link not in self.links:
            raise ValidationError(f'tip_link: expected one of the links of {self.name!r} '
                                  f'{list(self.links)}, got {tip_link!r}')
        if base_link is None:
            base_link = self.root_link()
        elif base_link not in self.links:
            raise ValidationError(f'base_link: expected one of the links of {self.name!r} '
                                  f'{list(self.links)}, got {base_link!r}')
        by_child = self.joint_by_child()
        path = []
        link = tip_link
        while link != base_link:
            if link not in by_child:
                raise ValidationError(f'tip_link: {tip_link!r} is not below base_link '
                                      f'{base_link!r} in robot {self.name!r}')
            joint = by_child[link]
            path.append(joint)
            link = joint.parent
        return path[::-1]


def rpy_to_matrix(rpy) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) of URDF fixed-axis roll, pitch, yaw: Rz(y) Ry(p) Rx(r)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr]])


def _floats(where: str, field: str, text: Optional[str], n: int, default=None) -> tuple:
    if text is None:
        if default is None:
            raise ValidationError(f'{where}: missing {field}')
        return default
    parts = text.split()
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        raise ValidationError(f'{where}: {field} expected {n} numbers, got {text!r}') from None
    if len(values) != n or not all(np.isfinite(values)):
        raise ValidationError(f'{where}: {field} expected {n} finite numbers, got {text!r}')
    return values


def _float(where: str, field: str, text: Optional[str], default: Optional[float]) -> float:
    if text is None:
        if default is None:
            raise ValidationError(f'{where}: missing {field}')
        return default
    try:
        value = float(text)
    except ValueError:
        raise ValidationError(f'{where}: {field} expected a number, got {text!r}') from None
    if not np.isfinite(value):
        raise ValidationError(f'{where}: {field} expected a finite number, got {text!r}')
    return value


def _parse_joint(el: ET.Element, links: set) -> UrdfJoint:
    name = el.get('name')
    if not name:
        raise ValidationError('joint: missing attribute name')
    where = f'joint {name!r}'
    jtype = el.get('type')
    if jtype not in JOINT_TYPES:
        raise ValidationError(f'{where}: type expected one of {JOINT_TYPES}, got {jtype!r}')
    ends = {}
    for tag in ('parent', 'child'):
        sub = el.find(tag)
        link = sub.get('link') if sub is not None else None
        if not link:
            raise ValidationError(f'{where}: missing <{tag} link="...">')
        if link not in links:
            raise ValidationError(f'{where}: {tag} link {link!r} is not a <link> of the robot')
        ends[tag] = link
    origin = el.find('origin')
    xyz = _floats(where, 'origin xyz', origin.get('xyz') if origin is not None else None,
                  3, (0.0, 0.0, 0.0))
    rpy = _floats(where, 'origin rpy', origin.get('rpy') if origin is not None else None,
                  3, (0.0, 0.0, 0.0))
    axis_el = el.find('axis')
    axis = _floats(where, 'axis xyz', axis_el.get('xyz') if axis_el is not None else None,
                   3, (1.0, 0.0, 0.0))
    lower, upper, velocity = -np.inf, np.inf, np.inf
    if jtype != 'fixed':
        norm = float(np.linalg.norm(axis))
        if norm < 1e-12:
            raise ValidationError(f'{where}: axis xyz expected a non-zero vector, got {axis}')
        axis = tuple(float(a) / norm for a in axis)
        limit = el.find('limit')
        if limit is None and jtype in ('revolute', 'prismatic'):
            raise ValidationError(f'{where}: missing <limit> (required for {jtype} joints)')
        if limit is not None:
            velocity = _float(where, 'limit velocity', limit.get('velocity'), None)
            if velocity <= 0:
                raise ValidationError(f'{where}: limit velocity expected > 0, got {velocity}')
            if jtype != 'continuous':
                lower = _float(where, 'limit lower', limit.get('lower'), 0.0)
                upper = _float(where, 'limit upper', limit.get('upper'), 0.0)
                if not lower < upper:
                    raise ValidationError(f'{where}: limit expected lower < upper, got '
                                          f'lower={lower}, upper={upper}')
    return UrdfJoint(name=name, type=jtype, parent=ends['parent'], child=ends['child'],
                     xyz=xyz, rpy=rpy, axis=axis, lower=lower, upper=upper, velocity=velocity)


def parse_urdf_string(text: str, source: str = '<string>') -> UrdfRobot:
    """Parse URDF XML text into a :class:`UrdfRobot`.

    Raises
    ------
    ValidationError
        Naming the element and field at fault (malformed XML, unknown joint type, missing
        parent/child, bad numbers, missing limits, duplicate names, a link with two parents).
    """
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValidationError(f'{source}: malformed XML ({exc})') from None
    if root.tag != 'robot':
        raise ValidationError(f'{source}: root element expected <robot>, got <{root.tag}>')
    links = []
    for el in root.findall('link'):
        name = el.get('name')
        if not name:
            raise ValidationError(f'{source}: a <link> is missing attribute name')
        if name in links:
            raise ValidationError(f'{source}: link {name!r} defined twice')
        links.append(name)
    link_set = set(links)
    joints = []
    names = set()
    children = {}
    for el in root.findall('joint'):
        joint = _parse_joint(el, link_set)
        if joint.name in names:
            raise ValidationError(f'{source}: joint {joint.name!r} defined twice')
        if joint.child in children:
            raise ValidationError(f'joint {joint.name!r}: child link {joint.child!r} already '
                                  f'has parent joint {children[joint.child]!r}')
        names.add(joint.name)
        children[joint.child] = joint.name
        joints.append(joint)
    return UrdfRobot(name=root.get('name', ''), links=tuple(links), joints=tuple(joints))


def parse_urdf(path: str) -> UrdfRobot:
    """Parse a URDF file (see :func:`parse_urdf_string`)."""
    try:
        with open(path, encoding='utf-8') as f:
            text = f.read()
    except OSError as exc:
        raise ValidationError(f'urdf path: cannot read {path!r} ({exc})') from None
    return parse_urdf_string(text, source=str(path))
