"""Learning primitives from demonstrations: the learner's configuration and its fit.

:func:`fit_primitive` fits a DMP, a CDMP (paper 000, Eq. 13-29, weights by ridge regression
jointly over the demonstrations, :meth:`cdmp_ros.core.dmp.dmp.DMP.fit_demonstrations`) or a ProMP
(paper 003, Eq. 1-4, EM with MAP priors, :meth:`cdmp_ros.core.promp.promp.ProMP.fit`) from a list
of demonstrations ``(T, Y)`` of possibly different lengths and durations.

:class:`LearnerConfig` and :class:`PrompLearnConfig` are mirrored 1:1 by the ROS parameters of
the learner node (ranges and descriptions in the field metadata, like
:class:`cdmp_ros.core.streaming.streamer.StreamerConfig`); the DMP constants are the
:class:`~cdmp_ros.core.dmp.dmp.DmpConfig` of the core.
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike

from cdmp_ros.core.config_fields import (check_chain_fields, check_fields, check_names, param,
                                         robot_description_param, tcp_offset_param,
                                         tip_link_param, tip_links_param, urdf_path_param)
from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.core.errors import ValidationError
from cdmp_ros.core.kinematics.builders import PANDA_JOINTS
from cdmp_ros.core.promp.promp import ProMP, RbfBasis
from cdmp_ros.core.validation import as_array, check_limits

KINDS = ('cdmp', 'dmp', 'promp')
#: The sample demonstrations of the package (bags/README.md), relative to the source tree or
#: to ``<prefix>/share/cdmp_ros``.
DEFAULT_BAGS = ('bags/panda_reach',)


@dataclass(frozen=True)
class LearnerConfig:
    """Parameters of the learner node (top level); mirrored 1:1 by its ROS parameters."""

    kind: str = param('cdmp', 'Primitive to fit: cdmp (limits held by construction), dmp or '
                      'promp; a change applies at the next refit.', choices=KINDS)
    joint_names: Tuple[str, ...] = param(
        PANDA_JOINTS, 'Joints of the primitive, in its order; demonstrations are mapped by '
        'name.', read_only=True)
    urdf_path: str = urdf_path_param('joint limits, which limits.lower/upper when set only '
                                     'tighten; kinematics of the ~/improve cost')
    tip_link: str = tip_link_param()
    tip_links: Tuple[str, ...] = tip_links_param()
    tcp_offset: Tuple[float, ...] = tcp_offset_param(use='the end-effector point of the '
                                                     '~/improve cost')
    robot_description: str = robot_description_param(topic=False)
    demonstration_bags: Tuple[str, ...] = param(
        DEFAULT_BAGS, 'Bags (or directories of bag directories) fitted with the topic '
        'demonstrations. Relative paths are looked up in the working directory, then in the '
        'source tree and <prefix>/share/cdmp_ros.')
    demonstration_topic: str = param(
        'demonstration', 'sensor_msgs/JointState topic read from the bags.')
    fit_on_start: bool = param(True, 'Fit from the bags and publish at start.')
    auto_refit: bool = param(False, 'Refit and publish after every completed topic '
                             'demonstration.')
    primitive_path: str = param('primitive.json', 'File written by ~/save (relative to the '
                                'working directory).')
    demonstration_gap: float = param(
        0.5, 'A topic demonstration ends when no sample came for this long [s] (receive '
        'time) or its stamps jump by more; an empty JointState (no names) ends it at once.',
        0.01, 3600.0)
    min_samples: int = param(10, 'Shortest demonstration kept [samples].', 3, 1000000)
    max_samples: int = param(
        100000, 'Longest demonstration [samples]; it is closed when reached.', 3, 10000000)
    max_demonstrations: int = param(
        100, 'Topic demonstrations kept (the oldest is dropped).', 1, 100000)
    limit_tolerance: float = param(
        0.05, 'Demonstrated positions further than this outside the limits are rejected '
        '[rad]; CDMPs clip the others to the demo margin.', 0.0, 10.0)
    max_stamp_age: float = param(5.0, 'Samples stamped more than this in the past are '
                                 'rejected [s].', 0.001, 1e6)
    max_stamp_lead: float = param(1.0, 'Samples stamped more than this in the future are '
                                  'rejected [s].', 0.001, 1e6)
    accept_unstamped: bool = param(True, 'Accept zero stamps (the receive time is used).')
    max_input_rate: float = param(
        2000.0, 'Messages per second accepted on demonstration; the excess is dropped and '
        'reported (flooding).', 1.0, 1e6)
    diagnostics_period: float = param(1.0, 'Period of the diagnostics messages [s].',
                                      0.01, 60.0)

    def __post_init__(self):
        check_fields(self)
        check_names('joint_names', self.joint_names)
        check_chain_fields(self)
        if not isinstance(self.demonstration_bags, tuple) or not all(
                isinstance(b, str) and b for b in self.demonstration_bags):
            raise ValidationError(f'demonstration_bags: expected a list of paths, got '
                                  f'{self.demonstration_bags!r}')
        if self.max_samples < self.min_samples:
            raise ValidationError(f'max_samples: expected >= min_samples '
                                  f'({self.min_samples}), got {self.max_samples}')
        if not self.demonstration_topic.strip('/'):
            raise ValidationError('demonstration_topic: expected a topic name, got '
                                  f'{self.demonstration_topic!r}')


@dataclass(frozen=True)
class PrompLearnConfig:
    """How ProMPs are learned (paper 003, Eq. 1-4); mirrored by the ``promp.*`` parameters."""

    n_basis: int = param(20, 'Normalised RBFs per joint.', 2, 500)
    basis_extension: float = param(
        0.1, 'Centres spread evenly over [-extension, 1 + extension] in phase.', 0.0, 1.0)
    prior_strength: float = param(
        1.0, 'Pseudo-observations of the inverse-Wishart prior on the weight covariance.',
        0.0, 1e6)
    n_iter: int = param(100, 'Largest number of EM iterations.', 1, 100000)
    tol: float = param(1e-6, 'Relative change that stops EM.', 1e-15, 1.0)

    def __post_init__(self):
        check_fields(self)


def fit_primitive(kind: str, demos: Sequence[Tuple[ArrayLike, ArrayLike]],
                  joint_names: Sequence[str], lower: ArrayLike, upper: ArrayLike,
                  dmp_config: Optional[DmpConfig] = None,
                  promp_config: Optional[PrompLearnConfig] = None):
    """Fit a primitive to demonstrations ``[(T (n_i,), Y (n_i, n_dims)), ...]``.

    Parameters
    ----------
    kind : {'cdmp', 'dmp', 'promp'}
    demos : sequence of (T, Y)
        Times [s] strictly increasing, positions [rad] in the order of ``joint_names``.
    joint_names : sequence of str
    lower, upper : array-like, shape (n_dims,)
        Joint limits; the CDMP's bounds, and stored as metadata for the others.
    dmp_config : DmpConfig, optional
    promp_config : PrompLearnConfig, optional

    Returns
    -------
    DMP, CDMP or ProMP
        Fitted; ``metadata`` holds the number of demonstrations and the fit error.

    Raises
    ------
    ValidationError
        Unknown kind, no demonstration, malformed arrays.
    """
    if kind not in KINDS:
        raise ValidationError(f'kind: expected one of {list(KINDS)}, got {kind!r}')
    if len(demos) == 0:
        raise ValidationError('demos: expected at least one demonstration, got none')
    n = len(joint_names)
    lo, hi = check_limits(lower, upper, n)
    pairs = []
    for i, (T, Y) in enumerate(demos):
        T = as_array(f'demos[{i}].T', T, (None,))
        pairs.append((T, as_array(f'demos[{i}].Y', Y, (T.size, n))))
    dmp_config = dmp_config if dmp_config is not None else DmpConfig()
    meta = {'source': 'cdmp_ros learner', 'n_demonstrations': len(pairs)}
    if kind == 'promp':
        pc = promp_config if promp_config is not None else PrompLearnConfig()
        prim = ProMP.fit(pairs, RbfBasis.uniform(pc.n_basis, pc.basis_extension),
                         prior_strength=pc.prior_strength, n_iter=pc.n_iter, tol=pc.tol,
                         joint_names=joint_names)
        errs = []
        for T, Y in pairs:
            s = (T - T[0]) / (T[-1] - T[0])
            errs.append(np.mean((prim.mean(s) - Y) ** 2))
        meta['fit_rms_error'] = float(np.sqrt(np.mean(errs)))
        meta['limits'] = {'lower': lo.tolist(), 'upper': hi.tolist()}
    else:
        prim = (CDMP(lo, hi, dmp_config, joint_names) if kind == 'cdmp'
                else DMP(n, dmp_config, joint_names))
        prim.fit_demonstrations(pairs)
        meta['fit_rms_error'] = float(prim.fit_rms_error_)
    prim.metadata = meta
    return prim
