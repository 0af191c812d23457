"""Recordings are verified before use (issue 25): a chunk whose CRC fails is named with its time range and
refused (or skipped, when asked) by info, play and replay; tiny and non-regular files are one line each; recover
leaves nothing behind on a file that is not MCAP. Hand-made recordings in tmp_path, real MCAP files."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from followbus.bus.recording import (
    CorruptChunkError,
    CorruptRecording,
    chunks_to_skip,
    corrupt_chunks,
    iter_bus_messages,
    read_summary,
)
from followbus.msgs.perception import Detections
from followbus.replay.plan import ReplayOptions, ReplayPlan
from followbus.tools.cli import main
from followbus.tools.recording.mcap_io import RecordingWriter

from .conftest import REPO, run_followbus

T0 = 1_700_000_000_000_000_000
DT = 33_000_000


def _recording(path: Path, chunks: int = 3, per_chunk: int = 4) -> Path:
    """Detections on fb/detection/detections, one chunk per ``per_chunk`` frames, with graph.yaml's metadata
    (prediction can be replayed from it)."""
    writer = RecordingWriter(path, compression="none")
    writer.metadata("graph", {"yaml": (REPO / "graph.yaml").read_text()})
    writer.metadata("followbus", {"namespace": "fb"})
    channel = writer.bus_channel("fb/detection/detections", "Detections")
    for k in range(chunks * per_chunk):
        msg = Detections()
        msg.header.frame_seq, msg.header.stamp_ns, msg.header.seq = k, T0 + k * DT, k
        writer.write(channel, T0 + k * DT, msg.encode(), sequence=k)
        if k % per_chunk == per_chunk - 1:
            writer.flush()
    writer.finish()
    return path


def _flip_middle_chunk(path: Path) -> tuple[int, int]:
    """Flip a byte inside the second chunk's last message; its (start, end) log times."""
    middle = read_summary(path).chunk_indexes[1]
    data = bytearray(path.read_bytes())
    data[middle.chunk_start_offset + middle.chunk_length - 8] ^= 0xFF
    path.write_bytes(bytes(data))
    return middle.message_start_time, middle.message_end_time


@pytest.fixture
def damaged(tmp_path) -> Path:
    path = _recording(tmp_path / "damaged.mcap")
    _flip_middle_chunk(path)
    return path


def test_a_corrupt_chunk_is_named_with_its_time_range(damaged):
    bad = corrupt_chunks(damaged)
    assert len(bad) == 1 and bad[0].reason == "CRC mismatch"
    assert (bad[0].start_ns, bad[0].end_ns) == (T0 + 4 * DT, T0 + 7 * DT)
    text = bad[0].describe()
    assert "2023-11-14 22:13:20.132" in text and "UTC" in text and "0.10 s" in text, text
    with pytest.raises(CorruptRecording, match="--on-corrupt skip"):
        chunks_to_skip(damaged, None, "refuse")
    # A reader that was not told to skip it does not hand out its messages either.
    with pytest.raises(CorruptChunkError):
        list(iter_bus_messages(damaged))


def test_skip_reads_every_other_chunk(damaged, caplog):
    skip = chunks_to_skip(damaged, ["fb/detection/detections"], "skip")
    assert "skipping corrupt chunk" in caplog.text
    assert [m.sequence for m in iter_bus_messages(damaged, skip_chunks=skip)] == [0, 1, 2, 3, 8, 9, 10, 11]


def test_an_intact_recording_passes(tmp_path):
    path = _recording(tmp_path / "good.mcap")
    assert corrupt_chunks(path) == [] and chunks_to_skip(path, None, "refuse") == frozenset()


def test_info_reports_the_corrupt_chunk_and_fails(damaged, capsys):
    assert main(["info", str(damaged)]) == 1
    out = capsys.readouterr().out
    assert "integrity:   2 of 3 chunks pass their CRC" in out and "corrupt:   chunk at byte" in out, out


def test_play_refuses_before_publishing(damaged, capsys):
    # Refused before a session is opened: nothing reaches the bus (the endpoint here does not even exist).
    assert main(["play", str(damaged), "--connect", "tcp/127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "corrupt chunk at byte" in err and "--on-corrupt skip" in err, err


def test_replay_refuses_instead_of_blaming_the_node(damaged):
    with pytest.raises(CorruptRecording):
        ReplayPlan(damaged, ReplayOptions(nodes=["prediction"]))
    plan = ReplayPlan(damaged, ReplayOptions(nodes=["prediction"], on_corrupt="skip"))
    assert len(plan.skip_chunks) == 1


def test_replay_command_refusal_is_one_line(damaged, capsys):
    assert main(["replay", str(damaged), "--node", "prediction", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "corrupt chunk" in err, err


@pytest.mark.parametrize("size", [8, 12, 16])
@pytest.mark.parametrize("command", ["info", "play", "replay", "recover"])
def test_tiny_files_are_one_line(tmp_path, capsys, size, command):
    path = tmp_path / "tiny.mcap"
    path.write_bytes((b"\x89MCAP0\r\n" * 2)[:size])
    args = {"play": ["--connect", "tcp/127.0.0.1:9"], "replay": ["--node", "prediction"],
            "recover": ["-o", str(tmp_path / "out.mcap")]}.get(command, [])
    assert main([command, str(path), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{size} bytes: too short" in err, err
    assert not (tmp_path / "out.mcap").exists()


@pytest.mark.parametrize("command", ["info", "play", "replay", "recover"])
def test_a_fifo_named_mcap_is_one_line_not_a_hang(tmp_path, command):
    fifo = tmp_path / "pipe.mcap"
    os.mkfifo(fifo)
    args = {"play": ["--connect", "tcp/127.0.0.1:9"], "replay": ["--node", "prediction"],
            "recover": ["-o", str(tmp_path / "out.mcap")]}.get(command, [])
    result = run_followbus(command, str(fifo), *args, timeout=30)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == f"followbus: {fifo}: not a regular file"
    assert not (tmp_path / "out.mcap").exists()


def test_recover_of_a_file_that_is_not_mcap_leaves_nothing(tmp_path, capsys):
    junk = tmp_path / "notes.mcap"
    junk.write_bytes(b"this is not a recording at all, just some text\n" * 4)
    out = tmp_path / "notes.recovered.mcap"
    assert main(["recover", str(junk), "-o", str(out)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    assert not out.exists()
