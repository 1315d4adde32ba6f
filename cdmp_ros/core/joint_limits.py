"""The joint limits a primitive is run with: the tighter of the primitive's and the robot's.

Position and velocity come from the URDF; acceleration and jerk from parameters in the
convention of MoveIt's and ros2_control's ``joint_limits.yaml`` (:func:`parse_joint_limits`);
:class:`KinematicLimits` holds all four orders and merges sources tighter-of-two.

A primitive file carries the limits it was learned with; the robot that runs it has its own
(its URDF). :func:`merge_limits` takes, per joint and per bound, the tighter of the two (never
widening what either side allows) and lists every difference, so that a node can report it.
"""
import math
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import check_limits

__all__ = ['LimitMismatch', 'merge_limits', 'describe_mismatches', 'KinematicLimits',
           'parse_joint_limits', 'joint_limits_entries', 'panda_limits', 'PANDA_DATASHEET',
           'default_joint_limits', 'shipped_limits']

#: Bounds closer than this [rad or m] are equal (URDF files round to 4 decimals).
LIMIT_TOLERANCE = 1e-9


@dataclass(frozen=True)
class LimitMismatch:
    """One bound of one joint on which the primitive and the robot differ.

    Attributes
    ----------
    joint : str
    bound : str
        ``'lower'`` or ``'upper'``.
    primitive, robot : float
        The two values.
    used : float
        The tighter one (``max`` of lower bounds, ``min`` of upper bounds).
    """

    joint: str
    bound: str
    primitive: float
    robot: float
    used: float

    @property
    def wider(self) -> bool:
        """True when the primitive allows more than the robot (it is clipped)."""
        return self.used == self.robot

    def __str__(self) -> str:
        side = 'robot' if self.wider else 'primitive'
        return (f'{self.joint} {self.bound}: primitive {self.primitive:.6g}, robot '
                f'{self.robot:.6g} -> {self.used:.6g} ({side})')


def merge_limits(joint_names: Sequence[str], robot_lower: ArrayLike, robot_upper: ArrayLike,
                 primitive_lower: ArrayLike, primitive_upper: ArrayLike
                 ) -> Tuple[NDArray[np.float64], NDArray[np.float64], List[LimitMismatch]]:
    """The tighter of the robot's and the primitive's limits, per joint and bound.

    Parameters
    ----------
    joint_names : sequence of str, length n_dims
    robot_lower, robot_upper, primitive_lower, primitive_upper : array-like, shape (n_dims,)
        In the order of ``joint_names``.

    Returns
    -------
    lower, upper : ndarray, shape (n_dims,)
    mismatches : list of LimitMismatch
        Every bound that differs by more than :data:`LIMIT_TOLERANCE`.

    Raises
    ------
    ValidationError
        Malformed limits, or limits whose intersection is empty on a joint (naming it).
    """
    n = len(joint_names)
    rlo, rhi = check_limits(robot_lower, robot_upper, n)
    plo, phi = check_limits(primitive_lower, primitive_upper, n)
    lo, hi = np.maximum(rlo, plo), np.minimum(rhi, phi)
    check_limits(lo, hi, n)
    out = []
    for j, name in enumerate(joint_names):
        for bound, p, r, u in (('lower', plo[j], rlo[j], lo[j]), ('upper', phi[j], rhi[j], hi[j])):
            if abs(p - r) > LIMIT_TOLERANCE:
                out.append(LimitMismatch(name, bound, float(p), float(r), float(u)))
    return lo, hi, out


def describe_mismatches(mismatches: Sequence[LimitMismatch]) -> str:
    """One line for diagnostics: every differing bound with both values and the one used."""
    if not mismatches:
        return 'none'
    return '; '.join(str(m) for m in mismatches)


# -- kinematic limits in the ROS convention ---------------------------------------------------

#: The keys of one joint's entry in MoveIt's / ros2_control's ``joint_limits.yaml``. The ones
#: the package uses are read; the others are accepted (a shared file carries them) and ignored.
USED_KEYS = ('has_position_limits', 'min_position', 'max_position', 'has_velocity_limits',
             'max_velocity', 'has_acceleration_limits', 'max_acceleration', 'has_jerk_limits',
             'max_jerk')
