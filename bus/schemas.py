"""The message base, its registry and codec binding, and generic validation: what every payload on the bus shares.

Every message starts with a :class:`Header`. ``stamp_ns`` is the capture stamp of the camera
frame the message derives from (so latency = now - stamp_ns, and replays are deterministic),
``frame_seq`` that frame's sequence number, ``pub_ns`` the wall-clock time of publication
(per-edge latency; never compared by replay verification). ``epoch_ns`` names the numbering
``frame_seq`` belongs to (the start time of the capture session that numbered the frame), so a
restarted camera that counts from 0 again is told apart from stale frames. ``feedback`` is the
provenance of a frame-synchronised output: for each feedback input (``offset: -1``) the frame_seq of
the message the node used (-1: none), and -1 for each optional same-frame input the set went on without,
so a replay reproduces what the live run did.

The application's messages are its own types (followbus's catalogue is the top-level ``msgs`` package, as ROS 2
keeps messages in interface packages and rclpy type-agnostic): a subclass of :class:`Message` that sets ``TYPE``
registers itself, and the importing program makes its types decodable. This module keeps only what the bus
itself publishes: camera frames (the runtime's frame lane and sync), node status, diagnostics ticks and replay
hints.

Messages are checked twice on the way in: :func:`decode` checks the wire types, :func:`validate`
the values: generic rules here (header in range, every float finite, the node never sees a NaN), then the
type's own :meth:`Message.check` (shapes, ranges, known enumerations); both raise DecodeError, which
subscribers count and drop, so a malformed or poisoned message never reaches a node.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import numpy as np

# Header is part of the frame layout, which bus/codec.py owns; re-exported here with the messages.
from .codec import (
    INT_LIMIT,
    INT_MIN,
    DecodeError,
    Header,
    decode_message,
    encode_message,
    encode_message_parts,
    header_from_wire,
    wire_value,
)
from .typecheck import TypeMismatch, conform

SCHEMA_VERSION = 1


# Message type name -> class: every subclass of Message that sets TYPE registers itself (a node may define its
# own message type in its module; importing the module makes it decodable).
SCHEMAS: dict[str, type[Message]] = {}


@dataclass
class Message:
    """Base of all payloads; subclasses set TYPE and add fields."""

    TYPE: ClassVar[str] = ""
    # Fields that measure the run that produced the message (a wall time): `followbus replay` does not compare them.
    MEASURED: ClassVar[frozenset[str]] = frozenset()
    # Fields added after recordings with this schema version were made: absent in such a message, they decode as
    # their default (an old recording stays readable).
    ADDED: ClassVar[frozenset[str]] = frozenset()
    # Free-form payloads (diagnostics): :func:`validate` checks their header only.
    FREE_FORM: ClassVar[bool] = False
    header: Header = field(default_factory=Header)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("TYPE")
        if not name:
            return
        known = SCHEMAS.get(name)
        if known is not None and (known.__module__, known.__qualname__) != (cls.__module__, cls.__qualname__):
            raise TypeError(f"message type {name!r} is defined twice: {known.__module__}.{known.__qualname__} "
                            f"and {cls.__module__}.{cls.__qualname__}")
        SCHEMAS[name] = cls

    def encode(self) -> bytes:
        return encode(self)

    def check(self) -> None:
        """The type's own value checks, after the generic ones of :func:`validate`: raise DecodeError (use
        :func:`require` and :func:`check_shape`) on a value a consumer must never see. Nothing by default."""


@dataclass
class Frame(Message):
    """A camera image. ``encoding`` is ``bgr8`` (data H×W×3 uint8) or ``jpeg`` (data 1-D uint8)."""

    TYPE: ClassVar[str] = "Frame"
    width: int = 0
    height: int = 0
    encoding: str = "bgr8"
    data: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), np.uint8))
    # Size of the camera frame this image was scaled from (previews); 0: the image's own size.
    # Boxes on the bus are in camera-frame pixels, so a viewer scales them by width / source_width.
    source_width: int = 0
    source_height: int = 0

    def check(self) -> None:
        if self.encoding == "bgr8":
            require(self.data.dtype == np.uint8 and self.data.shape == (self.height, self.width, 3), self,
                    f"bgr8 data {self.data.dtype} {list(self.data.shape)} does not match {self.width}x{self.height}")
        elif self.encoding == "jpeg":
            require(self.data.dtype == np.uint8 and self.data.ndim == 1, self, "jpeg data must be 1-D uint8")
        else:
            raise DecodeError(f"{self.TYPE}: unknown encoding {self.encoding!r}")


@dataclass
class NodeStatus(Message):
    """Once-a-second health and per-topic statistics of one node."""

    TYPE: ClassVar[str] = "NodeStatus"
    FREE_FORM: ClassVar[bool] = True
    node: str = ""
    pid: int = 0
    uptime_s: float = 0.0
    state: str = "running"
    # topic key -> {"direction": "in"/"out", "count", "rate_hz", "latency_p50_ms", "latency_p99_ms",
    #               "drops", "decode_errors"}
    topics: dict[str, dict[str, Any]] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class Tick(Message):
    """Diagnostic message (bus checks, benchmarks): a counter and an optional payload."""

    TYPE: ClassVar[str] = "Tick"
    FREE_FORM: ClassVar[bool] = True
    value: int = 0
    payload: np.ndarray | None = None


@dataclass
class ReplayHint(Message):
    """What the live run did with frame ``header.frame_seq``, sent by ``followbus replay`` before the frame's
    inputs so the replayed node does the same: skip it (the live node skipped it: lag bound, lost input), or
    join exactly these feedback frames (``header.feedback`` of the recorded output; -1: none) and go on without
    the optional same-frame inputs marked -1."""

    TYPE: ClassVar[str] = "ReplayHint"
    skip: bool = False
    feedback: dict[str, int] = field(default_factory=dict)


M = TypeVar("M", bound=Message)


def _hints(cls: type) -> dict[str, Any]:
    cached = _HINTS.get(cls)
    if cached is None:
        cached = typing.get_type_hints(cls)
        _HINTS[cls] = cached
    return cached


_HINTS: dict[type, dict[str, Any]] = {}
# Annotations a value of exactly that type satisfies unchanged (conform would return it as it is).
_PASS_THROUGH = frozenset({int, float, str, bool, np.ndarray})
_FIELD_PLANS: dict[type, tuple[tuple[str, Any, Any], ...]] = {}


def _field_plan(cls: type) -> tuple[tuple[str, Any, Any], ...]:
    """(name, annotation, pass-through type or None) of each field but the header, once per class: every
    message crosses encode and decode, and dataclasses.fields plus a hint lookup per field cost more there
    than the rest of the decode of a small message."""
    plan = _FIELD_PLANS.get(cls)
    if plan is None:
        hints = _hints(cls)
        plan = tuple((f.name, hints[f.name], hints[f.name] if hints[f.name] in _PASS_THROUGH else None)
                     for f in dataclasses.fields(cls) if f.name != "header")
        _FIELD_PLANS[cls] = plan
    return plan


def encode(msg: Message) -> bytes:
    """Serialise a message (type tag, version, header, fields) into a followbus frame (bus/codec.py)."""
    fields = {name: getattr(msg, name) for name, _, _ in _field_plan(type(msg))}
    return encode_message(msg.TYPE, SCHEMA_VERSION, msg.header, fields)


def encode_parts(msg: Message) -> tuple[bytes, list[np.ndarray]]:
    """:func:`encode` without joining: the frame's head (bytes) and the arrays of its blob area, uncopied."""
    fields = {name: getattr(msg, name) for name, _, _ in _field_plan(type(msg))}
    return encode_message_parts(msg.TYPE, SCHEMA_VERSION, msg.header, fields)


