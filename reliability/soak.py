"""The soak's judgement: the launched graph followed for minutes, each node's process sampled once a window.

A loop that runs for hours must not grow: memory, open files and threads of every node stay where they were after
the first window, no node restarts, and every window still answers the frames with the latency it had at the start.
``followbus bench soak`` (tools/bench/soak.py) runs it; this module samples /proc and judges, with no bus."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class ProcessSample:
    """One node's process at one moment (from /proc/<pid>)."""

    pid: int
    rss_mb: float
    fds: int
    threads: int


@dataclass
class SoakWindow:
    """One window of the soak: the pipeline's figures and every node's process at its end."""

    index: int
    figures: dict[str, Any]
    processes: dict[str, ProcessSample | None]
    load1: float = field(default_factory=lambda: os.getloadavg()[0])

    @property
    def answered(self) -> float:
        published = self.figures.get("frames_published", 0)
        return self.figures.get("tracks", 0) / published if published else 0.0

    @property
    def p99_ms(self) -> float:
        return float(self.figures.get("edges_ms", {}).get("total capture→command", {}).get("p99", float("nan")))

    def as_dict(self) -> dict[str, Any]:
        return {"index": self.index, "load1": self.load1, "answered": round(self.answered, 4),
                "p99_ms": self.p99_ms, "figures": self.figures,
                "processes": {n: asdict(p) if p else None for n, p in self.processes.items()}}


@dataclass(frozen=True)
class SoakBounds:
    """What "clean" means. Memory may settle after the first window (caches, the template's history) but not
    keep growing; descriptors and threads come back to what they were."""

    rss_growth_mb: float = 30.0  # per node, last window against the first
    fd_growth: int = 0
    thread_growth: int = 0
    # Frames answered may not fall more than this below the first window's (a fraction of those published): the
    # soak judges drift; how many a machine answers at all is `bench pipeline`'s figure, and this VM's own speed
    # moves it by several points from one hour to the next.
    answered_drop: float = 0.05
    p99_growth_ms: float = 50.0  # the last window's p99 against the first's


def sample_process(pid: int, proc: Path = Path("/proc")) -> ProcessSample | None:
    """RSS, open descriptors and threads of ``pid``; None when it is gone."""
    try:
        status = (proc / str(pid) / "status").read_text()
        fds = len(os.listdir(proc / str(pid) / "fd"))
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    try:
        rss_kb = int(fields.get("VmRSS", "0 kB").split()[0])
        threads = int(fields.get("Threads", "0").split()[0])
    except ValueError:
        return None
    return ProcessSample(pid=pid, rss_mb=rss_kb / 1024.0, fds=fds, threads=threads)


def judge_soak(windows: list[SoakWindow], bounds: SoakBounds = SoakBounds()) -> list[str]:
    """The soak's failures, one line each (empty: clean)."""
    if len(windows) < 2:
        return ["fewer than two windows: nothing to compare"]
    first, last = windows[0], windows[-1]
    failures = []
    for name, start in first.processes.items():
        failures += _process_failures(name, start, [w.processes.get(name) for w in windows[1:]], bounds)
    for w in windows[1:]:
        if w.answered < first.answered - bounds.answered_drop:
            failures.append(f"window {w.index}: {w.answered:.1%} of frames answered against {first.answered:.1%} "
                            f"in the first (bound -{bounds.answered_drop:.0%}, load {w.load1:.1f})")
    if last.p99_ms > first.p99_ms + bounds.p99_growth_ms:
        failures.append(f"p99 grew from {first.p99_ms:.0f} to {last.p99_ms:.0f} ms "
                        f"(bound +{bounds.p99_growth_ms:.0f} ms)")
    return failures


def _process_failures(name: str, start: ProcessSample | None, later: list[ProcessSample | None],
                      bounds: SoakBounds) -> list[str]:
    if start is None:
        return [f"{name}: no process in the first window"]
    if any(s is None or s.pid != start.pid for s in later):
        return [f"{name}: restarted or gone during the soak (pid {start.pid})"]
    end = later[-1]
    assert end is not None
    failures = []
    if end.rss_mb - start.rss_mb > bounds.rss_growth_mb:
        failures.append(f"{name}: RSS grew {start.rss_mb:.0f} -> {end.rss_mb:.0f} MB "
                        f"(bound +{bounds.rss_growth_mb:.0f} MB)")
    if end.fds - start.fds > bounds.fd_growth:
        failures.append(f"{name}: open descriptors grew {start.fds} -> {end.fds}")
    if end.threads - start.threads > bounds.thread_growth:
        failures.append(f"{name}: threads grew {start.threads} -> {end.threads}")
    return failures
