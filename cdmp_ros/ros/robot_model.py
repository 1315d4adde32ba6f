"""The robot model the nodes share: the default URDF, the chain of a URDF validated against
the node's parameters, and which model a node runs with (no ROS here: unit-tested without a ROS
graph).

Every node that uses joint limits (streamer, adapter, learner, sim) loads them here
(:func:`load_chain`), from the same ``urdf_path`` parameter (a file, ``package://<package>/
<path>``, or empty for pybullet_data's Panda: :func:`resolve_urdf_path`) or, when it is
non-empty, from a ``robot_description`` parameter (the URDF XML a ROS system already publishes
to its nodes), as the chain from the URDF's root link to ``tip_link`` with the tool centre point
``tcp_offset`` in that link, whose movable joints must be ``joint_names``; and says on
``/diagnostics`` where they came from (:func:`limits_source`). The streamer, the adapter and
the sim also read the latched ``robot_description`` topic (robot_state_publisher in Jazzy);
which model they run with, and what they make of a description that arrives later, is decided
by :class:`RobotModelSelector` (the ROS side: :mod:`cdmp_ros.ros.robot_description`).
"""
import dataclasses
import os
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.joint_limits import LIMIT_TOLERANCE
from cdmp_ros.core.kinematics import PANDA_EE_OFFSET, PANDA_TIP_LINK, chain_from_urdf
from cdmp_ros.core.kinematics.arms import arms_from_urdf, arms_of, has_link
from cdmp_ros.core.kinematics.urdf import parse_urdf, parse_urdf_string
from cdmp_ros.core.resources import data_path

#: The name of the limits' source when they come from the ``robot_description`` parameter.
ROBOT_DESCRIPTION = 'robot_description'
#: The name of the limits' source when they come from the ``robot_description`` topic.
ROBOT_DESCRIPTION_TOPIC = 'robot_description topic'
#: Joint origins, axes and link frames closer than this [m, or rad per unit] are the same.
KINEMATICS_TOLERANCE = 1e-6
#: ``urdf_path`` values of this form name a file in a package's share directory.
PACKAGE_SCHEME = 'package://'


def default_urdf_path() -> str:
    """The Panda URDF shipped with pybullet_data (the nodes' ``urdf_path: ''``)."""
    import pybullet_data
    return os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf')


def resolve_urdf_path(urdf_path: str) -> str:
    """The file ``urdf_path`` names: ``''`` is :func:`default_urdf_path`;
    ``package://<package>/<path>`` is ``<path>`` in the package's share directory, found with
    the ament index (``AMENT_PREFIX_PATH``, as ``ros2 launch`` and robot_state_publisher find
    it) or, for ``cdmp_ros`` outside any install (a source tree), beside the package
    (:func:`cdmp_ros.core.resources.data_path`, as the sim finds ``urdf/planar4.urdf``);
    anything else is a file path, returned as it is.

    Raises
    ------
    ValidationError
        Naming ``urdf_path``: a ``package://`` name without a path, of a package not found,
        or of a file the package does not have.
    """
    if not urdf_path:
        return default_urdf_path()
    if not urdf_path.startswith(PACKAGE_SCHEME):
        return urdf_path
    package, _, rel = urdf_path[len(PACKAGE_SCHEME):].partition('/')
    if not package or not rel.strip('/'):
        raise ValidationError(f'urdf_path: expected package://<package>/<path>, got '
                              f'{urdf_path!r}')
    try:
        from ament_index_python.packages import (PackageNotFoundError,
                                                 get_package_share_directory)
    except ImportError:  # no ROS installation: only this package's own files
        share = None
    else:
        try:
            share = get_package_share_directory(package, print_warning=False)
        except (PackageNotFoundError, ValueError, OSError):  # OSError: AMENT_PREFIX_PATH unset
            share = None
    if share is not None:
        path = os.path.join(share, rel)
        if not os.path.isfile(path):
            raise ValidationError(f'urdf_path: {urdf_path!r}: no file {path!r} in the share '
                                  f'directory of {package!r}')
        return path
    if package != 'cdmp_ros':
        raise ValidationError(f'urdf_path: {urdf_path!r}: package {package!r} not found in '
                              f'the ament index (AMENT_PREFIX_PATH)')
    try:
        return data_path(*rel.strip('/').split('/'))
    except CdmpError as exc:
        raise ValidationError(f'urdf_path: {urdf_path!r}: {exc}') from None


