"""The ``followbus`` command: a table of commands. Each subcommand's --help explains it with an example.

A command is a row (tools/command.py): name, one-line help, the function adding its arguments, the handler.
The graph commands (launch, demo, node, check, schema) and models are here; each room of tools/ owns its
rows: recording/commands.py, live/commands.py, bench/commands.py. Handlers import their work when they
run, and only the chosen command gets its arguments, so ``followbus --help`` imports neither numpy nor zenoh.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any

from . import __version__
from .bench.commands import COMMANDS as BENCH_COMMANDS
from .command import (
    Command,
    Lazy,
    OneLineParser,
    add_commands,
    describe,
    domain_args,
    graph_arg,
    load_graph,
    non_negative,
    output_file,
    positive,
    settings,
)
from .live.commands import COMMANDS as LIVE_COMMANDS
from .recording.commands import COMMANDS as RECORDING_COMMANDS
from .runs.commands import COMMANDS as RUNS_COMMANDS

EXIT_BAD_INPUT = 2

EPILOG = """\
examples:
  followbus demo                          the whole loop on a synthetic corridor scene, 20 s
  followbus launch graph.yaml             run the graph (one process per node)
  followbus launch graph.yaml --only capture,detection --duration 10
  followbus node detection                run one node of ./graph.yaml in this terminal
  followbus demo --domain auto            in the first domain where no graph runs (FOLLOWBUS_DOMAIN=N: that one)
  followbus up graph.yaml                 in the background, a log file per node; then: ps, logs, down
  followbus logs followbus reid -f        one node's log of a graph started with up
  followbus param set reid.reid_threshold 0.8   change a live-tunable parameter of a running node
  followbus graph graph.yaml --svg -o g.svg     draw the nodes and keys (or --dot)
  followbus topics                        keys seen on the bus with their rates
  followbus echo fb/prediction/track      print decoded messages
  followbus hz fb/capture/frame           rate and latency of one key
  followbus nodes                         node health from liveliness tokens
  followbus bench bus                     frame latency and CPU: bus/ vs raw zenoh (vs dora-rs)
  followbus record -o recordings/run.mcap  record the bus (opens in Foxglove)
  followbus replay recordings/run.mcap --node reid --verify   regression replay of a node
  followbus eval all --ablations         score followers on ../shared/data (results/results.md)
  followbus bench pipeline                capture -> motor command latency through the graph
  followbus bench chaos                   kill, stall, load and spoof the graph: does it recover?
  followbus models                        where the ONNX models are found; checks their SHA-256

