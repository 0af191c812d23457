"""``followbus demo``: launch graph.yaml on a synthetic scene, show a live status line, and end with
a summary against the scene's exact ground truth (TSR@20px, CLE) and the end-to-end latency from
frame capture to motor command."""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from ..bus.graph import Graph
from ..bus.pubsub import Subscriber
from ..bus.session import open_session
from ..evaluation.metrics import evaluate_single_target
from ..msgs.perception import Detections, GroundTruth
from ..msgs.robot import MotorCommand
from ..msgs.tracking import Template, Track
from ..vision.detectors import resolve_detector_model
from .launch import Launcher, install_stop_signals

log = logging.getLogger("followbus.demo")


class DemoWatcher:
    """Collects what the demo shows: tracks, ground truth, templates, commands."""

    def __init__(self, graph: Graph):
        self.graph = graph
        self.lock = threading.Lock()
        self.tracks: dict[int, Track] = {}
        self.truth: dict[int, GroundTruth] = {}
        self.track_times: deque[float] = deque(maxlen=90)
        self.template: Template | None = None
        self.command: MotorCommand | None = None
        self.latencies_ms: list[float] = []
        self.infer_ms: list[float] = []  # the detector's time per frame: what decides the skipped frames
        self.backend = ""
        self.session = open_session(graph.zenoh)  # a peer like the nodes: it may start first
        key = graph.key
        self.subs = [
            Subscriber(self.session, key("prediction", "track"), self._on_track, schema=Track),
            Subscriber(self.session, key("capture", "ground_truth"), self._on_truth, schema=GroundTruth),
            Subscriber(self.session, key("template", "template"), self._on_template, schema=Template),
            Subscriber(self.session, key("motor", "command"), self._on_command, schema=MotorCommand),
            Subscriber(self.session, key("detection", "detections"), self._on_dets, schema=Detections),
        ]

    def _on_track(self, msg: Track) -> None:
        with self.lock:
            self.tracks[msg.header.frame_seq] = msg
            self.track_times.append(time.monotonic())

    def _on_truth(self, msg: GroundTruth) -> None:
        with self.lock:
            self.truth[msg.header.frame_seq] = msg

    def _on_template(self, msg: Template) -> None:
        with self.lock:
            self.template = msg

    def _on_dets(self, msg: Detections) -> None:
        self.backend = msg.backend
        with self.lock:
            self.infer_ms.append(msg.infer_ms)

    def _on_command(self, msg: MotorCommand) -> None:
        with self.lock:
            self.command = msg
            if msg.header.frame_seq >= 0 and msg.header.stamp_ns > 0:  # answers a track (not a watchdog stop)
                self.latencies_ms.append((msg.header.pub_ns - msg.header.stamp_ns) / 1e6)

    def status_line(self) -> str:
        with self.lock:
            times = list(self.track_times)
            fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 and times[-1] > times[0] else 0.0
            last = self.tracks[max(self.tracks)] if self.tracks else None
            eta = self.template.eta if self.template else 0.0
            cmd = self.command
        state = last.state if last else "waiting"
        cmd_text = (f"vx {cmd.vx_mps:+.2f} m/s wz {cmd.wz_radps:+.2f} rad/s ({cmd.reason})" if cmd else "no command")
        return f"{fps:5.1f} fps | {state:<13} | eta {eta:.4f} | {cmd_text} | {self.backend or '...'}"

    def summary(self) -> dict:
        with self.lock:
            processed = set(self.tracks)
            # Frames captured after the last one processed were still in the pipeline when the graph stopped:
            # neither processed nor skipped.
            last = max(processed, default=-1)
            frames = [i for i in sorted(self.truth) if i <= last]
            in_flight = len(self.truth) - len(frames)
            preds = [None if (t := self.tracks.get(i)) is None or t.box is None else tuple(t.box) for i in frames]
            gts = [None if self.truth[i].box is None else tuple(self.truth[i].box) for i in frames]
            lat = np.array(self.latencies_ms)
            infer = np.array(self.infer_ms)
            stamps = np.array(sorted(t.header.stamp_ns for t in self.truth.values()), dtype=np.float64)
        out: dict = {"frames": len(frames), "in_flight": in_flight, "tracked_frames": sum(p is not None for p in preds),
                     "processed_frames": sum(i in processed for i in frames)}
        if frames and any(g is not None for g in gts):
            metrics = evaluate_single_target(preds, gts)
            out.update(tsr=metrics.tsr, cle=metrics.cle, precision=metrics.precision, reid=metrics.reid_events)
        if lat.size:
            out.update(latency_p50_ms=float(np.percentile(lat, 50)), latency_p99_ms=float(np.percentile(lat, 99)))
        if infer.size and stamps.size > 1:
            out.update(infer_ms_mean=float(infer.mean()), infer_ms_p90=float(np.percentile(infer, 90)),
                       frame_period_ms=float(np.median(np.diff(stamps))) / 1e6)
        return out

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