def limits_source(urdf_path: str, robot_description: str = '') -> str:
    """Where the robot model comes from: ``'robot_description'`` when that parameter is
    non-empty (it takes precedence), else the file ``urdf_path`` names
    (:func:`resolve_urdf_path`; ValidationError naming ``urdf_path`` if it names none)."""
    if robot_description.strip():
        return ROBOT_DESCRIPTION
    return resolve_urdf_path(urdf_path)


def load_chain(urdf_path: str, joint_names: Sequence[str],
               tip_link: Union[str, Sequence[str]] = PANDA_TIP_LINK,
               tcp_offset: Sequence[float] = PANDA_EE_OFFSET, robot_description: str = ''):
    """The serial chain of ``robot_description`` or ``urdf_path`` (see :func:`limits_source`)
    from the URDF's root link to ``tip_link``: joint limits, velocity limits and kinematics,
    with ``PointOfInterest('ee')`` at ``tcp_offset`` in ``tip_link``. The defaults are the
    Panda's (:func:`~cdmp_ros.core.kinematics.panda_chain`).

    ``tip_link`` a sequence of two or more links (a node's ``tip_links``): the
    :class:`~cdmp_ros.core.kinematics.arms.Arms` of one chain to each, ``joint_names`` their
    joints in any order.

    Raises
    ------
    ValidationError
        Naming the parameter: ``urdf_path`` (or ``robot_description``) when it cannot be read
        as a URDF, ``tip_link`` (``tip_links``) when it is not a link of it below a movable
        joint, ``tcp_offset`` when it is not 3 coordinates, ``joint_names`` when they are not
        the chain's movable joints in order (the arms' joints).
    """
    source = limits_source(urdf_path, robot_description)
    text = robot_description if source == ROBOT_DESCRIPTION else None
    name = ROBOT_DESCRIPTION if text is not None else 'urdf_path'
    try:  # read first: what follows is then about tip_link, joint_names or tcp_offset
        (parse_urdf(source) if text is None else parse_urdf_string(text, source)).root_link()
    except (OSError, CdmpError) as exc:
        raise ValidationError(f'{name}: cannot load a robot from {source!r}: '
                              f'{_strip(exc, source)}') from None
    tips = [tip_link] if isinstance(tip_link, str) else list(tip_link)
    try:
        if len(tips) > 1:
            return arms_from_urdf(source, tips, joint_names, ee_offset=tcp_offset,
                                  urdf_text=text)
        return chain_from_urdf(source, tips[0] if tips else '', ee_offset=tcp_offset,
                               urdf_text=text, joint_names=joint_names)
    except ValidationError as exc:  # 'tip_link: ...', 'joint_names: ...' or 'ee_offset: ...'
        msg = str(exc)
        if msg.startswith('joint_names'):
            raise
        if msg.startswith('ee_offset'):  # this node's tcp_offset
            msg = 'tcp_offset' + msg[len('ee_offset'):]
        raise ValidationError(f'{msg} (the robot of {source!r})') from None


