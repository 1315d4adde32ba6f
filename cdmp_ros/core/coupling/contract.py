"""The one coupling contract of the package: a joint-space acceleration from the state and the
obstacle set.

Every consumer (``DMP.rollout``, :class:`~cdmp_ros.core.dmp.stepper.DmpStepper` through
:meth:`~cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling`, the streamer and the
experiments) calls ``coupling.joint_acceleration(q, qd, obstacles)`` and hands the result to
the stepper, which alone maps it into the exogenous space of a CDMP (Eq. 21/29, paper 000, with
the cap near saturation). :class:`~cdmp_ros.core.coupling.obstacle.ObstacleCoupling` (Eq. 7 and
12) is the implementation for a kinematic chain; the streamer bounds its result
(:func:`cdmp_ros.core.streaming.streamer.bound_into`).
"""
from typing import List, Optional, Protocol, Sequence, runtime_checkable


@runtime_checkable
class Coupling(Protocol):
    """Joint acceleration coupling term (paper 000, Eq. 7/12 or any other).

    Attributes
    ----------
    last_distances : list of float
        Signed distances [m] of the points that the last call evaluated to their nearest
        obstacle (may be empty; ``inf`` for no obstacle).
    """

    last_distances: List[float]

    def joint_acceleration(self, q: Sequence[float], qd: Optional[Sequence[float]],
                           obstacles: Sequence) -> Optional[Sequence[float]]:
        """Joint acceleration change [rad/s^2] (n_dofs) at positions ``q`` and velocities
        ``qd`` (None: at rest) for the obstacle set; None means no coupling (zero)."""
