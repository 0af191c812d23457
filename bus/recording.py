"""Bus messages in MCAP files: the channel labels, the schema document, and reading.

Shared by the tools (record, play, replay, info: tools/recording/mcap_io.py writes) and by nodes (capture reads a
recording as its source), so it lives in bus/: it knows the frame (bus/codec.py) and the message types,
nothing of tracking.

A bus channel is labelled ``message_encoding: x-followbus-frame/1``: a custom encoding in the MCAP
spec's sense (custom values take the ``x-`` prefix), because the bytes are a followbus frame (magic,
length, MessagePack head, array blobs), not plain MessagePack: ``msgpack.unpackb`` of one raises
ExtraData. Its schema ``followbus.<Type>``, encoding ``x-followbus-schema/1``, is a UTF-8 text
document: the frame layout (:data:`followbus.bus.codec.FRAME_FORMAT`) and the type's fields, enough to
write a decoder from. Recordings made before this carried ``msgpack`` (schema encoding
``followbus-msgpack``) on the same bytes: read as an alias on channels the recorder made (``bus_key``
in the channel metadata).
"""

from __future__ import annotations

import dataclasses
import struct
import types
import typing
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Metadata
from mcap.stream_reader import StreamReader

from .codec import FRAME_FORMAT
from .schemas import SCHEMA_VERSION, SCHEMAS

BUS_MESSAGE_ENCODING = "x-followbus-frame/1"
BUS_SCHEMA_ENCODING = "x-followbus-schema/1"
BUS_SCHEMA_PREFIX = "followbus."
LEGACY_MESSAGE_ENCODING = "msgpack"  # what recordings said before; the bytes were the same frame


class RecordingError(Exception):
    """A recording that cannot be read for the requested purpose (exit status 2)."""


# --- the schema document ---------------------------------------------------------------------------

