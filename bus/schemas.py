"""Typed message schemas: the one place where every bus payload is defined.

Every message starts with a :class:`Header`. ``stamp_ns`` is the capture stamp of the camera
frame the message derives from (so latency = now - stamp_ns, and replays are deterministic),
``frame_seq`` that frame's sequence number, ``pub_ns`` the wall-clock time of publication
(per-edge latency; never compared by replay verification). ``epoch_ns`` names the numbering
``frame_seq`` belongs to (the start time of the capture session that numbered the frame), so a
restarted camera that counts from 0 again is told apart from stale frames. ``feedback`` is the
provenance of a frame-synchronised output: for each feedback input (``offset: -1``) the frame_seq of
the message the node used (-1: none), and -1 for each optional same-frame input the set went on without,
so a replay reproduces what the live run did.

Messages are checked twice on the way in: :func:`decode` checks the wire types, :func:`validate`
the values (finite numbers, boxes of non-negative size, consistent frames); both raise DecodeError,
which subscribers count and drop, so a malformed or poisoned message never reaches a filter.

Boxes are ``[x, y, w, h]`` float pixels, top-left origin.
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


@dataclass
class GroundTruth(Message):
    """Ground truth of the followed person for one frame, when the source has it."""

    TYPE: ClassVar[str] = "GroundTruth"
    available: bool = False  # False: this source has no ground truth (published anyway, so joins never wait)
    box: np.ndarray | None = None  # [x, y, w, h]; None when the target is absent
    visible_fraction: float = 1.0
    others: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # other people's boxes
    others_visible: np.ndarray = field(default_factory=lambda: np.zeros(0))  # their visible fractions


@dataclass
class Detections(Message):
    TYPE: ClassVar[str] = "Detections"
    MEASURED: ClassVar[frozenset[str]] = frozenset({"infer_ms"})
    ADDED: ClassVar[frozenset[str]] = frozenset({"low_boxes"})
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))  # x,y,w,h,score
    backend: str = ""
    infer_ms: float = 0.0
    # Boxes scoring below the detection node's score_threshold but at least its low_score_threshold (same
    # layout): only for a consumer that opts in (re-ID's second association stage, seed 002 / ByteTrack);
    # everything else reads ``boxes`` alone.
    low_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))


@dataclass
class Prior(Message):
    """Kalman prior for a frame (seed 000 Eq. 4-8)."""

    TYPE: ClassVar[str] = "Prior"
    initialised: bool = False
    state: np.ndarray = field(default_factory=lambda: np.zeros(4))  # x, y, vx, vy (px, px/s)
    size: np.ndarray = field(default_factory=lambda: np.zeros(2))  # w, h (px)
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((4, 4)))  # P_k
    innovation_cov: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))  # S = H P H^T + R
    gate_chi2: float = 9.488
    box: np.ndarray | None = None


@dataclass
class Measurement(Message):
    """Re-identification result for a frame (seed 000 Algorithm 1)."""

    TYPE: ClassVar[str] = "Measurement"
    state: str = "LOST"  # TRACKING | OCCLUDED | REACQUIRED | LOST | UNINITIALISED
    accepted: bool = False
    secure: bool = False
    box: np.ndarray | None = None  # the accepted box (Alg. 1 line 11)
    best_box: np.ndarray | None = None  # argmax M_fuse, even when rejected
    source: str = ""  # "detection" | "motion" | "init": where the chosen box came from
    m_fuse: float = 0.0
    s_color: float = 0.0
    s_geo: float = 0.0
    omega: float = 0.0
    c_t: float = 0.0
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))  # x,y,w,h,m_fuse
    candidate_sources: list[str] = field(default_factory=list)
    candidate_hist: np.ndarray | None = None
    init_box: np.ndarray | None = None  # set on the frame the target was initialised


@dataclass
class Track(Message):
    """Posterior target track published by prediction after each measurement."""

    TYPE: ClassVar[str] = "Track"
    state: str = "LOST"
    box: np.ndarray | None = None  # the tracker's output: accepted box, predicted box while OCCLUDED, else None
    filtered_box: np.ndarray | None = None  # Kalman posterior box
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))  # px/s
    measured: bool = False


@dataclass
class Template(Message):
    """Reference appearance model M and its learning rate eta_k (seed 000 Eq. 9-10)."""

    TYPE: ClassVar[str] = "Template"
    initialised: bool = False
    hist: np.ndarray | None = None  # bins_h x bins_s, sums to 1
    eta: float = 0.0
    p_specular: float = 0.0


@dataclass
class MotorCommand(Message):
    TYPE: ClassVar[str] = "MotorCommand"
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    wz_radps: float = 0.0
    wheel_radps: np.ndarray = field(default_factory=lambda: np.zeros(4))  # fl, fr, rl, rr
    range_m: float | None = None
    bearing_rad: float | None = None
    reason: str = ""


@dataclass
class Odometry(Message):
    TYPE: ClassVar[str] = "Odometry"
    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    wz_radps: float = 0.0


@dataclass
class NodeStatus(Message):
    """Once-a-second health and per-topic statistics of one node."""

    TYPE: ClassVar[str] = "NodeStatus"
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


@dataclass
class GroundPoints(Message):
    """One frame's people on the floor (groundplane node): robot frame (x forward, y left) and the fixed
    odometry frame (seed 004 Eq. 4, with the robot pose used), one row per kept detection."""

    TYPE: ClassVar[str] = "GroundPoints"
    points_robot_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    points_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # odometry frame
    covs_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))  # odometry frame
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    robot_x_m: float = 0.0
    robot_y_m: float = 0.0
    robot_theta_rad: float = 0.0
    odometry_stamp_ns: int = -1  # the odometry sample the pose came from (-1: none yet, the origin)


@dataclass
class GroupState(Message):
    """The followed group for one frame (seed 004 ME-CGT-UGV): odometry frame unless named ``_robot``."""

    TYPE: ClassVar[str] = "GroupState"
    MEASURED: ClassVar[frozenset[str]] = frozenset({"step_ms"})
    valid: bool = False  # False: no group yet (the other fields are zeros)
    lost: bool = False  # no member seen this frame: the state is the prediction
    centre_m: np.ndarray = field(default_factory=lambda: np.zeros(2))
    velocity_mps: np.ndarray = field(default_factory=lambda: np.zeros(2))
    orientation_rad: float = 0.0  # main axis of the group's extent
    centre_robot_m: np.ndarray = field(default_factory=lambda: np.zeros(2))  # at this frame's pose: what motor follows
    ellipse_centres_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    ellipse_extents_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    ellipse_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    members_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the points selected this frame
    others_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the points left out (disturbers)
    step_ms: float = 0.0  # tracker cost of this frame


@dataclass
class CameraMotion(Message):
    """Global image motion from the frame stamped ``from_stamp_ns`` to this one: p_k = M p_prev + t (px).

    ``valid`` False: no trustworthy estimate for this frame (``reason`` says why); consumers go without."""

    TYPE: ClassVar[str] = "CameraMotion"
    valid: bool = False
    matrix: np.ndarray = field(default_factory=lambda: np.eye(2, 3))  # 2x3 [M | t]
    inliers: int = 0  # points consistent with the matrix
    tracked: int = 0  # points the fit was made from
    from_stamp_ns: int = 0
    reason: str = ""
    # The fit's uncertainty (issue 22; tracking/egomotion.py), px at full resolution.
    residual_px: float = 0.0  # RMS distance of the inliers from the fit
    spread: float = 0.0  # fraction of the image's grid cells holding an inlier
    rival_px: float = 0.0  # how far the competing hypothesis moves the image centre from this one
    rival_inliers: int = 0
    agreement_px: float = -1.0  # distance from the previous frame's motion at the image centre; -1: none
    std_px: float = 0.0  # 1-σ of the displacement a point gets (prediction widens its prior by it)
    static_cells: int = 0  # grid cells taken for screen-fixed content and left out of the fit


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


TRACK_STATES = frozenset({"TRACKING", "OCCLUDED", "REACQUIRED", "LOST", "UNINITIALISED"})
BOX_FIELDS = frozenset({"box", "best_box", "init_box", "filtered_box"})
UNCHECKED_TYPES = frozenset({"NodeStatus", "Tick"})  # free-form diagnostics


def _check_box(name: str, box: np.ndarray) -> None:
    if box.shape != (4,):
        raise DecodeError(f"{name}: a box is [x, y, w, h], got shape {list(box.shape)}")
    if box[2] < 0 or box[3] < 0:
        raise DecodeError(f"{name}: box of negative size {box.tolist()}")


def validate(msg: Message) -> Message:
    """Check a decoded message's values; raise DecodeError on anything a node must never see.

    Every float and float array must be finite (a NaN reaching a Kalman filter poisons it for good),
    boxes have non-negative width and height, frames match their declared size, track states are known.
    Returns the message, so ``validate(decode(data))`` reads naturally.
    """
    h = msg.header
    where = msg.TYPE
    if h.stamp_ns < 0 or h.frame_seq < -1 or h.epoch_ns < 0:
        raise DecodeError(f"{where}: header out of range (stamp_ns {h.stamp_ns}, frame_seq {h.frame_seq})")
    if msg.TYPE in UNCHECKED_TYPES:
        return msg
    for field_name, _, _ in _field_plan(type(msg)):
        value = getattr(msg, field_name)
        if isinstance(value, float) and not math.isfinite(value):
            raise DecodeError(f"{where}.{field_name}: non-finite value {value}")
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and not np.isfinite(value).all():
            raise DecodeError(f"{where}.{field_name}: non-finite values in array")
        if field_name in BOX_FIELDS and value is not None:
            _check_box(f"{where}.{field_name}", value)
    if isinstance(msg, Detections):
        for name, boxes in (("boxes", msg.boxes), ("low_boxes", msg.low_boxes)):
            if boxes.ndim != 2 or boxes.shape[1] != 5:
                raise DecodeError(f"{where}.{name}: expected N x 5 (x, y, w, h, score), got {list(boxes.shape)}")
            if (boxes[:, 2:4] < 0).any():
                raise DecodeError(f"{where}.{name}: box of negative size")
    elif isinstance(msg, Frame):
        data = msg.data
        if msg.encoding == "bgr8":
            if data.dtype != np.uint8 or data.shape != (msg.height, msg.width, 3):
                raise DecodeError(f"{where}: bgr8 data {data.dtype} {list(data.shape)} does not match "
                                  f"{msg.width}x{msg.height}")
        elif msg.encoding == "jpeg":
            if data.dtype != np.uint8 or data.ndim != 1:
                raise DecodeError(f"{where}: jpeg data must be 1-D uint8")
        else:
            raise DecodeError(f"{where}: unknown encoding {msg.encoding!r}")
    elif isinstance(msg, (Measurement, Track)) and msg.state not in TRACK_STATES:
        raise DecodeError(f"{where}.state: unknown state {msg.state!r}")
    elif isinstance(msg, Prior) and (msg.state.shape != (4,) or msg.covariance.shape != (4, 4)
                                     or msg.innovation_cov.shape != (2, 2)):
        raise DecodeError(f"{where}: state, covariance or innovation covariance of the wrong shape")
    elif isinstance(msg, CameraMotion):
        if msg.matrix.shape != (2, 3) or not 0 <= msg.inliers <= msg.tracked:
            raise DecodeError(f"{where}: matrix must be 2 x 3 and 0 <= inliers <= tracked")
        if msg.valid and not 0 <= msg.from_stamp_ns < h.stamp_ns:
            raise DecodeError(f"{where}.from_stamp_ns: {msg.from_stamp_ns} is not before the frame's stamp")
    elif isinstance(msg, GroundPoints):
        n = len(msg.points_m)
        if (msg.points_m.shape != (n, 2) or msg.points_robot_m.shape != (n, 2) or msg.covs_m2.shape != (n, 2, 2)
                or msg.scores.shape != (n,)):
            raise DecodeError(f"{where}: points N x 2, covariances N x 2 x 2 and scores N must agree")
        if n and (msg.covs_m2[:, [0, 1], [0, 1]] < 0).any():
            raise DecodeError(f"{where}.covs_m2: negative variance")
    elif isinstance(msg, GroupState):
        n = len(msg.ellipse_weights)
        if (msg.centre_m.shape != (2,) or msg.velocity_mps.shape != (2,) or msg.centre_robot_m.shape != (2,)
                or msg.ellipse_centres_m.shape != (n, 2) or msg.ellipse_extents_m2.shape != (n, 2, 2)
                or msg.ellipse_weights.shape != (n,) or msg.members_m.ndim != 2 or msg.members_m.shape[1] != 2
                or msg.others_m.ndim != 2 or msg.others_m.shape[1] != 2):
            raise DecodeError(f"{where}: centre, velocity or ellipses of the wrong shape")
        if n and ((msg.ellipse_weights < 0).any() or (msg.ellipse_weights > 1).any()
                  or (msg.ellipse_extents_m2[:, [0, 1], [0, 1]] < 0).any()):
            raise DecodeError(f"{where}: ellipse weight outside [0, 1] or negative extent")
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
