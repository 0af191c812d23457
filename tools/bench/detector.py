"""``followbus bench detector``: the cost of each detector side by side, alternated over rounds.

Per inference (the runtime call alone, on letterboxed frames of the built-in scenes, threads as graph.yaml's
detection node): CPU ms of the process (``time.process_time``: the compute, nearly independent of how busy the
machine is, which wall time is not on a shared host) and wall ms. Each round runs every detector in turn, so a
change of load hits them all alike; the load average is recorded beside the figures.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

SCENE_FRAMES = (("lookalike", 30), ("corridor-occlusion", 60), ("ego-motion", 90))


def _load1() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def _frames(per_scene: int) -> list[np.ndarray]:
    from ...vision.scenes import make_scene

    frames = []
    for name, start in SCENE_FRAMES:
        for k, f in enumerate(make_scene(name, seed=0).frames()):
            if k >= start + per_scene:
                break
            if k >= start:
                frames.append(f.bgr)
    return frames


def _time_one(det: Any, frames: list[np.ndarray]) -> tuple[list[float], list[float]]:
    cpu, wall = [], []
    for bgr in frames:
        blob, _ = det.preprocess(bgr)
        c0, w0 = time.process_time(), time.perf_counter()
        det.session.run(None, {det.input_name: blob})
        cpu.append((time.process_time() - c0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
    return cpu, wall


def _stats(values: list[float]) -> dict[str, float]:
    return {"median": round(float(np.median(values)), 2), "p10": round(float(np.percentile(values, 10)), 2),
            "p90": round(float(np.percentile(values, 90)), 2)}


def run_bench_detector(args) -> int:
    from ...evaluation.runner import make_eval_detector
    from ...vision.models import ModelError

    names = [n.strip() for n in args.detectors.split(",") if n.strip()]
    try:
        dets = {n: make_eval_detector(n) for n in names}
    except (ModelError, ValueError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    frames = _frames(args.frames)
    for det in dets.values():  # warm-up: first runs allocate
        _time_one(det, frames[:2])
    cpu: dict[str, list[float]] = {n: [] for n in dets}
    wall: dict[str, list[float]] = {n: [] for n in dets}
    loads = []
    for r in range(args.rounds):
        for n, det in dets.items():
            c, w = _time_one(det, frames)
            cpu[n] += c
            wall[n] += w
            loads.append(_load1())
            print(f"round {r + 1}: {n} CPU {np.median(c):.1f} ms, wall {np.median(w):.1f} ms, load {loads[-1]}",
                  flush=True)
    result = {n: {"cpu_ms": _stats(cpu[n]), "wall_ms": _stats(wall[n]), "name": dets[n].name} for n in dets}
    base = result[names[0]]["cpu_ms"]["median"]
    print(f"\n{len(frames)} frames x {args.rounds} rounds, load (1 min) {min(loads)}-{max(loads)}")
    print("| detector | model | CPU ms/inference median (p10-p90) | x first | wall ms median |")
    print("|---|---|---:|---:|---:|")
    for n, v in result.items():
        c = v["cpu_ms"]
        print(f"| {n} | {v['name']} | {c['median']:.1f} ({c['p10']:.1f}-{c['p90']:.1f}) | "
              f"{c['median'] / base:.2f} | {v['wall_ms']['median']:.1f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"load_1min": [min(loads), max(loads)], "detectors": result}, indent=1))
    return 0
