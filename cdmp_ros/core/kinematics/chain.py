"""Serial kinematic chain with batched (numpy) forward kinematics and Jacobians.

Internal representation
-----------------------
Every movable joint ``k = 1..n`` owns an *internal frame* ``G_k`` whose z axis is the joint
axis::

    G_0 = base_transform @ (fixed transforms up to the first movable joint, folded into B_1)
    G_k = G_{k-1} @ B_k @ M_k(q_k),   M_k = Rz(q_k) (revolute) or Tz(q_k) (prismatic)

``B_k`` is constant (URDF joint origin, preceding fixed joints and a constant rotation ``P_k``
mapping z onto the joint axis), so a joint motion only mixes two columns of a rotation matrix
(revolute) or adds along one column (prismatic). Each URDF link is attached to one internal
frame ``k`` by a constant transform ``C``; a :class:`PointOfInterest` therefore resolves to
``(k, c)`` with ``c`` its coordinates in ``G_k``. The Jacobian column of joint ``j`` at a point
``x`` attached to frame ``k >= j`` is ``z_j x (x - o_j)`` (revolute) or ``z_j`` (prismatic).
"""
import threading
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import codegen


@dataclass(frozen=True)
class PointOfInterest:
    """A point rigidly attached to a link.

    Attributes
    ----------
    link : str
        Link name; ``'ee'`` means the chain's end-effector point (the tool centre point:
        ``Chain.ee_link`` frame moved by ``Chain.ee_offset``), and ``offset`` is then added in
        the ``ee_link`` frame.
    offset : tuple of 3 float
        Coordinates in the link frame [m].
    """

    link: str
    offset: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        try:
            off = tuple(float(v) for v in self.offset)
        except (TypeError, ValueError):
            raise ValidationError(f'PointOfInterest.offset: expected 3 numbers, got '
                                  f'{self.offset!r}') from None
        if len(off) != 3 or not all(np.isfinite(off)):
            raise ValidationError(f'PointOfInterest.offset: expected 3 finite numbers, got '
                                  f'{self.offset!r}')
        object.__setattr__(self, 'offset', off)


SNAP_TOLERANCE = 1e-10


