"""Checks shared by the loaders of JSON documents (primitive files, constraint sets).

One function, :func:`check_document`, is the gate every loader goes through: it refuses
non-finite numbers (Python's :mod:`json` reads the non-standard tokens ``NaN``, ``Infinity`` and
``-Infinity``, which strict JSON cannot express) and then validates the document against its
JSON Schema, where the ranges of every numeric field are written down. The first problem is
raised as the loader's error class with a message naming the field by its path in the document
(for example ``primitive.dmp.weights[3][7]`` or ``constraint_set.constraints[2].alpha``), what
was expected and what was received. Checks that a schema cannot express (sizes that must agree
between fields, ordering, positive definiteness) live next to each loader's schema check and use
:func:`field_path` for their messages.
"""
import math
from typing import Any, Callable, Iterable, Optional, Sequence, Tuple, Type

import jsonschema
from jsonschema.exceptions import best_match

from cdmp_ros.core.errors import ValidationError

__all__ = ['check_document', 'field_path', 'short_repr']

#: Deepest nesting accepted in a document (the schemas nest a few levels; metadata is free).
MAX_DEPTH = 64

_VALIDATORS = {}
_TYPE_NAMES = {'number': 'a number', 'integer': 'an integer', 'array': 'a list',
               'object': 'an object', 'string': 'a string', 'boolean': 'true or false'}


def field_path(root: str, path: Iterable[Any]) -> str:
    """``root`` followed by the keys (``.key``) and list indices (``[i]``) of ``path``."""
    out = root
    for p in path:
        out += f'[{p}]' if isinstance(p, int) else f'.{p}'
    return out


def short_repr(value: Any, limit: int = 60) -> str:
    """``repr`` of a received value, cut to ``limit`` characters (a huge list stays short)."""
    if isinstance(value, (list, dict)) and len(value) > 8:
        kind = 'list' if isinstance(value, list) else 'object'
        return f'a {kind} of {len(value)} items'
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'


def _non_finite(doc: Any, path: list, skip: Sequence[str], depth: int = 0):
    """Path and value of the first non-finite float (or too deep nesting) in ``doc``."""
    if depth > MAX_DEPTH:
        return path, f'nesting deeper than {MAX_DEPTH} levels'
    if isinstance(doc, float):
        return (None if math.isfinite(doc) else (path, doc))
    if isinstance(doc, dict):
        items = ((k, v) for k, v in doc.items() if not (depth == 0 and k in skip))
    elif isinstance(doc, list):
        try:  # a list of numbers in one C-level pass: a NaN or an infinity makes the sum so
            if math.isfinite(sum(doc, 0.0)):  # (an overflow only sends it to the scan below)
                return None
        except TypeError:  # not only numbers
            pass
        items = enumerate(doc)
    else:
        return None
    for k, v in items:
        if isinstance(v, (dict, list, float)):
            bad = _non_finite(v, path + [k], skip, depth + 1)
            if bad is not None:
                return bad
    return None


#: Numeric arrays at least this long are checked by :func:`_compact` instead of jsonschema.
_COMPACT_MIN = 32
_NUMBER_KEYS = {'type', 'minimum', 'maximum', 'exclusiveMinimum', 'exclusiveMaximum',
                'description'}
_ARRAY_KEYS = {'type', 'items', 'minItems', 'maxItems', 'description'}


def _resolve(schema: Any, root_schema: dict) -> Any:
    """``schema`` with a local ``$ref`` (``#/$defs/name``) merged with its sibling keywords."""
    while isinstance(schema, dict) and '$ref' in schema:
        ref = schema['$ref']
        if not ref.startswith('#/'):
            return schema
        target = root_schema
        for part in ref[2:].split('/'):
            target = target[part]
        schema = {**target, **{k: v for k, v in schema.items() if k != '$ref'}}
    return schema


def _numbers_ok(values: list, item: dict) -> bool:
    """All of ``values`` are JSON numbers within the bounds of the ``item`` schema."""
    if not all(type(x) is float or type(x) is int for x in values):  # bool is not a number
        return False
    if not values:
        return True
    lo, hi = min(values), max(values)
    return (lo >= item.get('minimum', -math.inf) and hi <= item.get('maximum', math.inf)
            and lo > item.get('exclusiveMinimum', -math.inf)
            and hi < item.get('exclusiveMaximum', math.inf))


