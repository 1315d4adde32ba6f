"""The robot model the nodes share: the default URDF and a validated Panda chain."""
import os
from typing import Sequence

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.kinematics import panda_chain


def default_urdf_path() -> str:
    """The Panda URDF shipped with pybullet_data (the nodes' ``urdf_path: ''``)."""
    import pybullet_data
    return os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf')


def load_panda_chain(urdf_path: str, joint_names: Sequence[str]):
    """The serial chain of ``urdf_path`` (limits, velocity limits, kinematics).

    Raises
    ------
    ValidationError
        Naming ``urdf_path`` when the file cannot be loaded as a Panda, or ``joint_names``
        when they are not the chain's joints in order.
    """
    try:
        chain = panda_chain(urdf_path)
    except (OSError, CdmpError) as exc:
        raise ValidationError(f'urdf_path: cannot load a Panda from {urdf_path!r}: '
                              f'{exc}') from None
    if list(chain.joint_names) != list(joint_names):
        raise ValidationError(f'joint_names: expected the joints of {urdf_path!r} '
                              f'{list(chain.joint_names)}, got {list(joint_names)}')
    return chain