def mesh_dirs(urdf_path: str, source: str, text: bool) -> List[str]:
    """Where the mesh files of a robot model are looked up, in turn: of a ``robot_description``
    (``text``) the working directory, then the directory of the node's ``urdf_path`` file (the
    robot that description usually describes); of a file ``source`` its directory; then the
    ``share`` directory of every ``AMENT_PREFIX_PATH`` prefix, which resolves
    ``package://<package>/<path>`` as ROS does."""
    if text:
        out = [os.getcwd()]
        try:
            out.append(os.path.dirname(os.path.abspath(resolve_urdf_path(urdf_path))))
        except ValidationError:
            pass
    else:
        out = [os.path.dirname(os.path.abspath(source))]
    out += [os.path.join(p, 'share') for p in os.environ.get('AMENT_PREFIX_PATH', '').split(
        os.pathsep) if p]
    return list(dict.fromkeys(out))


def load_collision_capsules(urdf_path: str, links: Sequence[str], robot_description: str = '',
                            chain=None, what: str = 'coupling_capsule_links'):
    """The capsules fitted around the collision geometry of ``links``
    (:func:`~cdmp_ros.core.kinematics.capsules.collision_capsules`) of the robot of
    :func:`limits_source`. Mesh files are looked up as :func:`mesh_dirs` says (absolute or
    ``file://`` names always work).

    ``chain``, if given: every link must be one of its links (the ones the coupling moves).

    Raises
    ------
    ValidationError
        Naming ``what`` (the parameter that lists the links) and what is wrong (unknown link, a
        link twice, a link not in the chain, no collision geometry, a mesh that cannot be
        read).
    """
    if not links:
        return []
    if chain is not None:
        for i, link in enumerate(links):
            if not has_link(chain, link):
                raise ValidationError(f'{what}[{i}]: {link!r} is not a link of the chain '
                                      f'{list(chain.link_names)}')
    from cdmp_ros.core.kinematics.capsules import collision_capsules
    source = limits_source(urdf_path, robot_description)
    text = robot_description if source == ROBOT_DESCRIPTION else None
    try:
        return collision_capsules(source, links, urdf_text=text,
                                  mesh_dirs=mesh_dirs(urdf_path, source, text is not None))
    except CdmpError as exc:
        raise ValidationError(f'{what}: {exc}') from None


# -- which model a node runs with --------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class RobotModel:
    """The robot model a node runs with.

    Attributes
    ----------
    chain : Chain
        Joint limits, velocity limits and kinematics.
    source : str
        Where it came from, as ``limits_source`` reports it: :data:`ROBOT_DESCRIPTION` (the
        parameter), :data:`ROBOT_DESCRIPTION_TOPIC` or the URDF file's path.
    text : str or None
        The URDF XML of a parameter or topic model (None: read from the file ``source``).
    capsules : tuple of Capsule
        The collision capsules of the links asked for (the streamer's
        ``coupling_capsule_links``; empty if none).
    """

    chain: object
    source: str
    text: Optional[str] = None
    capsules: tuple = ()


#: :attr:`DescriptionVerdict.status` values: the model in use came from this message; it
#: describes the model in use; it describes another robot model; it was rejected.
USED, SAME, DIFFERS, REJECTED = 'used', 'same', 'differs', 'rejected'


@dataclasses.dataclass(frozen=True)
class DescriptionVerdict:
    """What a ``robot_description`` message means for a node (:class:`RobotModelSelector`).

    Attributes
    ----------
    status : str
        :data:`USED`, :data:`SAME`, :data:`DIFFERS` or :data:`REJECTED`.
    message : str
        One line for the log and for diagnostics (``robot_description_topic``); a rejection
        names what was wrong.
    category : str or None
        A rejection's reason category (``rejected_<category>`` on diagnostics).
    warn : bool
        The node runs with another model than the topic describes, by no choice of the user
        (the ``robot_description`` parameter is empty): a standing warning.
    repeat : bool
        The same text as the previous message (judged then, not parsed again).
    """

    status: str
    message: str
    category: Optional[str] = None
    warn: bool = False
    repeat: bool = False


class _Rejected(Exception):
    def __init__(self, message: str, category: str):
        super().__init__(message)
        self.verdict = DescriptionVerdict(REJECTED, message, category, warn=True)


