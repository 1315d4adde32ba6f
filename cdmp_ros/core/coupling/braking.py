"""How far the arm travels while it brakes within its joint limits: what an obstacle coupling's
influence distance has to exceed.

A repeller acts from ``influence_distance`` on (paper 000, Eq. 7/12); a robot that must keep
its acceleration and jerk limits cannot stop in less than its braking distance. An obstacle
that appears closer to a moving point than that point's braking distance cannot be avoided by
any reference the robot accepts, and a coupling whose influence distance is shorter than the
braking distance acts too late at that speed. :func:`braking_distance` bounds the distance
from the joints' own brakes (:func:`~cdmp_ros.core.streaming.output_stage.brake_excursion`,
each joint at its acceleration and jerk limits) through the Jacobian: ``sum_j |J_j| e_j``
(triangle inequality; the Jacobian is taken at the current configuration, which the few
centimetres of a brake barely change).
"""
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.kinematics.arms import arms_of
from cdmp_ros.core.kinematics.chain import Chain, PointOfInterest
from cdmp_ros.core.streaming.output_stage import brake_excursion
from cdmp_ros.core.validation import as_array

__all__ = ['joint_brake_excursions', 'braking_distance']


def joint_brake_excursions(qd: ArrayLike, qdd: ArrayLike, max_acceleration: ArrayLike,
                           max_jerk: ArrayLike) -> NDArray[np.float64]:
    """Per joint, the distance [rad] to rest under a maximal brake, shape ``qd.shape``
    (``(..., n_dofs)``)."""
    qd = np.asarray(qd, dtype=float)
    qdd = np.broadcast_to(np.asarray(qdd, dtype=float), qd.shape)
    A = np.broadcast_to(np.minimum(np.asarray(max_acceleration, dtype=float), 1e12), qd.shape)
    J = np.broadcast_to(np.minimum(np.asarray(max_jerk, dtype=float), 1e12), qd.shape)
    out = np.empty(qd.shape)
    flat = out.reshape(-1)
    for i, (v, a, am, jm) in enumerate(zip(qd.reshape(-1), qdd.reshape(-1), A.reshape(-1),
                                           J.reshape(-1))):
        s = 1.0 if v >= 0.0 else -1.0  # in the direction of motion
        flat[i] = brake_excursion(s * v, s * a, am, jm)
    return out


def braking_distance(chain: Chain, Q: ArrayLike, Qd: ArrayLike, max_acceleration: ArrayLike,
                     max_jerk: ArrayLike, points: Sequence[PointOfInterest] = None,
                     Qdd: ArrayLike = 0.0) -> NDArray[np.float64]:
    """An upper bound of the distance [m] each point travels while the arm brakes.

    Parameters
    ----------
    chain : Chain
    Q, Qd : array-like, shape (n_steps, n_dofs) or (n_dofs,)
        Configurations and joint velocities (e.g. a primitive's rollout).
    max_acceleration, max_jerk : array-like, shape (n_dofs,)
    points : sequence of PointOfInterest, optional
        Default: the end effector.
    Qdd : array-like, optional
        Joint accelerations (default 0).

    Returns
    -------
    ndarray, shape (n_steps, n_points) (or (n_points,) for one configuration)
    """
    Q = as_array('Q', Q)
    single = Q.ndim == 1
    Q = np.atleast_2d(Q)
    Qd = as_array('Qd', Qd, Q.shape if not single else (Q.shape[1],)).reshape(Q.shape)
    pts = list(points) if points else [PointOfInterest('ee')]
    e = joint_brake_excursions(Qd, np.broadcast_to(np.asarray(Qdd, dtype=float), Q.shape),
                               max_acceleration, max_jerk)
    _, Jac = chain.forward_and_jacobian(Q, pts)  # (n, p, 3, d)
    col = np.linalg.norm(Jac, axis=-2)            # (n, p, d)
    out = np.einsum('npd,nd->np', col, e)
    return out[0] if single else out


def primitive_braking_distance(prim, chain: Chain, max_acceleration: ArrayLike,
                               max_jerk: ArrayLike, dt: float = 0.02) -> float:
    """The largest braking distance [m] of the end effector along a primitive's nominal
    motion (its open-loop rollout every ``dt``): an obstacle must be noticed at least this far
    from the hand for the arm to stop within its limits. ``chain`` an
    :class:`~cdmp_ros.core.kinematics.arms.Arms`: the largest of its arms' hands."""
    traj = prim.rollout(dt=dt)
    A = np.broadcast_to(np.asarray(max_acceleration, dtype=float), (traj.Y.shape[1],))
    J = np.broadcast_to(np.asarray(max_jerk, dtype=float), (traj.Y.shape[1],))
    return max(float(np.max(braking_distance(arm, traj.Y[:, idx], traj.Yd[:, idx], A[idx],
                                             J[idx])))
               for arm, idx in arms_of(chain))


def influence_warning(braking_m: float, influence_distance: float) -> str:
    """'' when the repeller acts earlier than the hand can stop; else the advice."""
    if not braking_m > influence_distance:
        return ''
    return (f'the hand needs up to {braking_m:.3f} m to stop within the joint limits on this '
            f'motion, more than repeller.influence_distance {influence_distance:.3f} m: an '
            f'obstacle first seen closer than that cannot be avoided; raise the influence '
            f'distance to at least {braking_m:.3f} m or slow the motion')
