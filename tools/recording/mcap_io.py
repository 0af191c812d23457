"""Writing MCAP files of followbus: the bus channels (exact frame bytes, one channel per key and type),
the Foxglove channels beside them, metadata; finalising a cut file in place, ``followbus info`` and
``followbus recover``. Reading them is bus/recording.py's (nodes read recordings too).

Layout of a recording:

- bus channels: topic = the bus key (``fb/capture/frame``), message encoding ``msgpack``: the MessagePack
  array ``[head, blob area]`` of the followbus frame (bus/codec.py RECORD_FORMAT; callers of ``write`` give
  the frame, the writer converts it, readers get the exact frame back), schema ``followbus.<TYPE>`` with
  encoding ``x-followbus-schema/1`` whose data is a text document of the array, the frame layout and the
  type's fields (bus/recording.py). ``sequence`` = header.seq,
  log_time = publish_time = header.stamp_ns (receive time only when the stamp is 0). Recordings made
  before stored the frame itself (``x-followbus-frame/1``, earlier ``msgpack``): they still read.
- view channels beside them, so every message decodes without followbus (tools/recording/views.py):
  ``<key>/image`` (sensor_msgs/msg/CompressedImage or Image), ``<key>/twist``, ``<key>/odometry``,
  ``<key>/detections2d`` (ROS 2 CDR, ``ros2msg`` schemas), ``<key>/json`` (JSON + JSON Schema) and
  ``<key>/annotations`` (foxglove.ImageAnnotations); channel metadata ``bus_key`` names their source.
- metadata records ``followbus`` (version, git commit, host, start time, ...), ``graph`` (graph.yaml
  text), ``params`` (each node's effective params as JSON) and, when the recorder stopped cleanly,
  ``recording_stats``.
"""

from __future__ import annotations

import contextlib
import os
import struct
import sys
import time
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from ...bus.codec import DecodeError, frame_to_record
from ...bus.recording import (
    BUS_MESSAGE_ENCODING,
    BUS_SCHEMA_ENCODING,
    BUS_SCHEMA_PREFIX,
    RecordingError,
    Salvage,
    corrupt_chunks,
    open_recording,
    read_metadata,
    read_summary,
    salvage_records,
    scan_data_section,
    schema_document,
    structure_damage,
)
from .. import __version__
from . import foxglove_schemas as fox

PROFILE = ""  # no ROS profile: ROS 2 CDR channels beside our own and JSON ones
ROS2_PROFILE = "ros2"  # the companion file of ROS 2 channels only (rosbags and rosbag2 require the profile)
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
# Uncompressed by default: lz4 shrinks raw frames by 1-3 % and every read decompresses whole chunks; zstd level 3,
# the mcap writer's, saturates its thread at 720p 30 Hz. Figures and command: tools/recording/record.py docstring.
DEFAULT_COMPRESSION = "none"
DEFAULT_CHUNK_BYTES = 4 * 1024 * 1024


# --- writing ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _FoxgloveSchema:
    name: str
    encoding: str
    data: bytes
    message_encoding: str


