"""Validation of the adapter's structured inputs (primitive and constraint-set JSON, Cartesian
goals); every failure raises :class:`~cdmp_ros.core.errors.ValidationError` naming the field."""
import json
import math
from typing import Any, Dict, Optional, Sequence

import numpy as np

from cdmp_ros.core.adaptation.requests import permutation, reorder_promp
from cdmp_ros.core.adaptation.constraints.parse import (RobotContext, parse_constraint_set,
                                                        validate_constraint_set)
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.core.joint_limits import merge_limits
from cdmp_ros.core.primitive_io import primitive_from_dict, validate_primitive_dict
from cdmp_ros.core.streaming.selection import primitive_id


def decode_json(topic: str, text: str, max_bytes: int) -> Any:
    """Size check and JSON decoding of a ``std_msgs/String`` payload."""
    size = len(text.encode('utf-8', 'surrogatepass'))
    if size > max_bytes:
        raise ValidationError(f'{topic}: payload of {size} bytes exceeds max_json_bytes '
                              f'= {max_bytes}')
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValidationError(f'{topic}: not valid JSON ({exc})') from None


def parse_primitive(text: str, joint_names: Sequence[str], max_bytes: int) -> Dict[str, Any]:
    """A primitive message -> ``{kind, d (the validated dict), prim, perm, sha1}``.

    ``prim`` is a ProMP in the order of ``joint_names`` or the DMP / CDMP in its own order;
    ``perm[i]`` is the index in the primitive of ``joint_names[i]``.
    """
    d = decode_json('primitive', text, max_bytes)
    try:
        validate_primitive_dict(d)
        perm = permutation(d['joint_names'], joint_names)
        prim = primitive_from_dict(d)
        if d['kind'] == 'promp':
            prim = reorder_promp(prim, joint_names)
    except CdmpError:
        raise
    except (ValueError, TypeError, KeyError) as exc:
        raise ValidationError(f'primitive: cannot be used: {exc!r}') from None
    return {'kind': d['kind'], 'd': d, 'prim': prim, 'perm': perm,
            'sha1': primitive_id(text)}


def primitive_limits(p: Dict[str, Any], chain):
    """The limits a primitive parsed by :func:`parse_primitive` is adapted within (robot
    joint order): the tighter of its own ``limits`` (if any) and the robot's, per joint and
    bound, never wider (:func:`cdmp_ros.core.joint_limits.merge_limits`).

    Returns
    -------
    lower, upper : ndarray, shape (n_dims,)
    mismatches : list of LimitMismatch
        Every bound on which the primitive and the robot differ (empty without limits).

    Raises
    ------
    ValidationError
        Naming ``primitive.limits`` when they leave no room on a joint within the robot's.
    """
    lim = p['d'].get('limits')
    if lim is None:
        return chain.lower.copy(), chain.upper.copy(), []
    perm = p['perm']
    try:
        return merge_limits(chain.joint_names, chain.lower, chain.upper,
                            np.asarray(lim['lower'], dtype=float)[perm],
                            np.asarray(lim['upper'], dtype=float)[perm])
    except ValidationError as exc:
        raise ValidationError(f'primitive.limits and the robot limits: {exc}') from None


def parse_constraints(text: str, promp, chain, max_bytes: int) -> Optional[dict]:
    """A constraint-set message -> the validated document (None if it is empty).

    Schema-validated always; parsed against ``promp`` and the robot too when a ProMP is given
    (joint indices, link names, dimensions).
    """
    doc = decode_json('constraints', text, max_bytes)
    validate_constraint_set(doc)
    if promp is not None:
        parse_constraint_set(doc, promp, RobotContext.of_robot(chain))
    return doc if doc['constraints'] or doc.get('optimizer') else None


def goal_point_target(msg, base_frame: str) -> np.ndarray:
    """The (3,) target of a ``geometry_msgs/PointStamped`` in the robot base frame."""
    frame = msg.header.frame_id
    if frame and frame.lstrip('/') != base_frame:
        raise ValidationError(f'goal_point.header.frame_id: expected the robot base frame '
                              f'{base_frame!r} (or empty), got {frame!r}')
    p = msg.point
    target = np.array([p.x, p.y, p.z])
    for axis, v in zip('xyz', target):
        if not math.isfinite(v):
            raise ValidationError(f'goal_point.point.{axis}: expected a finite value, got {v}')
    return target


def primitive_goal(p: Optional[Dict[str, Any]]) -> Optional[np.ndarray]:
    """The goal (robot joint order) of a primitive parsed by :func:`parse_primitive`: a
    ProMP's mean at phase 1, a DMP / CDMP's ``dmp.goal``; None without a primitive."""
    if p is None:
        return None
    if p['kind'] == 'promp':
        return p['prim'].mean([1.0])[0]
    return np.asarray(p['d']['dmp']['goal'], dtype=float)[p['perm']]