IGNORED_KEYS = ('has_deceleration_limits', 'max_deceleration', 'has_effort_limits',
                'max_effort', 'angle_wraparound', 'has_soft_limits', 'k_position',
                'k_velocity', 'soft_lower_limit', 'soft_upper_limit')
#: The orders of :class:`KinematicLimits` beside the position, as named in the convention.
ORDERS = ('velocity', 'acceleration', 'jerk')

#: Franka Emika Panda, datasheet ("Robot and interface specifications"): per joint
#: q_max / q_min [rad], dq_max [rad/s], ddq_max [rad/s^2], dddq_max [rad/s^3].
PANDA_DATASHEET = {
    'lower': (-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973),
    'upper': (2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973),
    'velocity': (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61),
    'acceleration': (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0),
    'jerk': (7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0),
}


@dataclass(frozen=True)
class KinematicLimits:
    """Position, velocity, acceleration and jerk limits per joint, and where each came from.

    Attributes
    ----------
    joint_names : tuple of str, length n_dims
    lower, upper : ndarray, shape (n_dims,)
        Position limits [rad or m].
    velocity, acceleration, jerk : ndarray, shape (n_dims,)
        Positive limits; ``inf`` where none is set.
    sources : tuple of str
        One line per source merged in, e.g. ``'urdf: position, velocity'``.
    """

    joint_names: Tuple[str, ...]
    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    velocity: NDArray[np.float64]
    acceleration: NDArray[np.float64]
    jerk: NDArray[np.float64]
    sources: Tuple[str, ...] = ()

    def __post_init__(self):
        n = len(self.joint_names)
        lo, hi = check_limits(self.lower, self.upper, n)
        object.__setattr__(self, 'joint_names', tuple(self.joint_names))
        object.__setattr__(self, 'lower', lo)
        object.__setattr__(self, 'upper', hi)
        for order in ORDERS:
            arr = np.array(getattr(self, order), dtype=np.float64).reshape(-1)
            if arr.shape != (n,) or np.any(np.isnan(arr)) or np.any(arr <= 0.0):
                raise ValidationError(f'{order} limits: expected {n} positive values (inf: '
                                      f'none), got {getattr(self, order)!r}')
            object.__setattr__(self, order, arr)

    @classmethod
    def unlimited(cls, joint_names: Sequence[str], lower: ArrayLike, upper: ArrayLike,
                  velocity: Optional[ArrayLike] = None, source: str = 'urdf'
                  ) -> 'KinematicLimits':
        """Position (and velocity) limits only, as a URDF gives them."""
        n = len(joint_names)
        vel = np.full(n, np.inf) if velocity is None else np.asarray(velocity, dtype=float)
        vel = np.where(np.isfinite(vel) & (vel > 0.0), vel, np.inf)
        what = 'position, velocity' if np.any(np.isfinite(vel)) else 'position'
        return cls(tuple(joint_names), lower, upper, vel, np.full(n, np.inf),
                   np.full(n, np.inf), (f'{source}: {what}',))

    def merged(self, other: 'KinematicLimits') -> 'KinematicLimits':
        """The tighter of the two per joint and bound (never wider than either); ``other``
        may name the joints in another order but must name the same ones.

        Raises
        ------
        ValidationError
            Other joints, or position limits whose intersection is empty.
        """
        if sorted(other.joint_names) != sorted(self.joint_names):
            raise ValidationError(f'joint limits: expected the joints {list(self.joint_names)}, '
                                  f'got {list(other.joint_names)}')
        idx = [other.joint_names.index(n) for n in self.joint_names]
        lo = np.maximum(self.lower, other.lower[idx])
        hi = np.minimum(self.upper, other.upper[idx])
        return KinematicLimits(self.joint_names, lo, hi,
                               np.minimum(self.velocity, other.velocity[idx]),
                               np.minimum(self.acceleration, other.acceleration[idx]),
                               np.minimum(self.jerk, other.jerk[idx]),
                               self.sources + other.sources)

    def subset(self, joint_names: Sequence[str]) -> 'KinematicLimits':
        """The limits of ``joint_names`` (in that order)."""
        try:
            idx = [self.joint_names.index(n) for n in joint_names]
        except ValueError as exc:
            raise ValidationError(f'joint limits: {exc}') from None
        return KinematicLimits(tuple(joint_names), self.lower[idx], self.upper[idx],
                               self.velocity[idx], self.acceleration[idx], self.jerk[idx],
                               self.sources)

    def ratios(self, v: ArrayLike, a: ArrayLike, j: ArrayLike) -> Tuple[float, float, float]:
        """The worst ratio of ``|v|``, ``|a|``, ``|j|`` (shape (..., n_dims)) to its limit
        (0 where a limit is infinite)."""
        out = []
        for x, lim in ((v, self.velocity), (a, self.acceleration), (j, self.jerk)):
            x = np.abs(np.asarray(x, dtype=float))
            out.append(float(np.max(x / lim, initial=0.0)) if x.size else 0.0)
        return out[0], out[1], out[2]

    def describe(self) -> str:
        """One line per order for diagnostics."""
        def fmt(arr):
            return '[' + ', '.join('none' if not np.isfinite(x) else f'{x:.6g}'
                                   for x in arr) + ']'
        pos = ', '.join(f'{lo:.4g}..{hi:.4g}' for lo, hi in zip(self.lower, self.upper))
        return (f'position [{pos}]'
                f'; velocity {fmt(self.velocity)}; acceleration {fmt(self.acceleration)}'
                f'; jerk {fmt(self.jerk)}')


