"""Primitive files and messages: JSON validated against ``msg_schemas/primitive.schema.json``.

Floats are written by :mod:`json` with ``repr`` precision, so a save/load round trip reproduces
every parameter exactly and therefore every rollout bit for bit.
"""
import json
import math
import os
from typing import Any, Dict, Union

import numpy as np

from cdmp_ros.core.dmp.basis import PhaseBasis
from cdmp_ros.core.dmp.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.joint_limits import parse_joint_limits
from cdmp_ros.core.file_checks import check_document, field_path
from cdmp_ros.core.promp.primitive_file import (covariance_matrix, promp_from_validated,
                                                promp_to_dict)
from cdmp_ros.core.promp.promp import ProMP
from cdmp_ros.core.resources import load_schema

FORMAT_VERSION = 1


def primitive_schema() -> dict:
    """The JSON Schema of primitive files (loaded once)."""
    return load_schema('primitive.schema.json')


#: Largest number of ProMP weights n_dims * len(promp.basis.centers) (cov_w is its square).
MAX_PROMP_WEIGHTS = 2048


def _len(path, value, expected: int, why: str) -> None:
    if len(value) != expected:
        raise PrimitiveFileError(f'{field_path("primitive", path)}: expected {expected} '
                                 f'{why}, got {len(value)}')


def validate_primitive_dict(d: Any) -> None:
    """Check a decoded primitive file; raise :class:`PrimitiveFileError` naming the field.

    The one gate of every primitive loader (files, topics, the streamer and the adapter):
    finite numbers and the schema's ranges (:func:`cdmp_ros.core.file_checks.check_document`),
    then what the schema cannot express: sizes that agree between fields, ordered limits, a
    symmetric positive semi-definite ProMP covariance.
    """
    check_document(d, primitive_schema(), 'primitive', PrimitiveFileError, skip=('metadata',))
    n = d['n_dims']
    if len(d['joint_names']) != n:
        raise PrimitiveFileError(f'primitive.n_dims: expected len(primitive.joint_names) = '
                                 f'{len(d["joint_names"])}, got {n}')
    per_joint = 'values (one per joint, primitive.n_dims)'
    if 'limits' in d:
        lo, hi = d['limits']['lower'], d['limits']['upper']
        _len(['limits', 'lower'], lo, n, per_joint)
        _len(['limits', 'upper'], hi, n, per_joint)
        for i, (a, b) in enumerate(zip(lo, hi)):
            if not a < b:
                raise PrimitiveFileError(f'primitive.limits.upper[{i}]: expected a value > '
                                         f'primitive.limits.lower[{i}] = {a!r}, got {b!r}')
    if 'velocity_limits' in d:
        _len(['velocity_limits'], d['velocity_limits'], n, per_joint)
    if 'joint_limits' in d:
        primitive_kinematic_limits(d)
    if d['kind'] in ('dmp', 'cdmp'):
        nb = len(d['basis']['centers'])
        per_kernel = 'values (len(primitive.basis.centers))'
        _len(['basis', 'widths'], d['basis']['widths'], nb, per_kernel)
        dm = d['dmp']
        _len(['dmp', 'weights'], dm['weights'], n, 'rows (primitive.n_dims)')
        for i, row in enumerate(dm['weights']):
            _len(['dmp', 'weights', i], row, nb, per_kernel)
        for key in ('start', 'goal'):
            _len(['dmp', key], dm[key], n, per_joint)
    if d['kind'] == 'promp':
        _validate_promp(d['promp'], n)