DEMO_LOG_DIR = Path("state")
CHECKOUT = Path(__file__).resolve().parents[1]  # the repository (followbus is installed editable from it)


def default_graph_path(given: str) -> str:
    """The demo's graph: ``given`` when it exists; run from another directory, the checkout's graph.yaml (said in
    one line); else a UsageError saying what to do."""
    from .errors import UsageError

    if Path(given).exists() or given != "graph.yaml":
        return given  # a missing --graph FILE is the graph loader's one line
    shipped = CHECKOUT / "graph.yaml"
    if shipped.exists():
        print(f"no graph.yaml in {Path.cwd()}: running the checkout's {shipped}", flush=True)
        return str(shipped)
    raise UsageError("no graph.yaml here: run `followbus demo` in the followbus checkout, or give --graph FILE")
ERROR_LINES_SHOWN = 3


def run_log_path(directory: Path = DEMO_LOG_DIR) -> Path:
    """A log file of this run only (state/demo-YYYYmmdd-HHMMSS.log): one run's reasons are not buried in the
    previous runs' lines."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = directory / f"demo-{stamp}.log"
    n = 1
    while path.exists():  # two demos started in the same second
        n += 1
        path = directory / f"demo-{stamp}-{n}.log"
    return path


def last_error_lines(log_path: Path, count: int = ERROR_LINES_SHOWN) -> list[str]:
    """The last lines of a node log that say why something stopped (logged errors, exceptions)."""
    from .launch import ERROR_LINE_RE

    try:
        lines = log_path.read_text(errors="replace").splitlines()
    except OSError:
        return []
    hits: list[str] = []  # newest first, each once (a crash-looping node repeats the same error)
    for line in reversed(lines):
        text = line.split("] ", 1)[1] if line.startswith("[") and "] " in line else line
        if ERROR_LINE_RE.search(text.strip()) and line.strip() not in hits:
            hits.append(line.strip())
            if len(hits) == count:
                break
    return hits[::-1]


def print_summary(summary: dict) -> None:
    """The demo's closing lines: frames, TSR@20px against the scene's truth, re-ID events, latency, detector time."""
    in_flight = f" (and {summary['in_flight']} still in the pipeline at the stop)" if summary["in_flight"] else ""
    skipped = summary["frames"] - summary["processed_frames"] - summary["in_flight"]
    why = f" ({skipped} skipped by a detector that could not keep up)" if skipped > 0 else ""
    print(f"summary: {summary['frames']} frames captured{in_flight}, {summary['processed_frames']} processed end to "
          f"end{why}, {summary['tracked_frames']} with a target box")
    if "tsr" in summary:
        print(f"  TSR@20px {summary['tsr'] * 100:.1f} % (a skipped frame counts as a failure)   "
              f"CLE {summary['cle']:.1f} px   precision {summary['precision'] * 100:.1f} %")
        for event in summary["reid"]:
            lat = f"{event.latency_ms:.0f} ms" if event.latency_ms is not None else "not re-locked"
            print(f"  occlusion of {event.occluded_frames} frames: re-identified {lat} after reappearance")
    if "latency_p50_ms" in summary:
        print(f"  capture -> motor command latency: p50 {summary['latency_p50_ms']:.1f} ms, "
              f"p99 {summary['latency_p99_ms']:.1f} ms")
    if "infer_ms_mean" in summary:
        # Skipped frames come from here: the detector's frame time against the camera's period.
        print(f"  detector: {summary['infer_ms_mean']:.1f} ms a frame (p90 {summary['infer_ms_p90']:.1f}) "
              f"for a {summary['frame_period_ms']:.1f} ms frame period")


def demo_detector(graph: Graph) -> str | None:
    """What the graph's detection node will run, said before anything is launched. Its model was already checked by
    the graph's validation (DetectionParams.check: a missing or corrupt one is refused there)."""
    detection = graph.nodes.get("detection")
    params = detection.params if detection else {}
    backend = str(params.get("backend", "auto"))
    model = resolve_detector_model(backend, model_dir=params.get("model_dir") or None,
                                   model_file=params.get("model_file") or None,
                                   input_size=_size(params.get("input_size_px", 416)),
                                   input_shape=str(params.get("input_shape", "square")))
    if model is not None:
        return f"detector: backend {backend}, model {model}"
    if backend == "hog":
        return "detector: OpenCV HOG (chosen explicitly; far less accurate than YOLOX)"
    return None


