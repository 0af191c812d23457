"""`followbus bench bus` runs every path in its own processes and leaves none behind: a tiny plan through raw
zenoh and bus/ (and dora-rs when it is installed) delivers every counted message and reports CPU per message.
Figures are not asserted: they live in BENCHMARKS.md."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import pytest

from followbus.tools.bench.bus import dora_available, run_bench_bus

pytestmark = pytest.mark.slow


def _bench_processes(where: Path) -> set[int]:
    """Processes of a bench bus run whose temporary directory is under ``where``: its children, a dora daemon."""
    found = set()
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if str(where).encode() in cmd:
            found.add(int(pid))
    return found


def _run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, against: str | None) -> dict:
    out = tmp_path / "bus.json"
    args = argparse.Namespace(count=3, rounds=1, sizes="1KB,921KB", rates="100", against=against, json=str(out))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # the run's own files and processes: under tmp_path
    assert run_bench_bus(args) == 0
    assert _bench_processes(tmp_path) == set(), "bench bus left processes behind"
    return json.loads(out.read_text())


def _check(result: dict, paths: list[str]) -> None:
    assert sorted(result["paths"]) == sorted(paths)
    for path in paths:
        rows = result["paths"][path]
        assert [r["size"] for r in rows] == ["1KB", "921KB"]
        for row in rows:
            assert row["n"] == row["expected"] == 3, (path, row)
            assert 0 < row["p50_ms"] <= row["p99_ms"]
            assert row["cpu_ms_per_msg"] > 0


def test_bench_bus_measures_raw_and_bus_each_in_its_own_processes(tmp_path, monkeypatch):
    _check(_run(tmp_path, monkeypatch, None), ["raw", "bus"])


def test_bench_bus_against_dora_runs_its_own_dataflow_and_counts_the_daemon(tmp_path, monkeypatch):
    why = dora_available()
    if why and os.environ.get("CI"):
        pytest.fail(f"`make test` installs dora-rs (the bench extra), yet: {why}")
    if why:
        pytest.skip(f"dora-rs not installed (pip install 'followbus[bench]'): {why}")
    result = _run(tmp_path, monkeypatch, "dora")
    _check(result, ["raw", "bus", "dora"])
    assert all(r["daemon_cpu_ms_per_msg"] is not None for r in result["paths"]["dora"])
