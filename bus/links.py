"""The links of a graph as its nodes report them: for each key a node subscribes to, what its publisher sent,
what arrived and what never arrived (``header.seq`` gaps, bus/stats.py SequenceGaps). Read from the nodes'
statuses alone (``NodeStatus.topics``; ``extra["host"]`` for the host), so `nodes` and `monitor` on a laptop
see them as the launcher does.

A graph spread over hosts (bus/hosts.py) lives by its links between them, and these fail where no node's own
health shows it: a node "up" on the compute host whose input never arrives (Zenoh peers on two hosts do not
forward each other's messages, so each side hears only the sessions it connected to), or arrives in part (a link
too slow for the frames). The launcher of such a graph watches the links that cross hosts (:class:`LinkWatch`)
and logs each one's delivered rate once it is measured, and again when it changes; one that delivers nothing,
or whose ends do not see each other, is named with what to do.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import zenoh

from .barrier import RECORDER_NAME
from .codec import DecodeError
from .pubsub import direct_callback, payload_bytes
from .schemas import NodeStatus, decode

HOLD_S = 3.0  # a link's new state is reported once it has held this long (no report for a passing blip)
UNSEEN_S = 5.0  # a node of another host whose status has not arrived in this long is reported missing
SENDING_HZ = 1.0  # a publisher at this rate or more is sending: a link that delivers nothing then is silent
LOSSY_FRACTION = 0.9  # a link delivering less than this fraction of what is sent is lossy
PEER_HINT = ("in peer mode, Zenoh peers do not forward each other's messages, so a node on one host hears only the "
             "sessions it connected to: run the robot's bus as a router (graph.robot.yaml) and join the other host "
             "as a client (docs/laptop-and-two-hosts.md)")
LINK_HINT = "check the network between the hosts and that both join the same bus"
MAX_PUBLISHED_KEYS = 1024  # keys a PublishedKeys keeps (statuses naming more are not followed further)


@dataclass(frozen=True)
class Edge:
    """Messages on ``key`` from node ``source`` to node ``target``."""

    key: str
    source: str
    target: str


@dataclass
class LinkFigures:
    """One link as the statuses report it; None where a status has not been seen (or the target does not
    subscribe to the key)."""

    edge: Edge
    source_host: str
    target_host: str
    sent_hz: float | None
    delivered_hz: float | None
    received: int | None
    lost: int | None

    @property
    def crosses_hosts(self) -> bool:
        return self.source_host != self.target_host

    def describe(self) -> str:
        """``t/capture/frame capture (robot) -> detection (gpu): 29.8 of 30.0 Hz delivered, 0 lost``."""
        return f"{self.route()}: {self.figures()}"

    def route(self) -> str:
        def end(node: str, host: str) -> str:
            return f"{node} ({host})" if host else node

        return (f"{self.edge.key} {end(self.edge.source, self.source_host)} -> "
                f"{end(self.edge.target, self.target_host)}")

    def figures(self) -> str:
        sent = "?" if self.sent_hz is None else f"{self.sent_hz:.1f}"
        if self.delivered_hz is None:
            return f"no status from {self.edge.target} (sent {sent} Hz)"
        return f"{self.delivered_hz:.1f} of {sent} Hz delivered, {self.lost} lost"


def edges_of_graph(graph: Any) -> list[Edge]:
    """Every input of every node of a graph (bus/graph/ Graph), as an edge."""
    return [Edge(graph.key(inp.source_node, inp.source_output), inp.source_node, name)
            for name, spec in graph.nodes.items() for inp in spec.inputs.values()]


def edges_of_statuses(statuses: Mapping[str, NodeStatus]) -> list[Edge]:
    """Every key a node reports as an input, from each node that reports it as an output."""
    publishers: dict[str, list[str]] = {}
    for name, status in statuses.items():
        for key, topic in status.topics.items():
            if topic.get("direction") == "out":
                publishers.setdefault(key, []).append(name)
    return [Edge(key, source, name) for name, status in sorted(statuses.items())
            for key, topic in sorted(status.topics.items()) if topic.get("direction") == "in"
            for source in publishers.get(key, [])]


def _host(name: str, statuses: Mapping[str, NodeStatus], hosts: Mapping[str, str] | None) -> str:
    if hosts is not None and hosts.get(name):
        return hosts[name]
    status = statuses.get(name)
    host = status.extra.get("host") if status is not None else None
    return host if isinstance(host, str) else ""


def _topic(status: NodeStatus | None, key: str, direction: str) -> dict[str, Any] | None:
    topic = status.topics.get(key) if status is not None else None
    return topic if isinstance(topic, dict) and topic.get("direction") == direction else None


def measure(edges: Iterable[Edge], statuses: Mapping[str, NodeStatus],
            hosts: Mapping[str, str] | None = None) -> list[LinkFigures]:
    """Each edge's figures from the statuses (``hosts``: node -> host, else each status's own)."""
    out = []
    for edge in edges:
        sent = _topic(statuses.get(edge.source), edge.key, "out")
        got = _topic(statuses.get(edge.target), edge.key, "in")
        out.append(LinkFigures(
            edge, _host(edge.source, statuses, hosts), _host(edge.target, statuses, hosts),
            None if sent is None else float(sent.get("rate_hz", 0.0)),
            None if got is None else float(got.get("rate_hz", 0.0)),
            None if got is None else int(got.get("count", 0)), None if got is None else int(got.get("lost", 0))))
    return out


def short_of_sent(link: LinkFigures) -> bool:
    """Whether a link whose publisher sends delivers nothing, or less than :data:`LOSSY_FRACTION` of it."""
    if link.sent_hz is None or link.sent_hz < SENDING_HZ or link.delivered_hz is None:
        return False
    return link.delivered_hz < LOSSY_FRACTION * link.sent_hz


def links_of_statuses(statuses: Mapping[str, NodeStatus]) -> list[LinkFigures]:
    """Every link the statuses show, measured (what `nodes` and `monitor` print)."""
    return measure(edges_of_statuses(statuses), statuses)


@dataclass
class PublishedKey:
    """One key as its publisher's status last reported it."""

    key: str
    node: str
    rate_hz: float
    mean_bytes: float | None  # None: nothing published yet


