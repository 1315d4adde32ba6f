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
        items = enumerate(doc)
    else:
        return None
    for k, v in items:
        if isinstance(v, (dict, list, float)):
            bad = _non_finite(v, path + [k], skip, depth + 1)
            if bad is not None:
                return bad
    return None


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
    if v == 'anyOf' and all(isinstance(s, dict) and s.keys() == {'required'} for s in vv):
        names = [n for s in vv for n in s['required']]
        kind = f' (type {inst["type"]!r})' if isinstance(inst, dict) and 'type' in inst else ''
        return path, f'expected at least one of the fields {names}{kind}'
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
    errors = list(validator.iter_errors(doc))
    if errors:
        errors.sort(key=order or (lambda e: (len(e.absolute_path), e.message)))
        where, text = _describe(errors[0], root)
        raise error(f'{field_path(root, where)}{label(where) if label else ""}: {text}')