def _strip(exc: Exception, prefix: str) -> str:
    text = str(exc)
    return text[len(prefix) + 2:] if text.startswith(prefix + ': ') else text


def _same(x: float, y: float, tol: float) -> bool:
    return x == y or abs(x - y) <= tol


def model_differences(used: RobotModel, other: RobotModel) -> List[str]:
    """What a node would do differently with ``other``'s model than with ``used``'s (both of
    the same joints): every differing position or velocity limit (``'<joint> <bound> <used>
    -> <other>'``), the joints whose origin or axis differ, other link frames, other collision
    capsules. Visual geometry, inertias and whatever else the nodes do not use is not
    compared."""
    a, b = used.chain, other.chain
    out = []
    for j, name in enumerate(a.joint_names):
        for label, x, y in (('lower', a.lower[j], b.lower[j]), ('upper', a.upper[j], b.upper[j]),
                            ('velocity', a.velocity_limits[j], b.velocity_limits[j])):
            if not _same(float(x), float(y), LIMIT_TOLERANCE):
                out.append(f'{name} {label} {x:.6g} -> {y:.6g}')
    arms_a, arms_b = arms_of(a), arms_of(b)
    if len(arms_a) != len(arms_b):
        out.append(f'{len(arms_a)} -> {len(arms_b)} arms')
    for (ca, _), (cb, _) in zip(arms_a, arms_b):
        out += _kinematic_differences(ca, cb)
    for ca, cb in zip(used.capsules, other.capsules):
        tol = KINEMATICS_TOLERANCE
        if not (np.allclose(ca.start, cb.start, rtol=0.0, atol=tol)
                and np.allclose(ca.end, cb.end, rtol=0.0, atol=tol)
                and _same(ca.radius, cb.radius, tol)):
            out.append(f'collision capsule of {ca.link}')
    return out


def _kinematic_differences(a, b) -> List[str]:
    """The joints of chain ``a`` whose origin or axis differ in ``b``, and 'link frames'."""
    out = []
    tol = KINEMATICS_TOLERANCE
    moved = [name for j, name in enumerate(a.joint_names)
             if not np.allclose(a.B[j], b.B[j], rtol=0.0, atol=tol)]
    if moved:
        out.append('origin or axis of ' + ', '.join(moved))
    frames = (set(a.attachments) != set(b.attachments)
              or not np.allclose(a.base_transform, b.base_transform, rtol=0.0, atol=tol)
              or not np.allclose(a.ee_offset, b.ee_offset, rtol=0.0, atol=tol)
              or any(a.attachments[k][0] != b.attachments[k][0]
                     or not np.allclose(a.attachments[k][1], b.attachments[k][1], rtol=0.0,
                                        atol=tol) for k in a.attachments))
    if frames and not moved:
        out.append('link frames')
    return out


