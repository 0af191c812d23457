"""``followbus bench flood``: what a read-only laptop that declares thousands of subscribers costs the robot.

The robot graph (graph.robot.yaml: router hub, user/password, access control; simulated detector by default, the
scene looping at 30 Hz) runs on loopback. A probe (tools/bench/link.py's, as the robot's identity) measures the
capture→command latency of every motor command per window. A flooder joins as ``monitor`` at nice 19 (a
laptop's CPU is its own; on one machine this is the nearest) and declares ``--subscribers`` subscribers on
distinct keys under the graph's namespace (each a new routing entry, the costly case: the same key declared
again costs a router nothing), holds them, then leaves. Phases:

- ``before``: no flooder;
- ``declaring``: windows until the flooder has declared them all (the worst window is reported);
- ``held``: every subscriber declared;
- ``left``: the flooder undeclared them and closed its session, the hub had a moment to hand memory back.

Per phase: the robot's p99, frames answered, the motor's watchdog stops (its log lines), and the RSS of the
launcher (the hub every link goes through) and of each node against ``before``.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...bus.children import interrupt_all
from ...reliability.soak import sample_process
from .link import MONITOR_PASSWORD, wait_for_launch, write_robot_graph
from .pipeline import cpu_ticks

PHASES = ("before", "declaring", "held", "left")
FLOODER_NICE = 19
LEFT_SETTLE_S = 3.0  # after the flooder closed: the hub trims what it freed (bus/session.py MemoryTrim, 1 s)
NAMESPACE = "flood"
IDENTITY_ENV = ("FOLLOWBUS_DOMAIN", "FOLLOWBUS_NAMESPACE", "FOLLOWBUS_PORT")  # the bench sets port and namespace


def bench_env(**extra: str) -> dict[str, str]:
    """This environment without the variables that would move the graph off the bench's port and namespace."""
    return {k: v for k, v in os.environ.items() if k not in IDENTITY_ENV} | extra


# --- the flooder (a process of its own, as the laptop) ---------------------------------------------------------

def flooder_main(endpoint: str, count: int, namespace: str) -> int:
    """Join as monitor, declare ``count`` subscribers on distinct keys, say so; on a line on stdin undeclare them
    and say so; on the next (or EOF) leave."""
    from ...bus.session import ZenohSettings, open_session

    session = open_session(ZenohSettings(
        mode="client", listen=[], connect=[endpoint],
        config={"transport/auth/usrpwd": {"user": "monitor", "password": os.environ["FOLLOWBUS_ZENOH_PASSWORD"]}}))
    start = time.monotonic()
    subs = [session.declare_subscriber(f"{namespace}/flood/{i}", lambda _sample: None) for i in range(count)]
    print(json.dumps({"declared_s": round(time.monotonic() - start, 1)}), flush=True)
    sys.stdin.readline()
    for sub in subs:
        sub.undeclare()
    print("undeclared", flush=True)
    sys.stdin.readline()
    session.close()
    return 0


# --- the robot --------------------------------------------------------------------------------------------------

def child_pids(pid: int) -> list[int]:
    children: list[int] = []
    with contextlib.suppress(OSError):
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                children += [int(p) for p in f.read().split()]
    return children


