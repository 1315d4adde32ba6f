"""Coupling of the reaching experiment (paper 000, IV-B): link avoidance of an oriented board
plus an end-effector hold.

The board of the reaching scene is a thin box whose faces are not aligned with the world axes
(its normal is the elbow's self-motion direction): it is an
:class:`~cdmp_ros.core.kinematics.closest.OrientedBox` obstacle (:func:`board_obstacle`), and
the link terms are those of the common coupling,
:class:`~cdmp_ros.core.coupling.obstacle.ObstacleCoupling`:

- links (Eq. 12, paper 000): every chosen link segment, inflated to a capsule of radius
  ``link_radius``, gets its closest point to the board; within ``field.influence_distance`` the
  constant field of IV-B (:func:`board_field`: a constant acceleration along the board normal,
  away from the face the link approaches) gives the Cartesian acceleration of that point,
  mapped by ``(J_o (I - J^+ J))^+`` into the null space of the end-effector task (near a joint
  limit in its limit-aware form, as the streamer's coupling);
- end effector (Eq. 7, optional hold): ``dx_dd_e = k_p (x_ref - x) + k_d (xd_ref - xd)``
  towards the end-effector path of the unmodified motion (its forward kinematics, the "virtual
  trajectory" of paper 000, Fig. 4), mapped by ``J^+``. It keeps the end effector on its goal
  while the null-space motion, exact only to first order, would let it drift. Eq. (7) and the
  link terms add up (the link terms do not depend on ``dx_dd_e``): the hold is the coupling's
  end-effector task (``ee_task``), evaluated in the same generated kernel.

:class:`ReachingCoupling` implements :class:`~cdmp_ros.core.coupling.contract.Coupling`; the
stepper maps its result into the exogenous space.
"""
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike

from cdmp_ros.core.coupling.obstacle import CouplingConfig, DampingConfig, ObstacleCoupling
from cdmp_ros.core.coupling.potential_fields import ConstantField
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import Chain
from cdmp_ros.core.kinematics.closest import OrientedBox
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


def board_obstacle(board) -> OrientedBox:
    """The scene's board (a pybullet box: ``size`` = half extents, ``position``,
    ``orientation`` quaternion ``(x, y, z, w)``) as an :class:`OrientedBox`."""
    return OrientedBox.from_quaternion(board.position, 2.0 * np.asarray(board.size),
                                       board.orientation)


def board_field(board: OrientedBox, magnitude: float, influence_distance: float
                ) -> ConstantField:
    """The constant field of IV-B for the board: ``magnitude`` [m/s^2] along the board's
    ``-z`` axis (away from the face the link approaches) within ``influence_distance`` [m]."""
    R = np.array(board.rotation)
    return ConstantField(magnitude, influence_distance, direction=tuple(-R[:, 2]))


@dataclass(frozen=True)
class HoldGains:
    """Gains of the end-effector hold (Eq. 7): ``k_p`` [1/s^2], ``k_d`` [1/s]; 0 disables."""

    kp: float = 400.0
    kd: float = 40.0

    def __post_init__(self):
        check_positive('HoldGains.kp', self.kp, allow_zero=True)
        check_positive('HoldGains.kd', self.kd, allow_zero=True)


class ReachingCoupling:
    """Link avoidance (Eq. 12, :class:`ObstacleCoupling`) plus end-effector hold (Eq. 7).

    Parameters
    ----------
    chain : Chain
        The robot's chain (world frame).
    field : ConstantField
        Field of the link points (:func:`board_field`).
    segments : sequence of (link, start, end)
        Link capsules' axes in the link frames.
    link_radius : float
        Capsule radius [m].
    hold : HoldGains
    ee_ref, ee_ref_velocity : (n_steps, 3) array-like, optional
        End-effector path of the unmodified motion (world), per tick (the last row is held
        beyond it). Required when the hold is enabled.
    damping : DampingConfig
        Damping of the pseudo-inverses.
    limits : CouplingConfig, optional
        Its ``limit_aware``, ``limit_onset`` and ``limit_lock`` select the limit-aware
        Eq. (12) (default: the ``CouplingConfig`` defaults); None: Eq. (12) as is.

    Attributes
    ----------
    tick : int
        Index into ``ee_ref`` of the next evaluation (set by the caller every tick).
    last_distances : list of float
        Capsule-obstacle signed distance of every segment at the last evaluation.
    """

    def __init__(self, chain: Chain, field: ConstantField,
                 segments: Sequence[Segment] = PANDA_SEGMENTS,
                 link_radius: float = PANDA_LINK_RADIUS, hold: HoldGains = HoldGains(0.0, 0.0),
                 ee_ref: Optional[ArrayLike] = None, ee_ref_velocity: Optional[ArrayLike] = None,
                 damping: DampingConfig = DampingConfig(),
                 limits: Optional[CouplingConfig] = CouplingConfig()):
        check_positive('link_radius', link_radius, allow_zero=True)
        config = limits if limits is not None else CouplingConfig(limit_aware=False)
        config = CouplingConfig(damping=damping, link_radius=float(link_radius),
                                end_effector=False, limit_aware=config.limit_aware,
                                limit_onset=config.limit_onset, limit_lock=config.limit_lock)
        self.chain = chain
        self.hold = hold
        self.damping = damping
        self.tick = 0
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
        self.links = ObstacleCoupling(chain, segments, box_field=field, config=config,
                                      ee_task=self._hold if self._hold_on else None)
        self.last_distances: List[float] = []

    def _hold(self, x: Sequence[float], xd: Sequence[float]) -> Tuple[float, float, float]:
        """The end-effector acceleration of the hold (the input of Eq. 7) at tick
        ``self.tick``."""
        i = min(self.tick, len(self._ref) - 1)
        r, rv = self._ref[i], self._ref_vel[i]
        kp, kd = self.hold.kp, self.hold.kd
        return (kp * (r[0] - x[0]) + kd * (rv[0] - xd[0]),
                kp * (r[1] - x[1]) + kd * (rv[1] - xd[1]),
                kp * (r[2] - x[2]) + kd * (rv[2] - xd[2]))

    def joint_acceleration(self, q: Sequence[float], qd: Optional[Sequence[float]],
                           obstacles: Sequence) -> List[float]:
        """Joint acceleration change [rad/s^2] for the state ``(q, qd)`` (n,) at tick
        ``self.tick``: Eq. (12) of the links and Eq. (7) of the hold, one generated kernel."""
        dq = self.links.joint_acceleration(q, qd, obstacles)
        self.last_distances = self.links.last_distances[1:]
        return dq
