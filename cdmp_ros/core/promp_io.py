"""ProMP <-> the "promp" property of a primitive file (msg_schemas/primitive.schema.json).

The common fields (kind, joint_names, n_dims, duration, format_version) are written and read
by cdmp_ros.core.primitive_io; these functions handle only the ProMP parameters.
"""
from typing import Any, Dict

import numpy as np

from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.promp import ProMP, RbfBasis


def promp_to_dict(promp: ProMP) -> Dict[str, Any]:
    """The "promp" sub-object: basis definition, weight mean, full weight covariance."""
    return {
        'basis': {'type': 'normalized_rbf_phase',
                  'centers': [float(c) for c in promp.basis.centers],
                  'width': float(promp.basis.width)},
        'n_basis': int(promp.n_basis),
        'mean_w': [float(v) for v in promp.mean_w],
        'cov_w': [[float(v) for v in r] for r in promp.cov_w],
        'sigma_y': [float(v) for v in promp.sigma_y],
    }


def promp_from_dict(d: Dict[str, Any], n_dims: int = None, duration: float = 1.0) -> ProMP:
    """Rebuild a ProMP from its "promp" sub-object (and, if given, the file's n_dims and
    duration). Raises PrimitiveFileError naming the bad field."""
    try:
        b = d['basis']
        basis = RbfBasis(tuple(b['centers']), float(b['width']))
        mean_w = np.asarray(d['mean_w'], dtype=float)
        M = basis.n_basis
        if mean_w.ndim != 1 or mean_w.size % M:
            raise PrimitiveFileError(f'promp.mean_w: expected a multiple of n_basis={M} '
                                     f'values, got shape {mean_w.shape}')
        D = mean_w.size // M
        if n_dims is not None and int(n_dims) != D:
            raise PrimitiveFileError(f'promp.mean_w: expected n_dims * n_basis = '
                                     f'{int(n_dims) * M} values, got {mean_w.size}')
        if 'n_basis' in d and int(d['n_basis']) != M:
            raise PrimitiveFileError(f'promp.n_basis: expected len(basis.centers) = {M}, '
                                     f'got {d["n_basis"]}')
        return ProMP(D, basis, mean_w, np.asarray(d['cov_w'], dtype=float),
                     d.get('sigma_y'), duration)
    except KeyError as exc:
        raise PrimitiveFileError(f'promp: missing field {exc.args[0]!r}') from None
    except PrimitiveFileError:
        raise
    except (ValidationError, TypeError, ValueError) as exc:
        raise PrimitiveFileError(f'promp: {exc}') from None
