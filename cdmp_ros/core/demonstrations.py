"""Demonstrations for the learner: validation, joint mapping and topic segmentation.

A demonstration is ``(T, Y)``: ``T`` (n_steps,) seconds from its first sample, strictly
increasing; ``Y`` (n_steps, n_dims) joint positions in the learner's joint order.

Segmentation of a stream of samples (:class:`DemonstrationSegmenter`, the ``demonstration``
topic of the learner node): a demonstration ends

- when no sample arrived for ``gap`` seconds (receive time, checked by :meth:`poll`),
- when a sample's stamp is more than ``gap`` seconds after the previous one (the new sample
  starts the next demonstration),
- on an explicit end marker (the node maps an empty ``JointState``, no names, to :meth:`end`),
- when it reaches ``max_samples``.

A sample whose stamp is not after the previous one (non-monotonic time) or whose position is
outside the limits by more than ``limit_tolerance`` is rejected on its own; the demonstration
goes on. A finished demonstration shorter than ``min_samples`` is discarded with a reason.
"""
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array, check_limits

Demo = Tuple[NDArray[np.float64], NDArray[np.float64]]


def check_inside_limits(name: str, Y: NDArray[np.float64], lower: NDArray[np.float64],
                        upper: NDArray[np.float64], tolerance: float,
                        joint_names: Sequence[str]) -> None:
    """Raise if a position lies further than ``tolerance`` outside ``[lower, upper]``."""
    bad = (Y < lower - tolerance) | (Y > upper + tolerance)
    if np.any(bad):
        idx = np.argwhere(bad)[0]
        j = int(idx[-1])
        v = float(Y[tuple(idx)])
        where = f' (sample {int(idx[0])})' if Y.ndim == 2 else ''
        raise ValidationError(f'{name} of {joint_names[j]!r}{where}: {v:.4g} is outside the '
                              f'limits [{lower[j]:.4g}, {upper[j]:.4g}] by more than '
                              f'{tolerance} rad')


def map_demonstration(name: str, T: ArrayLike, Y: ArrayLike, names: Sequence[str],
                      joint_names: Sequence[str], lower: ArrayLike, upper: ArrayLike,
                      min_samples: int = 3, limit_tolerance: float = 0.05) -> Demo:
    """Validate a recorded demonstration and reorder its columns as ``joint_names``.

    Parameters
    ----------
    name : str
        Used in error messages (e.g. the bag path).
    T : array-like, shape (n_steps,)
    Y : array-like, shape (n_steps, len(names))
    names : sequence of str
        The joint of each column; extra joints (grippers) are ignored.
    joint_names : sequence of str
        The learner's joints, all required.
    lower, upper : array-like, shape (n_dims,)
    min_samples : int
    limit_tolerance : float

    Returns
    -------
    (T, Y)
        ``T`` from 0, ``Y`` shape (n_steps, n_dims).

    Raises
    ------
    ValidationError
        Duplicate or missing joints, wrong shapes, non-finite values, too few samples,
        non-increasing times, positions outside the limits.
    """
    names = list(names)
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValidationError(f'{name}: duplicate joint name {dup!r}')
    missing = [n for n in joint_names if n not in names]
    if missing:
        raise ValidationError(f'{name}: missing joints {missing}; got {names}')
    T = as_array(f'{name}: T', T, (None,))
    Y = as_array(f'{name}: positions', Y, (T.size, len(names)))
    if T.size < min_samples:
        raise ValidationError(f'{name}: expected at least {min_samples} samples, got {T.size}')
    dT = np.diff(T)
    if np.any(dT <= 0):
        k = int(np.flatnonzero(dT <= 0)[0]) + 1
        raise ValidationError(f'{name}: non-monotonic time at sample {k} ({T[k]:.6f} s after '
                              f'{T[k - 1]:.6f} s)')
    Y = Y[:, [names.index(n) for n in joint_names]]
    lo, hi = check_limits(lower, upper, len(joint_names))
    check_inside_limits(f'{name}: position', Y, lo, hi, limit_tolerance, joint_names)
    return T - T[0], Y


