"""What ``followbus record`` subscribes to, and what it leaves out on a remote link.

A Zenoh subscriber receives everything its key expression matches: ``--exclude`` applied in the callback
would still carry the excluded messages over the link. So over a network the recorder subscribes to each
output key that is kept, one by one, and an excluded key never leaves the robot: the graph's output keys when
the graph file is known, else the keys the nodes' statuses announce (bus/links.py PublishedKeys), followed for
the whole recording.

A recorder that joins over a non-loopback endpoint (a laptop on Wi-Fi) leaves the raw frames out unless asked
(``--raw-frames``; tools/connect.py RAW_FRAME_OUTPUT), while the JPEG preview (``capture/preview``) stays.
"""

from __future__ import annotations

from typing import Any

import zenoh

from ..connect import RAW_FRAME_OUTPUT


def raw_frame_keys(graph: Any | None, namespace: str) -> list[str]:
    """The keys of raw frames: every node's ``frame`` output (without a graph: ``<ns>/*/frame``)."""
    if graph is None:
        return [f"{namespace}/*/{RAW_FRAME_OUTPUT}"]
    return [f"{namespace}/{name}/{RAW_FRAME_OUTPUT}" for name, spec in graph.nodes.items()
            if RAW_FRAME_OUTPUT in spec.outputs]


def _matches(key: str, exprs: list[zenoh.KeyExpr]) -> bool:
    return any(e.intersects(zenoh.KeyExpr(key)) for e in exprs)


def graph_keys(graph: Any, namespace: str) -> list[str]:
    """Every output key of a graph."""
    return [f"{namespace}/{name}/{out}" for name, spec in graph.nodes.items() for out in spec.outputs]


def kept_keys(keys: list[str], patterns: list[str], exclude: list[str]) -> list[str]:
    """The keys a pattern matches and no exclusion does."""
    wanted = [zenoh.KeyExpr(p) for p in patterns]
    excluded = [zenoh.KeyExpr(p) for p in exclude]
    return [k for k in keys if _matches(k, wanted) and not _matches(k, excluded)]


def subscription_patterns(patterns: list[str], exclude: list[str], graph: Any | None, namespace: str) -> list[str]:
    """The key expressions to subscribe to: ``patterns`` when nothing is excluded, else every output key of the
    graph that a pattern matches and no exclusion does (none without the graph: the keys the nodes announce
    are added as they come), plus the patterns on ``@`` chunks (status), which no output key covers."""
    if not exclude:
        return list(patterns)
    keys = kept_keys(graph_keys(graph, namespace), patterns, exclude) if graph is not None else []
    return keys + [p for p in patterns if "@" in p]