def parse_joint_limits(joint_names: Sequence[str], entries: Mapping[str, Mapping[str, Any]],
                       lower: ArrayLike, upper: ArrayLike, source: str = 'joint_limits'
                       ) -> KinematicLimits:
    """Limits from entries in the convention of ``joint_limits.yaml``.

    Parameters
    ----------
    joint_names : sequence of str
    entries : mapping joint name -> mapping
        The keys of :data:`USED_KEYS` (a ``max_*`` counts only with its ``has_*`` true) and
        :data:`IGNORED_KEYS`; joints without an entry get no limit from this source.
    lower, upper : array-like, shape (n_dims,)
        The position limits where an entry sets none (the URDF's).

    Raises
    ------
    ValidationError
        An entry for an unknown joint, an unknown key, a ``has_*`` that is not a bool, a
        ``max_*`` missing or not a positive finite number where its ``has_*`` is true, or
        ``min_position >= max_position`` (each naming the joint and the key).
    """
    n = len(joint_names)
    lo, hi = check_limits(lower, upper, n)
    lo, hi = lo.copy(), hi.copy()
    unknown = [k for k in entries if k not in joint_names]
    if unknown:
        raise ValidationError(f'joint_limits: entries for unknown joints {unknown}; the joints '
                              f'are {list(joint_names)}')
    vals = {o: np.full(n, np.inf) for o in ORDERS}
    seen = set()
    for d, name in enumerate(joint_names):
        entry = entries.get(name)
        if entry is None:  # 'joint:' with nothing under it
            entry = {}
        if not isinstance(entry, Mapping):
            raise ValidationError(f'joint_limits.{name}: expected a mapping of limits, got '
                                  f'{type(entry).__name__}')
        bad = [k for k in entry if k not in USED_KEYS + IGNORED_KEYS]
        if bad:
            raise ValidationError(f'joint_limits.{name}.{bad[0]}: unknown key (of {bad}); '
                                  f'expected some of {list(USED_KEYS)}')

        def flag(key):
            v = entry.get(key, False)
            if not isinstance(v, (bool, np.bool_)):
                raise ValidationError(f'joint_limits.{name}.{key}: expected true or false, got '
                                      f'{v!r}')
            return bool(v)

        def number(key, positive=True):
            v = entry.get(key)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            if not ok or (positive and v <= 0.0):
                kind = 'a positive number' if positive else 'a finite number'
                raise ValidationError(f'joint_limits.{name}.{key}: expected {kind}, got {v!r}')
            return float(v)

        if flag('has_position_limits'):
            pmin, pmax = number('min_position', False), number('max_position', False)
            if not pmin < pmax:
                raise ValidationError(f'joint_limits.{name}.min_position: {pmin} is not below '
                                      f'joint_limits.{name}.max_position {pmax}')
            lo[d], hi[d] = max(lo[d], pmin), min(hi[d], pmax)
            seen.add('position')
        for order in ORDERS:
            if flag(f'has_{order}_limits'):
                vals[order][d] = number(f'max_{order}')
                seen.add(order)
    what = ', '.join(o for o in ('position',) + ORDERS if o in seen) or 'nothing'
    return KinematicLimits(tuple(joint_names), lo, hi, vals['velocity'],
                           vals['acceleration'], vals['jerk'], (f'{source}: {what}',))