def _wire_type(hint: Any) -> str:
    """A field's annotation in the frame's terms (what a reader finds in the head map)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        kinds = [_wire_type(a) for a in args if a is not type(None)]
        return " or ".join(kinds) + (" or nil" if type(None) in args else "")
    if origin is list:
        return f"array of {_wire_type(args[0])}" if args else "array"
    if origin is dict:
        return f"map {_wire_type(args[0])} -> {_wire_type(args[1])}" if args else "map"
    return {int: "int", float: "float (an int is accepted)", bool: "bool", str: "str",
            typing.Any: "any"}.get(hint, "numpy array (ext type)" if getattr(hint, "__name__", "") == "ndarray"
                                   else getattr(hint, "__name__", str(hint)))


def schema_document(type_name: str) -> bytes:
    """The schema data of a bus channel: how to decode its messages, as UTF-8 text."""
    cls = SCHEMAS.get(type_name)
    lines = [f"{BUS_SCHEMA_PREFIX}{type_name}",
             f"Messages of channels with message_encoding \"{BUS_MESSAGE_ENCODING}\" and this schema "
             f"(encoding \"{BUS_SCHEMA_ENCODING}\": this text).", "", FRAME_FORMAT]
    if cls is None:
        lines.append(f"FIELDS of {type_name}: unknown to the recorder (a type of a newer or other build).")
    else:
        hints = typing.get_type_hints(cls)
        lines.append(f"FIELDS of {type_name} (VERSION {SCHEMA_VERSION}), the head keys after the header:")
        lines += [f"  {f.name}: {_wire_type(hints[f.name])}" for f in dataclasses.fields(cls) if f.name != "header"]
        doc = " ".join((cls.__doc__ or "").split())
        if doc and not doc.startswith(f"{cls.__name__}("):  # not the dataclass's generated signature
            lines += ["", doc]
    return ("\n".join(lines) + "\n").encode()


def is_bus_channel(channel: Channel) -> bool:
    """A channel of followbus frames: the current label, or the old one on a channel our recorder made."""
    return channel.message_encoding == BUS_MESSAGE_ENCODING or (
        channel.message_encoding == LEGACY_MESSAGE_ENCODING and "bus_key" in channel.metadata)


# --- reading ---------------------------------------------------------------------------------------

@dataclass
class BusMessage:
    key: str
    type_name: str
    log_time: int
    data: bytes
    sequence: int = 0


def open_recording(path: str | Path) -> IO[bytes]:
    try:
        return open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror}") from exc


def read_summary(path: str | Path):
    """The summary of a finalised recording; RecordingError for a file that was never finalised."""
    with open_recording(path) as f:
        try:
            summary = make_reader(f).get_summary()
        except (McapError, struct.error, ValueError) as exc:
            raise RecordingError(f"{path}: not a finalised MCAP file ({exc}); a recorder that was killed leaves "
                                 f"one that `followbus recover {path}` repairs") from exc
    if summary is None:
        raise RecordingError(f"{path}: MCAP file without summary; `followbus recover {path}` rewrites it")
    return summary


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """Every metadata record by name (the last one wins); works on unfinalised files too."""
    out: dict[str, dict[str, str]] = {}
    with open_recording(path) as f:
        try:
            for record in StreamReader(f, emit_chunks=True).records:
                if isinstance(record, Metadata):
                    out[record.name] = dict(record.metadata)
        except (McapError, struct.error, ValueError, EOFError):
            pass  # a truncated file: whatever came before the cut
    return out


def bus_channels(path: str | Path) -> dict[str, str]:
    """Bus key -> message type of every bus channel in a finalised recording."""
    summary = read_summary(path)
    return {ch.topic: ch.metadata.get("type", "") for ch in summary.channels.values() if is_bus_channel(ch)}


def iter_bus_messages(path: str | Path, keys: Iterable[str] | None = None) -> Iterator[BusMessage]:
    """Bus messages in log-time order (ties: recording order), optionally only the given keys."""
    summary = read_summary(path)
    wanted = None if keys is None else set(keys)
    topics = sorted({ch.topic for ch in summary.channels.values() if is_bus_channel(ch)
                     and (wanted is None or ch.topic in wanted)})
    if not topics:
        return
    if summary.chunk_indexes:
        yield from _iter_chunked(path, summary, {cid for cid, ch in summary.channels.items()
                                                 if is_bus_channel(ch) and ch.topic in topics})
        return
    with open_recording(path) as f:
        for _schema, channel, msg in make_reader(f).iter_messages(topics=topics, log_time_order=True):
            if is_bus_channel(channel):  # not a Foxglove channel that shares the topic
                yield BusMessage(channel.topic, channel.metadata.get("type", ""), msg.log_time, msg.data,
                                 msg.sequence)


_CHUNK_HEAD = struct.Struct("<QQQQII")  # record length, start, end, uncompressed size, crc, compression length
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_OP_MESSAGE = 0x05


def _iter_chunked(path: str | Path, summary: Any, channel_ids: set[int]) -> Iterator[BusMessage]:
    """What mcap's reader does in log-time order (a heap over chunks and their messages, ties by position),
    read straight from the chunk bytes: only chunks holding a wanted channel are decompressed and only wanted
    messages are copied. Several times faster than the generic reader on a recording of raw frames, where
    replaying a light node is bound by reading."""
    import heapq
    import mmap

    chunks = [c for c in summary.chunk_indexes if channel_ids & set(c.message_index_offsets)]
    heap: list[tuple[int, int, int, Any]] = [(c.message_start_time, c.chunk_start_offset, -1, c) for c in chunks]
    heapq.heapify(heap)
    with open_recording(path) as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
        while heap:
            log_time, offset, index, item = heapq.heappop(heap)
            if index >= 0:
                yield item
                continue
            for i, msg in enumerate(_chunk_messages(mapped, str(path), item, summary, channel_ids)):
                heapq.heappush(heap, (msg.log_time, offset, i, msg))


def _chunk_messages(mapped: Any, name: str, index: Any, summary: Any, channel_ids: set[int]) -> list[BusMessage]:
    """The wanted messages of one chunk (a list: no view of the mapped file outlives this call)."""
    with memoryview(mapped) as whole:
        raw = whole[index.chunk_start_offset + 1:index.chunk_start_offset + index.chunk_length]  # past the opcode
        try:
            return list(_parse_chunk(raw, name, index, summary, channel_ids))
        finally:
            raw.release()


def _parse_chunk(raw: memoryview, name: str, index: Any, summary: Any, channel_ids: set[int]) -> Iterator[BusMessage]:
    try:
        _length, _start, _end, size, _crc, name_len = _CHUNK_HEAD.unpack_from(raw)
        pos = _CHUNK_HEAD.size
        compression = bytes(raw[pos:pos + name_len]).decode()
        pos += name_len
        (records_len,) = struct.unpack_from("<Q", raw, pos)
        pos += 8
        records = raw[pos:pos + records_len]
        if compression == "lz4":
            import lz4.frame

            data = memoryview(lz4.frame.decompress(records))
        elif compression == "zstd":
            import zstandard

            data = memoryview(zstandard.ZstdDecompressor().decompress(records, max_output_size=size))
        elif compression == "":
            data = records
        else:
            raise RecordingError(f"{name}: chunk compression {compression!r} is not supported")
    except (struct.error, RuntimeError, ValueError) as exc:
        raise RecordingError(f"{name}: chunk at {index.chunk_start_offset} unreadable ({exc})") from exc
    pos, end = 0, len(data)
    while pos + _RECORD_HEAD.size <= end:
        op, length = _RECORD_HEAD.unpack_from(data, pos)
        body = pos + _RECORD_HEAD.size
        pos = body + length
        if op != _OP_MESSAGE:
            continue
        channel_id, sequence, log_time, _publish = _MESSAGE_HEAD.unpack_from(data, body)
        if channel_id in channel_ids:
            channel = summary.channels[channel_id]
            yield BusMessage(channel.topic, channel.metadata.get("type", ""), log_time,
                             bytes(data[body + _MESSAGE_HEAD.size:pos]), sequence)
