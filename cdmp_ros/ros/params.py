"""ROS parameters mirroring frozen config dataclasses 1:1.

:func:`declare_config` declares one parameter per dataclass field (``prefix.field`` for nested
configs), with a ``ParameterDescriptor`` carrying the description, the type, the range,
the choices and ``read_only``, all taken from the field metadata that
:func:`cdmp_ros.core.config_fields.param` writes (``description``, ``range=(lo, hi)``,
``choices``, ``read_only``): the ROS interface is declared in code, never read from a
docstring, and a parameter field without a description is a programming error
(:class:`TypeError` at declaration). The values are validated by the dataclass itself
(``__post_init__``): a bad startup value raises :class:`~cdmp_ros.core.errors.ValidationError`
(the node exits non-zero with the reason), a bad value set at run time is refused with the
reason (:class:`ConfigParameters`, through ``add_on_set_parameters_callback``).

Supported field types: bool, int, float, str, tuples of str and (non-empty) tuples of floats;
fields of other types (or whose default is None) are not exposed as parameters. A tuple of str
is a STRING_ARRAY parameter that always has a value, ``[]`` included (an empty list given in a
parameter file or by ``-p name:=[]`` arrives untyped and is read as ``[]``).
"""
import dataclasses
import math
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Type

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter

from cdmp_ros.core.errors import ValidationError

_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}


class FloatTuple(tuple):
    """The kind of a tuple-of-floats field (a DOUBLE_ARRAY parameter)."""


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _kind(f: dataclasses.Field):
    """The Python type of a field from its default (bool/int/float/str/tuple of str, or
    :class:`FloatTuple` for a non-empty tuple of floats)."""
    if f.default is not dataclasses.MISSING:
        default = f.default
    elif f.default_factory is not dataclasses.MISSING:
        default = f.default_factory()
    else:
        return None, None
    if isinstance(default, bool):
        return bool, default
    for t in (int, float, str):
        if type(default) is t:
            return t, default
    if isinstance(default, (tuple, list)) and all(isinstance(v, str) for v in default):
        return tuple, tuple(default)
    if isinstance(default, (tuple, list)) and default and all(map(_is_number, default)):
        return FloatTuple, tuple(float(v) for v in default)
    return None, None


def parameter_fields(cls) -> List[Tuple[dataclasses.Field, type, Any]]:
    """The (field, kind, default) of ``cls`` that are exposed as parameters."""
    out = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        kind, default = _kind(f)
        if kind is not None:
            out.append((f, kind, default))
    return out


def descriptor_for(cls, f: dataclasses.Field, kind: type, name: str) -> ParameterDescriptor:
    """The ParameterDescriptor of one field, from its metadata.

    Raises
    ------
    ValidationError
        The field has no ``description`` in its metadata (a config class defined without
        :func:`cdmp_ros.core.config_fields.param`).
    """
    meta = f.metadata
    text = meta.get('description')
    if not text:
        raise ValidationError(f'{cls.__name__}.{f.name}: a parameter field needs a description '
                              f'in its metadata (declare it with '
                              f'cdmp_ros.core.config_fields.param)')
    desc = ParameterDescriptor(name=name, description=text,
                               read_only=bool(meta.get('read_only', False)))
    if kind is tuple:
        desc.type = ParameterType.PARAMETER_STRING_ARRAY
    elif kind is FloatTuple:
        desc.type = ParameterType.PARAMETER_DOUBLE_ARRAY
    elif kind is float:
        # ints are accepted for floats ('rate:=1000'); the dataclass checks the value
        desc.dynamic_typing = True
    else:
        desc.type = _TYPES[kind]
    lo, hi = meta.get('range', (None, None))
    if lo is not None and hi is not None:
        range_text = f' Range [{lo}, {hi}].'
        if kind is int:
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        elif kind is float:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                            to_value=float(hi), step=0.0)]
        desc.description += range_text
    choices = meta.get('choices')
    if choices:
        desc.description += f' One of: {", ".join(map(str, choices))}.'
    return desc


def _coerce(name: str, kind: type, value: Any) -> Any:
    """A parameter value -> the field's Python type (ints for floats; lists -> tuples)."""
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if kind is tuple:
        if value is None:  # no value (declare_config gives every string array one)
            return ()
        if isinstance(value, (list, tuple)):
            return tuple(value)
        raise ValidationError(f'{name}: expected a list of strings, got {value!r}')
    if kind is FloatTuple:
        if isinstance(value, (list, tuple)) and all(map(_is_number, value)):
            return tuple(float(v) for v in value)
        raise ValidationError(f'{name}: expected a list of numbers, got {value!r}')
    return value


