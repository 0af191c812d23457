"""Recordings recover what is good (issue 36): `recover` rewrote 0 messages, exit 0, when the first chunk of a
`followbus record` file was damaged (its channel records were in it), gave a traceback on a `launch --record` file
(KeyError: a channel whose schema was in the lost chunk), and lost every chunk after a damaged length field; 40
damaged bytes before the first chunk passed `info` and `play`. Now every chunk whose CRC passes is rewritten,
whichever is bad, what was dropped is listed, and info/play check the magic, the header and the record framing.
Real recordings of a launched graph (`followbus record` and `launch --record`), damaged byte by byte."""

from __future__ import annotations

import io
import shutil
import signal
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from followbus.bus.recording import corrupt_chunks, iter_bus_messages, read_summary, structure_damage
from followbus.tools.cli import main

from .conftest import followbus_argv, free_port, run_followbus

NODES = """\
  ticker: {run: followbus.nodes.diagnostics, outputs: [tick], params: {rate_hz: 100}}
  capture:
    run: followbus.nodes.capture
    outputs: [frame, preview, ground_truth]
    params: {source: "scene:corridor-occlusion", width_px: 160, height_px: 120, loop: true}
  sink: {run: followbus.nodes.diagnostics_sink, inputs: {tick: ticker/tick}}
"""


