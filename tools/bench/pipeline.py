"""``followbus bench pipeline``: end-to-end latency through the launched graph at 30 Hz.

Every message header carries ``stamp_ns`` (the capture stamp of its frame) and ``pub_ns`` (when it was
published). Per frame_seq the edges are: capture→detection, detection→prediction prior, prior→reid
measurement, measurement→prediction track, track→motor command (differences of pub_ns), and the total
capture stamp→command. CPU per node comes from /proc/<pid>/stat (pids from the NodeStatus messages);
dropped frames = frames published by capture that never produced a track.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("followbus.bench")

REPO = Path(__file__).resolve().parents[2]
STAGES = [("capture", "frame"), ("detection", "detections"), ("prediction", "prior"), ("reid", "measurement"),
          ("prediction", "track"), ("motor", "command")]
EDGES = ["capture→detection", "detection→prior", "prior→measurement", "measurement→track", "track→command"]


def cpu_ticks(pid: int) -> int | None:
    """Clock ticks of CPU (user and system) ``pid`` has used; None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])  # utime + stime (fields 14, 15 of stat)
    except (OSError, IndexError, ValueError):
        return None


def _model_present(detector: str) -> bool:
    """Whether the detector's model file (if it has one) is on the model search path."""
    from ...evaluation.runner import detection_params
    from ...vision.detectors import DetectorUnavailable, resolve_detector_model

    p = detection_params(detector)
    try:
        resolve_detector_model(str(p.get("backend", "auto")), model_dir=p.get("model_dir") or None,
                               model_file=p.get("model_file") or None, input_size=int(p.get("input_size_px", 416)),
                               input_shape=str(p.get("input_shape", "square")))
    except DetectorUnavailable:
        return False
    return True


class LaunchedPipeline:
    """graph.yaml launched on a looping scene on a private port, with a subscriber to every stage's headers:
    ``measure(seconds)`` gives the figures of that stretch (latency per edge, frames answered, CPU per node).
    Use as a context manager; ``pids`` maps each node to its process (from its status messages)."""

    def __init__(self, *, detector: str, scene: str, resolution: tuple[int, int], lane: bool, port: int = 0,
                 namespace: str = "", overrides: list[str] | None = None) -> None:
        self.overrides = list(overrides or [])
        if not port:
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
        self.detector, self.scene, self.resolution, self.lane = detector, scene, resolution, lane
        self.port, self.namespace = port, namespace or f"bench{port}"
        self.pids: dict[str, int] = {}
        self._pub: dict[tuple[str, str], dict[int, tuple[int, int]]] = {st: {} for st in STAGES}
        self._lock = threading.Lock()
        self._recording = threading.Event()
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> LaunchedPipeline:
        try:
            self._start()
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stack.close()

    def _start(self) -> None:
        from ...bus.graph import apply_overrides, load_graph
        from ...bus.session import open_session
        from ...reliability.chaos import scene_graph
        from ..launch import Launcher

        tmp = self._stack.enter_context(tempfile.TemporaryDirectory(prefix="followbus-bench-"))
        path = Path(tmp) / "graph.yaml"
        path.write_text(scene_graph(scene=self.scene, port=self.port, namespace=self.namespace,
                                    detector=self.detector, resolution=self.resolution, lane=self.lane))
        graph = load_graph(path)
        apply_overrides(graph, self.overrides)
        session = open_session(graph.zenoh)
        self._stack.callback(session.close)
        self._subscribe(session, graph)
        logging.getLogger("followbus.launch").setLevel(logging.WARNING)  # the bench's output is its figures
        launcher = Launcher(graph, quiet=True, startup_timeout_s=60.0, overrides=self.overrides)
        ready = threading.Event()
        runner = threading.Thread(target=launcher.run, kwargs={"duration_s": 10 ** 6, "on_ready": ready.set},
                                  daemon=True)
        runner.start()
        self._stack.callback(runner.join, 30)
        self._stack.callback(launcher.request_stop)
        if not ready.wait(90):
            raise RuntimeError("the graph did not come up")
        time.sleep(4.0)  # warm-up: model load, first frames
        deadline = time.monotonic() + 30.0  # every node's pid (from its status, once a second) before measuring
        while set(graph.nodes) - set(self.pids) and time.monotonic() < deadline:
            time.sleep(0.1)

    def _subscribe(self, session: Any, graph: Any) -> None:
        from ...bus.pubsub import declare_subscriber, frame_bytes
        from ...bus.schemas import Frame, NodeStatus, decode
        from ...msgs.perception import Detections
        from ...msgs.robot import MotorCommand
        from ...msgs.tracking import Measurement, Prior, Track

        schemas = {("capture", "frame"): Frame, ("detection", "detections"): Detections,
                   ("prediction", "prior"): Prior, ("reid", "measurement"): Measurement,
                   ("prediction", "track"): Track, ("motor", "command"): MotorCommand}

        def header_cb(stage: tuple[str, str]):
            def cb(sample) -> None:
                if not self._recording.is_set():
                    return
                try:
                    msg = decode(frame_bytes(sample), schemas[stage])
                except Exception:  # a malformed sample is not a latency figure
                    return
                h = msg.header
                if h.frame_seq >= 0:
                    with self._lock:
                        self._pub[stage].setdefault(h.frame_seq, (h.stamp_ns, h.pub_ns))
            return cb

        def on_status(sample) -> None:
            try:
                st = decode(frame_bytes(sample), NodeStatus)
            except Exception:
                return
            with self._lock:
                self.pids[st.node] = st.pid

        for st in STAGES:
            # Frames on the lane's side key when the lane is on: a subscriber of the real key would make capture
            # send every frame inline as well (bus/shmlane.py) and the figures would not be the lane's.
            sub = declare_subscriber(session, graph.key(*st), header_cb(st), lane=graph.zenoh.shm_lane)
            self._stack.callback(sub.undeclare)
        sub = declare_subscriber(session, f"{self.namespace}/@status/*", on_status)
        self._stack.callback(sub.undeclare)

    def measure(self, seconds: float) -> dict[str, Any]:
        """The figures of the next ``seconds`` (every stage's headers of that stretch only)."""
        with self._lock:
            for seen in self._pub.values():
                seen.clear()
            cpu0 = {n: cpu_ticks(p) for n, p in self.pids.items()}
        t0 = time.monotonic()
        self._recording.set()
        time.sleep(seconds)
        self._recording.clear()
        wall = time.monotonic() - t0
        with self._lock:
            cpu1 = {n: cpu_ticks(p) for n, p in self.pids.items()}
            pub = {st: dict(seen) for st, seen in self._pub.items()}
        result = _figures(pub, _cpu_percent(cpu0, cpu1, wall), wall)
        result.update(detector=self.detector, scene=self.scene, resolution="x".join(map(str, self.resolution)),
                      lane="on" if self.lane else "off")
        return result


