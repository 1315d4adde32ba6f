"""Base classes of the probabilistic constraints (paper 003, Eq. 5b-6).

A constraint k requires P_w(constraint holds) >= alpha_k at every time of its temporal support
(``reduce = 'each'``: one Lagrange multiplier per time step), or at the best time of its support
(``reduce = 'max'``, temporally unbound waypoints, Eq. 19: one multiplier). Each constraint
returns the approximate satisfaction probability F (the CDF term of Eq. 10) and its gradients
w.r.t. the Gaussian moments (m_t, S_t) of its point of interest.
"""
from typing import Optional, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.adaptation.constraints.points import Point
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import check_positive

#: :meth:`Constraint.decided_near` decides only where the margin exceeds the radius by these
#: relative and absolute amounts (rounding of the reference point and of the distances).
DECIDED_RTOL = 1e-9
DECIDED_ATOL = 1e-12


def _set_common(c, alpha, lambda0, eta, name) -> None:
    """The confidence, multiplier settings and name every constraint has, checked."""
    c.alpha = float(alpha)
    if not 0.0 < c.alpha < 1.0:
        raise ValidationError(f'alpha: expected a probability in (0, 1), got {alpha}')
    c.lambda0 = None if lambda0 is None else check_positive('lambda0', lambda0)
    c.eta = None if eta is None else check_positive('eta', eta)
    c.name = name or c.kind


class Constraint:
    """Common parameters.

    Parameters
    ----------
    point : Point
        Point of interest x_t = T(z_t).
    support : (float, float)
        Temporal support [t0, t1] in phase; t0 == t1 is a point constraint at t0.
    alpha : float
        Confidence: required satisfaction probability, in (0, 1).
    lambda0 : float, optional
        Initial Lagrange multiplier (default: the optimiser's).
    eta : float, optional
        Multiplier learning rate of the exponential method of multipliers.
    name : str, optional
    """
    kind = 'constraint'
    reduce = 'each'

    def __init__(self, point: Point, support=(0.0, 1.0), alpha: float = 0.999,
                 lambda0: Optional[float] = None, eta: Optional[float] = None,
                 name: Optional[str] = None):
        self.point = point
        t0, t1 = (float(v) for v in support)
        if not (0.0 <= t0 <= t1 <= 1.0):
            raise ValidationError(f'support: expected 0 <= t0 <= t1 <= 1, got {support}')
        self.support = (t0, t1)
        _set_common(self, alpha, lambda0, eta, name)

    def times(self, grid: NDArray) -> NDArray:
        """Phases of the grid inside the support (the support's start if it is a point)."""
        t0, t1 = self.support
        eps = 1e-9
        sel = grid[(grid >= t0 - eps) & (grid <= t1 + eps)]
        return sel if sel.size else np.array([t0])

    def probability(self, m: NDArray, S: NDArray, times: NDArray
                    ) -> Tuple[NDArray, NDArray, NDArray]:
        """Satisfaction probability per time and its gradients.

        The default evaluates :meth:`probability_rows` on :meth:`rows`; subclasses either
        implement those two (then the optimiser evaluates every constraint of the same
        ``batch_kind`` in one vectorised call) or override this method.

        Parameters
        ----------
        m : (n, k) means of x_t; S : (n, k, k) covariances; times : (n,) phases.

        Returns
        -------
        F : (n,); dF_dm : (n, k); dF_dS : (n, k, k)
        """
        if self.batch_kind is None:
            raise NotImplementedError
        return self.probability_rows(m, S, self.rows(times))

    # Constraints sharing a ``batch_kind`` are evaluated together: their per-time parameters
    # (rows) are stacked and one ``probability_rows`` call handles every row.
    batch_kind: Optional[str] = None

    def rows(self, times: NDArray) -> dict:
        """Per-time parameters of :meth:`probability_rows`: arrays with leading size n."""
        raise NotImplementedError

    @staticmethod
    def probability_rows(m: NDArray, S: NDArray, params: dict
                         ) -> Tuple[NDArray, NDArray, NDArray]:
        """F, dF_dm, dF_dS for rows (m (N, k), S (N, k, k)) with stacked ``rows`` params."""
        raise NotImplementedError

    def satisfied(self, X: NDArray, times: NDArray) -> NDArray:
        """Whether sampled points satisfy the constraint.

        Parameters
        ----------
        X : (n_samples, n, k) sampled x_t at ``times``.

        Returns
        -------
        ndarray of bool, shape (n_samples, n) ('each') or (n_samples,) ('max').
        """
        raise NotImplementedError

    def decided_near(self, X: NDArray, radius: NDArray, times: NDArray
                     ) -> Optional[NDArray]:
        """Where :meth:`satisfied` gives every point within ``radius`` of ``X`` the outcome
        of ``X`` itself (the sampled verification then needs no kinematics there).

        Parameters
        ----------
        X : (n, k) reference points at ``times``, or (n_samples, n, k): one per pair.
        radius : (n_samples, n) distances from them.

        Returns
        -------
        ndarray of bool (n_samples, n), or None when the constraint cannot tell (the
        default: every sample is evaluated).
        """
        return None

    def screened(self, X: NDArray, radius: NDArray, times: NDArray
                 ) -> Tuple[Optional[NDArray], NDArray]:
        """:meth:`decided_near` and the violation at ``X`` in one call, on points ``X``
        (n_samples, n, k) of their own (the sampled verification's first-order screen):
        ``(decided, violated)``, both (n_samples, n) bool (decided None: cannot tell).
        Subclasses may compute both from one distance."""
        return (self.decided_near(X, radius, times),
                ~np.asarray(self.satisfied(X, times), bool))

    def describe(self) -> dict:
        return {'name': self.name, 'type': self.kind, 'alpha': self.alpha,
                'support': list(self.support)}


class WeightConstraint:
    """A constraint on the weight vector itself (smoothness as a constraint, Eq. 14-15)."""
    kind = 'weight_constraint'
    reduce = 'each'

    def __init__(self, alpha: float = 0.999, lambda0: Optional[float] = None,
                 eta: Optional[float] = None, name: Optional[str] = None):
        _set_common(self, alpha, lambda0, eta, name)

    def probability_w(self, mu: NDArray, Sigma: NDArray, tail: str = 'saddlepoint'
                      ) -> Tuple[NDArray, NDArray, NDArray]:
        """F (1,), dF/dmu (1, n), dF/dSigma (1, n, n); ``tail``: AdaptationConfig.tail."""
        raise NotImplementedError

    def satisfied_w(self, W: NDArray) -> NDArray:
        """W (n_samples, n) -> bool (n_samples,)."""
        raise NotImplementedError

    def describe(self) -> dict:
        return {'name': self.name, 'type': self.kind, 'alpha': self.alpha}