class RecordingWriter:
    """An mcap Writer that registers schemas and channels on first use and flushes whole chunks.

    It closes chunks itself (at ``chunk_bytes`` or on ``flush()``), so the file is consistent up to
    ``durable_offset`` after every chunk: after a write error (full disk, EIO, EFBIG) the writer's state
    is unknown, and ``finish_after_failure`` cuts the file back to that offset and finalises it there.
    """

    def __init__(self, path: str | Path, compression: str = DEFAULT_COMPRESSION,
                 chunk_bytes: int = DEFAULT_CHUNK_BYTES, profile: str = PROFILE):
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._created = not self.path.exists()  # discard() deletes only a file it created (never /dev/null)
        self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 (closed by finish)
        # The mcap Writer never closes a chunk on its own (chunk_size out of reach): write() does, so
        # every chunk end is a point where durable_offset and durable_counts are known.
        self._writer = Writer(self._file, chunk_size=1 << 62, compression=COMPRESSIONS[compression])
        self._chunk_bytes = chunk_bytes
        self._pending_bytes = 0
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[tuple[str, str, str], int] = {}
        self._schema_records: dict[int, Schema] = {}  # the summary after a failure repeats them
        self._channel_records: dict[int, Channel] = {}
        self._bus_topics: dict[int, str] = {}  # bus channel id -> key
        self._pending_counts: dict[str, int] = {}
        self.durable_counts: dict[str, int] = {}  # bus messages per key in complete, flushed chunks
        self.durable_offset = 0  # the file is consistent up to here
        self.durable_monotonic = time.monotonic()  # when it last was
        self.messages = 0
        self.compression = compression
        self._writer.start(profile=profile, library=f"followbus/{__version__}")
        self._durable()

    def _durable(self) -> None:
        self._file.flush()
        self.durable_offset = self._file.tell()
        self.durable_monotonic = time.monotonic()

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding)
        if key not in self._schemas:
            sid = self._writer.register_schema(name=name, encoding=encoding, data=data)
            self._schemas[key] = sid
            self._schema_records[sid] = Schema(id=sid, name=name, encoding=encoding, data=data)
        return self._schemas[key]

    def _register_channel(self, topic: str, message_encoding: str, schema_id: int, meta: dict[str, str]) -> int:
        cid = self._writer.register_channel(topic=topic, message_encoding=message_encoding, schema_id=schema_id,
                                            metadata=meta)
        self._channel_records[cid] = Channel(id=cid, topic=topic, message_encoding=message_encoding,
                                             schema_id=schema_id, metadata=dict(meta))
        return cid

    def bus_channel(self, key: str, type_name: str | None) -> int:
        """The channel of a bus key; a payload that is not a followbus message gets one without schema."""
        ident = (key, BUS_MESSAGE_ENCODING, type_name or "")
        if ident not in self._channels:
            schema_id = 0
            meta = {"bus_key": key}
            if type_name:
                schema_id = self.schema(BUS_SCHEMA_PREFIX + type_name, BUS_SCHEMA_ENCODING,
                                        schema_document(type_name))
                meta["type"] = type_name
            cid = self._register_channel(key, BUS_MESSAGE_ENCODING, schema_id, meta)
            self._channels[ident] = cid
            self._bus_topics[cid] = key
        return self._channels[ident]

    def view_channel(self, topic: str, schema: Any, source_key: str) -> int:
        """The channel of a view of a bus key (tools/recording/views.py): ``schema`` has name, encoding, data
        and the message_encoding of its messages."""
        ident = (topic, schema.message_encoding, schema.name)
        if ident not in self._channels:
            schema_id = self.schema(schema.name, schema.encoding, schema.data)
            self._channels[ident] = self._register_channel(topic, schema.message_encoding, schema_id,
                                                           {"bus_key": source_key})
        return self._channels[ident]

    def foxglove_channel(self, topic: str, schema_name: str, source_key: str) -> int:
        schema = _FoxgloveSchema(schema_name, fox.SCHEMA_ENCODING, fox.schema_bytes(schema_name), fox.MESSAGE_ENCODING)
        return self.view_channel(topic, schema, source_key)

    @property
    def size_bytes(self) -> int:
        """What the file will hold once the chunk in progress is written (for --split-size)."""
        return self.durable_offset + self._pending_bytes

    def write(self, channel_id: int, log_time: int, data: bytes, publish_time: int | None = None,
              sequence: int = 0) -> None:
        """``data``: a view's payload, or on a bus channel the message's frame as it travelled on the bus."""
        key = self._bus_topics.get(channel_id)
        if key is not None:
            data = _bus_record(data)
        self._writer.add_message(channel_id=channel_id, log_time=log_time, data=data,
                                 publish_time=log_time if publish_time is None else publish_time,
                                 sequence=sequence & 0xFFFFFFFF)
        self.messages += 1
        if key is not None:
            self._pending_counts[key] = self._pending_counts.get(key, 0) + 1
        self._pending_bytes += len(data) + 31  # + the Message record's own fields
        if self._pending_bytes >= self._chunk_bytes:
            self.flush()

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})
        self._durable()  # a top-level record: the open chunk is still in memory, the file is consistent

    def flush(self) -> None:
        """Close the chunk in progress and push it to the OS: it survives a SIGKILL from now on."""
        self._writer.flush()
        self._pending_bytes = 0
        self._commit_counts()
        self._durable()

    def _commit_counts(self) -> None:
        for key, n in self._pending_counts.items():
            self.durable_counts[key] = self.durable_counts.get(key, 0) + n
        self._pending_counts.clear()

    def finish(self) -> None:
        self._writer.finish()
        self._file.close()
        self._commit_counts()

    def discard(self) -> None:
        """Close the file and delete it if this writer created it (nothing worth keeping was written)."""
        with contextlib.suppress(OSError):
            self._file.close()
        if self._created and self.path.is_file():
            with contextlib.suppress(OSError):
                self.path.unlink()

    def finish_after_failure(self, metadata: Iterable[tuple[str, dict[str, str]]] = ()) -> FinaliseResult:
        """After a write error: cut the file back to ``durable_offset`` (dropping the chunk that failed)
        and finalise it there with ``metadata`` appended. Raises OSError when even that cannot be written;
        the file is then left cut at ``durable_offset``, every chunk complete, for ``followbus recover``."""
        with contextlib.suppress(OSError):  # closing flushes what is buffered: that fails again
            self._file.close()
        return finalise_in_place(self.path, self.durable_offset, self._schema_records.values(),
                                 self._channel_records.values(), metadata)


