"""``followbus bench chaos``: the tracking graph under faults (the runner: reliability/chaos.py, the faults:
reliability/faults.py, the checks: reliability/judging.py). This command launches the graph for the runner (it
owns the launcher), prints a line per fault, the table and the headline, and writes the JSON."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ...bus.graph import load_graph
from ...reliability.chaos import ChaosRunner
from ...reliability.faults import resolve_faults
from ...reliability.judging import (
    ChaosError,
    ChaosOptions,
    Fault,
    FaultResult,
    fmt,
    format_headline,
    format_table,
    headline,
    summarise,
)

log = logging.getLogger("followbus.chaos")


class ChaosGraph:
    """One launch of the graph by an in-process :class:`~followbus.tools.launch.Launcher`."""

    def __init__(self, path: Path, variant: str, log_file: Path, record_path: Path | None):
        from ...bus.barrier import RECORDER_NAME
        from ..launch import Launcher

        self.path = path
        self.variant = variant
        self.graph = load_graph(path)
        self.record_path = record_path
        extra = []
        if record_path is not None:
            # Everything but the raw frames (27 MB/s at 30 Hz; the JPEG previews stay): a chaos run is long.
            ns = self.graph.namespace
            topics = [f"{ns}/capture/preview", f"{ns}/capture/ground_truth",
                      *(f"{ns}/{name}/**" for name in self.graph.nodes if name != "capture")]
            extra.append((RECORDER_NAME, [sys.executable, "-m", "followbus.tools.cli", "record", "--graph", str(path),
                                          "-o", str(record_path), "--topics", *topics]))
        self.launcher = Launcher(self.graph, startup_timeout_s=60.0, grace_s=3.0, extra_children=extra,
                                 log_file=log_file)
        self._ready = threading.Event()
        self.ready_at = 0.0  # time.monotonic() when every node was up
        self.exit_status: int | None = None
        self._thread = threading.Thread(target=self._run, name="chaos-launcher", daemon=True)

    def _run(self) -> None:
        self.exit_status = self.launcher.run(on_ready=self._ready.set)

    def start(self, timeout_s: float = 90.0) -> None:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._ready.wait(0.1):
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise ChaosError(f"the graph did not come up (launcher status {self.exit_status})")
        self.ready_at = time.monotonic()

    @property
    def running(self) -> bool:
        return self._thread.is_alive() and not self.launcher.stop_event.is_set()

    def pid(self, name: str) -> int | None:
        for child in self.launcher.children:
            if child.name == name and child.proc is not None and child.proc.poll() is None:
                return child.proc.pid
        return None

    def failed(self) -> list[str]:
        return [c.name for c in self.launcher.children if c.failed]

    def stop(self) -> None:
        self.launcher.request_stop()
        self._thread.join(30)

    def recover_recording(self) -> Any:
        """What `followbus recover` makes of the recording (the recorder may have been killed mid-chunk)."""
        from ..recording.mcap_io import recover

        path = self.record_path
        return None if path is None else recover(path, path.with_name(path.stem + ".recovered.mcap"))


def _options(args: Any) -> ChaosOptions | str:
    """The runner's options from the command line, or what is wrong with it (one line)."""
    from ...vision.scenes import SCENES

    if args.detector == "yolox416":
        from ...vision.models import find_model

        if find_model("yolox_nano_416.onnx") is None:
            return "yolox_nano_416.onnx not found on the model search path"
    if args.scene not in SCENES:
        return f"unknown scene {args.scene!r} (scenes: {', '.join(SCENES)})"
    return ChaosOptions(detector=args.detector, scene=args.scene, burners=args.burners, load_s=args.load_seconds,
                        recovery_bound_s=args.recovery_bound, hold_s=args.hold,
                        malformed_per_key=args.malformed_per_key, record=args.record, port=args.port,
                        namespace=args.namespace, log_file=Path(args.log))


def _run_faults(runner: ChaosRunner, faults: list[Fault], repeat: int) -> list[FaultResult]:
    total, results = len(faults) * repeat, []
    for i, fault in enumerate([f for _ in range(repeat) for f in faults], start=1):
        print(f"[{i}/{total}] {fault.name}: {fault.description}", flush=True)
        result = runner.run(fault)
        results.append(result)
        rec = "never" if result.recovery_s is None else f"{result.recovery_s:.2f} s"
        print(f"[{i}/{total}] {fault.name}: {'survived' if result.survived else 'FAILED'} "
              f"(recovery {rec}, watchdog {fmt(result.watchdog_ms, '.0f')} ms, unsafe {result.unsafe_commands})"
              + "".join(f"\n    {f}" for f in result.failures), flush=True)
    return results


def run_bench_chaos(args: Any) -> int:
    """``followbus bench chaos``: run the faults, print a progress line each and the table; 0 when all survived."""
    try:
        faults = resolve_faults(args.faults, record=args.record, detector=args.detector)
    except ValueError as exc:
        print(f"followbus: bench chaos: {exc}", file=sys.stderr)
        return 2
    options = _options(args)
    if isinstance(options, str):
        print(f"followbus: bench chaos: {options}", file=sys.stderr)
        return 2
    if getattr(args, "verbose", 0) <= 0:
        logging.getLogger("followbus.launch").setLevel(logging.WARNING)  # starts and stops: the node log has them
    started = time.monotonic()
    print(f"bench chaos: {len(faults) * args.repeat} fault runs on scene:{args.scene} with the {args.detector} "
          f"detector; node logs in {args.log}", flush=True)
    try:
        with ChaosRunner(options, lambda line: print(line, flush=True), launch=ChaosGraph) as runner:
            results = _run_faults(runner, faults, args.repeat)
            launches, load_samples = runner.launches, list(runner.load_samples)
    except ChaosError as exc:
        print(f"bench chaos: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("bench chaos: interrupted", file=sys.stderr)
        return 130
    rows, head = summarise(results), headline(results, load_samples, options)
    print(f"\n{format_table(rows)}\n")
    print(format_headline(head, launches, time.monotonic() - started) if results else "no faults run")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(options).items()},
            "cpu_count": os.cpu_count(), "load_average": os.getloadavg(), "headline": head,
            "load_samples": load_samples,
            "summary": rows, "runs": [dataclasses.asdict(r) for r in results]}, indent=1, ensure_ascii=False))
    return 0 if results and head["survived"] == len(results) else 1
