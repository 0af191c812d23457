"""One type checker for values that come from outside: decoded message fields (bus.schemas) and node
parameters from graph.yaml or ``--set`` (bus.node_params). Both meet the same annotations (float, int, bool, str,
arrays, lists, maps, optionals), so they are checked by the same rules: a bool is never a number, an int
becomes a float where a float is wanted, a list stands for a list or a tuple."""

from __future__ import annotations

import types
import typing
from typing import Any, Union

import numpy as np


class TypeMismatch(ValueError):
    """``value`` does not fit ``expected`` (a readable name of the annotation)."""

    def __init__(self, expected: str, value: Any):
        self.expected = expected
        self.value = value
        super().__init__(f"expected {expected}, got {type(value).__name__}")


def type_name(hint: Any) -> str:
    if typing.get_origin(hint) is typing.Literal:
        return " or ".join(repr(a) for a in typing.get_args(hint))
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def conform(value: Any, hint: Any) -> Any:
    """``value`` checked against the annotation ``hint`` and lightly coerced (int → float, list → tuple
    where a tuple is wanted); raises :class:`TypeMismatch`. Annotations other than the ones above
    (a nested message type, say) are the caller's business: the value passes unchanged."""
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        return _conform_union(value, typing.get_args(hint))
    if origin is typing.Literal:
        if value not in typing.get_args(hint):
            raise TypeMismatch(" or ".join(repr(a) for a in typing.get_args(hint)), value)
        return value
    if hint is Any:
        return value
    if hint is float:
        return _conform_float(value)
    if hint is int:
        return _conform_int(value)
    if hint in (bool, str):
        return _conform_instance(value, hint, hint.__name__)
    if hint is np.ndarray:
        return _conform_instance(value, np.ndarray, "array")
    return _conform_container(value, origin or hint)


def _conform_union(value: Any, args: tuple[Any, ...]) -> Any:
    """The first member of the union that ``value`` fits wins; None passes only an optional."""
    if value is None and type(None) in args:
        return None
    for arg in args:
        if arg is type(None):
            continue
        try:
            return conform(value, arg)
        except TypeMismatch:
            continue
    raise TypeMismatch(" or ".join(type_name(a) for a in args), value)


def _conform_float(value: Any) -> float:
    # bool is a subclass of int, but True is never a number here
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeMismatch("float", value)
    return float(value)


def _conform_int(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeMismatch("int", value)
    return value


def _conform_instance(value: Any, kind: type, expected: str) -> Any:
    if not isinstance(value, kind):
        raise TypeMismatch(expected, value)
    return value


def _conform_container(value: Any, container: Any) -> Any:
    """Lists, tuples and maps (bare or parameterised: their items are not checked here); anything
    else passes unchanged."""
    if container in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise TypeMismatch(container.__name__, value)
        return list(value) if container is list else tuple(value)
    if container is dict:
        return _conform_instance(value, dict, "map")
    return value
