"""Points of interest x_t = T(z_t) of the constrained ProMP (paper 003, Section II-E).

A point of interest maps the joint (or Cartesian) state z_t of the ProMP to the coordinates the
constraint acts on. Linear maps (selecting dimensions of a Cartesian ProMP, or a joint) give exact
Gaussian moments; non-linear maps (forward kinematics) are approximated by a Gaussian with the
unscented transform over the dimensions ``dofs`` they depend on.
"""
from typing import Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

from cdmp_ros.core.errors import ValidationError


def _axes_index(axes: Tuple[int, ...]):
    """A slice for contiguous increasing axes (a view, no gather), else the list."""
    if list(axes) == list(range(axes[0], axes[0] + len(axes))):
        return slice(axes[0], axes[0] + len(axes))
    return list(axes)


class Point:
    """Base class. ``dofs``: indices of z the point depends on; ``n_out``: output dimension."""
    linear = False
    dofs: Tuple[int, ...] = ()
    n_out: int = 0

    def check(self, n_dims: int) -> None:
        if not self.dofs or min(self.dofs) < 0 or max(self.dofs) >= n_dims:
            raise ValidationError(f'point.dofs: expected indices in [0, {n_dims}), '
                                  f'got {list(self.dofs)}')

    def forward_and_jacobian(self, Z: NDArray) -> Tuple[NDArray, NDArray]:
        """Z (..., len(dofs)) -> X (..., n_out), J (..., n_out, len(dofs))."""
        raise NotImplementedError

    def forward(self, Z: NDArray) -> NDArray:
        return self.forward_and_jacobian(Z)[0]


class DofPoint(Point):
    """x_t = z_t[dofs]: joints of a joint-space ProMP or coordinates of a Cartesian ProMP.

    Parameters
    ----------
    dofs : sequence of int, length k
        ProMP dimensions; x_t has shape (k,).
    """
    linear = True

    def __init__(self, dofs: Sequence[int]):
        self.dofs = tuple(int(d) for d in dofs)
        self.n_out = len(self.dofs)

    def forward_and_jacobian(self, Z):
        J = np.broadcast_to(np.eye(self.n_out), Z.shape[:-1] + (self.n_out, self.n_out))
        return Z, J


class ChainPoint(Point):
    """A Cartesian point rigidly attached to a link of a kinematic chain whose joints are the
    ProMP dimensions ``dofs`` (cdmp_ros.core.kinematics.Chain, PointOfInterest).

    Parameters
    ----------
    chain : Chain
    point : PointOfInterest
    dofs : sequence of int, optional
        ProMP dimensions of the chain's joints, in chain order (default 0..n_dofs-1).
    axes : sequence of int, optional
        World coordinates kept (default (0, 1, 2); (0, 1) for a planar arm).
    """

    def __init__(self, chain, point, dofs: Sequence[int] = None,
                 axes: Sequence[int] = (0, 1, 2)):
        self.chain = chain
        self.point = point
        n = chain.n_dofs
        self.dofs = tuple(range(n)) if dofs is None else tuple(int(d) for d in dofs)
        if len(self.dofs) != n:
            raise ValidationError(f'point.dofs: expected {n} indices for the chain, '
                                  f'got {len(self.dofs)}')
        self.axes = tuple(int(a) for a in axes)
        if not self.axes or any(a not in (0, 1, 2) for a in self.axes):
            raise ValidationError(f'point.axes: expected indices in 0..2, got {list(axes)}')
        self.n_out = len(self.axes)

    def forward_and_jacobian(self, Z):
        X, J = self.chain.forward_and_jacobian(Z, [self.point])
        if self.axes == (0, 1, 2):
            return X[..., 0, :], J[..., 0, :, :]
        ax = _axes_index(self.axes)
        return X[..., 0, ax], J[..., 0, ax, :]

    def forward(self, Z):
        X = self.chain.forward(Z, [self.point])[..., 0, :]
        return X if self.axes == (0, 1, 2) else X[..., _axes_index(self.axes)]


class DifferencePoint(Point):
    """x_t = a(z_t) - b(z_t): relative position of two points (mutual avoidance, Eq. 22).

    Parameters
    ----------
    a, b : Point
        With equal ``n_out`` (k); x_t has shape (k,).
    """

    def __init__(self, a: Point, b: Point):
        if a.n_out != b.n_out:
            raise ValidationError(f'point: expected equal output sizes, got {a.n_out} and '
                                  f'{b.n_out}')
        self.a, self.b = a, b
        self.dofs = tuple(sorted(set(a.dofs) | set(b.dofs)))
        self.n_out = a.n_out
        self.linear = a.linear and b.linear
        self._ia = np.searchsorted(self.dofs, a.dofs)
        self._ib = np.searchsorted(self.dofs, b.dofs)

    def forward_and_jacobian(self, Z):
        Xa, Ja = self.a.forward_and_jacobian(Z[..., self._ia])
        Xb, Jb = self.b.forward_and_jacobian(Z[..., self._ib])
        J = np.zeros(Z.shape[:-1] + (self.n_out, len(self.dofs)))
        J[..., self._ia] += Ja
        J[..., self._ib] -= Jb
        return Xa - Xb, J

    def forward(self, Z):
        return self.a.forward(Z[..., self._ia]) - self.b.forward(Z[..., self._ib])


