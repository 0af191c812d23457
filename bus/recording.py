"""Bus messages in MCAP files: the channel labels, the schema document, and reading.

The one place that reads recordings: the tools (record, play, replay, info, recover:
tools/recording/mcap_io.py writes and repairs) and nodes (capture reads a recording as its source) share it,
so it lives in bus/: it knows the frame (bus/codec.py) and the message registry, no application type. The
record-level parsing of the file (a chunk's fields, the records of an unfinalised file) is here too, once.

A bus channel is labelled ``message_encoding: msgpack`` (the MCAP registry's well-known value): each message
is one MessagePack array ``[head, blob area]`` (:data:`followbus.bus.codec.RECORD_FORMAT`), the frame's head
bytes as they were published and its blobs in a bin, so any MessagePack library decodes it and followbus gets
the frame back byte for byte (:func:`followbus.bus.codec.record_to_frame`, the one conversion, used by every
reader here; the writer, tools/recording/mcap_io.py, makes the array). Its schema ``followbus.<Type>``,
encoding ``x-followbus-schema/1``, is a UTF-8 text document: the array, the frame layout
(:data:`followbus.bus.codec.FRAME_FORMAT`) and the type's fields, enough to write a decoder from.
Recordings made before stored the frame itself: labelled ``x-followbus-frame/1``, or earlier ``msgpack``
(schema encoding ``followbus-msgpack``) on channels the recorder made (``bus_key`` in the channel metadata).
Both still read: a message is told by its first bytes (``FB1``: a frame, 0x92: the array).
"""

from __future__ import annotations

import dataclasses
import io
import logging
import os
import re
import stat
import struct
import types
import typing
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

from .codec import FRAME_FORMAT, RECORD_FORMAT, DecodeError, record_to_frame
from .schemas import SCHEMA_VERSION, SCHEMAS

log = logging.getLogger("followbus.recording")

BUS_MESSAGE_ENCODING = "msgpack"  # on a channel with "bus_key" metadata: a followbus frame, as RECORD_FORMAT says
BUS_SCHEMA_ENCODING = "x-followbus-schema/1"
BUS_SCHEMA_PREFIX = "followbus."
FRAME_MESSAGE_ENCODING = "x-followbus-frame/1"  # what recordings said before: the frame's own bytes


class RecordingError(Exception):
    """A recording that cannot be read for the requested purpose (exit status 2)."""


ON_CORRUPT = ("refuse", "skip")  # what play, replay do with a chunk that fails its CRC (refuse: the default)


def _utc(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]


@dataclass
class CorruptChunk:
    """A part of a recording that cannot be trusted: a chunk whose CRC does not match, or that does not even
    decompress or parse; or (``chunk`` False) bytes whose records do not hold together (a damaged header,
    a damaged length field), ``length`` of them."""
    offset: int  # of the chunk record (or the damaged bytes) in the file
    start_ns: int  # log times of its first and last message (a chunk's fields or the summary's chunk index)
    end_ns: int
    reason: str
    chunk: bool = True
    length: int = 0  # bytes dropped with it
    messages: int = 0  # messages dropped with it, when its message indexes tell
    repaired: bool = False  # read all the same (a chunk whose length field alone is damaged: its CRC passes)

    def describe(self) -> str:
        lost = f" ({self.messages} messages)" if self.messages else ""
        if not self.chunk:
            return f"{self.length} bytes at byte {self.offset}{lost}: {self.reason}"
        return (f"chunk at byte {self.offset}, messages {_utc(self.start_ns)} to {_utc(self.end_ns)} UTC "
                f"({(self.end_ns - self.start_ns) / 1e9:.2f} s){lost}: {self.reason}")


class CorruptChunkError(RecordingError):
    def __init__(self, path: str | Path, chunk: CorruptChunk):
        self.chunk = chunk
        super().__init__(f"{path}: corrupt {chunk.describe()}")


