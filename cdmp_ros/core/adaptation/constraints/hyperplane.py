"""Hyperplanes / virtual walls (Eq. 16) and non-convex corners (Eq. 20-21), paper 003."""
from typing import Optional

import numpy as np

from cdmp_ros.core.adaptation.constraints.base import DECIDED_ATOL, DECIDED_RTOL, Constraint
from cdmp_ros.core.adaptation.constraints.points import Point
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.promp.gaussian import normal_cdf, normal_pdf
from cdmp_ros.core.validation import as_array


def _halfspace(m, S, n, b):
    """P(n^T (x - b) >= 0) for x ~ N(m, S) per row, and its gradients.

    m : (N, k); S : (N, k, k); n, b : (k,) or per row (N, k).
    """
    n = np.broadcast_to(n, m.shape)
    mu = np.einsum('ni,ni->n', m - b, n)
    var = np.maximum(np.einsum('ni,nij,nj->n', n, S, n), 1e-300)
    sd = np.sqrt(var)
    z = mu / sd
    P = normal_cdf(z)
    pdf = normal_pdf(z)
    dP_dm = (pdf / sd)[:, None] * n
    dP_dS = (-pdf * mu / (2.0 * var * sd))[:, None, None] * (n[:, :, None] * n[:, None, :])
    return P, dP_dm, dP_dS


class Hyperplane(Constraint):
    """Virtual wall: P(n^T (x_t - b) <= 0) >= alpha (Eq. 16, Gaussian approximation of x_t).

    Parameters
    ----------
    point : Point
        Point of interest x_t (k = ``point.n_out`` coordinates).
    normal : array-like, shape (k,)
        Normal n, pointing into the forbidden side.
    offset : array-like, shape (k,)
        A point b on the plane.
    support, alpha, lambda0, eta, name
        As :class:`~cdmp_ros.core.adaptation.constraints.base.Constraint`.
    """
    kind = 'hyperplane'

    def __init__(self, point: Point, normal, offset, support=(0.0, 1.0),
                 alpha: float = 0.999, lambda0: Optional[float] = None,
                 eta: Optional[float] = None, name: Optional[str] = None):
        super().__init__(point, support, alpha, lambda0, eta, name)
        self.normal = as_array('normal', normal, (point.n_out,))
        if not np.linalg.norm(self.normal) > 0:
            raise ValidationError('normal: expected a non-zero vector, got zeros')
        self.offset = as_array('offset', offset, (point.n_out,))

    batch_kind = 'hyperplane'

    def rows(self, times):
        n = times.size
        return {'n': np.tile(self.normal, (n, 1)), 'b': np.tile(self.offset, (n, 1))}

    @staticmethod
    def probability_rows(m, S, params):
        P, dP_dm, dP_dS = _halfspace(m, S, params['n'], params['b'])
        return 1.0 - P, -dP_dm, -dP_dS

    def satisfied(self, X, times):
        return (X - self.offset) @ self.normal <= 0.0

    def decided_near(self, X, radius, times):
        # the ball of ``radius`` around X lies wholly on one side of the plane
        gap = np.abs((X - self.offset) @ self.normal) / np.linalg.norm(self.normal)
        return gap > radius * (1.0 + DECIDED_RTOL) + DECIDED_ATOL

    def describe(self):
        d = super().describe()
        d.update(normal=self.normal.tolist(), offset=self.offset.tolist())
        return d


class NonConvexCorner(Constraint):
    """Avoid the corner {n1^T (x - b1) >= 0 and n2^T (x - b2) >= 0} (Eq. 20), with the product
    approximation P(A and B) ~ P(A) P(B) of Eq. (21): F = 1 - P1 P2.

    Parameters
    ----------
    point : Point
        Point of interest x_t (k = ``point.n_out`` coordinates).
    normal1, offset1, normal2, offset2 : array-like, shape (k,)
        The two half-spaces' normals (pointing into the corner) and points on their planes.
    support, alpha, lambda0, eta, name
        As :class:`~cdmp_ros.core.adaptation.constraints.base.Constraint`.
    """
    kind = 'corner'

    def __init__(self, point: Point, normal1, offset1, normal2, offset2, support=(0.0, 1.0),
                 alpha: float = 0.999, lambda0: Optional[float] = None,
                 eta: Optional[float] = None, name: Optional[str] = None):
        super().__init__(point, support, alpha, lambda0, eta, name)
        k = point.n_out
        self.n1 = as_array('normal1', normal1, (k,))
        self.b1 = as_array('offset1', offset1, (k,))
        self.n2 = as_array('normal2', normal2, (k,))
        self.b2 = as_array('offset2', offset2, (k,))

    batch_kind = 'corner'

    def rows(self, times):
        n = times.size
        return {k: np.tile(getattr(self, k), (n, 1)) for k in ('n1', 'b1', 'n2', 'b2')}

    @staticmethod
    def probability_rows(m, S, params):
        # product approximation of Eq. (21)
        P1, dm1, dS1 = _halfspace(m, S, params['n1'], params['b1'])
        P2, dm2, dS2 = _halfspace(m, S, params['n2'], params['b2'])
        F = 1.0 - P1 * P2
        dF_dm = -(P2[:, None] * dm1 + P1[:, None] * dm2)
        dF_dS = -(P2[:, None, None] * dS1 + P1[:, None, None] * dS2)
        return F, dF_dm, dF_dS

    def satisfied(self, X, times):
        inside = ((X - self.b1) @ self.n1 >= 0.0) & ((X - self.b2) @ self.n2 >= 0.0)
        return ~inside

    def describe(self):
        d = super().describe()
        d.update(normal1=self.n1.tolist(), offset1=self.b1.tolist(),
                 normal2=self.n2.tolist(), offset2=self.b2.tolist())
        return d
