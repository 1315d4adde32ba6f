"""ProMP <-> primitive file (msg_schemas/primitive.schema.json, kind "promp").

:func:`cdmp_ros.core.primitive_io.primitive_to_dict` writes the common fields (format_version,
kind, joint_names, n_dims) and merges in what :func:`promp_to_dict` returns (``duration`` and
the ``promp`` sub-object); :func:`promp_from_dict` accepts the whole validated file dict (or
just its ``promp`` sub-object).
"""
from typing import Any, Dict

import numpy as np

from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


def promp_body(promp: ProMP, compact: bool = False) -> Dict[str, Any]:
    """The "promp" sub-object: basis definition, weight mean, full weight covariance
    (``cov_w``, rows of numbers; ``compact``: ``cov_w_base64``, the same float64 values)."""
    from cdmp_ros.core.primitive_io import encode_covariance
    cov = np.asarray(promp.cov_w, dtype=float)
    return {
        'basis': {'type': 'normalized_rbf_phase',
                  'centers': [float(c) for c in promp.basis.centers],
                  'width': float(promp.basis.width)},
        'n_basis': int(promp.n_basis),
        'mean_w': np.asarray(promp.mean_w, dtype=float).tolist(),
        # Python floats, as float(v), or their exact float64 bytes
        **({'cov_w_base64': encode_covariance(cov)} if compact else {'cov_w': cov.tolist()}),
        'sigma_y': [float(v) for v in promp.sigma_y],
    }


def promp_to_dict(promp: ProMP, compact: bool = False) -> Dict[str, Any]:
    """File fields owned by the ProMP: ``duration``, ``promp``, (if any) ``metadata``, and
    ``limits`` when the metadata holds the position limits the ProMP was fitted or adapted
    within (``metadata['limits']``, ``{'lower': [...], 'upper': [...]}``); ``compact``: the
    covariance as ``cov_w_base64`` (:func:`promp_body`)."""
    d = {'duration': float(promp.duration)}
    meta = getattr(promp, 'metadata', None)
    if meta and isinstance(meta.get('limits'), dict):
        d['limits'] = {k: [float(v) for v in meta['limits'][k]] for k in ('lower', 'upper')}
    d['promp'] = promp_body(promp, compact)
    if meta:
        d['metadata'] = dict(meta)
    return d


def promp_from_dict(d: Dict[str, Any], n_dims: int = None, duration: float = None) -> ProMP:
    """Rebuild a ProMP from a primitive file dict (kind "promp") or its "promp" sub-object.

    A whole file dict is checked by :func:`cdmp_ros.core.primitive_io.validate_primitive_dict`
    first. Raises PrimitiveFileError naming the bad field."""
    if not isinstance(d, dict):
        raise PrimitiveFileError(f'promp: expected a JSON object, got {type(d).__name__}')
    if 'promp' in d:
        from cdmp_ros.core.primitive_io import validate_primitive_dict
        validate_primitive_dict(d)
    return promp_from_validated(d, n_dims, duration)


def promp_from_validated(d: Dict[str, Any], n_dims: int = None,
                         duration: float = None) -> ProMP:
    """:func:`promp_from_dict` without the file check (``d`` was validated already)."""
    joint_names = None
    if 'promp' in d:
        n_dims = d.get('n_dims', n_dims)
        duration = d.get('duration', duration)
        joint_names = d.get('joint_names')
        body = d['promp']
        prefix = 'primitive.promp'
    else:
        body = d
        prefix = 'promp'
    try:
        b = body['basis']
        basis = RbfBasis(tuple(b['centers']), float(b['width']))
        mean_w = np.asarray(body['mean_w'], dtype=float)
        M = basis.n_basis
        if mean_w.ndim != 1 or mean_w.size % M:
            raise PrimitiveFileError(f'{prefix}.mean_w: expected a multiple of n_basis={M} '
                                     f'values, got shape {mean_w.shape}')
        D = mean_w.size // M
        if n_dims is not None and int(n_dims) != D:
            raise PrimitiveFileError(f'{prefix}.mean_w: expected n_dims * n_basis = '
                                     f'{int(n_dims) * M} values, got {mean_w.size}')
        if 'n_basis' in body and int(body['n_basis']) != M:
            raise PrimitiveFileError(f'{prefix}.n_basis: expected len(basis.centers) = {M}, '
                                     f'got {body["n_basis"]}')
        from cdmp_ros.core.primitive_io import covariance_matrix
        p = ProMP(D, basis, mean_w, covariance_matrix(body, mean_w.size, prefix),
                  body.get('sigma_y'), 1.0 if duration is None else duration, joint_names)
        if isinstance(d.get('metadata'), dict):
            p.metadata = dict(d['metadata'])
        if isinstance(d.get('limits'), dict):  # kept for promp_to_dict (see there)
            p.metadata = dict(getattr(p, 'metadata', None) or {}, limits=dict(d['limits']))
        return p
    except KeyError as exc:
        raise PrimitiveFileError(f'{prefix}: missing field {exc.args[0]!r}') from None
    except PrimitiveFileError:
        raise
    except (ValidationError, TypeError, ValueError) as exc:
        raise PrimitiveFileError(f'{prefix}: {exc}') from None
