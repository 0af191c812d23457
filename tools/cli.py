"""The ``followbus`` command. Each subcommand's --help explains it with an example."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from . import __version__

EXIT_BAD_INPUT = 2

EPILOG = """\
examples:
  followbus demo                          the whole loop on a synthetic corridor scene, 20 s
  followbus launch graph.yaml             run the graph (one process per node)
  followbus launch graph.yaml --only capture,detection --duration 10
  followbus node detection                run one node of ./graph.yaml in this terminal
  followbus topics                        keys seen on the bus with their rates
  followbus echo fb/prediction/track      print decoded messages
  followbus hz fb/capture/frame           rate and latency of one key
  followbus nodes                         node health from liveliness tokens
  followbus bench bus                     bus latency/throughput vs raw zenoh
  followbus record -o recordings/run.mcap  record the bus (opens in Foxglove)
  followbus replay recordings/run.mcap --node reid --verify   regression replay of a node
  followbus eval all --ablations         score followers on ../shared/data (results/results.md)
  followbus bench pipeline                capture -> motor command latency through the graph
  followbus bench chaos                   kill, stall, load and spoof the graph: does it recover?
  followbus models                        where the ONNX models are found; checks their SHA-256

Every command that talks to the bus reads the zenoh settings of --graph (default ./graph.yaml);
--connect tcp/HOST:7447 joins another machine's graph as a client instead.
"""


def _graph_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--graph", default="graph.yaml", help="graph file (default: ./graph.yaml)")


def _connect_arg(p: argparse.ArgumentParser, timeout: bool = True) -> None:
    _graph_arg(p)
    p.add_argument("--connect", metavar="ENDPOINT", action="append",
                   help="join as a client via this endpoint (e.g. tcp/192.0.2.10:7447) instead of the graph's "
                        "zenoh settings; repeatable")
    if timeout:
        p.add_argument("--connect-timeout", type=float, metavar="S",
                       help="give up joining the graph after S seconds (default: the graph's connect_timeout_ms, "
                            "10 s; monitor: 3 s)")


def _viewer_args(p: argparse.ArgumentParser) -> None:
    """How a read-only viewer (monitor, foxglove) authenticates and which namespace it watches."""
    p.add_argument("--user", help="zenoh user name (transport/auth/usrpwd), e.g. monitor")
    p.add_argument("--password", help="zenoh password (default: $FOLLOWBUS_ZENOH_PASSWORD)")
    p.add_argument("--ca", metavar="FILE", help="CA certificate for a tls/ endpoint")
    p.add_argument("--namespace", help="bus namespace (default: the graph's, else fb)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="followbus", description="Perception and control of a person-following robot over Eclipse Zenoh.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"followbus {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("launch", help="launch a graph: one process per node",
                       description="Start every node of a graph as its own process, wait for their liveliness "
                                   "tokens, restart them by policy, and stop them all on Ctrl-C.",
                       epilog="example: followbus launch graph.yaml --only capture,detection --duration 30",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("graph", nargs="?", default="graph.yaml", help="graph file (default: ./graph.yaml)")
    p.add_argument("--only", help="comma-separated node names to launch (default: all)")
    p.add_argument("--host", help="launch only nodes whose host: is this name (or unset)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="stop S seconds after every node is up (start-up does not count)")
    p.add_argument("--record", metavar="FILE", help="also record the bus to this MCAP file")
    p.add_argument("--startup-timeout", type=float, default=30.0, metavar="S",
                   help="seconds to wait for every node's liveliness token (default 30)")
    p.add_argument("--grace", type=float, default=5.0, metavar="S",
                   help="seconds between SIGTERM and SIGKILL at shutdown (default 5)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a node parameter (YAML value), e.g. --set capture.source=camera:0; repeatable")

    p = sub.add_parser("demo", help="the whole loop on a synthetic scene, with a live status line and a summary",
                       description="Launch graph.yaml on a built-in synthetic scene (default: the corridor with a "
                                   "complete occlusion) for 20 s. Shows fps, target state, eta_k and the motor "
                                   "command live; ends with TSR@20px and CLE against the scene's exact ground truth "
                                   "and the capture-to-motor-command latency.",
                       epilog="example: followbus demo --scene lookalike --duration 10")
    _graph_arg(p)
    p.add_argument("--duration", type=float, default=20.0, metavar="S", help="seconds to run (default 20)")
    p.add_argument("--scene", default=None,
                   help="synthetic scene (corridor-occlusion, lookalike, wall-occlusion, night-puddles, sun-shadow, "
                        "ego-motion, lost-target); default: the graph's capture source")
    p.add_argument("--log", default=None, metavar="FILE",
                   help="where this run's node logs go (default: a new state/demo-YYYYmmdd-HHMMSS.log per run)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a node parameter, e.g. --set detection.backend=hog; repeatable")

    p = sub.add_parser("node", help="run one node of a graph in this process",
                       description="Run a single node (what the launcher runs for each node).",
                       epilog="example: followbus node prediction --graph graph.yaml")
    p.add_argument("name", help="node name in the graph")
    _graph_arg(p)
    p.add_argument("--clock", choices=("wall", "stamps"), default="wall",
                   help="node clock: wall time, or message stamps (lockstep replay)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a parameter of this node, e.g. --set detection.backend=hog; repeatable")

    p = sub.add_parser("check", help="validate a graph file and its capture source, and exit (status 2 on errors)",
                       description="Validate a graph file (keys, wiring, types, every node's params) and that its "
                                   "capture source opens (the file exists and decodes, the scene name is known, the "
                                   "camera device exists), without starting anything. Exit status 2 on an error.",
                       epilog="example: followbus check graph.yaml --set capture.source=recordings/run1.mcap")
    p.add_argument("graph", nargs="?", default="graph.yaml")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="check with this parameter override (as given to launch); repeatable")

    p = sub.add_parser("schema", help="print the JSON Schema of graph.yaml (editors validate and complete with it)",
                       description="Generate the JSON Schema (draft-07) of graph.yaml from the validator's own "
                                   "definitions and every followbus.nodes module's params. Editors using "
                                   "yaml-language-server (VS Code's YAML extension, yamlls) pick it up from the "
                                   "file's first line: # yaml-language-server: $schema=docs/graph.schema.json",
                       epilog="example: followbus schema -o docs/graph.schema.json")
    p.add_argument("-o", "--output", metavar="FILE", help="write to FILE instead of standard output")

    p = sub.add_parser("router", help="run a Zenoh router (multi-machine set-ups)",
                       description="A Zenoh session in router mode: robots and laptops connect to it.",
                       epilog="example: followbus router --listen tcp/127.0.0.1:7447")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (default tcp/127.0.0.1:7447); repeatable")
    p.add_argument("--duration", type=float, metavar="S")

    p = sub.add_parser("topics", help="list keys seen on the bus with their rates")
    _connect_arg(p)
    p.add_argument("--seconds", type=float, default=2.0, help="how long to listen (default 2)")

    p = sub.add_parser("echo", help="print decoded messages of a key",
                       epilog="example: followbus echo 'fb/prediction/track' -n 5")
    p.add_argument("key", help="key or key expression (e.g. fb/prediction/track, fb/**)")
    _connect_arg(p)
    p.add_argument("-n", "--count", type=int, help="stop after N messages")
    p.add_argument("--seconds", type=float, help="stop after S seconds")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="give up (exit status 1) when no message arrived within S seconds (default: wait)")

    p = sub.add_parser("hz", help="rate and latency of a key")
    p.add_argument("key")
    _connect_arg(p)
    p.add_argument("--seconds", type=float, help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="give up (exit status 1) when no message arrived within S seconds (default: wait)")

    p = sub.add_parser("nodes", help="node health from liveliness tokens and status messages")
    _connect_arg(p)
    p.add_argument("--seconds", type=float, default=1.5, help="how long to listen (default 1.5)")

    p = sub.add_parser("foxglove", help="serve the live bus to the Foxglove app (foxglove-sdk WebSocket server)",
                       description="Preview as foxglove.CompressedImage, target/gate/candidates as "
                                   "foxglove.ImageAnnotations, motor command and node status as JSON. Read-only.",
                       epilog="example: followbus foxglove --connect tcp/192.0.2.10:7447 --user monitor --port 8765")
    _connect_arg(p, timeout=False)
    _viewer_args(p)
    p.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765)")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--seconds", type=float, help="stop after S seconds")

    p = sub.add_parser("monitor", help="live, read-only dashboard of a running graph (terminal or --web)",
                       description="Join the robot's bus as a client and show node health, per-topic rates, the "
                                   "target, eta_k and the motor command; --web serves a page with the preview "
                                   "stream, plots and the health table. Reconnects by itself.",
                       epilog="example: followbus monitor --connect tcp/192.0.2.10:7447 --user monitor --web 8080")
    _connect_arg(p)
    _viewer_args(p)
    p.add_argument("--once", action="store_true", help="print one snapshot once every node is up (or --seconds) "
                                                       "and exit: 0 when all are up")
    p.add_argument("--seconds", type=float, help="stop after S seconds (--once: wait at most S, default 5)")
    p.add_argument("--web", type=int, nargs="?", const=8080, metavar="PORT",
                   help="serve the web view on PORT (default 8080) instead of the terminal dashboard")
    p.add_argument("--bind", default="127.0.0.1", help="address the web view listens on (default 127.0.0.1; "
                                                        "any other address requires a token)")
    p.add_argument("--web-token", metavar="TOKEN",
                   help="token the web view requires (also on loopback; default $FOLLOWBUS_WEB_TOKEN, else one "
                        "generated and printed when --bind is not loopback)")

    p = sub.add_parser("bench", help="benchmarks that write figures (see BENCHMARKS.md)")
    bench = p.add_subparsers(dest="bench", metavar="WHAT")
    b = bench.add_parser("bus", help="one-way latency and throughput through bus/ vs raw zenoh")
    b.add_argument("--count", type=int, default=200, help="messages per size (default 200)")
    b.add_argument("--rate", type=float, default=100.0, help="messages per second (default 100)")
    b.add_argument("--port", type=int, default=7461, help="loopback port to use (default 7461)")
    b.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    b = bench.add_parser("pipeline", help="end-to-end latency capture -> motor command through the launched graph",
                         description="Launch graph.yaml at 30 Hz on a synthetic scene and measure per-edge latency "
                                     "p50/p99 from the message headers, CPU per node and dropped frames.",
                         epilog="example: followbus bench pipeline --duration 20 --detector yolox")
    b.add_argument("--duration", type=float, default=20.0, metavar="S", help="seconds of measurement (default 20)")
    b.add_argument("--detector", default="yolox", choices=("yolox", "yolox640", "hog", "simulated"),
                   help="detection backend (default yolox = YOLOX-nano@416; falls back to hog without the model)")
    b.add_argument("--scene", default="corridor-occlusion", help="synthetic scene (default corridor-occlusion)")
    b.add_argument("--port", type=int, default=0, help="loopback port (default: a free one)")
    b.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    _add_bench_chaos_parser(bench)

    p = sub.add_parser("eval", help="score followers on sequences (paper metrics, baselines, ablations, plots)",
                       description="Run followbus, the Kalman baseline, ablations and peer trackers in-process "
                                   "over SOT/MOT sequences and synthetic scenes on the same cached detections; "
                                   "write results.md, results.json and PNG plots. Peers (Roboflow trackers: "
                                   "ByteTrack, OC-SORT, BoT-SORT) follow the id of the track overlapping the "
                                   "first ground-truth box; on MOT sequences they also get MOTA/IDF1/HOTA of "
                                   "their whole output. `make` installs them (requirements-peers.txt).",
                       epilog="examples:\n  followbus eval all --ablations --detector yolox640\n"
                              "  followbus eval ../shared/data/sot/otb-jogging scene:wall-occlusion "
                              "--method followbus\n"
                              "  followbus eval ../shared/data/mot/tud-campus --method followbus "
                              "--method peer:bytetrack --method peer:botsort\n"
                              "  followbus eval scene:wall-occlusion --graph-check\n"
                              "  followbus eval --group --out results/group\n"
                              "  followbus eval --group --camera --out results/group\n"
                              "  followbus eval ../shared/data/sot/otb-crossing --graph-check --detector yolox",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequences", nargs="*", metavar="SEQ",
                   help="sequence dir (sot/<name>, mot/<name>), scene:<name>, or 'all' (every sequence of the data)")
    p.add_argument("--group", action="store_true",
                   help="instead: seed 004's group-tracking benchmark on simulated squads (RMSE, OE, Lat-STD of "
                        "ME-CGT-UGV and its comparison methods per scenario; group.md, group.json, plots)")
    p.add_argument("--camera", action="store_true",
                   help="with --group: the same methods on the camera group sequences (SEQ dirs, default "
                        "sot/uav-group* and every mot/ clip): image-plane group-centre error; group_camera.md/json")
    p.add_argument("--method", action="append", metavar="M",
                   help="followbus | kalman | peer:bytetrack|ocsort|botsort; repeatable (default followbus + kalman)")
    p.add_argument("--ablations", action="store_true", help="also run the paper's Table 6 ablations of followbus")
    p.add_argument("--detector", default=None, choices=("yolox", "yolox640", "hog", "simulated"),
                   help="detections for every method (default yolox = YOLOX-nano@416; with --graph-check: "
                        "simulated for scenes, yolox for sequence dirs)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output directory (default results/)")
    p.add_argument("--max-frames", type=int, default=0, metavar="N", help="only the first N frames per sequence")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated detector (default 0)")
    p.add_argument("--graph-check", action="store_true",
                   help="instead: run the scene(s) through the launched graph and in-process, require identical boxes")
    p.set_defaults(argv=None)
    _add_recording_parsers(sub)
    from .models_cmd import add_parser as add_models_parser

    add_models_parser(sub)
    return parser


def _add_bench_chaos_parser(bench) -> None:
    """``bench chaos``: the fault-injection suite (tools/bench/chaos.py; RELIABILITY.md holds its figures)."""
    b = bench.add_parser(
        "chaos", help="fault injection: does the live loop always recover? (RELIABILITY.md)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Launch graph.yaml on a private loopback port (scene looping at 30 Hz, simulated detector)\n"
                    "and try one fault at a time. After each fault it requires:\n"
                    "  - 0 unsafe motor commands (a non-finite field, a speed beyond the motor's limits);\n"
                    "  - a zero command <= 200 ms after the last track whenever tracks stop;\n"
                    "  - the robot following again (TRACKING) within --recovery-bound of the fault's end (node\n"
                    "    back up, or injection over; time the scene itself hides the target is added), then\n"
                    "    tracking most of the next --hold seconds;\n"
                    "  - under load: p99 capture->command <= 250 ms, and >= 50 % of frames answered (burners).\n"
                    "A fault the loop does not survive is followed by a fresh launch of the graph.\n\n"
                    "faults (--faults, comma-separated; 'all' is the default, 'ci' the tests' subset):\n"
                    "  kill-capture (capture-restart), kill-detection, kill-prediction, kill-reid, kill-template,\n"
                    "  kill-motor          SIGKILL the node; the launcher restarts it\n"
                    "  stop-prediction-2s  SIGSTOP prediction for 2 s\n"
                    "  burners             --burners processes spinning a CPU for --load-seconds\n"
                    "  detector-delay-80ms detection takes 80 ms a frame (simulated sim_delay_ms; own launch)\n"
                    "  future-stamp-track  a TRACKING track stamped +1 h, then SIGKILL prediction\n"
                    "  future-seq-frame, future-seq-detections\n"
                    "                      one message with frame_seq +10**9, then a 0.3 s camera stall\n"
                    "  nan-measurement     an accepted TRACKING measurement with a NaN box\n"
                    "  malformed           garbage/wrong-type/truncated/wrong-field payloads on every input key\n"
                    "  flood               300 valid frames as fast as possible on capture/frame\n"
                    "  kill-recorder       SIGKILL the recorder (only with --record)\n"
                    "Exit status 0 when every fault was survived, 1 otherwise.",
        epilog="examples:\n  followbus bench chaos                                   every fault, the table\n"
               "  followbus bench chaos --faults kill-reid,nan-measurement --repeat 3\n"
               "  followbus bench chaos --faults burners --burners 2 --load-seconds 20 --json chaos.json\n"
               "  followbus bench chaos --record --faults kill-recorder")
    b.add_argument("--faults", metavar="NAME,...", help="faults to try, in order (default: all)")
    b.add_argument("--detector", default="simulated", choices=("simulated", "yolox416"),
                   help="detection backend (default simulated: deterministic, needs no model)")
    b.add_argument("--scene", default="corridor-occlusion", help="synthetic scene (default corridor-occlusion)")
    b.add_argument("--burners", type=int, default=2, metavar="N", help="CPU burners of the burners fault (default 2)")
    b.add_argument("--load-seconds", type=float, default=10.0, metavar="S",
                   help="how long burners and the detector delay last (default 10)")
    b.add_argument("--repeat", type=int, default=1, metavar="N", help="run the fault list N times (default 1)")
    b.add_argument("--record", action="store_true", help="run a recorder with the graph (adds kill-recorder)")
    b.add_argument("--recovery-bound", type=float, default=2.0, metavar="S",
                   help="seconds from the fault's end to following again (default 2)")
    b.add_argument("--hold", type=float, default=3.0, metavar="S",
                   help="after recovery, seconds that must be tracked most of the time (default 3)")
    b.add_argument("--malformed-per-key", type=int, default=10_000, metavar="N",
                   help="malformed payloads per input key (default 10000)")
    b.add_argument("--port", type=int, default=0, help="loopback port (default: a free one)")
    b.add_argument("--log", default="state/chaos.log", help="where node logs go (default state/chaos.log)")
    b.add_argument("--json", metavar="FILE", help="also write every run's checks and figures as JSON")


def _add_recording_parsers(sub) -> None:
    """record, play, replay, info, recover (MCAP recordings)."""
    fmt = argparse.RawDescriptionHelpFormatter
    p = sub.add_parser(
        "record", help="record the bus to an MCAP file that opens in Foxglove", formatter_class=fmt,
        description="Join the bus as a client and store every message losslessly (its msgpack bytes, one channel per "
                    "key) in an MCAP file, plus Foxglove views: frames as foxglove.CompressedImage, detections, the "
                    "Kalman gate and the target as foxglove.ImageAnnotations. Ctrl-C/SIGTERM finalise the file; a "
                    "killed recorder leaves one that `followbus recover` repairs. A write error (full disk) ends it at "
                    "once: the file is finalised at its last complete chunk, one line says what was lost, exit "
                    "status 1. Ends with received/written/dropped counts and the messages lost upstream "
                    "(header.seq gaps).",
        epilog="examples:\n  followbus record -o recordings/run1.mcap --duration 60\n"
               "  followbus record --topics 'fb/capture/**' 'fb/prediction/**' --status")
    p.add_argument("-o", "--output", metavar="FILE", help="output file (default recordings/<graph>-<time>.mcap)")
    p.add_argument("--topics", nargs="+", metavar="PATTERN", help="key expressions to record (default <ns>/**)")
    p.add_argument("--exclude", action="append", metavar="PATTERN",
                   help="leave out keys matching this key expression, e.g. 'fb/capture/frame' (raw frames; the "
                        "JPEG preview stays); repeatable")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--status", action="store_true", help="also record the @status keys (node statistics)")
    p.add_argument("--compression", choices=("lz4", "zstd", "none"), default="lz4",
                   help="chunk compression (default lz4: keeps up with 720p bgr8 at 30 Hz)")
    p.add_argument("--chunk-mb", type=float, default=4.0, metavar="MB", help="close a chunk at this size (default 4)")
    p.add_argument("--chunk-seconds", type=float, default=1.0, metavar="S",
                   help="close and flush a chunk at least this often: all a SIGKILL can lose (default 1)")
    p.add_argument("--jpeg-quality", type=int, default=80, metavar="Q",
                   help="JPEG quality of the Foxglove copies of bgr8 frames (default 80)")
    p.add_argument("--no-foxglove", action="store_true", help="store the bus messages only")
    p.add_argument("--max-queue-mb", type=float, default=256.0, metavar="MB",
                   help="memory the writer queue may hold before the recorder drops, counted per key (default 256)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="parameter overrides the graph runs with (as given to launch), stored in the metadata")
    _connect_arg(p)

    p = sub.add_parser(
        "play", help="publish a recording's bus messages again", formatter_class=fmt,
        description="Publish the stored bus messages (their exact bytes) on their keys, or remapped ones, paced by "
                    "their stamps. In a terminal: space pauses/resumes, s steps one message while paused, q quits.",
        epilog="examples:\n  followbus play recordings/run1.mcap --topics 'fb/capture/**' --rate 0.5\n"
               "  followbus play recordings/run1.mcap --remap fb=fb2 --fast --loop")
    p.add_argument("file", help="MCAP recording")
    p.add_argument("--topics", nargs="+", metavar="PATTERN", help="only keys matching these key expressions")
    p.add_argument("--remap", action="append", metavar="FROM=TO", help="key prefix remap, e.g. fb=fb2; repeatable")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=float, default=1.0, metavar="R", help="speed factor (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as the bus takes them")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--start-paused", action="store_true", help="wait for space (or s) before the first message")
    p.add_argument("--status", action="store_true", help="also publish recorded @status messages")
    _connect_arg(p)

    p = sub.add_parser(
        "replay", help="replay a recording into one node or a few (regression test with --verify)",
        formatter_class=fmt,
        description="Host the node in this process (its spec and params as recorded, --param overrides) with its "
                    "clock driven by message stamps and feed it its recorded inputs in the order they were "
                    "published, with what the live run did (skipped frames, feedback joined). --isolated runs the "
                    "deployed node as a process in a private graph over Zenoh instead. --verify diffs its outputs "
                    "with the recorded ones (exact for integers and strings, --rtol/--atol for floats) and exits 1 "
                    "on a difference.",
        epilog="examples:\n  followbus replay recordings/run1.mcap --node reid --verify\n"
               "  followbus replay recordings/run1.mcap --node reid,prediction --verify\n"
               "  followbus replay recordings/run1.mcap --node reid --verify --isolated\n"
               "  followbus replay recordings/run1.mcap --node prediction --param gate_chi2=5.99 --report out.json")
    p.add_argument("file", help="MCAP recording")
    p.add_argument("--node", required=True,
                   help="node to replay; several, comma-separated, run together (their edges in-process)")
    p.add_argument("--isolated", action="store_true",
                   help="run the node as its own process over Zenoh (the deployed node), not in-process")
    p.add_argument("--graph", default=None, help="graph file (default: the graph.yaml stored in the recording)")
    p.add_argument("--param", action="append", metavar="KEY=VALUE",
                   help="override a parameter (YAML value); with several nodes NODE.KEY=VALUE")
    p.add_argument("--verify", action="store_true", help="compare outputs with the recording; exit 1 on a mismatch")
    p.add_argument("--report", metavar="FILE", help="write a JSON summary")
    p.add_argument("--rtol", type=float, default=1e-6, help="relative tolerance for floats (default 1e-6)")
    p.add_argument("--atol", type=float, default=1e-6, help="absolute tolerance for floats (default 1e-6)")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="--isolated: seconds to wait for a frame's outputs (default 5)")
    p.add_argument("--startup-timeout", type=float, default=60.0, metavar="S",
                   help="--isolated: seconds to wait for the node to come up (default 60)")
    p.add_argument("--max-frames", type=int, default=0, metavar="N", help="only the first N frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("info", help="topics, counts, rates, duration and metadata of a recording",
                       epilog="example: followbus info recordings/run1.mcap")
    p.add_argument("file", help="MCAP recording")

    p = sub.add_parser("recover", help="rewrite a killed recorder's file into a valid MCAP",
                       description="Copy every complete chunk and metadata record of a truncated MCAP file (a "
                                   "recorder killed with SIGKILL, a full disk) into a new, finalised file.",
                       epilog="example: followbus recover recordings/run1.mcap -o recordings/run1-fixed.mcap")
    p.add_argument("file", help="truncated MCAP file")
    p.add_argument("-o", "--output", metavar="FILE", help="output (default: FILE with .recovered.mcap)")
    p.add_argument("--compression", choices=("lz4", "zstd", "none"), help="default: the input's")


def _dispatch_recording(args) -> int:
    cmd = args.command
    if cmd == "record":
        from ..bus.graph import apply_overrides
        from .recording.record import cmd_record

        graph = _load_graph(args.graph) if Path(args.graph).exists() else None
        if graph is not None:
            apply_overrides(graph, args.overrides)
        return cmd_record(args, _settings(args), graph)
    if cmd == "play":
        from .recording.play import cmd_play

        return cmd_play(args, _settings(args))
    if cmd == "replay":
        from .recording.replay import cmd_replay

        return cmd_replay(args)
    if cmd == "info":
        from .recording.mcap_io import cmd_info

        return cmd_info(args)
    from .recording.mcap_io import cmd_recover

    return cmd_recover(args)


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose < 0 else (logging.INFO if verbose == 0 else logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


def _load_graph(path: str):
    from ..bus.graph import load_graph

    return load_graph(path)


def _settings(args):
    """Zenoh settings for tools: --connect wins, else the graph's, joined as a client of its endpoint."""
    from ..bus.session import ZenohSettings

    if getattr(args, "connect", None):
        settings = ZenohSettings(mode="client", listen=[], connect=args.connect)
    elif Path(args.graph).exists():
        settings = _load_graph(args.graph).zenoh.as_client()
    else:
        settings = ZenohSettings().as_client()
    if getattr(args, "connect_timeout", None) is not None:
        settings.connect_timeout_ms = max(1, round(args.connect_timeout * 1000))
    return settings


