"""Failures the recorder and the publishers must survive, with real parts: a recorder whose disk fills up
(a real EFBIG from the kernel: RLIMIT_FSIZE on the recorder process, SIGXFSZ ignored), a finalisation that
fails too (recover salvages the file), a writer queue at its byte bound, and a publication over the
size limit (real Zenoh sessions on loopback)."""

from __future__ import annotations

import json
import logging
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from mcap.records import Footer, Message
from mcap.stream_reader import StreamReader

from followbus.bus.barrier import RECORDER_NAME
from followbus.bus.pubsub import MAX_PAYLOAD_BYTES, Publisher, direct_callback, payload_bytes
from followbus.bus.recording import iter_bus_messages, read_metadata, read_summary
from followbus.bus.schemas import Frame, Tick, decode
from followbus.bus.session import ZenohSettings, open_session

from .conftest import REPO, followbus_argv, run_followbus, wait_until

pytestmark = pytest.mark.slow

# The graph the recorder reads its bus settings and namespace from; nothing is launched.
NODES = "  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n"


def _fsize_limit(limit_bytes: int):
    def apply() -> None:  # runs in the child between fork and exec
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, resource.RLIM_INFINITY))

    return apply


def _peer(port: int) -> zenoh.Session:
    """The test's own bus endpoint: a peer listening on the private loopback port (no shared memory, so
    every payload really crosses the socket)."""
    return open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], connect=[], shm=False))


def _wait_for_recorder(session: zenoh.Session, namespace: str, timeout_s: float = 30.0) -> bool:
    """The recorder declares its liveliness token after its subscribers: from then on it receives."""
    up = threading.Event()
    sub = session.liveliness().declare_subscriber(f"{namespace}/@health/{RECORDER_NAME}",
                                                  direct_callback(lambda _s: up.set()), history=True)
    try:
        return up.wait(timeout_s)
    finally:
        sub.undeclare()


def _streamed_messages(path: Path) -> int:
    """Messages read front to back with mcap's streaming reader (no summary, CRCs checked): what a reader
    that does not seek sees. Raises on anything left between the last chunk and the summary."""
    with open(path, "rb") as f:
        records = list(StreamReader(f, validate_crcs=True).records)
    assert isinstance(records[-1], Footer)
    return sum(isinstance(r, Message) for r in records)


def _noise_frame(rng: np.random.Generator, seq: int, height: int = 240, width: int = 320) -> Frame:
    """Random pixels: no compression shrinks them, so file sizes follow the bytes published."""
    frame = Frame(width=width, height=height, data=rng.integers(0, 255, (height, width, 3), dtype=np.uint8))
    frame.header.stamp_ns, frame.header.frame_seq = time.time_ns(), seq
    return frame


def test_recorder_on_a_full_disk_stops_at_once_with_one_line_and_a_readable_file(graph_file, port, tmp_path):
    graph = graph_file(NODES)
    out = tmp_path / "full.mcap"
    limit_bytes, queue_mb = 3_000_000, 8
    session = _peer(port)
    frames = Publisher(session, "t/capture/frame", "test")
    ticks = Publisher(session, "t/ticker/tick", "test")
    proc = subprocess.Popen(
        followbus_argv("record", "--graph", str(graph), "-o", str(out), "--duration", "120", "--chunk-mb", "0.5",
                       "--max-queue-mb", str(queue_mb)),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL, cwd=REPO,
        preexec_fn=_fsize_limit(limit_bytes))
    try:
        assert _wait_for_recorder(session, "t"), "the recorder never came up"
        rng = np.random.default_rng(0)
        published = 0
        deadline = time.monotonic() + 60  # ~7 MB/s: the 3 MB limit is reached within a second or two
        while proc.poll() is None and time.monotonic() < deadline:
            frames.put(_noise_frame(rng, published))
            ticks.put(Tick())
            published += 1
            time.sleep(1 / 30)
        # It ends itself long before --duration 120, while still being fed.
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        session.close()

    assert proc.returncode == 1, stdout + stderr
    assert "Traceback" not in stderr, stderr
    failure = [line for line in stderr.splitlines() if "write failed" in line]
    assert len(failure) == 1, stderr
    assert failure[0].startswith("record: write failed after ") and "File too large" in failure[0], failure[0]
    assert "messages lost" in failure[0] and "finalised" in failure[0], failure[0]
    assert not [line for line in stderr.splitlines() if " ERROR " in line or " WARNING " in line], stderr

    # Finalised where it stood: a summary, the stats written at the failure, every counted message readable.
    assert out.stat().st_size <= limit_bytes
    summary = read_summary(out)
    stats = read_metadata(out)["recording_stats"]
    assert stats["write_error"].startswith("[Errno 27]")
    bus = list(iter_bus_messages(out))
    assert len(bus) == int(stats["written"]) > 0
    assert int(stats["received"]) > int(stats["written"])  # the chunk that hit the limit is lost, and said so
    assert {m.key for m in bus} == {"t/capture/frame", "t/ticker/tick"}
    assert all(decode(m.data).header.source == "test" for m in bus)
    assert summary.statistics.message_count >= len(bus)  # plus the Foxglove views
    assert _streamed_messages(out) == summary.statistics.message_count
    assert int(stats["max_queue_bytes"]) <= queue_mb * 2**20
    info = run_followbus("info", str(out), timeout=60)
    assert info.returncode == 0 and "write error: [Errno 27]" in info.stdout, info.stdout + info.stderr