class CorruptRecording(RecordingError):
    """Parts of a recording failed their check and the caller did not ask to skip them."""

    def __init__(self, path: str | Path, chunks: list[CorruptChunk]):
        self.chunks = chunks
        more = f" (and {len(chunks) - 1} more corrupt parts)" if len(chunks) > 1 else ""
        super().__init__(f"{path}: corrupt {chunks[0].describe()}{more}; --on-corrupt skip reads the rest, "
                         f"`followbus recover {path}` rewrites the good chunks")


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
             f"(encoding \"{BUS_SCHEMA_ENCODING}\": this text).", "", RECORD_FORMAT, FRAME_FORMAT]
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
    """A channel of followbus messages: ``msgpack`` on a channel our recorder made (``bus_key`` names the bus key;
    its views carry it too, with their own encodings), or the label of recordings made before."""
    return channel.message_encoding == FRAME_MESSAGE_ENCODING or (
        channel.message_encoding == BUS_MESSAGE_ENCODING and "bus_key" in channel.metadata)


def stored_frame(data: bytes | memoryview) -> bytes:
    """The frame a bus channel's message holds (:func:`followbus.bus.codec.record_to_frame`, any form a
    recording has used); bytes that are none of them come back as they are, so that whoever decodes them
    counts a message that does not decode, as for a corrupt frame."""
    try:
        return record_to_frame(data)
    except DecodeError:
        return bytes(data)


# --- reading ---------------------------------------------------------------------------------------

@dataclass
class BusMessage:
    key: str
    type_name: str
    log_time: int
    data: bytes
    sequence: int = 0


MIN_RECORDING_BYTES = 45  # magic, a footer record, magic: no MCAP file is shorter


