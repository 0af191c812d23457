"""Why a key is silent, said once after a second (``echo``, ``hz``), as ros2 topic echo's "does not appear to be
published yet": a key no node of the graph publishes (with the close matches: a typo, the namespace left out),
the node that publishes it not running (no graph at all, or not that node), or the node up and silent."""

from __future__ import annotations

import difflib
import sys
import threading
from pathlib import Path
from typing import Any

from ...bus.live_params import EVENTS_OUTPUT

SILENCE_S = 1.0


def graph_keys(graph_path: str | None) -> dict[str, str]:
    """Every key a node of the graph file (with this process's domain) publishes -> that node: its outputs, and
    the parameter_events every node publishes (bus/live_params.py)."""
    if not graph_path or not Path(graph_path).exists():
        return {}
    from ..command import load_graph

    graph = load_graph(graph_path)
    return {graph.key(name, out): name for name, spec in graph.nodes.items()
            for out in [*spec.outputs, EVENTS_OUTPUT]}


def alive_nodes(session: Any, namespace: str, timeout_s: float = 0.5) -> set[str]:
    replies = session.liveliness().get(f"{namespace}/@health/*", timeout=timeout_s)
    return {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}


def explain_silence(key: str, namespace: str, keys: dict[str, str], alive: set[str]) -> str:
    """One line: why nothing arrived on ``key``."""
    if not alive:
        return f"nothing on {key}: no graph is running in namespace {namespace} (no node is alive)"
    events_of = key[:-len(EVENTS_OUTPUT) - 1].rsplit("/", 1)[-1] if key.endswith(f"/{EVENTS_OUTPUT}") else None
    if events_of in alive:  # every node publishes its parameter events: no graph file needed to know that
        return (f"nothing on {key} yet: no parameter of {events_of} changed since it started (`followbus param set "
                f"{events_of}.PARAM VALUE` publishes one)")
    if any(ch in key for ch in "*$"):
        return f"nothing on {key} yet: no publisher matches it (`followbus topics` lists the keys with traffic)"
    if keys and key not in keys:
        guesses = [k for k in (f"{namespace}/{key}",) if k in keys]
        guesses += [k for k in difflib.get_close_matches(key, list(keys), n=3, cutoff=0.6) if k not in guesses]
        hint = f"; did you mean {' or '.join(guesses)}?" if guesses else " (`followbus topics` lists the keys)"
        return f"no node publishes {key}{hint}"
    node = keys.get(key)
    if node is not None and node not in alive:
        return f"nothing on {key} yet: node {node}, which publishes it, is not running"
    who = f"node {node} is up but has not published it" if node else "no publisher matches it"
    return f"nothing on {key} yet: {who} (a scene that has ended, or a node waiting for its inputs?)"


def warn_if_silent(session: Any, key: str, namespace: str, graph_path: str | None, arrived: Any,
                   timeout_s: float | None = None, after_s: float = SILENCE_S) -> threading.Timer:
    """Print the line on stderr once ``after_s`` passed with ``arrived()`` still false; returns the timer (cancel
    it when the command ends). A command that gives up (``timeout_s``) before the line is useful says its own."""

    def check() -> None:
        if arrived() or (timeout_s is not None and timeout_s <= after_s * 1.5):
            return
        try:
            line = explain_silence(key, namespace, graph_keys(graph_path), alive_nodes(session, namespace))
        except Exception:  # the session closed meanwhile: the command is ending
            return
        if not arrived():
            print(f"followbus: {line}", file=sys.stderr, flush=True)

    timer = threading.Timer(after_s, check)
    timer.daemon = True
    timer.start()
    return timer
