"""Primitives prepared for streaming: parsing, joint-order mapping, stepper construction.

Everything here runs outside the streaming tick (in a worker thread of the streamer node), so
it may allocate and take milliseconds: JSON parsing and schema validation, reordering the
primitive's joints into the streamer's order, building the :class:`DmpStepper` (which
precomputes the forcing profile). A ProMP (paper 003) is streamed through a CDMP fitted to
its mean trajectory (paper 000), so that the same integrator gives the limit guarantee, the
obstacle coupling and the jump-free switching for every kind of primitive.
"""
import json
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.dmp.dmp import CDMP, DmpConfig
from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.joint_limits import LimitMismatch, describe_mismatches, merge_limits
from cdmp_ros.core.primitive_io import (primitive_from_dict, primitive_kinematic_limits,
                                        promp_from_dict, validate_primitive_dict)
from cdmp_ros.core.dmp.stepper import DmpStepper
from cdmp_ros.core.streaming.selection import primitive_id
from cdmp_ros.core.validation import check_limits, name_permutation

#: Samples per second of the ProMP mean used to fit the streaming CDMP (at least 100).
PROMP_FIT_RATE = 200.0


@dataclass
class PreparedPrimitive:
    """A primitive ready to be switched in by the
    :class:`~cdmp_ros.core.streaming.streamer.ReferenceStreamer`.

    Attributes
    ----------
    prim : DMP or CDMP
        The primitive in the streamer's joint order.
    stepper : DmpStepper
        Built with the streamer's ``dt``; ``reset`` is called at activation.
    kind : str
        Kind of the received primitive (``dmp``, ``cdmp``, ``promp``).
    source : str
        Topic (or file) it came from.
    notes : list of str
        Non-fatal remarks (reordered joints, ProMP converted, limits differing, ...).
    limit_mismatches : list of LimitMismatch
        Where the primitive's limits differ from the robot's (the tighter ones are used).
    content_id : str
        :func:`~cdmp_ros.core.streaming.selection.primitive_id` of the received JSON text
        ('' when prepared from a dict).
    metadata : dict
        The received ``metadata`` (provenance; the adapter's ``metadata.adapter``).
    provenance : Provenance or None
        Of an adapted primitive (set by the streamer from ``metadata``; see
        :mod:`cdmp_ros.core.streaming.selection`).
    kinematic : KinematicLimits or None
        The primitive's own ``joint_limits`` (streamer order), merged by the streamer with
        the robot's while it runs.
    braking_m : float
        The largest braking distance of the hand along the nominal motion [m]
        (:func:`cdmp_ros.core.coupling.braking.primitive_braking_distance`; set by the
        streamer node, 0 if not computed).
    """

    prim: Any
    stepper: DmpStepper
    kind: str
    source: str
    notes: List[str]
    limit_mismatches: List[LimitMismatch] = field(default_factory=list)
    content_id: str = ''
    metadata: Dict[str, Any] = field(default_factory=dict)
    provenance: Any = None
    kinematic: Any = None
    braking_m: float = 0.0

    @property
    def goal_y(self) -> NDArray[np.float64]:
        return self.prim.goal_y_


def _reorder_dmp_dict(d: Dict[str, Any], perm: List[int]) -> Dict[str, Any]:
    """A copy of a dmp/cdmp dict with every per-joint array in the order ``perm``."""
    d = dict(d)
    d['joint_names'] = [d['joint_names'][i] for i in perm]
    if 'limits' in d:
        d['limits'] = {k: [d['limits'][k][i] for i in perm] for k in ('lower', 'upper')}
    if 'velocity_limits' in d:
        d['velocity_limits'] = [d['velocity_limits'][i] for i in perm]
    dm = dict(d['dmp'])
    for key in ('weights', 'start', 'goal'):
        dm[key] = [dm[key][i] for i in perm]
    d['dmp'] = dm
    return d


def _promp_to_cdmp(d: Dict[str, Any], perm: List[int], lower: NDArray, upper: NDArray,
                   config: DmpConfig, joint_names: Sequence[str]) -> CDMP:
    """A CDMP fitted to the mean trajectory of the ProMP in ``d`` (paper 003 Eq. 1-2)."""
    duration = float(d['duration'])
    promp = promp_from_dict(d['promp'], d['n_dims'], duration)
    n = max(100, int(PROMP_FIT_RATE * duration) + 1)
    s = np.linspace(0.0, 1.0, n)
    Y = promp.mean(s)[:, perm]  # E[y_t] = Phi_t mu_w, Eq. (2), paper 003
    if not np.all(np.isfinite(Y)):
        raise PrimitiveFileError('primitive.promp.mean_w: the mean trajectory is not finite')
    lo, hi = lower.copy(), upper.copy()
    if 'limits' in d:  # the tighter of the primitive's and the robot's limits
        lo = np.maximum(lo, np.asarray(d['limits']['lower'], dtype=float)[perm])
        hi = np.minimum(hi, np.asarray(d['limits']['upper'], dtype=float)[perm])
        check_limits(lo, hi)
    cdmp = CDMP(lo, hi, config, joint_names)
    return cdmp.fit(s * duration, Y)