def open_recording(path: str | Path) -> IO[bytes]:
    """The file opened for reading; RecordingError for anything but a regular file (reading a FIFO waits for a
    writer for ever) or one too short to be an MCAP file."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise RecordingError(f"{path}: not a regular file")
        f = open(path, "rb")  # noqa: SIM115 (the caller's)
        if st.st_size < MIN_RECORDING_BYTES:
            with f:
                is_mcap = f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
            raise RecordingError(f"{path}: {st.st_size} bytes: too short to be an MCAP recording" if is_mcap
                                 else f"{path}: not an MCAP file")
        return f
    except OSError as exc:
        raise RecordingError(f"{path}: {exc.strerror}") from exc


def read_summary(path: str | Path):
    """The summary of a finalised recording; RecordingError for a file that was never finalised."""
    with open_recording(path) as f:
        try:
            summary = make_reader(f).get_summary()
        except (McapError, struct.error, ValueError, OSError, EOFError) as exc:
            f.seek(0)
            if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:  # not one a killed recorder left: recover cannot help
                raise RecordingError(f"{path}: not an MCAP file") from exc
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


def frame_channel(path: str | Path, frame_key: str = "") -> tuple[Any, str]:
    """(summary, key) of the raw-frame channel to read a recording's frames from (capture's MCAP source):
    ``frame_key``, else the bus key ending in ``/frame``. RecordingError when there is none."""
    summary = read_summary(path)
    topics = sorted({ch.topic for ch in summary.channels.values() if is_bus_channel(ch)})
    keys = [frame_key] if frame_key else [t for t in topics if t.endswith("/frame")]
    if not keys or keys[0] not in topics:
        raise RecordingError(f"{path}: no frame channel (bus keys: {', '.join(topics) or 'none'})")
    return summary, keys[0]


def _channel_ids(summary: Any, keys: Iterable[str] | None) -> set[int]:
    wanted = None if keys is None else set(keys)
    return {cid for cid, ch in summary.channels.items()
            if is_bus_channel(ch) and (wanted is None or ch.topic in wanted)}


def corrupt_chunks(path: str | Path, keys: Iterable[str] | None = None) -> list[CorruptChunk]:
    """The chunks (those holding bus messages of ``keys``; None: every chunk) whose CRC does not match their
    records, or that do not decompress: each chunk is read once, as a reader of it would."""
    import mmap

    summary = read_summary(path)
    ids = set(summary.channels) if keys is None else _channel_ids(summary, keys)
    bad: list[CorruptChunk] = []
    with open_recording(path) as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
        for index in summary.chunk_indexes:
            if keys is not None and not ids & set(index.message_index_offsets):
                continue
            try:
                _chunk_messages(mapped, str(path), index, summary, set())
            except CorruptChunkError as exc:
                bad.append(exc.chunk)
    return bad


def chunks_to_skip(path: str | Path, keys: Iterable[str] | None, on_corrupt: str) -> frozenset[int]:
    """Check the chunks a reader of ``keys`` will read: CorruptRecording when one is corrupt and ``on_corrupt``
    is ``refuse``; with ``skip``, each is logged (named by its time range) and its offset returned."""
    if on_corrupt not in ON_CORRUPT:
        raise ValueError(f"on_corrupt must be one of {', '.join(ON_CORRUPT)}, not {on_corrupt!r}")
    damaged = structure_damage(path)  # the header, the magic, the records between chunks: whatever keys are read
    bad = corrupt_chunks(path, keys)
    if (damaged or bad) and on_corrupt == "refuse":
        raise CorruptRecording(path, damaged + bad)
    for part in damaged + bad:
        log.warning("%s: skipping corrupt %s", path, part.describe())
    return frozenset(c.offset for c in bad)


def iter_bus_messages(path: str | Path, keys: Iterable[str] | None = None,
                      skip_chunks: frozenset[int] = frozenset()) -> Iterator[BusMessage]:
    """Bus messages in log-time order (ties: recording order), optionally only the given keys. Every chunk's CRC
    is checked as it is read: a corrupt one raises CorruptChunkError, unless its offset is in ``skip_chunks``
    (see :func:`chunks_to_skip`, which callers run first so that nothing is used before the damage is known)."""
    summary = read_summary(path)
    wanted = None if keys is None else set(keys)
    topics = sorted({ch.topic for ch in summary.channels.values() if is_bus_channel(ch)
                     and (wanted is None or ch.topic in wanted)})
    if not topics:
        return
    if summary.chunk_indexes:
        yield from _iter_chunked(path, summary, _channel_ids(summary, topics), skip_chunks)
        return
    with open_recording(path) as f:
        for _schema, channel, msg in make_reader(f).iter_messages(topics=topics, log_time_order=True):
            if is_bus_channel(channel):  # not a Foxglove channel that shares the topic
                yield BusMessage(channel.topic, channel.metadata.get("type", ""), msg.log_time,
                                 stored_frame(msg.data), msg.sequence)


MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_CHUNK_FIELDS = struct.Struct("<QQQII")  # message start, end, uncompressed size, crc, compression name length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


@dataclass
class ChunkFields:
    """What precedes a Chunk record's compressed records."""
    start_ns: int
    end_ns: int
    uncompressed_size: int
    compression: str
    records_size: int
    records_at: int  # where the compressed records start, in the buffer parsed
    crc: int = 0  # CRC-32 of the uncompressed records; 0: not computed by the writer


def chunk_fields(buf: Any, pos: int) -> ChunkFields:
    """The fields of the Chunk record whose body (past opcode and length) starts at ``pos`` of ``buf``."""
    start_ns, end_ns, size, crc, name_len = _CHUNK_FIELDS.unpack_from(buf, pos)
    pos += _CHUNK_FIELDS.size
    compression = bytes(buf[pos:pos + name_len]).decode()
    (records_size,) = struct.unpack_from("<Q", buf, pos + name_len)
    return ChunkFields(start_ns, end_ns, size, compression, records_size, pos + name_len + 8, crc)


@dataclass
class DataSection:
    """The top-level records of an unfinalised file, read without decompressing chunks."""
    end: int  # offset after the last complete record
    chunks: list[ChunkIndex]
    metadata: list[MetadataIndex]
    counts: dict[int, int]  # messages per channel id, from the message indexes
    schemas: list[Schema]  # top-level ones
    channels: list[Channel]


