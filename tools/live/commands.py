"""The commands that watch a running graph: ``router``, ``topics``, ``echo``, ``hz``, ``nodes``, ``foxglove``,
``monitor`` (rows of tools/cli.py's table).

Light on purpose (argparse only): every ``followbus`` run imports it; each handler imports its module."""

from __future__ import annotations

import argparse

from ..command import Command, Lazy, connect_args, count, describe, key_expression, namespace, port, positive, settings


def _router_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "A Zenoh session in router mode: robots and laptops connect to it.",
             "example: followbus router --listen tcp/127.0.0.1:7447")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (default tcp/127.0.0.1:7447); repeatable")
    p.add_argument("--duration", type=positive, metavar="S")


def _topics_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "The keys with traffic: type, the publisher's rate (from header.seq and pub_ns: a slow link that "
             "loses messages does not lower it; - when fewer than two arrived), what arrived here, what was lost "
             "on the way, the mean size. Over a network (an endpoint beyond loopback) it subscribes key by key "
             "to what the nodes' statuses announce and leaves the raw frames out (a Wi-Fi link cannot carry them, "
             "and they would crowd out the rest), naming them; --raw-frames subscribes to every key.",
             "example: followbus topics --connect tcp/192.0.2.10:7447 --user monitor")
    connect_args(p)
    p.add_argument("--seconds", type=positive, default=2.0, help="how long to listen (default 2)")
    p.add_argument("--raw-frames", action="store_true",
                   help="over a network, subscribe to every key under <ns>/**, the raw frames too")


def _echo_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             None,
             "example: followbus echo 'fb/prediction/track' -n 5")
    p.add_argument("key", type=key_expression, help="key or key expression (e.g. fb/prediction/track, fb/**)")
    connect_args(p)
    p.add_argument("-n", "--count", type=count, help="stop after N messages")
    p.add_argument("--seconds", type=positive, help="stop after S seconds")
    p.add_argument("--timeout", type=positive, metavar="S",
                   help="give up (exit status 1) when no message arrived within S seconds (default: wait)")


def _hz_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("key", type=key_expression)
    connect_args(p)
    p.add_argument("--seconds", type=positive, help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--timeout", type=positive, metavar="S",
                   help="give up (exit status 1) when no message arrived within S seconds (default: wait)")


def _nodes_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Node health, and the links between nodes as their statuses report them (each key's sent and "
             "delivered rate, and the messages that never arrived: header.seq gaps). Links that cross hosts, lose "
             "messages or deliver nothing are listed; --links lists every one.",
             "example: followbus nodes --connect tcp/192.0.2.10:7447 --user monitor --links")
    connect_args(p)
    p.add_argument("--seconds", type=positive, default=1.5, help="how long to listen (default 1.5)")
    p.add_argument("--links", action="store_true", help="list every link, not only those that cross hosts, lose "
                                                        "messages or deliver nothing")


def _foxglove_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Preview as foxglove.CompressedImage, target/gate/candidates as "
             "foxglove.ImageAnnotations, motor command and node status as JSON. Read-only.",
             "example: followbus foxglove --connect tcp/192.0.2.10:7447 --user monitor --port 8765")
    connect_args(p, timeout=False)
    p.add_argument("--port", type=port, default=8765, help="WebSocket port (default 8765)")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--seconds", type=positive, help="stop after S seconds")


def _monitor_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Join the robot's bus as a client and show node health, per-topic rates, the "
             "target, eta_k and the motor command; --web serves a page with the preview "
             "stream, plots and the health table. Reconnects by itself.",
             "example: followbus monitor --connect tcp/192.0.2.10:7447 --user monitor --web 8080")
    connect_args(p)
    p.add_argument("--once", action="store_true", help="print one snapshot once every node is up (or --seconds) "
                                                       "and exit: 0 when all are up")
    p.add_argument("--seconds", type=positive, help="stop after S seconds (--once: wait at most S, default 5)")
    p.add_argument("--web", type=port, nargs="?", const=8080, metavar="PORT",
                   help="serve the web view on PORT (default 8080) instead of the terminal dashboard")
    p.add_argument("--bind", default="127.0.0.1", help="address the web view listens on (default 127.0.0.1; "
                                                        "any other address requires a token)")
    p.add_argument("--web-token", metavar="TOKEN",
                   help="token the web view requires (also on loopback; default $FOLLOWBUS_WEB_TOKEN, else one "
                        "generated and printed when --bind is not loopback)")

def _router(args: argparse.Namespace) -> int:
    from .introspect import run_router

    return run_router(args.listen or ["tcp/127.0.0.1:7447"], args.duration)


def _introspect(args: argparse.Namespace) -> int:
    """topics, echo, hz, nodes: introspect.cmd_<name> with the bus settings and namespace."""
    from . import introspect

    return getattr(introspect, f"cmd_{args.command}")(args, settings(args), namespace(args))


COMMANDS = (
    Command("router", "run a Zenoh router (multi-machine set-ups)", _router_args, _router),
    Command("topics", "list keys seen on the bus with their rates", _topics_args, _introspect),
    Command("echo", "print decoded messages of a key", _echo_args, _introspect),
    Command("hz", "rate and latency of a key", _hz_args, _introspect),
    Command("nodes", "node health from liveliness tokens and status messages", _nodes_args, _introspect),
    Command("foxglove", "serve the live bus to the Foxglove app (foxglove-sdk WebSocket server)", _foxglove_args,
            Lazy("live.foxglove_bridge", "run_foxglove")),
    Command("monitor", "live, read-only dashboard of a running graph (terminal or --web)", _monitor_args,
            Lazy("live.monitor", "run_monitor")),
)
