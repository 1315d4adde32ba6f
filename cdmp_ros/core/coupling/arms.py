"""The obstacle coupling of a robot of several arms: one coupling per arm, on its own joints.

Each arm (:class:`~cdmp_ros.core.kinematics.arms.Arms`) is a serial chain with its own
:class:`~cdmp_ros.core.coupling.obstacle.ObstacleCoupling` (Eq. 7 on its tool centre point,
Eq. 12 on its links); the arms move disjoint joints, so the robot's joint acceleration is the
arms' accelerations side by side. Avoidance between the arms is not a coupling term: the
adapter's mutual-avoidance constraints plan it.
"""
from typing import List, Optional, Sequence

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.arms import Arms


class ArmsCoupling:
    """:class:`~cdmp_ros.core.coupling.contract.Coupling` of an :class:`Arms` robot.

    Parameters
    ----------
    arms : Arms
    couplings : sequence of Coupling
        One per arm of ``arms``, in its order, each over that arm's joints.

    Attributes
    ----------
    last_distances : list of float
        The arms' ``last_distances``, arm after arm.
    """

    def __init__(self, arms: Arms, couplings: Sequence):
        self.arms = arms
        self.couplings = tuple(couplings)
        if len(self.couplings) != len(arms.chains):
            raise ValidationError(f'couplings: expected one per arm ({len(arms.chains)}), got '
                                  f'{len(self.couplings)}')
        self._index = [idx.tolist() for idx in arms.index]
        self.last_distances: List[float] = []

    def joint_acceleration(self, q: Sequence[float], qd: Optional[Sequence[float]],
                           obstacles: Sequence) -> List[float]:
        """Joint acceleration change [rad/s^2] (n_dofs, the robot's joint order): each arm's
        coupling at its joints' ``q`` and ``qd`` (None: at rest)."""
        out = [0.0] * self.arms.n_dofs
        distances: List[float] = []
        for coupling, idx in zip(self.couplings, self._index):
            a = coupling.joint_acceleration([q[i] for i in idx],
                                            None if qd is None else [qd[i] for i in idx],
                                            obstacles)
            if a is not None:
                for i, v in zip(idx, a):
                    out[i] = v
            distances += coupling.last_distances
        self.last_distances = distances
        return out