def scan_data_section(f: IO[bytes], end: int) -> DataSection:
    """Walk the top-level records of an MCAP file that may have no summary (a recorder killed or out of disk)
    up to ``end``, stopping at the last complete record: what finalising it in place needs."""
    f.seek(0)
    if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
        raise RecordingError(f"{getattr(f, 'name', '?')}: not an MCAP file")
    pos = good = len(MCAP_MAGIC)
    out = DataSection(pos, [], [], {}, [], [])
    open_chunk: ChunkIndex | None = None  # message indexes follow their chunk
    while pos + _RECORD_HEAD.size <= end:
        f.seek(pos)
        opcode, length = _RECORD_HEAD.unpack(f.read(_RECORD_HEAD.size))
        record_end = pos + _RECORD_HEAD.size + length
        if record_end > end or opcode in (Opcode.DATA_END, Opcode.FOOTER):
            break
        if opcode == Opcode.CHUNK:
            fields = chunk_fields(f.read(min(length, 4096)), 0)  # the fields, not the records
            open_chunk = ChunkIndex(message_start_time=fields.start_ns, message_end_time=fields.end_ns,
                                    chunk_start_offset=pos, chunk_length=record_end - pos, message_index_offsets={},
                                    message_index_length=0, compression=fields.compression,
                                    compressed_size=fields.records_size, uncompressed_size=fields.uncompressed_size)
            out.chunks.append(open_chunk)
        elif opcode == Opcode.MESSAGE_INDEX and open_chunk is not None:
            channel_id, entries_bytes = struct.unpack("<HI", f.read(6))
            open_chunk.message_index_offsets[channel_id] = pos
            open_chunk.message_index_length += record_end - pos
            out.counts[channel_id] = out.counts.get(channel_id, 0) + entries_bytes // 16
        else:
            open_chunk = None
            if opcode == Opcode.METADATA:
                (name_len,) = struct.unpack("<I", f.read(4))
                out.metadata.append(MetadataIndex(offset=pos, length=record_end - pos, name=f.read(name_len).decode()))
            elif opcode == Opcode.SCHEMA:
                out.schemas.append(Schema.read(ReadDataStream(f)))
            elif opcode == Opcode.CHANNEL:
                out.channels.append(Channel.read(ReadDataStream(f)))
        pos = good = record_end
    out.end = good
    return out


def _iter_chunked(path: str | Path, summary: Any, channel_ids: set[int],
                  skip_chunks: frozenset[int] = frozenset()) -> Iterator[BusMessage]:
    """What mcap's reader does in log-time order (a heap over chunks and their messages, ties by position),
    read straight from the chunk bytes: only chunks holding a wanted channel are decompressed and only wanted
    messages are copied. Several times faster than the generic reader on a recording of raw frames, where
    replaying a light node is bound by reading."""
    import heapq
    import mmap

    chunks = [c for c in summary.chunk_indexes if channel_ids & set(c.message_index_offsets)
              and c.chunk_start_offset not in skip_chunks]
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
    """The wanted messages of one chunk (a list: no view of the mapped file outlives this call); a corrupt chunk
    raises CorruptChunkError, once every view is released (an exception's frames would hold them)."""
    with memoryview(mapped) as whole:
        raw = whole[index.chunk_start_offset + 1:index.chunk_start_offset + index.chunk_length]  # past the opcode
        try:
            data, reason = _chunk_records(raw)
            messages = [] if data is None else list(_parse_records(data, summary, channel_ids))
            del data
        finally:
            raw.release()
    if reason:
        raise CorruptChunkError(name, CorruptChunk(index.chunk_start_offset, index.message_start_time,
                                                   index.message_end_time, reason))
    return messages


def _decompress(fields: ChunkFields, records: memoryview) -> memoryview:
    if fields.compression == "lz4":
        import lz4.frame

        return memoryview(lz4.frame.decompress(records))
    if fields.compression == "zstd":
        import zstandard

        return memoryview(zstandard.ZstdDecompressor().decompress(records, max_output_size=fields.uncompressed_size))
    if fields.compression == "":
        return records
    raise ValueError(f"compression {fields.compression!r} is not supported")


