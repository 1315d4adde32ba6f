"""Figures of a recorded run (the demo's summary) and the geometry of its scripted events.

Pure numpy: the demo driver (ROS side) uses :func:`path_progress` and :func:`drop_positions`
to place and drop an obstacle into the planned path; ``cdmp demo`` uses
:func:`tracking_error` and :func:`percentiles` on the arrays read back from the bag.
"""
from typing import Dict, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import as_array


def path_progress(path: ArrayLike, point: ArrayLike) -> float:
    """Fraction of the arc length of ``path`` at its sample nearest to ``point``.

    Parameters
    ----------
    path : array_like, shape (n_steps, 3)
        Planned end-effector path (n_steps >= 2).
    point : array_like, shape (3,)

    Returns
    -------
    float
        In [0, 1]; 0 for a path of zero length.
    """
    P = as_array('path', path, shape=(None, 3))
    x = as_array('point', point, shape=(3,))
    if P.shape[0] < 2:
        raise ValidationError(f'path: expected at least 2 samples, got {P.shape[0]}')
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0.0:
        return 0.0
    i = int(np.argmin(np.linalg.norm(P - x, axis=1)))
    return float(s[i] / s[-1])


def point_at_progress(path: ArrayLike, fraction: float) -> NDArray[np.float64]:
    """The point of ``path`` (n_steps, 3) at ``fraction`` of its arc length (linear)."""
    P = as_array('path', path, shape=(None, 3))
    if not 0.0 <= fraction <= 1.0:
        raise ValidationError(f'fraction: expected in [0, 1], got {fraction}')
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    if s[-1] <= 0.0:
        return P[0].copy()
    target = fraction * s[-1]
    return np.array([np.interp(target, s, P[:, k]) for k in range(3)])


def drop_positions(target: ArrayLike, height: float, n: int) -> NDArray[np.float64]:
    """Positions of an obstacle falling onto ``target`` from ``height`` above it.

    Constant acceleration from rest (a free fall in shape): ``z_k = z_t + height (1 - (k /
    (n - 1))^2)``, k = 0..n-1; the last position is ``target``.

    Returns
    -------
    ndarray, shape (n, 3)
    """
    x = as_array('target', target, shape=(3,))
    if n < 2:
        raise ValidationError(f'n: expected >= 2, got {n}')
    if not np.isfinite(height) or height < 0.0:
        raise ValidationError(f'height: expected a finite value >= 0, got {height}')
    u = np.linspace(0.0, 1.0, n)
    out = np.repeat(x[None, :], n, axis=0)
    out[:, 2] += height * (1.0 - u ** 2)
    return out


def tracking_error(T_ref: ArrayLike, Q_ref: ArrayLike, T: ArrayLike,
                   Q: ArrayLike) -> Dict[str, float]:
    """Reference-to-measurement error at the measurement times.

    The reference is sampled at each measurement time by the latest reference sample at or
    before it (what the robot had been told to track); measurements before the first
    reference are ignored.

    Parameters
    ----------
    T_ref : array_like, shape (n_ref,)
        Reference times, increasing.
    Q_ref : array_like, shape (n_ref, n_dims)
    T : array_like, shape (n_meas,)
        Measurement times.
    Q : array_like, shape (n_meas, n_dims)

    Returns
    -------
    dict
        ``max_rad`` (largest absolute joint error), ``rms_rad`` (root mean square of the
        per-sample largest joint error), ``n`` (measurements compared).
    """
    T_ref = as_array('T_ref', T_ref, shape=(None,))
    Q_ref = as_array('Q_ref', Q_ref, shape=(T_ref.size, None))
    T = as_array('T', T, shape=(None,))
    Q = as_array('Q', Q, shape=(T.size, Q_ref.shape[1]))
    if np.any(np.diff(T_ref) < 0):
        raise ValidationError('T_ref: expected non-decreasing times')
    idx = np.searchsorted(T_ref, T, side='right') - 1
    ok = idx >= 0
    if not np.any(ok):
        return {'max_rad': float('nan'), 'rms_rad': float('nan'), 'n': 0}
    err = np.abs(Q[ok] - Q_ref[idx[ok]]).max(axis=1)
    return {'max_rad': float(err.max()), 'rms_rad': float(np.sqrt(np.mean(err ** 2))),
            'n': int(ok.sum())}


def percentiles(samples: Sequence[float], qs=(50.0, 99.0)) -> Dict[str, float]:
    """``{'p50': ..., 'p99': ...}`` of ``samples`` (NaN when empty; linear interpolation)."""
    x = np.asarray(samples, dtype=np.float64)
    if x.size == 0:
        return {f'p{q:g}': float('nan') for q in qs}
    return {f'p{q:g}': float(v) for q, v in zip(qs, np.percentile(x, qs))}
