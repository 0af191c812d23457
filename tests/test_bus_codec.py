"""Codec and schema behaviour without a network."""

from __future__ import annotations

import numpy as np
import pytest

from followbus.bus.codec import DecodeError, pack, unpack
from followbus.bus.schemas import Frame, Header, Tick, decode, encode
from followbus.msgs.perception import Detections
from followbus.msgs.tracking import Measurement


def test_large_array_roundtrip_is_zero_copy_view():
    image = np.arange(480 * 640 * 3, dtype=np.uint32).astype(np.uint8).reshape(480, 640, 3)
    msg = Frame(header=Header(seq=1, stamp_ns=5, frame_seq=7, source="cam"), width=640, height=480, data=image)
    out = decode(encode(msg), Frame)
    assert np.array_equal(out.data, image)
    assert out.header == msg.header
    assert not out.data.flags.writeable  # a view on the received bytes, not a copy


def test_small_arrays_inline_and_optional_none():
    msg = Measurement(state="OCCLUDED", box=None, candidates=np.ones((2, 5), np.float32))
    out = decode(encode(msg))
    assert isinstance(out, Measurement)
    assert out.box is None and out.state == "OCCLUDED"
    assert out.candidates.dtype == np.float32 and out.candidates.shape == (2, 5)


@pytest.mark.parametrize("data", [
    b"", b"garbage", b"FB1\xff\xff\xff\xff", b"FB1\x01\x00\x00\x00\xc1",
    b"FB1" + (3).to_bytes(4, "little") + b"\x93\x01\x02",  # a list, not a map
])
def test_malformed_bytes_raise_decode_error(data):
    with pytest.raises(DecodeError):
        decode(data)


def test_wrong_field_type_and_unknown_type_are_decode_errors():
    good = unpack(encode(Tick(value=3)))
    good["value"] = "three"
    with pytest.raises(DecodeError, match="Tick.value"):
        decode(pack(good))
    with pytest.raises(DecodeError, match="unknown message type"):
        decode(pack({"_t": "Nope", "_v": 1}))
    with pytest.raises(DecodeError, match="expected Detections"):
        decode(encode(Tick()), Detections)


def test_out_of_bounds_array_reference_is_rejected():
    data = bytearray(encode(Frame(width=64, height=64, data=np.zeros((64, 64, 3), np.uint8))))
    with pytest.raises(DecodeError, match="out of bounds"):
        decode(bytes(data[:-10]))


def test_a_message_type_defined_outside_bus_registers_itself():
    """A node's own message type needs no edit of a table in bus/: defining the class makes it decodable,
    and a second class under the same type name is refused at once instead of shadowing the first."""
    from dataclasses import field, make_dataclass

    from followbus.bus.schemas import SCHEMAS, Message

    lidar = make_dataclass("LidarSummary", [("nearest_m", float, field(default=0.0))], bases=(Message,),
                           namespace={"TYPE": "TestLidarSummary"})
    try:
        assert SCHEMAS["TestLidarSummary"] is lidar
        back = decode(encode(lidar(nearest_m=1.25)), lidar)
        assert back.nearest_m == 1.25
        with pytest.raises(TypeError, match="defined twice"):
            make_dataclass("Impostor", [], bases=(Message,), namespace={"TYPE": "Detections"})
    finally:
        SCHEMAS.pop("TestLidarSummary", None)
    assert SCHEMAS["Detections"] is Detections


@pytest.mark.parametrize(("hint", "value", "ok"), [
    (float, 3, True), (float, True, False), (int, 2.0, False), (int, False, False), (bool, 1, False),
    (str, b"x", False), (list, (1, 2), True), (float | None, None, True), (float | None, "1", False),
])
def test_decoding_and_parameters_share_one_type_checker(hint, value, ok):
    """The same rules for a decoded field and a graph.yaml parameter: a bool is never a number, an int may
    stand for a float, a tuple for a list."""
    from dataclasses import field, make_dataclass

    from followbus.bus.node_params import ParamError, params_from_dict
    from followbus.bus.typecheck import TypeMismatch, conform

    params = make_dataclass("Params", [("value", hint, field(default=None))])
    if ok:
        conform(value, hint)
        params_from_dict(params, {"value": value})
    else:
        with pytest.raises(TypeMismatch):
            conform(value, hint)
        with pytest.raises(ParamError, match="must be"):
            params_from_dict(params, {"value": value})


