"""``followbus bench soak``: the launched graph followed for minutes, judged by reliability/soak.py."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from ...reliability.soak import SoakWindow, judge_soak, sample_process
from .pipeline import LaunchedPipeline, pipeline_detector


def _row(w: SoakWindow) -> str:
    procs = w.processes.values()
    rss = sum(p.rss_mb for p in procs if p)
    fds = sum(p.fds for p in procs if p)
    threads = sum(p.threads for p in procs if p)
    lat = w.figures["edges_ms"]["total capture→command"]
    return (f"| {w.index} | {w.load1:.1f} | {w.figures['tracks']} / {w.figures['frames_published']} "
            f"({w.answered:.1%}) | {lat['p50']:.1f} / {lat['p99']:.1f} | {w.figures['cpu_ms_per_frame']:.1f} | "
            f"{rss:.0f} | {fds} | {threads} |")


def run_bench_soak(args) -> int:
    detector = pipeline_detector(args.detector, "soak")
    count = max(2, math.ceil(args.minutes * 60 / args.window))
    print(f"bench soak: graph.yaml ({detector}) on scene:{args.scene} for {count} windows of {args.window:g} s; "
          f"load {os.getloadavg()[0]:.1f} at the start", flush=True)
    print("| window | load | frames answered | p50 / p99 ms | CPU ms/frame | RSS MB (all nodes) | fds | threads |\n"
          "|---:|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    windows: list[SoakWindow] = []
    try:
        with LaunchedPipeline(detector=detector, scene=args.scene, resolution=(640, 480), lane=False,
                              port=args.port, namespace=args.namespace) as pipeline:
            for index in range(1, count + 1):
                figures = pipeline.measure(args.window)
                w = SoakWindow(index, figures, {n: sample_process(p) for n, p in sorted(pipeline.pids.items())})
                windows.append(w)
                print(_row(w), flush=True)
    except RuntimeError as exc:
        print(f"bench soak: {exc}", flush=True)
        return 1
    failures = judge_soak(windows)
    print("soak: clean" if not failures else "soak: NOT clean\n" + "\n".join(f"  - {f}" for f in failures))
    if args.json:
        Path(args.json).write_text(json.dumps({"detector": detector, "scene": args.scene, "window_s": args.window,
                                               "windows": [w.as_dict() for w in windows], "failures": failures},
                                              indent=1, ensure_ascii=False))
    return 0 if not failures else 1