def _bus_record(frame: bytes) -> bytes:
    """What a bus channel stores for ``frame``: its MessagePack array; a payload that is no frame (a foreign
    publisher's bytes on a recorded key) is kept as it came, and reads back as such, counted as undecodable."""
    try:
        return frame_to_record(frame)
    except DecodeError:
        return frame


@dataclass
class FinaliseResult:
    chunks: int
    messages: int
    channel_counts: dict[str, int]  # messages per topic in the finalised file
    cut_bytes: int  # bytes dropped behind the last complete chunk
    file_bytes: int


def finalise_in_place(path: str | Path, end_offset: int, schemas: Iterable[Schema], channels: Iterable[Channel],
                      metadata: Iterable[tuple[str, dict[str, str]]] = ()) -> FinaliseResult:
    """Finalise an unfinished MCAP file where it stands, needing only a few kB more on disk (``recover``
    writes a whole new file): cut it after the last complete record at or before ``end_offset``, append
    ``metadata``, the summary (``schemas`` and ``channels``, usually kept in memory by the writer, plus
    any found at top level; statistics, chunk and metadata indexes) and the footer.

    Raises OSError when the file cannot be cut or appended to; it is then left cut at the last complete
    record, so ``followbus recover`` still salvages every complete chunk."""
    path = Path(path)
    # Unbuffered: a buffered file would retry its failed buffer on truncate() and close().
    with open(path, "r+b", buffering=0) as f:
        size = os.fstat(f.fileno()).st_size
        found = scan_data_section(f, min(end_offset, size))
        good = found.end
        f.truncate(good)
        try:
            return _append_summary(f, good, size - good, found.chunks, found.metadata, found.counts,
                                   {s.id: s for s in [*found.schemas, *schemas]},
                                   {c.id: c for c in [*found.channels, *channels]}, metadata)
        except OSError:
            with contextlib.suppress(OSError):  # leave a clean cut for `followbus recover`
                f.truncate(good)
            raise