def _field_value(type_name: str, name: str, hint: Any, exact: Any, value: Any) -> Any:
    """A read field checked against its annotation (a value of the exact pass-through type as it is); the
    same rule for decode and wire_copy. DecodeError if it does not fit."""
    if exact is not None and type(value) is exact:
        return value
    try:
        return conform(value, hint)
    except TypeMismatch as exc:
        raise DecodeError(f"{type_name}.{name}: {exc}") from None


def decode(data: bytes | bytearray | memoryview, expected: type[M] | None = None,
           blob_area: memoryview | None = None) -> M:
    """Parse bytes into the typed message; raise DecodeError on anything that does not fit. ``blob_area``:
    the arrays' bytes, when they are not after the head (bus/shmlane.py)."""
    type_name, version, header, obj = decode_message(data, blob_area)
    cls = SCHEMAS.get(type_name) if isinstance(type_name, str) else None
    if cls is None:
        raise DecodeError(f"unknown message type {type_name!r}")
    if version != SCHEMA_VERSION:
        raise DecodeError(f"{type_name}: schema version {version!r}, this build reads {SCHEMA_VERSION}")
    if expected is not None and cls is not expected:
        raise DecodeError(f"expected {expected.TYPE}, got {type_name}")
    if header is None:
        raise DecodeError(f"{type_name}: missing field 'header'")
    kwargs: dict[str, Any] = {"header": header}
    for name, hint, exact in _field_plan(cls):
        if name not in obj:
            if name in cls.ADDED:
                continue  # an older message: the field's default
            raise DecodeError(f"{type_name}: missing field {name!r}")
        kwargs[name] = _field_value(type_name, name, hint, exact, obj.pop(name))
    if obj:
        raise DecodeError(f"{type_name}: unknown fields {sorted(obj)}")
    return cls(**kwargs)  # type: ignore[return-value]