Every command that talks to the bus reads the zenoh settings of --graph (default ./graph.yaml);
--connect tcp/HOST:7447 joins another machine's graph as a client instead. $FOLLOWBUS_DOMAIN=N (as launch
--domain N) moves every command and node to the graph's port + N and namespace <namespace>-dN.
"""


# --- the graph commands: arguments -------------------------------------------------------------------

def _launch_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Start every node of a graph as its own process, wait for their liveliness "
             "tokens, restart them by policy, and stop them all on Ctrl-C.",
             "example: followbus launch graph.yaml --only capture,detection --duration 30",
             raw=True)
    p.add_argument("graph", nargs="?", default="graph.yaml", help="graph file (default: ./graph.yaml)")
    p.add_argument("--only", help="comma-separated node names to launch (default: all)")
    p.add_argument("--host", help="the machine this is: launch the nodes whose host: is this name, and those "
                                  "without one when it is the graph's default_host (default $FOLLOWBUS_HOST, else "
                                  "the hostname; needed only by a graph spread over several hosts)")
    p.add_argument("--duration", type=positive, metavar="S",
                   help="stop S seconds after every node is up (start-up does not count)")
    p.add_argument("--record", type=output_file, metavar="FILE", help="also record the bus to this MCAP file")
    p.add_argument("--startup-timeout", type=positive, default=30.0, metavar="S",
                   help="seconds to wait for every node's liveliness token (default 30)")
    p.add_argument("--grace", type=non_negative, default=5.0, metavar="S",
                   help="seconds between SIGTERM and SIGKILL at shutdown (default 5)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a node parameter (YAML value), e.g. --set capture.source=camera:0; repeatable")
    domain_args(p, auto=True)
    p.add_argument("--log-dir", metavar="DIR", help="also write each node's output to DIR/NODE.log (`followbus up`)")


def _demo_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Launch graph.yaml on a built-in synthetic scene (default: the corridor with a "
             "complete occlusion) for 20 s. Shows fps, target state, eta_k and the motor "
             "command live; ends with TSR@20px and CLE against the scene's exact ground truth "
             "and the capture-to-motor-command latency.",
             "example: followbus demo --scene lookalike --duration 10")
    graph_arg(p)
    p.add_argument("--duration", type=positive, default=20.0, metavar="S", help="seconds to run (default 20)")
    p.add_argument("--scene", default=None,
                   help="synthetic scene (corridor-occlusion, lookalike, wall-occlusion, night-puddles, sun-shadow, "
                        "ego-motion, lost-target); default: the graph's capture source")
    p.add_argument("--log", type=output_file, default=None, metavar="FILE",
                   help="where this run's node logs go (default: a new state/demo-YYYYmmdd-HHMMSS.log per run)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a node parameter, e.g. --set detection.backend=hog; repeatable")
    domain_args(p, auto=True)


def _node_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Run a single node (what the launcher runs for each node).",
             "example: followbus node prediction --graph graph.yaml")
    p.add_argument("name", help="node name in the graph")
    graph_arg(p)
    p.add_argument("--clock", choices=("wall", "stamps"), default="wall",
                   help="node clock: wall time, or message stamps (lockstep replay)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a parameter of this node, e.g. --set detection.backend=hog; repeatable")


def _check_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Validate a graph file (keys, wiring, types, every node's params) and that its "
             "capture source opens (the file exists and decodes, the scene name is known, the "
             "camera device exists), without starting anything. Exit status 2 on an error.",
             "example: followbus check graph.yaml --set capture.source=recordings/run1.mcap")
    p.add_argument("graph", nargs="?", default="graph.yaml")
    p.add_argument("--host", help="check only what this host runs (the capture source it opens); the graph's hosts "
                                  "and their nodes are listed either way")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="check with this parameter override (as given to launch); repeatable")


def _schema_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Generate the JSON Schema (draft-07) of graph.yaml from the validator's own "
             "definitions and every followbus.nodes module's params. Editors using "
             "yaml-language-server (VS Code's YAML extension, yamlls) pick it up from the "
             "file's first line: # yaml-language-server: $schema=docs/graph.schema.json",
             "example: followbus schema -o docs/graph.schema.json")
    p.add_argument("-o", "--output", type=output_file, metavar="FILE", help="write to FILE instead of standard output")


def _models_args(p: argparse.ArgumentParser) -> None:
    from .models_cmd import add_arguments

    add_arguments(p)


# --- the graph commands: handlers --------------------------------------------------------------------

def cmd_check(args: argparse.Namespace) -> int:
    from ..bus.graph import apply_overrides
    from ..bus.hosts import describe_plan

    graph = load_graph(args.graph)
    apply_overrides(graph, args.overrides)
    host, nodes = _host_nodes(graph, args.host) if args.host else (None, list(graph.nodes))
    _validate(graph, args.overrides, opened=set(nodes))
    print(f"{args.graph}: ok ({len(graph.nodes)} nodes)")
    plan = describe_plan(graph, host)
    if graph.default_host or len(plan) > 1 or host:
        print("hosts (`followbus launch --host HOST` starts these nodes):", *plan, sep="\n")
    return 0


def _host_nodes(graph, given: str | None) -> tuple[str | None, list[str]]:
    """The host this launch stands for and its nodes (bus/hosts.py); a host the graph does not use is one line."""
    from ..bus.hosts import HostError, nodes_on, this_host
    from .errors import UsageError

    try:
        host = this_host(graph, given)
        return host, nodes_on(graph, host)
    except HostError as exc:
        raise UsageError(str(exc)) from exc


def cmd_node(args: argparse.Namespace) -> int:
    from ..bus.graph import apply_overrides
    from ..bus.node_runtime import run_node

    graph = load_graph(args.graph)
    apply_overrides(graph, args.overrides)
    if args.name in graph.nodes:  # (an unknown name: run_node says which nodes there are)
        _validate(graph, args.overrides, opened={args.name}, nodes=[args.name])
    return run_node(graph, args.name, clock=args.clock)


def cmd_schema(args) -> int:
    from ..bus.graph_schema import schema_text
    from .errors import write_text_output

    return write_text_output(schema_text("followbus.nodes"), args.output)


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import default_graph_path, demo_detector, run_demo
    from .domains import apply_domain
    from .runs.claims import claim_from_args

    args.graph = default_graph_path(args.graph)
    # The graph file and the model first (its validation: DetectionParams.check), then the bus: a mistake in the
    # file or a missing model is said before whether another graph holds this domain.
    graph, overrides = demo_graph(args.graph, args.scene, args.overrides)
    detector = demo_detector(graph)
    held = claim_from_args(args, "demo")
    apply_domain(graph)
    try:
        return run_demo(graph, args.duration, Path(args.log) if args.log else None, overrides, detector)
    finally:
        held.close()


def demo_graph(path: str, scene: str | None, given_overrides: list[str]) -> tuple[Any, list[str]]:
    """The graph the demo runs and its overrides. It knows no node by name: ``scene`` goes to the params marked
    ``demo: source`` (field metadata), a source's first ground-truth box (its params' ``first_truth_box()``) to
    those marked ``demo: init_box``."""
    from ..bus.graph import apply_overrides
    from ..bus.graph import load_graph as load_graph_file
    from ..bus.node_checks import load_node_class
    from ..bus.node_params import marked
    from .errors import UsageError

    graph = load_graph_file(path)  # its domain is the caller's to apply (tools/domains.py apply_domain)
    roles: dict[str, dict[str, str]] = {}  # node -> {role: its param}
    for name, spec in graph.nodes.items():
        try:
            cls = load_node_class(spec.run)
        except ImportError as exc:  # as `check` says it
            raise graph.error(spec.line, f"node {name!r}: run: {exc}") from exc
        roles[name] = {role: param for param, role in marked(cls.Params, "demo").items()}
    overrides = list(given_overrides)
    labels = None
    if scene:
        sources = [f"{name}.{role['source']}" for name, role in roles.items() if "source" in role]
        if not sources:
            raise UsageError(f"--scene: no node of {path} takes a source")
        overrides[:0] = [f"{key}=scene:{scene}" for key in sources]
        labels = dict.fromkeys(sources, f"--scene {scene}")
    apply_overrides(graph, overrides)
    _validate(graph, overrides, labels=labels)
    init = next((box for spec in graph.nodes.values() if (box := _first_truth_box(graph, spec)) is not None), None)
    takers = {name: role["init_box"] for name, role in roles.items()
              if "init_box" in role and role["init_box"] not in graph.nodes[name].params}
    if init is not None and takers:
        # A follower is told whom to follow: on recorded sequences that is the first annotated box.
        box = f"[{', '.join(f'{v:.2f}' for v in init)}]"
        given = [f"{name}.{param}={box}" for name, param in takers.items()]
        overrides += given
        apply_overrides(graph, given)
        print(f"target: the first ground-truth box {tuple(round(v, 1) for v in init)}")
    return graph, overrides


def _first_truth_box(graph: Any, spec: Any) -> tuple[float, ...] | None:
    """The first ground-truth box of a node's source, when its params can tell one (``first_truth_box()``)."""
    from ..bus.node_checks import validate_node

    params = validate_node(graph, spec)[1]
    for part in params if isinstance(params, tuple) else (params,):
        first = getattr(part, "first_truth_box", None)
        if first is not None and (box := first()) is not None:
            return box
    return None


