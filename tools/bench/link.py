"""``followbus bench link``: does a laptop on a slow link slow the robot, and what does its recording hold?

The robot graph (graph.robot.yaml: router mode, user/password, access control; simulated detector by default,
the scene looping at 30 Hz) runs in one network namespace, the laptop in another with its own /dev/shm,
joined by a veth pair shaped to ``--rate-mbit`` each way (htb; tools/bench/netns.py). A probe on the robot
(its own namespace, over loopback, as the robot's identity) measures, per window, the capture→command latency
of every motor command (``pub_ns - stamp_ns``) and the frames answered (captured frames, counted by their
ground-truth message, that got a motor command). Cases, alternated round by round so that the load of a
shared machine falls on all of them alike:

- ``none``: no laptop;
- ``monitor``: ``followbus monitor --web`` as ``monitor`` (it subscribes to the JPEG preview too);
- ``record-all``: ``followbus record --raw-frames`` (every key, raw frames included: far beyond the link);
- ``record``: ``followbus record`` with the remote default (raw frames left out, the preview kept);
- ``watch``: plain Zenoh subscribers on the laptop (as ``monitor``) to what a slow link is meant to carry: the
  motor command, the track and the JPEG preview;
- ``frames``: the same and the raw frame key (what a subscriber to the camera gets over the link).

For each recording: messages received, dropped by the recorder, and lost on the way (``header.seq`` gaps)
per key, from the file's own ``recording_stats`` metadata. For ``watch`` and ``frames``, per key and window
(after the link has been full for a while): messages received a second, lost (``header.seq`` gaps) and their
age on arrival (``now - stamp_ns``, capture to laptop). ``--rate-mbit`` takes several rates (a pair of namespaces
and a robot launch each); ``--large-rule drop`` measures the robot with large messages to the laptop DROP, as
before bus/netif.py made them BLOCK_FIRST.
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...bus.children import interrupt_all
from .netns import NetnsPair, netns_unavailable

REPO = Path(__file__).resolve().parents[2]
CASES = ("none", "monitor", "record-all", "record", "watch", "frames")
# What a plain subscriber on the laptop listens to in the watch and frames cases (keys of the link namespace).
LAPTOP_KEYS = {"watch": ("motor/command", "prediction/track", "capture/preview"),
               "frames": ("motor/command", "prediction/track", "capture/preview", "capture/frame")}
LARGE_RULES = ("block_first", "drop")  # what the robot's router does with large messages to the laptop
DOMAIN_ENVS = ("FOLLOWBUS_DOMAIN", "FOLLOWBUS_NAMESPACE", "FOLLOWBUS_PORT")  # each namespace is a machine of its own
USERS_FILE = REPO / "docs" / "zenoh-users.example.txt"  # robot, monitor, operator with their example passwords
MONITOR_PASSWORD = "change-me-monitor"
SETTLE_S = 3.0  # the laptop joins and its subscriptions reach the robot before a window opens
LAPTOP_START_S = 30.0  # at most this long for the laptop's first line (it has started) before the settle time
# The laptop's processes share this machine's cores with the robot; a real laptop's CPU is its own. At nice 19
# they take only what the robot leaves, which is the nearest one machine comes to that (0: the laptop competes).
LAPTOP_NICE = 19
LINK_FILL_S = 5.0  # watch and frames: the link's queues fill for this long before a window opens
MIN_RECORDED_S = 5.0  # a check's laptop (run_case until_answered) records at least this long
NAMESPACE = "link"


# --- the robot's graph ---------------------------------------------------------------------------------

def write_robot_graph(tmp: Path, port: int, address: str, detector: str, namespace: str = NAMESPACE,
                      protect: bool = True, drop_wait_us: int | None = None, old_large_rule_on: str = "") -> Path:
    """graph.robot.yaml of the repository (its extends resolved) in ``tmp``: a private port on loopback and on
    ``address`` (the veth end the laptop reaches), the scene looping at 30 Hz, the given detector.
    ``old_large_rule_on``: an interface whose egress is DROP for every put, large ones too (as before BLOCK_FIRST)."""
    from ...bus.graph import load_graph

    robot = load_graph(REPO / "graph.robot.yaml")
    config = copy.deepcopy(robot.zenoh.config)
    config["transport/auth/usrpwd"]["dictionary_file"] = str(USERS_FILE)
    if drop_wait_us is not None:  # how long the hub waits on a full queue before dropping (zenoh: 1 ms, 50 ms)
        config["transport/link/tx/queue/congestion_control/drop"] = {
            "wait_before_drop": drop_wait_us, "max_wait_before_drop_fragments": drop_wait_us}
    if not protect:  # the robot's links to the laptop as before bus/netif.py: BLOCK messages block the router
        config["qos/network"] = []
    elif old_large_rule_on:
        from ...bus.netif import QOS_ID

        config["qos/network"] = [{"id": QOS_ID, "interfaces": [old_large_rule_on], "messages": ["put", "delete"],
                                  "flows": ["egress"], "overwrite": {"congestion_control": "drop"}}]
    robot = robot.override({
        "capture": {"source": "scene:corridor-occlusion", "pace": "realtime", "fps": 30.0, "loop": True},
        "detection": {"backend": detector}, "template": {"state_file": ""}}).with_namespace(namespace)
    robot = robot.with_zenoh(listen=[f"tcp/127.0.0.1:{port}", f"tcp/{address}:{port}"],
                             connect=[f"tcp/127.0.0.1:{port}"], config=config)
    path = tmp / "graph.robot.yaml"
    path.write_text(robot.to_yaml())
    return path


# --- the probe on the robot (a process in the robot's namespace) ---------------------------------------------

class Probe:
    """Motor commands and captured frames of one window (run in the robot's namespace: see probe_main)."""

    def __init__(self, graph_path: str):
        from ...bus.graph import load_graph
        from ...bus.pubsub import declare_subscriber
        from ..connect import client_settings, open_client_session

        graph = load_graph(graph_path)
        self.session = open_client_session(client_settings(graph_path))
        self.lock = threading.Lock()
        self.open = False
        self.latencies_ms: dict[int, float] = {}  # frame_seq -> capture->command of the command answering it
        self.frames: set[int] = set()
        self.subs = [declare_subscriber(self.session, graph.key("motor", "command"), self._on_command),
                     declare_subscriber(self.session, graph.key("capture", "ground_truth"), self._on_frame)]

    def _header(self, sample: Any):
        from ...bus.pubsub import frame_bytes
        from ...bus.schemas import decode
        from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)

        try:
            return decode(frame_bytes(sample)).header
        except Exception:  # not a figure
            return None

    def _on_command(self, sample: Any) -> None:
        h = self._header(sample)
        with self.lock:
            if self.open and h is not None and h.stamp_ns > 0:
                self.latencies_ms.setdefault(h.frame_seq, (h.pub_ns - h.stamp_ns) / 1e6)

    def _on_frame(self, sample: Any) -> None:
        h = self._header(sample)
        with self.lock:
            if self.open and h is not None:
                self.frames.add(h.frame_seq)

    def window(self, seconds: float) -> dict[str, Any]:
        with self.lock:
            self.latencies_ms, self.frames, self.open = {}, set(), True
        time.sleep(seconds)
        with self.lock:
            self.open = False
            # Only commands that answer a captured frame: the watchdog's stops (stamped when sent) are not a trip.
            lat = np.asarray([ms for seq, ms in self.latencies_ms.items() if seq in self.frames])
            return {"commands": len(self.latencies_ms), "frames": len(self.frames), "answered": int(lat.size),
                    "p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
                    "p99_ms": float(np.percentile(lat, 99)) if lat.size else None}


