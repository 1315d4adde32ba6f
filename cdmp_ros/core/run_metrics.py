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


#: Relative slack of :func:`kinematic_report` (rounding of stamps and positions).
KINEMATIC_TOLERANCE = 0.02


def stamped_differences(stamps_ns: ArrayLike, Q: ArrayLike):
    """Velocity, acceleration and jerk of a stream as a controller sees it: ``k!`` times the
    ``k``-th divided differences of consecutive positions on their own stamps. They are exact
    for a cubic whatever the gaps, and where a sample is missing the difference across the gap
    is a weighted mean of the differences the full grid would give (never above their
    maximum); on an exact grid they are the backward differences divided by ``dt^k``.

    Parameters
    ----------
    stamps_ns : array-like, shape (n,)
        Strictly increasing stamps [ns].
    Q : array-like, shape (n, n_dims)

    Returns
    -------
    V, A, J : ndarray, shapes (n-1, n_dims), (n-2, n_dims), (n-3, n_dims)

    Raises
    ------
    ValidationError
        Shapes differ, or the stamps do not increase strictly.
    """
    raw = np.asarray(stamps_ns)
    if raw.ndim != 1:
        raise ValidationError(f'stamps_ns: expected shape (*,), got {raw.shape}')
    # relative to the first stamp in integer nanoseconds: epoch seconds in float64 resolve
    # only ~0.2 us, which reads as 1e-4 of a 2 ms period in the differences
    t = (raw.astype(np.int64) - (int(raw[0]) if raw.size else 0)) * 1e-9
    Q = as_array('Q', Q, (t.size, None))
    if t.size > 1 and not np.all(np.diff(t) > 0.0):
        k = int(np.flatnonzero(np.diff(t) <= 0.0)[0])
        raise ValidationError(f'stamps_ns: expected strictly increasing stamps, got '
                              f'{stamps_ns[k]} then {stamps_ns[k + 1]} at index {k}')
    out, x = [], Q
    for k in (1, 2, 3):
        if x.shape[0] < 2:
            out.append(np.zeros((0, Q.shape[1])))
            continue
        x = np.diff(x, axis=0) * (k / (t[k:] - t[:-k]))[:, None]
        out.append(x)
    return out[0], out[1], out[2]


def kinematic_report(stamps_ns: ArrayLike, Q: ArrayLike, limits,
                     tolerance: float = KINEMATIC_TOLERANCE) -> Dict:
    """Per order (velocity, acceleration, jerk): the samples over the limit by more than
    ``tolerance`` and the worst ratio to the limit, of a stream differenced on its stamps
    (:func:`stamped_differences`); and the positions outside ``[lower, upper]``.

    ``limits`` is a :class:`~cdmp_ros.core.joint_limits.KinematicLimits` in the order of the
    columns of ``Q``. Returns ``{'velocity': {'over': int, 'worst_ratio': float}, ...,
    'position_outside': int, 'samples': int, 'ok': bool}``.
    """
    V, A, J = stamped_differences(stamps_ns, Q)
    Q = np.asarray(Q, dtype=float)
    rep: Dict = {'samples': int(Q.shape[0])}
    ok = True
    for name, X, lim in (('velocity', V, limits.velocity), ('acceleration', A,
                                                            limits.acceleration),
                         ('jerk', J, limits.jerk)):
        r = np.abs(X) / lim if X.size else np.zeros((0, Q.shape[1]))
        worst = float(r.max()) if r.size else 0.0
        over = int(np.count_nonzero(np.any(r > 1.0 + tolerance, axis=1)))
        rep[name] = {'over': over, 'worst_ratio': worst}
        ok &= over == 0
    outside = int(np.count_nonzero(np.any((Q <= limits.lower) | (Q >= limits.upper), axis=1)))
    rep['position_outside'] = outside
    rep['ok'] = bool(ok and outside == 0)
    return rep
