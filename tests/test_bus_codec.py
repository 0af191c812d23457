"""Codec and schema behaviour without a network."""

from __future__ import annotations

import numpy as np
import pytest

from followbus.bus.codec import DecodeError, pack, unpack
from followbus.bus.schemas import Detections, Frame, Header, Measurement, Tick, decode, encode


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
