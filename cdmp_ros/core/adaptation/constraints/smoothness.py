"""Smoothness as a constraint P(R(w) <= d) >= alpha with the Gamma approximation of the
generalised chi^2 variable R(w) = w^T Phi_R w (Eq. 14-15, paper 003). The regulariser
kappa * E[R(w)] is an option of the optimiser (AdaptationConfig.kappa)."""
from typing import Optional

import numpy as np

from cdmp_ros.core.adaptation.constraints.base import WeightConstraint
from cdmp_ros.core.promp.gaussian import gamma_cdf
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
    Phi : (n, n) matrix of the quadratic form (Eq. 14).
    bound : float
        d in P(R(w) <= d).
    """
    kind = 'smoothness'

    def __init__(self, Phi, bound: float, alpha: float = 0.999,
                 lambda0: Optional[float] = None, eta: Optional[float] = None,
                 name: Optional[str] = None):
        super().__init__(alpha, lambda0, eta, name)
        self.Phi = 0.5 * (np.asarray(Phi, float) + np.asarray(Phi, float).T)
        self.bound = check_positive('bound', bound)

    def probability_w(self, mu, Sigma):
        E, V, dE_dmu, dE_dS, dV_dmu, dV_dS = smoothness_moments(mu, Sigma, self.Phi)
        G, dG_dE, dG_dV = gamma_cdf(np.array([E]), np.array([V]), self.bound)
        dmu = dG_dE[0] * dE_dmu + dG_dV[0] * dV_dmu
        dS = dG_dE[0] * dE_dS + dG_dV[0] * dV_dS
        return G, dmu[None], dS[None]

    def satisfied_w(self, W):
        return np.einsum('ki,ij,kj->k', W, self.Phi, W) <= self.bound

    def describe(self):
        d = super().describe()
        d['bound'] = self.bound
        return d
