"""Batched forward kinematics and Jacobians of serial chains (numpy only).

``Chain.forward`` / ``Chain.forward_and_jacobian`` accept joint positions of any leading shape
(time x sigma points, ...) and vectorise over it; a single configuration ``(n_dofs,)`` takes a
pure-Python fast path. Build chains with :func:`planar_chain`, :func:`chain_from_urdf`,
:func:`panda_chain` (the Panda URDF path is passed in by the caller; core never imports
pybullet). Obstacles and closest points between link segments and obstacles: :mod:`.closest`.
"""
from cdmp_ros.core.kinematics.builders import (DUAL_PANDA_DISTANCE, PANDA_EE_OFFSET, PANDA_JOINTS,
                                               PANDA_TIP_LINK, chain_from_urdf, dual_panda_chains,
                                               panda_chain, planar_chain, pose)
from cdmp_ros.core.kinematics.chain import Chain, PointOfInterest
from cdmp_ros.core.kinematics.closest import Box, OrientedBox, Sphere

__all__ = ['Chain', 'PointOfInterest', 'planar_chain', 'chain_from_urdf', 'panda_chain',
           'dual_panda_chains', 'pose', 'PANDA_EE_OFFSET', 'PANDA_JOINTS', 'PANDA_TIP_LINK',
           'DUAL_PANDA_DISTANCE', 'Box', 'OrientedBox', 'Sphere']