# A child process with RLIMIT_FSIZE writes with RecordingWriter until the kernel refuses, then finalises
# (optionally after lowering its own limit so that even the few kB of the summary no longer fit).
_WRITER_CHILD = """
import json, resource, sys
import numpy as np
from followbus.bus.schemas import Tick, encode
from followbus.tools.recording.mcap_io import RecordingWriter

path, squeeze = sys.argv[1], sys.argv[2] == "squeeze"
writer = RecordingWriter(path, chunk_bytes=64 * 1024)
writer.metadata("followbus", {"note": "test"})
rng = np.random.default_rng(1)
error = ""
try:
    for seq in range(1_000_000):
        tick = Tick()
        tick.header.seq, tick.header.stamp_ns = seq, 1_700_000_000_000_000_000 + seq * 1_000_000
        writer.write(writer.bus_channel("t/tick", "Tick"), tick.header.stamp_ns, encode(tick), sequence=seq)
        writer.write(writer.foxglove_channel("t/tick/image", "foxglove.CompressedImage", "t/tick"),
                     tick.header.stamp_ns, rng.bytes(3000))
except OSError as exc:
    error = str(exc)
if squeeze:  # a file system that fills up again: the summary cannot be written either
    resource.setrlimit(resource.RLIMIT_FSIZE, (writer.durable_offset + 64, resource.RLIM_INFINITY))
result = {"error": error, "durable": writer.durable_counts.get("t/tick", 0)}
try:
    done = writer.finish_after_failure([("recording_stats", {"write_error": error})])
    result.update(finalised=done.messages, cut=done.cut_bytes)
except OSError as exc:
    result["finalise_error"] = str(exc)
print(json.dumps(result))
"""


def _run_writer_child(path: Path, squeeze: bool) -> dict:
    proc = subprocess.run([sys.executable, "-c", _WRITER_CHILD, str(path), "squeeze" if squeeze else "-"],
                          capture_output=True, text=True, timeout=120, cwd=REPO, stdin=subprocess.DEVNULL,
                          # Uncompressed 64 KB chunks end every ~66.6 kB: the limit falls half-way through one, so
                          # the failing write leaves part of a chunk to cut back (room for the summary).
                          preexec_fn=_fsize_limit(1_030_000))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads(proc.stdout)


def test_writer_after_a_write_error_keeps_every_complete_chunk(tmp_path):
    path = tmp_path / "efbig.mcap"
    result = _run_writer_child(path, squeeze=False)
    assert "File too large" in result["error"]
    assert result["durable"] > 0 and "finalise_error" not in result
    assert result["cut"] > 0  # the chunk that hit the limit was partly on disk, and is gone
    bus = list(iter_bus_messages(path))
    assert len(bus) == result["durable"]
    assert [m.sequence for m in bus] == list(range(result["durable"]))  # no hole: whole chunks only
    assert read_summary(path).statistics.message_count == result["finalised"] == 2 * result["durable"]
    assert _streamed_messages(path) == result["finalised"]
    assert read_metadata(path)["recording_stats"]["write_error"] == result["error"]


def test_when_finalising_fails_too_recover_salvages_the_complete_chunks(tmp_path):
    path = tmp_path / "squeezed.mcap"
    result = _run_writer_child(path, squeeze=True)
    assert "File too large" in result["finalise_error"]
    assert result["durable"] > 0
    fixed = tmp_path / "fixed.mcap"
    rec = run_followbus("recover", str(path), "-o", str(fixed), timeout=60)
    assert rec.returncode == 0, rec.stdout + rec.stderr
    bus = list(iter_bus_messages(fixed))
    assert [m.sequence for m in bus] == list(range(result["durable"]))



def test_recover_skips_a_corrupt_chunk_and_keeps_the_others(tmp_path):
    """bus/recording.salvage_records: a chunk whose body is damaged (its CRC fails) is skipped, counted, and the
    chunks before and after it are rewritten whole."""
    from followbus.tools.recording.mcap_io import RecordingWriter, recover

    path = tmp_path / "damaged.mcap"
    writer = RecordingWriter(path, compression="none")
    channel = writer.bus_channel("t/ticker/tick", "Tick")
    for chunk in range(3):
        for i in range(4):
            tick = Tick(value=chunk * 4 + i)
            tick.header.seq = chunk * 4 + i
            writer.write(channel, 1_000 + tick.header.seq, tick.encode(), sequence=tick.header.seq)
        writer.flush()
    writer.finish()
    middle = read_summary(path).chunk_indexes[1]
    data = bytearray(path.read_bytes())
    data[middle.chunk_start_offset + middle.chunk_length - 8] ^= 0xFF  # inside its last message's bytes
    path.write_bytes(bytes(data))
    result = recover(path, tmp_path / "fixed.mcap")
    assert (result.chunks, result.bad_chunks, result.complete, result.messages) == (2, 1, True, 8)
    assert [m.sequence for m in iter_bus_messages(tmp_path / "fixed.mcap")] == [0, 1, 2, 3, 8, 9, 10, 11]