def _sized(values: list, schema: dict) -> bool:
    return schema.get('minItems', 0) <= len(values) <= schema.get('maxItems', math.inf)


def _number_array(schema: Any, root_schema: dict, depth: int) -> Optional[list]:
    """The chain of array schemas if ``schema`` is an array (of arrays, ``depth`` levels) of
    plain numbers with only range and size keywords, else None."""
    chain = []
    for _ in range(depth):
        schema = _resolve(schema, root_schema)
        if not (isinstance(schema, dict) and schema.get('type') == 'array'
                and set(schema) <= _ARRAY_KEYS and isinstance(schema.get('items'), dict)):
            return None
        chain.append(schema)
        schema = schema['items']
    schema = _resolve(schema, root_schema)
    if not (isinstance(schema, dict) and schema.get('type') == 'number'
            and set(schema) <= _NUMBER_KEYS):
        return None
    return chain + [schema]


def _compact(doc: Any, schema: Any, root_schema: dict) -> Any:
    """``doc`` with its long arrays of numbers (and matrices of them) checked here, against
    their schema's type, range and size keywords, and replaced by a short prefix that the
    schema accepts alike; everything else is left for jsonschema (one pass over a ProMP's
    covariance in C-level ``min``/``max`` instead of a jsonschema call per number). An array
    that fails is kept whole, so jsonschema reports it with its usual message."""
    schema = _resolve(schema, root_schema)
    if not isinstance(schema, dict):
        return doc
    if isinstance(doc, list) and len(doc) >= _COMPACT_MIN:
        vector = _number_array(schema, root_schema, 1)
        if vector is not None:
            if _sized(doc, vector[0]) and _numbers_ok(doc, vector[1]):
                return doc[:max(vector[0].get('minItems', 1), 1)]
            return doc
        matrix = _number_array(schema, root_schema, 2)
        if matrix is not None:
            rows_ok = _sized(doc, matrix[0]) and all(
                isinstance(r, list) and _sized(r, matrix[1]) and _numbers_ok(r, matrix[2])
                for r in doc)
            if rows_ok:
                keep = max(matrix[1].get('minItems', 1), 1)
                return [r[:keep] for r in doc[:max(matrix[0].get('minItems', 1), 1)]]
            return doc
    if isinstance(doc, dict) and isinstance(schema.get('properties'), dict):
        props = schema['properties']
        out = None
        for k, v in doc.items():
            if k in props and isinstance(v, (list, dict)):
                c = _compact(v, props[k], root_schema)
                if c is not v:
                    out = dict(doc) if out is None else out
                    out[k] = c
        return doc if out is None else out
    if isinstance(doc, list) and isinstance(schema.get('items'), dict):
        out = [_compact(v, schema['items'], root_schema) if isinstance(v, (list, dict)) else v
               for v in doc]
        return doc if all(a is b for a, b in zip(out, doc)) else out
    return doc


def _closest(e: jsonschema.ValidationError) -> jsonschema.ValidationError:
    """The error of the form a oneOf / anyOf instance was meant to have: the first form whose
    required fields the instance has (else jsonschema's best match)."""
    inst = e.instance
    if isinstance(inst, dict):
        for i, form in enumerate(e.validator_value):
            if isinstance(form, dict) and set(form.get('required', ())) & set(inst):
                subs = [c for c in e.context if c.relative_schema_path
                        and c.relative_schema_path[0] == i]
                if subs:
                    return max(subs, key=lambda c: len(c.absolute_path))
    return best_match(e.context)


