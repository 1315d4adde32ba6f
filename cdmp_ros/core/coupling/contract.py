"""The one coupling contract of the package: a joint-space acceleration from the state and the
obstacle set.

Every consumer (``DMP.rollout``, :class:`~cdmp_ros.core.dmp.stepper.DmpStepper` through
:meth:`~cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling`, the streamer and the
experiments) calls ``coupling.joint_acceleration(q, qd, obstacles)`` and hands the result to
the stepper, which alone maps it into the exogenous space of a CDMP (Eq. 21/29, paper 000, with
the cap near saturation). :class:`~cdmp_ros.core.coupling.obstacle.ObstacleCoupling` (Eq. 7 and
12) is the implementation for a kinematic chain.

:func:`bound_into` is the one bound of a coupling's magnitude (the streamer's
``coupling_max_acceleration``): potential fields grow without bound as an obstacle approaches
(a FIRAS repeller like ``1/d^3``), and an obstacle that appears inside or next to a link can
ask for an acceleration that moves the reference from mid-range onto the joint limits in one
tick.
"""
import math
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


def bound_into(dq_dd, limit: float, out: List[float]) -> float:
    """Copy a joint acceleration ``dq_dd`` into ``out`` as floats, scaled so that
    ``max_d |out_d| <= limit``; returns the peak ``max_d |dq_dd_d|`` before scaling.

    One factor for all joints, so the direction of the coupling (the avoidance direction, the
    null-space structure of Eq. 12) is kept and only its magnitude is bounded. ``limit <= 0``
    copies without a bound. Returns -1.0, with ``out`` unspecified, when ``dq_dd`` is not
    ``len(out)`` finite numbers (the caller rejects it, as
    :meth:`~cdmp_ros.core.dmp.stepper.DmpStepper.set_joint_coupling` would). Never raises;
    allocation-free (the streaming tick).
    """
    n = len(out)
    peak = 0.0
    i = 0
    try:
        for v in dq_dd:
            if i == n:
                return -1.0
            f = float(v)
            if not -math.inf < f < math.inf:
                return -1.0
            out[i] = f
            i += 1
            if f > peak:
                peak = f
            elif -f > peak:
                peak = -f
    except (TypeError, ValueError, OverflowError):
        return -1.0
    if i != n:
        return -1.0
    if 0.0 < limit < peak:
        factor = limit / peak
        for d in range(n):
            out[d] *= factor
    return peak
