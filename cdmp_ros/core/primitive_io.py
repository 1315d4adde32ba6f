"""Primitive files and messages: JSON validated against ``msg_schemas/primitive.schema.json``.

Floats are written by :mod:`json` with ``repr`` precision, so a save/load round trip reproduces
every parameter exactly and therefore every rollout bit for bit.
"""
import json
import os
from typing import Any, Dict, Optional, Union

import jsonschema
import numpy as np

from cdmp_ros.core.basis import PhaseBasis
from cdmp_ros.core.dmp import CDMP, DMP, DmpConfig
from cdmp_ros.core.errors import PrimitiveFileError
from cdmp_ros.core.resources import schema_path

FORMAT_VERSION = 1
_SCHEMA: Optional[dict] = None


def primitive_schema() -> dict:
    """The JSON Schema of primitive files (loaded once)."""
    global _SCHEMA
    if _SCHEMA is None:
        with open(schema_path('primitive.schema.json')) as f:
            _SCHEMA = json.load(f)
    return _SCHEMA


def _path_str(path) -> str:
    out = 'primitive'
    for p in path:
        out += f'[{p}]' if isinstance(p, int) else f'.{p}'
    return out


def validate_primitive_dict(d: Any) -> None:
    """Raise :class:`PrimitiveFileError` naming the first offending field."""
    if not isinstance(d, dict):
        raise PrimitiveFileError(f'primitive: expected a JSON object, got {type(d).__name__}')
    validator = jsonschema.Draft202012Validator(primitive_schema())
    errors = sorted(validator.iter_errors(d), key=lambda e: (len(e.absolute_path), e.message))
    if errors:
        e = errors[0]
        raise PrimitiveFileError(f'{_path_str(e.absolute_path)}: {e.message}')
    n = d['n_dims']
    if len(d['joint_names']) != n:
        raise PrimitiveFileError(f'primitive.joint_names: expected {n} names (n_dims), got '
                                 f'{len(d["joint_names"])}')
    for key in ('lower', 'upper'):
        if 'limits' in d and len(d['limits'][key]) != n:
            raise PrimitiveFileError(f'primitive.limits.{key}: expected {n} values, got '
                                     f'{len(d["limits"][key])}')
    if 'velocity_limits' in d:
        vl = d['velocity_limits']
        if len(vl) != n or min(vl) <= 0:
            raise PrimitiveFileError(f'primitive.velocity_limits: expected {n} positive values')
    if d['kind'] in ('dmp', 'cdmp'):
        nb = len(d['basis']['centers'])
        if len(d['basis']['widths']) != nb:
            raise PrimitiveFileError('primitive.basis.widths: expected as many widths as '
                                     f'centers ({nb}), got {len(d["basis"]["widths"])}')
        dm = d['dmp']
        if len(dm['weights']) != n or any(len(r) != nb for r in dm['weights']):
            raise PrimitiveFileError(f'primitive.dmp.weights: expected shape ({n}, {nb})')
        for key in ('start', 'goal'):
            if len(dm[key]) != n:
                raise PrimitiveFileError(f'primitive.dmp.{key}: expected {n} values, got '
                                         f'{len(dm[key])}')


def primitive_to_dict(prim) -> Dict[str, Any]:
    """Serialise a fitted DMP, CDMP or ProMP to a schema-valid dict."""
    d: Dict[str, Any] = {'format_version': FORMAT_VERSION, 'kind': prim.kind,
                         'joint_names': list(prim.joint_names), 'n_dims': prim.n_dims}
    if prim.kind == 'promp':
        from cdmp_ros.core.promp_io import promp_to_dict
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


def primitive_from_dict(d: Any):
    """Build a DMP, CDMP or ProMP from a dict; raises :class:`PrimitiveFileError`."""
    validate_primitive_dict(d)
    if d['kind'] == 'promp':
        from cdmp_ros.core.promp_io import promp_from_dict
        return promp_from_dict(d)
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
    if 'metadata' in d:
        prim.metadata = d['metadata']
    return prim


def dumps_primitive(prim) -> str:
    """JSON text of a primitive (the payload of the primitive topics)."""
    return json.dumps(primitive_to_dict(prim))


def loads_primitive(text: Union[str, bytes]):
    """Parse JSON text of a primitive; raises :class:`PrimitiveFileError` on any problem."""
    try:
        d = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError) as exc:
        raise PrimitiveFileError(f'primitive: not valid JSON ({exc})') from None
    return primitive_from_dict(d)


def save_primitive(prim, path: Union[str, os.PathLike]) -> None:
    """Write a primitive file (atomically: a temporary file renamed into place)."""
    text = json.dumps(primitive_to_dict(prim), indent=1)
    tmp = f'{os.fspath(path)}.tmp'
    with open(tmp, 'w') as f:
        f.write(text)
    os.replace(tmp, path)


def load_primitive(path: Union[str, os.PathLike]):
    """Read a primitive file; raises :class:`PrimitiveFileError` naming the bad field."""
    try:
        with open(path) as f:
            text = f.read()
    except OSError as exc:
        raise PrimitiveFileError(f'primitive file {os.fspath(path)!r}: {exc}') from None
    return loads_primitive(text)