def node_name(pid: int) -> str:
    """A launched node's name from its command line (``... node NAME --graph ...``)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().decode(errors="replace").split("\0")
    except OSError:
        return str(pid)
    return argv[argv.index("node") + 1] if "node" in argv[:-1] else str(pid)


@dataclass
class Phase:
    name: str
    p99_ms: float | None = None
    answered: int = 0
    frames: int = 0
    stops: int = 0
    rss_mb: dict[str, float] = field(default_factory=dict)  # launcher and each node, against `before`
    cpu_pct: dict[str, float] = field(default_factory=dict)  # launcher, and the nodes together, % of one core


class FloodBench:
    """The robot graph and its probe on loopback, the flooder as ``monitor`` beside them."""

    def __init__(self, tmp: Path, port: int, detector: str, log: Path | None = None):
        from ...bus.graph import load_graph

        self.tmp, self.log, self.endpoint = tmp, log, f"tcp/127.0.0.1:{port}"
        graph = write_robot_graph(tmp, port, "127.0.0.1", detector, namespace=NAMESPACE)
        # write_robot_graph listens on loopback and on a laptop's address; here the laptop is on loopback too.
        robot = load_graph(graph).with_zenoh(listen=[self.endpoint])
        graph.write_text(robot.to_yaml())
        self.graph = graph
        self.robot = subprocess.Popen([sys.executable, "-m", "followbus.tools.cli", "launch", str(graph),
                                       "--startup-timeout", "90"], cwd=tmp, env=bench_env(), stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True)
        self.robot_lines: list[str] = []
        threading.Thread(target=lambda: self.robot_lines.extend(iter(self.robot.stdout.readline, "")),
                         daemon=True).start()
        self.probe: subprocess.Popen | None = None
        self.flooder: subprocess.Popen | None = None
        self.baseline: dict[str, float] = {}

    def start(self, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        wait_for_launch(self.robot, self.robot_lines, timeout_s)
        self.probe = subprocess.Popen([sys.executable, "-m", "followbus.tools.bench.link", "probe", str(self.graph)],
                                      cwd=self.tmp, env=bench_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      text=True)
        if self.probe.stdout.readline().strip() != "ready":
            raise RuntimeError("the probe did not start")
        while not self._window(1.0)["answered"]:  # warm-up: the target acquired
            if time.monotonic() > deadline:
                raise RuntimeError("the robot graph never answered a frame: " + "".join(self.robot_lines[-10:]))

    def _window(self, seconds: float) -> dict[str, Any]:
        assert self.probe is not None
        mark = len(self.robot_lines)
        self.probe.stdin.write(f"{seconds}\n")
        self.probe.stdin.flush()
        figures = json.loads(self.probe.stdout.readline())
        figures["stops"] = sum("watchdog:" in line for line in self.robot_lines[mark:])
        return figures

    def processes(self) -> dict[str, int]:
        return {"launcher": self.robot.pid} | {node_name(p): p for p in child_pids(self.robot.pid)}

    def cpu(self) -> dict[str, float]:
        """CPU seconds used so far by the launcher, and by the nodes together."""
        pids = self.processes()
        seconds = {name: (cpu_ticks(pid) or 0) / os.sysconf("SC_CLK_TCK") for name, pid in pids.items()}
        return {"launcher": seconds.pop("launcher"), "nodes": sum(seconds.values())}

    def memory(self) -> dict[str, float]:
        """RSS in MB of the launcher and of each node."""
        return {name: sample.rss_mb for name, pid in self.processes().items()
                if (sample := sample_process(pid)) is not None}

    def phase(self, name: str, seconds: float) -> Phase:
        cpu0, t0 = self.cpu(), time.monotonic()
        w = self._window(seconds)
        cpu1, elapsed = self.cpu(), time.monotonic() - t0
        now = self.memory()
        if not self.baseline:
            self.baseline = now
        grown = {k: round(now[k] - self.baseline[k], 1) for k in now if k in self.baseline}
        cpu = {k: round(100 * (cpu1[k] - cpu0[k]) / elapsed, 1) for k in cpu1}
        return Phase(name, w["p99_ms"], w["answered"], w["frames"], w["stops"], grown, cpu)

    def flood(self, count: int, seconds: float, progress: Any = print) -> tuple[list[Phase], dict[str, Any]]:
        """The phases after ``before``: the flooder declares, holds, leaves."""
        env = bench_env(FOLLOWBUS_ZENOH_PASSWORD=MONITOR_PASSWORD, PYTHONUNBUFFERED="1")
        argv = ["nice", "-n", str(FLOODER_NICE), sys.executable, "-m", "followbus.tools.bench.flood", "flooder",
                self.endpoint, str(count), NAMESPACE]
        self.flooder = subprocess.Popen(argv, cwd=self.tmp, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True)
        declared: dict[str, Any] = {}
        reader = threading.Thread(target=lambda: declared.update(json.loads(self.flooder.stdout.readline() or "{}")),
                                  daemon=True)
        reader.start()
        windows = []
        while reader.is_alive() or not windows:
            windows.append(self.phase("declaring", seconds))
            progress(f"  declaring: {_phase_line(windows[-1])}")
        phases = [_worst(windows), self.phase("held", seconds)]
        self.flooder.stdin.write("\n")
        self.flooder.stdin.flush()
        self.flooder.stdout.readline()  # undeclared
        self.flooder.stdin.close()  # it leaves
        self.flooder.wait(60)
        time.sleep(LEFT_SETTLE_S)
        phases.append(self.phase("left", seconds))
        return phases, declared

    def close(self) -> None:
        if self.log is not None:
            self.log.parent.mkdir(parents=True, exist_ok=True)
            self.log.write_text("".join(self.robot_lines))
        if self.probe is not None and self.probe.poll() is None:
            self.probe.stdin.close()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.probe.wait(10)
        interrupt_all((self.flooder, self.probe, self.robot))


def _worst(windows: list[Phase]) -> Phase:
    """The declaring phase: its worst window's p99, every window's frames and stops, the memory at its end."""
    p99s = [w.p99_ms for w in windows if w.p99_ms is not None]
    cpu = {k: round(sum(w.cpu_pct[k] for w in windows) / len(windows), 1) for k in windows[0].cpu_pct}
    return Phase("declaring", max(p99s) if p99s else None, sum(w.answered for w in windows),
                 sum(w.frames for w in windows), sum(w.stops for w in windows), windows[-1].rss_mb, cpu)


def _phase_line(phase: Phase) -> str:
    p99 = f"p99 {phase.p99_ms:.1f} ms" if phase.p99_ms is not None else "no command"
    nodes = [mb for name, mb in phase.rss_mb.items() if name != "launcher"]
    return (f"{p99}, answered {phase.answered}/{phase.frames}, {phase.stops} watchdog stops, launcher RSS "
            f"{phase.rss_mb.get('launcher', 0):+.1f} MB, nodes {max(nodes, default=0):+.1f} MB at most; CPU launcher "
            f"{phase.cpu_pct.get('launcher', 0):.0f}%, nodes {phase.cpu_pct.get('nodes', 0):.0f}%")


def run_flood_bench(count: int, seconds: float, detector: str, port: int, log: Path | None,
                    progress: Any = print) -> tuple[list[Phase], dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="followbus-flood-") as tmp:
        bench = FloodBench(Path(tmp), port, detector, log)
        try:
            bench.start()
            before = bench.phase("before", seconds)
            progress(f"  before: {_phase_line(before)}")
            phases, declared = bench.flood(count, seconds, progress)
        finally:
            bench.close()
    return [before, *phases], declared


def table(phases: list[Phase]) -> str:
    nodes = sorted({name for p in phases for name in p.rss_mb} - {"launcher"})
    head = ["phase", "capture→command p99 ms", "frames answered", "watchdog stops", "CPU % launcher / nodes",
            "launcher RSS Δ MB", *nodes]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for p in phases:
        p99 = f"{p.p99_ms:.1f}" if p.p99_ms is not None else "-"
        cpu = f"{p.cpu_pct.get('launcher', 0):.0f} / {p.cpu_pct.get('nodes', 0):.0f}"
        cells = [p.name, p99, f"{p.answered}/{p.frames}", str(p.stops), cpu, f"{p.rss_mb.get('launcher', 0):+.1f}",
                 *(f"{p.rss_mb.get(n, 0):+.1f}" for n in nodes)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _load() -> str:
    with open("/proc/loadavg") as f:
        return " ".join(f.read().split()[:3])


def cmd_bench_flood(args) -> int:
    print(f"bench flood: {args.subscribers} subscribers on distinct keys declared as monitor (nice {FLOODER_NICE}), "
          f"{args.seconds:g} s windows; detector {args.detector}; load {_load()}", flush=True)
    phases, declared = run_flood_bench(args.subscribers, args.seconds, args.detector, args.port,
                                       Path(args.log) if args.log else None)
    print(f"declared in {declared.get('declared_s', '?')} s; load at the end: {_load()}")
    print(table(phases))
    if args.json:
        Path(args.json).write_text(json.dumps({"declared": declared, "phases": [vars(p) for p in phases]}, indent=1))
    return 0


if __name__ == "__main__" and len(sys.argv) == 5 and sys.argv[1] == "flooder":
    sys.exit(flooder_main(sys.argv[2], int(sys.argv[3]), sys.argv[4]))