def _check_outputs(args) -> None:
    """The node logs' directory can be written: said before anything starts (UsageError), not by a thread's
    traceback while the node's output is lost (--record is checked by its argparse type)."""
    from .errors import writable_directory

    if args.log_dir:
        writable_directory(args.log_dir, "--log-dir")


def cmd_launch(args) -> int:
    from ..bus.barrier import RECORDER_NAME
    from ..bus.graph import apply_overrides
    from ..bus.graph import load_graph as load_graph_file
    from .domains import apply_domain
    from .launch import Launcher, install_stop_signals
    from .runs.claims import claim_from_args

    if args.host:  # which host's nodes this launch runs: the claim only minds those (runs/claims.py)
        from ..bus.hosts import HOST_ENV

        os.environ[HOST_ENV] = args.host
    graph = load_graph_file(args.graph)
    apply_overrides(graph, args.overrides)
    only = [n.strip() for n in args.only.split(",")] if args.only else None
    host, on_host = _host_nodes(graph, args.host)
    # Every node is validated; what a node would open (the capture source) only for the nodes started here. The
    # file first, then the bus: a mistake in it is said before whether another graph holds this domain.
    _validate(graph, args.overrides, opened={n for n in on_host if not only or n in only})
    _check_outputs(args)
    held = claim_from_args(args, "up" if args.log_dir else "launch", args.log_dir or "")
    apply_domain(graph)
    extra = []
    if args.record:
        extra.append((RECORDER_NAME, [sys.executable, "-m", "followbus.tools.cli", "record", "--graph", args.graph,
                                   "-o", args.record, *(f"--set={o}" for o in args.overrides)]))
    try:
        launcher = Launcher(graph, only=only, host=host, startup_timeout_s=args.startup_timeout,
                            grace_s=args.grace, extra_children=extra, overrides=args.overrides,
                            watch_outputs=args.duration is not None,
                            log_dir=Path(args.log_dir) if args.log_dir else None, quiet=bool(args.log_dir))
    except ValueError as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    _warn_unfed(graph, [c.name for c in launcher.children if c.spec.run != "<tool>"], bool(only or args.host),
                left_out=launcher.left_out)
    install_stop_signals(launcher)
    logging.getLogger("followbus.launch").setLevel(logging.INFO)
    try:
        status = launcher.run(args.duration)
    finally:
        held.close()
    if launcher.refusal:
        print(f"followbus launch: {launcher.refusal}", file=sys.stderr, flush=True)
        return EXIT_BAD_INPUT
    problems = launcher.problems() if args.duration is not None else []
    if problems:
        # A scripted run (CI, a smoke test) must not pass with a node that crash-looped or stayed silent.
        print(f"followbus launch: {'; '.join(problems)}", file=sys.stderr, flush=True)
        return status or 1
    return status


