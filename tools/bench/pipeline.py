"""``followbus bench pipeline``: end-to-end latency through the launched graph at 30 Hz.

Every message header carries ``stamp_ns`` (the capture stamp of its frame) and ``pub_ns`` (when it was
published). Per frame_seq the edges are: capture→detection, detection→prediction prior, prior→reid
measurement, measurement→prediction track, track→motor command (differences of pub_ns), and the total
capture stamp→command. CPU per node comes from /proc/<pid>/stat (pids from the NodeStatus messages);
dropped frames = frames published by capture that never produced a track.
"""

from __future__ import annotations

import json
import logging
import os
import socket
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


def _cpu_ticks(pid: int) -> int | None:
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
                               model_file=p.get("model_file") or None, input_size=int(p.get("input_size_px", 416)))
    except DetectorUnavailable:
        return False
    return True


def run_bench_pipeline(args) -> int:
    from ...bus.graph import load_graph
    from ...bus.pubsub import declare_subscriber, frame_bytes
    from ...bus.schemas import NodeStatus, decode
    from ...bus.session import open_session
    from ...reliability.chaos import scene_graph
    from ..launch import Launcher

    detector = args.detector
    if not _model_present(detector):
        print("bench pipeline: YOLOX model not found; using hog (figures are not comparable)", flush=True)
        detector = "hog"
    port = args.port
    if not port:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
    ns = args.namespace or f"bench{port}"
    pub: dict[tuple[str, str], dict[int, tuple[int, int]]] = {st: {} for st in STAGES}
    pids: dict[str, int] = {}
    lock = threading.Lock()
    recording = threading.Event()
    with tempfile.TemporaryDirectory(prefix="followbus-bench-") as tmp:
        path = Path(tmp) / "graph.yaml"
        path.write_text(scene_graph(scene=args.scene, port=port, namespace=ns, detector=detector,
                                    resolution=args.resolution,
                                    lane=args.lane == "on"))
        graph = load_graph(path)
        session = open_session(graph.zenoh)
        subs = []

        def header_cb(stage: tuple[str, str], schema):
            def cb(sample) -> None:
                if not recording.is_set():
                    return
                try:
                    msg = decode(frame_bytes(sample), schema)
                except Exception:  # a malformed sample is not a latency figure
                    return
                h = msg.header
                if h.frame_seq >= 0:
                    with lock:
                        pub[stage].setdefault(h.frame_seq, (h.stamp_ns, h.pub_ns))
            return cb

        from ...bus.schemas import Frame
        from ...msgs.perception import Detections
        from ...msgs.robot import MotorCommand
        from ...msgs.tracking import Measurement, Prior, Track

        schemas = {("capture", "frame"): Frame, ("detection", "detections"): Detections,
                   ("prediction", "prior"): Prior, ("reid", "measurement"): Measurement,
                   ("prediction", "track"): Track, ("motor", "command"): MotorCommand}
        for st in STAGES:
            # Frames on the lane's side key when the lane is on: a subscriber of the real key would make capture
            # send every frame inline as well (bus/shmlane.py) and the figures would not be the lane's.
            subs.append(declare_subscriber(session, graph.key(*st), header_cb(st, schemas[st]),
                                           lane=graph.zenoh.shm_lane))

        def on_status(sample) -> None:
            try:
                st = decode(frame_bytes(sample), NodeStatus)
            except Exception:
                return
            with lock:
                pids[st.node] = st.pid

        subs.append(declare_subscriber(session, f"{ns}/@status/*", on_status))
        launcher = Launcher(graph, quiet=True, startup_timeout_s=60.0)
        ready = threading.Event()
        runner = threading.Thread(target=launcher.run, kwargs={"duration_s": args.duration + 120,
                                                               "on_ready": ready.set}, daemon=True)
        runner.start()
        try:
            if not ready.wait(90):
                print("bench pipeline: the graph did not come up", flush=True)
                return 1
            time.sleep(4.0)  # warm-up: model load, first frames, status messages with pids
            with lock:
                cpu0 = {n: _cpu_ticks(p) for n, p in pids.items()}
            t0 = time.monotonic()
            recording.set()
            time.sleep(args.duration)
            recording.clear()
            wall = time.monotonic() - t0
            with lock:
                cpu1 = {n: _cpu_ticks(p) for n, p in pids.items()}
        finally:
            launcher.request_stop()
            runner.join(30)
            for s in subs:
                s.undeclare()
            session.close()
    result = _figures(pub, _cpu_percent(cpu0, cpu1, wall), wall)
    result.update(detector=detector, scene=args.scene, resolution="x".join(map(str, args.resolution)), lane=args.lane)
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
