"""The soak: /proc sampling, the judgement, and `followbus bench soak` on the launched graph."""

from __future__ import annotations

import json
import os
import threading

import pytest

from followbus.reliability.soak import ProcessSample, SoakBounds, SoakWindow, judge_soak, sample_process

from .conftest import free_port, run_followbus


def _window(index: int, procs: dict[str, ProcessSample | None], tracks: int = 300, p99: float = 60.0) -> SoakWindow:
    figures = {"frames_published": 300, "tracks": tracks, "edges_ms": {"total capture→command": {"p99": p99}}}
    return SoakWindow(index, figures, procs, load1=1.0)


def test_sample_process_sees_a_new_thread_and_descriptor():
    before = sample_process(os.getpid())
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait)
    thread.start()
    fd = os.open(os.devnull, os.O_RDONLY)
    try:
        during = sample_process(os.getpid())
    finally:
        os.close(fd)
        stop.set()
        thread.join()
    assert before is not None and during is not None and before.rss_mb > 1
    assert during.threads == before.threads + 1 and during.fds == before.fds + 1
    assert sample_process(2 ** 22 + 1) is None  # beyond pid_max: gone


def test_judge_soak_names_growth_restarts_and_unanswered_windows():
    steady = ProcessSample(pid=10, rss_mb=100.0, fds=20, threads=8)
    assert judge_soak([_window(1, {"reid": steady}), _window(2, {"reid": steady})]) == []
    grown = ProcessSample(pid=10, rss_mb=100.0 + SoakBounds().rss_growth_mb + 1, fds=21, threads=9)
    failures = judge_soak([_window(1, {"reid": steady}), _window(2, {"reid": grown})])
    assert [f.split(":")[1].split()[0] for f in failures] == ["RSS", "open", "threads"]
    restarted = ProcessSample(pid=11, rss_mb=100.0, fds=20, threads=8)
    assert judge_soak([_window(1, {"motor": steady}), _window(2, {"motor": restarted})]) == [
        "motor: restarted or gone during the soak (pid 10)"]
    assert judge_soak([_window(1, {"motor": steady}), _window(2, {"motor": None})])[0].startswith("motor: restarted")
    slow = judge_soak([_window(1, {}), _window(2, {}, tracks=290), _window(3, {}, tracks=240, p99=200.0)])
    assert slow == ["window 3: 80.0% of frames answered against 100.0% in the first (bound -5%, load 1.0)",
                    "p99 grew from 60 to 200 ms (bound +50 ms)"]  # window 2 (96.7 %) is within the bound
    assert judge_soak([_window(1, {})]) == ["fewer than two windows: nothing to compare"]


@pytest.mark.slow
def test_bench_soak_samples_every_node_each_window(tmp_path):
    out = tmp_path / "soak.json"
    result = run_followbus("bench", "soak", "--minutes", "0.1", "--window", "3", "--detector", "simulated",
                           "--port", str(free_port()), "--json", str(out), timeout=180)
    report = json.loads(out.read_text())
    windows = [SoakWindow(w["index"], w["figures"], {n: ProcessSample(**p) if p else None
                                                      for n, p in w["processes"].items()}, w["load1"])
               for w in report["windows"]]
    assert len(windows) == 2, result.stdout + result.stderr
    for w in windows:
        assert set(w.processes) == {"capture", "detection", "egomotion", "prediction", "redetection", "reid",
                                    "template", "motor"}
        assert all(p is not None and p.rss_mb > 10 and p.fds > 3 and p.threads > 1 for p in w.processes.values())
        assert w.figures["frames_published"] > 30 and w.answered > 0
    # The verdict is the judgement of what it printed and wrote, and the exit status says it.
    assert report["failures"] == judge_soak(windows)
    assert result.returncode == (0 if not report["failures"] else 1), result.stdout + result.stderr
    assert ("soak: clean" in result.stdout) == (not report["failures"])
