"""The bus channels of a recording are honestly labelled: a reader written only from the channel's label
and its schema document (this file's ``DocumentReader``: ``struct`` + ``msgpack``, nothing of followbus)
decodes every bus message of a real `followbus record` recording to what ``bus.schemas.decode`` gives.
Recordings made before, labelled ``msgpack``, still read (the shared reader, capture) and replay."""

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

from followbus.bus.recording import bus_channels, iter_bus_messages, schema_document
from followbus.bus.schemas import SCHEMAS, Frame, Header, Message, NodeStatus, Tick, decode, encode
from followbus.msgs.perception import Detections
from followbus.msgs.tracking import Measurement
from followbus.nodes.capture import McapFrameSource

from . import test_record_replay
from .conftest import copy_recording, run_followbus

recorded = test_record_replay.recorded  # the module-scoped fixture: `launch --record` of a real graph

FRAME_ENCODING = "x-followbus-frame/1"
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
    """Everything it knows comes from the schema text: the magic, where N and the head are, the two ext
    codes, the header element names and the type's field names."""

    def __init__(self, text: str):
        def find(pattern: str) -> str:
            match = re.search(pattern, text, re.M)
            assert match, f"the schema document does not say {pattern!r}"
            return match.group(1)

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

    def read(self, data: bytes) -> dict[str, Any]:
        assert data[:len(self.magic)] == self.magic
        (n,) = struct.unpack_from("<I", data, self.length_at)
        head, blobs = data[self.head_at:self.head_at + n], data[self.head_at + n:]

        def ext_hook(code: int, ext: bytes) -> Array:
            if code == self.inline_code:
                dtype, shape, body = ext.split(b"\0", 2)
                return self.array(dtype.decode("ascii"), json.loads(shape), body, True)
            assert code == self.ref_code, code
            dtype, shape, offset, nbytes = msgpack.unpackb(ext)
            return self.array(dtype, shape, blobs[offset:offset + nbytes], False)

        out = msgpack.unpackb(head, ext_hook=ext_hook, raw=False)
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
    """Decode with both readers and assert they agree on every header element and field; the arrays met."""
    by_document = reader.read(data)
    msg: Message = decode(data)
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
            # Nothing else: every other channel must carry the custom label a reader can act on.
            assert channel.message_encoding == FRAME_ENCODING, channel
            assert schema is not None and schema.encoding == SCHEMA_ENCODING, channel.topic
            if schema.id not in readers:
                readers[schema.id] = DocumentReader(schema.data.decode("utf-8"))
            with pytest.raises(msgpack.ExtraData):  # why the old `msgpack` label was wrong
                msgpack.unpackb(message.data)
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
        compare(reader, encode(msg))


def test_a_wrong_document_is_caught():
    """The negative control: a document whose header order is wrong makes the comparison fail."""
    right = schema_document("Tick").decode()
    wrong = right.replace("0. seq (int)", "0. frame_seq (int)", 1).replace("2. frame_seq (int)", "2. seq (int)", 1)
    assert wrong != right
    data = encode(Tick(value=1, header=Header(seq=3, frame_seq=9)))
    compare(DocumentReader(right), data)
    with pytest.raises(AssertionError):
        compare(DocumentReader(wrong), data)


# --- recordings made before: labelled msgpack ----------------------------------------------------

def relabel_as_before(src: Path, dst: Path) -> None:
    """Rewrite a recording the way the recorder labelled bus channels before: `msgpack` messages with a
    `followbus-msgpack` schema (the same bytes); Foxglove channels and metadata unchanged."""

    def relabel(schema, channel) -> tuple[str, bytes, str]:
        if channel.message_encoding == FRAME_ENCODING:
            return "followbus-msgpack", b"{}", "msgpack"
        return schema.encoding, schema.data, channel.message_encoding

    copy_recording(src, dst, relabel=relabel, library="followbus before x-followbus-frame")


def test_recordings_labelled_msgpack_still_read_and_replay(recorded, tmp_path):
    old = tmp_path / "old.mcap"
    relabel_as_before(recorded.path, old)
    with open(old, "rb") as f:
        summary = make_reader(f).get_summary()
    assert "msgpack" in {ch.message_encoding for ch in summary.channels.values()}
    assert FRAME_ENCODING not in {ch.message_encoding for ch in summary.channels.values()}

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