def _declare_string_array(node, name: str, default: List[str],
                          desc: ParameterDescriptor) -> Parameter:
    """Declare a STRING_ARRAY parameter that always has a value, ``[]`` included.

    rclpy infers the declared type from the value, and ``[]`` reads as a BYTE_ARRAY; declared by
    type alone, the parameter has no value (``ros2 param get``: "not set"), and so has one given
    an empty list in a parameter file or by ``-p name:=[]`` (untyped: NOT_SET). So it is
    declared by type with a writable descriptor, set to ``[]`` when it has no value, then given
    its final descriptor (``set_descriptor``: a read-only parameter refuses ``set_parameters``).
    """
    writable = ParameterDescriptor(description=desc.description)
    p = node.declare_parameter(name, default if default else Parameter.Type.STRING_ARRAY,
                               writable)
    if p.type_ == Parameter.Type.NOT_SET:
        result = node.set_parameters([Parameter(name, Parameter.Type.STRING_ARRAY, [])])[0]
        if not result.successful:
            raise ValidationError(f'parameter {name}: {result.reason}')
    node.set_descriptor(name, desc)
    return node.get_parameter(name)


def declare_config(node, cls: Type, prefix: str = '', overrides: Optional[Dict] = None):
    """Declare the parameters of ``cls`` on ``node`` and return the validated instance.

    Parameters
    ----------
    node : rclpy.node.Node
    cls : dataclass type
    prefix : str
        Parameter name prefix (``'repeller'`` gives ``repeller.gain``).
    overrides : dict, optional
        Defaults replacing the dataclass defaults (field name -> value).

    Raises
    ------
    ValidationError
        A value given at startup (``-p``, ``--params-file``) is of the wrong type or refused
        by the dataclass; the message names the parameter.
    """
    overrides = overrides or {}
    values = {}
    for f, kind, default in parameter_fields(cls):
        name = f'{prefix}.{f.name}' if prefix else f.name
        default = overrides.get(f.name, default)
        desc = descriptor_for(cls, f, kind, name)
        try:
            if kind is tuple:
                p = _declare_string_array(node, name, list(default), desc)
            else:
                value = list(default) if kind is FloatTuple else default
                p = node.declare_parameter(name, value, desc)
        except (ParameterException, TypeError, ValueError) as exc:
            raise ValidationError(f'parameter {name}: {exc}') from None
        values[f.name] = _coerce(name, kind, p.value)
    try:
        return cls(**values)
    except ValidationError as exc:
        raise ValidationError(f'parameters{" " + prefix if prefix else ""}: {exc}') from None
    except (TypeError, ValueError) as exc:
        raise ValidationError(f'parameters{" " + prefix if prefix else ""}: {exc}') from None


class ConfigParameters:
    """Declared parameters of several config dataclasses, validated again on every change.

    Parameters
    ----------
    node : rclpy.node.Node
    sections : sequence of (prefix, dataclass type) or (prefix, dataclass type, overrides)
        ``prefix`` '' for the top-level config.
    on_change : callable, optional
        ``on_change(configs)`` with the dict ``prefix -> new config`` after an accepted change;
        if it raises :class:`ValidationError` the change is refused with its message.
    """

    def __init__(self, node, sections: Sequence[tuple],
                 on_change: Optional[Callable[[Dict[str, Any]], None]] = None):
        self.node = node
        self.configs: Dict[str, Any] = {}
        self._fields: Dict[str, Tuple[str, str, type]] = {}  # param -> (prefix, field, kind)
        for section in sections:
            prefix, cls = section[0], section[1]
            overrides = section[2] if len(section) > 2 else None
            self.configs[prefix] = declare_config(node, cls, prefix, overrides)
            for f, kind, _ in parameter_fields(cls):
                name = f'{prefix}.{f.name}' if prefix else f.name
                self._fields[name] = (prefix, f.name, kind)
        self.on_change = on_change
        node.add_on_set_parameters_callback(self._on_set)

    def __getitem__(self, prefix: str):
        return self.configs[prefix]

    def _on_set(self, params: List[Parameter]) -> SetParametersResult:
        changes: Dict[str, Dict[str, Any]] = {}
        try:
            for p in params:
                if p.name not in self._fields:
                    continue
                prefix, field, kind = self._fields[p.name]
                value = _coerce(p.name, kind, p.value)
                if kind is float and not isinstance(value, float):
                    raise ValidationError(f'{p.name}: expected a number, got {p.value!r}')
                if kind is float and not math.isfinite(value):
                    raise ValidationError(f'{p.name}: expected a finite number, got {value}')
                changes.setdefault(prefix, {})[field] = value
            if not changes:
                return SetParametersResult(successful=True)
            new = dict(self.configs)
            for prefix, values in changes.items():
                try:
                    new[prefix] = dataclasses.replace(self.configs[prefix], **values)
                except (TypeError, ValueError) as exc:
                    raise ValidationError(str(exc)) from None
            if self.on_change is not None:
                self.on_change(new)
        except ValidationError as exc:
            self.node.get_logger().warning(f'parameter change refused: {exc}')
            return SetParametersResult(successful=False, reason=str(exc))
        self.configs = new
        return SetParametersResult(successful=True)
