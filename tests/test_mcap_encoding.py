"""The bus channels of a recording are honestly labelled: each message is plain MessagePack (``msgpack``), and a
reader written only from the channel's label and its schema document (this file's ``DocumentReader``: ``struct``
+ ``msgpack``, nothing of followbus) decodes every bus message of a real `followbus record` recording to what
``bus.schemas.decode`` gives, and rebuilds the exact frame. Every channel of that recording decodes with
third-party readers. The conversion frame <-> record is bit-exact; recordings made before (the frame itself,
labelled ``x-followbus-frame/1`` or earlier ``msgpack``) still read (the shared reader, capture) and replay."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from followbus.bus.codec import DecodeError, frame_to_record, record_to_frame
from followbus.bus.recording import bus_channels, is_bus_channel, iter_bus_messages, schema_document, stored_frame
from followbus.bus.schemas import SCHEMAS, Frame, Header, Message, NodeStatus, Tick, decode, encode
from followbus.msgs.perception import Detections
from followbus.msgs.tracking import Measurement
from followbus.nodes.capture import McapFrameSource

from . import test_record_replay
from .conftest import copy_recording, run_followbus
from .test_record_views import decode_every_channel

recorded = test_record_replay.recorded  # the module-scoped fixture: `launch --record` of a real graph

BUS_ENCODING = "msgpack"
FRAME_ENCODING = "x-followbus-frame/1"  # recordings made before: the frame's own bytes
SCHEMA_ENCODING = "x-followbus-schema/1"


# --- a reader written from the schema text alone ----------------------------------------------------

@dataclass
class Array:
    dtype: str
    shape: list[int]
    values: tuple  # flat, C order
    inline: bool


# The document names dtypes by byte order, kind and itemsize; struct's letters for them.
STRUCT_CODES = {("u", 1): "B", ("i", 1): "b", ("u", 2): "H", ("i", 2): "h", ("u", 4): "I", ("i", 4): "i",
                ("u", 8): "Q", ("i", 8): "q", ("f", 2): "e", ("f", 4): "f", ("f", 8): "d", ("b", 1): "?"}


class DocumentReader:
    """Everything it knows comes from the schema text: the array and bin markers of a message, the magic,
    where N and the head are in the frame, the two ext codes, the header element names and the type's field
    names."""

    def __init__(self, text: str):
        def find(pattern: str) -> str:
            match = re.search(pattern, text, re.M)
            assert match, f"the schema document does not say {pattern!r}"
            return match.group(1)

        self.array_marker = bytes.fromhex(find(r"^\s*0x([0-9a-f]{2})\s+the array marker"))
        self.bin_marker = bytes.fromhex(find(r"^\s*0x([0-9a-f]{2})\s+bin 32 marker"))
        self.magic = find(r'^\s*0\s+\d+\s+magic: the ASCII bytes "([^"]+)"').encode("ascii")
        self.length_at = int(find(r"^\s*(\d+)\s+4\s+N: uint32 little-endian"))
        self.head_at = int(find(r"^\s*(\d+)\s+N\s+head:"))
        self.inline_code = int(find(r"ext type (\d+) \(inline\)"))
        self.ref_code = int(find(r"ext type (\d+) \(out of band\)"))
        self.type_key, self.version_key, self.header_key = (
            find(r'^\s*"(\w+)"\s+str: the message type name'), find(r'^\s*"(\w+)"\s+int: the version'),
            find(r'^\s*"(\w+)"\s+array of \d+ elements'))
        header_block = text[text.index(f'"{self.header_key}"'):text.index("then one key per field")]
        self.header_names = re.findall(r"^\s+\d+\. (\w+) \(", header_block, re.M)
        self.legacy_header = int(find(r"carry only the first (\d+)"))
        self.type_name = find(r"^FIELDS of (\w+) \(VERSION")
        self.version = int(find(r"^FIELDS of \w+ \(VERSION (\d+)\)"))
        block = text[text.index(f"FIELDS of {self.type_name} (VERSION"):].split("\n\n")[0]
        self.fields = re.findall(r"^  (\w+): ", block, re.M)

    def array(self, dtype: str, shape: list[int], body: bytes, inline: bool) -> Array:
        order, kind, size = dtype[0], dtype[1], int(dtype[2:])
        assert order in "<|", dtype
        count = math.prod(shape)  # 1 for shape []
        assert len(body) == count * size
        return Array(dtype, list(shape), struct.unpack(f"<{count}{STRUCT_CODES[kind, size]}", body), inline)

    def resolve(self, value: Any, blobs: bytes) -> Any:
        """The head's values with its ext values made arrays."""
        if isinstance(value, dict):
            return {k: self.resolve(v, blobs) for k, v in value.items()}
        if isinstance(value, list):
            return [self.resolve(v, blobs) for v in value]
        if not isinstance(value, msgpack.ExtType):
            return value
        if value.code == self.inline_code:
            dtype, shape, body = value.data.split(b"\0", 2)
            return self.array(dtype.decode("ascii"), json.loads(shape), body, True)
        assert value.code == self.ref_code, value.code
        dtype, shape, offset, nbytes = msgpack.unpackb(value.data)
        return self.array(dtype, shape, blobs[offset:offset + nbytes], False)

    def frame(self, data: bytes) -> bytes:
        """The followbus frame of a message, built as the document says: the head's bytes lie between the array
        marker and the bin 32 header (5 bytes) of the blob area."""
        assert data[:1] == self.array_marker
        _head, blobs = msgpack.unpackb(data, strict_map_key=False)
        head_end = len(data) - 5 - len(blobs)
        assert data[head_end:head_end + 1] == self.bin_marker
        head = data[1:head_end]
        frame = self.magic + struct.pack("<I", len(head)) + head + blobs
        assert struct.unpack_from("<I", frame, self.length_at)[0] == len(head) and frame[self.head_at:][:1] == head[:1]
        return frame

    def read(self, data: bytes) -> dict[str, Any]:
        assert data[:1] == self.array_marker
        head, blobs = msgpack.unpackb(data, raw=False)  # one plain MessagePack value: nothing before or after
        out = self.resolve(head, blobs)
        assert out.pop(self.type_key) == self.type_name and out.pop(self.version_key) == self.version
        header = out.pop(self.header_key)
        assert len(header) in (len(self.header_names), self.legacy_header)
        assert sorted(out) == sorted(self.fields), (sorted(out), self.fields)  # the document lists every field
        return {"header": dict(zip(self.header_names, header, strict=False)), **out}


