"""The tanh map between joint space and the exogenous space of CDMPs (paper 000).

``y = y_delta * tanh(xi) + y_o`` with ``y_o = (y_min + y_max) / 2`` and
``y_delta = (y_max - y_min) / 2`` (Eq. 3/19, with the definitions corrected as in
../shared/papers/README.md). Whatever finite ``xi`` is, ``y`` lies in the open interval
``(y_min, y_max)``; to keep that strict in floating point, ``xi`` is saturated at
``+-XI_SAT`` (``tanh(XI_SAT) = 1 - 1e-9``), so a position is never closer to a limit than
``1e-9 * y_delta``.

Positions that touch or cross a limit (demonstrations, goals beyond the limits) cannot be mapped
by ``arctanh``; they are first clipped to ``y_o +- (1 - margin) * y_delta`` (``margin``
defaults to 1e-3, i.e. 0.1 % of the half range), so they map to finite ``xi``.
"""
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import check_limits

#: Saturation of the exogenous state: tanh(XI_SAT) = 1 - 1e-9.
SAT_MARGIN = 1e-9
XI_SAT = math.atanh(1.0 - SAT_MARGIN)


class TanhTransform:
    """Map between joint positions ``y`` and exogenous states ``xi`` for per-joint limits.

    Parameters
    ----------
    y_min, y_max : array-like, shape (n_dims,)
        Lower and upper position limits, finite, ``y_min < y_max``.
    margin : float
        Fraction of the half range kept free when clipping positions at or beyond a limit
        before ``arctanh``; ``0 < margin < 1``.
    """

    def __init__(self, y_min: ArrayLike, y_max: ArrayLike, margin: float = 1e-3):
        lo, hi = check_limits(y_min, y_max)
        if not (0.0 < float(margin) < 1.0):
            raise ValidationError(f'margin: expected 0 < margin < 1, got {margin!r}')
        self.y_min = lo
        self.y_max = hi
        self.margin = float(margin)
        self.y_o = 0.5 * (lo + hi)
        self.y_delta = 0.5 * (hi - lo)
        self.n_dims = lo.shape[0]

    def clip_position(self, Y: ArrayLike) -> NDArray[np.float64]:
        """Clip positions to ``y_o +- (1 - margin) * y_delta``."""
        Y = np.asarray(Y, dtype=np.float64)
        bound = (1.0 - self.margin) * self.y_delta
        return np.clip(Y, self.y_o - bound, self.y_o + bound)

    def to_exogenous(self, Y: ArrayLike) -> NDArray[np.float64]:
        """Eq. (20), paper 000: ``xi = arctanh((y - y_o) / y_delta)``, after clipping.

        Parameters
        ----------
        Y : array-like, shape (..., n_dims)

        Returns
        -------
        XI : ndarray, shape (..., n_dims), finite for any finite input.
        """
        Yc = self.clip_position(Y)
        return np.arctanh((Yc - self.y_o) / self.y_delta)  # Eq. (20), paper 000

    def to_joint(self, XI: ArrayLike) -> NDArray[np.float64]:
        """Eq. (19)/(27), paper 000: ``y = y_delta * tanh(xi) + y_o`` (xi saturated)."""
        XI = np.clip(np.asarray(XI, dtype=np.float64), -XI_SAT, XI_SAT)
        return self.y_delta * np.tanh(XI) + self.y_o  # Eq. (19), paper 000

    def jacobian(self, XI: ArrayLike) -> NDArray[np.float64]:
        """``J(xi) = y_delta * (1 - tanh(xi)^2)``, the diagonal of dy/dxi."""
        t = np.tanh(np.asarray(XI, dtype=np.float64))
        return self.y_delta * (1.0 - t * t)

    def velocity(self, XI: ArrayLike, XId: ArrayLike) -> NDArray[np.float64]:
        """Eq. (28), paper 000: ``yd = J(xi) xid``."""
        return self.jacobian(XI) * np.asarray(XId, dtype=np.float64)  # Eq. (28), paper 000

    def acceleration(self, XI: ArrayLike, XId: ArrayLike, XIdd: ArrayLike
                     ) -> NDArray[np.float64]:
        """Eq. (29), paper 000: ``ydd = J(xi) xidd + Jdot(xi, xid) xid``.

        ``Jdot xid = -2 y_delta tanh(xi) (1 - tanh(xi)^2) xid^2``.
        """
        t = np.tanh(np.asarray(XI, dtype=np.float64))
        XId = np.asarray(XId, dtype=np.float64)
        s = 1.0 - t * t
        return self.y_delta * s * (np.asarray(XIdd, dtype=np.float64)
                                   - 2.0 * t * XId * XId)  # Eq. (29), paper 000
