"""``followbus eval``: score followers on real sequences and synthetic scenes; followbus is scored as the
graph's own tracking nodes run in-process (bus/inproc.py); ``--graph-check`` proves the launched graph (one
process per node, over Zenoh) gives the same outputs as that in-process run.

Output (``--out``, default results/): results.md (tables + the exact command), results.json, PNG plots
per sequence, and the detection cache (``cache/``) so a repeated run does not re-run the detector.
"""

from __future__ import annotations

import json
import logging
import math
import shlex
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from ...evaluation.metrics import SingleTargetMetrics, aggregate, format_markdown_table
from ...evaluation.runner import DEFAULT_DETECTOR, SequenceRun, detector_key
from ...evaluation.trace import worst_episodes_markdown
from ...vision.detector_presets import apply_detector_preset

log = logging.getLogger("followbus.eval")

REPO = Path(__file__).resolve().parents[2]


def expand_sequences(specs: list[str]) -> list[str]:
    """``all`` → every sequence under the data root; ``scene:<name>`` and directories pass through."""
    from ...evaluation.datasets import find_data_root, list_sequences

    out: list[str] = []
    for s in specs:
        if s == "all":
            root = find_data_root()
            if root is None:
                raise FileNotFoundError("'all': no evaluation data found: set FOLLOWBUS_DATA to a folder holding "
                                        "sot/ and/or mot/ (the layouts of ../shared/data/README.md)")
            found = [str(p) for p in list_sequences(root)]
            if not found:
                raise FileNotFoundError(f"'all': no sequences under {root}/sot or {root}/mot")
            out += found
        elif s.startswith("scene:"):
            from ...vision.scenes import SCENES

            if s.split(":", 1)[1] not in SCENES:
                raise ValueError(f"unknown scene {s!r}; available: {', '.join(SCENES)}")
            out.append(s)
        else:
            out += _sequence_folders(s)
    return out


def _sequence_folders(spec: str) -> list[str]:
    """A sequence folder of any layout, or a folder of them (a benchmark's root); each read before any work
    starts (no pixels: cheap), so a folder that is not a sequence is one line naming what is missing."""
    from ...evaluation.datasets import detect_layout, load_sequence, sequences_in

    path = Path(spec)
    if not path.is_dir():
        raise FileNotFoundError(f"{spec}: not a directory (a sequence folder, scene:<name> or all)")
    folders = [path] if detect_layout(path) is not None else sequences_in(path) or [path]
    for folder in folders:
        try:
            load_sequence(folder)
        except (OSError, ValueError) as exc:
            raise ValueError(str(exc)) from exc
    return [str(f) for f in folders]


# --------------------------------------------------------------------------- reporting


def _num(v: Any) -> Any:
    if isinstance(v, float | np.floating):
        return None if not math.isfinite(float(v)) else round(float(v), 6)
    if isinstance(v, np.integer):
        return int(v)
    return v


def _metrics_json(m: SingleTargetMetrics) -> dict[str, Any]:
    d = {k: _num(v) for k, v in m.as_dict().items()}
    d["reid"] = [{"occlusion_start": e.occlusion_start, "reappear_frame": e.reappear_frame,
                  "occluded_frames": e.occluded_frames, "latency_frames": e.latency_frames,
                  "latency_ms": _num(e.latency_ms) if e.latency_ms is not None else None}
                 for e in m.reid_events]
    return d


def _fmt(v: float, spec: str = ".2f") -> str:
    return "–" if not math.isfinite(v) else format(v, spec)