def _chunk_records(raw: memoryview) -> tuple[memoryview | None, str]:
    """(the uncompressed records of the chunk record ``raw`` (past its opcode), "") when they pass the chunk's
    CRC, else (None, why not)."""
    try:
        fields = chunk_fields(raw, 8)  # past the record length
        data = _decompress(fields, raw[fields.records_at:fields.records_at + fields.records_size])
    except Exception as exc:  # struct, decoding, a codec's own error on damaged bytes
        return None, f"unreadable ({type(exc).__name__}: {exc})"
    if len(data) != fields.uncompressed_size:
        return None, f"{len(data)} bytes where its header says {fields.uncompressed_size}"
    if fields.crc and zlib.crc32(data) != fields.crc:
        return None, "CRC mismatch"
    return data, ""


def _parse_records(data: memoryview, summary: Any, channel_ids: set[int]) -> Iterator[BusMessage]:
    pos, end = 0, len(data)
    while pos + _RECORD_HEAD.size <= end:
        op, length = _RECORD_HEAD.unpack_from(data, pos)
        body = pos + _RECORD_HEAD.size
        pos = body + length
        if op != Opcode.MESSAGE:
            continue
        channel_id, sequence, log_time, _publish = _MESSAGE_HEAD.unpack_from(data, body)
        if channel_id in channel_ids:
            channel = summary.channels[channel_id]
            yield BusMessage(channel.topic, channel.metadata.get("type", ""), log_time,
                             stored_frame(data[body + _MESSAGE_HEAD.size:pos]), sequence)


# --- the records of a file that may be damaged ------------------------------------------------------

_DATA_SECTION_RECORDS: dict[int, Any] = {
    Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.MESSAGE: Message,
    Opcode.CHUNK: Chunk, Opcode.MESSAGE_INDEX: MessageIndex, Opcode.ATTACHMENT: Attachment,
    Opcode.METADATA: Metadata, Opcode.DATA_END: DataEnd}
_PRIVATE_OPCODES = 0x80  # and above: records of other writers, skipped as the MCAP spec says
# Where a chunk or metadata record may start after damage: its opcode, then a length below 2**40 (three high bytes 0).
_RESYNC_AT = re.compile(rb"(?=[\x06\x0c].{5}\x00\x00\x00)", re.DOTALL)


class Unreadable(Exception):
    """The record at some offset does not hold together (its framing or its fields)."""


@dataclass
class ChunkFraming:
    """A chunk record checked by its fields only (``fields_only``): its records are not copied out."""
    fields: ChunkFields


def _record_at(buf: Any, pos: int, limit: int, index: Any = None, fields_only: bool = False) -> tuple[Any, int]:
    """(the record at ``pos`` of ``buf``, parsed by mcap's record classes, and the offset after it); None for a
    private record. Unreadable when it runs past ``limit``, has no place in the data section, or its fields do not
    fill it exactly. ``index``: the summary's ChunkIndex of a chunk there, whose opcode and length it gives,
    whatever the record's own bytes say; ``fields_only``: a chunk is checked by its fields (a ChunkFraming), its
    records not copied out."""
    if pos + _RECORD_HEAD.size > limit:
        raise Unreadable(f"{limit - pos} bytes: too short for a record")
    opcode, length = _RECORD_HEAD.unpack_from(buf, pos)
    if index is not None:
        opcode, length = Opcode.CHUNK, index.chunk_length - _RECORD_HEAD.size
    body, end = pos + _RECORD_HEAD.size, pos + _RECORD_HEAD.size + length
    if end > limit:
        raise Unreadable(f"a record (opcode 0x{opcode:02x}) of {length} bytes runs past byte {limit}")
    if opcode >= _PRIVATE_OPCODES:
        return None, end
    kind = _DATA_SECTION_RECORDS.get(opcode)
    if kind is None:
        raise Unreadable(f"opcode 0x{opcode:02x} has no place in the data section")
    if kind is Chunk and fields_only:
        try:
            fields = chunk_fields(buf, body)
        except (struct.error, UnicodeDecodeError) as exc:
            raise Unreadable(f"Chunk record: {type(exc).__name__}: {exc}") from None
        if fields.records_at + fields.records_size != end:
            raise Unreadable(f"Chunk record: its fields take {fields.records_at + fields.records_size - body} of "
                             f"its {length} bytes")
        return ChunkFraming(fields), end
    stream = ReadDataStream(io.BytesIO(buf[body:end]))
    try:
        record = kind.read(stream, length) if kind is Message else kind.read(stream)
    except Exception as exc:  # struct, EndOfFile, UnicodeDecodeError: whatever damaged bytes make of the fields
        raise Unreadable(f"{kind.__name__} record: {type(exc).__name__}: {exc}") from None
    if stream.count != length:
        raise Unreadable(f"{kind.__name__} record: its fields take {stream.count} of its {length} bytes")
    return record, end