def _validate_promp(body: Dict[str, Any], n: int) -> None:
    M = len(body['basis']['centers'])
    nw = n * M
    if nw > MAX_PROMP_WEIGHTS:
        raise PrimitiveFileError(f'primitive.promp.basis.centers: expected n_dims * '
                                 f'len(centers) <= {MAX_PROMP_WEIGHTS} weights, got {n} * {M}')
    if 'n_basis' in body and body['n_basis'] != M:
        raise PrimitiveFileError(f'primitive.promp.n_basis: expected len(primitive.promp.basis.'
                                 f'centers) = {M}, got {body["n_basis"]}')
    why = f'values (n_dims * len(primitive.promp.basis.centers) = {n} * {M})'
    _len(['promp', 'mean_w'], body['mean_w'], nw, why)
    C = covariance_matrix(body, nw)
    rows = 'cov_w' in body   # else cov_w_base64
    field = 'primitive.promp.' + ('cov_w' if rows else 'cov_w_base64')

    def at(i: int, j: int) -> str:   # an entry, by its row and column
        return f'{field}[{i}][{j}]' if rows else f'{field} entry [{i}][{j}]'
    asym = np.abs(C - C.T) > 1e-12 + 1e-9 * np.abs(C.T)  # the ProMP's own tolerance
    if np.any(asym):
        i, j = (int(v) for v in np.argwhere(asym)[0])
        raise PrimitiveFileError(f'{at(i, j)} and {at(j, i)}: expected equal values (a '
                                 f'symmetric matrix), got {float(C[i, j])!r} and '
                                 f'{float(C[j, i])!r}')
    d = np.diag(C)
    if np.any(d < 0):
        i = int(np.flatnonzero(d < 0)[0])
        raise PrimitiveFileError(f'{at(i, i)}: expected a variance >= 0, got {float(d[i])!r}')
    # every 2x2 principal minor of a PSD matrix is PSD: |C_ij| <= sqrt(C_ii C_jj)
    bad = C * C > np.outer(d, d) * (1.0 + 1e-9) + 1e-300
    if np.any(bad):
        i, j = (int(v) for v in np.argwhere(bad)[0])
        raise PrimitiveFileError(
            f'{at(i, j)}: expected |value| <= sqrt({at(i, i)} * {at(j, j)}) = '
            f'{math.sqrt(d[i] * d[j]):.6g} (a positive semi-definite matrix), got '
            f'{float(C[i, j])!r}')
    eig = np.linalg.eigvalsh(0.5 * (C + C.T))
    if eig[0] < -1e-8 * max(float(np.max(np.abs(eig))), 1e-300):
        raise PrimitiveFileError(f'{field}: expected a positive semi-definite '
                                 f'matrix, got the eigenvalue {eig[0]:.3g}')
    if 'sigma_y' in body:
        _len(['promp', 'sigma_y'], body['sigma_y'], n, 'values (primitive.n_dims)')


def primitive_to_dict(prim) -> Dict[str, Any]:
    """Serialise a fitted DMP, CDMP or ProMP to a schema-valid dict (the file's JSON object;
    arrays as nested lists, e.g. ``dmp.weights`` of shape (n_dims, n_weights_per_dim))."""
    d: Dict[str, Any] = {'format_version': FORMAT_VERSION, 'kind': prim.kind,
                         'joint_names': list(prim.joint_names), 'n_dims': prim.n_dims}
    if getattr(prim, 'joint_limits', None):
        d['joint_limits'] = prim.joint_limits
    if prim.kind == 'promp':
        body = promp_to_dict(prim)
        d.update({k: v for k, v in body.items() if k not in d})
        validate_primitive_dict(d)
        return d
    prim._check_fitted()
    cfg = prim.config
    d['duration'] = float(prim.tau_)
    if prim.kind == 'cdmp':
        d['limits'] = {'lower': prim.y_min.tolist(), 'upper': prim.y_max.tolist()}
    vl = getattr(prim, 'velocity_limits', None)
    if vl is not None:
        d['velocity_limits'] = np.asarray(vl, dtype=float).tolist()
    d['phase'] = {'type': 'exponential', 'alpha_s': float(cfg.alpha_s)}
    d['basis'] = {'type': 'gaussian_phase', 'centers': prim.basis.centers.tolist(),
                  'widths': prim.basis.widths.tolist(), 'basis_width': float(cfg.basis_width)}
    d['dmp'] = {'alpha_y': float(cfg.alpha_y), 'beta_y': float(cfg.beta_y),
                'alpha_g': float(cfg.alpha_g), 'demo_margin': float(cfg.demo_margin),
                'weights': prim.weights_.tolist(), 'start': prim.start_y_.tolist(),
                'goal': prim.goal_y_.tolist()}
    meta = getattr(prim, 'metadata', None)
    if meta:
        d['metadata'] = meta
    return d


def primitive_kinematic_limits(d: Dict[str, Any]):
    """The ``joint_limits`` of a primitive dict as
    :class:`~cdmp_ros.core.joint_limits.KinematicLimits` in its joint order (position limits:
    its ``limits``, else unbounded), or None without them.

    Raises
    ------
    PrimitiveFileError
        Entries for other joints, unknown keys, or values of the wrong kind (naming them).
    """
    if 'joint_limits' not in d:
        return None
    names = d['joint_names']
    n = len(names)
    lim = d.get('limits') or {}
    lo = lim.get('lower', [-1e300] * n)
    hi = lim.get('upper', [1e300] * n)
    try:
        return parse_joint_limits(names, d['joint_limits'], lo, hi, source='primitive')
    except ValidationError as exc:
        raise PrimitiveFileError(f'primitive.{exc}') from None