def test_detections_of_an_older_recording_without_low_boxes_still_decode():
    """``low_boxes`` was added to Detections later (Message.ADDED): a message without it decodes with no low
    boxes, while a message missing an original field is still refused, and malformed low boxes are rejected."""
    from followbus.bus.schemas import validate

    new = unpack(encode(Detections(boxes=np.array([[1, 2, 3, 4, 0.9]], np.float32), backend="yolox",
                                   low_boxes=np.array([[5, 6, 7, 8, 0.2]], np.float32))))
    assert decode(pack(new)).low_boxes.tolist() == [[5.0, 6.0, 7.0, 8.0, np.float32(0.2)]]
    old = dict(new)
    del old["low_boxes"]
    out = decode(pack(old), Detections)
    assert out.low_boxes.shape == (0, 5) and out.boxes.shape == (1, 5)
    del old["backend"]
    with pytest.raises(DecodeError, match="missing field 'backend'"):
        decode(pack(old))
    with pytest.raises(DecodeError, match="low_boxes"):
        validate(Detections(low_boxes=np.zeros((2, 4), np.float32)))


@pytest.mark.parametrize("shape, ok", [
    (b"[2, 3]", True), (b"[6]", True), (b"[]", False), (b"[2,3]", True), (b" [2, 3]", True),  # [] is 1 element
    (b"[02, 3]", False), (b"[-2, -3]", False), (b"[2.0, 3]", False), (b"[2, ]", False), (b"[\"2\", 3]", False),
    (b"{}", False), (b"", False), (b"[2, 3", False), (b"[1, 2, 3]", True),
])
def test_inline_array_shapes_read_as_json_reads_them(shape, ok):
    """The fast reading of an inline array's shape accepts exactly what json does (and _check_meta then wants
    non-negative ints that fit the body); everything else stays a DecodeError, never a crash."""
    import msgpack

    from followbus.bus.codec import MAGIC, NDARRAY_EXT

    head = msgpack.packb({"a": msgpack.ExtType(NDARRAY_EXT, b"|u1\0" + shape + b"\0" + bytes(range(6)))})
    frame = MAGIC + len(head).to_bytes(4, "little") + head
    if ok:
        assert unpack(frame)["a"].size == 6
    else:
        with pytest.raises(DecodeError):
            unpack(frame)


# --------------------------------------------------------------------------- wire_copy: decode(encode(m)), no bytes

def _same(got, want, where: str) -> None:
    """The same types, values (NaN as NaN), dtypes, shapes and bytes, all the way down; arrays read-only."""
    assert type(got) is type(want), (where, type(got), type(want))
    if isinstance(want, np.ndarray):
        assert (got.dtype, got.shape, got.tobytes()) == (want.dtype, want.shape, want.tobytes()), where
        assert not got.flags.writeable and not want.flags.writeable, where
    elif isinstance(want, dict):
        assert list(got) == list(want), where
        for key in want:
            _same(got[key], want[key], f"{where}.{key}")
    elif isinstance(want, list):
        assert len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            _same(g, w, f"{where}[{i}]")
    elif isinstance(want, float) and want != want:
        assert got != got, where
    else:
        assert got == want, where


def _same_as_decoded(copy, decoded) -> None:
    assert type(copy) is type(decoded)
    for name, want in vars(decoded).items():
        _same(getattr(copy, name), want, name)


def _outcome(fn, msg):
    try:
        return fn(msg)
    except DecodeError:
        return DecodeError
    except Exception as exc:  # what encode raises for a value it cannot write
        return type(exc)


def _wire_cases():
    from followbus.bus.schemas import SCHEMAS, NodeStatus, ReplayHint
    from followbus.msgs.group import GroupState
    from followbus.msgs.robot import MotorCommand
    from followbus.msgs.tracking import Prior, Track

    rng = np.random.default_rng(3)
    header = Header(seq=4, stamp_ns=1_700_000_000_123_456_789, frame_seq=12, source="reid", pub_ns=9, epoch_ns=7,
                    feedback={"template": 11})
    cases = [cls() for cls in SCHEMAS.values()]  # every registered type, defaults
    cases += [
        Frame(header=header, width=8, height=4, data=rng.integers(0, 255, (4, 8, 3), np.uint8)),
        Frame(header=header, width=640, height=480, data=rng.integers(0, 255, (480, 640, 3), np.uint8)),  # blob
        Prior(header=header, initialised=True, state=rng.normal(size=4), size=np.array([30.0, 80.0]),
              covariance=np.eye(4)[::-1], innovation_cov=np.asfortranarray(rng.normal(size=(2, 2))),  # not C order
              gate_chi2=np.float64(9.2), box=np.array([1, 2, 3, 4], ">f8")),  # numpy scalar, big-endian
        Measurement(header=header, state="TRACKING", accepted=np.bool_(True), box=np.arange(4.0),
                    candidates=rng.random((3, 5)), candidate_sources=("detection", "motion", "detection"),
                    m_fuse=np.float32(0.25), s_color=1, init_box=np.arange(8.0)[::2]),  # int for a float, strided
        Track(header=header, state="OCCLUDED", box=np.array([[1.0, 2.0, 3.0, 4.0]])[0],
              velocity=np.zeros(2, np.float32)),
        MotorCommand(header=header, vx_mps=float("nan"), range_m=None, wheel_radps=np.zeros((4,))),  # validate's job
        NodeStatus(header=header, node="ünïcode", pid=np.int64(12), topics={"a": {"b": [1, 2.5, None, "x"]}},
                   extra={"nested": (1, (2, 3)), "raw": b"\x00\x01", "arr": np.arange(3), "big": 2**63 - 1}),
        ReplayHint(header=header, feedback={"reid": np.int32(3)}),
        GroupState(header=header, centre_m=np.array(1.5), ellipse_weights=np.array([0.2, 0.8])),  # 0-d array
        # what cannot be written, or would not read back
        NodeStatus(header=header, extra={"too big": 2**64}),
        NodeStatus(header=header, extra={"obj": object()}),
        NodeStatus(header=header, extra={"complex": 1j}),
        NodeStatus(header=header, extra={3: "int key"}),
        Track(header=header, state=7),
        Prior(header=header, state=np.zeros(4, np.complex128)),
        Frame(header=Header(frame_seq=np.int64(3), source="cam"), data=np.zeros((0, 0, 3), np.uint8)),
    ]
    return cases