def probe_main(graph_path: str) -> int:
    """Read ``<seconds>`` lines on stdin, answer each with one JSON line (a window's figures)."""
    probe = Probe(graph_path)
    print("ready", flush=True)
    for line in sys.stdin:
        print(json.dumps(probe.window(float(line))), flush=True)
    probe.session.close()
    return 0


class LaptopProbe:
    """What plain subscribers on the laptop get per key in one window: messages, lost (``header.seq`` gaps), and
    their age on arrival (capture to laptop). Run in the laptop's namespace: see laptop_main."""

    def __init__(self, endpoint: str, keys: list[str]):
        from ...bus.pubsub import declare_subscriber
        from ...bus.stats import SequenceGaps
        from ..connect import client_settings, open_client_session

        self.session = open_client_session(client_settings(None, [endpoint], "monitor", MONITOR_PASSWORD))
        self.lock = threading.Lock()
        self.open = False
        self.gaps = SequenceGaps()
        self.seen: dict[str, dict[str, Any]] = {}
        self.subs = [declare_subscriber(self.session, key, self._on_sample) for key in keys]

    def _on_sample(self, sample: Any) -> None:
        from ...bus.pubsub import frame_bytes
        from ...bus.schemas import decode
        from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)

        now = time.time_ns()
        try:
            h = decode(frame_bytes(sample)).header
        except Exception:  # not a figure
            return
        key = str(sample.key_expr)
        with self.lock:
            missing = self.gaps.see((key, h.source), h.seq)  # followed between windows too
            if self.open:
                seen = self.seen.setdefault(key, {"received": 0, "lost": 0, "ages_ms": []})
                seen["received"] += 1
                seen["lost"] += max(missing, 0)
                seen["ages_ms"].append((now - h.stamp_ns) / 1e6)

    def window(self, seconds: float) -> dict[str, Any]:
        with self.lock:
            self.seen, self.open = {}, True
        time.sleep(seconds)
        with self.lock:
            self.open = False
            out = {}
            for key, seen in self.seen.items():
                ages = np.asarray(seen["ages_ms"])
                out[key] = {"received": seen["received"], "per_s": seen["received"] / seconds, "lost": seen["lost"],
                            "age_p50_ms": float(np.percentile(ages, 50)), "age_p99_ms": float(np.percentile(ages, 99))}
            return out


