"""The chaos bench (``followbus bench chaos``): the tracking graph under faults. Does the loop always recover?

The harness launches the tracking graph of graph.yaml (private loopback port and namespace; the demo
scene, looping, real time at 30 Hz; the real YOLOX-nano detector by default), optionally under a background
load of ``--burners N`` processes spinning a CPU each for the whole run, and tries one fault at a time: SIGKILL
of each node (the launcher restarts it), SIGSTOP of prediction for 2 s, a stretch of following under the
load, a slow (simulated) detector, and messages injected on the real bus from the harness's own Zenoh session (a track
stamped an hour ahead, a far-future frame_seq, a NaN measurement, malformed payloads, a flood of
frames). An observer on the same bus records every track, motor command and ground-truth message
with its receive time, and after each fault the harness checks:

* **safe**: no motor command with a non-finite field or a speed beyond the controller's limits (the
  graph's motor params over :class:`~followbus.control.follow.FollowParams` defaults);
* **watchdog**: whenever tracks stop for longer than the bound while the last one was followable
  (TRACKING, REACQUIRED, OCCLUDED), an all-zero command arrives within the bound of that last track;
* **resumed**: a command following the target (reason tracking/reacquired, i.e. a TRACKING or
  REACQUIRED track reached the motor) arrives within the recovery bound of the fault's end (node back
  up = its liveliness token reappeared, or injection over); time in which the scene itself hides the
  target (ground truth) is added to the bound;
* **held**: over the next seconds the latest track is TRACKING/REACQUIRED most of the time (time
  samples where the scene hides the target are not counted);
* fault-specific checks: the node really restarted, malformed messages were counted in
  ``decode_errors`` with no restart, p99 capture→command latency and the fraction of captured frames
  that produced a command under load.

Every figure comes with the machine's load: the 1-minute load average is sampled through the run and
printed with the summary (and each fault's result), since a bound that holds on a quiet machine may not.

If the loop did not recover, the next fault starts on a freshly launched graph, so one lock-up does
not spoil the others. Pure harness: nothing here changes the graph's code paths.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zenoh

from ..bus.children import die_with_parent
from ..bus.codec import pack
from ..bus.graph import Graph, load_graph
from ..bus.health import HealthWatcher
from ..bus.pubsub import Publisher, ShmPool, Subscriber, declare_subscriber, frame_bytes
from ..bus.schemas import (
    Detections,
    Frame,
    GroundTruth,
    Measurement,
    Message,
    MotorCommand,
    Tick,
    Track,
    decode,
    encode,
)
from ..bus.session import open_session
from ..vision.detector_presets import apply_detector_preset
from .judging import (
    FOLLOW_REASONS,
    FRAME_PERIOD_NS,
    INJECTOR,
    MS,
    NS,
    ChaosError,
    CommandObs,
    Limits,
    TrackObs,
    TruthObs,
    WatchdogReport,
    first_follow_ns,
    hidden_ns,
    latency_figures,
    tracking_coverage,
    watchdog_report,
)

log = logging.getLogger("followbus.chaos")

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- the observer


class Observer:
    """Everything the harness sees on the bus, with receive times (wall clock, ns)."""

    def __init__(self, session: zenoh.Session, graph: Graph, limits: Limits):
        self.limits = limits
        self.lock = threading.Lock()
        self.tracks: list[TrackObs] = []
        self.commands: list[CommandObs] = []
        self.truth: list[TruthObs] = []
        self.unsafe: list[tuple[CommandObs, list[str]]] = []
        self._frame: bytes | None = None
        self._frame_copied = 0.0
        quiet = logging.getLogger("followbus.chaos.observer")  # the harness's own malformed payloads
        quiet.setLevel(logging.ERROR)
        self._subs = [
            Subscriber(session, graph.key("prediction", "track"), self._on_track, schema=Track, logger=quiet),
            Subscriber(session, graph.key("motor", "command"), self._on_command, schema=MotorCommand, logger=quiet),
            Subscriber(session, graph.key("capture", "ground_truth"), self._on_truth, schema=GroundTruth,
                       logger=quiet),
        ]
        self._frame_sub = declare_subscriber(session, graph.key("capture", "frame"), self._on_frame)

    @property
    def command_decode_errors(self) -> int:
        return self._subs[1].stats.decode_errors

    def _on_track(self, msg: Message) -> None:
        assert isinstance(msg, Track)
        h = msg.header
        with self.lock:
            self.tracks.append(TrackObs(time.time_ns(), h.frame_seq, h.stamp_ns, msg.state, h.source, h.pub_ns))

    def _on_command(self, msg: Message) -> None:
        assert isinstance(msg, MotorCommand)
        h = msg.header
        cmd = CommandObs(time.time_ns(), h.frame_seq, h.stamp_ns, h.pub_ns, float(msg.vx_mps), float(msg.vy_mps),
                         float(msg.wz_radps), tuple(float(w) for w in np.asarray(msg.wheel_radps).reshape(-1)),
                         msg.range_m, msg.bearing_rad, msg.reason)
        why = self.limits.unsafe(cmd)
        with self.lock:
            self.commands.append(cmd)
            if why:
                self.unsafe.append((cmd, why))

    def _on_truth(self, msg: Message) -> None:
        assert isinstance(msg, GroundTruth)
        visible = bool(msg.available and msg.box is not None and msg.visible_fraction >= 0.3)
        with self.lock:
            self.truth.append(TruthObs(time.time_ns(), msg.header.frame_seq, msg.header.stamp_ns, visible))

    def _on_frame(self, sample: zenoh.Sample) -> None:
        # One recent frame is all the injectors need: copy one every half second, not 27 MB/s.
        now = time.monotonic()
        if now - self._frame_copied < 0.5:
            return
        self._frame_copied = now
        try:
            data = frame_bytes(sample)
        except Exception:  # a lane frame overwritten meanwhile: the next one will do
            return
        with self.lock:
            self._frame = data

    def latest_frame(self) -> Frame | None:
        with self.lock:
            data = self._frame
        if data is None:
            return None
        try:
            return decode(data, Frame)
        except Exception:
            return None

    def window(self, t0_ns: int, t1_ns: int) -> tuple[list[TrackObs], list[CommandObs], list[TruthObs]]:
        with self.lock:
            return ([t for t in self.tracks if t0_ns <= t.recv_ns <= t1_ns],
                    [c for c in self.commands if t0_ns <= c.recv_ns <= t1_ns],
                    [g for g in self.truth if t0_ns <= g.recv_ns <= t1_ns])

    def last_track(self) -> TrackObs | None:
        with self.lock:
            own = [t for t in self.tracks[-50:] if t.source != INJECTOR]
        return own[-1] if own else None

    def last_truth(self) -> TruthObs | None:
        with self.lock:
            return self.truth[-1] if self.truth else None

    def follow_times(self, since_ns: int) -> list[int]:
        """Receive times of the commands since ``since_ns`` that followed the target."""
        with self.lock:
            recent = self.commands[-200:]
        return [c.recv_ns for c in recent if c.recv_ns >= since_ns and c.reason in FOLLOW_REASONS and c.answers_track]

    def trim(self, before_ns: int) -> None:
        """Forget observations older than ``before_ns`` (long runs)."""
        with self.lock:
            self.tracks = [t for t in self.tracks if t.recv_ns >= before_ns]
            self.commands = [c for c in self.commands if c.recv_ns >= before_ns]
            self.truth = [g for g in self.truth if g.recv_ns >= before_ns]

    def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        with contextlib.suppress(Exception):
            self._frame_sub.undeclare()


# ----------------------------------------------------------------------------- the launched graph

def clear_phases(scene: str, clear_s: float, fps: float = 30.0) -> tuple[int, set[int]]:
    """(frames in the scene, the frame indices from which the target stays detectable for ``clear_s``
    without the scene looping). Capture publishes scene frame ``frame_seq % frames``. All indices when
    no stretch is that long."""
    from ..vision.detectors import SimulatedDetector
    from ..vision.scenes import make_scene

    sc = make_scene(scene, fps=fps)
    visible = [f.target_box is not None and f.target_visible_fraction >= SimulatedDetector.MIN_VISIBLE_FRACTION
               for f in sc.frames()]
    need = max(1, round(clear_s * fps))
    good = {i for i in range(len(visible) - need + 1) if all(visible[i:i + need])}
    return len(visible), good or set(range(len(visible)))


# ----------------------------------------------------------------------------- faults and results


@dataclass
class ChaosOptions:
    detector: str = "yolox416"  # yolox416 | simulated
    scene: str = "corridor-occlusion"
    burners: int = 0  # processes spinning a CPU each for the whole run (background load)
    load_s: float = 10.0  # the load fault and the detector delay: how long the measured stretch lasts
    recovery_bound_s: float = 2.0  # fault over (node back / injection done) -> following again
    hold_s: float = 3.0  # then: tracking most of this long
    hold_fraction: float = 0.5
    watchdog_bound_ms: float = 200.0  # the product's promise: zero command <= this after the last track
    load_p99_ms: float = 250.0
    load_processed: float = 0.5
    malformed_per_key: int = 10_000
    flood_frames: int = 300
    settle_s: float = 25.0  # before a fault: wait this long at most for the robot to follow (a scene loop)
    # and let a fresh graph run this long first: faults strike a loop in its steady state (a capture restart
    # from frame_seq 17 is not the one that happens on a robot after minutes)
    warmup_s: float = 8.0
    clear_s: float = 7.0  # a fault starts at a point of the scene with the target in view this long after it
    restart_timeout_s: float = 30.0
    record: bool = False
    port: int = 0
    namespace: str = ""  # default chaos<port>
    workdir: Path | None = None
    log_file: Path | None = None


@dataclass
class Injection:
    """What an injector did: when the fault started and ended, plus its own checks and notes."""

    start_ns: int
    end_ns: int
    back_s: float | None = None  # restarted node: kill -> liveliness back
    checks: dict[str, tuple[bool, str]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    load_window: tuple[int, int] | None = None
    injected_stamps: set[int] = field(default_factory=set)
    expect_pause: bool = False  # the fault stops the track stream (noted when no watchdog stop was seen)
    motor_down: tuple[int, int] | None = None  # the motor process itself was dead (kill -> back up)
    check_load_processed: bool = False
    after: Callable[[], None] | None = None  # checks that need the status messages after the fault


@dataclass
class Fault:
    name: str
    description: str
    inject: Callable[[ChaosRunner], Injection]
    variant: str = "base"  # which launch of the graph it needs
    needs_record: bool = False
    simulated_only: bool = False


@dataclass
class FaultResult:
    fault: str
    description: str
    survived: bool
    checks: dict[str, bool]
    failures: list[str]
    unsafe_commands: int
    commands: int
    watchdog_ms: float | None
    watchdog_bound_ms: float
    back_s: float | None
    recovery_s: float | None
    recovery_bound_s: float
    hidden_s: float
    held: float | None
    latency_p50_ms: float | None = None
    latency_p99_ms: float | None = None
    processed: float | None = None
    load1: float | None = None  # 1-minute load average when the fault's judgement ended
    relaunched: bool = False
    notes: list[str] = field(default_factory=list)

    def explain(self) -> str:
        lines = [f"{self.fault}: {'survived' if self.survived else 'NOT survived'}"]
        lines += [f"  - {f}" for f in self.failures]
        lines += [f"  . {n}" for n in self.notes]
        return "\n".join(lines)


def _check(checks: dict[str, tuple[bool, str]], name: str, ok: bool, detail: str) -> None:
    checks[name] = (bool(ok), detail)


def _sleep_until(t_ns: int) -> None:
    time.sleep(max(0.0, (t_ns - time.time_ns()) / NS))


def _wait(predicate: Callable[[], Any], timeout_s: float, interval_s: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value
        time.sleep(interval_s)


def _kill(node: str) -> Callable[[ChaosRunner], Injection]:
    def inject(run: ChaosRunner) -> Injection:
        return run.kill_and_wait(node)
    return inject


def _kill_capture(run: ChaosRunner) -> Injection:
    before = run.observer.last_truth()
    inj = run.kill_and_wait("capture")
    first = _wait(lambda: next((g for g in run.observer.window(inj.end_ns, time.time_ns())[2]), None), 5.0)
    restarted = first is not None and before is not None and first.frame_seq < before.frame_seq
    _check(inj.checks, "frame_seq restarted", restarted,
           f"capture's frame_seq went {before.frame_seq if before else '?'} -> "
           f"{first.frame_seq if first else 'nothing'} across the restart")
    return inj


def _stop_prediction(run: ChaosRunner) -> Injection:
    start = time.time_ns()
    run.stall("prediction", 2.0)
    return Injection(start, time.time_ns(), expect_pause=True, notes=["prediction SIGSTOPped for 2 s"])


def start_burners(n: int) -> list[subprocess.Popen]:
    """``n`` processes spinning a CPU each (at the default priority), dying with this one."""
    return [subprocess.Popen([sys.executable, "-c", "while 1: pass"], preexec_fn=die_with_parent,
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL) for _ in range(n)]


def stop_burners(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


def _load(run: ChaosRunner) -> Injection:
    # The run's background burners (--burners) are the load; this stretch measures following under it.
    start = time.time_ns()
    time.sleep(run.options.load_s)
    end = time.time_ns()
    return Injection(start, end, load_window=(start, end), check_load_processed=True,
                     notes=[f"{run.options.burners} background CPU burners on {os.cpu_count()} cores, "
                            f"load average {os.getloadavg()[0]:.1f}, {run.options.load_s:.0f} s measured"])


def _detector_delay(run: ChaosRunner) -> Injection:
    # The whole launch runs with the slow detector; the fault window is a stretch of it.
    start = time.time_ns()
    time.sleep(run.options.load_s)
    end = time.time_ns()
    inj = Injection(start, start, load_window=(start, end), notes=["detection takes >= 80 ms per frame"])
    return inj


def _future_stamp_track(run: ChaosRunner) -> Injection:
    last = run.observer.last_track()
    pub = run.publisher("prediction", "track")
    track = Track(state="TRACKING", box=np.array([280.0, 110.0, 80.0, 220.0]), filtered_box=None, measured=True)
    track.header.stamp_ns = time.time_ns() + 3600 * NS
    track.header.frame_seq = (last.frame_seq + 1) if last else 0
    start = time.time_ns()
    pub.put(track)
    inj = run.kill_and_wait("prediction", start_ns=start)
    inj.injected_stamps.add(track.header.stamp_ns)
    inj.notes.insert(0, "a TRACKING track stamped +1 h on the track key, then prediction SIGKILLed")
    return inj


def _future_seq(node: str, output: str) -> Callable[[ChaosRunner], Injection]:
    def inject(run: ChaosRunner) -> Injection:
        truth = run.observer.last_truth()
        seq = (truth.frame_seq if truth else 0) + 10**9
        if output == "frame":
            frame = run.observer.latest_frame()
            if frame is None:
                raise ChaosError("no frame seen on the bus to copy")
            msg: Message = Frame(width=frame.width, height=frame.height, encoding=frame.encoding,
                                 data=np.array(frame.data))
        else:
            msg = Detections(boxes=np.zeros((0, 5), np.float32), backend="chaos")
        msg.header.frame_seq = seq
        msg.header.stamp_ns = time.time_ns()
        start = time.time_ns()
        run.publisher(node, output).put(msg)
        # A far-future frame_seq can lie dormant in a synchroniser while frames keep coming, and bite at the
        # next hiccup longer than a sync timeout: so a 0.3 s camera stall follows, as cameras do stall.
        time.sleep(0.5)
        run.stall("capture", 0.3)
        return Injection(start, time.time_ns(),
                         notes=[f"one valid {msg.TYPE} with frame_seq {seq}, then capture stalled 0.3 s"])
    return inject


def _nan_measurement(run: ChaosRunner) -> Injection:
    last = run.observer.last_track()
    nan = np.full(4, np.nan)
    msg = Measurement(state="TRACKING", accepted=True, secure=True, box=nan, best_box=nan.copy(), source="detection",
                      m_fuse=1.0, s_color=1.0, s_geo=1.0, omega=0.5, c_t=1.0)
    msg.header.frame_seq = (last.frame_seq + 1) if last else 0
    msg.header.stamp_ns = (last.stamp_ns + FRAME_PERIOD_NS) if last else time.time_ns()
    start = time.time_ns()
    run.publisher("reid", "measurement").put(msg)
    inj = Injection(start, time.time_ns(),
                    notes=[f"an accepted TRACKING measurement with a NaN box for frame {msg.header.frame_seq}"])
    inj.injected_stamps.add(msg.header.stamp_ns)
    return inj


def malformed_payloads(schema: type[Message], n: int, rng: np.random.Generator) -> list[bytes]:
    """n undecodable payloads for a key carrying ``schema``, in turn: garbage bytes, a valid message of
    another type, a valid message cut short, and a well-formed map of the right type with wrong field types."""
    valid = encode(schema())
    other = encode(Tick(value=7) if schema is not Tick else Track())
    wrong_fields: dict[str, Any] = {"_t": schema.TYPE, "_v": 1, "header": "not a header"}
    wrong_fields.update({f.name: {"bad": 1} for f in dataclasses.fields(schema) if f.name != "header"})
    kinds = [lambda: rng.integers(0, 256, size=int(rng.integers(0, 200)), dtype=np.uint8).tobytes(),
             lambda: other,
             lambda: valid[: int(rng.integers(0, len(valid)))],
             lambda: pack(wrong_fields)]
    return [kinds[i % len(kinds)]() for i in range(n)]


def _malformed(run: ChaosRunner) -> Injection:
    graph = run.graph.graph
    n = run.options.malformed_per_key
    consumers: dict[str, list[str]] = {}
    for spec in graph.nodes.values():
        for inp in spec.inputs.values():
            consumers.setdefault(graph.key(inp.source_node, inp.source_output), []).append(spec.name)
    producers = {graph.key(n_, o): n_ for n_, s in graph.nodes.items() for o in s.outputs}
    before = run.statuses()
    ups = {name: h.ups for name, h in run.health.snapshot().items()}
    pids = {name: run.graph.pid(name) for name in graph.nodes}
    rng = np.random.default_rng(14)
    start = time.time_ns()
    for key in sorted(consumers):
        node = producers[key]
        cls = graph_output_schema(graph, node, key.rsplit("/", 1)[1])
        pub = run.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        try:
            for payload in malformed_payloads(cls, n, rng):
                pub.put(payload)
        finally:
            pub.undeclare()
    end = time.time_ns()
    inj = Injection(start, end, notes=[f"{n} malformed payloads on each of {len(consumers)} input keys"])

    def after() -> None:
        fresh = _wait(lambda: all(run.status_ns(name) > end + NS for ks in consumers.values() for name in ks), 6.0)
        now = run.statuses()
        short = []
        for key, names in sorted(consumers.items()):
            for name in names:
                b = before.get(name, {}).get(key, {}).get("decode_errors", 0)
                a = now.get(name, {}).get(key, {}).get("decode_errors", 0)
                if a - b < n:
                    short.append(f"{name} counted {a - b} on {key}")
        _check(inj.checks, "counted in decode_errors", bool(fresh) and not short,
               "every consumer counted every payload" if not short else "; ".join(short[:4]))
        same_ups = {name: h.ups for name, h in run.health.snapshot().items()}
        restarted = [name for name in graph.nodes
                     if same_ups.get(name) != ups.get(name) or run.graph.pid(name) != pids.get(name)]
        _check(inj.checks, "no node restarted", not restarted, ", ".join(restarted) or "all pids unchanged")

    inj.after = after
    return inj


def graph_output_schema(graph: Graph, node: str, output: str) -> type[Message]:
    from ..bus.node import load_node_class

    return load_node_class(graph.nodes[node].run).OUTPUTS[output]


def _flood(run: ChaosRunner) -> Injection:
    frame = run.observer.latest_frame()
    truth = run.observer.last_truth()
    if frame is None or truth is None:
        raise ChaosError("no frame seen on the bus to copy")
    pub = run.publisher("capture", "frame", congestion="block", shm=True)
    data = np.array(frame.data)
    start = time.time_ns()
    for i in range(run.options.flood_frames):
        msg = Frame(width=frame.width, height=frame.height, encoding=frame.encoding, data=data)
        msg.header.frame_seq = truth.frame_seq + 1 + i
        msg.header.stamp_ns = time.time_ns()
        pub.put(msg)
    end = time.time_ns()
    return Injection(start, end, notes=[f"{run.options.flood_frames} valid frames in {(end - start) / MS:.0f} ms, "
                                        f"frame_seq {truth.frame_seq + 1}..."])


def _kill_recorder(run: ChaosRunner) -> Injection:
    from ..bus.node import RECORDER_NAME

    pid = run.require_pid(RECORDER_NAME)
    start = time.time_ns()
    os.kill(pid, signal.SIGKILL)
    time.sleep(3.0)
    inj = Injection(start, time.time_ns(), notes=["recorder SIGKILLed; the loop must still follow 3 s later"])
    alive = run.graph.running and run.health.alive() >= set(run.graph.graph.nodes)
    _check(inj.checks, "graph kept running", alive,
           "launcher and every node up" if alive else f"launcher running={run.graph.running}, "
                                                      f"failed={run.graph.failed()}")
    path = run.graph.record_path
    try:
        result = run.graph.recover_recording() if path is not None else None
        ok = result is not None and result.messages > 0
        detail = f"{result.messages} messages recovered" if result is not None else "no file"
    except Exception as exc:  # a file the recover tool cannot read is the finding
        ok, detail = False, f"recover failed: {exc}"
    _check(inj.checks, "recording recoverable", ok, detail)
    return inj


def _faults() -> dict[str, Fault]:
    faults = [
        Fault("kill-capture", "SIGKILL capture; the launcher restarts it and frame_seq starts again at 0 "
                              "(capture-restart)", _kill_capture),
        *(Fault(f"kill-{n}", f"SIGKILL {n}; the launcher restarts it", _kill(n))
          for n in ("detection", "prediction", "reid", "template", "motor")),
        Fault("stop-prediction-2s", "SIGSTOP prediction for 2 s, then SIGCONT", _stop_prediction),
        Fault("load", "--load-seconds of following under the run's load (--burners background CPU burners): "
                      "p99 capture->command and frames answered", _load),
        Fault("detector-delay-80ms", "the simulated detector takes 80 ms per frame (sim_delay_ms: 80)",
              _detector_delay, variant="delay80", simulated_only=True),
        Fault("future-stamp-track", "a TRACKING track stamped one hour ahead on prediction/track, then SIGKILL "
                                    "prediction: the motor must still stop", _future_stamp_track),
        Fault("future-seq-frame", "one valid frame with frame_seq +10**9 on capture/frame, then a 0.3 s camera "
                                  "stall", _future_seq("capture", "frame")),
        Fault("future-seq-detections", "one valid Detections with frame_seq +10**9 on detection/detections, then "
                                       "a 0.3 s camera stall", _future_seq("detection", "detections")),
        Fault("nan-measurement", "an accepted TRACKING Measurement with NaN box and best_box on reid/measurement",
              _nan_measurement),
        Fault("malformed", "garbage, wrong-type, truncated and wrong-field payloads, --malformed-per-key on every "
                           "input key", _malformed),
        Fault("flood", "300 valid frames (plausible frame_seqs) as fast as the bus takes them on capture/frame",
              _flood),
        Fault("kill-recorder", "SIGKILL the recorder of --record: the graph keeps going, the file is recoverable",
              _kill_recorder, needs_record=True),
    ]
    return {f.name: f for f in faults}


FAULTS: dict[str, Fault] = _faults()
ALIASES = {"capture-restart": "kill-capture", "burners": "load", "burners-2": "load"}
CI_FAULTS = ("future-stamp-track", "future-seq-frame", "future-seq-detections", "nan-measurement", "kill-capture",
             "kill-reid", "malformed", "flood")


def resolve_faults(spec: str | None, *, record: bool, detector: str) -> list[Fault]:
    """Fault list from ``--faults`` (names, aliases, ``all``, ``ci``); raises ValueError naming an unknown one."""
    names: list[str] = []
    for item in (spec or "all").split(","):
        item = item.strip()
        if not item:
            continue
        if item == "all":
            names += [n for n, f in FAULTS.items() if (record or not f.needs_record)
                      and (detector == "simulated" or not f.simulated_only)]
        elif item == "ci":
            names += list(CI_FAULTS)
        elif ALIASES.get(item, item) in FAULTS:
            names.append(ALIASES.get(item, item))
        else:
            raise ValueError(f"unknown fault {item!r} (known: all, ci, {', '.join([*FAULTS, *ALIASES])})")
    out = list(dict.fromkeys(names))
    for name in out:
        if FAULTS[name].needs_record and not record:
            raise ValueError(f"fault {name!r} needs --record")
        if FAULTS[name].simulated_only and detector != "simulated":
            raise ValueError(f"fault {name!r} needs --detector simulated")
    # Faults needing another launch of the graph go after the others, the recorder's death last.
    order = {"base": 0, "delay80": 1}
    return sorted((FAULTS[n] for n in out), key=lambda f: (f.needs_record, order.get(f.variant, 2)))


# ----------------------------------------------------------------------------- the runner


class LaunchedGraph(Protocol):
    """One launch of a graph file, as the runner drives it (the command provides it: it owns the launcher)."""

    graph: Graph
    record_path: Path | None
    ready_at: float

    @property
    def running(self) -> bool: ...
    def start(self, timeout_s: float = 90.0) -> None: ...
    def pid(self, name: str) -> int | None: ...
    def failed(self) -> list[str]: ...
    def stop(self) -> None: ...
    def recover_recording(self) -> Any: ...


def scene_graph(*, scene: str, port: int, namespace: str, detector: str, sim_delay_ms: float = 0.0,
                resolution: tuple[int, int] | None = None, lane: bool | None = None) -> str:
    """graph.yaml of the repository on a private port and namespace, the scene looping in real time (the graph
    `followbus bench chaos` and `bench pipeline` launch)."""
    capture: dict[str, Any] = {"source": f"scene:{scene}", "pace": "realtime", "fps": 30.0, "loop": True}
    if resolution is not None:
        capture.update(width_px=resolution[0], height_px=resolution[1])
    detection = apply_detector_preset({}, "yolox" if detector == "yolox416" else detector)
    if sim_delay_ms:
        detection["sim_delay_ms"] = float(sim_delay_ms)
    graph = load_graph(REPO / "graph.yaml").override({"capture": capture, "detection": detection,
                                                      "template": {"state_file": ""}})  # the same start each launch
    graph = graph.with_namespace(namespace).with_port(port)
    return (graph if lane is None else graph.with_zenoh(shm_lane=lane)).to_yaml()


class ChaosRunner:
    """Launches the graph, runs faults one at a time, judges each. Use as a context manager."""

    def __init__(self, options: ChaosOptions, progress: Callable[[str], None] | None = None, *,
                 launch: Callable[[Path, str, Path, Path | None], LaunchedGraph]):
        self.options = options
        self._launch = launch  # the command's launcher of a graph file (tools/bench/chaos.py ChaosGraph)
        self.progress = progress or (lambda _line: None)
        self.port = options.port or _free_port()
        self.namespace = options.namespace or f"chaos{self.port}"
        self._tmp: tempfile.TemporaryDirectory | None = None
        self.workdir = options.workdir
        self.graph: LaunchedGraph | None = None
        self.session: zenoh.Session | None = None
        self.health: HealthWatcher | None = None
        self.observer: Observer | None = None
        self.limits: Limits | None = None
        self.stopped_pid: int | None = None
        self.scene_frames = 1
        self.good_phases: set[int] = set()
        self._publishers: dict[tuple[str, str, str, bool], Publisher] = {}
        self._last_survived = True
        self.launches = 0
        self._burners: list[subprocess.Popen] = []
        self.load_samples: list[float] = []  # 1-minute load average, once a second through the run
        self._sampling = threading.Event()

    # -- lifecycle
    def __enter__(self) -> ChaosRunner:
        if self.workdir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="followbus-chaos-")
            self.workdir = Path(self._tmp.name)
        self.workdir.mkdir(parents=True, exist_ok=True)
        try:
            # The scene first: an unknown scene name is a ValueError before anything is opened.
            self.scene_frames, self.good_phases = clear_phases(self.options.scene, self.options.clear_s)
            graph = load_graph(self._write_graph("base"))
            self.limits = Limits.from_graph(graph)
            self.session = open_session(graph.zenoh)  # the harness holds the port: it outlives every node
            self.health = HealthWatcher(self.session, self.namespace)
            self.observer = Observer(self.session, graph, self.limits)
            self._burners = start_burners(self.options.burners)
            threading.Thread(target=self._sample_load, name="chaos-load", daemon=True).start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _sample_load(self) -> None:
        while not self._sampling.wait(1.0):
            self.load_samples.append(os.getloadavg()[0])

    def close(self) -> None:
        self._sampling.set()
        stop_burners(self._burners)
        self._burners = []
        if self.stopped_pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.stopped_pid, signal.SIGCONT)
        if self.graph is not None:
            self.graph.stop()
            self.graph = None
        for pub in self._publishers.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
        self._publishers.clear()
        if self.observer is not None:
            self.observer.close()
        if self.health is not None:
            self.health.close()
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
            self.session = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    @property
    def watchdog_bound_ms(self) -> float:
        return self.options.watchdog_bound_ms

    def _write_graph(self, variant: str) -> Path:
        assert self.workdir is not None
        text = scene_graph(scene=self.options.scene, port=self.port, namespace=self.namespace,
                           detector=self.options.detector,
                           sim_delay_ms=80.0 if variant == "delay80" and self.options.detector == "simulated" else 0.0)
        path = self.workdir / f"graph-{variant}.yaml"
        path.write_text(text)
        return path

    def launch(self, variant: str) -> None:
        assert self.workdir is not None
        if self.graph is not None:
            self.graph.stop()
            self.graph = None
        path = self._write_graph(variant)
        record = self.workdir / f"record-{self.launches}.mcap" if self.options.record else None
        log_file = self.options.log_file or (self.workdir / "nodes.log")
        log_file.parent.mkdir(parents=True, exist_ok=True)
        self.graph = self._launch(path, variant, log_file, record)
        self.launches += 1
        self.graph.start()

    def ensure_following(self, variant: str) -> bool:
        """Make sure the robot follows the target on a graph of this variant; returns True if relaunched."""
        relaunched = False
        if self.graph is None or self.graph.variant != variant or not self.graph.running or not self._last_survived:
            self.progress(f"  launching the graph ({variant})")
            self.launch(variant)
            relaunched = True
        for attempt in range(2):
            if _wait(self._following, self.options.settle_s, 0.1):
                # Strike where the scene shows the target for a while: a fault's recovery is then not mixed
                # up with the scene's own occlusion or loop (at most one scene loop of waiting).
                _wait(lambda: self._following() and self._good_phase(), self.scene_frames / 30.0 + 1.0, 0.02)
                if _wait(self._following, 2.0, 0.02):  # and still following: it may have stopped meanwhile
                    return relaunched
            if attempt == 0:
                self.progress("  the robot does not follow the target: relaunching the graph")
                self.launch(variant)
                relaunched = True
        raise ChaosError(f"the robot never followed the target on a fresh graph ({variant}); "
                         f"node logs: {self.options.log_file or (self.workdir or Path('.')) / 'nodes.log'}")

    def _good_phase(self) -> bool:
        truth = self.observer.last_truth() if self.observer is not None else None
        return truth is not None and truth.frame_seq % self.scene_frames in self.good_phases

    def _following(self) -> bool:
        assert self.graph is not None and self.observer is not None and self.health is not None
        # Steadily: following commands all through the last second (>= 5: a slow detector answers ~12 frames
        # a second), the newest just now.
        now = time.time_ns()
        times = self.observer.follow_times(now - NS)
        nodes = set(self.graph.graph.nodes)
        warm = time.monotonic() - self.graph.ready_at >= self.options.warmup_s
        return (self.graph.running and warm and len(times) >= 5 and now - max(times) < 300 * MS
                and self.health.alive() >= nodes and all(self.graph.pid(n) for n in nodes))

    # -- helpers for injectors
    def require_pid(self, name: str) -> int:
        assert self.graph is not None
        pid = _wait(lambda: self.graph.pid(name), 10.0)
        if not pid:
            raise ChaosError(f"no running process for {name}")
        return int(pid)

    def publisher(self, node: str, output: str, congestion: str = "block", shm: bool = False) -> Publisher:
        assert self.session is not None and self.graph is not None
        key = (node, output, congestion, shm)
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = Publisher(self.session, self.graph.graph.key(node, output), INJECTOR,
                                                    congestion=congestion, shm=ShmPool() if shm else None)
        return pub

    def statuses(self) -> dict[str, dict[str, dict[str, Any]]]:
        assert self.health is not None
        return {n: dict(h.status.topics) for n, h in self.health.snapshot().items() if h.status is not None}

    def status_ns(self, name: str) -> int:
        assert self.health is not None
        h = self.health.snapshot().get(name)
        return h.status_ns if h is not None else 0

    def stall(self, node: str, seconds: float) -> None:
        """SIGSTOP a node for ``seconds``, then SIGCONT (also on an interrupt)."""
        pid = self.require_pid(node)
        os.kill(pid, signal.SIGSTOP)
        self.stopped_pid = pid
        try:
            time.sleep(seconds)
        finally:
            os.kill(pid, signal.SIGCONT)
            self.stopped_pid = None

    def kill_and_wait(self, node: str, start_ns: int | None = None) -> Injection:
        """SIGKILL a node and wait until the launcher has it back (new pid, liveliness token back)."""
        assert self.graph is not None and self.health is not None
        pid = self.require_pid(node)
        ups = self.health.snapshot()[node].ups
        start = start_ns or time.time_ns()
        os.kill(pid, signal.SIGKILL)

        def back() -> bool:
            h = self.health.snapshot().get(node)
            new = self.graph.pid(node)
            return h is not None and h.alive and h.ups > ups and new is not None and new != pid

        ok = _wait(back, self.options.restart_timeout_s)
        h = self.health.snapshot()[node]
        end = h.since_ns if ok else time.time_ns()
        inj = Injection(start, end, back_s=(end - start) / NS if ok else None, expect_pause=node != "motor",
                        motor_down=(start, end) if node == "motor" else None)
        _check(inj.checks, "restarted", ok,
               f"{node} back after {(end - start) / NS:.1f} s (pid {pid} -> {self.graph.pid(node)})" if ok
               else f"{node} not back within {self.options.restart_timeout_s:.0f} s")
        return inj

    # -- one fault
    def run(self, fault: Fault) -> FaultResult:
        """Try one fault and judge it; a fault the harness could not even set up is a failed result."""
        try:
            return self._run(fault)
        except ChaosError as exc:
            self._last_survived = False  # start the next fault on a fresh graph
            # A fault that comes with its own launch (the slow detector) is there from the start: a graph that
            # never follows with it did not survive it. Otherwise the harness could not set the fault up.
            what = "resumed" if fault.variant != "base" else "set-up"
            return FaultResult(
                fault=fault.name, description=fault.description, survived=False, checks={what: False},
                failures=[f"{what}: {exc}"], unsafe_commands=0, commands=0, watchdog_ms=None,
                watchdog_bound_ms=self.watchdog_bound_ms, back_s=None, recovery_s=None,
                recovery_bound_s=self.options.recovery_bound_s, hidden_s=0.0, held=None)

    def _run(self, fault: Fault) -> FaultResult:
        assert self.observer is not None and self.limits is not None
        opts = self.options
        relaunched = self.ensure_following(fault.variant)
        assert self.graph is not None
        self.observer.trim(time.time_ns() - 60 * NS)
        unsafe_before = len(self.observer.unsafe)
        decode_before = self.observer.command_decode_errors
        inj = fault.inject(self)
        t_r = self._wait_resumed(inj)
        hold_end = (t_r if t_r is not None else time.time_ns()) + int(opts.hold_s * NS)
        if inj.load_window is not None:
            hold_end = max(hold_end, inj.load_window[1])
        _sleep_until(hold_end + 300 * MS)  # + in-flight messages
        if inj.after is not None:
            inj.after()
        t_end = time.time_ns()
        tracks, commands, truth = self.observer.window(inj.start_ns - NS, t_end)
        checks = dict(inj.checks)
        unsafe = self.observer.unsafe[unsafe_before:]
        _judge_safety(checks, unsafe, self.observer.command_decode_errors - decode_before, len(commands))
        wd = watchdog_report(tracks, commands, inj.start_ns - NS, t_end - 300 * MS,
                             self.limits.watchdog_timeout_ms, self.watchdog_bound_ms, inj.motor_down)
        _judge_watchdog(checks, wd, inj)
        hidden_s = hidden_ns(truth, inj.end_ns, t_r if t_r is not None else t_end) / NS
        recovery_s = (t_r - inj.end_ns) / NS if t_r is not None else None
        held = _judge_recovery(checks, opts, recovery_s, hidden_s, tracks, truth, t_r)
        figures = _judge_load(checks, opts, inj, commands, truth)
        up = self.graph.running and not self.graph.failed()
        if fault.name != "kill-recorder":
            _check(checks, "graph up", up, "launcher running" if up else f"failed: {self.graph.failed()}")
        failures = [f"{name}: {detail}" for name, (passed, detail) in checks.items() if not passed]
        survived = not failures
        self._last_survived = survived and up
        return FaultResult(
            fault=fault.name, description=fault.description, survived=survived,
            checks={k: v[0] for k, v in checks.items()}, failures=failures, unsafe_commands=len(unsafe),
            commands=len(commands), watchdog_ms=wd.worst_ms, watchdog_bound_ms=self.watchdog_bound_ms,
            back_s=inj.back_s, recovery_s=recovery_s, recovery_bound_s=opts.recovery_bound_s, hidden_s=hidden_s,
            held=held, latency_p50_ms=figures.get("p50_ms"), latency_p99_ms=figures.get("p99_ms"),
            processed=figures.get("processed"), load1=os.getloadavg()[0], relaunched=relaunched,
            notes=inj.notes + [f"{name}: {detail}" for name, (passed, detail) in checks.items() if passed],
        )

    def _wait_resumed(self, inj: Injection) -> int | None:
        """When the robot follows again after the fault (None: not within the recovery bound plus the time the
        scene itself hid the target)."""
        assert self.observer is not None
        bound_ns = int(self.options.recovery_bound_s * NS)
        while True:
            now = time.time_ns()
            t_r = first_follow_ns(self.observer.window(inj.end_ns, now)[1], inj.end_ns, inj.injected_stamps)
            hidden = hidden_ns(self.observer.window(inj.end_ns, now)[2], inj.end_ns, now)
            if t_r is not None or now > inj.end_ns + bound_ns + hidden:
                return t_r
            time.sleep(0.05)


def _judge_safety(checks: dict[str, tuple[bool, str]], unsafe: list[Any], undecodable: int, commands: int) -> None:
    _check(checks, "safe", not unsafe and not undecodable,
           f"{len(unsafe)} unsafe of {commands} commands"
           + (f" (first: {unsafe[0][1]})" if unsafe else "")
           + (f", {undecodable} undecodable" if undecodable else ""))


def _judge_watchdog(checks: dict[str, tuple[bool, str]], wd: WatchdogReport, inj: Injection) -> None:
    if wd.violations:
        more = f" (+{len(wd.violations) - 3} more)" if len(wd.violations) > 3 else ""
        detail = "; ".join(wd.violations[:3]) + more
    else:
        detail = f"worst stop {wd.worst_ms:.0f} ms" if wd.stops_ms else "tracks never paused while the robot moved"
    _check(checks, "watchdog", not wd.violations, detail)
    if inj.expect_pause and not wd.stops_ms:
        inj.notes.append("the fault did not pause the tracks while the robot moved (nothing for the watchdog)")


def _judge_recovery(checks: dict[str, tuple[bool, str]], opts: ChaosOptions, recovery_s: float | None,
                    hidden_s: float, tracks: list[TrackObs], truth: list[TruthObs], t_r: int | None) -> float | None:
    """resumed (within the bound plus the hidden time) and held (tracking most of the next seconds)."""
    ok = recovery_s is not None and recovery_s <= opts.recovery_bound_s + hidden_s
    _check(checks, "resumed", ok,
           f"following again {recovery_s:.2f} s after the fault ended" if recovery_s is not None
           else f"not following {opts.recovery_bound_s + hidden_s:.1f} s after the fault ended")
    if t_r is None:
        return None
    held = tracking_coverage(tracks, truth, t_r, t_r + int(opts.hold_s * NS))
    _check(checks, "held", held is None or held >= opts.hold_fraction,
           f"tracking {100 * held:.0f} % of the next {opts.hold_s:.0f} s" if held is not None
           else "the scene hid the target all along")
    return held


def _judge_load(checks: dict[str, tuple[bool, str]], opts: ChaosOptions, inj: Injection,
                commands: list[CommandObs], truth: list[TruthObs]) -> dict[str, Any]:
    """Under load: p99 capture->command latency, and the fraction of frames that produced a command."""
    if inj.load_window is None:
        return {}
    figures = latency_figures(commands, truth, *inj.load_window)
    p99 = figures["p99_ms"]
    _check(checks, "latency", p99 is not None and p99 <= opts.load_p99_ms,
           f"p99 capture->command {p99:.0f} ms" if p99 is not None else "no command under load")
    if inj.check_load_processed:
        processed = figures["processed"]
        _check(checks, "processed", processed is not None and processed >= opts.load_processed,
               f"{100 * (processed or 0):.0f} % of {figures['frames']} frames produced a command")
    return figures


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ----------------------------------------------------------------------------- the summary

def fmt(value: float | None, spec: str, none: str = "—") -> str:
    return none if value is None else format(value, spec)


def _worst(results: Sequence[FaultResult], attr: str, pick: Callable[[list[Any]], Any] = max) -> Any:
    """``pick`` (max, min, median) of a figure over the results that have it; None when none has."""
    values = [getattr(r, attr) for r in results if getattr(r, attr) is not None]
    return pick(values) if values else None


def summarise(results: Sequence[FaultResult]) -> list[dict[str, Any]]:
    """One row per fault over repeats: tried, survived, worst figures."""
    rows: list[dict[str, Any]] = []
    for name in dict.fromkeys(r.fault for r in results):
        rs = [r for r in results if r.fault == name]
        rows.append({
            "fault": name, "tried": len(rs), "survived": sum(r.survived for r in rs),
            "unsafe": sum(r.unsafe_commands for r in rs), "watchdog_worst_ms": _worst(rs, "watchdog_ms"),
            "back_max_s": _worst(rs, "back_s"), "recovery_median_s": _worst(rs, "recovery_s", statistics.median),
            "recovery_max_s": _worst(rs, "recovery_s"), "not_resumed": sum(r.recovery_s is None for r in rs),
            "held_min": _worst(rs, "held", min), "p50_ms": _worst(rs, "latency_p50_ms"),
            "p99_ms": _worst(rs, "latency_p99_ms"), "processed_min": _worst(rs, "processed", min),
            "load1_max": _worst(rs, "load1"),
            "failures": sorted({f.split(":", 1)[0] for r in rs for f in r.failures}),
        })
    return rows


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    lines = ["| fault | survived / tried | unsafe cmds | watchdog stop ms (worst) | node back s | "
             "recovery s (median / max) | tracking held (min) | p50 / p99 ms | processed | load (max) | "
             "failed checks |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        rec = (f"{fmt(r['recovery_median_s'], '.2f')} / {fmt(r['recovery_max_s'], '.2f')}"
               + (f" ({r['not_resumed']} never)" if r["not_resumed"] else ""))
        lat = "—" if r["p99_ms"] is None else f"{fmt(r['p50_ms'], '.0f')} / {fmt(r['p99_ms'], '.0f')}"
        lines.append(f"| {r['fault']} | {r['survived']} / {r['tried']} | {r['unsafe']} | "
                     f"{fmt(r['watchdog_worst_ms'], '.0f')} | {fmt(r['back_max_s'], '.1f')} | {rec} | "
                     f"{fmt(None if r['held_min'] is None else 100 * r['held_min'], '.0f')}"
                     f"{'' if r['held_min'] is None else ' %'} | {lat} | "
                     f"{fmt(None if r['processed_min'] is None else 100 * r['processed_min'], '.0f')}"
                     f"{'' if r['processed_min'] is None else ' %'} | {fmt(r['load1_max'], '.1f')} | "
                     f"{', '.join(r['failures']) or '—'} |")
    return "\n".join(lines)


def headline(results: Sequence[FaultResult], load_samples: Sequence[float], options: ChaosOptions) -> dict[str, Any]:
    """The figures a reader compares across runs and machines: load, survival, unsafe commands, the worst stop,
    following latency and frames answered under load (the load fault's)."""
    return {
        "detector": options.detector, "burners": options.burners, "cpu_count": os.cpu_count(),
        "load1_mean": statistics.fmean(load_samples) if load_samples else None,
        "load1_max": max(load_samples) if load_samples else None,
        "loadavg_end": Path("/proc/loadavg").read_text().strip() if Path("/proc/loadavg").exists() else None,
        "runs": len(results), "survived": sum(r.survived for r in results),
        "unsafe_commands": sum(r.unsafe_commands for r in results),
        "commands": sum(r.commands for r in results),
        "stop_max_ms": _worst(results, "watchdog_ms"), "stop_bound_ms": options.watchdog_bound_ms,
        "following_p99_ms": _worst(results, "latency_p99_ms"), "p99_bound_ms": options.load_p99_ms,
        "frames_answered_min": _worst(results, "processed", min),
    }


def format_headline(head: dict[str, Any], launches: int, elapsed_s: float) -> str:
    answered = head["frames_answered_min"]
    return "\n".join([
        f"load: {head['burners']} background burners on {head['cpu_count']} cores; 1-min load average "
        f"{fmt(head['load1_mean'], '.1f')} mean, {fmt(head['load1_max'], '.1f')} max; "
        f"/proc/loadavg at the end: {head['loadavg_end']}",
        f"survived: {head['survived']} of {head['runs']} fault runs ({head['detector']} detector); "
        f"unsafe commands: {head['unsafe_commands']} of {head['commands']}",
        f"stop latency max: {fmt(head['stop_max_ms'], '.0f')} ms (bound {head['stop_bound_ms']:.0f}); "
        f"following p99: {fmt(head['following_p99_ms'], '.0f')} ms (bound {head['p99_bound_ms']:.0f}); "
        f"frames answered: {fmt(None if answered is None else 100 * answered, '.0f')} %",
        f"{launches} launch{'es' if launches != 1 else ''} of the graph; {elapsed_s:.0f} s",
    ])
