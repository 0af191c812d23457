"""Which machine runs which node of a graph spread over several (``host:`` and ``default_host:``).

Every node runs on exactly one host: its ``host:``, else the graph's ``default_host``. A graph that names
hosts for some nodes and not others must say ``default_host`` (bus/graph/checks.py refuses it otherwise), so
``followbus launch --host H`` on each machine starts disjoint sets of nodes and no node runs twice (a node
without a host of its own would otherwise be started by *every* ``launch --host``). A graph that names no
host at all is a one-machine graph: ``launch`` without ``--host`` starts every node.
"""

from __future__ import annotations

import os
import socket
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .graph import Graph

HOST_ENV = "FOLLOWBUS_HOST"  # which host this machine is, when --host is not given


class HostError(ValueError):
    """A host that the graph does not use, or a multi-host graph launched without saying which host this is."""


def host_plan(graph: Graph) -> dict[str, list[str]]:
    """Each host and its nodes, in graph order (a graph without hosts: {"": every node})."""
    plan: dict[str, list[str]] = {}
    for name in graph.nodes:
        plan.setdefault(graph.host_of(name) or "", []).append(name)
    return plan


def nodes_on(graph: Graph, host: str | None) -> list[str]:
    """The nodes ``launch --host host`` starts (None: every node of a one-machine graph)."""
    plan = host_plan(graph)
    if host is None:
        return list(graph.nodes)
    if host not in plan:
        known = ", ".join(h for h in plan if h) or "none: the graph names no host"
        raise HostError(f"no node of {graph.path} runs on host {host!r} (hosts: {known})")
    return plan[host]


def this_host(graph: Graph, given: str | None) -> str | None:
    """The host a launch on this machine stands for: ``given`` (--host), else $FOLLOWBUS_HOST, else this
    machine's name when the graph uses it. A graph on one host (or none) needs none; one spread over
    several refuses to guess, since starting every node here would run some twice."""
    if given:
        return given
    plan = host_plan(graph)
    hosts = [h for h in plan if h]
    if len(plan) <= 1:
        return hosts[0] if hosts else None
    named = os.environ.get(HOST_ENV) or socket.gethostname()
    if named in plan:
        return named
    raise HostError(f"{graph.path} runs on hosts {', '.join(hosts)}: say which this machine is with --host "
                    f"(or ${HOST_ENV}); `followbus check {graph.path}` lists what each host runs")


def describe_plan(graph: Graph, only_host: str | None = None) -> list[str]:
    """Lines for `followbus check`: each host and the nodes it runs (the default host marked)."""
    lines = []
    for host, names in host_plan(graph).items():
        if only_host is not None and host != only_host:
            continue
        label = host or "(any)"
        if host and host == graph.default_host:
            label += " (default_host)"
        lines.append(f"  {label}: {', '.join(names)}")
    return lines
