"""A node's parameters: graph.yaml's ``params`` mapping read into the dataclass(es) its class names (``Node.Params``).

Every key must be a field (a key no class declares is an error at its line), every value of the field's type
(bus/typecheck.py) and finite. A params class checks its own ranges in ``__post_init__`` (a ``ValueError`` with an
attribute ``key`` points at that parameter's line), and may define ``check()``: what its node would open (a file,
a device), run by ``followbus check``, ``launch`` and ``demo`` before anything starts, not on every validation.

A field's ``metadata`` says more of it to the tools:

- ``live``: ``followbus param set`` may change it while the node runs (bus/live_params.py): only for a parameter
  the node's code reads afresh from its params object on every message;
- ``was``: its old name; a graph (or a recording's graph) written before the rename still loads, with a warning;
- ``state_file``: a file the node keeps its state in across restarts: a replay clears it, so it neither starts
  from nor overwrites the live graph's state.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import typing
from dataclasses import dataclass
from typing import Any

from .typecheck import TypeMismatch, conform

ParamsSpec = typing.Union[type, tuple[type, ...]]  # noqa: UP007  # Node.Params: one dataclass or a tuple of them


class ParamError(ValueError):
    """A node parameter problem; ``key`` lets the caller point at the graph.yaml line."""

    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(message)


@dataclass
class NoParams:
    pass


def params_from_dict(cls: type, data: dict[str, Any]) -> Any:
    """Build a params dataclass from a dict, rejecting unknown keys and wrong types."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            raise ParamError(key, f"unknown parameter {key!r} (known: {', '.join(sorted(names)) or 'none'})")
    kwargs = {}
    for key, value in data.items():
        kwargs[key] = _coerce(value, hints[key], key)
    try:
        return cls(**kwargs)
    except ValueError as exc:
        # A params class's own range check that names its parameter (an attribute ``key``) points at its line.
        key = getattr(exc, "key", None)
        if isinstance(exc, ParamError) or not isinstance(key, str):
            raise
        raise ParamError(key, str(exc)) from exc


def split_params(raw: dict[str, Any], *classes: type) -> tuple[Any, ...]:
    """One params dataclass per class from one flat ``params`` mapping: each key goes to the first class with a
    field of that name; a key no class has is a ParamError naming it (so validation points at its line)."""
    parts: list[dict[str, Any]] = [{} for _ in classes]
    owners = [{f.name for f in dataclasses.fields(cls)} for cls in classes]
    for key, value in raw.items():
        owner = next((i for i, names in enumerate(owners) if key in names), None)
        if owner is None:
            known = ", ".join(sorted(set().union(*owners))) or "none"
            raise ParamError(key, f"unknown parameter {key!r} (known: {known})")
        parts[owner][key] = value
    return tuple(params_from_dict(cls, part) for cls, part in zip(classes, parts, strict=True))


def _renamed(raw: dict[str, Any], renamed: dict[str, str]) -> dict[str, Any]:
    """``raw`` with the old names of renamed parameters replaced by the new ones (the new name wins if both)."""
    old = [key for key in raw if key in renamed]
    for key in old:
        logging.getLogger(__name__).warning("parameter %r is now called %r", key, renamed[key])
    return {renamed.get(key, key): value for key, value in raw.items() if key not in old or renamed[key] not in raw}


def _non_finite(value: Any) -> bool:
    """Whether a parameter value holds NaN or ±inf anywhere (in a list or mapping too)."""
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return any(_non_finite(v) for v in value)
    if isinstance(value, dict):
        return any(_non_finite(v) for v in value.values())
    return False


# A number YAML 1.1 reads as text (1e-3, 1e309: its floats need a dot), which YAML 1.2 and Python read as a number.
_EXPONENT_NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$")


def _coerce(value: Any, hint: Any, key: str) -> Any:
    # No parameter means anything with NaN or inf: a NaN gate never follows, an infinite timeout never fires.
    if _non_finite(value):
        raise ParamError(key, f"parameter {key!r} must be finite, not {value!r}")
    try:
        return conform(value, hint)
    except TypeMismatch as exc:
        if isinstance(value, str) and _EXPONENT_NUMBER.match(value.strip()):
            return _coerce_exponent(value, hint, key)
        raise ParamError(key, f"parameter {key!r} must be {exc.expected}, not {type(value).__name__} "
                              f"({value!r})") from None


def _coerce_exponent(text: str, hint: Any, key: str) -> Any:
    """``1e-3`` for a number parameter: the number it says, or a ParamError when no float holds it (1e309)."""
    number = float(text)
    if not math.isfinite(number):
        raise ParamError(key, f"parameter {key!r}: {text.strip()} is beyond the range of a float (at most ~1.8e308)")
    try:
        return conform(number, hint)
    except TypeMismatch as exc:
        raise ParamError(key, f"parameter {key!r} must be {exc.expected}, not {text.strip()}") from None


def params_classes(spec: ParamsSpec) -> tuple[type, ...]:
    """The dataclasses whose fields are a node's graph.yaml ``params`` (``followbus schema`` documents them,
    ``followbus param`` reads and sets them)."""
    return spec if isinstance(spec, tuple) else (spec,)


def param_names(spec: ParamsSpec) -> frozenset[str]:
    """Every parameter a node reads (its params classes' fields)."""
    return frozenset(f.name for c in params_classes(spec) for f in dataclasses.fields(c))


def marked(spec: ParamsSpec, key: str) -> dict[str, Any]:
    """The parameters whose field metadata has ``key`` (live, was, state_file, ...), with its value."""
    return {f.name: f.metadata[key] for c in params_classes(spec) for f in dataclasses.fields(c) if key in f.metadata}


def parse_params(spec: ParamsSpec, raw: dict[str, Any]) -> Any:
    """A node's params from its graph.yaml mapping (ParamError naming the key): one instance, or with a tuple of
    classes one instance of each, the mapping split by field name."""
    renamed = {old: new for new, old in marked(spec, "was").items()}
    raw = _renamed(raw, renamed)
    if isinstance(spec, tuple):
        return split_params(raw, *spec)
    return params_from_dict(spec, raw)
