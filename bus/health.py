"""Node health from Zenoh liveliness tokens (``<ns>/@health/<node>``) and status messages
(``<ns>/@status/<node>``, once a second), cross-checked against the launchers' process tables
(``<ns>/@launcher/<launcher id>``, once a second and on every start and exit).

A liveliness token only says that *some* session declared that key: on a bus without access control any
local process can declare ``fb/@health/<node>`` and keep a dead node looking alive. The launcher knows
better (it started the process and saw it exit), so a node is shown down when a fresh launcher table says
its process is gone, whatever the token says, and a contradiction is flagged ``spoofed?``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from .codec import DecodeError
from .liveness import SOURCE_FINISHED, SOURCE_STALLED
from .pubsub import direct_callback, payload_bytes
from .schemas import NodeStatus, decode

log = logging.getLogger(__name__)

LAUNCHER_SEGMENT = "@launcher"
LAUNCHER_PERIOD_S = 1.0  # the launcher republishes its table this often (and at once on every change)
LAUNCHER_STALE_S = 5.0  # a table not refreshed for this long is ignored (its launcher is gone)
# A token and the launcher can disagree for a moment (a node that just died: its exit is seen before its
# token's DELETE arrives): a token alive this long after the launcher saw its process exit is flagged.
MISMATCH_GRACE_S = 2.0
MAX_WATCHED_NODES = 256  # names a HealthWatcher watches; tokens and statuses of more are ignored
SPOOF_HOLD_S = 10.0  # a status from a pid the launcher never ran keeps the node flagged this long

VERIFIED = "verified"  # a fresh launcher table agrees with the token (and the status pid)
UNVERIFIED = "unverified"  # no launcher speaks for this node (started by hand, or no table yet)
SPOOFED = "spoofed?"  # the launcher contradicts the token or the status pid


def node_state(alive: bool, extra: dict[str, Any] | None) -> str:
    """A node table's state column: ``down``; ``stalled``, a source that publishes nothing (its status says so:
    bus/liveness.py SourceActivity); ``done``, a source that published every frame it had; else ``up``."""
    if not alive:
        return "down"
    return {SOURCE_STALLED: "stalled", SOURCE_FINISHED: "done"}.get((extra or {}).get("source"), "up")


def launcher_key(namespace: str, launcher_id: str) -> str:
    return f"{namespace}/{LAUNCHER_SEGMENT}/{launcher_id}"


def launcher_id(host: str, pid: int) -> str:
    """A key-safe, unique name for one launcher: host and pid (key expressions forbid ``* $ # ? /``)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", f"{host}-{pid}")


@dataclass
class LaunchedProcess:
    """One line of a launcher's process table."""

    pid: int
    running: bool
    restarts: int = 0
    exit_code: int | None = None
    since_s: float = 0.0  # since the process started (running) or exited, when the table was published
    changed_ns: int = 0  # the same moment on the receiver's clock (set on receipt; no clock sync needed)

    def as_dict(self) -> dict[str, Any]:
        return {"pid": self.pid, "running": self.running, "restarts": self.restarts, "exit_code": self.exit_code,
                "since_s": round(self.since_s, 3)}

    @classmethod
    def from_dict(cls, data: Any, received_ns: int = 0) -> LaunchedProcess:
        if not isinstance(data, dict):
            raise DecodeError("process entry is not a map")
        pid, running = data.get("pid"), data.get("running")
        restarts, code, since_s = data.get("restarts", 0), data.get("exit_code"), data.get("since_s", 0.0)
        if (not isinstance(pid, int) or not isinstance(running, bool) or not isinstance(restarts, int)
                or not (code is None or isinstance(code, int)) or not isinstance(since_s, (int, float))
                or not 0 <= since_s < 1e9):
            raise DecodeError(f"bad process entry {data!r}")
        return cls(pid, running, restarts, code, float(since_s), received_ns - int(since_s * 1e9))


def process_table(launcher: str, processes: dict[str, LaunchedProcess], pid: int, uptime_s: float,
                  stopped: bool = False) -> NodeStatus:
    """The launcher's table as a NodeStatus (``extra["processes"]``); ``stopped`` retracts it."""
    msg = NodeStatus(node=launcher, pid=pid, uptime_s=uptime_s, state="stopped" if stopped else "running",
                     extra={"processes": {name: p.as_dict() for name, p in processes.items()}})
    msg.header.stamp_ns = time.time_ns()
    return msg


@dataclass
class NodeHealth:
    name: str
    alive: bool = False  # the token is alive and no fresh launcher table says the process is gone
    since_ns: int = 0
    ups: int = 0  # times the node came up: ups - 1 restarts seen by this watcher
    status: NodeStatus | None = None
    status_ns: int = 0
    history: list[tuple[int, bool]] = field(default_factory=list)
    token_alive: bool = False  # what the liveliness token alone says
    launched: LaunchedProcess | None = None  # this node's line in a fresh launcher table, if any
    trust: str = UNVERIFIED  # VERIFIED | UNVERIFIED | SPOOFED
    trust_reason: str = ""
    token_seen: bool = False
    launcher_pids: set[int] = field(default_factory=set)  # every pid a launcher reported for this node
    bad_status_ns: int = 0  # when a status last came from a pid no launcher ran for this node
    bad_status_pid: int = 0

    @property
    def restarts(self) -> int:
        return max(0, self.ups - 1)


class HealthWatcher:
    """Follows liveliness and status of every node in a namespace.

    With ``cross_check`` (default: on when ``watch_status`` is) it also follows the launchers' process
    tables: ``alive`` then means "token alive and not contradicted by the launcher", and each node carries a
    ``trust`` verdict. Readiness checks inside the graph (launcher, node start-up barrier) keep raw tokens.
    """

    def __init__(self, session: zenoh.Session, namespace: str,
                 on_change: Callable[[str, bool], None] | None = None, watch_status: bool = True,
                 cross_check: bool | None = None, mismatch_grace_s: float = MISMATCH_GRACE_S,
                 launcher_stale_s: float = LAUNCHER_STALE_S, spoof_hold_s: float = SPOOF_HOLD_S):
        self.namespace = namespace
        self.on_change = on_change
        self.nodes: dict[str, NodeHealth] = {}
        self.cross_check = watch_status if cross_check is None else cross_check
        self.mismatch_grace_ns = int(mismatch_grace_s * 1e9)
        self.launcher_stale_ns = int(launcher_stale_s * 1e9)
        self.spoof_hold_ns = int(spoof_hold_s * 1e9)
        self.bad_tables = 0  # launcher tables that did not decode (counted and dropped)
        self.ignored = 0  # tokens and statuses of names past MAX_WATCHED_NODES (counted and dropped)
        self._tables: dict[str, tuple[int, dict[str, LaunchedProcess]]] = {}  # launcher id -> (received, table)
        self._lock = threading.Lock()
        prefix = f"{namespace}/@health/"
        self._prefix = prefix
        self._live_sub = session.liveliness().declare_subscriber(
            f"{prefix}*", direct_callback(self._on_liveliness), history=True)
        self._status_sub = (session.declare_subscriber(f"{namespace}/@status/*", direct_callback(self._on_status))
                            if watch_status else None)
        self._launcher_sub = (session.declare_subscriber(launcher_key(namespace, "*"),
                                                         direct_callback(self._on_launcher))
                              if self.cross_check else None)

    def _node(self, name: str) -> NodeHealth | None:
        """The node's entry, made on first sight; None past MAX_WATCHED_NODES names (a flood of tokens or
        statuses under made-up names must not grow this process, nor the work of every update, without bound)."""
        health = self.nodes.get(name)
        if health is None:
            if len(self.nodes) >= MAX_WATCHED_NODES:
                self.ignored += 1
                return None
            health = self.nodes[name] = NodeHealth(name)
        return health

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr)[len(self._prefix):]
        with self._lock:
            health = self._node(name)
            if health is None:
                return
            health.token_alive = sample.kind == zenoh.SampleKind.PUT
            health.token_seen = True
            changes = self._update(time.time_ns())
        self._notify(changes)

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = decode(payload_bytes(sample), NodeStatus)
        except DecodeError:
            return
        now = time.time_ns()
        with self._lock:
            health = self._node(status.node)
            if health is None:
                return
            health.status = status
            health.status_ns = now
            # Any pid a launcher ever ran for this node is genuine (an old one is a status still in flight
            # from before a restart); another pid means a second publisher under this node's name.
            if health.launched is not None and status.pid not in health.launcher_pids:
                health.bad_status_ns, health.bad_status_pid = now, status.pid

    def _on_launcher(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            msg = decode(payload_bytes(sample), NodeStatus)
            entries = msg.extra.get("processes")
            if not isinstance(entries, dict):
                raise DecodeError("no process table")
            now = time.time_ns()
            table = {str(name): LaunchedProcess.from_dict(entry, now) for name, entry in entries.items()}
        except DecodeError as exc:
            with self._lock:
                self.bad_tables += 1
            log.debug("dropped a bad launcher table on %s: %s", key, exc)
            return
        launcher = key.rsplit("/", 1)[-1]
        with self._lock:
            if msg.state == "stopped":
                self._tables.pop(launcher, None)
            else:
                self._tables[launcher] = (now, table)
            changes = self._update(now)
        self._notify(changes)

    def _update(self, now_ns: int) -> list[tuple[str, bool]]:
        """Recompute every node's effective liveness and trust (caller holds the lock); returns the
        liveness changes to report."""
        launched: dict[str, tuple[int, LaunchedProcess]] = {}
        for launcher, (received_ns, table) in list(self._tables.items()):
            if now_ns - received_ns > self.launcher_stale_ns:
                del self._tables[launcher]
                continue
            for name, proc in table.items():
                if name not in launched or received_ns > launched[name][0]:
                    launched[name] = (received_ns, proc)
        changes = []
        for name in set(self.nodes) | set(launched):
            health = self._node(name)
            if health is None:
                continue
            proc = launched[name][1] if name in launched else None
            if proc is not None and len(health.launcher_pids) < 1000:
                health.launcher_pids.add(proc.pid)
            health.launched = proc
            self._judge(health, now_ns)
            alive = health.token_alive and (proc is None or proc.running)
            if not health.token_seen or (alive == health.alive and health.since_ns):
                continue
            health.alive = alive
            health.since_ns = now_ns
            if alive:
                health.ups += 1
            health.history.append((now_ns, alive))
            changes.append((name, alive))
        return changes

    def _judge(self, health: NodeHealth, now_ns: int) -> None:
        proc = health.launched
        trust, reason = VERIFIED, ""
        if proc is None:
            trust = UNVERIFIED
        elif health.token_alive and not proc.running:
            reason = f"token alive but the launcher saw pid {proc.pid} exit (status {proc.exit_code})"
            trust = SPOOFED if now_ns - proc.changed_ns >= self.mismatch_grace_ns else UNVERIFIED
        elif health.bad_status_ns and now_ns - health.bad_status_ns < self.spoof_hold_ns:
            reason = f"status from pid {health.bad_status_pid}, which the launcher never ran (it runs {proc.pid})"
            trust = SPOOFED
        if trust == SPOOFED and health.trust != SPOOFED:
            log.warning("node %s: %s", health.name, reason)
        health.trust, health.trust_reason = trust, reason

    def _notify(self, changes: list[tuple[str, bool]]) -> None:
        if self.on_change is not None:
            for name, alive in changes:
                self.on_change(name, alive)

    def _refresh(self) -> None:
        # Table staleness and the mismatch grace depend on time, not only on samples: re-judge on every read.
        with self._lock:
            changes = self._update(time.time_ns())
        self._notify(changes)

    def alive(self) -> set[str]:
        self._refresh()
        with self._lock:
            return {n for n, h in self.nodes.items() if h.alive}

    def snapshot(self) -> dict[str, NodeHealth]:
        self._refresh()
        with self._lock:
            return {n: dataclasses.replace(h, history=list(h.history), launcher_pids=set(h.launcher_pids))
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
        for sub in (self._live_sub, self._status_sub, self._launcher_sub):
            if sub is not None:
                with contextlib.suppress(Exception):
                    sub.undeclare()


def live_namespaces(session: zenoh.Session, timeout_s: float = 1.0) -> dict[str, list[str]]:
    """Every namespace with a node's liveliness token, and its nodes: what a tool watching an empty namespace
    can suggest instead (``**/@health/*``: the ``@health`` chunk is matched verbatim, ``**`` the namespace)."""
    found: dict[str, set[str]] = {}
    with contextlib.suppress(Exception):  # a refused or closed session: nothing to suggest
        for reply in session.liveliness().get("**/@health/*", timeout=timeout_s):
            with contextlib.suppress(Exception):
                namespace, _, node = str(reply.ok.key_expr).rpartition("/@health/")
                found.setdefault(namespace, set()).add(node)
    return {ns: sorted(nodes) for ns, nodes in sorted(found.items())}


def namespaces_hint(namespace: str, found: dict[str, list[str]]) -> str:
    """One line for a namespace without nodes: which namespaces do have some (and how to pick one)."""
    others = {ns: nodes for ns, nodes in found.items() if ns != namespace}
    if not others:
        return f"no node under {namespace}/@health, and none in any other namespace"
    listed = "; ".join(f"{ns} ({', '.join(nodes)})" for ns, nodes in others.items())
    return f"no node under {namespace}/@health; nodes are alive in: {listed} (pick one with --namespace)"