def test_recorder_queue_bound_drops_counts_per_key_and_warns_once(graph_file, port, tmp_path):
    """A bound smaller than one frame: every frame is dropped (deterministically), the small ticks are not,
    --exclude'd keys never reach the recorder, and the warning is rate-limited to one line."""
    graph = graph_file(NODES)
    out = tmp_path / "bounded.mcap"
    session = _peer(port)
    pubs = {key: Publisher(session, key, "test") for key in ("t/capture/frame", "t/ticker/tick", "t/noise/tick")}
    proc = subprocess.Popen(
        followbus_argv("record", "--graph", str(graph), "-o", str(out), "--max-queue-mb", "0.1",
                       "--exclude", "t/noise/**"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL, cwd=REPO)
    try:
        assert _wait_for_recorder(session, "t"), "the recorder never came up"
        # Its token can reach this session before its subscriptions do (a loaded machine): a put before then
        # goes to nobody. The recorded keys' publishers wait until they match the recorder.
        assert wait_until(lambda: pubs["t/capture/frame"].listened and pubs["t/ticker/tick"].listened, 30)
        rng = np.random.default_rng(2)
        for seq in range(5):
            pubs["t/capture/frame"].put(_noise_frame(rng, seq))  # 230 kB > the 105 kB bound
            pubs["t/ticker/tick"].put(Tick())
            pubs["t/noise/tick"].put(Tick())
        time.sleep(3.0)  # in flight on loopback before the recorder unsubscribes
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        session.close()
    assert proc.returncode == 130, stdout + stderr  # stopped by Ctrl-C (SIGINT): 130, as every command
    keys = json.loads(read_metadata(out)["recording_stats"]["keys"])
    assert set(keys) == {"t/capture/frame", "t/ticker/tick"}
    # A starved recorder may still have some in flight when it unsubscribes: what it received is the measure.
    frames, ticks = keys["t/capture/frame"], keys["t/ticker/tick"]
    assert 1 <= frames["received"] <= 5 and frames["dropped"] == frames["received"] and frames["written"] == 0
    assert 1 <= ticks["received"] <= 5 and ticks["dropped"] == 0 and ticks["written"] == ticks["received"]
    assert int(read_metadata(out)["recording_stats"]["max_queue_bytes"]) <= 0.1 * 2**20
    warnings = [line for line in stderr.splitlines() if "recorder queue at its bound" in line]
    assert len(warnings) == 1 and "t/capture/frame" in warnings[0], stderr
    assert f"dropped by the recorder: {frames['dropped']}" in stdout, stdout


def test_oversized_publication_is_refused_counted_and_not_delivered(port, caplog):
    receiver = _peer(port)
    sender = open_session(ZenohSettings(mode="client", listen=[], connect=[f"tcp/127.0.0.1:{port}"], shm=False))
    got: list[tuple[int, int]] = []  # (header.seq, payload bytes)
    sub = receiver.declare_subscriber("t/big", direct_callback(
        lambda s: got.append((decode(data := payload_bytes(s)).header.seq, len(data)))))
    pub = Publisher(sender, "t/big", "test")
    try:
        # The subscription reaches the sender: a first frame arrives.
        assert wait_until(lambda: pub.put(Frame(width=1, height=1, data=np.zeros((1, 1, 3), np.uint8))) and bool(got),
                          10, interval=0.1)
        assert wait_until(lambda: got[-1][0] == pub._seq - 1, 10)  # the last probe is in: none in flight
        sent_before = pub.stats.count
        got.clear()
        refused_seq = pub._seq
        huge = Frame(width=4100, height=4096, data=np.zeros((4096, 4100, 3), np.uint8))  # 50.4 MB > 48 MiB
        with caplog.at_level(logging.WARNING, logger="followbus.bus.pubsub"):
            assert pub.put(huge) is False
            assert pub.put_bytes(b"\0" * (MAX_PAYLOAD_BYTES + 1)) is False
        snap = pub.stats.snapshot()
        assert snap["refused"] == 2 and pub.stats.refused == 2
        assert snap["count"] == sent_before  # refused puts are not counted as sent
        refusals = [r for r in caplog.records if "refused" in r.getMessage()]
        assert len(refusals) == 1 and "t/big" in refusals[0].getMessage()  # rate-limited: one line for two
        # The next normal put still goes out, and is the only thing that arrives: the refused one never did.
        assert pub.put(Frame(width=2, height=2, data=np.ones((2, 2, 3), np.uint8))) is True
        assert wait_until(lambda: bool(got), 10)
        # One publisher's puts arrive in order: had the refused ones gone out, they would come first.
        assert got[0][0] == refused_seq + 1 and got[0][1] < 1000  # the refused seq is a gap subscribers see
    finally:
        sub.undeclare()
        pub.undeclare()
        sender.close()
        receiver.close()
