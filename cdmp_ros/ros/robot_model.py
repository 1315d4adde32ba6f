"""The robot model the nodes share: the default URDF and a validated Panda chain.

Every node that uses joint limits (streamer, adapter, learner) loads them here, from the same
``urdf_path`` parameter or, when it is non-empty, from a ``robot_description`` parameter (the
URDF XML a ROS system already publishes to its nodes), and says on ``diagnostics`` where they
came from (:func:`limits_source`).
"""
import os
from typing import Sequence

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.kinematics import panda_chain

#: The name of the limits' source when they come from the ``robot_description`` parameter.
ROBOT_DESCRIPTION = 'robot_description'


def default_urdf_path() -> str:
    """The Panda URDF shipped with pybullet_data (the nodes' ``urdf_path: ''``)."""
    import pybullet_data
    return os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf')


def limits_source(urdf_path: str, robot_description: str = '') -> str:
    """Where the robot model comes from: ``'robot_description'`` when that parameter is
    non-empty (it takes precedence), else the file ``urdf_path`` (empty: the default)."""
    if robot_description.strip():
        return ROBOT_DESCRIPTION
    return urdf_path or default_urdf_path()


def load_panda_chain(urdf_path: str, joint_names: Sequence[str], robot_description: str = ''):
    """The serial chain of ``robot_description`` or ``urdf_path`` (limits, velocity limits,
    kinematics); see :func:`limits_source`.

    Raises
    ------
    ValidationError
        Naming ``urdf_path`` (or ``robot_description``) when it cannot be loaded as a Panda,
        or ``joint_names`` when they are not the chain's joints in order.
    """
    source = limits_source(urdf_path, robot_description)
    text = robot_description if source == ROBOT_DESCRIPTION else None
    name = ROBOT_DESCRIPTION if text is not None else 'urdf_path'
    try:
        chain = panda_chain(source, urdf_text=text)
    except (OSError, CdmpError) as exc:
        raise ValidationError(f'{name}: cannot load a Panda from {source!r}: '
                              f'{exc}') from None
    if list(chain.joint_names) != list(joint_names):
        raise ValidationError(f'joint_names: expected the joints of {source!r} '
                              f'{list(chain.joint_names)}, got {list(joint_names)}')
    return chain


def load_collision_capsules(urdf_path: str, links: Sequence[str], robot_description: str = '',
                            chain=None):
    """The capsules fitted around the collision geometry of ``links``
    (:func:`~cdmp_ros.core.kinematics.capsules.collision_capsules`) of the robot of
    :func:`limits_source`. Mesh files of a ``robot_description`` are looked up from the
    working directory (absolute or ``file://`` names always work).

    ``chain``, if given: every link must be one of its links (the ones the coupling moves).

    Raises
    ------
    ValidationError
        Naming ``coupling_capsule_links`` and what is wrong (unknown link, a link twice, a link
        not in the chain, no collision geometry, a mesh that cannot be read).
    """
    if not links:
        return []
    if chain is not None:
        for i, link in enumerate(links):
            if link not in chain.attachments:
                raise ValidationError(f'coupling_capsule_links[{i}]: {link!r} is not a link of '
                                      f'the chain {list(chain.link_names)}')
    from cdmp_ros.core.kinematics.capsules import collision_capsules
    source = limits_source(urdf_path, robot_description)
    text = robot_description if source == ROBOT_DESCRIPTION else None
    try:
        return collision_capsules(source, links, urdf_text=text,
                                  mesh_dir=os.getcwd() if text is not None else None)
    except CdmpError as exc:
        raise ValidationError(f'coupling_capsule_links: {exc}') from None
