"""``followbus record``: store every bus message, losslessly, in an MCAP file that opens in Foxglove.

Beside each bus channel (the exact bytes, for replay) go views every MCAP reader decodes without followbus
(tools/recording/views.py): ROS 2 CDR for frames, the command, odometry and detections, JSON with a JSON Schema
for every message. The ROS 2 views go again into ``<name>.ros2.mcap`` (MCAP profile ``ros2``, CDR only), the file
rosbags and ``ros2 bag`` open (they refuse a file with other encodings). ``--split-size`` / ``--split-duration``
start a new file (``<name>_0.mcap``, ``<name>_1.mcap``, ... as rosbag2 names them), each complete on its own.

A plain Zenoh subscriber on ``<namespace>/**`` (or the given key expressions). Zenoh's callback
only copies the payload into a queue; two threads do everything else (``convert``: header parsing
and the Foxglove views; ``write``: MCAP records, chunk compression, disk), so a slow disk never stalls
the callbacks and publishers keep the congestion control they chose. The queue is bounded in bytes
(``--max-queue-mb``, bus payloads plus their Foxglove views): past that, messages are dropped, counted
per key and reported (a warning at most every 5 s while it drops) rather than growing memory without
bound. ``--exclude`` leaves keys out (the raw frames, say, keeping the JPEG preview).

A write error (ENOSPC, EIO, EFBIG, ...) ends the recording at once: the recorder stops accepting
messages, cuts the file back to its last complete chunk and finalises it there (readable by ``info``,
``play``, Foxglove), prints one line on stderr saying what was lost and exits with status 1. If even
finalising fails, the file is left cut at a complete chunk and ``followbus recover`` salvages it.

Every chunk is closed and flushed at least every ``--chunk-seconds`` (and whenever it reaches
``--chunk-mb``), so a recorder killed with SIGKILL loses at most that much: ``followbus recover``
rewrites the complete chunks into a valid file. SIGINT/SIGTERM finalise the file (summary, index).

Compression (figures: BENCHMARKS.md, the recorder): zstd (level 3, the mcap writer's) saturates its thread on
two cores at 30 Hz 1280x720 bgr8, and its queue grows without bound. lz4 keeps up but shrinks raw frames by only
1-3 % and costs its CPU twice: on the robot while recording, and at every read, since a chunk is decompressed
whole even to read one of its small messages. So chunks are uncompressed by default; ``--compression zstd``
suits lower rates or recordings without raw frames (``--exclude``), ``lz4`` a slow disk.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import zenoh

from ...bus import ros2
from ...bus.barrier import RECORDER_NAME
from ...bus.codec import DecodeError, Header, peek
from ...bus.links import PublishedKeys
from ...bus.pubsub import RateLimitedLog, declare_subscriber, frame_bytes
from ...bus.schemas import decode
from ...bus.stats import SequenceGaps
from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)
from .. import __version__
from ..connect import is_remote
from .mcap_io import DEFAULT_CHUNK_BYTES, DEFAULT_COMPRESSION, ROS2_PROFILE, FinaliseResult, RecordingWriter
from .remote import kept_keys, raw_frame_keys, subscription_patterns
from .views import ROS2_SCHEMA_ENCODING, View, message_views

log = logging.getLogger("followbus.record")

STATUS_SEGMENTS = ("@status", "@health")
# ~10 s of the default graph's recording (raw 640x480 frames at 30 Hz: ~26 MB/s) if the disk stalls.
DEFAULT_MAX_QUEUE_MB = 256.0
EXIT_WRITE_FAILED = 1
STATUS_WAIT_S = 2.0  # a remote recording without the graph file waits this long for the nodes to announce their keys


@dataclass
class RecordOptions:
    output: Path
    patterns: list[str]
    include_status: bool = False
    compression: str = DEFAULT_COMPRESSION
    chunk_bytes: int = DEFAULT_CHUNK_BYTES
    chunk_seconds: float = 1.0
    jpeg_quality: int = 80
    foxglove: bool = True  # the views beside the bus channels (tools/recording/views.py)
    raw_images: bool = False  # bgr8 frames viewed as sensor_msgs/Image (lossless) instead of JPEG
    split_bytes: int = 0  # start a new file past this size (0: never)
    split_seconds: float = 0.0  # ... or past this long (0: never)
    ros2_file: bool = True  # the ROS 2 views also in <name>.ros2.mcap (profile ros2: rosbags, ros2 bag)
    max_queue_bytes: int = int(DEFAULT_MAX_QUEUE_MB * 1024 * 1024)
    exclude: list[str] = field(default_factory=list)  # key expressions left out


@dataclass
class KeyStats:
    type_name: str = ""
    received: int = 0
    written: int = 0  # in the file (after a write error: in its complete chunks)
    dropped: int = 0  # recorder queue full
    seq_gaps: int = 0  # messages missing between two received header.seq of one publisher
    restarts: int = 0  # header.seq went back: the publisher restarted


@dataclass
class RecordReport:
    path: Path  # the file being written (the last one when the recording was split)
    files: list[Path] = field(default_factory=list)  # every file of the recording, in order
    ros2_files: list[Path] = field(default_factory=list)  # their ROS 2 companions (<name>.ros2.mcap)
    duration_s: float = 0.0
    keys: dict[str, KeyStats] = field(default_factory=dict)
    foxglove_messages: int = 0
    foxglove_errors: int = 0
    undecodable: int = 0
    writer_busy_s: float = 0.0
    convert_busy_s: float = 0.0
    max_queue_bytes: int = 0
    file_bytes: int = 0
    write_error: str = ""  # the error that ended the recording, "" when it ended normally
    failed_at_bytes: int = 0  # file size when the write failed
    recorded_s: float = 0.0  # after a write error: the span the complete chunks cover (recorder clock)
    finalise_error: str = ""  # finalising after the write error failed too

    @property
    def received(self) -> int:
        return sum(k.received for k in self.keys.values())

    @property
    def written(self) -> int:
        return sum(k.written for k in self.keys.values())

    @property
    def dropped(self) -> int:
        return sum(k.dropped for k in self.keys.values())

    @property
    def seq_gaps(self) -> int:
        return sum(k.seq_gaps for k in self.keys.values())

    @property
    def unrecorded(self) -> int:
        """Messages received and not in the file: dropped, or still queued or in the failed chunk at a write error."""
        return self.received - self.written

    def failure_line(self) -> str:
        """The one line a write error prints (stderr)."""
        head = (f"record: write failed after {self.failed_at_bytes / 1e6:.1f} MB: {self.write_error}; "
                f"{self.recorded_s:.1f} s recorded, {self.unrecorded} messages lost")
        if self.finalise_error:
            return (f"{head}; finalising failed too ({self.finalise_error}): `followbus recover {self.path}` "
                    f"salvages its complete chunks")
        return f"{head}; {self.path} finalised ({self.file_bytes / 1e6:.1f} MB, {self.written} messages)"

    def as_metadata(self) -> dict[str, str]:
        extra = {"write_error": self.write_error} if self.write_error else {}
        return {**extra,
            "received": str(self.received), "written": str(self.written), "dropped": str(self.dropped),
            "seq_gaps": str(self.seq_gaps), "undecodable": str(self.undecodable),
            "foxglove_messages": str(self.foxglove_messages), "foxglove_errors": str(self.foxglove_errors),
            "duration_s": f"{self.duration_s:.3f}", "writer_busy_s": f"{self.writer_busy_s:.3f}",
            "convert_busy_s": f"{self.convert_busy_s:.3f}",
            "max_queue_bytes": str(self.max_queue_bytes),
            "keys": json.dumps({k: vars(v) for k, v in sorted(self.keys.items())}),
        }


def _error_text(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, OSError) and str(exc) else repr(exc)


def is_status_key(key: str) -> bool:
    return any(seg in STATUS_SEGMENTS for seg in key.split("/"))


@dataclass
class _Item:
    key: str
    data: bytes
    recv_ns: int
    type_name: str | None = None
    header: Header | None = None
    log_time: int = 0
    views: list[View] = field(default_factory=list)  # the decodable copies beside the bus bytes

    @property
    def view_bytes(self) -> int:
        return sum(len(v.payload) for v in self.views)


class Recorder:
    """Subscribes, queues, converts and writes from threads. ``start()``, then ``stop()`` returns the report.

    Two threads form a pipeline so JPEG encoding and chunk compression (both release the GIL) overlap:
    ``convert`` parses headers and builds the Foxglove views, ``write`` feeds the MCAP writer. An error
    in the writer sets ``failed``; ``stop()`` then finalises what reached the disk (see the module doc).
    """

    def __init__(self, options: RecordOptions, metadata: dict[str, dict[str, str]],
                 subscribe: list[str] | None = None):
        self.opts = options
        self._metadata = metadata
        self._split = bool(options.split_bytes or options.split_seconds)
        self.report = RecordReport(options.output)
        self._closed_counts: dict[str, int] = {}  # bus messages per key in the files already finished
        self.ros2_writer: RecordingWriter | None = None
        self.writer = self._open_writer()
        if options.foxglove:
            ros2.typestore()  # built now, not by the first frame's conversion while the graph starts
        # What the subscribers ask for: the patterns, or the graph's kept keys one by one (recording/remote.py).
        self.subscribe = list(subscribe) if subscribe is not None else list(options.patterns)
        self._key_exprs = [zenoh.KeyExpr(p) for p in self.subscribe]
        self._excluded = [zenoh.KeyExpr(p) for p in options.exclude]
        self._subs: list[Any] = []
        self._raw: deque[_Item] = deque()
        self._ready: deque[_Item] = deque()
        self._queued_bytes = 0  # from the callback until written
        self._cond = threading.Condition()
        self._closing = False
        self._converted_all = False
        self.failed = threading.Event()  # the writer hit an error: the recording is over
        self._failure: BaseException | None = None
        self._seq_gaps = SequenceGaps()
        self._warn = RateLimitedLog(log, 5.0)
        self._threads = [threading.Thread(target=self._convert_loop, name="record-convert", daemon=True),
                         threading.Thread(target=self._write_loop, name="record-write", daemon=True)]
        self._started = 0.0

    # --- files ------------------------------------------------------------------------------------
    def _open_writer(self) -> RecordingWriter:
        """The next file: ``output`` itself, or ``<stem>_<i><suffix>`` when splitting (rosbag2's naming)."""
        index = len(self.report.files)
        out = self.opts.output
        path = out.with_name(f"{out.stem}_{index}{out.suffix}") if self._split else out
        writer = RecordingWriter(path, self.opts.compression, self.opts.chunk_bytes)
        for name, data in self._metadata.items():
            writer.metadata(name, data)
        if self._split:
            writer.metadata("split", {"index": str(index), "first_file": self.opts.output.stem + "_0" + out.suffix})
        writer.flush()
        self.report.files.append(path)
        self.report.path = path
        self._file_started = time.monotonic()
        if self.opts.ros2_file and self.opts.foxglove:
            self.ros2_writer = RecordingWriter(ros2_path(path), self.opts.compression, self.opts.chunk_bytes,
                                               profile=ROS2_PROFILE)
            self.report.ros2_files.append(ros2_path(path))
        return writer

    def _finish_ros2(self, metadata: dict[str, str] | None = None) -> None:
        if self.ros2_writer is not None:
            if metadata:
                self.ros2_writer.metadata("recording_stats", metadata)
            self.ros2_writer.finish()
            self.ros2_writer = None

    def _split_due(self) -> bool:
        o = self.opts
        return ((o.split_bytes > 0 and self.writer.size_bytes >= o.split_bytes)
                or (o.split_seconds > 0 and time.monotonic() - self._file_started >= o.split_seconds))

    def _next_file(self) -> None:
        """Finish this file (summary, index, its own recording_stats so far) and go on in a new one."""
        self.writer.metadata("recording_stats", self.report.as_metadata())
        self.writer.finish()
        self._finish_ros2(self.report.as_metadata())
        for key, n in self.writer.durable_counts.items():
            self._closed_counts[key] = self._closed_counts.get(key, 0) + n
        self.writer = self._open_writer()

    # --- zenoh side (must stay cheap) -------------------------------------------------------------
    def start_threads(self) -> None:
        """The convert and write threads, without a bus (start() subscribes too; tests feed _enqueue)."""
        self._started = time.monotonic()
        for thread in self._threads:
            thread.start()

    def start(self, session: zenoh.Session) -> None:
        self.start_threads()
        for i, pattern in enumerate(self.subscribe):
            # Direct: the callback runs on zenoh's receive thread (it only copies and enqueues), which
            # keeps the order samples arrived in; zenoh-python's default hands each subscriber a thread.
            # On the real keys, not the lane's side keys (bus/shmlane.py): publishers send the recorder the
            # messages themselves, so a stall of the recorder (a slow disk) loses no frame to a rewritten segment.
            self._subs.append(declare_subscriber(session, pattern, self._callback_for(i)))

    def add_subscription(self, session: zenoh.Session, pattern: str) -> None:
        """Subscribe to one more key expression while recording (a key a node announced after the start)."""
        self.subscribe.append(pattern)
        self._key_exprs.append(zenoh.KeyExpr(pattern))
        self._subs.append(declare_subscriber(session, pattern, self._callback_for(len(self.subscribe) - 1)))

    def _callback_for(self, index: int):
        def callback(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            if len(self._key_exprs) > 1:
                # Overlapping patterns deliver a sample once per subscriber: only the first that matches keeps it.
                first = next(i for i, k in enumerate(self._key_exprs) if k.intersects(sample.key_expr))
                if first != index:
                    return
            if self._excluded and any(k.intersects(sample.key_expr) for k in self._excluded):
                return
            try:
                data = frame_bytes(sample)
            except Exception as exc:  # never let one sample kill zenoh's callback thread
                self._warn.warning("unreadable sample on %s: %r", key, exc)
                return
            self._enqueue(key, data)

        return callback

    def _enqueue(self, key: str, data: bytes) -> None:
        now = time.time_ns()
        with self._cond:
            if self._closing:  # stopping, or the writer failed: the recording is over
                return
            stats = self.report.keys.get(key)
            if stats is None:
                stats = self.report.keys[key] = KeyStats()
            stats.received += 1
            if self._queued_bytes + len(data) > self.opts.max_queue_bytes:
                stats.dropped += 1
                self._warn.warning("recorder queue at its bound (%.1f MB queued, %.1f MB message, --max-queue-mb "
                                   "%.0f): dropping on %s", self._queued_bytes / 1e6, len(data) / 1e6,
                                   self.opts.max_queue_bytes / 2**20, key)
                return
            self._raw.append(_Item(key, data, now))
            self._queued_bytes += len(data)
            self.report.max_queue_bytes = max(self.report.max_queue_bytes, self._queued_bytes)
            self._cond.notify_all()

    # --- convert thread ---------------------------------------------------------------------------
    def _convert_loop(self) -> None:
        while True:
            with self._cond:
                while not self._raw and not self._closing:
                    self._cond.wait()
                if not self._raw:
                    self._converted_all = True
                    self._cond.notify_all()
                    return
                item = self._raw.popleft()
            busy_from = time.perf_counter()
            try:
                self._convert(item)
            except Exception:
                log.exception("failed to convert a message on %s", item.key)
            self.report.convert_busy_s += time.perf_counter() - busy_from
            with self._cond:
                if self.failed.is_set():
                    continue  # nobody writes it any more
                self._ready.append(item)
                self._queued_bytes += item.view_bytes  # the JPEG views count against the bound too
                self.report.max_queue_bytes = max(self.report.max_queue_bytes, self._queued_bytes)
                self._cond.notify_all()

    def _convert(self, item: _Item) -> None:
        try:
            head = peek(item.data)  # the fields and arrays are stored as they came, never decoded here
            item.type_name, item.header = head.type_name, head.header
        except DecodeError:
            pass
        stamp = item.header.stamp_ns if item.header else 0
        item.log_time = stamp if stamp > 0 else item.recv_ns  # the bus stamp; receive time only without one
        if self.opts.foxglove and item.type_name is not None:
            try:
                msg = decode(item.data)
                item.views = message_views(item.key, msg, msg.header.stamp_ns or item.log_time,
                                           self.opts.jpeg_quality, self.opts.raw_images)
            except Exception as exc:  # a view that cannot be made must not cost the bus message
                self.report.foxglove_errors += 1
                self._warn.warning("no view of %s: %r", item.key, exc)

    # --- write thread -----------------------------------------------------------------------------
    def _write_loop(self) -> None:
        last_flush = time.monotonic()
        while True:
            with self._cond:
                while not self._ready and not self._converted_all:
                    remaining = self.opts.chunk_seconds - (time.monotonic() - last_flush)
                    if remaining <= 0:
                        break
                    self._cond.wait(remaining)
                item = self._ready.popleft() if self._ready else None
                if item is None and self._converted_all:
                    return
            busy_from = time.perf_counter()
            try:
                if item is not None:
                    self._write(item)
                if time.monotonic() - last_flush >= self.opts.chunk_seconds:
                    self._flush()  # a closed chunk survives a SIGKILL
                    last_flush = time.monotonic()
            except Exception as exc:
                # ENOSPC, EIO, EFBIG, ... and anything else: the mcap writer's state is unknown from here
                # on, so the recording ends; stop() finalises what reached the disk.
                self._fail(exc)
                return
            finally:
                if item is not None and not self.failed.is_set():
                    with self._cond:
                        self._queued_bytes -= len(item.data) + item.view_bytes
            self.report.writer_busy_s += time.perf_counter() - busy_from

    def _fail(self, exc: BaseException) -> None:
        log.debug("write failed", exc_info=exc)
        with self._cond:
            self._failure = exc
            self._closing = True
            self._raw.clear()  # lost: the report counts them as received and not written
            self._ready.clear()
            self._queued_bytes = 0
            self.failed.set()
            self._cond.notify_all()

    def _flush(self) -> None:
        self.writer.flush()
        if self.ros2_writer is not None:
            self.ros2_writer.flush()

    def _write(self, item: _Item) -> None:
        if self._split and self._split_due():
            self._next_file()
        header = item.header
        if item.type_name is None:
            self.report.undecodable += 1
        seq = header.seq if header else 0
        self.writer.write(self.writer.bus_channel(item.key, item.type_name), item.log_time, item.data, sequence=seq)
        stats = self.report.keys[item.key]
        stats.written += 1
        stats.type_name = item.type_name or "?"
        if header is not None:
            self._track_seq(stats, item.key, header.source, seq)
        for view in item.views:
            self.writer.write(self.writer.view_channel(view.topic, view.schema, item.key), item.log_time,
                              view.payload, sequence=seq)
            if self.ros2_writer is not None and view.schema.encoding == ROS2_SCHEMA_ENCODING:
                self.ros2_writer.write(self.ros2_writer.view_channel(view.topic, view.schema, item.key),
                                       item.log_time, view.payload, sequence=seq)
            self.report.foxglove_messages += 1

    def _track_seq(self, stats: KeyStats, key: str, source: str, seq: int) -> None:
        missing = self._seq_gaps.see((key, source), seq)
        if missing > 0:
            stats.seq_gaps += missing
        elif missing < 0:
            stats.restarts += 1

    # --- shutdown ---------------------------------------------------------------------------------
    def discard(self) -> None:
        """Remove the file of a recorder that never started (no bus to record)."""
        self.writer.discard()
        if self.ros2_writer is not None:
            self.ros2_writer.discard()

    def queued_bytes(self) -> int:
        with self._cond:
            return self._queued_bytes

    def stop(self) -> RecordReport:
        """Unsubscribe, drain the queue to disk and finalise the file; after a write error (``failed``),
        finalise what reached the disk instead. Never raises for a write error: see ``report.write_error``."""
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        for thread in self._threads:
            thread.join()
        self.report.duration_s = time.monotonic() - self._started
        if self._failure is None:
            try:
                self.writer.metadata("recording_stats", self.report.as_metadata())
                self.writer.finish()
                self._finish_ros2(self.report.as_metadata())
            except Exception as exc:  # the disk filled up at the very end
                self._failure = exc
        if self._failure is not None:
            self._finalise_after_failure(self._failure)
        self.report.file_bytes = sum(path.stat().st_size for path in self.report.files if path.exists())
        return self.report

    def _finalise_after_failure(self, exc: BaseException) -> None:
        report = self.report
        report.write_error = _error_text(exc)
        with contextlib.suppress(OSError):
            report.failed_at_bytes = report.path.stat().st_size
        report.recorded_s = max(0.0, self.writer.durable_monotonic - self._started)
        for key, stats in report.keys.items():
            stats.written = self._closed_counts.get(key, 0) + self.writer.durable_counts.get(key, 0)
        try:
            if self.ros2_writer is not None:  # its complete chunks: the views of what the main file holds, or more
                with contextlib.suppress(Exception):
                    self.ros2_writer.finish_after_failure()
            result: FinaliseResult = self.writer.finish_after_failure([("recording_stats", report.as_metadata())])
            log.debug("finalised after the write error: %s", result)
            report.foxglove_messages = result.messages - report.written
        except Exception as fin_exc:
            report.finalise_error = _error_text(fin_exc)


def ros2_path(path: Path) -> Path:
    """The companion file of a recording's ROS 2 channels: ``run.mcap`` -> ``run.ros2.mcap``."""
    return path.with_name(f"{path.stem}.ros2{path.suffix}")


# --- metadata --------------------------------------------------------------------------------------

def git_info() -> tuple[str, bool]:
    """(commit, dirty) of the followbus source tree, ("unknown", False) when it is not a git checkout."""
    root = Path(__file__).resolve().parents[2]  # tools/ sits in the repository root
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip() != ""
        return commit or "unknown", dirty
    except (OSError, subprocess.SubprocessError):
        return "unknown", False


def build_metadata(graph: Any | None, options: RecordOptions, namespace: str,
                   argv: list[str] | None = None) -> dict[str, dict[str, str]]:
    commit, dirty = git_info()
    now_ns = time.time_ns()
    info = {
        "version": __version__,
        "git_commit": commit,
        "git_dirty": "true" if dirty else "false",
        "host": socket.gethostname(),
        "start_time": datetime.fromtimestamp(now_ns / 1e9, tz=timezone.utc).isoformat(timespec="milliseconds"),
        "start_time_ns": str(now_ns),
        "namespace": namespace,
        "graph_name": graph.name if graph is not None else "",
        "graph_path": str(Path(graph.path).resolve()) if graph is not None else "",
        "topics": json.dumps(options.patterns),
        "include_status": "true" if options.include_status else "false",
        "compression": options.compression,
        "jpeg_quality": str(options.jpeg_quality),
        "argv": json.dumps(argv if argv is not None else sys.argv),
    }
    meta = {"followbus": info}
    if graph is not None:
        meta["graph"] = {"path": info["graph_path"], "yaml": graph.text}
        meta["params"] = {name: json.dumps(spec.params, default=str) for name, spec in graph.nodes.items()}
    return meta


# --- command ---------------------------------------------------------------------------------------

def default_output(graph_name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return Path("recordings") / f"{graph_name or 'followbus'}-{stamp}.mcap"


def _files_text(report: RecordReport) -> str:
    if len(report.files) <= 1:
        return str(report.path)
    return f"{len(report.files)} files {report.files[0]} .. {report.files[-1].name}"


def print_report(report: RecordReport, out=sys.stdout) -> None:
    rows = sorted(report.keys.items())
    width = max([len(k) for k, _ in rows] + [3])
    print(f"{'key':<{width}}  {'type':<12} {'received':>8} {'written':>8} {'dropped':>7} {'lost':>5}", file=out)
    for key, s in rows:
        print(f"{key:<{width}}  {s.type_name:<12} {s.received:>8} {s.written:>8} {s.dropped:>7} {s.seq_gaps:>5}",
              file=out)
    busy = 100 * report.writer_busy_s / report.duration_s if report.duration_s else 0.0
    conv = 100 * report.convert_busy_s / report.duration_s if report.duration_s else 0.0
    print(f"recorded {report.written} of {report.received} messages received in {report.duration_s:.1f} s to "
          f"{_files_text(report)} ({report.file_bytes / 1e6:.1f} MB, {report.foxglove_messages} view messages); "
          f"dropped by the recorder: {report.dropped}; lost on the way (header.seq gaps): {report.seq_gaps}; "
          f"threads busy: convert {conv:.0f}%, write {busy:.0f}%; queue max {report.max_queue_bytes / 1e6:.1f} MB",
          file=out, flush=True)
    if report.ros2_files:
        print(f"ROS 2 channels also in {report.ros2_files[0]}" + (f" .. {report.ros2_files[-1].name}"
              if len(report.ros2_files) > 1 else "") + " (rosbags, `ros2 bag`)", file=out, flush=True)


def record_options(args, namespace: str, graph_name: str) -> RecordOptions | str:
    """The options of ``followbus record`` from its arguments, or the one line that says what is wrong."""
    patterns = list(args.topics or [f"{namespace}/**"])
    if args.status and f"{namespace}/@status/*" not in patterns:
        # '@' chunks are verbatim in Zenoh: no wildcard matches them, so status is only ever recorded on request.
        patterns.append(f"{namespace}/@status/*")
    options = RecordOptions(
        output=Path(args.output) if args.output else default_output(graph_name), patterns=patterns,
        include_status=args.status, compression=args.compression,
        chunk_bytes=int(args.chunk_mb * 1024 * 1024), chunk_seconds=args.chunk_seconds,
        jpeg_quality=args.jpeg_quality, foxglove=not args.no_foxglove, raw_images=args.raw_images,
        split_bytes=int((args.split_size or 0) * 1e6), split_seconds=args.split_duration or 0.0,
        ros2_file=not args.no_ros2_file,
        max_queue_bytes=int(args.max_queue_mb * 1024 * 1024), exclude=list(getattr(args, "exclude", None) or []),
    )
    for pattern in [*options.patterns, *options.exclude]:
        try:
            zenoh.KeyExpr(pattern)
        except zenoh.ZError as exc:
            return f"{pattern!r} is not a key expression: {exc}"
    return options


def _link_excludes(args, settings, graph, namespace: str) -> tuple[list[str], list[str]]:
    """--exclude, plus the raw frames when recording over a network without --raw-frames; and the lines that
    say so at start."""
    exclude = list(getattr(args, "exclude", None) or [])
    notes = []
    if is_remote(settings) and not getattr(args, "raw_frames", False):
        raw = [k for k in raw_frame_keys(graph, namespace) if k not in exclude]
        exclude += raw
        notes.append(f"remote link ({', '.join(settings.connect)}): leaving out raw frames ({', '.join(raw)}; "
                     "--raw-frames records them), the JPEG preview stays")
    if exclude and graph is None and is_remote(settings):
        notes.append(f"without the graph file: subscribing key by key to what the nodes announce on "
                     f"{namespace}/@status, so excluded keys never cross the link")
    return exclude, notes


class AnnouncedKeys:
    """A remote recording without the graph file: the keys the nodes' statuses announce (bus/links.py
    PublishedKeys), each kept one subscribed to as it appears, for the whole recording. Inert (``active`` False)
    for any other recording, which subscribes to its patterns or the graph's keys at start."""

    def __init__(self, session: zenoh.Session, recorder: Recorder, namespace: str, active: bool):
        self.session, self.recorder = session, recorder
        self.published = PublishedKeys(session, namespace) if active else None
        self.subscribed: set[str] = set()

    @classmethod
    def start(cls, session: zenoh.Session, recorder: Recorder, namespace: str, active: bool) -> AnnouncedKeys:
        """Follow the announced keys, the nodes' first statuses waited for (their keys subscribed before the
        recording goes on)."""
        announced = cls(session, recorder, namespace, active)
        if announced.published is not None:
            announced.published.wait(STATUS_WAIT_S)
        announced.follow()
        return announced

    def follow(self) -> None:
        """Subscribe to every kept key announced since the last call."""
        if self.published is None:
            return
        opts = self.recorder.opts
        new = [k for k in self.published.announced() if k not in self.subscribed]
        for key in kept_keys(new, opts.patterns, opts.exclude):
            self.recorder.add_subscription(self.session, key)
        self.subscribed.update(new)

    def unannounced(self) -> list[str]:
        """Nodes up by their liveliness tokens whose status never came: none of their keys was recorded."""
        return self.published.unannounced() if self.published is not None else []

    def close(self) -> None:
        if self.published is not None:
            self.published.close()


def _follows_announced(settings, graph, options: RecordOptions) -> bool:
    """Whether the recording subscribes key by key to what the nodes announce: over a network, keys left out,
    no graph file to list the keys."""
    return is_remote(settings) and graph is None and bool(options.exclude)


def cmd_record(args, settings, graph) -> int:
    """``followbus record``; ``graph`` is the loaded --graph (with --set applied) or None."""
    from ..command import namespace as command_namespace

    namespace = command_namespace(args) if graph is None else (getattr(args, "namespace", None) or graph.namespace)
    options = record_options(args, namespace, graph.name if graph is not None else "")
    if isinstance(options, str):
        print(f"followbus: {options}", file=sys.stderr)
        return 2
    options.exclude, notes = _link_excludes(args, settings, graph, namespace)
    output, patterns = options.output, options.patterns
    # Over a network an excluded key must not cross the link: the graph's kept keys one by one. On this machine
    # the patterns themselves, so a key no node of the graph declares (a tool's, a test's) is recorded too.
    subscribed = (subscription_patterns(options.patterns, options.exclude, graph, namespace)
                  if is_remote(settings) else list(options.patterns))
    try:  # before joining the bus: an unwritable output is reported at once
        recorder = Recorder(options, build_metadata(graph, options, namespace), subscribed)
    except OSError as exc:
        print(f"followbus: cannot write {output}: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum, _frame):
        log.info("received %s: finalising %s", signal.Signals(signum).name, output)
        if signum == signal.SIGINT:
            from ..errors import INTERRUPTED

            INTERRUPTED.set()  # exit 130 once the file is finalised, as every command after Ctrl-C
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    from ..connect import open_client_session

    try:
        session = open_client_session(settings)
    except Exception:  # BusUnreachable: one line from the command line; no empty file left behind
        recorder.discard()
        raise
    recorder.start(session)
    announced = AnnouncedKeys.start(session, recorder, namespace, _follows_announced(settings, graph, options))
    # Declared after the subscribers: a capture node launched with --record waits for it before frame 0,
    # so a recording holds the run from its first frame (a replayed node must start where the live one did).
    token = session.liveliness().declare_token(f"{namespace}/@health/{RECORDER_NAME}")
    for note in notes:
        print(note, flush=True)
    split = " (then _1, _2, ... as it splits)" if options.split_bytes or options.split_seconds else ""
    print(f"recording {' '.join(patterns)} to {recorder.report.path}{split} ({options.compression} chunks); "
          "Ctrl-C to stop",
          flush=True)
    started = time.monotonic()
    next_status = started + 10.0
    try:
        while not stop.is_set() and not recorder.failed.is_set():
            if args.duration is not None and time.monotonic() - started >= args.duration:
                break
            stop.wait(0.1)
            announced.follow()
            if time.monotonic() >= next_status:
                next_status += 10.0
                log.info("%d messages received, queue %.1f MB", recorder.report.received,
                         recorder.queued_bytes() / 1e6)
    finally:
        unannounced = announced.unannounced()
        announced.close()
        report = recorder.stop()
        with contextlib.suppress(Exception):
            token.undeclare()
        with contextlib.suppress(Exception):
            session.close()
    print_report(report)
    if unannounced:
        print(f"not recorded: every key of {', '.join(unannounced)}: no status of theirs came over this link, though "
              "their liveliness tokens say they are up (their statuses name the keys a recording without the graph "
              "file subscribes to; --graph lists them instead)", flush=True)
    if report.write_error:
        print(report.failure_line(), file=sys.stderr, flush=True)
        return EXIT_WRITE_FAILED
    return 0
