"""Node health from Zenoh liveliness tokens (``<ns>/@health/<node>``) and status messages
(``<ns>/@status/<node>``, once a second)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from followbus.bus.codec import DecodeError
from followbus.bus.pubsub import direct_callback, payload_bytes
from followbus.bus.schemas import NodeStatus, decode


@dataclass
class NodeHealth:
    name: str
    alive: bool = False
    since_ns: int = 0
    ups: int = 0  # times the token appeared: ups - 1 restarts seen by this watcher
    status: NodeStatus | None = None
    status_ns: int = 0
    history: list[tuple[int, bool]] = field(default_factory=list)

    @property
    def restarts(self) -> int:
        return max(0, self.ups - 1)


class HealthWatcher:
    """Follows liveliness and status of every node in a namespace."""

    def __init__(self, session: zenoh.Session, namespace: str,
                 on_change: Callable[[str, bool], None] | None = None, watch_status: bool = True):
        self.namespace = namespace
        self.on_change = on_change
        self.nodes: dict[str, NodeHealth] = {}
        self._lock = threading.Lock()
        prefix = f"{namespace}/@health/"
        self._prefix = prefix
        self._live_sub = session.liveliness().declare_subscriber(
            f"{prefix}*", direct_callback(self._on_liveliness), history=True)
        self._status_sub = (session.declare_subscriber(f"{namespace}/@status/*", direct_callback(self._on_status))
                            if watch_status else None)

    def _node(self, name: str) -> NodeHealth:
        health = self.nodes.get(name)
        if health is None:
            health = self.nodes[name] = NodeHealth(name)
        return health

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr)[len(self._prefix):]
        alive = sample.kind == zenoh.SampleKind.PUT
        now = time.time_ns()
        with self._lock:
            health = self._node(name)
            if health.alive == alive and health.since_ns:
                return
            health.alive = alive
            health.since_ns = now
            if alive:
                health.ups += 1
            health.history.append((now, alive))
        if self.on_change is not None:
            self.on_change(name, alive)

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = decode(payload_bytes(sample), NodeStatus)
        except DecodeError:
            return
        with self._lock:
            health = self._node(status.node)
            health.status = status
            health.status_ns = time.time_ns()

    def alive(self) -> set[str]:
        with self._lock:
            return {n for n, h in self.nodes.items() if h.alive}

    def snapshot(self) -> dict[str, NodeHealth]:
        with self._lock:
            return {n: NodeHealth(h.name, h.alive, h.since_ns, h.ups, h.status, h.status_ns, list(h.history))
                    for n, h in self.nodes.items()}

    def wait_for(self, names: set[str], timeout_s: float, stop: threading.Event | None = None) -> set[str]:
        """Wait until every named node is alive; returns the ones still missing."""
        deadline = time.monotonic() + timeout_s
        while True:
            missing = names - self.alive()
            if not missing or time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return missing
            time.sleep(0.05)

    def close(self) -> None:
        for sub in (self._live_sub, self._status_sub):
            if sub is not None:
                with contextlib.suppress(Exception):
                    sub.undeclare()
