"""Constructors of :class:`Chain`: analytic planar chains, URDF chains, the Franka Panda."""
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.chain import Chain
from cdmp_ros.core.kinematics.urdf import parse_urdf, parse_urdf_string, rpy_to_matrix
from cdmp_ros.core.validation import as_array

#: Panda tool centre point in the ``panda_hand`` frame: between the fingertips, the origin of
#: the URDF's ``panda_grasptarget`` link (fixed joint ``panda_grasptarget_hand``).
PANDA_EE_OFFSET = (0.0, 0.0, 0.105)
#: The link at the end of the Panda arm chain: the hand flange (``PANDA_EE_OFFSET`` is in it).
PANDA_TIP_LINK = 'panda_hand'
PANDA_JOINTS = tuple(f'panda_joint{i}' for i in range(1, 8))
#: Distance between the two Panda bases of the dual-arm cell of paper 003, III-C [m].
DUAL_PANDA_DISTANCE = 1.13


def pose(xyz: ArrayLike = (0.0, 0.0, 0.0), rpy: ArrayLike = (0.0, 0.0, 0.0)
         ) -> NDArray[np.float64]:
    """Homogeneous transform (4, 4) from a translation and URDF roll-pitch-yaw angles."""
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(as_array('rpy', rpy, (3,)))
    T[:3, 3] = as_array('xyz', xyz, (3,))
    return T


def _axis_frame(axis: ArrayLike) -> NDArray[np.float64]:
    """A rotation P (3, 3) with ``P @ e_z == axis`` (exactly I or diag(1, -1, -1) for +-z)."""
    a = np.asarray(axis, dtype=np.float64)
    if np.array_equal(a, [0.0, 0.0, 1.0]):
        return np.eye(3)
    if np.array_equal(a, [0.0, 0.0, -1.0]):
        return np.diag([1.0, -1.0, -1.0])
    e = np.zeros(3)
    e[int(np.argmin(np.abs(a)))] = 1.0
    x = e - (e @ a) * a
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(a, x), a])


def _check_transform(name: str, T: Optional[ArrayLike]) -> NDArray[np.float64]:
    if T is None:
        return np.eye(4)
    T = as_array(name, T, (4, 4))
    R = T[:3, :3]
    if (not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or abs(np.linalg.det(R) - 1) > 1e-9
            or not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])):
        raise ValidationError(f'{name}: expected a rigid transform (rotation block, last row '
                              f'0 0 0 1), got {T.tolist()}')
    return T


def chain_from_urdf(path: str, tip_link: str, base_link: Optional[str] = None,
                    base_transform: Optional[ArrayLike] = None,
                    ee_offset: ArrayLike = (0.0, 0.0, 0.0),
                    urdf_text: Optional[str] = None,
                    joint_names: Optional[Sequence[str]] = None) -> Chain:
    """Serial chain from a URDF file, from ``base_link`` (default: root) to ``tip_link``.

    Parameters
    ----------
    path : str
        URDF file (callers pass it; e.g. ``pybullet_data.getDataPath()``-based paths).
    tip_link : str
        End-effector link (``Chain.ee_link``).
    base_link : str, optional
        First link of the chain; default the URDF root link.
    base_transform : array-like (4, 4), optional
        World pose of ``base_link`` (placing the robot in a cell); default identity.
    ee_offset : array-like (3,)
        End-effector point in the ``tip_link`` frame.
    urdf_text : str, optional
        The URDF XML itself (a ``robot_description``); ``path`` then only names it in messages.
    joint_names : sequence of str, optional
        The movable joints the chain must have, in order (ValidationError naming
        ``joint_names`` otherwise); default any.

    Returns
    -------
    Chain
        Joint limits and velocity limits from the URDF ``<limit>`` elements (continuous
        joints: -inf/inf position limits).
    """
    robot = parse_urdf(path) if urdf_text is None else parse_urdf_string(urdf_text, path)
    joints = robot.path(tip_link, base_link)
    base = _check_transform('base_transform', base_transform)
    base_link = base_link if base_link is not None else robot.root_link()
    attachments = {base_link: (0, np.eye(4))}
    link_names = [base_link]
    names, prismatic, B, lower, upper, vel = [], [], [], [], [], []
    cur = np.eye(4)  # from the current internal frame to the current URDF link frame
    for joint in joints:
        A = cur @ joint.origin
        if joint.type == 'fixed':
            cur = A
        else:
            P = np.eye(4)
            P[:3, :3] = _axis_frame(joint.axis)
            B.append(A @ P)
            cur = P.T
            names.append(joint.name)
            prismatic.append(joint.type == 'prismatic')
            lower.append(joint.lower)
            upper.append(joint.upper)
            vel.append(joint.velocity)
        attachments[joint.child] = (len(names), cur.copy())
        link_names.append(joint.child)
    if not names:
        raise ValidationError(f'tip_link: no movable joint between {base_link!r} and '
                              f'{tip_link!r} in {path!r}')
    if joint_names is not None and list(names) != list(joint_names):
        raise ValidationError(f'joint_names: expected the movable joints of {path!r} from '
                              f'{base_link!r} to tip_link {tip_link!r} {names}, got '
                              f'{list(joint_names)}')
    return Chain(names, prismatic, B, base, attachments, link_names, tip_link,
                 as_array('ee_offset', ee_offset, (3,)), lower, upper, vel)