def _passes(chunk: Any) -> bool:
    try:
        breakup_chunk(chunk, validate_crc=True)
    except Exception:
        return False
    return bool(chunk.uncompressed_crc)


def _trusted_at(buf: Any, pos: int, limit: int) -> bool:
    """Whether reading may resume at ``pos``: a chunk there passes its CRC (the one check that garbage, or the records
    inside a damaged uncompressed chunk, cannot pass by chance), or a metadata record (never inside a chunk) parses
    exactly and so does the record after it."""
    try:
        record, end = _record_at(buf, pos, limit)
        if isinstance(record, Chunk):
            return _passes(record)
        if not isinstance(record, Metadata):
            return False
        if end < limit:
            _record_at(buf, end, limit, fields_only=True)  # Unreadable when the record after it does not hold
        return True
    except Unreadable:
        return False


def _resync(buf: Any, start: int, limit: int, known: list[int]) -> int | None:
    """The offset of the next record to trust after damage at ``start``: the next one the summary indexes (chunks,
    metadata, attachments), else the next one :func:`_trusted_at` accepts."""
    later = [offset for offset in known if offset >= start]
    if later:
        return min(later)
    return next((m.start() for m in _RESYNC_AT.finditer(buf, start, limit) if _trusted_at(buf, m.start(), limit)),
                None)


def _chunk_by_fields(buf: Any, pos: int, limit: int) -> tuple[Any, int] | None:
    """A chunk whose length field alone is damaged, read by its own fields (its records' size), when its CRC passes."""
    if buf[pos] != Opcode.CHUNK:
        return None
    try:
        fields = chunk_fields(buf, pos + _RECORD_HEAD.size)
        end = fields.records_at + fields.records_size
        if end > limit:
            return None
        chunk = Chunk.read(ReadDataStream(io.BytesIO(buf[pos + _RECORD_HEAD.size:end])))
    except Exception:
        return None
    return (chunk, end) if _passes(chunk) else None


@dataclass
class _Layout:
    """What the end of a finalised file says of its data section: where it ends, and the offsets it indexes."""
    summary: Any = None
    data_end: int = 0
    chunks: dict[int, Any] = field(default_factory=dict)  # offset -> ChunkIndex
    known: list[int] = field(default_factory=list)  # offsets of indexed records (chunks, metadata, attachments)
    summary_damage: str = ""


def _layout(f: IO[bytes], buf: Any) -> _Layout:
    """The summary of ``f`` if its footer and summary hold (their CRC checked), else only where its data may end."""
    out = _Layout(data_end=len(buf))
    try:
        summary = make_reader(f).get_summary()
        tail = len(buf) - len(MCAP_MAGIC)
        footer = Footer.read(ReadDataStream(io.BytesIO(buf[tail - 20:tail])))  # its fields, past opcode and length
    except Exception:
        return out  # unfinalised (a killed recorder), or its end is damaged: walked to the end of the file
    if summary is None or not footer.summary_start:
        return out
    crc_end = len(buf) - len(MCAP_MAGIC) - 4
    if footer.summary_crc and zlib.crc32(buf[footer.summary_start:crc_end]) != footer.summary_crc:
        out.summary_damage = f"the summary at byte {footer.summary_start} fails its CRC"
        return out
    out.summary, out.data_end = summary, footer.summary_start
    out.chunks = {ci.chunk_start_offset: ci for ci in summary.chunk_indexes}
    out.known = sorted([*out.chunks, *(m.offset for m in summary.metadata_indexes),
                        *(a.offset for a in summary.attachment_indexes)])
    return out


