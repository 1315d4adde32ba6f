"""The robot of a ``cdmp demo``: its kinematic model, where its hands are, and how far a
sphere is from its arms (ROS-free; the demo driver places its sphere with it, the summary reads
the recorded run with it).

- ``panda``: one Franka Panda of pybullet_data (``cdmp demo --kind cdmp|promp``), frame
  ``panda_link0``; its URDF comes from the caller (``panda_urdf``: the core does not look up
  pybullet_data);
- ``dual_panda``: the two Pandas of ``urdf/dual_panda.urdf`` (``cdmp demo --kind dual``), frame
  ``world``, joints of ``left_`` then ``right_`` (the sim's order).

A hand is the arm's tool centre point (:data:`~cdmp_ros.core.kinematics.builders.
PANDA_EE_OFFSET` in its ``panda_hand``, between the fingertips). The arm's clearance to a sphere
is measured from capsules around the collision geometry of its links
(:mod:`~cdmp_ros.core.kinematics.capsules`) and from a capsule of :data:`FINGER_RADIUS` around
the wrist-to-fingertips axis (the fingers are not links of the chain).
"""
from typing import List, Optional, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics import PointOfInterest
from cdmp_ros.core.kinematics.arms import arms_from_urdf, arms_of
from cdmp_ros.core.kinematics.capsules import ArmCapsules

#: The robots a demo runs on.
ROBOTS = ('panda', 'dual_panda')
#: Radius [m] around the wrist-to-fingertips axis that holds the fingers.
FINGER_RADIUS = 0.06
#: Prefix of each arm's links and joints in ``dual_panda``.
DUAL_PREFIXES = ('left_', 'right_')
EE = PointOfInterest('ee')


def _panda_links(prefix: str = '') -> List[str]:
    return [f'{prefix}panda_link{i}' for i in range(1, 8)] + [f'{prefix}panda_hand']


class DemoRobot:
    """One of :data:`ROBOTS` (see the module docstring); ``panda_urdf`` the file of
    ``panda`` (pybullet_data's ``franka_panda/panda.urdf``), unused by ``dual_panda``.

    Attributes
    ----------
    name : str
    model : Chain or Arms
        Joints in the order of the sim's ``joint_states``.
    urdf : str
        The URDF file the model was read from.
    frame : str
        The frame the demo's obstacles are published in (the model's root).
    arm_links : list of list of str
        Per arm, the links whose capsules count in :meth:`clearance`.
    """

    def __init__(self, name: str, panda_urdf: Optional[str] = None):
        from cdmp_ros.core.kinematics.builders import PANDA_EE_OFFSET, panda_chain
        from cdmp_ros.core.resources import data_path
        if name == 'panda':
            if not panda_urdf:
                raise ValidationError('robot panda: give panda_urdf, the Panda URDF of '
                                      'pybullet_data (what the nodes load for urdf_path "")')
            self.urdf = panda_urdf
            self.model = panda_chain(self.urdf)
            self.frame = 'panda_link0'
            self.arm_links = [_panda_links()]
        elif name == 'dual_panda':
            self.urdf = data_path('urdf', 'dual_panda.urdf')
            self.model = arms_from_urdf(self.urdf, [f'{p}panda_hand' for p in DUAL_PREFIXES],
                                        [f'{p}panda_joint{i}' for p in DUAL_PREFIXES
                                         for i in range(1, 8)], ee_offset=PANDA_EE_OFFSET)
            self.frame = 'world'
            self.arm_links = [_panda_links(p) for p in DUAL_PREFIXES]
        else:
            raise ValidationError(f'robot: expected one of {list(ROBOTS)}, got {name!r}')
        self.name = name
        self.arms = arms_of(self.model)
        #: per arm, its :class:`~cdmp_ros.core.kinematics.capsules.ArmCapsules`
        self.capsules = [ArmCapsules.from_urdf(chain, self.urdf, links, FINGER_RADIUS)
                         for (chain, _), links in zip(self.arms, self.arm_links)]

    @property
    def joint_names(self) -> List[str]:
        return list(self.model.joint_names)

    @property
    def n_dofs(self) -> int:
        return int(self.model.n_dofs)

    @property
    def n_arms(self) -> int:
        return len(self.arms)

    def positions(self, Q: ArrayLike, points: Sequence[Sequence[PointOfInterest]]
                  ) -> List[NDArray[np.float64]]:
        """Per arm, the positions ``(..., P_arm, 3)`` of its ``points[arm]`` at joint
        positions ``Q (..., n_dofs)``."""
        Q = np.asarray(Q, dtype=np.float64)
        if Q.shape[-1] != self.n_dofs:
            raise ValidationError(f'{self.name}: expected joint positions of {self.n_dofs} '
                                  f'joints, got shape {Q.shape}')
        flat = Q.reshape(-1, self.n_dofs)
        return [chain.forward(flat[:, idx], list(pts)).reshape(Q.shape[:-1] + (len(pts), 3))
                for (chain, idx), pts in zip(self.arms, points)]

    def hands(self, Q: ArrayLike) -> NDArray[np.float64]:
        """Tool centre points ``(..., n_arms, 3)`` at joint positions ``Q`` ``(..., n_dofs)``."""
        return np.concatenate(self.positions(Q, [[EE]] * self.n_arms), axis=-2)

    def clearance(self, q: ArrayLike, center: ArrayLike, radius: float) -> float:
        """Least distance [m] between a sphere and the capsules of every arm at ``q``
        (negative: they overlap)."""
        q = np.asarray(q, dtype=np.float64)
        return min(caps.sphere_clearance(q[idx], center, radius)
                   for caps, (_, idx) in zip(self.capsules, self.arms))

    def split(self, names: Sequence[str], what: str) -> List[List[str]]:
        """Per arm, the links of ``names`` that belong to it (ValidationError naming
        ``what[i]`` for a link of no arm)."""
        from cdmp_ros.core.kinematics.arms import split_by_arm
        return split_by_arm(self.model, names, what)


def between_hands(hands: ArrayLike) -> NDArray[np.float64]:
    """The point midway between the hands ``(n_arms, 3)`` (one arm: its hand)."""
    return np.asarray(hands, dtype=np.float64).mean(axis=0)
