"""Config dataclass fields that carry what a ROS parameter descriptor needs (description,
range, read-only, choices, step), and the checks of a config built from them. Shared by the
config dataclasses of every node (streamer, adapter, learner, sim)."""
import math
from dataclasses import MISSING, field, fields

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.builders import PANDA_EE_OFFSET, PANDA_TIP_LINK

__all__ = ['param', 'check_fields', 'check_names', 'stamp_age_param', 'stamp_lead_param',
           'accept_unstamped_param', 'max_obstacles_param', 'obstacle_size_param',
           'obstacle_distance_param', 'max_json_bytes_param', 'robot_description_param',
           'robot_description_timeout_param', 'urdf_path_param', 'tip_link_param',
           'tip_links_param', 'tcp_offset_param', 'check_chain_fields', 'chain_tips']


def param(default, description, lo=None, hi=None, read_only=False, choices=None, step=None):
    """A dataclass field carrying what the ROS parameter descriptor needs (list and tuple
    defaults become a tuple factory)."""
    meta = {'description': description, 'range': (lo, hi), 'read_only': read_only}
    if choices is not None:
        meta['choices'] = tuple(choices)
    if step is not None:
        meta['step'] = step
    if isinstance(default, (list, tuple)):
        return field(default_factory=lambda: tuple(default), metadata=meta)
    return field(default=default, metadata=meta)


def check_fields(cfg) -> None:
    """Type, range and choice checks of a config built with :func:`param` fields."""
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        lo, hi = f.metadata.get('range', (None, None))
        default = f.default if f.default is not MISSING else f.default_factory()
        if isinstance(default, bool):
            if not isinstance(v, bool):
                raise ValidationError(f'{f.name}: expected a bool, got {v!r}')
            continue
        choices = f.metadata.get('choices')
        if choices is not None and v not in choices:
            raise ValidationError(f'{f.name}: expected one of {list(choices)}, got {v!r}')
        if isinstance(default, str) and not isinstance(v, str):
            raise ValidationError(f'{f.name}: expected a string, got {v!r}')
        if lo is None:
            continue
        kind = int if isinstance(default, int) else float
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (
                kind is int and not float(v).is_integer()):
            raise ValidationError(f'{f.name}: expected {kind.__name__}, got {v!r}')
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ValidationError(f'{f.name}: expected a value in [{lo}, {hi}], got {v!r}')


def check_names(name: str, names, allow_empty: bool = False) -> None:
    """``names`` is a tuple of unique non-empty strings (empty only with ``allow_empty``)."""
    if (not isinstance(names, tuple) or (not names and not allow_empty)
            or len(set(names)) != len(names)
            or not all(isinstance(n, str) and n for n in names)):
        raise ValidationError(f'{name}: expected unique non-empty names, got {names!r}')


# -- the input checks shared by the nodes (same names, defaults and ranges in every node) ---
def stamp_age_param():
    return param(5.0, 'Input messages stamped more than this [s] in the past are rejected.',
                 0.001, 3600.0)


def stamp_lead_param():
    return param(1.0, 'Input messages stamped more than this [s] in the future are rejected.',
                 0.001, 3600.0)


def accept_unstamped_param():
    return param(True, 'Accept input messages with a zero stamp (e.g. from the command line).')


def max_obstacles_param():
    return param(64, 'Largest number of obstacles kept; a MarkerArray of more than '
                 'max_obstacles + 1 markers is rejected before it is parsed.', 0, 10000)


def obstacle_size_param():
    return param(10.0, 'Largest accepted marker scale (sphere diameter, box edge) [m].',
                 1e-6, 1000.0)


def obstacle_distance_param():
    return param(100.0, 'Largest accepted distance of a marker from the base [m].', 1e-3, 1e6)


def max_json_bytes_param():
    return param(4_000_000, 'Largest accepted JSON payload (primitive, constraints) [bytes]; '
                 'a longer message is rejected before it is parsed.', 100, 100_000_000)


