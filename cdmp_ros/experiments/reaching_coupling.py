"""Link-avoidance coupling of the reaching experiment (paper 000, IV-B) for an oriented board.

The board of the reaching scene is a thin box whose faces are not aligned with the world axes
(its normal is the elbow's self-motion direction). The coupling therefore works in the board's
frame: the chain is built with ``base_transform`` = (world -> board), so every point and
Jacobian is expressed there and the board is the axis-aligned box ``[-h, h]``. Joint-space
accelerations do not depend on the frame (``(R J)^+ R dx = J^+ dx`` for a rotation ``R``, and
the same for the null-space term), so the result is the coupling of the world-frame problem.

Per tick, on plain floats (see :class:`BoardLinkCoupling`):

- links (Eq. 12, paper 000): every chosen link segment, inflated to a capsule of radius
  ``link_radius``, gets its closest point to the board (the signed distance along a segment is
  convex, found by golden-section search); within ``field.influence_distance`` the constant
  field of IV-B gives the Cartesian acceleration ``dx_dd_l`` of that point, mapped by
  ``(J_o (I - J^+ J))^+`` into the null space of the end-effector task (near a joint limit in
  its limit-aware form, :mod:`cdmp_ros.core.coupling.terms`, as the streamer's coupling);
- end effector (Eq. 7, optional hold): ``dx_dd_e = k_p (x_ref - x) + k_d (xd_ref - xd)``
  towards the end-effector path of the unmodified motion (its forward kinematics, the "virtual
  trajectory" of paper 000, Fig. 4), mapped by ``J^+``. It keeps the end effector on its goal
  while the null-space motion, exact only to first order, would let it drift.

The sum is the joint acceleration change; :meth:`BoardLinkCoupling.exogenous` maps it into the
coupling term ``P`` of Eq. 21 (``tau^2`` times the exogenous acceleration) for a CDMP, or
``tau^2`` times it for a DMP.
"""
import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.coupling.terms import DampingConfig, LimitScale, coupling_3d
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.coupling.potential_fields import ConstantField
from cdmp_ros.core.kinematics import Chain, PointOfInterest
from cdmp_ros.core.coupling.obstacle import CouplingConfig, ObstacleCoupling
from cdmp_ros.core.validation import as_array, check_positive

Segment = Tuple[str, Tuple[float, float, float], Tuple[float, float, float]]