def _append_summary(f: IO[bytes], good: int, cut: int, chunk_indexes: list[ChunkIndex],
                    meta_indexes: list[MetadataIndex], counts: dict[int, int], schemas: dict[int, Schema],
                    channels: dict[int, Channel], metadata: Iterable[tuple[str, dict[str, str]]]) -> FinaliseResult:
    """Append metadata records, DataEnd, summary and footer at ``good`` (what mcap's Writer.finish writes)."""
    builder = RecordBuilder()
    for name, data in metadata:
        start = builder.count
        Metadata(name=name, metadata={k: str(v) for k, v in data.items()}).write(builder)
        meta_indexes.append(MetadataIndex(offset=good + start, length=builder.count - start, name=name))
    DataEnd(0).write(builder)
    summary_start = good + builder.count
    times = [(ci.message_start_time, ci.message_end_time) for ci in chunk_indexes]
    stats = Statistics(
        message_count=sum(counts.values()), schema_count=len(schemas), channel_count=len(channels),
        attachment_count=0, metadata_count=len(meta_indexes), chunk_count=len(chunk_indexes),
        message_start_time=min((t[0] for t in times), default=0),
        message_end_time=max((t[1] for t in times), default=0),
        channel_message_counts=dict(counts))
    summary = RecordBuilder()
    offsets: list[SummaryOffset] = []
    groups: list[tuple[Opcode, list[Any]]] = [
        (Opcode.SCHEMA, list(schemas.values())), (Opcode.CHANNEL, list(channels.values())),
        (Opcode.STATISTICS, [stats]), (Opcode.CHUNK_INDEX, chunk_indexes), (Opcode.ATTACHMENT_INDEX, []),
        (Opcode.METADATA_INDEX, meta_indexes)]
    for opcode, records in groups:
        group_start = summary.count
        for record in records:
            record.write(summary)
        offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + group_start,
                                     group_length=summary.count - group_start))
    summary_offset_start = summary_start + summary.count
    for offset in offsets:
        offset.write(summary)
    summary_data = summary.end()
    crc = zlib.crc32(summary_data)
    crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
    tail = RecordBuilder()
    Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(tail)
    f.seek(good)
    data = memoryview(builder.end() + summary_data + tail.end() + MCAP0_MAGIC)
    while data:
        data = data[f.write(data) or 0:]  # a short write is followed by one that raises (ENOSPC, EFBIG)
    os.fsync(f.fileno())  # a failure to store it must show here, not at a later close
    by_topic: dict[str, int] = {}
    for cid, n in counts.items():
        topic = channels[cid].topic if cid in channels else str(cid)
        by_topic[topic] = by_topic.get(topic, 0) + n
    return FinaliseResult(chunks=len(chunk_indexes), messages=stats.message_count, channel_counts=by_topic,
                          cut_bytes=cut, file_bytes=f.tell())


# --- recover ---------------------------------------------------------------------------------------

@dataclass
class RecoverResult:
    chunks: int = 0
    messages: int = 0
    metadata: int = 0
    bad_chunks: int = 0  # chunks dropped: they failed their CRC, or did not decompress or parse
    complete: bool = False  # the input was finalised (its footer and summary hold)
    stopped_by: str = ""
    channels: dict[str, int] = field(default_factory=dict)
    dropped: list[str] = field(default_factory=list)  # one line per thing not rewritten, and why

    @property
    def lost_anything(self) -> bool:
        return any(not line.startswith("read all the same") for line in self.dropped)


class _Rewriter:
    """The output file, opened on the first record to write, with the input's schemas and channels re-registered
    as its messages need them."""

    def __init__(self, out_path: str | Path, compression: str | None, found: Salvage):
        self.out_path, self.compression, self.found = Path(out_path), compression, found
        self.header: Header | None = None
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.lost_schemas: set[int] = set()  # channels written without the schema their record names
        self.orphans: dict[int, int] = {}  # channel id -> messages whose channel record was lost
        self._out: Writer | None = None
        self._file: IO[bytes] | None = None

    def writer(self) -> Writer:
        if self._out is None:
            self._file = open(self.out_path, "wb")  # noqa: SIM115 (closed by finish)
            chosen = self.compression or self.found.compression or DEFAULT_COMPRESSION
            self._out = Writer(self._file, compression=COMPRESSIONS.get(chosen, COMPRESSIONS[DEFAULT_COMPRESSION]))
            self._out.start(profile=self.header.profile if self.header else PROFILE,
                            library=f"followbus/{__version__} recover")
        return self._out

    def channel_id(self, channel: Channel) -> int:
        if channel.id not in self.channel_ids:
            sid = 0
            schema = self.schemas.get(channel.schema_id) if channel.schema_id else None
            if schema is not None:
                if schema.id not in self.schema_ids:
                    self.schema_ids[schema.id] = self.writer().register_schema(schema.name, schema.encoding,
                                                                               schema.data)
                sid = self.schema_ids[schema.id]
            elif channel.schema_id:
                self.lost_schemas.add(channel.id)
            self.channel_ids[channel.id] = self.writer().register_channel(
                channel.topic, channel.message_encoding, sid, dict(channel.metadata))
        return self.channel_ids[channel.id]

    def message(self, record: Message, result: RecoverResult) -> None:
        channel = self.channels.get(record.channel_id)
        if channel is None:
            self.orphans[record.channel_id] = self.orphans.get(record.channel_id, 0) + 1
            return
        self.writer().add_message(self.channel_id(channel), record.log_time, record.data, record.publish_time,
                                  record.sequence)
        result.messages += 1
        result.channels[channel.topic] = result.channels.get(channel.topic, 0) + 1

    def finish(self) -> None:
        self.writer().finish()
        assert self._file is not None
        self._file.close()


