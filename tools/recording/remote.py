"""What ``followbus record`` subscribes to, and what it leaves out on a remote link.

A Zenoh subscriber receives everything its key expression matches: ``--exclude`` applied in the callback
would still carry the excluded messages over the link. So when the graph is known, the recorder subscribes
to each of its output keys that is kept, one by one, and an excluded key never leaves the robot.

A recorder that joins over a non-loopback endpoint (a laptop on Wi-Fi) leaves the raw frames out unless asked
(``--raw-frames``): at 640x480 bgr8 and 30 Hz they are ~27 MB/s, more than any wireless link carries, while the
JPEG preview (``capture/preview``, a few KB) stays.
"""

from __future__ import annotations

from typing import Any

import zenoh

from ...bus.session import ZenohSettings, is_local_endpoint

RAW_FRAME_OUTPUT = "frame"  # the uncompressed camera frame of a graph's capture node(s)


def is_remote(settings: ZenohSettings) -> bool:
    """Whether the recorder reaches the graph over a network (any endpoint beyond loopback)."""
    return any(not is_local_endpoint(ep) for ep in settings.connect)


def raw_frame_keys(graph: Any | None, namespace: str) -> list[str]:
    """The keys of raw frames: every node's ``frame`` output (without a graph: ``<ns>/*/frame``)."""
    if graph is None:
        return [f"{namespace}/*/{RAW_FRAME_OUTPUT}"]
    return [f"{namespace}/{name}/{RAW_FRAME_OUTPUT}" for name, spec in graph.nodes.items()
            if RAW_FRAME_OUTPUT in spec.outputs]


def _matches(key: str, exprs: list[zenoh.KeyExpr]) -> bool:
    return any(e.intersects(zenoh.KeyExpr(key)) for e in exprs)


def subscription_patterns(patterns: list[str], exclude: list[str], graph: Any | None, namespace: str) -> list[str]:
    """The key expressions to subscribe to: ``patterns`` when nothing is excluded or the graph is unknown
    (the recorder then drops excluded keys on arrival), else every output key of the graph that a pattern
    matches and no exclusion does, plus the patterns on ``@`` chunks (status), which no output key covers."""
    if not exclude or graph is None:
        return list(patterns)
    wanted = [zenoh.KeyExpr(p) for p in patterns]
    excluded = [zenoh.KeyExpr(p) for p in exclude]
    keys = [f"{namespace}/{name}/{out}" for name, spec in graph.nodes.items() for out in spec.outputs]
    kept = [k for k in keys if _matches(k, wanted) and not _matches(k, excluded)]
    return kept + [p for p in patterns if "@" in p]