def same(read: Any, decoded: Any) -> bool:
    """A value of the document reader equals the one bus.schemas.decode gave."""
    if isinstance(read, Array):
        return (isinstance(decoded, np.ndarray) and decoded.dtype.str == read.dtype
                and list(decoded.shape) == read.shape and decoded.ravel().tolist() == list(read.values))
    return read == decoded and type(read) is type(decoded) or (isinstance(decoded, float) and read == decoded)


def compare(reader: DocumentReader, data: bytes) -> list[Array]:
    """Decode a bus channel's message with both readers and assert they agree on every header element and field
    and on the frame; the arrays met."""
    by_document = reader.read(data)
    assert reader.frame(data) == stored_frame(data)
    msg: Message = decode(stored_frame(data))
    assert reader.type_name == msg.TYPE
    header = dataclasses.asdict(msg.header)
    assert all(header[name] == value for name, value in by_document.pop("header").items())
    arrays = []
    for name, value in by_document.items():
        assert same(value, getattr(msg, name)), (reader.type_name, name, value, getattr(msg, name))
        arrays += [value] if isinstance(value, Array) else []
    return arrays


# --- the recording ----------------------------------------------------------------------------------

def test_every_bus_channel_decodes_from_its_label_and_schema_text(recorded):
    decoded: dict[str, int] = {}
    arrays: list[Array] = []
    readers: dict[int, DocumentReader] = {}
    with open(recorded.path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding in ("json", "cdr"):
                continue  # the views (tests/test_record_views.py decodes them, tests/js checks the Foxglove ones)
            # Nothing else: every other channel must carry the label a reader can act on.
            assert channel.message_encoding == BUS_ENCODING and is_bus_channel(channel), channel
            assert schema is not None and schema.encoding == SCHEMA_ENCODING, channel.topic
            if schema.id not in readers:
                readers[schema.id] = DocumentReader(schema.data.decode("utf-8"))
            arrays += compare(readers[schema.id], message.data)
            decoded[channel.topic] = decoded.get(channel.topic, 0) + 1
    assert decoded["t/ticker/tick"] == decoded["t/relay/tick"] == test_record_replay.TICKS
    for key in ("t/capture/frame", "t/detection/detections", "t/prediction/prior", "t/prediction/track"):
        assert decoded[key] == test_record_replay.VIEW_FRAMES, key
    # Both array forms the document describes were met (the 64x48 frames travel out of band).
    assert {a.inline for a in arrays} == {True, False}


def test_the_document_describes_every_message_type():
    """Types the recording above does not carry: each one's document lists its fields, and a reader built
    from it decodes a message of that type with arrays inline and out of band, optional fields set."""
    samples: list[Message] = [cls() for cls in SCHEMAS.values()] + [
        Measurement(box=np.array([1.0, 2.0, 3.0, 4.0]), candidate_hist=np.ones((30, 32), np.float32),
                    candidate_sources=["detection"], candidates=np.arange(10.0).reshape(2, 5)),
        Frame(width=40, height=30, data=np.full((30, 40, 3), 7, np.uint8)),
        Detections(boxes=np.zeros((3, 5), np.float32)),
        NodeStatus(topics={"t/x": {"count": 3, "rate_hz": 1.5}}, extra={"a": [1, 2]}),
    ]
    for msg in samples:
        msg.header.feedback = {"template": 4}
        reader = DocumentReader(schema_document(msg.TYPE).decode())
        assert reader.fields == [f.name for f in dataclasses.fields(msg) if f.name != "header"]
        compare(reader, frame_to_record(encode(msg)))


def test_a_wrong_document_is_caught():
    """The negative control: a document whose header order is wrong makes the comparison fail."""
    right = schema_document("Tick").decode()
    wrong = right.replace("0. seq (int)", "0. frame_seq (int)", 1).replace("2. frame_seq (int)", "2. seq (int)", 1)
    assert wrong != right
    data = frame_to_record(encode(Tick(value=1, header=Header(seq=3, frame_seq=9))))
    compare(DocumentReader(right), data)
    with pytest.raises(AssertionError):
        compare(DocumentReader(wrong), data)


# --- every channel by third-party readers -------------------------------------------------------------

def test_every_channel_of_a_recorded_graph_decodes_with_third_party_readers(recorded):
    """The recording of a real graph (``launch --record``): bus channels by the mcap reader and msgpack alone,
    views by mcap-ros2-support and json (tests/test_record_views.decode_every_channel fails on any channel left
    undecoded), and what msgpack reads of a bus message is what followbus decodes of its frame."""
    bus, views = decode_every_channel(recorded.path)
    assert set(bus) == set(bus_channels(recorded.path)) and len(bus) == 6
    assert views and all(any(topic.startswith(key + "/") for topic in views) for key in bus)
    ticks = bus["t/ticker/tick"]
    assert len(ticks) == test_record_replay.TICKS
    assert sorted(t["value"] for t in ticks) == list(range(test_record_replay.TICKS))
    ours = {key: [decode(m.data) for m in iter_bus_messages(recorded.path, [key])] for key in bus}
    for key, heads in bus.items():
        assert [(h["_t"], h["header"][0], h["header"][1]) for h in heads] == [
            (m.TYPE, m.header.seq, m.header.stamp_ns) for m in ours[key]], key
    assert len(bus["t/capture/frame"]) == test_record_replay.VIEW_FRAMES
    assert all(h["data"].code == 2 for h in bus["t/capture/frame"])  # the 64x48 frames: out of band


# --- the conversion --------------------------------------------------------------------------------------

def test_frame_to_record_and_back_is_bit_exact():
    """A frame with a big array (out of band), one with small arrays only and one with no array at all: the
    record is plain MessagePack [head, blobs] holding the head's very bytes, and converts back to the frame."""
    big = Frame(width=640, height=480, data=(np.arange(480 * 640 * 3) % 251).astype(np.uint8).reshape(480, 640, 3))
    big.header = Header(seq=7, stamp_ns=1_700_000_000_000_000_001, frame_seq=3, source="capture", epoch_ns=5)
    samples = [big, Detections(boxes=np.ones((2, 5), np.float32)), Tick(value=3)]
    for msg in samples:
        frame = encode(msg)
        record = frame_to_record(frame)
        head_len = struct.unpack_from("<I", frame, 3)[0]
        head, blobs = msgpack.unpackb(record, strict_map_key=False)
        assert record[1:1 + head_len] == frame[7:7 + head_len] and blobs == frame[7 + head_len:]
        assert record[1 + head_len] == 0xC6 and head["_t"] == msg.TYPE  # bin 32 even when empty
        assert record_to_frame(record) == frame and record_to_frame(memoryview(record)) == frame
        assert record_to_frame(frame) == frame  # a frame as older recordings stored it: as it is
    assert len(frame_to_record(encode(big))) == len(encode(big)) - 1  # 7 bytes of prefix, 1 + 5 of array and bin


def test_malformed_records_are_decode_errors_never_crashes(tmp_path):
    """Neither form, or truncated: record_to_frame raises DecodeError; the readers give such a message's bytes
    as they are, so whoever decodes it counts a message that does not decode (as a corrupt frame)."""
    from mcap.writer import Writer

    record = frame_to_record(encode(Tick(value=1)))
    bad = [record[:-1], record + b"\0", record[:4], b"\x92", b"\x92\xc1", b"", b"{}", b"\x93\x01\x02\x03",
           b"\x92\x80\xc4\x00"]  # the last: a bin 8 blob area
    for data in bad:
        with pytest.raises(DecodeError):
            record_to_frame(data)
    for chunked in (True, False):  # the chunk parser and the mcap reader's path
        path = tmp_path / f"bad-{chunked}.mcap"
        with open(path, "wb") as f:
            writer = Writer(f, use_chunking=chunked)
            writer.start()
            sid = writer.register_schema("followbus.Tick", SCHEMA_ENCODING, schema_document("Tick"))
            cid = writer.register_channel("t/tick", BUS_ENCODING, sid, {"bus_key": "t/tick", "type": "Tick"})
            for i, data in enumerate([record, *bad, encode(Tick(value=2))]):
                writer.add_message(cid, 1000 + i, data, 1000 + i)
            writer.finish()
        messages = list(iter_bus_messages(path))
        assert [m.data for m in messages] == [encode(Tick(value=1)), *bad, encode(Tick(value=2))]
        for m in messages[1:-1]:
            with pytest.raises(DecodeError):
                decode(m.data)


# --- recordings made before: the frame itself, labelled x-followbus-frame/1 or msgpack ---------------------

def relabel_as_before(src: Path, dst: Path, label: str) -> None:
    """Rewrite a recording the way the recorder stored bus channels before: the frame's bytes, labelled
    ``x-followbus-frame/1`` (``x-followbus-schema/1`` schema) or earlier ``msgpack`` (a ``followbus-msgpack``
    schema); the views and metadata unchanged."""

    def relabel(schema, channel) -> tuple[str, bytes, str]:
        if not is_bus_channel(channel):
            return schema.encoding, schema.data, channel.message_encoding
        return (SCHEMA_ENCODING, schema.data, label) if label == FRAME_ENCODING else ("followbus-msgpack", b"{}", label)

    def rewrite(channel, data: bytes) -> bytes:
        return stored_frame(data) if is_bus_channel(channel) else data

    copy_recording(src, dst, relabel=relabel, rewrite=rewrite, library=f"followbus when bus channels said {label}")


@pytest.mark.parametrize("label", [FRAME_ENCODING, "msgpack"])
def test_recordings_of_frames_still_read_and_replay(recorded, tmp_path, label):
    old = tmp_path / "old.mcap"
    relabel_as_before(recorded.path, old, label)
    with open(old, "rb") as f:
        summary = make_reader(f).get_summary()
        bus_data = [m.data for _s, c, m in make_reader(f).iter_messages() if is_bus_channel(c)]
    assert label in {ch.message_encoding for ch in summary.channels.values()}
    assert bus_data and all(data[:3] == b"FB1" for data in bus_data)  # the frames themselves

    assert bus_channels(old) == bus_channels(recorded.path)
    assert len(bus_channels(old)) == 6
    assert [(m.key, m.data) for m in iter_bus_messages(old)] == [(m.key, m.data) for m in
                                                                iter_bus_messages(recorded.path)]
    # Capture reads a recording as its source through the same reader.
    frames = [f.bgr for f in McapFrameSource(str(old), "t/capture/frame")]
    assert len(frames) == test_record_replay.VIEW_FRAMES
    assert all(np.array_equal(a, b.bgr) for a, b in zip(frames, McapFrameSource(str(recorded.path),
                                                                                 "t/capture/frame"), strict=True))

    report_path = tmp_path / "replay.json"
    result = run_followbus("replay", str(old), "--node", "relay", "--verify", "--report", str(report_path),
                           timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(report_path.read_text())
    assert report["outputs_compared"] == report["matched"] == test_record_replay.TICKS
    assert report["mismatch_count"] == 0