def _warn_unfed(graph, started: list[str], partial: bool, left_out: set[str]) -> None:
    """launch --only/--host: say at once which inputs of the started nodes nothing started here produces, and which
    consumers on other hosts a source waits for before its first message (bus/barrier.py DownstreamBarrier; nodes
    that --only left out are not waited for)."""
    if not partial:
        return
    unfed = [f"{name}.{inp.name} ({inp.source_node}/{inp.source_output})" for name in started
             for inp in graph.nodes[name].inputs.values() if inp.source_node not in started]
    if unfed:
        print(f"followbus launch: no producer launched for {', '.join(unfed)}: they wait for a node started "
              "elsewhere (or a replay)", file=sys.stderr, flush=True)
    for source in (n for n in started if not graph.nodes[n].inputs):
        waits = sorted(c for c, spec in graph.nodes.items() if c not in started and c not in left_out
                       and any(i.source_node == source for i in spec.inputs.values()))
        if waits:
            print(f"followbus launch: {source} waits for {', '.join(waits)} (on another host) up to its "
                  f"wait_for_consumers_s before its first message (--set {source}.wait_for_consumers_s=0: at once)",
                  file=sys.stderr, flush=True)


def _check_what_it_opens(graph, cls, params) -> None:
    """What a node started here would open: its params' own ``check()`` (the capture source), and the files it keeps
    its state in (a ``state_file`` field, {namespace} filled in), which it must be able to write (ParamError)."""
    from ..bus.node_params import ParamError, marked
    from .errors import output_file_problem

    parts = params if isinstance(params, tuple) else (params,)
    for part in parts:
        if hasattr(part, "check"):
            part.check()
    for key in marked(cls.Params, "state_file"):
        value = next(getattr(p, key) for p in parts if hasattr(p, key))
        path = value.replace("{namespace}", graph.namespace)
        problem = output_file_problem(path) if value else None
        if problem:
            raise ParamError(key, f"{key} {path}: {problem} (the node could not keep its state there)")


def _validate(graph, overrides: list[str] | None = None, *, opened: set[str] | None = None,
              labels: dict[str, str] | None = None, nodes: list[str] | None = None) -> None:
    """Validate every node (or ``nodes``) against its class, and check what the nodes in ``opened`` (default:
    all) would open (the capture source: CaptureParams.check), before anything starts. A problem with a value given on
    the command line names the option (``labels``: node.param -> how it was given, else its --set); one from
    the file names its line (GraphError)."""
    from ..bus.node_checks import validate_node
    from ..bus.node_params import ParamError
    from .errors import UsageError

    given = {item.partition("=")[0].strip(): f"--set {item}" for item in overrides or []}
    given.update(labels or {})
    for name in nodes if nodes is not None else list(graph.nodes):
        spec = graph.nodes[name]
        try:
            cls, params = validate_node(graph, spec)
            if opened is None or name in opened:
                _check_what_it_opens(graph, cls, params)
        except Exception as exc:
            param = exc if isinstance(exc, ParamError) else exc.__cause__
            key = f"{name}.{param.key}" if isinstance(param, ParamError) else ""
            if key in given:
                raise UsageError(f"{given[key]}: {param}") from exc
            if isinstance(exc, ParamError):
                raise graph.error(spec.param_lines.get(exc.key, spec.line), f"node {name!r}: {exc}") from exc
            raise


# --- the table ----------------------------------------------------------------------------------------