def timing_table(runs: list[SequenceRun], methods: list[str]) -> str:
    """Re-ID latency in frames, censored events, detector and tracker ms per frame."""
    lines = ["### Re-ID latency and timing", "",
             "| Sequence | Frames | Detector ms/fr | Method | Re-ID frames (mean) | Re-ID censored | Tracker ms/fr |",
             "|---|---:|---:|---|---:|---:|---:|"]
    for r in runs:
        for m in methods:
            mr = r.runs.get(m)
            if mr is None or mr.metrics is None:
                continue
            cached = " (cached)" if r.detections_cached else ""
            lines.append(f"| {r.sequence.name} | {r.sequence.n_frames} | {_fmt(r.detector_ms_mean)}{cached} | {m} | "
                         f"{_fmt(mr.metrics.reid_latency_frames_mean, '.1f')} | {mr.metrics.reid_censored} | "
                         f"{_fmt(mr.tracker_ms_mean)} |")
    total = sum(r.sequence.n_frames for r in runs)
    det = sum(r.detector_ms_mean * r.sequence.n_frames for r in runs if math.isfinite(r.detector_ms_mean))
    for m in methods:
        ms = [t for r in runs if m in r.runs for t in r.runs[m].tracker_ms]
        agg = aggregate([r.runs[m].metrics for r in runs if m in r.runs and r.runs[m].metrics is not None])
        lines.append(f"| overall | {total} | {_fmt(det / total if total else math.nan)} | {m} | "
                     f"{_fmt(agg.reid_latency_frames_mean, '.1f')} | {agg.reid_censored} | "
                     f"{_fmt(float(np.mean(ms)) if ms else math.nan)} |")
    return "\n".join(lines) + "\n"


CEILING = "detector ceiling"


def summary_matrix(runs: list[SequenceRun], methods: list[str]) -> str:
    """Sequences × methods, each cell "TSR % / CLE px", with the frame-weighted overall row and, last, the
    detector ceiling (the detection nearest the target on every frame: the bound of any follower that
    outputs detections; one that coasts on a prediction through misses can exceed it)."""
    lines = ["### TSR@20px % / CLE px, sequences × methods", "",
             "| Sequence | Frames | " + " | ".join(methods) + f" | {CEILING} |",
             "|---|---:|" + "---:|" * (len(methods) + 1)]

    def cell(m: SingleTargetMetrics | None) -> str:
        return "–" if m is None else f"{_fmt(100 * m.tsr, '.1f')} / {_fmt(m.cle, '.0f')}"

    for r in runs:
        cells = [cell(r.runs[m].metrics if m in r.runs else None) for m in methods] + [cell(r.ceiling)]
        lines.append(f"| {r.sequence.name} | {r.sequence.n_frames} | " + " | ".join(cells) + " |")
    scored = [[r.runs[m].metrics for r in runs if m in r.runs and r.runs[m].metrics is not None] for m in methods]
    scored.append([r.ceiling for r in runs if r.ceiling is not None])
    overall = [aggregate(ms) if ms else None for ms in scored]
    total = sum(r.sequence.n_frames for r in runs)
    lines.append(f"| **overall (frame-weighted)** | {total} | "
                 + " | ".join(f"**{cell(m)}**" for m in overall) + " |")
    return "\n".join(lines) + "\n"