def _plain_header_copy(h: Header) -> Header | None:
    """The header as it would decode, when its values are the plain types the wire keeps as they are (as good
    as always: then the header costs a copy, not a walk through wire_value); None otherwise."""
    feedback = h.feedback
    if not (type(h.seq) is int and type(h.stamp_ns) is int and type(h.frame_seq) is int and type(h.pub_ns) is int
            and type(h.epoch_ns) is int and type(h.source) is str and h.source.isascii() and type(feedback) is dict
            and all(INT_MIN <= v < INT_LIMIT for v in (h.seq, h.stamp_ns, h.frame_seq, h.pub_ns, h.epoch_ns))
            and all(type(k) is str and k.isascii() and type(f) is int and INT_MIN <= f < INT_LIMIT
                    for k, f in feedback.items())):
        return None
    return Header(h.seq, h.stamp_ns, h.frame_seq, h.source, h.pub_ns, h.epoch_ns, dict(feedback))


def wire_copy(msg: M, *, share_arrays: bool = False) -> M:
    """What ``decode(encode(msg))`` gives, made without the bytes (bus/codec.py ``wire_value`` for the header
    and every field, then :func:`decode`'s own type checks): the in-process runtime's copy of a published
    message, for every subscriber a copy of its own, as the bus would give it. Raises what :func:`encode`
    raises for a value that cannot be written and :class:`DecodeError` for one that would not decode;
    ``tests/test_bus_codec.py`` holds it to ``decode(encode(msg))``. ``share_arrays``: the message's own
    arrays are viewed read-only, not copied (the caller hands the message over; see ``wire_value``)."""
    cls = type(msg)
    if SCHEMAS.get(cls.TYPE) is not cls:
        raise DecodeError(f"unknown message type {cls.TYPE!r}")
    plan = _field_plan(cls)
    # As on the bus: the whole message is written (a value that cannot be written raises at once) before any of
    # it is read (what would not read back is a DecodeError, then the header, then each field's type).
    header = _plain_header_copy(msg.header)
    raw = [getattr(msg, name) for name, _, _ in plan]
    if header is None:
        raw.insert(0, msg.header.to_wire())
    unreadable: DecodeError | None = None
    values: list[Any] = []
    for value in raw:
        try:
            values.append(wire_value(value, share_arrays=share_arrays))
        except DecodeError as exc:
            unreadable = unreadable or exc
            values.append(None)
    if unreadable is not None:
        raise unreadable
    if header is None:
        header = header_from_wire(values.pop(0))[0]
    kwargs: dict[str, Any] = {"header": header}
    for (name, hint, exact), value in zip(plan, values, strict=True):
        kwargs[name] = _field_value(cls.TYPE, name, hint, exact, value)
    return cls(**kwargs)  # type: ignore[return-value]


def require(condition: bool, msg: Message, what: str) -> None:
    """Raise DecodeError naming the message type unless ``condition`` holds (a message's own checks use it)."""
    if not condition:
        raise DecodeError(f"{msg.TYPE}: {what}")


def check_shape(msg: Message, name: str, value: np.ndarray, shape: tuple[int | None, ...]) -> None:
    """Raise DecodeError unless array field ``name`` has ``shape`` (None: any length on that axis)."""
    fits = value.ndim == len(shape) and all(want is None or got == want
                                            for got, want in zip(value.shape, shape, strict=True))
    if not fits:
        wanted = " x ".join("N" if n is None else str(n) for n in shape)
        raise DecodeError(f"{msg.TYPE}.{name}: expected {wanted}, got {list(value.shape)}")


def _check_header(msg: Message) -> None:
    h = msg.header
    if h.stamp_ns < 0 or h.frame_seq < -1 or h.epoch_ns < 0:
        raise DecodeError(f"{msg.TYPE}: header out of range (stamp_ns {h.stamp_ns}, frame_seq {h.frame_seq})")


def _check_finite(msg: Message) -> None:
    """Every float and float array finite: a NaN reaching a filter poisons it for good."""
    for field_name, _, _ in _field_plan(type(msg)):
        value = getattr(msg, field_name)
        if isinstance(value, float) and not math.isfinite(value):
            raise DecodeError(f"{msg.TYPE}.{field_name}: non-finite value {value}")
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and not np.isfinite(value).all():
            raise DecodeError(f"{msg.TYPE}.{field_name}: non-finite values in array")


def validate(msg: Message) -> Message:
    """Check a decoded message's values; raise DecodeError on anything a node must never see.

    Generic rules first (the header in range, every float finite), then the type's own :meth:`Message.check`;
    free-form diagnostics get the header check only. Returns the message, so ``validate(decode(data))`` reads
    naturally.
    """
    _check_header(msg)
    if msg.FREE_FORM:
        return msg
    _check_finite(msg)
    msg.check()
    return msg


def to_plain(msg: Message) -> dict[str, Any]:
    """A JSON-friendly dict of a message (arrays become lists; large images are summarised)."""
    out: dict[str, Any] = {"type": msg.TYPE, "header": dataclasses.asdict(msg.header)}
    for f in dataclasses.fields(msg):
        if f.name == "header":
            continue
        value = getattr(msg, f.name)
        if isinstance(value, np.ndarray):
            value = (
                f"<array {value.dtype} {list(value.shape)}>" if value.size > 64 else value.round(4).tolist()
            )
        out[f.name] = value
    return out
