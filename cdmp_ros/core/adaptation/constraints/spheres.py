"""Waypoints and repellers (Eq. 17-18), temporally unbound waypoints (Eq. 19) and mutual
avoidance (Eq. 22), paper 003: the law of c_t = |x_t - x_bar|^2 under the Gaussian
approximation of x_t (unscented transform for non-linear points of interest, exact for linear
ones), evaluated by the saddle-point approximation of the generalised chi-square law
(:func:`cdmp_ros.core.promp.quadratic_tail.quadratic_form_cdf`, accurate in the 1e-4 ... 1e-2
tails a confidence alpha asks about) or, with ``tail = 'gamma'``, by the paper's Gamma moment
match (Eq. 15), whose tail is too light (violations 1.4-2.5 times the requested level)."""
from typing import Optional

import numpy as np

from cdmp_ros.core.adaptation.constraints.base import DECIDED_ATOL, DECIDED_RTOL, Constraint
from cdmp_ros.core.adaptation.constraints.points import DifferencePoint, Point
from cdmp_ros.core.promp.gaussian import gamma_cdf, quadratic_moments
from cdmp_ros.core.promp.quadratic_tail import quadratic_form_cdf
from cdmp_ros.core.validation import as_array, check_positive


#: The far-waypoint guide (:meth:`_Sphere.guide_rows`) acts below this standardised distance
#: (the normal match's P = Phi(-3) = 1.3e-3) with this slope (phi(-3): one unit of z below the
#: threshold it pulls as hard as the probability itself does at the threshold).
GUIDE_Z = -3.0
GUIDE_SLOPE = 0.00443


def _gamma_rows(m, S, params):
    """P(|x - x_bar|^2 <= d^2) per row by the Gamma match of Eq. 17-18 (Eq. 15's moments),
    with its gradients w.r.t. the point's mean and covariance."""
    E, V, dE_dm, dE_dS, dV_dm, dV_dS = quadratic_moments(m, S, params['center'])
    G, dG_dE, dG_dV = gamma_cdf(E, V, params['r2'])
    dG_dm = dG_dE[:, None] * dE_dm + dG_dV[:, None] * dV_dm
    dG_dS = dG_dE[:, None, None] * dE_dS + dG_dV[:, None, None] * dV_dS
    return G, dG_dm, dG_dS


class _Sphere(Constraint):
    inside = True  # waypoint: satisfied inside the ball

    def __init__(self, point: Point, center, radius: float, support=(0.0, 1.0),
                 alpha: float = 0.999, lambda0: Optional[float] = None,
                 eta: Optional[float] = None, name: Optional[str] = None):
        super().__init__(point, support, alpha, lambda0, eta, name)
        if callable(center):
            self.center = center
        else:
            self.center = as_array('center', center, (point.n_out,))
        self.radius = check_positive('radius', radius)

    def centers(self, times):
        if callable(self.center):
            return np.broadcast_to(np.asarray(self.center(times), float),
                                   (times.size, self.point.n_out))
        return np.broadcast_to(self.center, (times.size, self.point.n_out))

    batch_kind = 'sphere'

    def rows(self, times):
        n = times.size
        return {'center': np.asarray(self.centers(times), float),
                'r2': np.full(n, self.radius ** 2), 'inside': np.full(n, bool(self.inside))}

    @staticmethod
    def probability_rows(m, S, params):
        """P(|x - x_bar|^2 <= d^2) (waypoints) or its complement (repellers) per row.

        ``params`` may carry ``'tail'`` ('saddlepoint', the default, 'gamma' or
        'conservative': per row the law with the larger violation probability) and
        ``'state'``, a dict kept between calls on the same rows (the saddle points' warm
        start), as the optimiser's batches do (:class:`AdaptationConfig.tail`)."""
        inside = params['inside']
        tail = params.get('tail', 'saddlepoint')
        if tail == 'gamma':
            G, dG_dm, dG_dS = _gamma_rows(m, S, params)
        else:
            G, dG_dm, dG_dS = quadratic_form_cdf(m, S, params['center'], params['r2'],
                                                 params.get('state'))
            if tail == 'conservative':
                Gg, dGg_dm, dGg_dS = _gamma_rows(m, S, params)
                # the violation is G for a repeller, 1 - G for a waypoint: keep the larger
                gamma = np.where(inside, Gg < G, Gg > G)
                G = np.where(gamma, Gg, G)
                dG_dm = np.where(gamma[:, None], dGg_dm, dG_dm)
                dG_dS = np.where(gamma[:, None, None], dGg_dS, dG_dS)
        if np.all(inside):
            return G, dG_dm, dG_dS
        if not np.any(inside):
            return 1.0 - G, -dG_dm, -dG_dS
        sign = np.where(inside, 1.0, -1.0)
        return (np.where(inside, G, 1.0 - G), sign[:, None] * dG_dm,
                sign[:, None, None] * dG_dS)

    @staticmethod
    def guide_rows(m, S, params):
        """The far-waypoint guide (a robust objective): an addition ``G <= 0`` to
        the probability of each *inside* row, used only in the Lagrangian.

        Far from a waypoint the probability of being inside the ball and its gradient vanish
        (to below 1e-300, or exactly 0 where the saddle point skips rows beyond 7.5 standard
        deviations), so the optimiser cannot move the distribution towards it. With
        ``z = (r^2 - E[Q]) / sqrt(V[Q])`` (the standardised distance of the normal match of
        Q = |x - c|^2; Eq. 15's moments), ``G = -GUIDE_SLOPE / 2 (GUIDE_Z - z)^2`` while
        ``z < GUIDE_Z`` and 0 above it: continuous with its gradient, zero wherever the
        constraint can hold, so the optimum and every reported probability are unchanged.
        Its slope grows with the distance, so the pull never fades. Repeller rows: 0.
        """
        inside = np.asarray(params['inside'], bool)
        n = m.shape[0]
        G = np.zeros(n)
        dG_dm = np.zeros_like(m)
        dG_dS = np.zeros_like(S)
        if not inside.any():
            return G, dG_dm, dG_dS
        E, V, dE_dm, dE_dS, dV_dm, dV_dS = quadratic_moments(m, S, params['center'])
        sV = np.sqrt(np.maximum(V, 1e-300))
        num = params['r2'] - E
        z = num / sV
        act = inside & (z < GUIDE_Z)
        if not act.any():
            return G, dG_dm, dG_dS
        gap = np.where(act, GUIDE_Z - z, 0.0)
        G = -0.5 * GUIDE_SLOPE * gap * gap
        # dz = -dE / sqrt(V) - num dV / (2 V^1.5); dG = GUIDE_SLOPE gap dz
        a = GUIDE_SLOPE * gap / sV
        b = GUIDE_SLOPE * gap * num / (2.0 * sV * V)
        dG_dm = -a[:, None] * dE_dm - b[:, None] * dV_dm
        dG_dS = -a[:, None, None] * dE_dS - b[:, None, None] * dV_dS
        return G, dG_dm, dG_dS

    def decided_near(self, X, radius, times):
        return self._decided(self._dist2(X, times), radius)

    def screened(self, X, radius, times):
        d2 = self._dist2(X, times)
        inside = d2 <= self.radius ** 2
        return self._decided(d2, radius), (~inside if self.inside else inside)

    def _decided(self, d2, radius):
        # the ball of ``radius`` around the point lies wholly inside or wholly outside the sphere
        return np.abs(np.sqrt(d2) - self.radius) > radius * (1.0 + DECIDED_RTOL) + DECIDED_ATOL

    def _dist2(self, X, times):
        # per coordinate: X may be a view whose coordinates are planes in memory (the
        # verification's first-order screen)
        ctr = self.centers(times)
        d2 = np.square(X[..., 0] - ctr[:, 0])
        for k in range(1, X.shape[-1]):
            d2 += np.square(X[..., k] - ctr[:, k])
        return d2

    def describe(self):
        d = super().describe()
        d['radius'] = self.radius
        if not callable(self.center):
            d['center'] = self.center.tolist()
        return d