class PublishedKeys:
    """The keys a namespace's nodes publish, as their statuses announce them (``<ns>/@status/*``, once a second per
    node, a few hundred bytes each): what a tool without the graph file can subscribe to key by key, so that a key
    it leaves out never crosses the link (a subscription on ``<ns>/**`` would carry every key, raw frames too).
    Keeps listening until :meth:`close`: nodes that start later are announced later. Also follows the nodes'
    liveliness tokens (``<ns>/@health/*``, declarations that no full link drops), so a tool can name the nodes that
    are up but whose status has not come (:meth:`unannounced`): their keys are missing from what it lists."""

    def __init__(self, session: zenoh.Session, namespace: str):
        self._lock = threading.Lock()
        self._keys: dict[str, PublishedKey] = {}
        self._statuses = 0
        self._announcing: set[str] = set()  # nodes whose status came
        self._alive: set[str] = set()  # nodes whose liveliness token is up
        self._health_prefix = f"{namespace}/@health/"
        self._sub = session.declare_subscriber(f"{namespace}/@status/*", direct_callback(self._on_status))
        self._live_sub = session.liveliness().declare_subscriber(
            f"{self._health_prefix}*", direct_callback(self._on_liveliness), history=True)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr)[len(self._health_prefix):]
        if name == RECORDER_NAME:  # a recorder's token, not a node's: it has no status
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                if len(self._alive) < MAX_PUBLISHED_KEYS:
                    self._alive.add(name)
            else:
                self._alive.discard(name)

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = decode(payload_bytes(sample), NodeStatus)
        except DecodeError:
            return
        with self._lock:
            self._statuses += 1
            if len(self._announcing) < MAX_PUBLISHED_KEYS:
                self._announcing.add(status.node)
            for key, topic in status.topics.items():
                if not isinstance(topic, dict) or topic.get("direction") != "out":
                    continue
                if key not in self._keys and len(self._keys) >= MAX_PUBLISHED_KEYS:
                    continue
                count, size = topic.get("count", 0), topic.get("bytes", 0)
                mean = size / count if isinstance(count, int) and count > 0 and isinstance(size, int) else None
                rate = topic.get("rate_hz", 0.0)
                self._keys[key] = PublishedKey(key, status.node, float(rate) if isinstance(rate, (int, float))
                                               else 0.0, mean)

    def wait(self, timeout_s: float) -> bool:
        """Wait until a status has arrived (at most ``timeout_s``); whether one did."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if self._statuses:
                    return True
            time.sleep(0.05)
        with self._lock:
            return bool(self._statuses)

    def announced(self) -> dict[str, PublishedKey]:
        with self._lock:
            return dict(self._keys)

    def unannounced(self) -> list[str]:
        """The nodes up by their liveliness token whose status has not come: a link too full for it, or a node
        that has not reported yet. Their keys are not in :meth:`announced`."""
        with self._lock:
            return sorted(self._alive - self._announcing)

    def close(self) -> None:
        for sub in (self._sub, self._live_sub):
            with contextlib.suppress(Exception):
                sub.undeclare()


def _blind(edge: Edge, statuses: Mapping[str, NodeStatus], health: Mapping[str, Any]) -> bool:
    """Whether the edge's source still waits for its target (its start-up barrier, in its status) while the target
    is up as the caller sees it."""
    source, target = statuses.get(edge.source), health.get(edge.target)
    waiting = source.extra.get("waiting_for", []) if source is not None else []
    return isinstance(waiting, list) and edge.target in waiting and target is not None and bool(target.alive)


# --- the launcher's watch over a graph spread over hosts ---------------------------------------------------

OK, LOSSY, SILENT, BLIND, UNSEEN, UNKNOWN = "ok", "lossy", "silent", "blind", "unseen", "unknown"


@dataclass
class _EdgeState:
    reported: str | None = None
    candidate: str = UNKNOWN
    candidate_since: float = 0.0
    received: int | None = None
    received_since: float = 0.0  # when the received count last changed (or was first seen)
    grew: bool = False  # the received count grew while watched: the link carries something


class LinkWatch:
    """The links between this host and others, judged on every :meth:`check` (about once a second) from the nodes'
    health and statuses (bus/health.py HealthWatcher with statuses). Each link's state (delivering, lossy, silent,
    its ends blind to each other, or the other end unseen) is reported when it has held :data:`HOLD_S`; the
    lines come back as (logging level, text) for the caller to log."""

    def __init__(self, edges: Iterable[Edge], hosts: Mapping[str, str], here: str, *, peer_mode: bool = False,
                 hold_s: float = HOLD_S, unseen_s: float = UNSEEN_S):
        self.hosts = dict(hosts)
        self.edges = [e for e in edges if self.hosts.get(e.source) != self.hosts.get(e.target)
                      and here in (self.hosts.get(e.source), self.hosts.get(e.target))]
        self.here = here
        self.hint = PEER_HINT if peer_mode else LINK_HINT
        self.hold_s, self.unseen_s = hold_s, unseen_s
        self._states = {edge: _EdgeState() for edge in self.edges}
        self._started: float | None = None

    def check(self, health: Mapping[str, Any], now_s: float) -> list[tuple[int, str]]:
        """``health``: node name -> bus/health.py NodeHealth (``alive``, ``status``)."""
        if self._started is None:
            self._started = now_s
        statuses = {name: h.status for name, h in health.items() if h.status is not None}
        changed = []
        for link in measure(self.edges, statuses, self.hosts):
            state = self._states[link.edge]
            judged = self._judge(link, state, health, statuses, now_s)
            if judged != state.candidate:
                state.candidate, state.candidate_since = judged, now_s
            if judged not in (state.reported, UNKNOWN) and now_s - state.candidate_since >= self.hold_s:
                state.reported = judged
                changed.append((judged, link))
        return self._lines(changed)

    def _judge(self, link: LinkFigures, state: _EdgeState, health: Mapping[str, Any],
               statuses: Mapping[str, NodeStatus], now_s: float) -> str:
        if link.received is not None and link.received != state.received:
            state.grew = state.grew or (state.received is not None and link.received > state.received)
            state.received, state.received_since = link.received, now_s
        if _blind(link.edge, statuses, health):
            return BLIND
        if statuses.get(self._other(link.edge)) is None:
            assert self._started is not None
            return UNSEEN if now_s - self._started >= self.unseen_s else UNKNOWN
        if link.delivered_hz is None or link.sent_hz is None or link.sent_hz < SENDING_HZ:
            return UNKNOWN  # the target does not subscribe to it (an input its params never read), or nothing sent
        if now_s > state.received_since and not state.grew:  # nothing ever arrived (held like any state)
            return SILENT
        return LOSSY if link.delivered_hz < LOSSY_FRACTION * link.sent_hz else OK

    def _other(self, edge: Edge) -> str:
        """The end of an edge on the other host."""
        return edge.source if self.hosts.get(edge.target) == self.here else edge.target

    def _lines(self, changed: list[tuple[str, LinkFigures]]) -> list[tuple[int, str]]:
        """One line per link delivering (its figures); one per pair of nodes cut apart (their keys together); one
        per host unseen (its nodes together)."""
        lines: list[tuple[int, str]] = []
        pairs: dict[tuple[str, str, str], list[LinkFigures]] = {}
        unseen: dict[str, set[str]] = {}
        for state, link in changed:
            if state == OK:
                lines.append((logging.INFO, f"link {link.describe()}"))
            elif state == LOSSY:
                lines.append((logging.WARNING, f"link {link.describe()}: the link does not carry all of it"))
            elif state == UNSEEN:
                other = self._other(link.edge)
                unseen.setdefault(self.hosts.get(other, ""), set()).add(other)
            else:
                pairs.setdefault((state, link.edge.source, link.edge.target), []).append(link)
        for (state, source, target), links in pairs.items():
            keys = ", ".join(link.edge.key for link in links)
            where = f"{source} ({links[0].source_host}) -> {target} ({links[0].target_host})"
            if state == SILENT:
                sent = max(link.sent_hz or 0.0 for link in links)
                why = (f"nothing delivered in {self.hold_s:.0f} s while {source} sends {sent:.1f} Hz: the hosts do not "
                       "exchange data")
            else:
                why = (f"{source} does not see {target}, which this launcher sees: the hosts' sessions do not reach "
                       "each other")
            lines.append((logging.WARNING, f"links {where} ({keys}): {why}; {self.hint}"))
        for host, nodes in unseen.items():
            lines.append((logging.WARNING, f"no status from {', '.join(sorted(nodes))} (host {host}) in "
                                           f"{self.unseen_s:.0f} s, so this host's nodes are cut off from them: is "
                                           f"`followbus launch GRAPH --host {host}` running, and does it reach this "
                                           f"bus? ({self.hint})"))
        return lines
