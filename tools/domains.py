"""A graph's domain on the bus: its namespace and its well-known port, chosen at launch.

``--domain N`` (or ``$FOLLOWBUS_DOMAIN``) selects both, as ``ROS_DOMAIN_ID`` does: domain 0 is the graph as
written; domain N moves the well-known port N above the graph's own (7447 -> 7447+N) and the namespace to
``<namespace>-dN``, so two graphs of different domains share neither a bus nor a key. ``--namespace`` and
``--port`` (``$FOLLOWBUS_NAMESPACE``, ``$FOLLOWBUS_PORT``) set one of them outright. The launcher passes its
environment to its nodes, so every process of a graph (and every tool run with the same variables) loads the
same domain (tools/command.py load_graph applies it).
"""

from __future__ import annotations

import os
import re
from typing import Any

from .errors import UsageError

DOMAIN_ENV = "FOLLOWBUS_DOMAIN"
NAMESPACE_ENV = "FOLLOWBUS_NAMESPACE"
PORT_ENV = "FOLLOWBUS_PORT"
MAX_DOMAIN = 232  # as ROS 2's: enough graphs for one machine, and ports stay far below the ephemeral range
AUTO = "auto"
_PORT_RE = re.compile(r"^(?P<head>(?:tcp|udp|tls|quic|ws)/[^#?]*:)(?P<port>\d+)(?P<tail>.*)$")


def parse_domain(text: str | None, what: str = "--domain") -> int | None:
    """A domain number (None: not given); ``auto`` is resolved by the caller (tools/runs/claims.py)."""
    if text is None or text == "":
        return None
    try:
        domain = int(text)
    except ValueError:
        raise UsageError(f"{what} {text!r}: a domain is a number 0..{MAX_DOMAIN} (or auto for demo/up)") from None
    if not 0 <= domain <= MAX_DOMAIN:
        raise UsageError(f"{what} {domain}: a domain is a number 0..{MAX_DOMAIN}")
    return domain


def parse_port(text: str | None, what: str = "--port") -> int | None:
    if text is None or text == "":
        return None
    try:
        port = int(text)
    except ValueError:
        port = 0
    if not 1 <= port <= 65535:
        raise UsageError(f"{what} {text!r}: a port is a number 1..65535")
    return port


def well_known_port(zenoh: Any) -> int | None:
    """The port of the graph's first TCP-like endpoint (connect, else listen): the one every peer meets on."""
    for endpoint in [*zenoh.connect, *zenoh.listen]:
        match = _PORT_RE.match(endpoint)
        if match:
            return int(match["port"])
    return None


def _move_port(endpoints: list[str], old: int, new: int) -> list[str]:
    out = []
    for endpoint in endpoints:
        match = _PORT_RE.match(endpoint)
        if match and int(match["port"]) == old:
            endpoint = f"{match['head']}{new}{match['tail']}"
        out.append(endpoint)
    return out


def apply_domain(graph: Any, environ: dict[str, str] | None = None) -> Any:
    """Apply $FOLLOWBUS_NAMESPACE / $FOLLOWBUS_PORT (replacing the graph's) and then $FOLLOWBUS_DOMAIN (moving
    both) to a loaded graph, in place; returned."""
    env = os.environ if environ is None else environ
    domain = parse_domain(env.get(DOMAIN_ENV), f"${DOMAIN_ENV}") or 0
    namespace = env.get(NAMESPACE_ENV) or graph.namespace
    old = well_known_port(graph.zenoh)
    port = parse_port(env.get(PORT_ENV), f"${PORT_ENV}") or old
    if domain:
        namespace = f"{namespace}-d{domain}"
        port = port + domain if port is not None else None
    from ..bus.graph import NAMESPACE_RE

    if not NAMESPACE_RE.match(namespace):
        raise UsageError(f"namespace {namespace!r} is not a valid key prefix (letters, digits, _ - and /)")
    graph.namespace = namespace
    if port is not None and old is not None and port != old:
        graph.zenoh.listen = _move_port(graph.zenoh.listen, old, port)
        graph.zenoh.connect = _move_port(graph.zenoh.connect, old, port)
    return graph


def set_domain(domain: int | None = None, namespace: str | None = None, port: int | None = None) -> None:
    """Make the launch options the environment of this process and of every process it starts."""
    for name, value in ((DOMAIN_ENV, domain), (NAMESPACE_ENV, namespace), (PORT_ENV, port)):
        if value is not None:
            os.environ[name] = str(value)


def endpoint(graph: Any) -> str:
    """The graph's well-known endpoint, for messages."""
    return next(iter([*graph.zenoh.connect, *graph.zenoh.listen]), "(no endpoint)")


def load_graph(path: str) -> Any:
    """The graph file with this process's domain applied ($FOLLOWBUS_DOMAIN, ...)."""
    from ..bus.graph import load_graph as load

    return apply_domain(load(path))


class DefaultGraph:
    """What a tool assumes with no graph file: namespace fb on the default endpoint (then the domain)."""

    def __init__(self) -> None:
        from ..bus.session import ZenohSettings

        self.namespace = "fb"
        self.zenoh = ZenohSettings()