def _refit_cdmp(prim: CDMP, lower: NDArray, upper: NDArray) -> CDMP:
    """A CDMP whose tanh transform (Eq. 19) has the limits ``lower, upper``, fitted to the
    rollout of ``prim`` clipped into them (with the demonstration margin): the limits of a
    CDMP enter through its transform, so wider ones are replaced, not clipped afterwards."""
    traj = prim.rollout(dt=1.0 / PROMP_FIT_RATE)
    margin = prim.config.demo_margin * (upper - lower)
    Y = np.clip(traj.Y, lower + margin, upper - margin)
    new = CDMP(lower, upper, prim.config, prim.joint_names).fit(traj.T, Y)
    for attr in ('velocity_limits', 'metadata'):
        if hasattr(prim, attr):
            setattr(new, attr, getattr(prim, attr))
    return new


def prepare_primitive(payload: Union[str, bytes, Dict[str, Any]], joint_names: Sequence[str],
                      dt: float, lower: ArrayLike, upper: ArrayLike,
                      velocity_limits: Optional[ArrayLike] = None, source: str = 'primitive',
                      promp_config: Optional[DmpConfig] = None) -> PreparedPrimitive:
    """Parse, validate and prepare a primitive message for streaming.

    Parameters
    ----------
    payload : str, bytes or dict
        JSON text (``std_msgs/String.data``) or the decoded dict.
    joint_names : sequence of str
        The streamer's joints; the primitive must name exactly these (any order).
    dt : float
        Streaming period [s].
    lower, upper : array-like, shape (n_dims,)
        Robot position limits (streamer order). Where the primitive's limits differ, the
        tighter of the two are used and listed in ``limit_mismatches`` and ``notes``; a CDMP
        whose limits are wider than the robot's is refitted into the tighter ones, a ProMP is
        converted within them. A plain DMP has no limits of its own (the streamer's guard
        holds the robot's).
    velocity_limits : array-like, shape (n_dims,), optional
        Robot velocity limits; the stepper uses the smaller of these and the primitive's.
    source : str
        Name of the topic, for messages.
    promp_config : DmpConfig, optional
        Constants of the CDMP fitted to a ProMP's mean.

    Raises
    ------
    PrimitiveFileError
        Malformed JSON, schema violation, different joints, or a primitive that cannot be
        integrated at this ``dt``; the message names the field.
    """
    if isinstance(payload, dict):
        d = payload
    else:
        try:
            d = json.loads(payload)
        except (json.JSONDecodeError, UnicodeDecodeError, TypeError, RecursionError) as exc:
            raise PrimitiveFileError(f'{source}: not valid JSON ({exc})') from None
    validate_primitive_dict(d)
    perm = name_permutation(joint_names, d['joint_names'],
                            'primitive.joint_names: expected the streamer joints',
                            PrimitiveFileError)
    notes = []
    if perm != list(range(len(perm))):
        notes.append(f'joints reordered from {d["joint_names"]}')
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    mismatches: List[LimitMismatch] = []
    if 'limits' in d:  # the tighter of the primitive's and the robot's, reported
        try:
            lo_m, hi_m, mismatches = merge_limits(
                joint_names, lower, upper, np.asarray(d['limits']['lower'], dtype=float)[perm],
                np.asarray(d['limits']['upper'], dtype=float)[perm])
        except ValidationError as exc:
            raise PrimitiveFileError(f'{source}: primitive.limits and the robot limits: '
                                     f'{exc}') from None
    if mismatches:
        notes.append(f'limits differ from the robot: {describe_mismatches(mismatches)}')
    try:
        if d['kind'] == 'promp':
            prim = _promp_to_cdmp(d, perm, lower, upper, promp_config or DmpConfig(),
                                  joint_names)
            notes.append(f'ProMP streamed through a CDMP fitted to its mean (rms '
                         f'{prim.fit_rms_error_:.2e})')
        else:
            prim = primitive_from_dict(_reorder_dmp_dict(d, perm))
            if d['kind'] == 'cdmp' and any(m.wider for m in mismatches):
                prim = _refit_cdmp(prim, lo_m, hi_m)
                notes.append(f'CDMP refitted into the tighter limits (rms '
                             f'{prim.fit_rms_error_:.2e})')
        vmax = None if velocity_limits is None else np.asarray(velocity_limits, dtype=float)
        pvl = getattr(prim, 'velocity_limits', None)
        if pvl is not None:
            vmax = pvl if vmax is None else np.minimum(vmax, pvl)
        stepper = prim.stepper(dt, velocity_limits=vmax)
    except PrimitiveFileError:
        raise
    except (ValueError, TypeError, KeyError, np.linalg.LinAlgError) as exc:
        raise PrimitiveFileError(f'{source}: cannot be streamed: {exc}') from None
    meta = d.get('metadata')
    kinematic = primitive_kinematic_limits(d)
    if kinematic is not None:
        kinematic = kinematic.subset(joint_names)
        notes.append("joint_limits of the primitive merged with the robot's")
    return PreparedPrimitive(prim, stepper, d['kind'], source, notes, mismatches,
                             '' if isinstance(payload, dict) else primitive_id(payload),
                             meta if isinstance(meta, dict) else {}, kinematic=kinematic)