def recover(in_path: str | Path, out_path: str | Path, compression: str | None = None) -> RecoverResult:
    """Rewrite every record of a possibly truncated or damaged MCAP file that can be trusted into a valid one: every
    chunk whose CRC passes, whichever chunk is bad (bus/recording.py salvage_records); what could not be rewritten
    is listed in ``dropped``."""
    with open_recording(in_path) as f:  # a regular file, long enough, and an MCAP one: else nothing is written
        if f.read(8) != MCAP0_MAGIC and not _ends_as_mcap(f):
            raise RecordingError(f"{in_path}: not an MCAP file")
    result = RecoverResult()
    found = Salvage()
    out = _Rewriter(out_path, compression, found)
    for record in salvage_records(in_path, found):
        if isinstance(record, Header):
            out.header = record
        elif isinstance(record, Schema):
            out.schemas[record.id] = record
        elif isinstance(record, Channel):
            out.channels[record.id] = record
        elif isinstance(record, Message):
            out.message(record, result)
        elif isinstance(record, Metadata):
            out.writer().add_metadata(record.name, dict(record.metadata))
            result.metadata += 1
        elif isinstance(record, Attachment):
            out.writer().add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                        record.data)
    out.finish()
    result.chunks, result.bad_chunks = found.chunks, found.bad_chunks
    result.complete, result.stopped_by = found.complete, found.stopped_by
    result.dropped = _dropped_lines(found, out)
    return result


def _ends_as_mcap(f: IO[bytes]) -> bool:
    """Whether a file whose first bytes are damaged ends as an MCAP file does (its closing magic)."""
    f.seek(-len(MCAP0_MAGIC), os.SEEK_END)
    return f.read(len(MCAP0_MAGIC)) == MCAP0_MAGIC


def _dropped_lines(found: Salvage, out: _Rewriter) -> list[str]:
    lines = [f"{'read all the same' if d.repaired else 'dropped'} {d.describe()}" for d in found.damage]
    lines += [f"dropped {n} messages of channel {cid}: its channel record was in a dropped part"
              for cid, n in sorted(out.orphans.items())]
    lines += [f"channel {out.channels[cid].topic}: its schema was in a dropped part; written without one"
              for cid in sorted(out.lost_schemas)]
    if found.doubtful:
        lines.append(f"taken from a damaged chunk for want of another copy (check them): {', '.join(found.doubtful)}")
    return lines


# --- commands --------------------------------------------------------------------------------------

def _fmt_time(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).isoformat(timespec="milliseconds")