def laptop_main(endpoint: str, keys: list[str]) -> int:
    """Read ``<seconds>`` lines on stdin, answer each with one JSON line (a window's figures per key)."""
    probe = LaptopProbe(endpoint, keys)
    print("ready", flush=True)
    for line in sys.stdin:
        print(json.dumps(probe.window(float(line))), flush=True)
    probe.session.close()
    return 0


# --- the laptop ----------------------------------------------------------------------------------------------

def laptop_argv(case: str, endpoint: str, graph: Path, tmp: Path, seconds: float) -> list[str] | None:
    """The laptop's command of a case (None: no laptop)."""
    cli = [sys.executable, "-m", "followbus.tools.cli"]
    join = ["--connect", endpoint, "--user", "monitor", "--graph", str(graph)]
    if case == "monitor":
        return [*cli, "monitor", *join, "--web", "18080", "--seconds", f"{seconds:g}"]
    if case in ("record", "record-all"):
        extra = ["--raw-frames"] if case == "record-all" else []
        return [*cli, "record", *join, *extra, "-o", str(tmp / f"{case}.mcap"), "--duration", f"{seconds:g}"]
    return None


def recording_summary(path: Path) -> dict[str, Any]:
    """What a laptop's recording holds, from its own recording_stats: per key received, dropped, seq gaps."""
    from ...bus.recording import read_metadata

    stats = read_metadata(path).get("recording_stats", {})
    keys = json.loads(stats.get("keys", "{}"))
    return {"received": int(stats.get("received", 0)), "dropped": int(stats.get("dropped", 0)),
            "seq_gaps": int(stats.get("seq_gaps", 0)),
            "keys": {k: {f: v[f] for f in ("received", "dropped", "seq_gaps")} for k, v in keys.items()}}


