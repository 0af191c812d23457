"""The commands that operate graphs running in the background: ``up``, ``ps``, ``logs``, ``down``, ``graph``
(rows of tools/cli.py's table). Light on purpose (argparse only); each handler imports its module."""

from __future__ import annotations

import argparse

from ..command import Command, Lazy, connect_args, describe, domain_args, output_file, positive


def _up_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Start a graph in the background (it survives this terminal) and return once every node is up. Each "
             "node's output goes to its own log file in a run directory (~/.local/state/followbus/runs/NAME-DATE, "
             "or $FOLLOWBUS_RUNS); `followbus logs NAME NODE` shows one, `followbus down NAME` stops the graph.",
             "example: followbus up graph.yaml --domain auto && followbus ps")
    p.add_argument("graph", nargs="?", default="graph.yaml", help="graph file (default: ./graph.yaml)")
    p.add_argument("--only", help="comma-separated node names to launch (default: all)")
    p.add_argument("--startup-timeout", type=positive, default=30.0, metavar="S",
                   help="seconds to wait for every node to be up (default 30)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a node parameter (YAML value); repeatable")
    domain_args(p, auto=True)


def _ps_args(p: argparse.ArgumentParser) -> None:
    describe(p, "The graphs running on this machine (up, launch, demo): name, namespace, endpoint, uptime, nodes, "
                "their health (all up, or which are stalled, done, restarting, failed), the launcher's pid and "
                "the user who started it.", "example: followbus ps")


def _logs_args(p: argparse.ArgumentParser) -> None:
    describe(p, "Print a node's log file of a graph started with `followbus up` (the running one, else its latest "
                "run); -f follows it until the graph stops.",
             "example: followbus logs followbus detection -f")
    p.add_argument("names", nargs="+", metavar="[GRAPH] NODE",
                   help="the graph's name or pid (optional: your one running graph, else your latest run) and the "
                        "node")
    p.add_argument("-f", "--follow", action="store_true", help="keep printing what the node writes")


def _down_args(p: argparse.ArgumentParser) -> None:
    describe(p, "Stop a running graph: its launcher stops every node (SIGTERM, then SIGKILL after its grace).",
             "example: followbus down followbus")
    p.add_argument("name", nargs="?", help="the graph's name or its launcher's pid (optional when one graph of yours "
                                           "runs: another user's is never picked for you)")


def _graph_args(p: argparse.ArgumentParser) -> None:
    describe(p, "Draw a graph: its nodes (boxes) and the keys they publish (ellipses), arrows along the data; a "
                "feedback input (offset -1) dashed. DOT for Graphviz (`| dot -Tpng > g.png`), or a standalone SVG "
                "(laid out by followbus, no Graphviz needed). The web view (`followbus monitor --web`) shows it too.",
             "example: followbus graph graph.yaml --svg -o graph.svg")
    p.add_argument("graph", nargs="?", default="graph.yaml",
                   help="a graph file, or the name of a running graph (default: ./graph.yaml)")
    form = p.add_mutually_exclusive_group()
    form.add_argument("--dot", action="store_true", help="Graphviz DOT (the default)")
    form.add_argument("--svg", action="store_true", help="SVG")
    p.add_argument("-o", "--output", type=output_file, metavar="FILE", help="write to FILE instead of standard output")


def _param_get_args(p: argparse.ArgumentParser) -> None:
    describe(p, "Print the value a running node's parameter has now (and whether it can be changed live).",
             "example: followbus param get reid.reid_threshold")
    p.add_argument("target", metavar="NODE.PARAM")
    connect_args(p, timeout=False)


def _param_set_args(p: argparse.ArgumentParser) -> None:
    describe(p, "Change a parameter of a running node, for the parameters the node declares live-tunable; checked "
                "as at launch. The change shows in the node's status (params_set) and is published on "
                "<ns>/<node>/parameter_events, so a recording keeps it. It lasts until the node restarts.",
             "example: followbus param set reid.reid_threshold 0.8")
    p.add_argument("target", metavar="NODE.PARAM")
    p.add_argument("value", help="a YAML value, as --set takes it")
    connect_args(p, timeout=False)


PARAM_COMMANDS: tuple[Command, ...] = (
    Command("get", "a running node's parameter", _param_get_args, Lazy("runs.params_cmd", "cmd_param_get")),
    Command("set", "change a live-tunable parameter of a running node", _param_set_args,
            Lazy("runs.params_cmd", "cmd_param_set")),
)


def _check_logs(args: argparse.Namespace) -> int:
    if len(args.names) > 2:
        from ..errors import UsageError

        raise UsageError("logs takes [GRAPH] NODE: at most two names")
    return Lazy("runs.detached", "cmd_logs")(args)


COMMANDS: tuple[Command, ...] = (
    Command("up", "start a graph in the background, a log file per node", _up_args, Lazy("runs.detached", "cmd_up")),
    Command("ps", "the graphs running on this machine", _ps_args, Lazy("runs.detached", "cmd_ps")),
    Command("logs", "a node's log of a graph started with `up` (-f: follow)", _logs_args, _check_logs),
    Command("down", "stop a graph started with `up` (or any running launch)", _down_args,
            Lazy("runs.detached", "cmd_down")),
    Command("param", "read or change a running node's parameters", subcommands=PARAM_COMMANDS, metavar="get|set"),
    Command("graph", "draw a graph's nodes and keys (DOT or SVG)", _graph_args, Lazy("runs.drawing_cmd", "cmd_graph")),
)