class RobotModelSelector:
    """Which robot model a node runs with, and what a ``robot_description`` message means.

    The sources, first match wins:

    1. the ``robot_description`` parameter (``parameter``), when non-empty: no wait;
    2. the latched ``robot_description`` topic: a message received within ``timeout`` seconds
       of the start (:attr:`wait_s`; the node's ``robot_description_timeout``), if it is a
       URDF of ``joint_names`` (and, with ``capsule_links``, of their collision geometry);
    3. the file ``urdf_path`` (:func:`resolve_urdf_path`; empty: pybullet_data's Panda).

    Each is loaded by :func:`load_chain` with ``joint_names``, ``tip_link`` and ``tcp_offset``.

    The model is chosen once (:meth:`start`). A message arriving later (:meth:`offer`) is
    compared with it and only reported: rejected (not a URDF, other joints), the same model,
    or another one, which a restart applies (unless the parameter is set: it takes
    precedence). The model is never swapped under a running node: its limits, kinematics,
    coupling capsules and the primitives prepared with them stay consistent.

    Parameters
    ----------
    urdf_path : str
    joint_names : sequence of str
        The node's joints: a description of other joints is rejected.
    parameter : str
        The ``robot_description`` parameter (URDF XML or '').
    timeout : float
        ``robot_description_timeout`` [s]; 0: no wait.
    capsule_links : sequence of str
        Links whose collision capsules the node needs (loaded with the model; a description
        whose geometry of them cannot be read is rejected).
    tip_link : str
        The last link of the chain (default the Panda's hand flange); a description without
        it is rejected.
    tcp_offset : sequence of 3 float
        The tool centre point in ``tip_link`` (``PointOfInterest('ee')`` of the chain).

    Attributes
    ----------
    model : RobotModel or None
        The model in use (after :meth:`start`).
    verdict : DescriptionVerdict or None
        Of the last ``robot_description`` message (None: none so far).
    """

    def __init__(self, urdf_path: str, joint_names: Sequence[str], parameter: str = '',
                 timeout: float = 0.0, capsule_links: Sequence[str] = (),
                 tip_link: str = PANDA_TIP_LINK,
                 tcp_offset: Sequence[float] = PANDA_EE_OFFSET):
        self.urdf_path = urdf_path
        self.joint_names = list(joint_names)
        self.tip_link = tip_link
        self.tcp_offset = tuple(tcp_offset)
        self.parameter = parameter
        self.timeout = float(timeout)
        self.capsule_links = tuple(capsule_links)
        self.model: Optional[RobotModel] = None
        self.verdict: Optional[DescriptionVerdict] = None
        self._last_text: Optional[str] = None

    @property
    def by_parameter(self) -> bool:
        """The ``robot_description`` parameter is set (and takes precedence)."""
        return bool(self.parameter.strip())

    @property
    def wait_s(self) -> float:
        """How long to wait for the topic at start-up [s] (0 with the parameter set)."""
        return 0.0 if self.by_parameter else max(0.0, self.timeout)

    @property
    def topic_state(self) -> str:
        """The diagnostics value ``robot_description_topic``: what the last message was."""
        v = self.verdict
        if v is None:
            return 'none received'
        if v.status == REJECTED:
            return 'rejected: ' + _strip(v.message, ROBOT_DESCRIPTION)
        return v.message

    def start(self, text: Optional[str] = None,
              rejection: Optional[DescriptionVerdict] = None) -> Tuple[RobotModel, str, bool]:
        """Choose the model at start-up.

        Parameters
        ----------
        text : str, optional
            The ``robot_description`` message received while waiting (None: none; ignored
            with the parameter set).
        rejection : DescriptionVerdict, optional
            Of a message rejected before it could be read (:meth:`reject`).

        Returns
        -------
        model : RobotModel
        note : str
            How it was chosen, for the log ('' when the topic was not waited for).
        warn : bool
            The note is a warning (the topic was waited for and is not used).

        Raises
        ------
        ValidationError
            The parameter or ``urdf_path`` cannot be loaded (naming it), or a link of
            ``capsule_links`` has no usable collision geometry in it.
        """
        if self.by_parameter:
            self.model = self._from_text(self.parameter, ROBOT_DESCRIPTION)
            return self.model, '', False
        model = None
        if text is not None:
            self._last_text = text
            try:
                model = self._from_topic(text)
            except _Rejected as exc:
                rejection = exc.verdict
            else:
                self.verdict = DescriptionVerdict(USED, 'in use')
        if rejection is not None:
            self.verdict = rejection
        if model is not None:
            self.model = model
            return model, (f'robot model from the robot_description topic (waited at most '
                           f'{self.timeout:g} s)'), False
        self.model = self._from_file()
        if rejection is not None:
            return self.model, (f'{rejection.message}; using urdf_path '
                                f'{self.model.source}'), True
        if self.wait_s > 0.0:
            return self.model, (f'no robot_description message within robot_description_'
                                f'timeout = {self.timeout:g} s; using urdf_path '
                                f'{self.model.source}'), True
        return self.model, '', False

    def reject(self, message: str, category: str) -> DescriptionVerdict:
        """A message rejected before it could be read (too large, not deserialisable)."""
        self._last_text = None
        self.verdict = DescriptionVerdict(REJECTED, message, category,
                                          warn=not self.by_parameter)
        return self.verdict

    def offer(self, text: str) -> DescriptionVerdict:
        """A ``robot_description`` message after :meth:`start`: compared with the model in
        use, which is kept whatever the message says. A repeat of the previous text is not
        parsed again (its verdict, with ``repeat`` set)."""
        if self.model is None:
            raise CdmpError('RobotModelSelector.offer() called before start()')
        if text == self._last_text and self.verdict is not None:
            return dataclasses.replace(self.verdict, repeat=True)
        self._last_text = text
        self.verdict = self._judge(text)
        return self.verdict

    def _judge(self, text: str) -> DescriptionVerdict:
        model = self.model
        if model.text is not None and text == model.text:
            if model.source == ROBOT_DESCRIPTION_TOPIC:
                return DescriptionVerdict(USED, 'in use')
            return DescriptionVerdict(SAME, f'matches the model in use ({model.source})')
        try:
            other = self._from_topic(text)
        except _Rejected as exc:
            return dataclasses.replace(exc.verdict, warn=not self.by_parameter)
        diffs = model_differences(model, other)
        if not diffs:
            return DescriptionVerdict(SAME, f'matches the model in use ({model.source})')
        shown = '; '.join(diffs[:8]) + (f'; and {len(diffs) - 8} more' if len(diffs) > 8 else '')
        if self.by_parameter:
            used, advice = 'the robot_description parameter, which takes precedence', ''
        elif model.source == ROBOT_DESCRIPTION_TOPIC:
            used, advice = ('the robot_description topic at start-up',
                            '; a restart of the node applies it')
        elif self.wait_s > 0.0:
            used, advice = (model.source, f'; it came after robot_description_timeout = '
                                          f'{self.timeout:g} s: a restart of the node applies it')
        else:
            used, advice = (model.source, '; a restart of the node with '
                                          'robot_description_timeout > 0 applies it')
        return DescriptionVerdict(DIFFERS, f'differs from the model in use ({used}): '
                                           f'{shown}{advice}', warn=not self.by_parameter)

    # -- loading -----------------------------------------------------------------------------
    def _chain(self, text: str = ''):
        return load_chain(self.urdf_path, self.joint_names, self.tip_link, self.tcp_offset,
                          text)

    def _from_file(self) -> RobotModel:
        chain = self._chain()
        return RobotModel(chain, limits_source(self.urdf_path), None,
                          tuple(load_collision_capsules(self.urdf_path, self.capsule_links,
                                                        chain=chain)))

    def _from_text(self, text: str, source: str, chain=None) -> RobotModel:
        chain = self._chain(text) if chain is None else chain
        return RobotModel(chain, source, text,
                          tuple(load_collision_capsules(self.urdf_path, self.capsule_links,
                                                        text, chain)))

    def _from_topic(self, text: str) -> RobotModel:
        """The model of a topic message, or :class:`_Rejected` naming what is wrong."""
        try:
            parse_urdf_string(text, 'URDF')
        except ValidationError as exc:
            raise _Rejected(f'robot_description: not a valid URDF: {_strip(exc, "URDF")}',
                            'malformed') from None
        try:  # a URDF: what is wrong is its joints, tip link (or this node's tcp_offset)
            chain = self._chain(text)
        except ValidationError as exc:
            raise _Rejected(f'robot_description: not a robot of the configured joint_names '
                            f'and tip_link: {exc}', 'joint_names') from None
        try:
            return self._from_text(text, ROBOT_DESCRIPTION_TOPIC, chain)
        except ValidationError as exc:  # the collision geometry of capsule_links
            raise _Rejected(f'robot_description: {exc}', 'malformed') from None