def pipeline_detector(detector: str, command: str) -> str:
    """``detector``, or hog (said in one line) when its model is not on the model search path."""
    if _model_present(detector):
        return detector
    print(f"bench {command}: YOLOX model not found; using hog (figures are not comparable)", flush=True)
    return "hog"


def run_bench_pipeline(args) -> int:
    from ...bus.graph import GraphError

    detector = pipeline_detector(args.detector, "pipeline")
    try:
        with LaunchedPipeline(detector=detector, scene=args.scene, resolution=args.resolution,
                              lane=args.lane == "on", port=args.port, namespace=args.namespace,
                              overrides=getattr(args, "overrides", [])) as pipeline:
            result = pipeline.measure(args.duration)
    except GraphError as exc:
        print(f"followbus bench pipeline: {exc}", file=sys.stderr, flush=True)
        return 2
    except RuntimeError as exc:
        print(f"bench pipeline: {exc}", flush=True)
        return 1
    _print_figures(result)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, ensure_ascii=False))
    return 0


def _cpu_percent(cpu0: dict[str, int | None], cpu1: dict[str, int | None], wall: float) -> dict[str, float]:
    hz = os.sysconf("SC_CLK_TCK")
    return {n: 100.0 * (cpu1[n] - cpu0[n]) / hz / wall for n in cpu1  # type: ignore[operator]
            if cpu0.get(n) is not None and cpu1[n] is not None}


def _figures(pub: dict[tuple[str, str], dict[int, tuple[int, int]]], cpu: dict[str, float],
             wall: float) -> dict[str, Any]:
    """Latency per edge and in total, frames answered, CPU per node and per frame."""
    frames = pub[("capture", "frame")]
    result: dict[str, Any] = {"duration_s": round(wall, 2), "frames_published": len(frames), "tracks": 0,
                              "edges_ms": {}, "cpu_percent": {}}
    for i, name in enumerate(EDGES):
        a, b = STAGES[i], STAGES[i + 1]
        result["edges_ms"][name] = _pct([(pub[b][k][1] - pub[a][k][1]) / 1e6 for k in pub[b] if k in pub[a]])
    total = [(v[1] - v[0]) / 1e6 for v in pub[("motor", "command")].values() if v[0] > 0]
    result["edges_ms"]["total capture→command"] = _pct(total)
    tracks = pub[("prediction", "track")]
    result["tracks"] = sum(1 for k in frames if k in tracks)
    result["dropped_frames"] = len(frames) - result["tracks"]
    result["cpu_percent"] = {n: round(v, 1) for n, v in sorted(cpu.items())}
    # CPU of every node together per captured frame (ms of one core): what the lane can save shows here.
    result["cpu_ms_per_frame"] = round(sum(cpu.values()) / 100 * wall / max(1, len(frames)) * 1e3, 2)
    return result


def _print_figures(result: dict[str, Any]) -> None:
    print(f"bench pipeline: {result['detector']} on scene:{result['scene']} {result['resolution']}, lane "
          f"{result['lane']}, 30 Hz, {result['duration_s']:.1f} s")
    print("| edge | n | p50 ms | p99 ms |\n|---|---:|---:|---:|")
    for name, v in result["edges_ms"].items():
        print(f"| {name} | {v['n']} | {v['p50']:.2f} | {v['p99']:.2f} |")
    print(f"frames published {result['frames_published']}, tracks {result['tracks']}, "
          f"dropped {result['dropped_frames']}")
    print("CPU per node (% of one core): " + ", ".join(f"{n} {v:.1f}" for n, v in result["cpu_percent"].items()))
    print(f"CPU of all nodes per frame: {result['cpu_ms_per_frame']:.2f} ms")


def _pct(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0, "p50": float("nan"), "p99": float("nan")}
    a = np.asarray(values)
    return {"n": int(a.size), "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}
