"""``followbus eval``: score followers on real sequences and synthetic scenes; followbus is scored as the
graph's own tracking nodes run in-process (bus/inproc.py); ``--graph-check`` proves the launched graph (one
process per node, over Zenoh) gives the same outputs as that in-process run.

Output (``--out``, default results/): results.md (tables + the exact command), results.json, PNG plots
per sequence, and the detection cache (``cache/``) so a repeated run does not re-run the detector.
"""

from __future__ import annotations

import dataclasses
import logging
import shlex
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ...evaluation.campaign import campaign_notes, expand_sequences, run_campaign
from ...evaluation.report import write_report
from ...evaluation.runner import DEFAULT_DETECTOR, SequenceRun, detector_key
from ...vision.detector_presets import apply_detector_preset
from ..errors import writable_directory

log = logging.getLogger("followbus.eval")

REPO = Path(__file__).resolve().parents[2]


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



def _cmd_group(args, command: str) -> int:
    """--group (the simulator's scenarios) and --group --camera (real sequences through the group graph)."""
    from ...evaluation.group_sim import SCENARIOS

    if getattr(args, "camera", False):
        from ...evaluation.group_camera import cmd_eval_group_camera

        if args.detector == "simulated":
            print("followbus: --group --camera needs a real detector (yolox, yolox640 or hog)", file=sys.stderr)
            return 2
        return cmd_eval_group_camera(Path(args.out), command, args.sequences or None,
                                     args.detector or DEFAULT_DETECTOR, args.max_frames)
    from ...evaluation.group_eval import cmd_eval_group

    # With --group the positional names are simulator scenarios (default: all of them).
    unknown = [s for s in args.sequences if s not in SCENARIOS]
    if unknown:
        print(f"followbus: unknown group scenario {unknown[0]!r}; available: {', '.join(SCENARIOS)}",
              file=sys.stderr)
        return 2
    return cmd_eval_group(Path(args.out), args.seed, command, args.sequences or None)


def _cmd_graph_check(args) -> int:
    """--graph-check: each named sequence through the launched graph and in-process; 0 when they agree."""
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if "all" in args.sequences:
        print("followbus: --graph-check takes named sequences (scene:<name> or a sequence dir), not 'all'",
              file=sys.stderr)
        return 2
    status = 0
    for spec in args.sequences:
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


def _methods(args, notes: list[str]) -> dict[str, Any]:
    """The followers asked for (peers skipped with a note when they are not installed); ValueError: unknown."""
    from ...evaluation.baselines import peer_available
    from ...evaluation.runner import method_factories

    methods = list(dict.fromkeys(args.method or ["followbus", "kalman"]))
    peers = [m for m in methods if m.startswith("peer:")]
    if peers and (reason := peer_available()):
        print(f"followbus: skipping {', '.join(peers)}: {reason} (make installs it; by hand: "
              "pip install -e '.[peers]' && pip install --no-deps -r requirements-peers.txt)", file=sys.stderr)
        notes.append(f"peer trackers {', '.join(peers)} skipped: {reason}")
        methods = [m for m in methods if m not in peers]
    return method_factories(methods, ablations=args.ablations, trace=_wants_trace(args),
                            detector=args.detector or DEFAULT_DETECTOR)


def _no_model(exc: Exception, detector: str) -> int:
    hint = ""
    if detector not in ("hog", "simulated"):
        hint = ("; or score without a model: --detector simulated (ground truth + noise)"
                if getattr(exc, "sequence", "").startswith("scene:")
                else "; or --detector hog (no model, far less accurate)")
    print(f"followbus: {exc}{hint}", file=sys.stderr)
    return 2


def _jitter_notes(args) -> list[str]:
    """The report's note on --jitter-px (none without it; the option is a finite number >= 0: tools/command.py)."""
    if args.jitter_px == 0:
        return []
    return [f"detections jittered: x, y, w, h + N(0, {args.jitter_px:g} px), score + N(0, {args.jitter_px / 200:g}), "
            f"seed {args.seed} (--jitter-px; the cache holds them as detected)."]


