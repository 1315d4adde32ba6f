"""Speed and separation monitoring of the streamed motion: slow the primitive so that every
coupling point can stop before it comes within ``margin`` of an obstacle.

The obstacle coupling (paper 000, Eq. 7/12) pushes the arm away, but its push can be absorbed:
joints at their velocity limits, a push along directions that move the closest point little,
the acceleration limits of the output stage. Then nothing slows the rest of the motion, which
keeps closing the distance (a ProMP demo run went from 8.4 cm to contact in 1.4 s with the
coupling at its bound). Speed and separation monitoring (the rule of ISO/TS 15066 for robots
beside people, here between the arm's points and the obstacles) bounds the *approach* instead:

For every coupling point ``i`` (the tool centre point, every link capsule) with clearance
``d_i`` (the coupling's ``last_distances``) and approach speed ``r_i = -dd_i/dt`` (the change
of ``d_i`` between two evaluations of the same obstacle set), the motion must be able to stop
in the clearance left::

    r_i (t_r + T / 2) <= d_i - margin,      T = max_j |qd_j| / A_j

``T`` is the time a time-scaled brake takes: slowing the whole motion by one factor ``s(t)``
from 1 to 0 keeps the path and decelerates joint ``j`` by ``|qd_j| |ds/dt|``, which the
acceleration limit ``A_j`` bounds, so ``s`` falls from 1 to 0 in ``T`` at the fastest and the
point covers ``r_i T / 2`` of its approach meanwhile (a linear brake; ``t_r`` is the reaction
time: the evaluation period, the jerk ramp ``max_j A_j / J_j`` and the output stage's lag).
Slowing the motion by a factor ``f`` scales both ``r_i`` and ``T``, so the largest admissible
factor solves ``f r_i t_r + f^2 r_i T / 2 = d_i - margin``::

    f_i = (-r_i t_r + sqrt((r_i t_r)^2 + 2 r_i T (d_i - margin))) / (r_i T)

The monitor returns the new speed cap ``kappa * min_i f_i`` (``kappa``: the speed the motion
runs at now, at which ``r_i`` and ``T`` were measured), at least :data:`MIN_SPEED`; when no
point needs it the cap is lifted (1.0) and the stepper's own recovery rate brings the speed
back. A new obstacle set keeps the cap in force until its second evaluation has measured the
approach. The cap acts on the stepper's time warp (:meth:`~cdmp_ros.core.dmp.stepper.DmpStepper.
set_speed_cap`), so the path is kept and only its speed changes; the output stage keeps the
published references within the limits whatever the cap does.

What this is not: a proof of no contact. The approach speed is measured on the reference, not
predicted; an obstacle that moves toward the arm is seen one evaluation late; the coupling's
own contribution to the approach is not scaled by the cap. It makes the approach slow down
in time wherever the motion itself closes the distance, which is what the repeller alone could
not.
"""
import math
from typing import List, Sequence

__all__ = ['SeparationMonitor', 'admissible_factor', 'brake_time', 'MIN_SPEED']

#: The least speed cap the monitor asks for (a motion never frozen exactly: its time warp
#: divides by it nowhere, and a point that stops approaching lifts the cap again).
MIN_SPEED = 1e-3


def brake_time(qd: Sequence[float], max_acceleration: Sequence[float]) -> float:
    """``T = max_j |qd_j| / A_j`` [s]: how long a time-scaled brake of the motion with joint
    velocities ``qd`` takes within the acceleration limits (0 at rest; joints without a
    limit, ``A_j`` inf or 0, do not count)."""
    T = 0.0
    for j in range(min(len(qd), len(max_acceleration))):
        a = max_acceleration[j]
        if 0.0 < a < math.inf:
            t = abs(qd[j]) / a
            if t > T:
                T = t
    return T


def admissible_factor(approach: float, clearance: float, T: float, reaction: float) -> float:
    """The largest factor ``f >= 0`` by which the motion may keep its speed so that a point
    approaching at ``approach`` [m/s] stops within ``clearance`` [m] (beyond the margin):
    ``f approach reaction + f^2 approach T / 2 <= clearance``; inf when it does not approach."""
    if not approach > 0.0:
        return math.inf
    if not clearance > 0.0:
        return 0.0
    a = 0.5 * approach * T
    b = approach * reaction
    if a <= 0.0:
        return clearance / b if b > 0.0 else math.inf
    return (-b + math.sqrt(b * b + 4.0 * a * clearance)) / (2.0 * a)


class SeparationMonitor:
    """The speed cap of the streamed motion from its clearances (module docstring).

    Parameters
    ----------
    margin : float
        Clearance [m] the coupling points keep from the obstacles.
    reaction_time : float
        ``t_r`` [s].
    max_acceleration : sequence of float
        ``A_j`` [rad/s^2] of every joint (:meth:`set_limits` replaces them).

    Attributes
    ----------
    cap : float
        The speed cap in force (1.0: none).
    limiting : int
        Index of the coupling point that set the cap (-1: none).
    lowest : float
        The lowest cap since the caller last set it (the node does, every diagnostics
        period).
    """

    def __init__(self, margin: float, reaction_time: float, max_acceleration: Sequence[float]):
        self.margin = float(margin)
        self.reaction_time = float(reaction_time)
        self.set_limits(max_acceleration)
        self._prev: List[float] = []
        self._prev_step = 0
        self._obstacles = None
        self.cap = 1.0
        self.limiting = -1
        self.lowest = 1.0

    def set_limits(self, max_acceleration: Sequence[float]) -> None:
        self.max_acceleration = [float(a) for a in max_acceleration]

    def reset(self) -> None:
        """No obstacles: nothing to keep apart; the cap is lifted."""
        self._obstacles = None
        self.cap = 1.0
        self.limiting = -1

    def update(self, distances: Sequence[float], obstacles, step: int, dt: float,
               qd: Sequence[float], kappa: float) -> float:
        """The cap after one evaluation of the coupling; never raises.

        Parameters
        ----------
        distances : sequence of float
            The coupling points' clearances [m] (``Coupling.last_distances``).
        obstacles : object
            The obstacle set they were computed for (compared by identity: the approach
            speed is only measured across evaluations of the same set).
        step : int
            A count of the integration steps (the approach is measured over
            ``(step - previous step) * dt``).
        dt : float
            The step [s].
        qd : sequence of float
            The joint velocities of the motion [rad/s].
        kappa : float
            The speed factor the motion runs at now (the stepper's time warp).
        """
        prev = self._prev
        n = len(distances)
        same = obstacles is self._obstacles and len(prev) == n
        elapsed = (step - self._prev_step) * dt
        f_min = math.inf
        limiting = -1
        if same and elapsed > 0.0:
            T = brake_time(qd, self.max_acceleration)
            margin, reaction = self.margin, self.reaction_time
            for i in range(n):
                d = distances[i]
                p = prev[i]
                if not (-math.inf < d < math.inf and -math.inf < p < math.inf):
                    continue
                f = admissible_factor((p - d) / elapsed, d - margin, T, reaction)
                if f < f_min:
                    f_min, limiting = f, i
        if len(prev) != n:
            self._prev = prev = [0.0] * n
        for i in range(n):
            prev[i] = float(distances[i])
        self._prev_step = step
        self._obstacles = obstacles
        if same and elapsed > 0.0:
            self.cap = 1.0 if f_min == math.inf else max(MIN_SPEED, min(1.0, kappa * f_min))
            self.limiting = limiting if self.cap < 1.0 else -1
            if self.cap < self.lowest:
                self.lowest = self.cap
        # else (a new obstacle set, no approach measured yet): the cap in force stays
        return self.cap
