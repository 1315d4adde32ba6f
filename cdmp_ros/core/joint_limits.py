"""The joint limits a primitive is run with: the tighter of the primitive's and the robot's.

A primitive file carries the limits it was learned with; the robot that runs it has its own
(its URDF). :func:`merge_limits` takes, per joint and per bound, the tighter of the two (never
widening what either side allows) and lists every difference, so that a node can report it.
"""
from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.validation import check_limits

__all__ = ['LimitMismatch', 'merge_limits', 'describe_mismatches']

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
