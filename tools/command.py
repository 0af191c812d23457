"""A ``followbus`` command as a row of a table, and the arguments and bus settings commands share.

Each room of tools/ (recording/, live/, bench/) lists its commands in its ``commands.py``; tools/cli.py
puts the rows together. A row costs nothing until it runs: its module imports only argparse and this
file, and its handler imports the work (numpy, zenoh, mcap, ...) when called. Arguments are added only to
the command being run (:func:`add_commands`), so ``followbus --help`` builds names and one-line helps.
"""

from __future__ import annotations

import argparse
import importlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from .domains import load_graph  # noqa: F401  (the commands load graphs from here: domain applied)

Handler = Callable[[argparse.Namespace], int]


class OneLineParser(argparse.ArgumentParser):
    """argparse's parser whose usage errors are one line, ``followbus CMD: error: ...``, exit 2, as every other
    mistake (argparse prints the usage block first); ``--help`` still shows the usage. Subcommands inherit it."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


@dataclass(frozen=True)
class Lazy:
    """A handler imported when it runs: ``function`` of ``module`` (a module path under followbus.tools, e.g.
    ``recording.replay``), called with the parsed arguments."""

    module: str
    function: str

    def resolve(self) -> Handler:
        return getattr(importlib.import_module(f"{__package__}.{self.module}"), self.function)

    def __call__(self, args: argparse.Namespace) -> int:
        return self.resolve()(args)


@dataclass(frozen=True)
class Command:
    """One ``followbus`` command: its name, one-line help, the function adding its arguments (and setting
    its description and epilog), and the handler run with the parsed arguments. A command with
    ``subcommands`` (``bench``) has no handler of its own: one of its subcommands is required."""

    name: str
    help: str
    arguments: Callable[[argparse.ArgumentParser], None] | None = None
    run: Handler | None = None
    subcommands: tuple[Command, ...] = ()
    metavar: str = "WHAT"  # of the subcommand argument


def add_commands(sub: Any, commands: Sequence[Command], argv: Sequence[str] | None, dest: str = "command") -> None:
    """Add a subparser per command to ``sub``; arguments only for the one ``argv`` names (its first word
    that is not an option), since no other parser will parse anything."""
    chosen = next((a for a in argv if not a.startswith("-")), None) if argv is not None else None
    for command in commands:
        p = sub.add_parser(command.name, help=command.help)
        if argv is not None and command.name != chosen:
            continue
        rest = list(argv[argv.index(chosen) + 1:]) if argv is not None and chosen is not None else None
        if command.arguments is not None:
            command.arguments(p)
        if command.subcommands:
            nested = p.add_subparsers(dest=command.name, metavar=command.metavar, required=True)
            add_commands(nested, command.subcommands, rest, dest=command.name)
        else:
            assert command.run is not None, f"command {command.name!r} has neither a handler nor subcommands"
            p.set_defaults(run=command.run)


def describe(p: argparse.ArgumentParser, description: str | None = None, epilog: str | None = None,
             raw: bool = False) -> None:
    """Set a command's --help texts (``raw``: keep their line breaks)."""
    p.description = description
    p.epilog = epilog
    if raw:
        p.formatter_class = argparse.RawDescriptionHelpFormatter


# --- arguments several commands take -----------------------------------------------------------------

def _number(text: str, kind: type) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a {'whole ' if kind is int else ''}number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, not {text}")
    return value


def positive(text: str) -> float:
    """argparse type of an amount above 0 (seconds, megabytes, a rate): a negative or zero duration is a mistake,
    said at once (exit 2), not a command that ends at once in silence."""
    value = _number(text, float)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be above 0, not {text}")
    return value


def non_negative(text: str) -> float:
    """argparse type of an amount of 0 or more (a tolerance, a grace period, jitter in pixels)."""
    value = _number(text, float)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, not {text}")
    return value


def count(text: str) -> int:
    """argparse type of a number of things, 1 or more (messages, rounds, repeats)."""
    value = int(_number(text, int))
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, not {text}")
    return value


def count_or_zero(text: str) -> int:
    """argparse type of a number of things where 0 has a meaning (no limit, none)."""
    value = int(_number(text, int))
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, not {text}")
    return value


