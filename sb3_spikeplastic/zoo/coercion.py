"""Values checked against the type hints of a constructor's signature and coerced to them (integral floats to
``int``, ints to ``float``, tuples to lists), so that a mistake in a hyperparameter file is a one-line
``ValueError`` naming the key and what it accepts, raised before anything is built.
"""

from __future__ import annotations

import collections.abc
import difflib
import inspect
import math
import types
import typing
from typing import Any, Mapping, Sequence, Union


def _describe(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return "anything"
    if hint is type(None):
        return "null"
    if hint is bool:
        return "true or false"
    if hint is int:
        return "an integer"
    if hint is float:
        return "a number"
    if hint is str:
        return "a string"
    if hint in (dict, collections.abc.Mapping) or origin in (dict, collections.abc.Mapping):
        return "a mapping"
    if hint is tuple or hint is list:
        return "a list"
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if origin in (list, tuple, collections.abc.Sequence):
        return f"a list of {_describe(args[0]).removeprefix('an ').removeprefix('a ')}s" if args else "a list"
    if origin is typing.Literal:
        return "one of " + ", ".join(map(repr, args))
    return getattr(hint, "__name__", str(hint))


class _Mismatch(Exception):
    pass


def coerce(value: Any, hint: Any) -> Any:
    """``value`` converted to ``hint`` (integral floats -> int, ints -> float, tuples -> lists), or ``_Mismatch``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any or hint is inspect.Parameter.empty:
        return value
    if hint is type(None):
        if value is None:
            return None
        raise _Mismatch
    if origin in (Union, types.UnionType):
        for arg in sorted(args, key=lambda a: a is str):  # try str last: "1e3" strings stay numbers elsewhere
            try:
                return coerce(value, arg)
            except _Mismatch:
                pass
        raise _Mismatch
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise _Mismatch
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and math.isfinite(value) and value == int(value):
            return int(value)
        raise _Mismatch
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise _Mismatch
    if hint is str:
        if isinstance(value, str):
            return value
        raise _Mismatch
    if hint in (dict, collections.abc.Mapping) or origin in (dict, collections.abc.Mapping):
        if isinstance(value, dict):
            return value
        raise _Mismatch
    if hint in (tuple, list) or origin in (list, tuple, collections.abc.Sequence):
        if not isinstance(value, (list, tuple)):
            raise _Mismatch
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise _Mismatch
            return [coerce(v, a) for v, a in zip(value, args)]
        item = args[0] if args else Any
        return [coerce(v, item) for v in value]
    if origin is typing.Literal:
        if value in args:
            return value
        raise _Mismatch
    return value  # classes, callables...: left to the constructor


def check_value(name: str, value: Any, hint: Any) -> Any:
    """``value`` coerced to ``hint``; ``ValueError`` ``name=value must be <what hint accepts>`` otherwise."""
    try:
        return coerce(value, hint)
    except _Mismatch:
        raise ValueError(f"{name}={value!r} must be {_describe(hint)}") from None


def check_keys(what: str, values: Mapping, accepted: Sequence[str], context: str = "") -> None:
    """``ValueError`` naming the first key of ``values`` not in ``accepted``, the closest accepted one and all of
    them; ``what`` names the kind of key and ``context`` follows the key in the message."""
    unknown = [k for k in values if k not in accepted]
    if unknown:
        close = difflib.get_close_matches(str(unknown[0]), sorted(accepted), n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"unknown {what} {unknown[0]!r}{context}{hint}; accepted: {', '.join(sorted(accepted)) or 'none'}"
        )


def signature_hints(fn) -> dict[str, Any]:
    """The keyword arguments ``fn`` takes (not ``*args`` or ``**kwargs``) with their type hints (``Any`` where it
    has none or they cannot be resolved)."""
    params = inspect.signature(fn).parameters
    try:
        hints = typing.get_type_hints(fn)
    except Exception:  # unresolvable annotations: no type checks, keys still checked
        hints = {}
    return {name: hints.get(name, Any) for name, p in params.items() if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