def _namespace(args) -> str:
    if Path(getattr(args, "graph", "graph.yaml")).exists():
        return _load_graph(args.graph).namespace
    return "fb"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    if args.command is None:
        parser.print_help()
        return 0
    from ..bus.graph import GraphError
    from ..vision.models import ModelError
    from .connect import BusUnreachable, explain_connect_failure, is_connect_failure
    from .errors import UsageError

    # A user's mistake (or a graph that is not running) is one line on stderr and exit status 2; a failure
    # found while running (a node crashed, nothing arrived, a replay differs) is reported by the command: 1.
    try:
        return dispatch(args)
    except (GraphError, UsageError, BusUnreachable) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ModelError as exc:  # a missing or corrupt model (DetectorUnavailable too): the message says what to do
        print(f"followbus: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:
        if not is_connect_failure(exc) or not hasattr(args, "connect"):
            raise
        # A command that opened its session itself (play, record, ...): the same line as topics or echo.
        print(f"followbus: {explain_connect_failure(_settings(args))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


def _validate(graph, overrides: list[str] | None = None, *, opened: set[str] | None = None,
              labels: dict[str, str] | None = None, nodes: list[str] | None = None) -> None:
    """Validate every node (or ``nodes``) against its class, and check what the nodes in ``opened`` (default:
    all) would open (the capture source: Capture.check_params), before anything starts. A problem with a value given on
    the command line names the option (``labels``: node.param -> how it was given, else its --set); one from
    the file names its line (GraphError)."""
    from ..bus.node import ParamError, validate_node
    from .errors import UsageError

    given = {item.partition("=")[0].strip(): f"--set {item}" for item in overrides or []}
    given.update(labels or {})
    for name in nodes if nodes is not None else list(graph.nodes):
        spec = graph.nodes[name]
        try:
            cls, params = validate_node(graph, spec)
            check = getattr(cls, "check_params", None)
            if check is not None and (opened is None or name in opened):
                check(params)
        except Exception as exc:
            param = exc if isinstance(exc, ParamError) else exc.__cause__
            key = f"{name}.{param.key}" if isinstance(param, ParamError) else ""
            if key in given:
                raise UsageError(f"{given[key]}: {param}") from exc
            if isinstance(exc, ParamError):
                raise graph.error(spec.param_lines.get(exc.key, spec.line), f"node {name!r}: {exc}") from exc
            raise


def dispatch(args) -> int:
    cmd = args.command
    if cmd == "schema":
        return cmd_schema(args)
    if cmd == "check":
        from ..bus.graph import apply_overrides

        graph = _load_graph(args.graph)
        apply_overrides(graph, args.overrides)
        _validate(graph, args.overrides)
        print(f"{args.graph}: ok ({len(graph.nodes)} nodes)")
        return 0
    if cmd == "node":
        from ..bus.graph import apply_overrides
        from ..bus.node import run_node

        graph = _load_graph(args.graph)
        apply_overrides(graph, args.overrides)
        if args.name in graph.nodes:  # (an unknown name: run_node says which nodes there are)
            _validate(graph, args.overrides, opened={args.name}, nodes=[args.name])
        return run_node(graph, args.name, clock=args.clock)
    if cmd == "demo":
        return cmd_demo(args)
    if cmd == "launch":
        return cmd_launch(args)
    if cmd in ("record", "play", "replay", "info", "recover"):
        return _dispatch_recording(args)
    if cmd == "router":
        from .live.introspect import run_router

        return run_router(args.listen or ["tcp/127.0.0.1:7447"], args.duration)
    if cmd == "foxglove":
        from .live.foxglove_bridge import run_foxglove

        return run_foxglove(args)
    if cmd == "monitor":
        from .live.monitor import run_monitor

        return run_monitor(args)
    if cmd in ("topics", "echo", "hz", "nodes"):
        from .live import introspect

        return getattr(introspect, f"cmd_{cmd}")(args, _settings(args), _namespace(args))
    if cmd == "bench" and args.bench == "bus":
        from .bench_bus import run_bench_bus

        return run_bench_bus(args)
    if cmd == "bench" and args.bench == "pipeline":
        from .bench.pipeline import run_bench_pipeline

        return run_bench_pipeline(args)
    if cmd == "bench" and args.bench == "chaos":
        from .bench.chaos import run_bench_chaos

        return run_bench_chaos(args)
    if cmd == "eval":
        from .bench.eval import cmd_eval

        return cmd_eval(args)
    if cmd == "models":
        from .models_cmd import cmd_models

        return cmd_models(args)
    raise AssertionError(f"unhandled command {cmd!r}")


def cmd_schema(args) -> int:
    from ..bus.graph_schema import schema_text

    text = schema_text("followbus.nodes")
    if not args.output:
        sys.stdout.write(text)
        return 0
    try:
        Path(args.output).write_text(text)
    except OSError as exc:
        print(f"followbus: cannot write {args.output}: {exc.strerror}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"wrote {args.output}")
    return 0


def cmd_demo(args) -> int:
    from ..bus.graph import apply_overrides
    from .demo import run_demo

    graph = _load_graph(args.graph)
    overrides = list(args.overrides)
    if args.scene:
        overrides.insert(0, f"capture.source=scene:{args.scene}")
    apply_overrides(graph, overrides)
    _validate(graph, overrides, labels={"capture.source": f"--scene {args.scene}"} if args.scene else None)
    init = _first_truth_box(graph)
    if init is not None and "init_box" not in graph.nodes["reid"].params:
        # A follower is told whom to follow: on recorded sequences that is the first annotated box.
        overrides.append(f"reid.init_box=[{', '.join(f'{v:.2f}' for v in init)}]")
        apply_overrides(graph, overrides[-1:])
        print(f"target: the first ground-truth box {tuple(round(v, 1) for v in init)}")
    return run_demo(graph, args.duration, Path(args.log) if args.log else None, overrides)


def _first_truth_box(graph) -> tuple[float, ...] | None:
    """The ground-truth box of frame 0 when the capture source is an annotated image folder."""
    capture = graph.nodes.get("capture")
    source = str(capture.params.get("source", "")) if capture else ""
    if not source or source.startswith(("scene:", "camera:")) or not Path(source).is_dir():
        return None
    from ..vision.sources import ImageFolderSource

    folder = ImageFolderSource(Path(source))
    if not folder.has_ground_truth:
        return None
    box, _ = folder.ground_truth(0)
    return None if box is None else tuple(float(v) for v in box)


def cmd_launch(args) -> int:
    from ..bus.graph import apply_overrides
    from ..bus.node import RECORDER_NAME
    from .launch import Launcher, install_stop_signals

    graph = _load_graph(args.graph)
    apply_overrides(graph, args.overrides)
    only = [n.strip() for n in args.only.split(",")] if args.only else None
    # Every node is validated; what a node would open (the capture source) only for the nodes started here.
    _validate(graph, args.overrides, opened={n for n, spec in graph.nodes.items() if (not only or n in only)
                                             and (args.host is None or spec.host in (None, args.host))})
    extra = []
    if args.record:
        extra.append((RECORDER_NAME, [sys.executable, "-m", "followbus.tools.cli", "record", "--graph", args.graph,
                                   "-o", args.record, *(f"--set={o}" for o in args.overrides)]))
    try:
        launcher = Launcher(graph, only=only, host=args.host, startup_timeout_s=args.startup_timeout,
                            grace_s=args.grace, extra_children=extra, overrides=args.overrides,
                            watch_outputs=args.duration is not None)
    except ValueError as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    install_stop_signals(launcher)
    logging.getLogger("followbus.launch").setLevel(logging.INFO)
    status = launcher.run(args.duration)
    problems = launcher.problems() if args.duration is not None else []
    if problems:
        # A scripted run (CI, a smoke test) must not pass with a node that crash-looped or stayed silent.
        print(f"followbus launch: {'; '.join(problems)}", file=sys.stderr, flush=True)
        return status or 1
    return status


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