def _walk(buf: Any, layout: _Layout, damage: list[CorruptChunk],
          fields_only: bool = False) -> Iterator[tuple[int, Any]]:
    """(offset, record) of every top-level record of the data section that holds together, up to DataEnd; damaged
    bytes are appended to ``damage`` and skipped to the next record to trust (:func:`_resync`)."""
    pos = len(MCAP_MAGIC)
    while pos < layout.data_end:
        try:
            record, end = _record_at(buf, pos, layout.data_end, layout.chunks.get(pos), fields_only)
        except Unreadable as exc:
            repaired = _chunk_by_fields(buf, pos, layout.data_end)
            if repaired is not None:
                record, end = repaired
                damage.append(CorruptChunk(pos, record.message_start_time, record.message_end_time,
                                           f"its length field is damaged ({exc}); read by its own fields, its CRC "
                                           "passes", repaired=True))
                yield pos, (ChunkFraming(chunk_fields(buf, pos + _RECORD_HEAD.size)) if fields_only else record)
                pos = end
                continue
            resumed = _resync(buf, pos + 1, layout.data_end, layout.known)
            damage.append(CorruptChunk(pos, 0, 0, str(exc), chunk=False,
                                       length=(layout.data_end if resumed is None else resumed) - pos))
            if resumed is None:
                return
            pos = resumed
            continue
        if record is None:  # a private record: another writer's (never followbus's), or a damaged opcode byte
            damage.append(CorruptChunk(pos, 0, 0, f"a private record (opcode 0x{buf[pos]:02x}), skipped",
                                       chunk=False, length=end - pos))
            pos = end
            continue
        index = layout.chunks.get(pos)
        if index is not None and _RECORD_HEAD.unpack_from(buf, pos) != (Opcode.CHUNK, end - pos - _RECORD_HEAD.size):
            damage.append(CorruptChunk(pos, index.message_start_time, index.message_end_time, "its opcode or length "
                                       "field disagrees with the summary's chunk index, which is followed",
                                       repaired=True))
        yield pos, record
        if isinstance(record, DataEnd):
            return
        pos = end


def _framing_doubts(walked: list[tuple[int, Any]], damage: list[CorruptChunk]) -> list[CorruptChunk]:
    """A data section that does not start with its Header."""
    out = []
    header_damaged = any(d.offset == len(MCAP_MAGIC) for d in damage)
    if not header_damaged and (not walked or not isinstance(walked[0][1], Header)):
        out.append(CorruptChunk(len(MCAP_MAGIC), 0, 0, "no Header record after the magic", chunk=False))
    return out


def structure_damage(path: str | Path) -> list[CorruptChunk]:
    """What is wrong with a recording besides its chunks' contents (:func:`corrupt_chunks`): its magic, its header,
    the framing of the records from the header to the summary (a damaged length field, garbage between records),
    the summary's CRC. Chunk bodies are not read: this is cheap."""
    import mmap

    damage: list[CorruptChunk] = []
    with open_recording(path) as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        if buf[:len(MCAP_MAGIC)] != MCAP_MAGIC:
            damage.append(CorruptChunk(0, 0, 0, "not the MCAP magic", chunk=False, length=len(MCAP_MAGIC)))
        layout = _layout(f, buf)
        if layout.summary_damage:
            damage.append(CorruptChunk(layout.data_end, 0, 0, layout.summary_damage, chunk=False))
        walked = list(_walk(buf, layout, damage, fields_only=True))
        damage += _framing_doubts(walked, damage)
    return sorted(damage, key=lambda d: d.offset)


# --- salvaging a damaged file ----------------------------------------------------------------------

