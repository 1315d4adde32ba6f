"""Joint (coordinate) limits, one- and two-sided, possibly time-varying (Eq. 11-13, paper 003)."""
from typing import Callable, Optional, Union

import numpy as np

from cdmp_ros.core.adaptation.constraints.base import Constraint
from cdmp_ros.core.adaptation.constraints.points import DofPoint
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.gaussian import normal_cdf, normal_pdf

Bound = Union[None, float, Callable]


def _bound(b: Bound, times, default):
    if b is None:
        return np.full(times.shape, default)
    if callable(b):
        return np.broadcast_to(np.asarray(b(times), dtype=float), times.shape)
    return np.full(times.shape, float(b))


class JointLimit(Constraint):
    """P(a_t < z_t^j <= b_t) >= alpha (Eq. 12; Eq. 11 with a = -inf).

    Parameters
    ----------
    joint : int
        Index of the ProMP dimension.
    lower, upper : float, callable(times) -> array, or None
        Bounds a_t and b_t (None: unbounded on that side); callables give time-varying limits.
    """
    kind = 'joint_limit'

    def __init__(self, joint: int, lower: Bound = None, upper: Bound = None,
                 support=(0.0, 1.0), alpha: float = 0.999, lambda0: Optional[float] = None,
                 eta: Optional[float] = None, name: Optional[str] = None):
        super().__init__(DofPoint([joint]), support, alpha, lambda0, eta, name)
        if lower is None and upper is None:
            raise ValidationError('limits: expected a lower or an upper bound, got neither')
        self.joint = int(joint)
        self.lower, self.upper = lower, upper

    def bounds(self, times):
        a = _bound(self.lower, times, -np.inf)
        b = _bound(self.upper, times, np.inf)
        return a, b

    batch_kind = 'limit'

    def rows(self, times):
        a, b = self.bounds(times)
        a, b = np.asarray(a, float), np.asarray(b, float)
        finite = bool(np.all(np.isfinite(a)) and np.all(np.isfinite(b)))
        return {'a': a, 'b': b, 'finite': np.full(times.size, finite)}

    @staticmethod
    def probability_rows(m, S, params):
        # Eq. (13), paper 003
        a, b = params['a'], params['b']
        mu = m[:, 0]
        sd = np.sqrt(np.maximum(S[:, 0, 0], 1e-300))
        finite = params.get('finite')
        if finite is not None and np.all(finite):    # every bound finite: no masking
            zb, za = (b - mu) / sd, (a - mu) / sd
            pb, pa = normal_pdf(zb), normal_pdf(za)
            F = normal_cdf(zb) - normal_cdf(za)
            dF_dvar = (-pb * zb + pa * za) / (2.0 * sd * sd)
            return F, ((pa - pb) / sd)[:, None], dF_dvar[:, None, None]
        fb, fa = np.isfinite(b), np.isfinite(a)
        zb0 = np.where(fb, (np.where(fb, b, 0.0) - mu) / sd, 0.0)
        za0 = np.where(fa, (np.where(fa, a, 0.0) - mu) / sd, 0.0)
        F = np.where(fb, normal_cdf(zb0), 1.0) - np.where(fa, normal_cdf(za0), 0.0)
        pb = np.where(fb, normal_pdf(zb0), 0.0)
        pa = np.where(fa, normal_pdf(za0), 0.0)
        dF_dmu = (-pb + pa) / sd
        dF_dvar = (-pb * zb0 + pa * za0) / (2.0 * sd * sd)
        return F, dF_dmu[:, None], dF_dvar[:, None, None]

    def satisfied(self, X, times):
        a, b = self.bounds(times)
        z = X[..., 0]
        return (z > a) & (z <= b)

    def describe(self):
        d = super().describe()
        d['joint'] = self.joint
        return d