#: Capsules of the Panda's upper-arm/elbow link (the housing of joint 4, which the board of the
#: scene touches) and of the forearm, in the link frames [m]; radius :data:`PANDA_LINK_RADIUS`.
#: Checked against pybullet's mesh distances in test_sim_reaching.py (conservative within 4 mm).
PANDA_SEGMENTS: Tuple[Segment, ...] = (
    ('panda_link3', (0.0825, -0.05, 0.0), (0.0825, 0.06, 0.0)),
    ('panda_link4', (0.0, 0.0, 0.0), (-0.0825, 0.30, 0.0)),
)
PANDA_LINK_RADIUS = 0.055
_SEARCH_ITERATIONS = 24
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def quaternion_matrix(quaternion: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = as_array('quaternion', quaternion, (4,)) / np.linalg.norm(quaternion)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def world_to_frame(position: ArrayLike, quaternion: ArrayLike) -> NDArray[np.float64]:
    """Homogeneous transform (4, 4) from world coordinates into the frame at ``position`` (3,)
    with orientation ``quaternion`` (x, y, z, w)."""
    R = quaternion_matrix(quaternion)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ as_array('position', position, (3,))
    return T


def point_box_distance(p: Sequence[float], h: Sequence[float]) -> Tuple[float, tuple]:
    """Signed distance of a point to the box ``[-h, h]`` and the unit normal (out of the box,
    towards the point); inside, the depth below the nearest face (negative)."""
    g0 = abs(p[0]) - h[0]
    g1 = abs(p[1]) - h[1]
    g2 = abs(p[2]) - h[2]
    o0, o1, o2 = max(g0, 0.0), max(g1, 0.0), max(g2, 0.0)
    out = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
    if out > 0.0:
        return out, (math.copysign(o0, p[0]) / out, math.copysign(o1, p[1]) / out,
                     math.copysign(o2, p[2]) / out)
    axis = max(range(3), key=(g0, g1, g2).__getitem__)
    n = [0.0, 0.0, 0.0]
    n[axis] = math.copysign(1.0, p[axis])
    return max(g0, g1, g2), tuple(n)


def segment_box_distance(a: Sequence[float], b: Sequence[float], h: Sequence[float]
                         ) -> Tuple[float, float, tuple]:
    """Closest point of the segment ``a -> b`` to the box ``[-h, h]``: ``(t, distance,
    normal)`` with the point ``a + t (b - a)``. The signed distance of a convex set is convex,
    so along the segment it is convex in ``t`` (golden-section search to about 1e-5 of the
    length, a few micrometres for a link)."""
    a0, a1, a2 = a[0], a[1], a[2]
    u0, u1, u2 = b[0] - a0, b[1] - a1, b[2] - a2
    h0, h1, h2 = h[0], h[1], h[2]

    def f(t):  # signed distance only (point_box_distance without the normal)
        g0 = abs(a0 + t * u0) - h0
        g1 = abs(a1 + t * u1) - h1
        g2 = abs(a2 + t * u2) - h2
        if g0 > 0.0 or g1 > 0.0 or g2 > 0.0:
            g0 = g0 if g0 > 0.0 else 0.0
            g1 = g1 if g1 > 0.0 else 0.0
            g2 = g2 if g2 > 0.0 else 0.0
            return math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        return max(g0, g1, g2)

    lo, hi = 0.0, 1.0
    m1, m2 = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    f1, f2 = f(m1), f(m2)
    for _ in range(_SEARCH_ITERATIONS):
        if f1 <= f2:
            hi, m2, f2 = m2, m1, f1
            m1 = hi - _GOLDEN * (hi - lo)
            f1 = f(m1)
        else:
            lo, m1, f1 = m1, m2, f2
            m2 = lo + _GOLDEN * (hi - lo)
            f2 = f(m2)
    t = 0.5 * (lo + hi)
    d, n = point_box_distance((a0 + t * u0, a1 + t * u1, a2 + t * u2), h)
    return t, d, n


@dataclass(frozen=True)
class HoldGains:
    """Gains of the end-effector hold (Eq. 7): ``k_p`` [1/s^2], ``k_d`` [1/s]; 0 disables."""

    kp: float = 400.0
    kd: float = 40.0

    def __post_init__(self):
        check_positive('HoldGains.kp', self.kp, allow_zero=True)
        check_positive('HoldGains.kd', self.kd, allow_zero=True)


class BoardLinkCoupling:
    """Joint acceleration coupling of link avoidance (Eq. 12) and end-effector hold (Eq. 7).

    Parameters
    ----------
    chain : Chain
        The robot's chain built with ``base_transform = world_to_frame(board pose)``.
    half_extents : (3,) array-like
        Half extents of the board [m].
    field : ConstantField
        Field of the link points, in the board frame (IV-B: a constant acceleration along
        ``-z``, away from the board face the link approaches, within the influence distance).
    segments : sequence of (link, start, end)
        Link capsules' axes in the link frames.
    link_radius : float
        Capsule radius [m].
    hold : HoldGains
    ee_ref, ee_ref_velocity : (n_steps, 3) array-like, optional
        End-effector path of the unmodified motion in the board frame, per tick (the last row
        is held beyond it). Required when the hold is enabled.
    damping : DampingConfig
        Damping of the pseudo-inverses.
    limits : CouplingConfig, optional
        Its ``limit_aware``, ``limit_onset`` and ``limit_lock`` select the limit-aware
        Eq. (12) (default: the ``CouplingConfig`` defaults); None: Eq. (12) as is.
    """

    def __init__(self, chain: Chain, half_extents: ArrayLike, field: ConstantField,
                 segments: Sequence[Segment] = PANDA_SEGMENTS,
                 link_radius: float = PANDA_LINK_RADIUS, hold: HoldGains = HoldGains(0.0, 0.0),
                 ee_ref: Optional[ArrayLike] = None, ee_ref_velocity: Optional[ArrayLike] = None,
                 damping: DampingConfig = DampingConfig(),
                 limits: Optional[CouplingConfig] = CouplingConfig()):
        self.chain = chain
        self.h = tuple(as_array('half_extents', half_extents, (3,)).tolist())
        self.field = field
        self.link_radius = check_positive('link_radius', link_radius, allow_zero=True)
        self.hold = hold
        self.damping = damping
        self.segments = tuple(segments)
        points = [PointOfInterest('ee')]
        for link, start, end in self.segments:
            points += [PointOfInterest(link, tuple(start)), PointOfInterest(link, tuple(end))]
        self._kernel = chain.fast_kernel(tuple(points))
        frames, _ = chain.resolve(tuple(points))
        self._n_moving = [int(frames[1 + 2 * i]) for i in range(len(self.segments))]
        self._hold_on = hold.kp > 0.0 or hold.kd > 0.0
        if self._hold_on:
            if ee_ref is None:
                raise ValidationError('ee_ref: expected the end-effector path (n_steps, 3) when '
                                      'the hold is enabled, got None')
            ref = as_array('ee_ref', ee_ref, (None, 3))
            vel = (np.zeros_like(ref) if ee_ref_velocity is None
                   else as_array('ee_ref_velocity', ee_ref_velocity, ref.shape))
            self._ref = ref.tolist()
            self._ref_vel = vel.tolist()
        self.last_distances: List[float] = []
        self._limit = (LimitScale(chain.lower, chain.upper, limits.limit_onset,
                                  limits.limit_lock)
                       if limits is not None and limits.limit_aware else None)

    def joint_acceleration(self, k: int, q: Sequence[float], qd: Sequence[float]
                           ) -> List[float]:
        """Joint acceleration change [rad/s^2] at tick ``k`` for the state ``(q, qd)`` (n,).

        ``self.last_distances`` then holds the capsule-board signed distance of every segment.
        """
        n = self.chain.n_dofs
        x, jac = self._kernel(list(q))
        rows_e = [jac[0:n], jac[n:2 * n], jac[2 * n:3 * n]]
        dx_e = None
        if self._hold_on:
            i = min(k, len(self._ref) - 1)
            r, rv = self._ref[i], self._ref_vel[i]
            kp, kd = self.hold.kp, self.hold.kd
            dx_e = []
            for c in range(3):
                row = rows_e[c]
                xd = sum(a * b for a, b in zip(row, qd))
                dx_e.append(kp * (r[c] - x[c]) + kd * (rv[c] - xd))   # Eq. (7) input
        links = []
        dists = []
        stride = 3 * n
        field = self.field
        for i, m in enumerate(self._n_moving):
            pa, pb = x[3 + 6 * i:6 + 6 * i], x[6 + 6 * i:9 + 6 * i]
            t, d, normal = segment_box_distance(pa, pb, self.h)
            d -= self.link_radius
            dists.append(d)
            p = tuple(pa[j] + t * (pb[j] - pa[j]) for j in range(3))
            a = field.acceleration(p, None, None, d, normal)
            if not (a[0] or a[1] or a[2]):
                continue
            base_a = (1 + 2 * i) * stride
            base_b = base_a + stride
            s = 1.0 - t
            J_o = [[s * u + t * v for u, v in zip(jac[base_a + r * n:base_a + r * n + m],
                                                  jac[base_b + r * n:base_b + r * n + m])]
                   for r in range(3)]
            links.append((J_o, a))                                       # Eq. (12) input
        self.last_distances = dists
        if not links and dx_e is None:
            return [0.0] * n
        scale = self._limit(list(q)) if self._limit is not None and links else None
        return coupling_3d(rows_e, dx_e, links, self.damping, scale)   # Eq. (7) + (12)

    @staticmethod
    def exogenous(dq_dd: Sequence[float], xi: Sequence[float], tau: float,
                  y_delta: Optional[Sequence[float]]) -> List[float]:
        """Coupling term ``P`` of Eq. 21 (CDMP, ``y_delta`` given) or Eq. 13 (DMP, None):
        ``tau^2 dq_dd / (y_delta (1 - tanh(xi)^2))`` resp. ``tau^2 dq_dd`` (Eq. 29 solved for
        the exogenous acceleration), with the streamer's cap near saturation
        (:meth:`cdmp_ros.core.coupling.obstacle.ObstacleCoupling.to_internal`)."""
        return ObstacleCoupling.to_internal(dq_dd, xi, tau, y_delta)