class StackedChainPoints(Point):
    """Several ChainPoints of one chain (same ``dofs`` and ``axes``) evaluated together: one
    forward-kinematics call and one unscented transform for all of them. Output: the points'
    coordinates concatenated, point i at ``[i * q, (i + 1) * q)`` with q = len(axes)."""

    def __init__(self, points: Sequence[ChainPoint]):
        first = points[0]
        for p in points[1:]:
            if p.chain is not first.chain or p.dofs != first.dofs or p.axes != first.axes:
                raise ValidationError('points: expected chain points of one chain with the '
                                      'same dofs and axes')
        self.points = list(points)
        self.chain, self.dofs, self.axes = first.chain, first.dofs, first.axes
        self.q = len(self.axes)
        self.n_out = self.q * len(self.points)

    def forward_and_jacobian(self, Z):
        X, J = self.chain.forward_and_jacobian(Z, [p.point for p in self.points])
        if self.axes != (0, 1, 2):
            ax = _axes_index(self.axes)
            X = X[..., ax]
            J = J[..., ax, :]
        lead = Z.shape[:-1]
        return (X.reshape(lead + (self.n_out,)),
                J.reshape(lead + (self.n_out, Z.shape[-1])))


class StackedDifferencePoints(Point):
    """Several DifferencePoints of ChainPoints over the same ProMP dimensions (mutual
    avoidance of two arms, Eq. 22) evaluated together: one forward-kinematics call per chain
    for all the chain points the differences use, and one unscented transform for all of
    them. Output: the differences concatenated, member i at ``[i * q, (i + 1) * q)``."""

    def __init__(self, points: Sequence[DifferencePoint]):
        first = points[0]
        self.q = first.n_out
        for p in points:
            if (type(p.a) is not ChainPoint or type(p.b) is not ChainPoint
                    or p.dofs != first.dofs or p.n_out != self.q
                    or p.a.axes != first.a.axes or p.b.axes != first.a.axes):
                raise ValidationError('points: expected differences of chain points with the '
                                      'same dofs and axes')
        self.points = list(points)
        self.dofs = first.dofs
        self.axes = first.a.axes
        self.n_out = self.q * len(self.points)
        # per chain (and its dofs): the distinct points of interest, in order of appearance,
        # and where the chain's dofs sit among self.dofs (a slice when contiguous)
        self._chains = {}
        self._where = []            # per member: (chain key, point index) of a and of b
        for p in self.points:
            ends = []
            for cp in (p.a, p.b):
                key = (id(cp.chain), cp.dofs)
                if key not in self._chains:
                    idx = tuple(int(i) for i in np.searchsorted(self.dofs, cp.dofs))
                    self._chains[key] = (cp.chain, _axes_index(idx), [])
                pois = self._chains[key][2]
                if cp.point not in pois:
                    pois.append(cp.point)
                ends.append((key, pois.index(cp.point)))
            self._where.append(tuple(ends))
        self._disjoint = {(ka, kb) for (ka, _), (kb, _) in self._where
                          if not set(ka[1]) & set(kb[1])}

    def forward_and_jacobian(self, Z):
        ax = _axes_index(self.axes)
        fk = {}
        for key, (chain, idx, pois) in self._chains.items():
            X, J = chain.forward_and_jacobian(Z[..., idx], pois)
            if self.axes != (0, 1, 2):
                X, J = X[..., ax], J[..., ax, :]
            fk[key] = (X, J)
        lead = Z.shape[:-1]
        q = self.q
        X = np.empty(lead + (self.n_out,))
        J = np.zeros(lead + (self.n_out, len(self.dofs)))
        for i, ((ka, ia), (kb, ib)) in enumerate(self._where):
            Xa, Ja = fk[ka][0][..., ia, :], fk[ka][1][..., ia, :, :]
            Xb, Jb = fk[kb][0][..., ib, :], fk[kb][1][..., ib, :, :]
            rows = slice(i * q, (i + 1) * q)
            X[..., rows] = Xa - Xb
            da, db = self._chains[ka][1], self._chains[kb][1]
            if ka == kb:                             # two points of one chain
                J[..., rows, da] = Ja - Jb
            elif (ka, kb) in self._disjoint:         # the usual case: two arms
                J[..., rows, da] = Ja
                J[..., rows, db] = -Jb
            else:                                    # chains sharing ProMP dimensions
                J[..., rows, da] += Ja
                J[..., rows, db] -= Jb
        return X, J