COMMANDS: tuple[Command, ...] = (
    Command("launch", "launch a graph: one process per node", _launch_args, cmd_launch),
    Command("demo", "the whole loop on a synthetic scene, with a live status line and a summary", _demo_args,
            cmd_demo),
    Command("node", "run one node of a graph in this process", _node_args, cmd_node),
    Command("check", "validate a graph file and its capture source, and exit (status 2 on errors)", _check_args,
            cmd_check),
    Command("schema", "print the JSON Schema of graph.yaml (editors validate and complete with it)", _schema_args,
            cmd_schema),
    *RUNS_COMMANDS,
    *LIVE_COMMANDS,
    *BENCH_COMMANDS,
    *RECORDING_COMMANDS,
    Command("models", "where the ONNX models are found and whether their SHA-256 matches", _models_args,
            Lazy("models_cmd", "cmd_models")),
)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of ``argv`` (only its command gets its arguments); None: every command's, complete."""
    parser = OneLineParser(
        prog="followbus", description="Perception and control of a person-following robot over Eclipse Zenoh.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"followbus {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)")
    add_commands(parser.add_subparsers(dest="command", metavar="COMMAND"), COMMANDS, argv)
    return parser


def _setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose < 0 else (logging.INFO if verbose == 0 else logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


def _find_nodes_here() -> None:
    """A node module in the working directory (graph.yaml ``run: my_node``) is found, as the node processes find it
    (``python -m`` puts the working directory first); last on the path, so it shadows nothing installed."""
    here = os.getcwd()
    if "" not in sys.path and here not in sys.path:
        sys.path.append(here)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    _find_nodes_here()
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    if args.command is None:
        parser.print_help()
        return 0
    from ..bus.graph import GraphError
    from ..vision.models import ModelError
    from .connect import BusUnreachable, explain_connect_failure, is_connect_failure
    from .errors import INTERRUPTED, UsageError

    _note_interrupts()
    # A user's mistake (or a graph that is not running) is one line on stderr and exit status 2; a failure
    # found while running (a node crashed, nothing arrived, a replay differs) is reported by the command: 1.
    try:
        status = args.run(args)
        return 130 if INTERRUPTED.is_set() else status
    except BrokenPipeError:
        # The reader went away (`followbus info F | head`): stop quietly, as any Unix tool does. Standard output
        # is pointed at /dev/null so the interpreter's final flush does not fail a second time.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
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
        print(f"followbus: {explain_connect_failure(settings(args))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        if _EXIT_AT_INTERRUPT:
            _exit_interrupted()  # here, with the traceback alive: see _exit_interrupted
        return 130


# Set by run() (the `followbus` process): Ctrl-C ends the process from within main's handler.
_EXIT_AT_INTERRUPT = False


def _exit_interrupted() -> None:
    """End the process with status 130 at once. Called while the KeyboardInterrupt is still being handled: its
    traceback keeps the interrupted command's frames, and with them any Zenoh session or subscriber they held, alive.
    Leaving the handler would free them, and dropping a Zenoh session can block for a long time on a loaded machine
    (a minute, beside two burners and two test workers)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(130)


def _note_interrupts() -> None:
    """Ctrl-C raises KeyboardInterrupt as ever, and is remembered: a command that catches it to stop cleanly
    still exits 130 (the shell's convention, docs/running.md). A SIGINT ignored by the caller (a background job)
    stays so."""
    from .errors import INTERRUPTED

    def on_sigint(_signum, _frame) -> None:
        INTERRUPTED.set()
        raise KeyboardInterrupt

    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, on_sigint)


def run() -> None:
    """The `followbus` command: main(), then exit. After Ctrl-C (status 130) the command has already cleaned up
    what it owns (a recorder finalises its file before it returns); the process then ends at once, without the
    interpreter's shutdown, which can wait for ever on a Zenoh session the interrupt left open."""
    global _EXIT_AT_INTERRUPT
    _EXIT_AT_INTERRUPT = True
    # `kill -USR1 <pid>` prints every thread's Python stack on stderr: what a command that seems stuck is doing.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    code = main()
    if code == 130:
        _exit_interrupted()
    _exit_now(code)


def _exit_now(code: int) -> None:
    """End the process with ``code`` once the command has closed what it opened, without the interpreter's
    shutdown: Zenoh's runtime threads outlive the command's sessions for a moment, and one that touches the
    interpreter while it is being torn down aborts the process (a laptop's `echo` ended with SIGABRT after printing
    its two messages, in a test beside two burners). Log handlers and the standard streams are flushed first."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe (`| head`): nothing more can reach it
            stream.flush()
    os._exit(int(code or 0))


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    run()
