"""Field-by-field comparison of a recorded and a replayed message (``followbus replay --verify``): exact for
integers, strings, booleans and integer arrays, a tolerance for floats; header.seq, header.source, header.pub_ns
and the measured times a message type declares (``MEASURED``) are ignored."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from ..bus.codec import HEADER_KEY, DecodeError, frame_parts
from ..bus.schemas import Message, decode

IGNORED_HEADER_FIELDS = ("seq", "source", "pub_ns")
_IGNORED_HEADER_INDEXES = (0, 3, 4)  # their places in the header array (bus.codec.HEADER_FIELDS)

# --- field-by-field comparison ---------------------------------------------------------------------

@dataclass
class Tolerance:
    rtol: float = 1e-6
    atol: float = 1e-6


@dataclass
class Difference:
    field: str
    recorded: Any
    replayed: Any


def show_value(value: Any) -> Any:
    """A JSON-friendly rendering of a value in a report."""
    if isinstance(value, np.ndarray):
        return value.tolist() if value.size <= 16 else f"<array {value.dtype} {list(value.shape)}>"
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _first_index(mask: np.ndarray) -> str:
    idx = np.argwhere(~mask)[0]
    return "".join(f"[{int(i)}]" for i in idx)


def _diff_array(path: str, a: np.ndarray, b: np.ndarray, tol: Tolerance) -> Difference | None:
    if a.shape != b.shape:
        return Difference(f"{path}.shape", list(a.shape), list(b.shape))
    exact = a.dtype.kind in "biuSUO" and b.dtype.kind in "biuSUO"
    if a.dtype.kind != b.dtype.kind and not (a.dtype.kind in "iu" and b.dtype.kind in "iu"):
        return Difference(f"{path}.dtype", str(a.dtype), str(b.dtype))
    if a.size == 0:
        return None
    if exact:
        mask = np.asarray(a == b)
    else:
        mask = np.isclose(a.astype(np.float64), b.astype(np.float64), rtol=tol.rtol, atol=tol.atol, equal_nan=True)
    if mask.all():
        return None
    idx = np.argwhere(~mask)[0]
    where = tuple(int(i) for i in idx)
    return Difference(path + _first_index(mask), show_value(a[where]), show_value(b[where]))


def diff_values(path: str, a: Any, b: Any, tol: Tolerance) -> Difference | None:
    """The first difference between two decoded values, or None."""
    if a is None or b is None:
        return None if a is None and b is None else Difference(path, show_value(a), show_value(b))
    for applies, compare in _COMPARERS:
        if applies(a, b):
            return compare(path, a, b, tol)
    return None if (type(a) is type(b) and a == b) else Difference(path, show_value(a), show_value(b))


def _diff_any_array(path: str, a: Any, b: Any, tol: Tolerance) -> Difference | None:
    if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
        return Difference(path, show_value(a), show_value(b))
    return _diff_array(path, a, b, tol)


def _diff_exact(path: str, a: Any, b: Any, tol: Tolerance) -> Difference | None:
    return None if (type(a) is type(b) and a == b) else Difference(path, a, b)


def _diff_number(path: str, a: float, b: float, tol: Tolerance) -> Difference | None:
    if math.isnan(a) and math.isnan(b):
        return None
    return None if math.isclose(a, b, rel_tol=tol.rtol, abs_tol=tol.atol) else Difference(path, a, b)


def _diff_sequence(path: str, a: list | tuple, b: list | tuple, tol: Tolerance) -> Difference | None:
    if len(a) != len(b):
        return Difference(f"{path}.length", len(a), len(b))
    diffs = (diff_values(f"{path}[{i}]", x, y, tol) for i, (x, y) in enumerate(zip(a, b, strict=True)))
    return next((d for d in diffs if d is not None), None)


def _diff_mapping(path: str, a: dict, b: dict, tol: Tolerance) -> Difference | None:
    for k in sorted(set(a) | set(b), key=str):
        if k not in a or k not in b:
            return Difference(f"{path}.{k}", show_value(a.get(k)), show_value(b.get(k)))
        d = diff_values(f"{path}.{k}", a[k], b[k], tol)
        if d is not None:
            return d
    return None


# (applies to the pair, compares it), the first that applies decides: arrays, booleans (before ints: a bool is an
# int), integers exactly, numbers within the tolerance, sequences and mappings element by element
_COMPARERS: tuple[tuple[Callable[[Any, Any], bool], Callable[..., Difference | None]], ...] = (
    (lambda a, b: isinstance(a, np.ndarray) or isinstance(b, np.ndarray), _diff_any_array),
    (lambda a, b: isinstance(a, bool) or isinstance(b, bool), _diff_exact),
    (lambda a, b: isinstance(a, int) and isinstance(b, int), _diff_exact),
    (lambda a, b: isinstance(a, (int, float)) and isinstance(b, (int, float)), _diff_number),
    (lambda a, b: isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)), _diff_sequence),
    (lambda a, b: isinstance(a, dict) and isinstance(b, dict), _diff_mapping),
)


def diff_messages(recorded: Message, replayed: Message, tol: Tolerance) -> Difference | None:
    """First differing field of two messages; header.seq/source/pub_ns and measured times (``MEASURED``, e.g.
    Detections.infer_ms) are not compared."""
    if recorded.TYPE != replayed.TYPE:
        return Difference("type", recorded.TYPE, replayed.TYPE)
    for f in dataclasses.fields(recorded.header):
        if f.name in IGNORED_HEADER_FIELDS:
            continue
        a, b = getattr(recorded.header, f.name), getattr(replayed.header, f.name)
        if a != b:
            return Difference(f"header.{f.name}", a, b)
    for f in dataclasses.fields(recorded):
        if f.name == "header" or f.name in recorded.MEASURED:
            continue
        d = diff_values(f.name, getattr(recorded, f.name), getattr(replayed, f.name), tol)
        if d is not None:
            return d
    return None


def _same_bytes(a: bytes, b: bytes) -> bool:
    """Identical but for the ignored header fields, judged on the frames without decoding any array: most
    outputs of a replay are, and this costs microseconds where a field-by-field diff costs a decode."""
    try:
        (head_a, blobs_a), (head_b, blobs_b) = frame_parts(a), frame_parts(b)
        map_a, map_b = msgpack.unpackb(head_a), msgpack.unpackb(head_b)
        for m in (map_a, map_b):
            header = m[HEADER_KEY]
            for i in _IGNORED_HEADER_INDEXES:
                header[i] = None
    except Exception:  # malformed: the decoding diff reports it
        return False
    return map_a == map_b and blobs_a == blobs_b


def compare_output(recorded: bytes, replayed: bytes, tol: Tolerance) -> Difference | None:
    if _same_bytes(recorded, replayed):
        return None
    try:
        return diff_messages(decode(recorded), decode(replayed), tol)
    except DecodeError as exc:
        return Difference("<decode>", "decodable", str(exc))