def _snap(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Round rotation entries within :data:`SNAP_TOLERANCE` of 0 or +-1 to exactly 0 or +-1.

    URDFs write pi/2 with about 11 digits (the Panda: ``1.57079632679``, whose cosine is
    4.9e-12); snapping changes the kinematics by less than 1e-10 rad and makes the constant
    rotations sparse, which the single-configuration kernel exploits.
    """
    T = T.copy()
    rot = T[..., :3, :3]
    rot[np.abs(rot) < SNAP_TOLERANCE] = 0.0
    rot[np.abs(rot - 1.0) < SNAP_TOLERANCE] = 1.0
    rot[np.abs(rot + 1.0) < SNAP_TOLERANCE] = -1.0
    return T


class Chain:
    """Serial kinematic chain (see the module docstring for the representation).

    Use :func:`planar_chain`, :func:`chain_from_urdf` or :func:`panda_chain` to build one.

    Attributes
    ----------
    joint_names : list of str
        Movable joints, base to tip.
    n_dofs : int
    link_names : list of str
        Links on the path base -> tip (the base link first).
    ee_link : str
        Link carrying the end-effector point.
    ee_offset : ndarray (3,)
        End-effector point (tool centre point) in the ``ee_link`` frame.
    lower, upper, velocity_limits : ndarray (n_dofs,)
        Joint limits (``-inf``/``inf`` for continuous joints) and velocity limits.
    task_axes : tuple of int
        Cartesian axes in which the chain can move its points (``(0, 1)`` for planar chains,
        ``(0, 1, 2)`` otherwise); the coupling terms use these rows of the Jacobians.
    base_transform : ndarray (4, 4)
        World pose of the base link.
    """

    def __init__(self, joint_names: Sequence[str], prismatic: Sequence[bool],
                 B: Sequence[ArrayLike], base_transform: ArrayLike,
                 attachments: Dict[str, Tuple[int, ArrayLike]], link_names: Sequence[str],
                 ee_link: str, ee_offset: ArrayLike, lower: ArrayLike, upper: ArrayLike,
                 velocity_limits: ArrayLike, task_axes: Tuple[int, ...] = (0, 1, 2)):
        self.joint_names = list(joint_names)
        self.n_dofs = len(self.joint_names)
        if self.n_dofs == 0:
            raise ValidationError('chain: expected at least one movable joint, got none')
        self.prismatic = np.array(prismatic, dtype=bool)
        self.B = _snap(np.array(B, dtype=np.float64).reshape(self.n_dofs, 4, 4))
        self.base_transform = _snap(np.array(base_transform, dtype=np.float64).reshape(4, 4))
        self.attachments = {k: (int(v[0]), np.array(v[1], dtype=np.float64).reshape(4, 4))
                            for k, v in attachments.items()}
        self.link_names = list(link_names)
        self.ee_link = ee_link
        self.ee_offset = np.array(ee_offset, dtype=np.float64).reshape(3)
        self.lower = np.array(lower, dtype=np.float64).reshape(self.n_dofs)
        self.upper = np.array(upper, dtype=np.float64).reshape(self.n_dofs)
        self.velocity_limits = np.array(velocity_limits, dtype=np.float64).reshape(self.n_dofs)
        self.task_axes = tuple(task_axes)
        if ee_link not in self.attachments:
            raise ValidationError(f'ee_link: expected one of {list(self.attachments)}, '
                                  f'got {ee_link!r}')
        self._resolved: Dict[tuple, Tuple[NDArray, NDArray]] = {}
        self._kernels: Dict[tuple, object] = {}
        self._work: Dict[tuple, tuple] = {}
        self._Rb4 = np.zeros((self.n_dofs, 4, 4))
        self._Rb4[:, :3, :3] = self.B[:, :3, :3]
        self._tb4 = np.zeros((self.n_dofs, 4))
        self._tb4[:, :3] = self.B[:, :3, 3]

    def __repr__(self) -> str:
        return (f'Chain(n_dofs={self.n_dofs}, joints={self.joint_names}, '
                f'ee_link={self.ee_link!r})')

    # ------------------------------------------------------------------ points
    def resolve(self, points: Sequence[PointOfInterest]) -> Tuple[NDArray, NDArray]:
        """Internal frame index (n_points,) and coordinates in it (n_points, 3) of points."""
        if isinstance(points, PointOfInterest):
            points = (points,)
        key = tuple(points)
        hit = self._resolved.get(key)
        if hit is not None:
            return hit
        frames = np.empty(len(key), dtype=np.intp)
        coords = np.empty((len(key), 3))
        for i, poi in enumerate(key):
            if not isinstance(poi, PointOfInterest):
                raise ValidationError(f'points[{i}]: expected PointOfInterest, got '
                                      f'{type(poi).__name__}')
            link, offset = poi.link, np.asarray(poi.offset, dtype=np.float64)
            if link == 'ee':
                link, offset = self.ee_link, offset + self.ee_offset
            if link not in self.attachments:
                raise ValidationError(f'points[{i}].link: expected one of '
                                      f'{["ee"] + list(self.attachments)}, got {poi.link!r}')
            k, C = self.attachments[link]
            frames[i] = k
            coords[i] = C[:3, :3] @ offset + C[:3, 3]
        if len(self._resolved) > 256:
            self._resolved.clear()
        self._resolved[key] = (frames, coords)
        return frames, coords

    def point_in_link(self, frame: int, coords: ArrayLike) -> PointOfInterest:
        """The :class:`PointOfInterest` of internal-frame coordinates ``coords`` of frame
        ``frame`` (expressed on the first link attached to that frame)."""
        for link in self.link_names:
            k, C = self.attachments[link]
            if k == frame:
                c = np.asarray(coords, dtype=np.float64) - C[:3, 3]
                return PointOfInterest(link, tuple(float(v) for v in C[:3, :3].T @ c))
        raise ValidationError(f'frame: expected 0..{self.n_dofs}, got {frame}')

    # ------------------------------------------------------------------ batched
    def curvature_bound(self, points: Sequence[PointOfInterest]) -> Optional[NDArray]:
        """Weights ``M`` (n_points, n_dofs, n_dofs) of the second-order remainder of the
        forward kinematics: for every pair of configurations q, r and every point p,

            |x_p(q) - x_p(r) - J_p(r) (q - r)| <= 1/2 sum_jk M[p, j, k] |q_j - r_j| |q_k - r_k|,

        with ``M[p, j, k] = D_p[max(j, k)]``, ``D_p[k]`` the distance from joint k's origin to
        the point along the chain's fixed transforms (the sum of their translations beyond
        joint k, plus the point's offset in its link), 0 for joints after the point's link.
        None when the chain has a prismatic joint (the distances then change with it).

        Why: with revolute joints, Jacobian column k is ``w_k = z_k x (x - o_k)``; moving an
        earlier (or the same) joint j rotates ``w_k`` rigidly about axis j, so
        ``|d2x / dq_j dq_k| = |z_j x w_k| <= |x - o_k| <= D_p[k]`` for j <= k, at every
        configuration; Taylor's theorem with the integral remainder along the segment from r
        to q gives the bound."""
        if self.prismatic.any():
            return None
        frames, coords = self.resolve(points)
        step = np.linalg.norm(self.B[:, :3, 3], axis=1)       # |t(B_m)|
        n = self.n_dofs
        later = np.maximum.outer(np.arange(n), np.arange(n))
        M = np.zeros((len(frames), n, n))
        for i, (f, c) in enumerate(zip(frames.tolist(), coords)):
            D = np.array([step[k + 1:f].sum() + np.linalg.norm(c) if k < f else 0.0
                          for k in range(n)])
            M[i] = D[later]
        return M

    def _check_q(self, Q: ArrayLike) -> NDArray[np.float64]:
        Q = np.asarray(Q, dtype=np.float64)
        if Q.ndim == 0 or Q.shape[-1] != self.n_dofs:
            raise ValidationError(f'Q: expected shape (..., {self.n_dofs}), got {Q.shape}')
        return Q

    def _frames(self, Q: NDArray) -> Tuple[NDArray, NDArray]:
        """Internal frames of flat ``Q`` (B, n) as 3x4 homogeneous matrices ``[R | p]``.

        Returns ``F`` (n+1, 3, B, 4) with ``F[k, i, b, :3]`` row i of frame k's rotation
        for configuration b and ``F[k, i, b, 3]`` its position, and the view ``p = F[..., 3]``
        (n+1, 3, B).

        Each step is one BLAS product ``(3B, 4) @ B_k`` (rotation and translation at once),
        and the joint rotation ``Rz(q)`` mixes columns 0 and 1: with a row's entries 0 and 1
        viewed as the complex number ``m0 + i m1`` it is a multiplication by ``exp(-i q)``,
        computed from ``t = tan(q / 2)`` as ``(1 - t^2 - 2 i t) / (1 + t^2)`` (one
        transcendental function instead of two).
        """
        nb, n = Q.shape
        F, E, T, T2 = self._workspace('frames', ((n + 1, 3, nb, 4), np.float64),
                                      ((n, nb), np.complex128), ((n, nb), np.float64),
                                      ((n, nb), np.float64))
        F[0] = self.base_transform[:3, None, :]
        np.multiply(Q.T, 0.5, out=T)
        np.tan(T, out=T)
        np.multiply(T, T, out=T2)
        np.multiply(T, -2.0, out=E.imag)
        np.subtract(1.0, T2, out=E.real)
        T2 += 1.0
        E.real /= T2
        E.imag /= T2
        for k in range(n):
            M = F[k + 1]
            np.dot(F[k].reshape(3 * nb, 4), self.B[k], out=M.reshape(3 * nb, 4))
            if self.prismatic[k]:
                M[:, :, 3] += M[:, :, 2] * Q[:, k]
            else:
                M.view(np.complex128)[:, :, 0] *= E[k]                # Rz(q_k)
        return F, F[..., 3]

    def _points(self, F, p, points):
        """World points (P, 3, B) of resolved points from frames of :meth:`_frames`."""
        frames, coords = self.resolve(points)
        nb = F.shape[2]
        X = np.empty((len(frames), 3, nb))
        c4 = np.ones(4)
        for i, (k, c) in enumerate(zip(frames.tolist(), coords)):
            c4[:3] = c
            np.dot(F[k].reshape(3 * nb, 4), c4, out=X[i].reshape(3 * nb))
        return X, frames

    def forward(self, Q: ArrayLike, points: Sequence[PointOfInterest]) -> NDArray[np.float64]:
        """World positions of points.

        Parameters
        ----------
        Q : array-like (..., n_dofs)
            Joint positions; any leading shape.
        points : sequence of PointOfInterest (n_points)

        Returns
        -------
        X : ndarray (..., n_points, 3)
        """
        Q = self._check_q(Q)
        if Q.ndim == 1:
            return self.forward_and_jacobian(Q, points)[0]
        lead = Q.shape[:-1]
        R, p = self._frames(Q.reshape(-1, self.n_dofs))
        X, _ = self._points(R, p, points)
        return X.transpose(2, 0, 1).reshape(lead + X.shape[:2])

    def forward_and_jacobian(self, Q: ArrayLike, points: Sequence[PointOfInterest]
                             ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World positions of points and their translational Jacobians.

        A single configuration (``Q`` of shape ``(n_dofs,)``) takes a pure-Python fast path.

        Parameters
        ----------
        Q : array-like (..., n_dofs)
        points : sequence of PointOfInterest (n_points)

        Returns
        -------
        X : ndarray (..., n_points, 3)
        J : ndarray (..., n_points, 3, n_dofs)
            ``J[..., i, :, j] = d X[..., i, :] / d Q[..., j]``.

        Batched results are views whose batch axis is innermost in memory (the layout the
        vectorised recursion produces); use ``np.ascontiguousarray`` if a consumer needs
        C order.
        """
        n = self.n_dofs
        if type(Q) is np.ndarray and Q.shape == (n,) and Q.dtype == np.float64:
            q = Q.tolist()
        else:
            Q = self._check_q(Q)
            q = Q.tolist() if Q.ndim == 1 else None
        if q is not None:
            if not -1e300 < sum(q) < 1e300:
                raise ValidationError(f'Q: expected finite values, got {q}')
            kernel = self.fast_kernel(points)
            x, jac = kernel(q)
            n_points = len(x) // 3
            return (np.array(x).reshape(n_points, 3), np.array(jac).reshape(n_points, 3, n))
        if not np.all(np.isfinite(Q)):
            raise ValidationError('Q: expected finite values')
        lead = Q.shape[:-1]
        R, p = self._frames(Q.reshape(-1, n))
        X, frames = self._points(R, p, points)               # (P, 3, B)
        nb = X.shape[-1]
        Jt = np.empty((len(frames), 3, n, nb))               # batch last: contiguous rows
        kmax = int(frames.max())
        Z, org, D, tmp = self._workspace('jacobian', ((3, n, nb), np.float64),
                                         ((3, n, nb), np.float64), ((3, n, nb), np.float64),
                                         ((n, nb), np.float64))
        Z[:, :kmax] = R[1:kmax + 1, :, :, 2].transpose(1, 0, 2)       # (3, k, B) axes
        org[:, :kmax] = p[1:kmax + 1].transpose(1, 0, 2)               # (3, k, B) origins
        for i, k in enumerate(frames.tolist()):
            Jt[i, :, k:] = 0.0
            if k == 0:
                continue
            d = D[:, :k]
            np.subtract(X[i][:, None, :], org[:, :k], out=d)  # lever arms x - o_j
            t = tmp[:k]
            for c, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):
                out = Jt[i, c, :k]
                np.multiply(Z[a, :k], d[b], out=out)
                np.multiply(Z[b, :k], d[a], out=t)
                out -= t
            for j in np.flatnonzero(self.prismatic[:k]).tolist():
                Jt[i, :, j] = Z[:, j]
        # views with the batch axis first (no copy; the batch axis stays innermost in memory)
        Xo = X.transpose(2, 0, 1)
        J = Jt.transpose(3, 0, 1, 2)
        return Xo.reshape(lead + Xo.shape[1:]), J.reshape(lead + J.shape[1:])

    def _workspace(self, name: str, *specs) -> List[NDArray]:
        """Scratch arrays of the batched path: C-contiguous arrays of the ``(shape, dtype)``
        specs, views of flat buffers kept per thread and name that only grow (to the next
        power of two of elements), so calls of any batch size reuse them (fresh large arrays
        cost page faults every call, and the verification's batch size changes from call to
        call). Valid until the next call of the same name in the same thread."""
        key = (threading.get_ident(), name)
        bufs = self._work.get(key)
        sizes = [int(np.prod(shape)) for shape, _ in specs]
        if bufs is None or any(b.size < k for b, k in zip(bufs, sizes)):
            if bufs is None and len(self._work) > 16:
                self._work.clear()
            bufs = [b if bufs is not None and b.size >= k
                    else np.empty(1 << max(k - 1, 1).bit_length(), dtype=dtype)
                    for b, k, (_, dtype) in zip(bufs or [None] * len(specs), sizes, specs)]
            self._work[key] = bufs
        return [b[:k].reshape(shape) for b, k, (shape, _) in zip(bufs, sizes, specs)]

    def joint_origins(self, Q: ArrayLike) -> NDArray[np.float64]:
        """World positions (..., n_dofs + 1, 3) of the base and of every movable joint."""
        Q = self._check_q(Q)
        lead = Q.shape[:-1]
        _, p = self._frames(Q.reshape(-1, self.n_dofs))
        p = p.transpose(2, 0, 1).copy()                     # F is a reused workspace
        return p.reshape(lead + p.shape[1:])

    def link_segments(self) -> List[Tuple[str, Tuple[float, ...], Tuple[float, ...]]]:
        """Links of the moving part as segments between consecutive joint origins.

        Returns
        -------
        list of (link, start, end)
            For every movable joint ``k``: the link it moves, and the origin of joint ``k``
            and of joint ``k + 1`` (the end-effector point for the last joint), both in that
            link's frame. Segments of zero length are kept (they model the link as a point).
        """
        out = []
        for k in range(1, self.n_dofs + 1):
            link = next(name for name in self.link_names if self.attachments[name][0] == k)
            if k < self.n_dofs:
                end_internal = self.B[k, :3, 3]
            else:
                frames, coords = self.resolve((PointOfInterest('ee'),))
                end_internal = coords[0]
            start = self.point_in_link(k, np.zeros(3))
            end = self.point_in_link(k, end_internal)
            assert start.link == link and end.link == link
            out.append((link, start.offset, end.offset))
        return out

    def fast_kernel(self, points: Sequence[PointOfInterest]):
        """The generated single-configuration kernel of ``points`` (see :mod:`.codegen`).

        ``kernel(q)`` takes a list of n_dofs floats and returns flat lists ``x``
        (3 * n_points) and ``jac`` (n_points * 3 * n_dofs, row-major (n_points, 3, n_dofs)).
        Kernels are cached per tuple of points.
        """
        key = points if isinstance(points, tuple) else tuple(points)
        kernel = self._kernels.get(key)
        if kernel is None:
            frames, coords = self.resolve(key)
            desc = (f'Chain {self!r}; points (internal frame: coordinates [m]): '
                    + '; '.join(f'{k}: {tuple(c)}' for k, c in zip(frames.tolist(),
                                                                   coords.tolist())))
            kernel = codegen.compile_kernel(self.B, self.base_transform, self.prismatic,
                                            frames.tolist(), coords, desc)
            if len(self._kernels) > 64:
                self._kernels.clear()
            self._kernels[key] = kernel
        return kernel
