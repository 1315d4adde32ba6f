"""ProMP <-> primitive file (msg_schemas/primitive.schema.json, kind "promp").

:func:`cdmp_ros.core.primitive_io.primitive_to_dict` writes the common fields (format_version,
kind, joint_names, n_dims) and merges in what :func:`promp_to_dict` returns (``duration`` and
the ``promp`` sub-object); :func:`promp_from_validated` accepts the whole file dict validated
by :func:`cdmp_ros.core.primitive_io.validate_primitive_dict` (or just its ``promp``
sub-object; :func:`cdmp_ros.core.primitive_io.promp_from_dict` validates first). The weight
covariance is written as rows of numbers (``cov_w``) or in base64 (``cov_w_base64``,
:func:`encode_covariance`, :func:`covariance_matrix`).
"""
import base64
import binascii
from typing import Any, Dict

import numpy as np

from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.promp.promp import ProMP, RbfBasis


#: Encoding of ``promp.cov_w_base64``: the row-major entries as little-endian IEEE-754 float64,
#: in base64 (RFC 4648, padded). The adapter sends its adapted covariance this way: encoding
#: and decoding it is several times cheaper than writing and parsing rows of JSON numbers.
COV_DTYPE = '<f8'


def base64_length(n_entries: int) -> int:
    """Characters of the base64 text of ``n_entries`` float64 values (padded)."""
    return 4 * ((8 * n_entries + 2) // 3)


def encode_covariance(C) -> str:
    """``promp.cov_w_base64`` of the square matrix ``C`` (see :data:`COV_DTYPE`)."""
    C = np.ascontiguousarray(C, dtype=COV_DTYPE)
    return base64.b64encode(C.tobytes()).decode('ascii')


def covariance_matrix(body: Dict[str, Any], nw: int, prefix: str = 'primitive.promp'
                      ) -> np.ndarray:
    """Sigma_w (nw, nw) of a ``promp`` object, from ``cov_w`` (rows of numbers) or
    ``cov_w_base64``; the size is checked before anything is converted or decoded, then every
    entry must be finite and within [-1e12, 1e12] (the symmetry and semi-definiteness checks
    are :func:`~cdmp_ros.core.primitive_io.validate_primitive_dict`'s). Raises
    PrimitiveFileError naming the field."""
    why = f'(n_dims * len({prefix}.basis.centers) = {nw})'
    if ('cov_w' in body) == ('cov_w_base64' in body):
        raise PrimitiveFileError(f'{prefix}: expected exactly one of cov_w and cov_w_base64, '
                                 f'got {"both" if "cov_w" in body else "neither"}')
    if 'cov_w' in body:
        cov = body['cov_w']
        if not isinstance(cov, list) or len(cov) != nw:
            got = len(cov) if isinstance(cov, list) else type(cov).__name__
            raise PrimitiveFileError(f'{prefix}.cov_w: expected {nw} rows {why}, got {got}')
        for i, row in enumerate(cov):
            if not isinstance(row, list) or len(row) != nw:
                got = len(row) if isinstance(row, list) else type(row).__name__
                raise PrimitiveFileError(f'{prefix}.cov_w[{i}]: expected {nw} values {why}, '
                                         f'got {got}')
        try:
            return np.asarray(cov, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise PrimitiveFileError(f'{prefix}.cov_w: expected numbers ({exc})') from None
    text = body['cov_w_base64']
    size = base64_length(nw * nw)
    if not isinstance(text, str) or len(text) != size:
        got = f'{len(text)} characters' if isinstance(text, str) else type(text).__name__
        raise PrimitiveFileError(f'{prefix}.cov_w_base64: expected {size} characters (the '
                                 f'base64 of {nw} x {nw} float64 values {why}), got {got}')
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise PrimitiveFileError(f'{prefix}.cov_w_base64: not valid base64 ({exc})') from None
    C = np.frombuffer(raw, dtype=COV_DTYPE).astype(np.float64).reshape(nw, nw)
    bad = ~np.isfinite(C) | (np.abs(C) > 1e12)
    if np.any(bad):
        i, j = (int(v) for v in np.argwhere(bad)[0])
        raise PrimitiveFileError(f'{prefix}.cov_w_base64: entry [{i}][{j}]: expected a finite '
                                 f'number in [-1e12, 1e12], got {float(C[i, j])!r}')
    return C


def promp_body(promp: ProMP, compact: bool = False) -> Dict[str, Any]:
    """The "promp" sub-object: basis definition, weight mean, full weight covariance
    (``cov_w``, rows of numbers; ``compact``: ``cov_w_base64``, the same float64 values)."""
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


def promp_from_validated(d: Dict[str, Any], n_dims: int = None,
                         duration: float = None) -> ProMP:
    """Rebuild a ProMP from a primitive file dict (kind "promp") validated by
    :func:`~cdmp_ros.core.primitive_io.validate_primitive_dict`, or from its "promp"
    sub-object (sizes and covariance entries are checked here). Raises PrimitiveFileError
    naming the bad field."""
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