@dataclass
class SegmentEvent:
    """A demonstration closed by the segmenter: ``demo`` is None when it was discarded."""

    demo: Optional[Demo]
    message: str


class DemonstrationSegmenter:
    """Cuts a stream of joint samples into demonstrations (see the module docstring).

    Parameters
    ----------
    joint_names : sequence of str
    lower, upper : array-like, shape (n_dims,)
    gap : float
        Seconds without samples (or between two stamps) that end a demonstration.
    min_samples, max_samples : int
    limit_tolerance : float
    """

    def __init__(self, joint_names: Sequence[str], lower: ArrayLike, upper: ArrayLike,
                 gap: float = 0.5, min_samples: int = 10, max_samples: int = 100000,
                 limit_tolerance: float = 0.05):
        self.joint_names = list(joint_names)
        self.lower, self.upper = check_limits(lower, upper, len(self.joint_names))
        self.configure(gap, min_samples, max_samples, limit_tolerance)
        self._t: List[float] = []
        self._y: List[NDArray[np.float64]] = []
        self._last_receive = None
        self.n_completed = 0

    def configure(self, gap: float, min_samples: int, max_samples: int,
                  limit_tolerance: float) -> None:
        self.gap = float(gap)
        self.min_samples = int(min_samples)
        self.max_samples = int(max_samples)
        self.limit_tolerance = float(limit_tolerance)

    @property
    def n_pending(self) -> int:
        """Samples of the demonstration in progress."""
        return len(self._t)

    def add(self, stamp: float, q: ArrayLike, now: float,
            name: str = 'demonstration') -> List[SegmentEvent]:
        """Add one sample (``stamp`` [s], ``q`` (n_dims,) in joint order) received at ``now``.

        Returns the demonstrations this sample closed (a stamp gap closes the previous one,
        ``max_samples`` closes the current one).

        Raises
        ------
        ValidationError
            Non-finite or out-of-limit position, non-monotonic stamp; the sample is dropped.
        """
        q = as_array(f'{name}.position', q, (len(self.joint_names),))
        check_inside_limits(f'{name}.position', q, self.lower, self.upper,
                            self.limit_tolerance, self.joint_names)
        stamp = float(stamp)
        events = []
        if self._t:
            last = self._t[-1]
            if stamp <= last:
                raise ValidationError(
                    f'{name}.header.stamp: non-monotonic time, {stamp - last:+.6f} s from the '
                    f'previous sample of the demonstration in progress')
            if stamp - last > self.gap:
                events += self.end(f'stamp gap of {stamp - last:.3f} s > {self.gap} s')
        self._t.append(stamp)
        self._y.append(q)
        self._last_receive = now
        if len(self._t) >= self.max_samples:
            events += self.end(f'max_samples ({self.max_samples}) reached')
        return events

    def poll(self, now: float) -> List[SegmentEvent]:
        """Close the demonstration in progress if no sample came for ``gap`` seconds."""
        if self._t and now - self._last_receive > self.gap:
            return self.end(f'no sample for {now - self._last_receive:.3f} s')
        return []

    def end(self, reason: str = 'end marker') -> List[SegmentEvent]:
        """Close the demonstration in progress (nothing if none)."""
        if not self._t:
            return []
        T = np.asarray(self._t)
        Y = np.vstack(self._y)
        self._t, self._y = [], []
        n = T.size
        if n < self.min_samples:
            return [SegmentEvent(None, f'demonstration discarded ({reason}): {n} samples, '
                                       f'expected at least min_samples={self.min_samples}')]
        self.n_completed += 1
        return [SegmentEvent((T - T[0], Y), f'demonstration complete ({reason}): {n} samples, '
                                            f'{T[-1] - T[0]:.3f} s')]
