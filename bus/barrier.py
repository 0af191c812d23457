"""The start-up barrier of a source node (see :class:`DownstreamBarrier`)."""

from __future__ import annotations

import logging
import math
import os
import time
from typing import Any

from .graph import Graph

# Set by the launcher for its children: the comma-separated names of the nodes it started.
LAUNCHED_NODES_ENV = "FOLLOWBUS_LAUNCHED_NODES"
# Set by the launcher for its children: the nodes of this host that ``--only`` left out. A source does not wait
# for them: the user said they are not running (a node the graph puts on another host is still waited for).
LEFT_OUT_NODES_ENV = "FOLLOWBUS_LEFT_OUT_NODES"
LEFT_OUT_DISCOVERY_S = 2.0  # how long a source looks for a left-out consumer that may run in another launch

RECORDER_NAME = "recorder"  # liveliness name of `followbus record`, and the launcher's name for it


class DownstreamBarrier:
    """Start-up barrier for source nodes: is everyone who should hear our first message listening?

    Waits for the liveliness of the node's direct consumers (graph.yaml), of every node downstream of it
    that the launcher started (FOLLOWBUS_LAUNCHED_NODES: waiting for the whole chain keeps frame 0's
    results from racing the routes between later nodes), and of a recorder the launcher started. Nodes
    declare their token after their subscribers, so a visible token means they listen. Gives up after
    ``timeout_s`` with a warning naming who is missing, then lets ``settle_s`` pass for routes to settle.
    A node hosted without a session (in-process, bus.inproc) opens at once: every node there is listening
    before any publishes.
    """

    def __init__(self, graph: Graph, name: str, session: Any, timeout_s: float, settle_s: float,
                 log: logging.Logger):
        from .health import HealthWatcher

        self.log = log
        self.timeout_s = timeout_s
        self.settle_s = settle_s
        self._open_at: float | None = None
        self._health: HealthWatcher | None = None
        self.waiting_for: set[str] = set()
        # Who is still missing while it waits: in the node's status (a launcher that sees a consumer this node
        # cannot, two hosts whose sessions do not route to each other, names the split from it: bus/links.py).
        self.missing: set[str] = set()
        if session is None:
            self._open_at = -math.inf
            return
        self.waiting_for = {n for n, spec in graph.nodes.items()
                            if any(i.source_node == name for i in spec.inputs.values())}
        launched = os.environ.get(LAUNCHED_NODES_ENV)
        if launched:
            started = set(launched.split(","))
            frontier = {name}
            while frontier:
                fed = {n for n, spec in graph.nodes.items() if n in started and n not in self.waiting_for | {name}
                       and any(i.source_node in frontier for i in spec.inputs.values())}
                self.waiting_for |= fed
                frontier = fed
            if RECORDER_NAME in started:
                self.waiting_for.add(RECORDER_NAME)
        # Consumers --only left out: waited for only as long as discovery takes (one already running in another
        # launch is seen within it and still hears frame 0), not the whole timeout for one nobody will start.
        self.left_out = self.waiting_for & set(filter(None, os.environ.get(LEFT_OUT_NODES_ENV, "").split(",")))
        self.waiting_for.discard(name)
        self._health = HealthWatcher(session, graph.namespace, watch_status=False)
        self._deadline = time.monotonic() + timeout_s
        self._left_out_deadline = time.monotonic() + min(timeout_s, LEFT_OUT_DISCOVERY_S)

    def wait_s(self) -> float:
        """Seconds to wait before the first message (0: go)."""
        if self._open_at == -math.inf:
            return 0.0
        if self._open_at is None:
            assert self._health is not None
            missing = self.missing = self.waiting_for - self._health.alive()
            now = time.monotonic()
            if missing - self.left_out and now < self._deadline or missing and now < self._left_out_deadline:
                return 0.05
            if missing & self.left_out:
                self.log.info("not waiting for %s: left out of this launch by --only and not running",
                              ", ".join(sorted(missing & self.left_out)))
                missing -= self.left_out
            if missing:
                self.log.warning("starting without %s (not up after %.0f s)", ", ".join(sorted(missing)),
                                 self.timeout_s)
            self.missing = set()
            self._open_at = time.monotonic() + self.settle_s
        return max(0.0, self._open_at - time.monotonic())

    @property
    def opened(self) -> bool:
        """Whether the wait is over (the first message may go)."""
        return self._open_at is not None and time.monotonic() >= self._open_at

    def close(self) -> None:
        if self._health is not None:
            self._health.close()

