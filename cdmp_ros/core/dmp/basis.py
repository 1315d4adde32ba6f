"""Canonical system and the Gaussian forcing basis of DMPs/CDMPs (paper 000, Eq. 16-18/24-26)."""
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError

#: Normalised time at which the basis switches to its exponential tail (s = exp(-alpha_s u)).
U_END = 2.0


@dataclass(frozen=True)
class PhaseBasis:
    """Gaussian kernels in the phase ``s`` of the canonical system.

    ``s(u) = exp(-alpha_s * u)`` with the normalised time ``u = t / tau`` (Eq. 18/26,
    ``tau * ds/dt = -alpha_s * s``). Kernel ``j``:
    ``psi_j(s) = exp(-0.5 * h_j * (s - c_j)^2)`` (Eq. 17/25) with centres
    ``c_j = exp(-alpha_s * j / (n - 1))`` (equally spaced in normalised time over [0, 1]) and
    ``h_j = 1 / (basis_width * |c_{j+1} - c_j|)^2``. Features (Eq. 16/24 without the goal
    factor): ``phi_j(s) = psi_j(s) * s / sum_k psi_k(s)``.

    Beyond ``u = U_END`` the features follow the exponential tail
    ``phi(u) = phi(U_END) * exp(-alpha_s * (u - U_END))``, which is the limit of the exact
    formula as the last kernel dominates; it keeps the features cheap and smooth forever.
    """

    n_weights_per_dim: int = 30
    alpha_s: float = 4.0
    basis_width: float = 1.0
    centers: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    widths: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = self.n_weights_per_dim
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValidationError(f'n_weights_per_dim: expected an integer >= 1, got {n!r}')
        for name in ('alpha_s', 'basis_width'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValidationError(f'{name}: expected a finite positive number, got {v!r}')
        if n == 1:
            centers = np.array([1.0])
            spacing = np.array([1.0])
        else:
            centers = np.exp(-self.alpha_s * np.linspace(0.0, 1.0, n))
            d = np.abs(np.diff(centers))
            spacing = np.append(d, d[-1])
        widths = 1.0 / (self.basis_width * spacing) ** 2
        object.__setattr__(self, 'centers', centers)
        object.__setattr__(self, 'widths', widths)

    @classmethod
    def from_arrays(cls, centers: ArrayLike, widths: ArrayLike, alpha_s: float,
                    basis_width: float = 1.0) -> 'PhaseBasis':
        """A basis with explicit centres and widths (as stored in primitive files)."""
        centers = np.asarray(centers, dtype=np.float64)
        widths = np.asarray(widths, dtype=np.float64)
        if centers.ndim != 1 or widths.shape != centers.shape:
            raise ValidationError(f'basis: expected centers and widths of equal length, got '
                                  f'{centers.shape} and {widths.shape}')
        if not (np.all(np.isfinite(centers)) and np.all(widths > 0)
                and np.all(np.isfinite(widths))):
            raise ValidationError('basis: expected finite centers and finite positive widths')
        b = cls(n_weights_per_dim=int(centers.shape[0]), alpha_s=alpha_s,
                basis_width=basis_width)
        object.__setattr__(b, 'centers', centers.copy())
        object.__setattr__(b, 'widths', widths.copy())
        return b

    def phase(self, u: ArrayLike) -> NDArray[np.float64]:
        """Eq. (18)/(26), paper 000, solved: ``s = exp(-alpha_s * u)``."""
        return np.exp(-self.alpha_s * np.asarray(u, dtype=np.float64))

    def _exact(self, u: NDArray[np.float64]) -> NDArray[np.float64]:
        s = self.phase(u)[..., None]
        logpsi = -0.5 * self.widths * (s - self.centers) ** 2  # Eq. (17), paper 000
        logpsi -= logpsi.max(axis=-1, keepdims=True)  # stable normalisation
        psi = np.exp(logpsi)
        return psi * s / psi.sum(axis=-1, keepdims=True)  # Eq. (16), paper 000

    def features(self, u: ArrayLike) -> NDArray[np.float64]:
        """Features ``phi_j`` at normalised times ``u``.

        Parameters
        ----------
        u : array-like, shape (...)
            Normalised time ``t / tau`` (>= 0).

        Returns
        -------
        Phi : ndarray, shape (..., n_weights_per_dim)
        """
        u = np.maximum(np.asarray(u, dtype=np.float64), 0.0)
        out = self._exact(np.minimum(u, U_END))
        tail = u > U_END
        if np.any(tail):
            out = np.where(tail[..., None],
                           out * np.exp(-self.alpha_s * (u - U_END))[..., None], out)
        return out