def cmd_info(args) -> int:
    path = Path(args.file)
    try:
        summary = read_summary(path)
    except RecordingError as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    meta = read_metadata(path)
    stats = summary.statistics
    start, end = (stats.message_start_time, stats.message_end_time) if stats else (0, 0)
    duration = max(0.0, (end - start) / 1e9)
    compressions = sorted({ci.compression or "none" for ci in summary.chunk_indexes})
    compressed = sum(ci.compressed_size for ci in summary.chunk_indexes)
    uncompressed = sum(ci.uncompressed_size for ci in summary.chunk_indexes)
    fb = meta.get("followbus", {})
    print(f"file:        {path} ({os.path.getsize(path) / 1e6:.1f} MB)")
    print(f"start:       {_fmt_time(start) if start else '-'}")
    print(f"end:         {_fmt_time(end) if end else '-'}")
    print(f"duration:    {duration:.2f} s")
    print(f"messages:    {stats.message_count if stats else 0} in {len(summary.chunk_indexes)} chunks, "
          f"compression {', '.join(compressions) or 'none'}"
          + (f" ({uncompressed / 1e6:.1f} MB -> {compressed / 1e6:.1f} MB)" if uncompressed else ""))
    print(f"graph:       {fb.get('graph_name', '?')} (namespace {fb.get('namespace', '?')})")
    print(f"git commit:  {fb.get('git_commit', '?')}{' (dirty)' if fb.get('git_dirty') == 'true' else ''}")
    print(f"host:        {fb.get('host', '?')}   followbus {fb.get('version', '?')}   "
          f"started {fb.get('start_time', '?')}")
    rec = meta.get("recording_stats")
    if rec:
        print(f"recorder:    received {rec.get('received')}, written {rec.get('written')}, dropped "
              f"{rec.get('dropped')}, lost upstream (seq gaps) {rec.get('seq_gaps')}")
        if rec.get("write_error"):
            print(f"write error: {rec['write_error']} (the recording ends at its last complete chunk)")
    else:
        print("recorder:    no recording_stats (the recorder did not stop cleanly)")
    bad = corrupt_chunks(path)
    damaged = structure_damage(path)  # the magic, the header, the records between the chunks, the summary's CRC
    print(f"integrity:   {len(summary.chunk_indexes) - len(bad)} of {len(summary.chunk_indexes)} chunks pass their "
          "CRC" + ("; magic, header and record framing hold" if not damaged else "")
          + "".join(f"\n  corrupt:   {c.describe()}" for c in damaged + bad))
    _print_channels(summary, stats, duration)
    return 1 if bad or damaged else 0


def _print_channels(summary: Any, stats: Any, duration: float) -> None:
    counts = stats.channel_message_counts if stats else {}
    rows = []
    for ch in summary.channels.values():
        schema = summary.schemas.get(ch.schema_id)
        n = counts.get(ch.id, 0)
        rows.append((ch.topic, schema.name if schema else "-", ch.message_encoding, n,
                     n / duration if duration > 0 else 0.0))
    width = max([len(r[0]) for r in rows] + [5])
    enc_width = max([len(r[2]) for r in rows] + [8])
    print(f"\n{'topic':<{width}}  {'schema':<26} {'encoding':<{enc_width}} {'count':>7} {'rate Hz':>8}")
    for topic, schema_name, enc, n, rate in sorted(rows):
        print(f"{topic:<{width}}  {schema_name:<26} {enc:<{enc_width}} {n:>7} {rate:>8.1f}")


def cmd_recover(args) -> int:
    src = Path(args.file)
    dst = Path(args.output) if args.output else src.with_name(src.stem + ".recovered.mcap")
    if dst.resolve() == src.resolve():
        print("followbus: recover writes a new file; choose another -o", file=sys.stderr)
        return 2
    existed = dst.exists()
    try:
        result = recover(src, dst, args.compression)
    except (RecordingError, McapError) as exc:
        if not existed:  # nothing half-written left behind
            dst.unlink(missing_ok=True)
        print(f"followbus: {exc}" if isinstance(exc, RecordingError) else f"followbus: {src}: not an MCAP file ({exc})",
              file=sys.stderr)
        return 2
    state = "the file was finalised" if result.complete else f"stopped at the cut ({result.stopped_by or 'EOF'})"
    print(f"recovered {result.messages} messages from {result.chunks} complete chunks and {result.metadata} "
          f"metadata records into {dst}; {state}")
    for line in result.dropped:
        print(f"  {line}")
    if not (result.messages or result.metadata):
        return 1
    return 1 if result.lost_anything else 0