@pytest.mark.parametrize("msg", _wire_cases(), ids=lambda m: m.TYPE)
def test_wire_copy_is_exactly_what_decoding_the_encoded_message_gives(msg):
    from followbus.bus.schemas import wire_copy

    expected = _outcome(lambda m: decode(encode(m)), msg)
    got = _outcome(wire_copy, msg)
    if isinstance(expected, type):  # both must fail the same way: at the writer, or at the reader
        assert got is expected
        return
    _same_as_decoded(got, expected)


def test_wire_copy_owns_its_arrays_and_header():
    from followbus.bus.schemas import wire_copy
    from followbus.msgs.tracking import Prior

    state = np.zeros(4)
    msg = Prior(header=Header(feedback={"reid": 1}), state=state)
    copied = wire_copy(msg)
    state[0] = 5.0  # the publisher reuses its buffer for the next frame
    msg.header.feedback["reid"] = 2
    msg.header.seq = 9
    assert copied.state[0] == 0.0 and copied.header.feedback == {"reid": 1} and copied.header.seq == 0
    with pytest.raises(ValueError):
        copied.state[0] = 1.0  # read-only, as a decoded array


def _bad_messages():
    """One message per kind of value a consumer must never see, each caught by its type's own check()
    (msgs/) or by bus/schemas.py's generic rules."""
    from followbus.msgs.group import GroundPoints, GroupState
    from followbus.msgs.perception import CameraMotion, GroundTruth
    from followbus.msgs.tracking import Prior, Track

    bad_motion = CameraMotion(valid=True, matrix=np.eye(2, 3), inliers=5, tracked=4)
    bad_motion.header.stamp_ns = 10
    return [
        (Track(state="FOLLOWING"), "unknown state"),
        (Measurement(state="TRACKING", box=np.array([0.0, 0.0, -1.0, 5.0])), "negative size"),
        (GroundTruth(available=True, box=np.zeros(3)), "GroundTruth.box"),
        (Prior(initialised=True, covariance=np.eye(3)), "Prior.covariance"),
        (bad_motion, "inliers"),
        (GroundPoints(points_m=np.zeros((2, 2)), points_robot_m=np.zeros((1, 2)), covs_m2=np.zeros((2, 2, 2)),
                      scores=np.zeros(2)), "must agree"),
        (GroupState(centre_m=np.zeros(3)), "GroupState.centre_m"),
        (Frame(width=2, height=2, data=np.zeros((2, 3, 3), np.uint8)), "does not match"),
        (Track(state="TRACKING", velocity=np.array([np.nan, 0.0])), "non-finite"),  # generic: any type
    ]


@pytest.mark.parametrize("msg, error", _bad_messages(), ids=lambda v: getattr(v, "TYPE", None) or str(v))
def test_each_message_type_checks_its_own_fields(msg, error):
    from followbus.bus.schemas import validate

    with pytest.raises(DecodeError, match=error):
        validate(msg)
    with pytest.raises(DecodeError, match=error):
        validate(decode(encode(msg)))  # the same on the way in from the wire


def test_free_form_diagnostics_get_the_header_check_only():
    from followbus.bus.schemas import validate

    assert validate(Tick(payload=np.array([np.nan])))  # a benchmark's payload is not a node's input
    with pytest.raises(DecodeError, match="header out of range"):
        validate(Tick(header=Header(stamp_ns=-1)))