def _describe(e: jsonschema.ValidationError, root: str) -> Tuple[list, str]:
    """Path of the offending field and ``expected ..., got ...`` for one schema error."""
    v, vv, inst = e.validator, e.validator_value, e.instance
    path = list(e.absolute_path)
    if v == 'required':
        missing = [k for k in vv if isinstance(inst, dict) and k not in inst]
        return path + missing[:1], 'missing (a required field)'
    if v == 'additionalProperties':
        allowed = set(e.schema.get('properties', {}))
        extra = sorted(k for k in inst if k not in allowed)
        return path + extra[:1], f'unexpected field (expected one of {sorted(allowed)})'
    if v == 'type':
        names = vv if isinstance(vv, list) else [vv]
        expected = ' or '.join(_TYPE_NAMES.get(n, n) for n in names)
        return path, f'expected {expected}, got {short_repr(inst)}'
    ops = {'minimum': '>=', 'exclusiveMinimum': '>', 'maximum': '<=',
           'exclusiveMaximum': '<'}
    if v in ops:
        return path, f'expected a value {ops[v]} {vv}, got {short_repr(inst)}'
    if v in ('minItems', 'maxItems'):
        word = 'at least' if v == 'minItems' else 'at most'
        return path, f'expected {word} {vv} items, got {len(inst)}'
    if v in ('minLength', 'maxLength'):
        word = 'at least' if v == 'minLength' else 'at most'
        return path, f'expected a string of {word} {vv} characters, got {short_repr(inst)}'
    if v == 'enum':
        return path, f'expected one of {vv}, got {short_repr(inst)}'
    if v == 'const':
        return path, f'expected {vv!r}, got {short_repr(inst)}'
    if v == 'uniqueItems':
        seen = []
        for j, item in enumerate(inst):
            if item in seen:
                first = seen.index(item)
                return path + [j], (f'expected unique items, got a repeat of '
                                    f'{field_path(root, path + [first])} ({short_repr(item)})')
            seen.append(item)
        return path, f'expected unique items, got {short_repr(inst)}'
    if v in ('anyOf', 'oneOf') and all(isinstance(s, dict) and s.keys() == {'required'}
                                       for s in vv):
        names = [n for s in vv for n in s['required']]
        kind = f' (type {inst["type"]!r})' if isinstance(inst, dict) and 'type' in inst else ''
        how = 'at least' if v == 'anyOf' else 'exactly'
        return path, f'expected {how} one of the fields {names}{kind}'
    if v in ('oneOf', 'anyOf') and e.context:
        sub_path, sub_text = _describe(_closest(e), root)
        return path, (f'matches none of its allowed forms (closest: '
                      f'{field_path(root, sub_path)}: {sub_text})')
    return path, short_repr(e.message, 200)


def check_document(doc: Any, schema: dict, root: str, error: Type[ValidationError],
                   skip: Sequence[str] = (),
                   order: Optional[Callable[[jsonschema.ValidationError], Any]] = None,
                   label: Optional[Callable[[list], str]] = None) -> None:
    """Refuse non-finite numbers, then validate ``doc`` against ``schema``.

    Parameters
    ----------
    doc : any
        The decoded JSON document.
    schema : dict
        Its JSON Schema (draft 2020-12); numeric ranges are written there.
    root : str
        Name of the document in messages (``primitive``, ``constraint_set``).
    error : type
        The :class:`~cdmp_ros.core.errors.ValidationError` subclass to raise.
    skip : sequence of str
        Top-level keys exempt from the finiteness check (free-form ``metadata``).
    order : callable, optional
        Sort key choosing which schema error to report first (default: the shallowest).
    label : callable, optional
        ``label(path) -> str`` appended to the path in messages (e.g. a constraint's name).

    Raises
    ------
    ValidationError
        Of class ``error``; the message starts with the path of the offending field.
    """
    if not isinstance(doc, dict):
        raise error(f'{root}: expected a JSON object, got {type(doc).__name__}')
    bad = _non_finite(doc, [], skip)
    if bad is not None:
        where, value = bad
        text = (value if isinstance(value, str) else f'expected a finite number, got {value!r} '
                '(NaN and Infinity are not JSON numbers)')
        raise error(f'{field_path(root, where)}{label(where) if label else ""}: {text}')
    key = id(schema)
    if key not in _VALIDATORS:
        _VALIDATORS[key] = (schema, jsonschema.Draft202012Validator(schema))
    validator = _VALIDATORS[key][1]
    errors = list(validator.iter_errors(_compact(doc, schema, schema)))
    if errors:  # the full document, so that paths and messages are jsonschema's own
        errors = list(validator.iter_errors(doc))
    if errors:
        errors.sort(key=order or (lambda e: (len(e.absolute_path), e.message)))
        where, text = _describe(errors[0], root)
        raise error(f'{field_path(root, where)}{label(where) if label else ""}: {text}')
