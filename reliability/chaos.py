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
* **on target**: over those seconds, at least 90 % of the followed tracks (frames with the target in view) have
  their box centre in the target's ground-truth box: a loop that recovers onto a bystander is not recovered;
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
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zenoh

from ..bus.children import die_with_parent
from ..bus.codec import peek
from ..bus.graph import Graph, load_graph
from ..bus.health import HealthWatcher
from ..bus.pubsub import Publisher, ShmPool, Subscriber, declare_subscriber, frame_bytes
from ..bus.schemas import Frame, Message, decode
from ..bus.session import open_session
from ..msgs.perception import GroundTruth
from ..msgs.robot import MotorCommand
from ..msgs.tracking import Track
from ..vision.detector_presets import apply_detector_preset
from .judging import (
    FOLLOW_REASONS,
    INJECTOR,
    MS,
    NS,
    ChaosError,
    ChaosOptions,
    CommandObs,
    Fault,
    FaultResult,
    Injection,
    Limits,
    TrackObs,
    TruthObs,
    check,
    first_follow_ns,
    hidden_ns,
    judge_load,
    judge_recovery,
    judge_safety,
    judge_watchdog,
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
        self.injected_frame_ns = 0  # when the newest frame the harness itself published arrived here
        self.watching_injected = False  # a flood is on: read every frame to see when its last one arrives
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
            self.tracks.append(TrackObs(time.time_ns(), h.frame_seq, h.stamp_ns, msg.state, h.source, h.pub_ns,
                                        _box(msg.box)))

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
            self.truth.append(TruthObs(time.time_ns(), msg.header.frame_seq, msg.header.stamp_ns, visible,
                                       _box(msg.box)))

    def _on_frame(self, sample: zenoh.Sample) -> None:
        # One recent camera frame every half second is all the injectors need, not 27 MB/s; only while a flood is
        # being delivered is every frame read (the flood is over once the bus has delivered its last frame).
        now = time.monotonic()
        watching = self.watching_injected
        if not watching and now - self._frame_copied < 0.5:
            return
        try:
            data = frame_bytes(sample)
            injected = watching and peek(data).header.source == INJECTOR
        except Exception:  # a lane frame overwritten meanwhile, a malformed one: the next one will do
            return
        if injected:
            self.injected_frame_ns = time.time_ns()
            return
        if now - self._frame_copied < 0.5:
            return
        self._frame_copied = now
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


def sleep_until(t_ns: int) -> None:
    time.sleep(max(0.0, (t_ns - time.time_ns()) / NS))


def wait_for(predicate: Callable[[], Any], timeout_s: float, interval_s: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value
        time.sleep(interval_s)


def start_burners(n: int) -> list[subprocess.Popen]:
    """``n`` processes spinning a CPU each (at the default priority), dying with this one."""
    return [subprocess.Popen([sys.executable, "-c", "while 1: pass"], preexec_fn=die_with_parent,
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL) for _ in range(n)]


def stop_burners(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


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
            if wait_for(self._following, self.options.settle_s, 0.1):
                # Strike where the scene shows the target for a while: a fault's recovery is then not mixed
                # up with the scene's own occlusion or loop (at most one scene loop of waiting).
                wait_for(lambda: self._following() and self._good_phase(), self.scene_frames / 30.0 + 1.0, 0.02)
                if wait_for(self._following, 2.0, 0.02):  # and still following: it may have stopped meanwhile
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
        pid = wait_for(lambda: self.graph.pid(name), 10.0)
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

        ok = wait_for(back, self.options.restart_timeout_s)
        h = self.health.snapshot()[node]
        end = h.since_ns if ok else time.time_ns()
        inj = Injection(start, end, back_s=(end - start) / NS if ok else None, expect_pause=node != "motor",
                        motor_down=(start, end) if node == "motor" else None)
        check(inj.checks, "restarted", ok,
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
        sleep_until(hold_end + 300 * MS)  # + in-flight messages
        if inj.after is not None:
            inj.after()
        t_end = time.time_ns()
        tracks, commands, truth = self.observer.window(inj.start_ns - NS, t_end)
        checks = dict(inj.checks)
        unsafe = self.observer.unsafe[unsafe_before:]
        judge_safety(checks, unsafe, self.observer.command_decode_errors - decode_before, len(commands))
        wd = watchdog_report(tracks, commands, inj.start_ns - NS, t_end - 300 * MS,
                             self.limits.watchdog_timeout_ms, self.watchdog_bound_ms, inj.motor_down)
        judge_watchdog(checks, wd, inj)
        hidden_s = hidden_ns(truth, inj.end_ns, t_r if t_r is not None else t_end) / NS
        recovery_s = (t_r - inj.end_ns) / NS if t_r is not None else None
        held, on_target = judge_recovery(checks, opts, recovery_s, hidden_s, tracks, truth, t_r)
        figures = judge_load(checks, opts, inj, commands, truth)
        up = self.graph.running and not self.graph.failed()
        if fault.name != "kill-recorder":
            check(checks, "graph up", up, "launcher running" if up else f"failed: {self.graph.failed()}")
        failures = [f"{name}: {detail}" for name, (passed, detail) in checks.items() if not passed]
        survived = not failures
        self._last_survived = survived and up
        return FaultResult(
            fault=fault.name, description=fault.description, survived=survived,
            checks={k: v[0] for k, v in checks.items()}, failures=failures, unsafe_commands=len(unsafe),
            commands=len(commands), watchdog_ms=wd.worst_ms, watchdog_bound_ms=self.watchdog_bound_ms,
            back_s=inj.back_s, recovery_s=recovery_s, recovery_bound_s=opts.recovery_bound_s, hidden_s=hidden_s,
            held=held, on_target=on_target, latency_p50_ms=figures.get("p50_ms"), latency_p99_ms=figures.get("p99_ms"),
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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _box(box: np.ndarray | None) -> tuple[float, float, float, float] | None:
    """A message's [x, y, w, h] as the observer keeps it."""
    if box is None:
        return None
    x, y, w, h = (float(v) for v in np.asarray(box).reshape(-1)[:4])
    return x, y, w, h
