"""A robot of several arms: serial chains that share one joint vector (the dual-Panda cell).

A node's robot model is a :class:`~cdmp_ros.core.kinematics.chain.Chain` (one arm) or an
:class:`Arms` (several, read from one URDF with one tip link per arm: ``tip_links``). An
:class:`Arms` offers what a node reads of the whole robot (joint names, limits, link names) in
the order of the node's ``joint_names``; kinematics stay per arm: :func:`arms_of` gives the
chains of either model with the positions of their joints in that order, and the couplings,
the braking distances and the adaptation's points work arm by arm.
"""
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.chain import Chain


class Arms:
    """Several serial chains moving disjoint sets of one robot's joints.

    Parameters
    ----------
    chains : sequence of Chain
        At least two; no joint in two of them.
    joint_names : sequence of str, optional
        The robot's joint order: every joint of the chains, each once (default: the chains'
        joints, arm after arm).

    Attributes
    ----------
    chains : tuple of Chain
    index : tuple of ndarray of int
        Per arm, the positions of its joints in ``joint_names``.
    joint_names : list of str
    n_dofs : int
    lower, upper, velocity_limits : ndarray (n_dofs,)
        The arms' limits in ``joint_names`` order.
    link_names : list of str
        Every link of the arms, each once (a shared base link once), arm after arm.

    Raises
    ------
    ValidationError
        Fewer than two chains, a joint in two arms, or ``joint_names`` that are not the arms'
        joints (naming ``joint_names`` and what is missing or extra).
    """

    def __init__(self, chains: Sequence[Chain], joint_names: Optional[Sequence[str]] = None):
        self.chains = tuple(chains)
        if len(self.chains) < 2:
            raise ValidationError(f'arms: expected at least two chains, got {len(self.chains)}')
        own = [j for c in self.chains for j in c.joint_names]
        twice = sorted({j for j in own if own.count(j) > 1})
        if twice:
            raise ValidationError(f'arms: joints {twice} belong to more than one arm')
        names = list(own if joint_names is None else joint_names)
        if sorted(names) != sorted(own):
            missing = [j for j in own if j not in names]
            extra = [j for j in names if j not in own]
            raise ValidationError(f'joint_names: expected the joints of the arms {own} in any '
                                  f'order, each once; missing {missing}, not of an arm {extra}'
                                  if missing or extra else
                                  f'joint_names: a joint listed twice in {names}')
        self.joint_names = names
        self.n_dofs = len(names)
        pos = {j: i for i, j in enumerate(names)}
        self.index = tuple(np.array([pos[j] for j in c.joint_names], dtype=np.intp)
                           for c in self.chains)
        self.lower = self._gather('lower')
        self.upper = self._gather('upper')
        self.velocity_limits = self._gather('velocity_limits')
        self.link_names = list(dict.fromkeys(n for c in self.chains for n in c.link_names))

    def _gather(self, name: str) -> NDArray[np.float64]:
        out = np.empty(self.n_dofs)
        for c, idx in zip(self.chains, self.index):
            out[idx] = getattr(c, name)
        return out

    def __repr__(self) -> str:
        return f'Arms({", ".join(f"{c.ee_link}: {c.n_dofs} joints" for c in self.chains)})'

    def arm_of(self, link: str) -> int:
        """The arm whose chain moves ``link`` (a link of several arms, a shared fixed base,
        moves with none of them: the first is returned)."""
        k = _arm_index(self, link)
        if k is None:
            raise ValidationError(f'link {link!r} is in none of the arms (links '
                                  f'{self.link_names})')
        return k


def arms_of(model) -> List[Tuple[Chain, NDArray]]:
    """``[(chain, index)]``: the chains of a :class:`Chain` (one, index ``0..n-1``) or an
    :class:`Arms`, each with the positions of its joints in the model's joint order."""
    if isinstance(model, Arms):
        return list(zip(model.chains, model.index))
    return [(model, np.arange(model.n_dofs))]


def _arm_index(model, link: str) -> Optional[int]:
    """The first arm of ``model`` (a Chain: arm 0) that has ``link``, or None."""
    return next((k for k, (c, _) in enumerate(arms_of(model)) if link in c.attachments), None)


def has_link(model, link: str) -> bool:
    """``link`` is a link of the chain or of one of the arms."""
    return _arm_index(model, link) is not None


def split_by_arm(model, names: Sequence[str], what: str) -> List[List[str]]:
    """Per arm of ``model``, the names of ``names`` that are links of it (in their order);
    ValidationError naming ``what[i]`` for a name in no arm."""
    out: List[List[str]] = [[] for _ in arms_of(model)]
    for i, name in enumerate(names):
        k = _arm_index(model, name)
        if k is None:
            raise ValidationError(f'{what}[{i}]: {name!r} is not a link of the robot '
                                  f'{list(model.link_names)}')
        out[k].append(name)
    return out


def arms_from_urdf(path: str, tip_links: Sequence[str], joint_names: Sequence[str],
                   ee_offset: ArrayLike = (0.0, 0.0, 0.0),
                   urdf_text: Optional[str] = None) -> Arms:
    """The arms of a URDF: one chain from the root link to each of ``tip_links``, the tool
    centre point ``ee_offset`` in each tip's frame, joints in ``joint_names`` order.

    Raises
    ------
    ValidationError
        Naming ``tip_links`` (a link twice, not a link of the URDF, no movable joint on its
        path) or ``joint_names`` (not the arms' joints, each once).
    """
    from cdmp_ros.core.kinematics.builders import chain_from_urdf
    tips = list(tip_links)
    for i, t in enumerate(tips):
        if t in tips[:i]:
            raise ValidationError(f'tip_links[{i}]: {t!r} is listed twice')
    chains = []
    for i, t in enumerate(tips):
        try:
            chains.append(chain_from_urdf(path, t, ee_offset=ee_offset, urdf_text=urdf_text))
        except ValidationError as exc:
            msg = str(exc)
            raise ValidationError(f'tip_links[{i}]' + msg[len('tip_link'):]
                                  if msg.startswith('tip_link') else msg) from None
    return Arms(chains, joint_names)