def cmd_eval(args) -> int:
    from ...vision.models import ModelError

    command = "followbus " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if args.argv is None else args.argv
    writable_directory(args.out, "--out")
    if getattr(args, "group", False):
        return _cmd_group(args, command)
    if getattr(args, "camera", False):
        print("followbus: --camera goes with --group", file=sys.stderr)
        return 2
    if not args.sequences:
        print("followbus: eval needs at least one SEQ (a sequence dir, scene:<name> or all), or --group",
              file=sys.stderr)
        return 2
    if args.graph_check:
        return _cmd_graph_check(args)
    args.detector = args.detector or DEFAULT_DETECTOR
    notes = _jitter_notes(args)
    try:
        seqs = expand_sequences(args.sequences)
        factories = _methods(args, notes)
    except (FileNotFoundError, ValueError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    methods, out = list(factories), Path(args.out)
    try:
        runs = run_campaign(seqs, factories, args.detector, out, seed=args.seed, max_frames=args.max_frames or 0,
                            jitter_px=args.jitter_px,
                            write_frames=lambda run: _write_frames(run, out, args, methods[0]))
    except ModelError as exc:
        return _no_model(exc, args.detector)
    _say_frame_files(args, out)
    md, js = write_report(runs, methods, out, command, _detector_label(args.detector),
                          notes + campaign_notes(runs, args.detector))
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
    inputs = graph.nodes["prediction"].inputs
    if "transform" in inputs and "egomotion" in graph.nodes:
        # The live rule for an optional input (not waited for before its first message) lets a cold egomotion's
        # first transforms miss frames 0-1 or only frame 0, whichever process ran first: the priors then differ
        # by ~3e-4 px. Lockstep waits for every transform (egomotion answers every frame, frame 0 included).
        graph = graph.with_node("prediction", inputs={**inputs, "transform": dataclasses.replace(
            inputs["transform"], optional=False)})
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
    from ...evaluation.runner import open_sequence

    is_scene = spec.startswith("scene:")
    detector = detector or ("simulated" if is_scene else DEFAULT_DETECTOR)
    if detector == "simulated" and not is_scene:
        raise ValueError(f"{spec}: simulated detections are reproduced by the graph for scenes only; "
                         "use --detector yolox|yolox640|hog")
    shipped = load_graph(REPO / "graph.yaml")
    seq = open_sequence(spec, seed=seed, max_frames=max_frames)
    n = seq.n_frames
    inproc, init_box = _run_in_process(spec, seq, _graph_detector(shipped, detector), "egomotion" in shipped.nodes,
                                       detector)
    if port is None:
        import socket

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
    source = spec if is_scene else str(Path(spec).resolve())
    tracks = _run_graph_once(source, port, init_box, n, max_in_flight, timeout_s, log_file, detector)
    mismatches = [k for k in range(n) if k in tracks and not _same_box(tracks[k], inproc[k])]
    missing = sum(k not in tracks for k in range(n))
    return {"compared": n - missing, "mismatches": len(mismatches), "missing": missing,
            "first_mismatch": mismatches[0] if mismatches else None,
            "graph": [tracks.get(k) for k in range(n)], "inproc": inproc, "detector": detector}


def _same_box(a: Any, b: Any) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.allclose(a, b, rtol=0.0, atol=1e-9))


def _graph_detector(graph: Any, detector: str) -> Any:
    """item -> (high, low) detections as the graph's detection node makes them (its thresholds, threads, model),
    switched to ``detector``; simulated: the node's defaults (noise 4 px, miss 0.05, fp 0.02, seed 0)."""
    from ...nodes.detection import detection_params, detector_from_params, split_detections
    from ...vision.detectors import SimulatedDetector

    node_params = detection_params(apply_detector_preset(dict(graph.nodes["detection"].params), detector))
    if detector == "simulated":
        sim = SimulatedDetector(seed=0)
        return lambda item: split_detections(node_params, sim.detect(item.bgr, item.truth))
    real = detector_from_params(node_params)
    return lambda item: split_detections(node_params, real.detect(item.bgr))


def _run_in_process(spec: str, seq: Any, detect: Any, has_egomotion: bool,
                    detector: str) -> tuple[list[Any], list[float]]:
    """The same frames, detector and initial box through the graph's nodes in-process (v_ego = 0): the boxes
    and the initial box. The prior is warped by camera motion only where the graph has an egomotion node."""
    from ...evaluation.graph_follower import GraphFollower

    follower = GraphFollower({"camera_motion_compensation": has_egomotion}, detector=detector)
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
    return inproc, init_box


def _run_graph_once(source: str, port: int, init_box: list[float], n: int, max_in_flight: int, timeout_s: float,
                    log_file: Path | None, detector: str) -> dict[int, Any]:
    """Launch the derived graph once (motor omitted) and collect Track boxes by frame_seq. Capture publishes
    frame 0 only once every consuming node is listening (nodes/capture.py), so the lockstep always starts."""
    from ...bus.graph import load_graph
    from ...bus.pubsub import Subscriber
    from ...bus.session import open_session
    from ...msgs.tracking import Track
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
