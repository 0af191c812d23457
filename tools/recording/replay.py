"""``followbus replay FILE --node NAME``: a recording fed into one node (or a few), outputs diffed.

The node is the graph's own class, hosted in this process by the in-process runtime (bus/inproc.py, the
same NodeHost as on the bus) on a clock that follows the message stamps; its spec is the recorded one
(graph.yaml text and effective params from the file's metadata, or ``--graph``), params overridden by
``--param``. The recording is read once, in the order its messages were published; each input of the
node is handed over and delivered before the next, so the node sees its inputs in the live order and
handles each as soon as it can. What the live run decided under time pressure is given to the node as
replay hints (bus.schemas.ReplayHint) before the frame they concern: frames it skipped, the feedback each
set joined, choices it noted; the runtime holds back a feedback message the live node received late.
``--node reid,prediction`` runs several nodes together, the edges between them in-process.

``--isolated`` runs the node as the deployed process instead (``followbus node NAME --clock stamps`` in a
private graph: private namespace, private loopback port) and feeds it over Zenoh, with the same order and
hints. When to send the next input is not guessed: the in-process run of the same node, fed alongside,
says how many outputs the process must have published by then (it runs the same code).

``--verify`` diffs each produced output against the recorded one field by field: exact for integers,
strings, booleans and integer arrays, ``--rtol``/``--atol`` for floats; header.seq, header.source,
header.pub_ns and the measured times a message type declares (``MEASURED``) are ignored, and so are a
timer's outputs of no frame (live they tick on the wall clock). A recording thus becomes a regression test.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

from ...bus.graph import GraphError, parse_assignments
from ...bus.recording import RecordingError
from ...replay.diff import Tolerance
from ...replay.engine import RESYNC_FRAMES, RESYNC_MAX_FRAMES, RESYNC_SETTLE_FRAMES, Replayer
from ...replay.plan import ReplayOptions, ReplayReport

# --- command ---------------------------------------------------------------------------------------

def _print_summary(report: ReplayReport, verify: bool) -> None:
    """What `followbus replay` says after a run, in this order: timing, output counts, notes, first
    differences, verdict."""
    _print_timing(report)
    _print_output_counts(report)
    _print_notes(report)
    _print_first_differences(report)
    _print_verdict(report, verify)
    sys.stdout.flush()


def _print_timing(report: ReplayReport) -> None:
    """How much was replayed, how fast, and where the time went."""
    print(f"replayed {report.frames} frames ({report.inputs_sent} input messages) into {report.node} "
          f"({report.mode}) in {report.wall_s:.2f} s: {report.speed_x:.1f}x real time over "
          f"{report.recorded_span_s:.2f} s recorded")
    if report.mode == "in-process" and report.wall_s > 0:
        node_s = report.handler_s + report.decode_s
        print(f"node time: {report.handler_s:.2f} s handlers + {report.decode_s:.2f} s decoding = {node_s:.2f} s; "
              f"replay time {report.wall_s / node_s if node_s else math.inf:.2f}x that "
              f"(the rest: reading the recording, ordering, diffing)")
    elif report.startup_s:
        print(f"node process up in {report.startup_s:.2f} s (not counted above)")


def _print_output_counts(report: ReplayReport) -> None:
    print(f"outputs: {report.outputs_expected} recorded, {report.outputs_received} produced, "
          f"{report.outputs_compared} compared, {report.matched} identical, {report.mismatch_count} differing, "
          f"{len(report.missing)} missing, {len(report.extra)} extra"
          + (f"; {len(report.timeouts)} frame timeouts" if report.mode == "isolated" else ""))


def _print_notes(report: ReplayReport) -> None:
    """Recorded outputs not compared, or differing for a known reason: each said with why."""
    if report.timer_outputs:
        print(f"not compared: {report.timer_outputs} recorded outputs of the node's timer (no frame: odometry, "
              "watchdog stops); live it ticks on the wall clock, a replay on the message stamps")
    if report.unverifiable:
        print(f"not verifiable: {report.unverifiable} recorded outputs of frames whose inputs are not all in "
              "the recording (the recorder joined late, dropped them, or stopped before them); "
              "the node cannot produce them")
    if report.stand_ins:
        print(f"stood in: {report.stand_ins} recorded outputs handed to the next replayed node for frames a node "
              "could not handle (an input missing from the recording)")
    if report.after_gap:
        print(f"re-converging: {report.after_gap} outputs differed after a frame the recording lacks inputs of, "
              f"within {RESYNC_FRAMES} frames, or until they matched on {RESYNC_SETTLE_FRAMES} in a row (at most "
              f"{RESYNC_MAX_FRAMES}): the node's state missed that frame; not failures")
    if report.hints:
        print(f"live fallbacks reproduced: {report.hints} frames skipped or joined older feedback live "
              "(a late feedback, a skipped backlog), and were replayed the same way")
    if report.recording_first_frame:
        print(f"note: the recording starts at frame {report.recording_first_frame} of the run (recorded mid-run): "
              "the node starts without the state it had built before (template, track state, filter), so its first "
              "outputs can differ until that state converges; `followbus launch --record` records from frame 0")


def _print_first_differences(report: ReplayReport) -> None:
    """The first mismatch, missing and extra output (where to start looking), and the run's error."""
    if report.mismatches:
        first = min(report.mismatches, key=lambda m: (m["frame_seq"], m["key"], m["index"]))
        print(f"first mismatch: frame {first['frame_seq']}, key {first['key']} (#{first['index']}), field "
              f"{first['field']}: recorded {first['recorded']!r}, replayed {first['replayed']!r}")
    if report.missing:
        m = report.missing[0]
        print(f"first missing output: frame {m['frame_seq']}, key {m['key']}")
    if report.extra:
        m = report.extra[0]
        print(f"first extra output: frame {m['frame_seq']}, key {m['key']}")
    if report.error:
        print(f"error: {report.error}")


def _print_verdict(report: ReplayReport, verify: bool) -> None:
    if verify and not report.outputs_compared and not report.error:
        print(f"verify: FAILED: nothing compared (the recording holds no output of {report.node} for the frames "
              "replayed; record the node's outputs too, e.g. `followbus launch --record`)")
    elif verify:
        print("verify: " + ("OK" if report.ok(True) else "FAILED"))


def cmd_replay(args) -> int:
    nodes = [n.strip() for n in args.node.split(",") if n.strip()]
    try:
        params = parse_assignments(args.param or [], flag="--param", nodes=nodes,
                                   default_node=nodes[0] if len(nodes) == 1 else None)
    except GraphError as exc:  # a command-line mistake: said as typed, no file
        print(f"followbus: {exc.message}", file=sys.stderr)
        return 2
    try:
        options = ReplayOptions(
            nodes=nodes, graph_path=args.graph, params=params, verify=args.verify, isolated=args.isolated,
            tolerance=Tolerance(args.rtol, args.atol), frame_timeout_s=args.timeout,
            startup_timeout_s=args.startup_timeout, max_frames=args.max_frames or 0, progress=not args.no_progress,
            on_corrupt=args.on_corrupt)
        if not options.nodes:
            raise ValueError("--node: name a node (or several, comma-separated)")
        replayer = Replayer(Path(args.file), options)
    except (RecordingError, ValueError, GraphError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    report = replayer.run()
    _print_summary(report, args.verify)
    if args.report:
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        Path(args.report).write_text(json.dumps(dataclasses.asdict(report), indent=1, default=str))
    return 0 if report.ok(args.verify) else 1