def panda_chain(urdf_path: str, base_transform: Optional[ArrayLike] = None,
                urdf_text: Optional[str] = None) -> Chain:
    """The 7 arm joints of the Franka Panda (``panda_joint1..7``), tip ``panda_hand``.

    ``PointOfInterest('ee')`` is the tool centre point between the fingertips,
    :data:`PANDA_EE_OFFSET` in the ``panda_hand`` frame (the URDF's ``panda_grasptarget``);
    ``PointOfInterest('panda_hand')`` is the hand (flange) frame origin.

    Parameters
    ----------
    urdf_path : str
        The Panda URDF (e.g. ``pybullet_data``'s ``franka_panda/panda.urdf``).
    base_transform : array-like (4, 4), optional
        World pose of ``panda_link0``; default identity.
    urdf_text : str, optional
        The URDF XML itself (a ``robot_description``); ``urdf_path`` then only names it.

    Returns
    -------
    Chain
        7 degrees of freedom; joint limits from the URDF.
    """
    return chain_from_urdf(urdf_path, PANDA_TIP_LINK, base_transform=base_transform,
                           ee_offset=PANDA_EE_OFFSET, urdf_text=urdf_text,
                           joint_names=PANDA_JOINTS)


def dual_panda_chains(urdf_path: str, distance: float = DUAL_PANDA_DISTANCE
                      ) -> Tuple[Chain, Chain]:
    """The dual-Panda cell of paper 003, III-C: bases ``distance`` apart on the x axis, facing
    each other (the second robot at ``(distance, 0, 0)`` turned by pi about z)."""
    return (panda_chain(urdf_path),
            panda_chain(urdf_path, base_transform=pose((distance, 0.0, 0.0), (0.0, 0.0, np.pi))))


def planar_chain(link_lengths: Sequence[float], lower: Optional[ArrayLike] = None,
                 upper: Optional[ArrayLike] = None,
                 velocity_limits: Optional[ArrayLike] = None) -> Chain:
    """Planar n-link arm (paper 003, III-A uses 4 links of 1 m).

    Joint ``i`` rotates about z; link ``i`` lies along the x axis of its joint frame, and
    joint ``i + 1`` sits at ``(l_i, 0, 0)`` of link ``i``. Links are named ``base``,
    ``link1..linkn`` and ``tip`` (the end effector, at the end of the last link), so the
    end effector is at ``sum_i l_i (cos(theta_i), sin(theta_i))`` with
    ``theta_i = q_1 + ... + q_i``. ``task_axes == (0, 1)``.

    Parameters
    ----------
    link_lengths : sequence of float (n_dofs)
    lower, upper : array-like (n_dofs,), optional
        Joint limits; default -pi, pi.
    velocity_limits : array-like (n_dofs,), optional
        Default +inf.
    """
    lengths = as_array('link_lengths', link_lengths, (None,))
    n = lengths.size
    if n == 0 or np.any(lengths <= 0):
        raise ValidationError(f'link_lengths: expected positive lengths, got {lengths.tolist()}')
    lower = np.full(n, -np.pi) if lower is None else as_array('lower', lower, (n,))
    upper = np.full(n, np.pi) if upper is None else as_array('upper', upper, (n,))
    if np.any(~(upper > lower)):
        raise ValidationError(f'limits: expected lower < upper, got lower={lower.tolist()}, '
                              f'upper={upper.tolist()}')
    vel = (np.full(n, np.inf) if velocity_limits is None
           else as_array('velocity_limits', velocity_limits, (n,)))
    B = []
    for i in range(n):
        b = np.eye(4)
        b[0, 3] = lengths[i - 1] if i > 0 else 0.0
        B.append(b)
    attachments = {'base': (0, np.eye(4))}
    for i in range(n):
        attachments[f'link{i + 1}'] = (i + 1, np.eye(4))
    tip = np.eye(4)
    tip[0, 3] = lengths[-1]
    attachments['tip'] = (n, tip)
    names = [f'joint{i + 1}' for i in range(n)]
    return Chain(names, [False] * n, B, np.eye(4), attachments, list(attachments), 'tip',
                 (0.0, 0.0, 0.0), lower, upper, vel, task_axes=(0, 1))