@dataclass
class Files:
    record: Path  # by `followbus record`
    launch: Path  # by `launch --record`


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Files:
    """One graph, recorded both ways at once: a chunk a second, each file several chunks. The recorder runs until
    the launch's 6 s (counted from the moment every node is up) are over, then stops on SIGTERM as Ctrl-C stops it:
    a recorder of fixed length ends on the clock, however late the graph came up, and on a loaded machine held one or
    two chunks (seen beside two burners, and in CI)."""
    tmp = tmp_path_factory.mktemp("salvage")
    port = free_port()
    graph = tmp / "graph.yaml"
    graph.write_text(f"name: test\nnamespace: t\nzenoh:\n  listen: [tcp/127.0.0.1:{port}]\n"
                     f"  connect: [tcp/127.0.0.1:{port}]\nnodes:\n{NODES}")
    files = Files(tmp / "record.mcap", tmp / "launch.mcap")
    launch = subprocess.Popen(followbus_argv("launch", str(graph), "--record", str(files.launch), "--duration", "6"),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    record = subprocess.Popen(followbus_argv("record", "--graph", str(graph), "-o", str(files.record),
                                             "--connect-timeout", "30"),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    try:
        out, _ = launch.communicate(timeout=90)
        assert launch.returncode == 0, out
        record.send_signal(signal.SIGTERM)
        out, _ = record.communicate(timeout=60)
        assert record.returncode == 0, out
    finally:
        for proc in (launch, record):
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    for path in (files.record, files.launch):
        assert len(read_summary(path).chunk_indexes) >= 3, path
    return files


def _copy(src: Path, dst: Path) -> Path:
    shutil.copyfile(src, dst)
    return dst


def _messages(path: Path) -> int:
    with open(path, "rb") as f:
        return sum(1 for _ in make_reader(f).iter_messages(log_time_order=False))


def _first_chunk(path: Path) -> tuple[int, int, int]:
    """(offset, length, messages) of the first chunk."""
    index = read_summary(path).chunk_indexes[0]
    with open(path, "rb") as f:
        f.seek(index.chunk_start_offset)
        raw = f.read(index.chunk_length)
    chunk = Chunk.read(ReadDataStream(io.BytesIO(raw[9:])))
    return index.chunk_start_offset, index.chunk_length, sum(isinstance(r, Message) for r in breakup_chunk(chunk))


def _damage(path: Path, offset: int, data: bytes | None = None, xor: int = 0) -> None:
    raw = bytearray(path.read_bytes())
    if data is not None:
        raw[offset:offset + len(data)] = data
    else:
        raw[offset] ^= xor
    path.write_bytes(bytes(raw))


def _unfinalised(path: Path) -> None:
    """Cut the file after its last chunk and message indexes: what a killed recorder leaves."""
    last = read_summary(path).chunk_indexes[-1]
    cut = last.chunk_start_offset + last.chunk_length + last.message_index_length
    path.write_bytes(path.read_bytes()[:cut])


def _recover(src: Path, tmp_path: Path) -> tuple[subprocess.CompletedProcess, Path]:
    out = tmp_path / "fixed.mcap"
    return run_followbus("recover", str(src), "-o", str(out), timeout=120), out


@pytest.mark.parametrize("which", ["record", "launch"])
def test_a_bit_flipped_in_the_first_chunk_loses_that_chunk_only(recordings, tmp_path, which):
    """On d899b0d: `record` file 0 messages and exit 0; `launch --record` file KeyError (a traceback)."""
    src = _copy(getattr(recordings, which), tmp_path / "damaged.mcap")
    total = _messages(src)
    offset, length, lost = _first_chunk(src)
    _damage(src, offset + length // 2, xor=0x10)
    result, fixed = _recover(src, tmp_path)
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == 1, result.stdout + result.stderr  # recovered, but something was dropped
    assert f"recovered {total - lost} messages" in result.stdout, result.stdout
    assert f"dropped chunk at byte {offset}" in result.stdout and f"({lost} messages): crc" in result.stdout, \
        result.stdout
    assert _messages(fixed) == total - lost and corrupt_chunks(fixed) == [] and structure_damage(fixed) == []
    with open(fixed, "rb") as f:  # every channel that has a schema kept it
        for schema, channel, _ in make_reader(f).iter_messages():
            assert schema is not None or not channel.schema_id


def test_a_killed_recorders_file_with_a_bad_first_chunk_keeps_the_others(recordings, tmp_path):
    """No summary to take the channel records from: those of the damaged chunk are used, and named."""
    src = _copy(recordings.record, tmp_path / "killed.mcap")
    total = _messages(src)
    offset, length, lost = _first_chunk(src)
    _unfinalised(src)
    _damage(src, offset + length // 2, xor=0x10)
    result, fixed = _recover(src, tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert f"recovered {total - lost} messages" in result.stdout, result.stdout
    assert "taken from a damaged chunk for want of another copy (check them): " in result.stdout, result.stdout
    bus = list(iter_bus_messages(fixed, ["t/ticker/tick"]))
    assert bus and [m.sequence for m in bus] == sorted(m.sequence for m in bus)


@pytest.mark.parametrize("finalised", [True, False])
def test_a_damaged_length_field_loses_nothing_after_it(recordings, tmp_path, finalised):
    """On d899b0d reading stopped at the damaged length: every later chunk was lost."""
    src = _copy(recordings.record, tmp_path / "length.mcap")
    total = _messages(src)
    offset, _, _ = _first_chunk(src)
    if not finalised:
        _unfinalised(src)
    _damage(src, offset + 1 + 4, xor=0x40)  # the chunk's record length: 2**38 bytes more
    result, fixed = _recover(src, tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"recovered {total} messages" in result.stdout, result.stdout
    assert f"read all the same chunk at byte {offset}" in result.stdout, result.stdout
    assert _messages(fixed) == total


def test_damaged_bytes_before_the_first_chunk_are_found_by_info_and_play(recordings, tmp_path, capsys):
    """On d899b0d: info "N of N chunks pass", play published everything, exit 0."""
    src = _copy(recordings.record, tmp_path / "header.mcap")
    total = _messages(src)
    assert _first_chunk(src)[0] > 100  # the header and the metadata records come first
    _damage(src, 20, data=b"\xaa" * 40)
    assert main(["info", str(src)]) == 1
    out = capsys.readouterr().out
    assert "corrupt:   " in out and "bytes at byte 8: Header record" in out, out
    assert main(["play", str(src), "--connect", "tcp/127.0.0.1:9"]) == 2  # refused before joining any bus
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bytes at byte 8: Header record" in err and "--on-corrupt skip" in err, err
    result, fixed = _recover(src, tmp_path)
    assert result.returncode == 1 and f"recovered {total} messages" in result.stdout, result.stdout
    assert "dropped " in result.stdout and "bytes at byte 8: Header record" in result.stdout, result.stdout
    assert structure_damage(fixed) == [] and _messages(fixed) == total


def test_an_intact_recording_passes_every_check(recordings, capsys):
    for path in (recordings.record, recordings.launch):
        assert structure_damage(path) == [] and corrupt_chunks(path) == []
        assert main(["info", str(path)]) == 0
        assert "magic, header and record framing hold" in capsys.readouterr().out


def test_recover_of_an_intact_recording_is_exact(recordings, tmp_path):
    result, fixed = _recover(recordings.launch, tmp_path)
    assert result.returncode == 0 and "dropped" not in result.stdout, result.stdout
    assert _messages(fixed) == _messages(recordings.launch)