def mot_table(runs: list[SequenceRun], methods: list[str]) -> str:
    """MOTA/IDF1/HOTA of the multi-object trackers' whole output on the MOT sequences; "" when none ran."""
    from ...evaluation.mot_metrics import evaluate_mot_combined
    from ...evaluation.runner import gt_mot_frames

    mot_runs = [r for r in runs if any(mr.mot is not None for mr in r.runs.values())]
    if not mot_runs:
        return ""
    lines = ["### Multi-object metrics (MOT sequences, every annotated person)", "",
             "| Sequence | Frames | Method | MOTA % | IDF1 % | HOTA % | DetA % | AssA % | IDSW | FP | FN |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def row(name: str, frames: int, m: str, mm) -> str:
        c = mm.clear
        return (f"| {name} | {frames} | {m} | {_fmt(100 * c.mota, '.1f')} | {_fmt(100 * mm.idf1, '.1f')} | "
                f"{_fmt(100 * mm.hota.hota, '.1f')} | {_fmt(100 * mm.hota.deta, '.1f')} | "
                f"{_fmt(100 * mm.hota.assa, '.1f')} | {c.num_switches} | {c.num_false_positives} | {c.num_misses} |")

    for r in mot_runs:
        lines += [row(r.sequence.name, r.sequence.n_frames, m, r.runs[m].mot) for m in methods
                  if m in r.runs and r.runs[m].mot is not None]
    for m in methods:
        pairs = [(gt_mot_frames(r.gt_people), r.runs[m].mot_frames)
                 for r in mot_runs if m in r.runs and r.runs[m].mot is not None]
        if pairs:
            frames = sum(len(g) for g, _ in pairs)
            lines.append(row("**combined**", frames, m, evaluate_mot_combined(pairs)))
    lines += ["", "Scored as MOTChallenge/TrackEval do: IoU ≥ 0.5 for CLEAR and identity, HOTA over α = 0.05…0.95; "
              "gt = pedestrian rows not flagged 0; a tracker box matched to a distractor (person on vehicle, static "
              "person, distractor, reflection) is removed before scoring. Combined = all MOT sequences as one "
              "benchmark (counts summed).", ""]
    return "\n".join(lines) + "\n"


def _episode_json(boxes: list, run: SequenceRun) -> dict[str, Any] | None:
    from ...evaluation.trace import worst_episode

    ep = worst_episode(boxes, run.gt_boxes, run.other_gt)
    return None if ep is None else {"first_frame": ep.first, "frames": ep.length, "followed": ep.followed}


def write_report(runs: list[SequenceRun], methods: list[str], out: Path, command: str, detector: str,
                 notes: list[str]) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict[str, SingleTargetMetrics]] = {m: {} for m in methods}
    for r in runs:
        for m in methods:
            if m in r.runs and r.runs[m].metrics is not None:
                rows[m][r.sequence.name] = r.runs[m].metrics
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    md = [f"# followbus eval — {stamp}", "", f"Command: `{command}`", "",
          f"Detector: {detector} (the same cached detections for every method); "
          f"methods initialised with the first ground-truth box.", ""]
    md.append(summary_matrix(runs, methods))
    md.append(format_markdown_table(rows))
    md.append(mot_table(runs, methods))
    md.append(worst_episodes_markdown(runs, methods))
    md.append(timing_table(runs, methods))
    md += ["### Notes", ""] + [f"- {n}" for n in notes] + [""]
    md_path = out / "results.md"
    md_path.write_text("\n".join(md), encoding="utf-8")
    data: dict[str, Any] = {"command": command, "detector": detector, "date": stamp, "notes": notes,
                            "sequences": {}, "overall": {}}
    for r in runs:
        data["sequences"][r.sequence.name] = {
            "kind": r.sequence.kind, "frames": r.sequence.n_frames, "fps": r.sequence.fps,
            "size": [r.sequence.width, r.sequence.height], "detector_ms": _num(r.detector_ms_mean),
            "detections_cached": r.detections_cached,
            "detector_ceiling": _metrics_json(r.ceiling) if r.ceiling is not None else None,
            "methods": {m: {**_metrics_json(mr.metrics), "tracker_ms": _num(mr.tracker_ms_mean),
                            "worst_episode": _episode_json(mr.boxes, r),
                            **({"mot": {k: _num(v) for k, v in mr.mot.as_dict().items()}} if mr.mot else {})}
                        for m, mr in r.runs.items() if mr.metrics is not None},
        }
    for m, per_seq in rows.items():
        if per_seq:
            data["overall"][m] = _metrics_json(aggregate(per_seq.values()))
    ceilings = [r.ceiling for r in runs if r.ceiling is not None]
    if ceilings:
        data["overall"][CEILING] = _metrics_json(aggregate(ceilings))
    json_path = out / "results.json"
    json_path.write_text(json.dumps(data, indent=1, ensure_ascii=False), encoding="utf-8")
    return md_path, json_path


# --------------------------------------------------------------------------- command


def _wants_trace(args) -> bool:
    """Whether the followers record every frame's details (--trace, and --video, which draws them)."""
    return bool(args.trace or args.video)


def _say_frame_files(args, out: Path) -> None:
    if _wants_trace(args):
        print(f"per-frame traces in {out / 'trace'}, OTB result files in {out / 'tracker_results'}"
              + (f", videos in {out / 'videos'}" if args.video else ""))


def _write_frames(run: SequenceRun, out: Path, args, method: str) -> None:
    """--trace: every method's per-frame trace and OTB result file; --video: the MP4 of ``method``'s run."""
    from ...evaluation.trace import file_stem, write_run_files

    if args.trace:
        write_run_files(run, out)
    if args.video:
        from ...evaluation.render import render_run

        path = out / "videos" / f"{file_stem(run.sequence.name)}-{file_stem(method)}.mp4"
        n = render_run(run, method, path)
        log.info("wrote %s (%d frames)", path, n)


def _detector_label(name: str) -> str:
    """``graph`` named with what it amounts to (the report says which detector the robot runs)."""
    return f"graph.yaml's ({detector_key(name)})" if name == "graph" else name