def robot_description_param(topic: bool = True):
    """``topic``: the node also reads the ``robot_description`` topic
    (:func:`robot_description_timeout_param`)."""
    over = 'the robot_description topic and urdf_path' if topic else 'urdf_path'
    return param('', 'The robot URDF as XML text, as a ROS system passes it to its nodes; when '
                 f'non-empty it takes precedence over {over} for the joint limits and the '
                 'kinematics (diagnostics: limits_source).', read_only=True)


def robot_description_timeout_param(what: str = 'the joint limits and the kinematics'):
    return param(0.0, 'With the robot_description parameter empty: wait up to this long [s] at '
                 'start-up for the URDF on the latched robot_description topic (as '
                 f'robot_state_publisher publishes it) and take {what} from it '
                 "(limits_source: 'robot_description topic'); none, or a rejected one, within "
                 'the time: urdf_path (logged). The wait ends as soon as the message arrives. '
                 '0: no wait, urdf_path. Either way a description arriving later is only '
                 'compared with the model in use (diagnostics: robot_description_topic; a '
                 'different one is a warning, applied by a restart), never swapped in.',
                 0.0, 3600.0, read_only=True)


# -- the robot chain of the streamer, the adapter and the learner ------------------------------
def urdf_path_param(use: str):
    return param('', f'Robot URDF ({use}): a file path, or package://<package>/<path> for a '
                 'file in the share directory of a package (package://cdmp_ros/urdf/planar4.urdf '
                 'is the planar 4-link arm). Empty: the Panda of pybullet_data.', read_only=True)


def tip_link_param():
    return param(PANDA_TIP_LINK, 'Link at the end of the robot chain: the chain runs from the '
                 "URDF's root link to it, its movable joints are joint_names in order, and "
                 "tcp_offset is given in its frame. Default: the Panda's hand flange.",
                 read_only=True)


def tip_links_param():
    return param((), 'A robot of several arms (two or more links): the link at the end of each '
                 "arm, each arm a chain from the URDF's root link to it; joint_names are the "
                 'joints of the arms in any order, tcp_offset is in each of these frames, and '
                 'tip_link is not used. Empty: one chain to tip_link.', read_only=True)


def chain_tips(cfg):
    """The tip link (``tip_link``) or, for a robot of several arms, the tip links
    (``tip_links``) that :func:`cdmp_ros.ros.robot_model.load_chain` takes."""
    return cfg.tip_links if cfg.tip_links else cfg.tip_link


def tcp_offset_param(read_only: bool = True, use: str = 'the end-effector point of the '
                     'kinematics (constraints, IK, planned path)'):
    return param(PANDA_EE_OFFSET, 'Tool centre point: 3 coordinates [m] in the frame of '
                 f"tip_link, {use}. Default: the Panda's fingertips (panda_grasptarget), "
                 "0.105 m along the hand flange's z axis.", read_only=read_only)


def check_chain_fields(cfg) -> None:
    """``tip_link`` is a link name, ``tip_links`` empty or two or more unique link names,
    and ``tcp_offset`` 3 finite coordinates within 10 m (normalised to a tuple of floats); the
    message names the parameter."""
    if not isinstance(cfg.tip_link, str) or not cfg.tip_link.strip():
        raise ValidationError(f'tip_link: expected a link name, got {cfg.tip_link!r}')
    check_names('tip_links', cfg.tip_links, allow_empty=True)
    if len(cfg.tip_links) == 1:
        raise ValidationError(f'tip_links: expected two or more links (one arm: tip_link), '
                              f'got {list(cfg.tip_links)}')
    try:
        tcp = tuple(float(v) for v in cfg.tcp_offset)
    except (TypeError, ValueError):
        tcp = ()
    if len(tcp) != 3 or not all(math.isfinite(v) and abs(v) <= 10.0 for v in tcp):
        raise ValidationError(f'tcp_offset: expected 3 finite coordinates [m] within 10 m '
                              f'of tip_link, got {cfg.tcp_offset!r}')
    object.__setattr__(cfg, 'tcp_offset', tcp)
