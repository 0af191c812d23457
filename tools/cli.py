"""The ``followbus`` command. Each subcommand's --help explains it with an example."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from followbus import __version__

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
  followbus eval all --ablations         score followers on ../shared/data (results/results.md)
  followbus bench pipeline                capture -> motor command latency through the graph

Every command that talks to the bus reads the zenoh settings of --graph (default ./graph.yaml);
--connect tcp/HOST:7447 joins another machine's graph as a client instead.
"""


def _graph_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--graph", default="graph.yaml", help="graph file (default: ./graph.yaml)")


def _connect_arg(p: argparse.ArgumentParser) -> None:
    _graph_arg(p)
    p.add_argument("--connect", metavar="ENDPOINT", action="append",
                   help="join as a client via this endpoint (e.g. tcp/192.0.2.10:7447) instead of the graph's "
                        "zenoh settings; repeatable")


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
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
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
    p.add_argument("--log", default="state/demo.log", help="where node logs go (default state/demo.log)")
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

    p = sub.add_parser("check", help="validate a graph file and exit (status 2 on errors)")
    p.add_argument("graph", nargs="?", default="graph.yaml")

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

    p = sub.add_parser("hz", help="rate and latency of a key")
    p.add_argument("key")
    _connect_arg(p)
    p.add_argument("--seconds", type=float, help="stop after S seconds (default: until Ctrl-C)")

    p = sub.add_parser("nodes", help="node health from liveliness tokens and status messages")
    _connect_arg(p)
    p.add_argument("--seconds", type=float, default=1.5, help="how long to listen (default 1.5)")

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

    p = sub.add_parser("eval", help="score followers on sequences (paper metrics, baselines, ablations, plots)",
                       description="Run followbus, the Kalman baseline, ablations and optional peer trackers "
                                   "in-process over SOT/MOT sequences and synthetic scenes on the same cached "
                                   "detections; write results.md, results.json and PNG plots.",
                       epilog="examples:\n  followbus eval all --ablations --detector yolox640\n"
                              "  followbus eval ../shared/data/sot/otb-jogging scene:wall-occlusion --method followbus\n"
                              "  followbus eval scene:wall-occlusion --graph-check",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sequences", nargs="+", metavar="SEQ",
                   help="sequence dir (sot/<name>, mot/<name>), scene:<name>, or 'all' (every sequence of the data)")
    p.add_argument("--method", action="append", metavar="M",
                   help="followbus | kalman | peer:bytetrack|ocsort|botsort; repeatable (default followbus + kalman)")
    p.add_argument("--ablations", action="store_true", help="also run the paper's Table 6 ablations of followbus")
    p.add_argument("--detector", default="yolox", choices=("yolox", "yolox640", "hog", "simulated"),
                   help="detections for every method (default yolox = YOLOX-nano@416)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output directory (default results/)")
    p.add_argument("--max-frames", type=int, default=0, metavar="N", help="only the first N frames per sequence")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated detector (default 0)")
    p.add_argument("--graph-check", action="store_true",
                   help="instead: run the scene(s) through the launched graph and in-process, require identical boxes")
    p.set_defaults(argv=None)
    return parser


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose < 0 else (logging.INFO if verbose == 0 else logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


def _load_graph(path: str):
    from followbus.bus.graph import load_graph

    return load_graph(path)


def _settings(args):
    """Zenoh settings for tools: --connect wins, else the graph's, joined as a client of its endpoint."""
    from followbus.bus.session import ZenohSettings

    if getattr(args, "connect", None):
        return ZenohSettings(mode="client", listen=[], connect=args.connect)
    if Path(args.graph).exists():
        graph = _load_graph(args.graph)
        return graph.zenoh.as_client()
    return ZenohSettings().as_client()


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
    from followbus.bus.graph import GraphError

    try:
        return dispatch(args)
    except GraphError as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


def dispatch(args) -> int:
    cmd = args.command
    if cmd == "check":
        from followbus.bus.node import validate_node

        graph = _load_graph(args.graph)
        for spec in graph.nodes.values():
            validate_node(graph, spec)
        print(f"{args.graph}: ok ({len(graph.nodes)} nodes)")
        return 0
    if cmd == "node":
        from followbus.bus.graph import apply_overrides
        from followbus.bus.node import run_node

        graph = _load_graph(args.graph)
        apply_overrides(graph, args.overrides)
        return run_node(graph, args.name, clock=args.clock)
    if cmd == "demo":
        return cmd_demo(args)
    if cmd == "launch":
        return cmd_launch(args)
    if cmd == "router":
        from followbus.tools.introspect import run_router

        return run_router(args.listen or ["tcp/127.0.0.1:7447"], args.duration)
    if cmd in ("topics", "echo", "hz", "nodes"):
        from followbus.tools import introspect

        return getattr(introspect, f"cmd_{cmd}")(args, _settings(args), _namespace(args))
    if cmd == "bench" and args.bench == "bus":
        from followbus.tools.bench_bus import run_bench_bus

        return run_bench_bus(args)
    if cmd == "bench" and args.bench == "pipeline":
        from followbus.tools.bench_pipeline import run_bench_pipeline

        return run_bench_pipeline(args)
    if cmd == "eval":
        from followbus.tools.eval import cmd_eval

        return cmd_eval(args)
    raise AssertionError(f"unhandled command {cmd!r}")


def cmd_demo(args) -> int:
    from followbus.bus.graph import apply_overrides
    from followbus.bus.node import validate_node
    from followbus.tools.demo import run_demo

    graph = _load_graph(args.graph)
    overrides = list(args.overrides)
    if args.scene:
        overrides.insert(0, f"capture.source=scene:{args.scene}")
    apply_overrides(graph, overrides)
    init = _first_truth_box(graph)
    if init is not None and "init_box" not in graph.nodes["reid"].params:
        # A follower is told whom to follow: on recorded sequences that is the first annotated box.
        overrides.append(f"reid.init_box=[{', '.join(f'{v:.2f}' for v in init)}]")
        apply_overrides(graph, overrides[-1:])
        print(f"target: the first ground-truth box {tuple(round(v, 1) for v in init)}")
    for spec in graph.nodes.values():
        validate_node(graph, spec)
    return run_demo(graph, args.duration, Path(args.log), overrides)


def _first_truth_box(graph) -> tuple[float, ...] | None:
    """The ground-truth box of frame 0 when the capture source is an annotated image folder."""
    capture = graph.nodes.get("capture")
    source = str(capture.params.get("source", "")) if capture else ""
    if not source or source.startswith(("scene:", "camera:")) or not Path(source).is_dir():
        return None
    from followbus.vision.sources import ImageFolderSource

    folder = ImageFolderSource(Path(source))
    if not folder.has_ground_truth:
        return None
    box, _ = folder.ground_truth(0)
    return None if box is None else tuple(float(v) for v in box)


def cmd_launch(args) -> int:
    from followbus.bus.graph import apply_overrides
    from followbus.bus.node import validate_node
    from followbus.tools.launch import Launcher, install_stop_signals

    graph = _load_graph(args.graph)
    apply_overrides(graph, args.overrides)
    for spec in graph.nodes.values():
        validate_node(graph, spec)
    only = [n.strip() for n in args.only.split(",")] if args.only else None
    extra = []
    if args.record:
        extra.append(("recorder", [sys.executable, "-m", "followbus.tools.cli", "record", "--graph", args.graph,
                                   "-o", args.record]))
    try:
        launcher = Launcher(graph, only=only, host=args.host, startup_timeout_s=args.startup_timeout,
                            grace_s=args.grace, extra_children=extra, overrides=args.overrides)
    except ValueError as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    install_stop_signals(launcher)
    logging.getLogger("followbus.launch").setLevel(logging.INFO)
    return launcher.run(args.duration)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
