"""Input validation helpers: every failure names the variable, the expectation and what came."""
from typing import List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdmp_ros.core.errors import ValidationError


def as_array(name: str, value: ArrayLike, shape: Optional[Sequence[Optional[int]]] = None,
             finite: bool = True) -> NDArray[np.float64]:
    """Convert ``value`` to a float64 array and check its shape and finiteness.

    Parameters
    ----------
    name : str
        Name of the variable, used in error messages.
    value : array-like
        The value to check.
    shape : sequence of int or None, optional
        Expected shape; ``None`` entries match any length.
    finite : bool
        Reject NaN and infinite entries.

    Raises
    ------
    ValidationError
        If the value is not numeric, has the wrong shape or non-finite entries.
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValidationError(f'{name}: expected numbers, got {type(value).__name__} '
                              f'({exc})') from None
    if shape is not None:
        ok = arr.ndim == len(shape) and all(
            e is None or e == a for e, a in zip(shape, arr.shape))
        if not ok:
            expected = '(' + ', '.join('*' if e is None else str(e) for e in shape) + ')'
            raise ValidationError(f'{name}: expected shape {expected}, got {arr.shape}')
    if finite and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))
        raise ValidationError(f'{name}: expected finite values, got {arr[tuple(bad[0])]} '
                              f'at index {tuple(int(i) for i in bad[0])}')
    return arr


def check_positive(name: str, value: float, allow_zero: bool = False) -> float:
    """Check that a scalar is finite and positive (or non-negative)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValidationError(f'{name}: expected a number, got {value!r}') from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        kind = 'non-negative' if allow_zero else 'positive'
        raise ValidationError(f'{name}: expected a finite {kind} number, got {value!r}')
    return v


def name_permutation(expected: Sequence[str], got: Sequence[str], what: str,
                     error: type = ValidationError) -> List[int]:
    """Index into ``got`` of each of ``expected``, when ``got`` holds the names of ``expected``
    in any order; else raises ``error`` ``'<what> <expected>, got <got> (missing [...],
    unknown [...])'``, naming the names of ``expected`` not in ``got`` and those of ``got``
    not in ``expected``."""
    missing = [n for n in expected if n not in got]
    unknown = [n for n in got if n not in expected]
    if missing or unknown or len(got) != len(expected):
        raise error(f'{what} {list(expected)}, got {list(got)} (missing {missing}, unknown '
                    f'{unknown})')
    return [list(got).index(n) for n in expected]


def lookup(what: str, table, key, choices=None, sort: bool = False):
    """``table[key]``; a missing key raises ValidationError ``'<what>: expected one of
    <names>, got <key!r>'``, the names being the keys of ``table`` (or ``choices``) in their
    order, or sorted with ``sort``."""
    try:
        return table[key]
    except KeyError:
        names = table if choices is None else choices
        raise ValidationError(f'{what}: expected one of '
                              f'{sorted(names) if sort else list(names)}, got {key!r}') from None


def check_limits(y_min: ArrayLike, y_max: ArrayLike, n_dims: Optional[int] = None
                 ) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate per-joint lower/upper limits (finite, lower < upper)."""
    lo = as_array('y_min', y_min, (n_dims,) if n_dims is not None else (None,))
    hi = as_array('y_max', y_max, lo.shape)
    bad = np.flatnonzero(~(hi > lo))
    if bad.size:
        i = int(bad[0])
        raise ValidationError(f'limits: expected y_min < y_max for every joint, got '
                              f'y_min[{i}]={lo[i]} >= y_max[{i}]={hi[i]}')
    return lo, hi
