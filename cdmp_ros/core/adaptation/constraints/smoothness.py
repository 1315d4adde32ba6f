"""Smoothness as a constraint P(R(w) <= d) >= alpha on the generalised chi^2 variable
R(w) = w^T Phi_R w (Eq. 14-15, paper 003). With Phi_R = V diag(e) V^T, R(w) = |A w|^2 for
A = diag(sqrt(e)) V^T, a quadratic form |y|^2 of the Gaussian y = A w: its CDF is the
saddle-point approximation of the repellers' and waypoints' law
(:func:`cdmp_ros.core.promp.quadratic_tail.quadratic_form_cdf`), or the paper's Gamma moment
match (Eq. 15) with ``tail = 'gamma'``. The regulariser kappa * E[R(w)] is an option of the
optimiser (AdaptationConfig.kappa)."""
from typing import Optional

import numpy as np

from cdmp_ros.core.adaptation.constraints.base import WeightConstraint
from cdmp_ros.core.promp.gaussian import gamma_cdf
from cdmp_ros.core.promp.quadratic_tail import quadratic_form_cdf
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.validation import check_positive


def smoothness_moments(mu, Sigma, Phi):
    """E[R] and V[R] of Eq. (15) with gradients w.r.t. mu and Sigma."""
    Pm = Phi @ mu
    PS = Phi @ Sigma
    E = mu @ Pm + np.trace(PS)
    V = 4.0 * Pm @ Sigma @ Pm + 2.0 * np.sum(PS * PS.T)
    dE_dmu = 2.0 * Pm
    dE_dS = Phi
    dV_dmu = 8.0 * Phi @ Sigma @ Pm
    dV_dS = 4.0 * np.outer(Pm, Pm) + 4.0 * PS @ Phi
    return E, V, dE_dmu, dE_dS, dV_dmu, dV_dS


class SmoothnessConstraint(WeightConstraint):
    """P(R(w) <= bound) >= alpha with Phi_R from ProMP.smoothness_matrix.

    Parameters
    ----------
    Phi : array-like, shape (D * M, D * M)
        Matrix of the quadratic form R(w) = w^T Phi w (Eq. 14).
    bound : float
        d in P(R(w) <= d).
    alpha, lambda0, eta, name
        As :class:`~cdmp_ros.core.adaptation.constraints.base.Constraint`.
    """
    kind = 'smoothness'

    def __init__(self, Phi, bound: float, alpha: float = 0.999,
                 lambda0: Optional[float] = None, eta: Optional[float] = None,
                 name: Optional[str] = None):
        super().__init__(alpha, lambda0, eta, name)
        self.Phi = 0.5 * (np.asarray(Phi, float) + np.asarray(Phi, float).T)
        self.bound = check_positive('bound', bound)
        e, V = np.linalg.eigh(self.Phi)
        keep = e > 1e-12 * max(float(e[-1]), 0.0)
        if not np.any(keep):
            raise ValidationError('Phi: expected a positive semi-definite matrix with a '
                                  'positive eigenvalue')
        self.A = np.sqrt(e[keep])[:, None] * V[:, keep].T      # R(w) = |A w|^2
        self._state = {}

    def probability_w(self, mu, Sigma, tail='saddlepoint'):
        if tail == 'gamma':
            E, V, dE_dmu, dE_dS, dV_dmu, dV_dS = smoothness_moments(mu, Sigma, self.Phi)
            G, dG_dE, dG_dV = gamma_cdf(np.array([E]), np.array([V]), self.bound)
            dmu = dG_dE[0] * dE_dmu + dG_dV[0] * dV_dmu
            dS = dG_dE[0] * dE_dS + dG_dV[0] * dV_dS
            return G, dmu[None], dS[None]
        A = self.A
        G, dG_dm, dG_dS = quadratic_form_cdf((A @ mu)[None], (A @ Sigma @ A.T)[None],
                                             np.zeros(A.shape[0]), self.bound, self._state)
        return G, (dG_dm @ A), (A.T @ dG_dS[0] @ A)[None]

    def satisfied_w(self, W):
        return np.einsum('ki,ij,kj->k', W, self.Phi, W) <= self.bound

    def describe(self):
        d = super().describe()
        d['bound'] = self.bound
        return d