def primitive_from_dict(d: Any):
    """Build a DMP, CDMP or ProMP from a primitive file's dict (validated against the schema
    first); raises :class:`PrimitiveFileError` naming the bad field."""
    validate_primitive_dict(d)
    if d['kind'] == 'promp':
        prim = promp_from_validated(d)
        if 'joint_limits' in d:
            prim.joint_limits = d['joint_limits']
        return prim
    dm = d['dmp']
    try:
        cfg = DmpConfig(n_weights_per_dim=len(d['basis']['centers']),
                        alpha_y=dm['alpha_y'], beta_y=dm['beta_y'], alpha_g=dm['alpha_g'],
                        alpha_s=d['phase']['alpha_s'],
                        basis_width=d['basis'].get('basis_width', 1.0),
                        demo_margin=dm.get('demo_margin', 1e-3))
        if d['kind'] == 'cdmp':
            prim = CDMP(d['limits']['lower'], d['limits']['upper'], cfg, d['joint_names'])
        else:
            prim = DMP(d['n_dims'], cfg, d['joint_names'])
        prim.basis = PhaseBasis.from_arrays(d['basis']['centers'], d['basis']['widths'],
                                            cfg.alpha_s, cfg.basis_width)
        prim.set_parameters(dm['weights'], dm['start'], dm['goal'], d['duration'])
    except PrimitiveFileError:
        raise
    except ValueError as exc:
        raise PrimitiveFileError(f'primitive: {exc}') from None
    if 'velocity_limits' in d:
        prim.velocity_limits = np.asarray(d['velocity_limits'], dtype=float)
    if 'joint_limits' in d:
        prim.joint_limits = d['joint_limits']
    if 'metadata' in d:
        prim.metadata = d['metadata']
    return prim


def promp_from_dict(d: Dict[str, Any], n_dims: int = None, duration: float = None) -> ProMP:
    """Rebuild a ProMP from a primitive file dict (kind "promp") or its "promp" sub-object.

    A whole file dict is checked by :func:`validate_primitive_dict` first; a sub-object by
    :func:`~cdmp_ros.core.promp.primitive_file.promp_from_validated` (sizes, finite
    covariance). Raises PrimitiveFileError naming the bad field."""
    if not isinstance(d, dict):
        raise PrimitiveFileError(f'promp: expected a JSON object, got {type(d).__name__}')
    if 'promp' in d:
        validate_primitive_dict(d)
    return promp_from_validated(d, n_dims, duration)


def dumps_primitive(prim) -> str:
    """JSON text of a primitive (the payload of the primitive topics).

    Parameters
    ----------
    prim : DMP, CDMP or ProMP
        Fitted.

    Returns
    -------
    str
        Schema-valid JSON (``msg_schemas/primitive.schema.json``).
    """
    return json.dumps(primitive_to_dict(prim))


def loads_primitive(text: Union[str, bytes]):
    """Parse JSON text of a primitive; raises :class:`PrimitiveFileError` on any problem.

    Parameters
    ----------
    text : str or bytes
        JSON of a primitive file or message.

    Returns
    -------
    DMP, CDMP or ProMP
        By the file's ``kind``.
    """
    try:
        d = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError, RecursionError) as exc:
        raise PrimitiveFileError(f'primitive: not valid JSON ({exc})') from None
    return primitive_from_dict(d)


def save_primitive(prim, path: Union[str, os.PathLike]) -> None:
    """Write a primitive file (atomically: a temporary file renamed into place).

    Parameters
    ----------
    prim : DMP, CDMP or ProMP
        Fitted.
    path : str or path-like
        The ``*.json`` file (schema ``msg_schemas/primitive.schema.json``).
    """
    text = json.dumps(primitive_to_dict(prim), indent=1)
    tmp = f'{os.fspath(path)}.tmp'
    with open(tmp, 'w') as f:
        f.write(text)
    os.replace(tmp, path)


def load_primitive(path: Union[str, os.PathLike]):
    """Read a primitive file; raises :class:`PrimitiveFileError` naming the bad field.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    DMP, CDMP or ProMP
        By the file's ``kind``; a save/load round trip reproduces every parameter exactly.
    """
    try:
        with open(path) as f:
            text = f.read()
    except OSError as exc:
        raise PrimitiveFileError(f'primitive file {os.fspath(path)!r}: {exc}') from None
    return loads_primitive(text)