def run_demo(graph: Graph, duration_s: float, log_path: Path | None, overrides: list[str] | None = None,
             detector: str | None = None) -> int:
    """Launch ``graph`` for ``duration_s`` and score it; ``detector`` is demo_detector's line."""
    if detector:
        print(detector, flush=True)
    log_path = log_path or run_log_path()
    log_path.parent.mkdir(parents=True, exist_ok=True)
    log_path.write_text("")  # this run's lines only
    print(f"launching {len(graph.nodes)} nodes for {duration_s:.0f} s (Ctrl-C to stop); node logs: {log_path}",
          flush=True)
    logging.getLogger("followbus.launch").setLevel(logging.WARNING)
    launcher = Launcher(graph, log_file=log_path, overrides=overrides, watch_outputs=True)
    install_stop_signals(launcher)
    watcher = DemoWatcher(graph)
    stop = threading.Event()

    def show() -> None:
        tty = sys.stdout.isatty()
        while not stop.wait(0.5):
            line = watcher.status_line()
            if tty:
                sys.stdout.write("\r\033[K" + line)
            elif int(time.monotonic() * 2) % 4 == 0:  # a line every 2 s when not a terminal
                sys.stdout.write(line + "\n")
            sys.stdout.flush()

    shower = threading.Thread(target=show, daemon=True)
    shower.start()
    try:
        status = launcher.run(duration_s)
    finally:
        stop.set()
        shower.join(1.0)
    summary = watcher.summary()
    watcher.close()
    print()
    if launcher.refusal:
        print(f"followbus demo: {launcher.refusal}", file=sys.stderr, flush=True)
        return 2
    print_summary(summary)
    problems = _cause_first(launcher, summary["frames"])
    if problems:
        # The reason is in the node log; say it here, where the user is looking.
        print(f"followbus demo: {'; '.join(problems)} (node logs: {log_path})", file=sys.stderr)
        for line in last_error_lines(log_path):
            print(f"  {line}", file=sys.stderr)
        sys.stderr.flush()
        return status or 1
    return status


def _cause_first(launcher: Launcher, frames: int) -> list[str]:
    """The run's problems, the cause first: a node that failed is why no frame came through and why the graph was
    not up (on a loaded machine both happen before the failing node's restarts run out), so it leads."""
    if frames or launcher.interrupted:
        return launcher.problems()
    consequences = ["0 frames captured"]
    if not launcher.ready_event.is_set():
        consequences.append(f"the graph was not up after {launcher.ran_s:.0f} s (start-up takes a few seconds)")
    return launcher.failures() + consequences + launcher.silences()


def _size(value: object) -> int:
    """input_size_px as the model's file name needs it (auto: the dynamic model, any size)."""
    return 416 if value == "auto" else int(value)  # type: ignore[call-overload]