@dataclass
class Salvage:
    """What reading a possibly truncated or corrupt file found besides its records."""
    chunks: int = 0  # chunks read whole (their CRC passes)
    compression: str | None = None  # of its first chunk ("none" when uncompressed)
    complete: bool = False  # its footer and summary were there and hold: the file was finalised
    stopped_by: str = ""  # why reading stopped before the end of the data section (the cut of a killed recorder)
    damage: list[CorruptChunk] = field(default_factory=list)  # what was dropped (bad chunks, damaged bytes)
    # Schema or channel records read from a damaged chunk, for want of any other copy: named, so that they
    # can be checked (a record a flipped bit hit would name a wrong topic or type).
    doubtful: list[str] = field(default_factory=list)

    @property
    def bad_chunks(self) -> int:
        return sum(1 for d in self.damage if d.chunk)


def _definitions(chunk: Any) -> list[Any]:
    """The Schema and Channel records of a chunk that failed its CRC, as far as its records still parse."""
    out: list[Any] = []
    try:
        stream, size = get_chunk_data_stream(chunk, validate_crc=False)
        while stream.count < size:
            opcode, length = stream.read1(), stream.read8()
            start = stream.count
            if opcode == Opcode.SCHEMA:
                out.append(Schema.read(stream))
            elif opcode == Opcode.CHANNEL:
                out.append(Channel.read(stream))
            else:
                stream.read(length)
            if stream.count != start + length:
                break
    except Exception:  # what follows the damage does not parse
        pass
    return out


def salvage_records(path: str | Path, found: Salvage) -> Iterator[Any]:
    """Every record of an MCAP file that can still be trusted, in file order, chunks broken up into their records
    (Header, Schema, Channel, Message, Metadata, Attachment): the summary's schemas and channels first, when the
    file has a summary (a chunk that holds the only other copy may be the damaged one); every chunk whose CRC
    passes, whichever chunk is bad; after damaged bytes (a damaged header, a damaged length field) reading
    resumes at the next record the summary indexes, else the next chunk whose CRC passes. ``found`` is filled in
    as it goes: what was dropped, and why reading stopped (``followbus recover`` rewrites the records)."""
    import mmap

    with open_recording(path) as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        layout = _layout(f, buf)
        found.complete = layout.summary is not None
        if layout.summary is not None:
            yield from layout.summary.schemas.values()
            yield from layout.summary.channels.values()
        walked: list[CorruptChunk] = []
        last_bad: CorruptChunk | None = None
        for offset, record in _walk(buf, layout, walked):
            found.damage.extend(walked)
            walked.clear()
            if isinstance(record, MessageIndex):
                if last_bad is not None:
                    last_bad.messages += len(record.records)
                continue
            last_bad = None
            if isinstance(record, Chunk):
                last_bad = yield from _salvage_chunk(path, offset, record, layout, found)
            elif not isinstance(record, DataEnd):
                yield record
        if walked and layout.summary is None and walked[-1].offset + walked[-1].length == layout.data_end:
            found.stopped_by = walked.pop().reason  # the cut of a file its recorder never finished
        found.damage.extend(walked)


def _salvage_chunk(path: str | Path, offset: int, chunk: Any, layout: _Layout,
                   found: Salvage) -> Iterator[Any]:
    """A chunk's records when its CRC passes; else nothing but the schema and channel records nothing else defines
    (a damaged chunk's, named in ``found.doubtful``), and its damage record, returned (its message indexes follow)."""
    found.compression = found.compression or chunk.compression or "none"
    try:
        records = breakup_chunk(chunk, validate_crc=True)
    except Exception as exc:  # a corrupt chunk body (any codec error): skipped, the rest kept
        bad = CorruptChunk(offset, chunk.message_start_time, chunk.message_end_time,
                           str(exc) if isinstance(exc, ValueError) and "crc" in str(exc) else
                           f"unreadable ({type(exc).__name__}: {exc})")
        found.damage.append(bad)
        log.warning("%s: skipping corrupt %s", path, bad.describe())
        for record in [] if layout.summary is not None else _definitions(chunk):  # the summary has them all
            found.doubtful.append(f"{type(record).__name__.lower()} {record.id}"
                                  + (f" ({record.topic})" if isinstance(record, Channel) else f" ({record.name})"))
            yield record
        return bad
    found.chunks += 1
    yield from records
    return None