def key_expression(text: str) -> str:
    """argparse type of a Zenoh key expression (echo, hz, record and play --topics): a malformed one is said at once,
    in Zenoh's words without its source path, not as a traceback from the subscriber."""
    import zenoh  # only when a command with a key runs: the table of commands imports no work

    try:
        zenoh.KeyExpr(text)
    except zenoh.ZError as exc:
        raise argparse.ArgumentTypeError(f"not a key expression: {str(exc).split(' at /')[0]}") from None
    return text


def bus_namespace(text: str) -> str:
    """argparse type of --namespace: a prefix of keys (letters, digits, _ - and /, as graph.yaml's). One that is not
    is said at once: a bus command would otherwise wait on keys no graph can publish, in silence."""
    from ..bus.graph import NAMESPACE_RE

    if text and not NAMESPACE_RE.match(text):
        raise argparse.ArgumentTypeError(f"not a key prefix (letters, digits, _ - and /): {text!r}")
    return text


def output_file(text: str) -> str:
    """argparse type of a file a command writes (--json, --report, --log, -o): one it could not write is said before
    the command runs, not after a benchmark's minutes are lost. Nothing is created to find out."""
    from .errors import output_file_problem

    problem = output_file_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(f"{text}: {problem}")
    return text


def port(text: str) -> int:
    """argparse type of a TCP port (0: any free one, where the command says so)."""
    value = int(_number(text, int))
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0..65535, not {text}")
    return value


def graph_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--graph", default="graph.yaml", help="graph file (default: ./graph.yaml)")


def connect_args(p: argparse.ArgumentParser, timeout: bool = True) -> None:
    """Where and as whom a command joins the bus: the same options for every command that does (topics, echo,
    hz, nodes, record, play, monitor, foxglove), read by :func:`settings` (tools/connect.py client_settings)."""
    graph_arg(p)
    p.add_argument("--connect", metavar="ENDPOINT", action="append",
                   help="join as a client via this endpoint (e.g. tcp/192.0.2.10:7447) instead of the graph's "
                        "zenoh settings; repeatable")
    if timeout:
        p.add_argument("--connect-timeout", type=positive, metavar="S",
                       help="give up joining the graph after S seconds (default: the graph's connect_timeout_ms, "
                            "10 s; monitor: 3 s)")
    p.add_argument("--user", help="zenoh user name (transport/auth/usrpwd), e.g. monitor (default: "
                                  "$FOLLOWBUS_ZENOH_USER; without either and without --connect, the graph's own)")
    p.add_argument("--password", help="zenoh password (default: $FOLLOWBUS_ZENOH_PASSWORD; asked on a terminal)")
    p.add_argument("--ca", metavar="FILE", help="CA certificate for a tls/ endpoint")
    p.add_argument("--namespace", type=bus_namespace, help="bus namespace (default: the graph's, else fb)")


# --- what commands that join the bus need --------------------------------------------------------------

def settings(args: argparse.Namespace) -> Any:
    """Zenoh client settings of a bus command (--connect, --user, --password, --ca, --connect-timeout)."""
    from .connect import settings_from_args

    return settings_from_args(args)


def namespace(args: argparse.Namespace) -> str:
    if getattr(args, "namespace", None):
        return args.namespace
    if Path(getattr(args, "graph", "graph.yaml")).exists():
        return load_graph(args.graph).namespace
    from .domains import DefaultGraph, apply_domain

    return apply_domain(DefaultGraph()).namespace


def domain_args(p: argparse.ArgumentParser, auto: bool = False) -> None:
    """A launched graph's domain on the bus (tools/domains.py): refused when that namespace already runs there."""
    p.add_argument("--domain", metavar="N" + ("|auto" if auto else ""),
                   help="run in domain N: the graph's port + N and namespace <namespace>-dN, apart from every other "
                        "domain (default: $FOLLOWBUS_DOMAIN, else 0: the graph as written)"
                        + ("; auto: the first domain where no graph runs" if auto else ""))
    p.add_argument("--namespace", type=bus_namespace,
                   help="bus namespace (default: the graph's, or $FOLLOWBUS_NAMESPACE)")
    p.add_argument("--port", help="the well-known port peers meet on (default: the graph's, or $FOLLOWBUS_PORT)")