def cmd_eval(args) -> int:
    from ...evaluation.baselines import peer_available
    from ...evaluation.plots import plot_sequence
    from ...evaluation.runner import method_factories, open_sequence, run_sequence

    command = "followbus " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if args.argv is None else args.argv
    if getattr(args, "group", False) and getattr(args, "camera", False):
        from ...evaluation.group_camera import cmd_eval_group_camera

        if args.detector == "simulated":
            print("followbus: --group --camera needs a real detector (yolox, yolox640 or hog)", file=sys.stderr)
            return 2
        return cmd_eval_group_camera(Path(args.out), command, args.sequences or None,
                                     args.detector or DEFAULT_DETECTOR,
                                     args.max_frames)
    if getattr(args, "camera", False):
        print("followbus: --camera goes with --group", file=sys.stderr)
        return 2
    if getattr(args, "group", False):
        from ...evaluation.group_eval import cmd_eval_group
        from ...evaluation.group_sim import SCENARIOS

        # With --group the positional names are simulator scenarios (default: all of them).
        unknown = [s for s in args.sequences if s not in SCENARIOS]
        if unknown:
            print(f"followbus: unknown group scenario {unknown[0]!r}; available: {', '.join(SCENARIOS)}",
                  file=sys.stderr)
            return 2
        return cmd_eval_group(Path(args.out), args.seed, command, args.sequences or None)
    if not args.sequences:
        print("followbus: eval needs at least one SEQ (a sequence dir, scene:<name> or all), or --group",
              file=sys.stderr)
        return 2
    if args.graph_check:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        status = 0
        for spec in args.sequences:
            if spec == "all":
                print("followbus: --graph-check takes named sequences (scene:<name> or a sequence dir), not 'all'",
                      file=sys.stderr)
                return 2
            try:
                res = graph_check(spec, detector=args.detector, max_frames=args.max_frames or 0,
                                  log_file=Path(args.out) / "graph.log")
            except (FileNotFoundError, ValueError) as exc:
                print(f"followbus: {exc}", file=sys.stderr)
                return 2
            print(f"{spec} ({res['detector']} detections): {res['compared']} frames compared, "
                  f"{res['mismatches']} mismatches, {res['missing']} frames without a track from the graph"
                  + (f"; first mismatch at frame {res['first_mismatch']}" if res["mismatches"] else ""))
            status |= 0 if res["mismatches"] == 0 and res["missing"] == 0 and res["compared"] > 0 else 1
        return status
    args.detector = args.detector or DEFAULT_DETECTOR
    try:
        seqs = expand_sequences(args.sequences)
    except (FileNotFoundError, ValueError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    methods = list(dict.fromkeys(args.method or ["followbus", "kalman"]))
    notes: list[str] = []
    peers = [m for m in methods if m.startswith("peer:")]
    if peers and (reason := peer_available()):
        print(f"followbus: skipping {', '.join(peers)}: {reason} (make installs it; by hand: "
              "pip install -e '.[peers]' && pip install --no-deps -r requirements-peers.txt)", file=sys.stderr)
        notes.append(f"peer trackers {', '.join(peers)} skipped: {reason}")
        methods = [m for m in methods if m not in peers]
    try:
        factories = method_factories(methods, ablations=args.ablations, trace=_wants_trace(args))
    except ValueError as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    methods = list(factories)
    out = Path(args.out)
    from tqdm import tqdm

    from ...vision.models import ModelError

    runs: list[SequenceRun] = []
    # delay: a run that fails at once (no model) shows its one line without a progress bar before it
    for spec in tqdm(seqs, desc="sequences", unit="seq", file=sys.stderr, delay=1.0):
        seq = open_sequence(spec, max_frames=args.max_frames or 0)
        try:
            run = run_sequence(seq, factories, args.detector, cache_dir=out / "cache", seed=args.seed,
                               progress=True)
        except ModelError as exc:
            hint = ""
            if args.detector not in ("hog", "simulated"):
                hint = ("; or score without a model: --detector simulated (ground truth + noise)"
                        if spec.startswith("scene:") else "; or --detector hog (no model, far less accurate)")
            print(f"followbus: {exc}{hint}", file=sys.stderr)
            return 2
        runs.append(run)
        plot_sequence(run, out / "plots")
        _write_frames(run, out, args, methods[0])
        fb = run.runs.get("followbus")
        if fb is not None and fb.metrics is not None:
            log.info("%s: followbus TSR %.3f CLE %.1f px", seq.name, fb.metrics.tsr, fb.metrics.cle)
    if any(r.sequence.kind == "mot" for r in runs):
        notes.append("MOT sequences are scored as single-target following of the target chosen by "
                     "evaluation/datasets.py (feet nearest the image bottom-centre on the first annotated frame); "
                     "MOTA/IDF1/HOTA are multi-object metrics: reported only for the peer MOT trackers (their "
                     "whole output), never for single-target followers.")
    if args.detector == "simulated":
        notes.append("simulated detector = ground truth + noise: tracking numbers only, never detection accuracy.")
    if any(r.detections_cached for r in runs):
        notes.append("detector ms/frame of cached sequences is the time measured when the cache was filled.")
    notes.append("detector ceiling = the detection nearest the target on every frame (an oracle): the best a "
                 "follower that only outputs detections can do; followbus, kalman and the peers coast on their "
                 "prediction through missed detections and can exceed it there.")
    notes.append("Miss = gt frames without an output; Switch = output moved from the target onto another "
                 "annotated person (SOT sequences annotate only the target, so switches there are always 0); "
                 "Wrong re-lock = an episode of >= 10 frames with an output that does not overlap the target's box "
                 "(following someone else; counted on every sequence).")
    _say_frame_files(args, out)
    md, js = write_report(runs, methods, out, command, _detector_label(args.detector), notes)
    print(f"wrote {md}, {js} and plots in {out / 'plots'}")
    print((out / "results.md").read_text(encoding="utf-8"))
    return 0


# --------------------------------------------------------------------------- graph check


def derived_graph(source: str, port: int, namespace: str, init_box: list[float], max_frames: int,
                  base: Path = REPO / "graph.yaml", max_in_flight: int = 1, detector: str = "simulated") -> str:
    """graph.yaml adapted for a lockstep run: private port/namespace, ``source`` (scene:<name> or a sequence
    dir), fast pace with capture acked by prediction/track, ``detector`` as in ``followbus eval``, no
    persisted template, the target given by init_box."""
    from ...bus.graph import load_graph

    graph = load_graph(base).with_namespace(namespace).with_port(port)
    graph = graph.with_input("capture", "ack", "prediction/track", sync="none")
    graph = graph.override({
        "capture": {"source": source, "pace": "fast", "max_frames": max_frames, "max_in_flight": max_in_flight},
        "detection": apply_detector_preset({}, detector), "template": {"state_file": ""},
        "reid": {"init_box": [float(v) for v in init_box]}})
    for node in graph.nodes:
        # Lockstep loses nothing, so a timeout could only mean a slow (cold, loaded) node, and a set
        # emitted without its feedback would make the graph diverge from the in-process run.
        graph = graph.with_node(node, sync_timeout_ms=10_000.0)
    return graph.to_yaml()


def graph_check(spec: str, *, detector: str | None = None, max_frames: int = 0, port: int | None = None,
                seed: int = 0, max_in_flight: int = 1, timeout_s: float = 120.0,
                log_file: Path | None = None) -> dict[str, Any]:
    """Run ``spec`` (scene:<name> or a sot/mot sequence dir) through the launched graph (motor omitted:
    v_ego = 0) and through the same nodes in-process as eval runs them (evaluation/graph_follower.py), on the
    same detector; compare the track boxes frame by frame.

    ``detector``: simulated (scenes only: the graph's detection node rebuilds its input from the capture's
    ground truth) or a real one (a name of vision/detector_presets.py), run by the detection node on the frames
    it receives and in-process on the frames read here. Default: simulated for scenes, graph.yaml's otherwise.

    Returns {"compared", "mismatches", "missing", "first_mismatch", "graph", "inproc", "detector"}.
    """
    from ...bus.graph import load_graph
    from ...evaluation.graph_follower import GraphFollower
    from ...evaluation.runner import open_sequence
    from ...nodes.detection import Detection, detector_from_params, split_detections
    from ...vision.detectors import SimulatedDetector

    is_scene = spec.startswith("scene:")
    detector = detector or ("simulated" if is_scene else DEFAULT_DETECTOR)
    # the detection node's params as the graph runs them (thresholds, threads, model), switched to ``detector``
    shipped = load_graph(REPO / "graph.yaml")
    node_params = Detection.parse_params(apply_detector_preset(dict(shipped.nodes["detection"].params), detector))
    if detector == "simulated" and not is_scene:
        raise ValueError(f"{spec}: simulated detections are reproduced by the graph for scenes only; "
                         "use --detector yolox|yolox640|hog")
    seq = open_sequence(spec, seed=seed, max_frames=max_frames)
    source = spec if is_scene else str(Path(spec).resolve())
    n = seq.n_frames
    # in-process: the same frames, the same detector, the same init box, v_ego = 0
    if detector == "simulated":
        sim = SimulatedDetector(seed=0)  # detection node defaults: noise 4 px, miss 0.05, fp 0.02, seed 0

        def detect(item):
            return split_detections(node_params, sim.detect(item.bgr, item.truth))
    else:
        # exactly the detector the graph's detection node builds (threads, thresholds, model)
        real = detector_from_params(node_params)

        def detect(item):
            return split_detections(node_params, real.detect(item.bgr))
    from ...tracking.params import TrackerParams

    # The graph warps the prior by camera motion only where an egomotion node publishes it; in-process likewise.
    has_egomotion = "egomotion" in shipped.nodes
    follower = GraphFollower(TrackerParams(camera_motion_compensation=has_egomotion))
    inproc: list[Any] = []
    init_box: list[float] | None = None
    for item in seq.frames():
        if init_box is None:
            if item.gt_box is None:
                raise ValueError(f"{spec}: the target has no ground-truth box on frame 0 (the graph is told "
                                 "whom to follow on its first frame)")
            init_box = list(item.gt_box)
        high, low = detect(item)
        box, _ = follower.step(item.bgr, high, item.t_ns, (0.0, 0.0), init_box if not inproc else None,
                               low_detections=low)
        inproc.append(box)
    assert init_box is not None

    if port is None:
        import socket

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
    tracks = _run_graph_once(source, port, init_box, n, max_in_flight, timeout_s, log_file, detector)
    mismatches, missing, first = 0, 0, None
    for k in range(n):
        if k not in tracks:
            missing += 1
            continue
        a, b = tracks[k], inproc[k]
        same = (a is None and b is None) or (a is not None and b is not None
                                             and np.allclose(a, b, rtol=0.0, atol=1e-9))
        if not same:
            mismatches += 1
            first = k if first is None else first
    return {"compared": n - missing, "mismatches": mismatches, "missing": missing, "first_mismatch": first,
            "graph": [tracks.get(k) for k in range(n)], "inproc": inproc, "detector": detector}


def _run_graph_once(source: str, port: int, init_box: list[float], n: int, max_in_flight: int, timeout_s: float,
                    log_file: Path | None, detector: str) -> dict[int, Any]:
    """Launch the derived graph once (motor omitted) and collect Track boxes by frame_seq. Capture publishes
    frame 0 only once every consuming node is listening (nodes/capture.py), so the lockstep always starts."""
    from ...bus.graph import load_graph
    from ...bus.pubsub import Subscriber
    from ...bus.schemas import Track
    from ...bus.session import open_session
    from ..launch import Launcher

    tracks: dict[int, Any] = {}
    done = threading.Event()
    with tempfile.TemporaryDirectory(prefix="followbus-graphcheck-") as tmp:
        path = Path(tmp) / "graph.yaml"
        path.write_text(derived_graph(source, port, f"gc{port}", init_box, n, max_in_flight=max_in_flight,
                                      detector=detector))
        graph = load_graph(path)
        session = open_session(graph.zenoh)

        def on_track(msg: Track) -> None:
            tracks[msg.header.frame_seq] = None if msg.box is None else tuple(float(v) for v in msg.box)
            if len(tracks) >= n:
                done.set()

        sub = Subscriber(session, graph.key("prediction", "track"), on_track, schema=Track)
        launcher = Launcher(graph, only=[m for m in graph.nodes if m != "motor"], quiet=log_file is None,
                            log_file=log_file, startup_timeout_s=60.0, grace_s=5.0)
        runner = threading.Thread(target=launcher.run, kwargs={"duration_s": timeout_s}, daemon=True)
        t0 = time.monotonic()
        runner.start()
        try:
            done.wait(timeout_s)
        finally:
            launcher.request_stop()
            runner.join(30)
            sub.undeclare()
            session.close()
        log.info("graph check %s: %d/%d tracks in %.1f s", source, len(tracks), n, time.monotonic() - t0)
    return dict(tracks)