class Waypoint(_Sphere):
    """P(|x_t - x_bar|^2 <= d^2) >= alpha at every time of the support (Eq. 17).

    Parameters
    ----------
    point, center, radius, support, alpha, lambda0, eta, name
        As :class:`Repeller` (``radius``: the tolerance d [m]).
    """
    kind = 'waypoint'
    inside = True

    def satisfied(self, X, times):
        return self._dist2(X, times) <= self.radius ** 2


class Repeller(_Sphere):
    """P(|x_t - x_bar|^2 > d^2) >= alpha at every time of the support (Eq. 18).

    Parameters
    ----------
    point : Point
        Point of interest x_t (k = ``point.n_out`` coordinates).
    center : array-like, shape (k,), or callable(times) -> array (n_times, k)
        Centre x_bar (fixed or moving).
    radius : float
        d [m].
    support, alpha, lambda0, eta, name
        As :class:`~cdmp_ros.core.adaptation.constraints.base.Constraint`.
    """
    kind = 'repeller'
    inside = False

    def satisfied(self, X, times):
        return self._dist2(X, times) > self.radius ** 2


class UnboundWaypoint(_Sphere):
    """max_t P(|x_t - x_bar|^2 <= d^2) >= alpha over the support (Eq. 19): one multiplier,
    gradient through t_max = argmax_t of the approximate probability.

    Parameters
    ----------
    point, center, radius, support, alpha, lambda0, eta, name
        As :class:`Repeller` (``radius``: the tolerance d [m]).
    """
    kind = 'unbound_waypoint'
    inside = True
    reduce = 'max'

    def satisfied(self, X, times):
        return np.any(self._dist2(X, times) <= self.radius ** 2, axis=1)


class MutualAvoidance(Repeller):
    """P(|x1_t - x2_t|^2 > d^2) >= alpha (Eq. 22): a repeller at 0 on the difference of two
    points of interest of a joint ProMP w = (w1, w2).

    Parameters
    ----------
    point1, point2 : Point
        Points of interest of the two robots, with equal ``n_out`` (e.g. two
        :class:`~cdmp_ros.core.adaptation.constraints.points.ChainPoint` s).
    distance : float
        d [m].
    support, alpha, lambda0, eta, name
        As :class:`~cdmp_ros.core.adaptation.constraints.base.Constraint`.
    """
    kind = 'mutual_avoidance'

    def __init__(self, point1: Point, point2: Point, distance: float, support=(0.0, 1.0),
                 alpha: float = 0.999, lambda0: Optional[float] = None,
                 eta: Optional[float] = None, name: Optional[str] = None):
        point = DifferencePoint(point1, point2)
        super().__init__(point, np.zeros(point.n_out), distance, support, alpha, lambda0, eta,
                         name)