def joint_limits_entries(limits: KinematicLimits, position: bool = False
                         ) -> Dict[str, Dict[str, Any]]:
    """``limits`` as ``joint_limits.yaml`` entries (the inverse of :func:`parse_joint_limits`)."""
    out = {}
    for d, name in enumerate(limits.joint_names):
        e: Dict[str, Any] = {}
        if position:
            e.update(has_position_limits=True, min_position=float(limits.lower[d]),
                     max_position=float(limits.upper[d]))
        for order in ORDERS:
            x = float(getattr(limits, order)[d])
            e[f'has_{order}_limits'] = math.isfinite(x)
            if math.isfinite(x):
                e[f'max_{order}'] = x
        out[name] = e
    return out


def panda_limits(prefix: str = 'panda_') -> KinematicLimits:
    """The Panda's datasheet limits (joint names ``<prefix>joint1..7``)."""
    names = tuple(f'{prefix}joint{i}' for i in range(1, 8))
    ds = PANDA_DATASHEET
    return KinematicLimits(names, ds['lower'], ds['upper'], ds['velocity'],
                           ds['acceleration'], ds['jerk'], ('Franka datasheet',))


#: Shipped acceleration and jerk limits of the planar arm of paper 003, III-A (no datasheet:
#: a stiff 1 m link arm; position and velocity come from its generated URDF).
PLANAR_ACCELERATION = 10.0
PLANAR_JERK = 5000.0


def default_joint_limits(joint_names: Sequence[str]) -> Dict[str, Dict[str, Any]]:
    """The shipped ``joint_limits`` entries of the joints the package knows: the Panda's
    datasheet for ``[<prefix>]panda_joint1..7`` (the dual-arm cell's ``left_``/``right_``
    included), :data:`PLANAR_ACCELERATION` and :data:`PLANAR_JERK` for the planar arm's
    ``joint1..n``; no entry for other joints."""
    ds = PANDA_DATASHEET
    out = {}
    for name in joint_names:
        head, _, tail = name.rpartition('panda_joint')
        if tail.isdigit() and 1 <= int(tail) <= 7 and (head == '' or head.endswith('_')):
            i = int(tail) - 1
            out[name] = {'has_velocity_limits': True, 'max_velocity': ds['velocity'][i],
                         'has_acceleration_limits': True,
                         'max_acceleration': ds['acceleration'][i],
                         'has_jerk_limits': True, 'max_jerk': ds['jerk'][i]}
        elif name.startswith('joint') and name[5:].isdigit():
            out[name] = {'has_acceleration_limits': True,
                         'max_acceleration': PLANAR_ACCELERATION,
                         'has_jerk_limits': True, 'max_jerk': PLANAR_JERK}
    return out


def shipped_limits(joint_names: Sequence[str], lower: ArrayLike, upper: ArrayLike,
                   velocity: Optional[ArrayLike], source: str,
                   entries: Optional[Mapping[str, Mapping[str, Any]]] = None
                   ) -> KinematicLimits:
    """The limits a node runs with: the URDF's position and velocity (named ``source``)
    merged tighter-of-two with ``joint_limits`` entries (default: the shipped ones of
    :func:`default_joint_limits`)."""
    urdf = KinematicLimits.unlimited(joint_names, lower, upper, velocity, source=source)
    if entries is None:
        entries, what = default_joint_limits(joint_names), 'shipped joint_limits'
    else:
        what = 'joint_limits parameters'
    return urdf.merged(parse_joint_limits(joint_names, entries, lower, upper, source=what))