@dataclass
class CaseRun:
    case: str
    robot: dict[str, Any]
    laptop: dict[str, Any] = field(default_factory=dict)
    rate_mbit: float = 0.0


class LinkBench:
    """The robot graph and its probe in namespace a, one laptop case at a time in namespace b."""

    def __init__(self, pair: NetnsPair, tmp: Path, port: int, detector: str, protect: bool = True,
                 log: Path | None = None, drop_wait_us: int | None = None, laptop_nice: int = LAPTOP_NICE,
                 large_rule: str = "block_first"):
        self.pair, self.tmp, self.log = pair, tmp, log
        self.laptop_nice = laptop_nice
        self.graph = write_robot_graph(tmp, port, pair.addresses[0], detector, protect=protect,
                                       drop_wait_us=drop_wait_us,
                                       old_large_rule_on=pair.links[0] if large_rule == "drop" else "")
        self.endpoint = f"tcp/{pair.addresses[0]}:{port}"
        # The namespaces are machines of their own: this shell's domain settings (domain, namespace, port) is not
        # theirs, and the probes read the graph file as written.
        env = {k: v for k, v in os.environ.items() if k not in DOMAIN_ENVS}
        self.env = dict(env, FOLLOWBUS_ZENOH_PASSWORD=MONITOR_PASSWORD, PYTHONUNBUFFERED="1")
        self.robot = subprocess.Popen(pair.argv(0, [sys.executable, "-m", "followbus.tools.cli", "launch",
                                                    str(self.graph), "--startup-timeout", "90"]),
                                      cwd=tmp, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        self.robot_lines: list[str] = []
        threading.Thread(target=lambda: self.robot_lines.extend(iter(self.robot.stdout.readline, "")),
                         daemon=True).start()
        self.probe: subprocess.Popen | None = None

    def start(self, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        wait_for_launch(self.robot, self.robot_lines, timeout_s)
        self.probe = subprocess.Popen(self.pair.argv(0, [sys.executable, "-m", "followbus.tools.bench.link",
                                                         "probe", str(self.graph)]),
                                      cwd=self.tmp, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                      env=self.env)
        if self.probe.stdout.readline().strip() != "ready":
            raise RuntimeError("the probe did not start")
        # Warm-up: the robot answers frames (models loaded, the target acquired) before any window counts.
        while not self.window(1.0)["answered"]:
            if time.monotonic() > deadline:
                raise RuntimeError("the robot graph never answered a frame: " + "".join(self.robot_lines[-10:]))

    def window(self, seconds: float) -> dict[str, Any]:
        assert self.probe is not None
        self.probe.stdin.write(f"{seconds}\n")
        self.probe.stdin.flush()
        return json.loads(self.probe.stdout.readline())

    def run_case(self, case: str, seconds: float, until_answered: bool = False) -> CaseRun:
        """One window of ``seconds`` with the case's laptop; ``until_answered``: 1 s windows until the robot
        answers a frame or ``seconds`` pass, then the laptop is stopped (a test's check, not a figure)."""
        if case in LAPTOP_KEYS:
            return self._probed_case(case, seconds)
        argv = laptop_argv(case, self.endpoint, self.graph, self.tmp, SETTLE_S + seconds + 1.0)
        laptop = None
        cpu0 = _children_cpu_s()
        if argv is not None:
            niced = ["nice", "-n", str(self.laptop_nice), *argv]
            laptop = subprocess.Popen(self.pair.argv(1, niced), cwd=self.tmp, env=self.env, stdin=subprocess.DEVNULL,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            output = _LineReader(laptop)
            # The window opens once the laptop has said it is there: on a loaded machine a niced laptop can take
            # longer than the settle time just to start, and would be stopped before it had recorded anything.
            output.first_line(LAPTOP_START_S)
            time.sleep(SETTLE_S)
        robot = self._until_answered(seconds) if until_answered else self.window(seconds)
        run = CaseRun(case, robot)
        if laptop is not None:
            if until_answered:
                laptop.send_signal(signal.SIGINT)  # a recorder finalises its file and prints its report
            out = output.finish()
            # On this one machine the laptop's CPU is the robot's too (a real laptop's is not): say how much.
            run.laptop = {"exit": laptop.returncode, "first_lines": out.splitlines()[:2],
                          "cpu_s": round(_children_cpu_s() - cpu0, 2)}
            mcap = self.tmp / f"{case}.mcap"
            if mcap.exists():
                run.laptop.update(recording_summary(mcap))
                mcap.unlink()
        return run

    def _probed_case(self, case: str, seconds: float) -> CaseRun:
        """The robot's window and the laptop probe's side by side, once the link has been full for a while."""
        keys = [f"{NAMESPACE}/{k}" for k in LAPTOP_KEYS[case]]
        argv = ["nice", "-n", str(self.laptop_nice), sys.executable, "-m", "followbus.tools.bench.link", "laptop",
                self.endpoint, *keys]
        laptop = subprocess.Popen(self.pair.argv(1, argv), cwd=self.tmp, env=self.env, stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
        try:
            if laptop.stdout.readline().strip() != "ready":
                raise RuntimeError("the laptop probe did not start")
            time.sleep(LINK_FILL_S)
            laptop.stdin.write(f"{seconds}\n")
            laptop.stdin.flush()
            robot = self.window(seconds)
            figures = json.loads(laptop.stdout.readline())
        finally:
            laptop.stdin.close()
            try:
                laptop.wait(20)
            except subprocess.TimeoutExpired:
                laptop.kill()
                laptop.wait()
        return CaseRun(case, robot, {"keys": figures})

    def _until_answered(self, seconds: float) -> dict[str, Any]:
        start = time.monotonic()
        robot = self.window(1.0)
        while not robot["answered"] and time.monotonic() < start + seconds:
            robot = self.window(1.0)
        # The laptop keeps recording for a few seconds in all: a robot that answers at once (a hub that drops
        # after 1 ms) would otherwise leave it one message per key, too few to count what the link lost.
        time.sleep(max(0.0, start + MIN_RECORDED_S - time.monotonic()))
        return robot

    def close(self) -> None:
        if self.log is not None:
            self.log.parent.mkdir(parents=True, exist_ok=True)
            self.log.write_text("".join(self.robot_lines))
        if self.probe is not None and self.probe.poll() is None:
            self.probe.stdin.close()  # its loop ends
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.probe.wait(10)
        interrupt_all((self.probe, self.robot))


def wait_for_launch(robot: subprocess.Popen, lines: list[str], timeout_s: float) -> None:
    """Until the launcher has said ``ready:`` (every node up); its last lines if it ended or took too long."""
    deadline = time.monotonic() + timeout_s
    while not any("ready:" in line for line in lines):
        if time.monotonic() > deadline or robot.poll() is not None:
            raise RuntimeError("the robot graph did not come up: " + "".join(lines[-10:]))
        time.sleep(0.2)


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)  # waited-for children: the laptop's processes
    return usage.ru_utime + usage.ru_stime


class _LineReader:
    """A child's output read as it comes (so its first line can be waited for), whole at the end."""

    def __init__(self, proc: subprocess.Popen):
        self.proc = proc
        self.lines: list[str] = []
        self._first = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            self._first.set()
        self._first.set()  # ended without a word

    def first_line(self, timeout_s: float) -> bool:
        return self._first.wait(timeout_s)

    def finish(self, timeout_s: float = 60.0) -> str:
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.send_signal(signal.SIGINT)
            self.proc.wait(timeout=30)
        self._thread.join(5.0)
        return "".join(self.lines)


# --- the command ---------------------------------------------------------------------------------------------

def run_link_bench(rate_mbit: float, seconds: float, rounds: int, cases: list[str], detector: str,
                   port: int = 21650, progress: Any = print, protect: bool = True,
                   log: Path | None = None, drop_wait_us: int | None = None,
                   laptop_nice: int = LAPTOP_NICE, large_rule: str = "block_first") -> list[CaseRun]:
    """Every case ``rounds`` times, alternated; the robot graph is launched once."""
    runs = []
    with tempfile.TemporaryDirectory(prefix="followbus-link-") as tmp, NetnsPair(rate_mbit=rate_mbit) as pair:
        bench = LinkBench(pair, Path(tmp), port, detector, protect=protect, log=log, drop_wait_us=drop_wait_us,
                          laptop_nice=laptop_nice, large_rule=large_rule)
        try:
            bench.start()
            for r in range(rounds):
                for case in cases:
                    runs.append(bench.run_case(case, seconds))
                    runs[-1].rate_mbit = rate_mbit
                    progress(f"{rate_mbit:g} Mbit/s round {r + 1}/{rounds} {case}: {_robot_line(runs[-1].robot)}"
                             f"{_laptop_line(runs[-1].laptop)}")
        finally:
            bench.close()
    return runs


def _laptop_line(laptop: dict[str, Any]) -> str:
    if "per_s" not in next(iter(laptop.get("keys", {}).values()), {}):
        return ""
    return "; laptop " + ", ".join(f"{key.rsplit('/', 1)[-1]} {k['per_s']:.1f}/s" for key, k in laptop["keys"].items())


def _robot_line(robot: dict[str, Any]) -> str:
    p50, p99 = robot["p50_ms"], robot["p99_ms"]
    figures = f"p50 {p50:.1f} ms p99 {p99:.1f} ms" if p50 is not None else "no command"
    return f"{figures}, answered {robot['answered']}/{robot['frames']} frames"


def table(runs: list[CaseRun]) -> str:
    """Markdown: one row per case and round (robot figures), then per recording its keys."""
    lines = ["| link Mbit/s | case | round | capture→command p50 ms | p99 ms | frames answered | laptop received | "
             "dropped | seq gaps | laptop CPU s |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    rounds: dict[tuple[float, str], int] = {}
    for run in runs:
        if run.case in LAPTOP_KEYS:
            continue  # laptop_table
        rounds[(run.rate_mbit, run.case)] = rounds.get((run.rate_mbit, run.case), 0) + 1
        r, lap = run.robot, run.laptop
        p50 = f"{r['p50_ms']:.1f}" if r["p50_ms"] is not None else "-"
        p99 = f"{r['p99_ms']:.1f}" if r["p99_ms"] is not None else "-"
        rec = (f"{lap['received']} | {lap['dropped']} | {lap['seq_gaps']}" if "received" in lap else "- | - | -")
        cpu = f"{lap['cpu_s']:.1f}" if "cpu_s" in lap else "-"
        lines.append(f"| {run.rate_mbit:g} | {run.case} | {rounds[(run.rate_mbit, run.case)]} | {p50} | {p99} | "
                     f"{r['answered']}/{r['frames']} | {rec} | {cpu} |")
    return "\n".join(lines)


def laptop_table(runs: list[CaseRun]) -> str:
    """Markdown: the watch and frames cases, one row per rate, case and round: the robot's figures beside what
    the laptop received a second per key (lost on the way; median age on arrival)."""
    shown = ("command", "track", "preview", "frame")
    lines = ["| link Mbit/s | case | round | robot p50 ms | robot p99 ms | frames answered | "
             + " | ".join(f"laptop {k}/s (lost, age p50 ms)" for k in shown) + " |",
             "|---:|---|---:|---:|---:|---:|" + "---:|" * len(shown)]
    rounds: dict[tuple[float, str], int] = {}
    for run in runs:
        if run.case not in LAPTOP_KEYS:
            continue
        rounds[(run.rate_mbit, run.case)] = rounds.get((run.rate_mbit, run.case), 0) + 1
        r, keys = run.robot, {k.rsplit("/", 1)[-1]: v for k, v in run.laptop.get("keys", {}).items()}
        cells = []
        for name in shown:
            k = keys.get(name)
            wanted = any(name == w.rsplit("/", 1)[-1] for w in LAPTOP_KEYS[run.case])
            cells.append("-" if not wanted else "0" if k is None else
                         f"{k['per_s']:.1f} ({k['lost']}, {k['age_p50_ms']:.0f})")
        p50 = f"{r['p50_ms']:.1f}" if r["p50_ms"] is not None else "-"
        p99 = f"{r['p99_ms']:.1f}" if r["p99_ms"] is not None else "-"
        lines.append(f"| {run.rate_mbit:g} | {run.case} | {rounds[(run.rate_mbit, run.case)]} | {p50} | {p99} | "
                     f"{r['answered']}/{r['frames']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def key_table(runs: list[CaseRun]) -> str:
    """The last recording of each recording case, per key."""
    last = {run.case: run for run in runs if "keys" in run.laptop and run.case not in LAPTOP_KEYS}
    lines = ["| recording | key | received | dropped | seq gaps (lost on the way) |", "|---|---|---:|---:|---:|"]
    for case, run in last.items():
        for key, s in sorted(run.laptop["keys"].items()):
            lines.append(f"| {case} | {key} | {s['received']} | {s['dropped']} | {s['seq_gaps']} |")
    return "\n".join(lines)


def _rates(text: str) -> list[float]:
    """``2,20,100`` -> [2.0, 20.0, 100.0]; [] when any is not a positive number."""
    try:
        rates = [float(r) for r in text.split(",")]
    except ValueError:
        return []
    return rates if all(r > 0 for r in rates) else []


def cmd_bench_link(args) -> int:
    reason = netns_unavailable()
    if reason:
        print(f"followbus: bench link needs two network namespaces: {reason}", file=sys.stderr)
        return 2
    cases = [c.strip() for c in args.cases.split(",")] if args.cases else list(CASES)
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        print(f"followbus: --cases: unknown {', '.join(unknown)} (of {', '.join(CASES)})", file=sys.stderr)
        return 2
    rates = _rates(str(args.rate_mbit))
    if not rates:
        print(f"followbus: --rate-mbit {args.rate_mbit!r}: one or more rates in Mbit/s, e.g. 2,20,100",
              file=sys.stderr)
        return 2
    with open("/proc/loadavg") as f:
        load = f.read().strip()
    print(f"bench link: {', '.join(f'{r:g}' for r in rates)} Mbit/s each way, {args.seconds:g} s windows, "
          f"{args.rounds} rounds of {', '.join(cases)}; detector {args.detector}; remote links "
          f"{'as before (BLOCK)' if args.unprotected else 'DROP (bus/netif.py)'}, large messages "
          f"{args.large_rule.upper()}; laptop at nice {args.laptop_nice}; load {load}", flush=True)
    runs = []
    for rate in rates:
        runs += run_link_bench(rate, args.seconds, args.rounds, cases, args.detector, args.port,
                               protect=not args.unprotected, log=Path(args.log), drop_wait_us=args.drop_wait_us,
                               laptop_nice=args.laptop_nice, large_rule=args.large_rule)
    with open("/proc/loadavg") as f:
        print(f"load at the end: {f.read().strip()}")
    for text in (table(runs), laptop_table(runs), key_table(runs)):
        if text.count("\n") > 1:
            print(text)
            print()
    if args.json:
        Path(args.json).write_text(json.dumps([vars(r) for r in runs], indent=1))
    return 0


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "probe":
    sys.exit(probe_main(sys.argv[2]))
if __name__ == "__main__" and len(sys.argv) >= 4 and sys.argv[1] == "laptop":
    sys.exit(laptop_main(sys.argv[2], sys.argv[3:]))
