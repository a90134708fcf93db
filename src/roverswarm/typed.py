"""Types of config values from files: a sweep file or a run's ``config.json`` can hold any
YAML/JSON value, and a wrong-typed one (``seeds: 2.0``, ``hidden: 64``) must be refused by
name before anything trains, not fail later in the middle of a run.

:func:`check_types` walks a (nested) config dataclass and compares every value with its
field's annotation: ``bool``, ``int`` (not a bool), ``float`` (an int is accepted), ``str``,
``None``, unions, ``Literal`` (its values' type; the values themselves are checked by
:func:`roverswarm.config.validate`) and ``tuple[int, ...]``.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing

from roverswarm.errors import UserError


def _describe(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Annotated:
        return _describe(args[0])
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if origin is typing.Literal:
        return "one of " + ", ".join(map(str, args))
    if origin is tuple:
        return "a list of " + {int: "integers", float: "numbers"}.get(args[0], str(args[0]))
    return {bool: "true or false", int: "an integer", float: "a number", str: "text", type(None): "null"}.get(
        hint, str(hint)
    )


def matches(value: object, hint) -> bool:
    """Whether ``value`` has the type annotation ``hint`` (see the module docstring)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Annotated:
        return matches(value, args[0])
    if origin in (typing.Union, types.UnionType):
        return any(matches(value, a) for a in args)
    if origin is typing.Literal:
        return any(type(value) is type(a) for a in args)
    if origin is tuple:
        return isinstance(value, tuple) and all(matches(v, args[0]) for v in value)
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is type(None):
        return value is None
    if isinstance(hint, type):
        return isinstance(value, hint)
    return True  # an annotation this check does not know: left to validate()


@functools.cache
def _hints(cls) -> dict[str, object]:
    return typing.get_type_hints(cls, include_extras=True)


def check_types(config, where: str) -> None:
    """:class:`UserError` naming the first field of ``config`` (and its nested configs) whose
    value does not have its annotated type; ``where`` says where the value came from."""
    hints = _hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            check_types(value, where)
        elif not matches(value, hints[field.name]):
            raise UserError(f"{where}: {field.name} must be {_describe(hints[field.name])}, got {value!r}")
