"""Bus introspection: topics, echo, hz, nodes, and a plain router."""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from ...bus.codec import DecodeError
from ...bus.health import HealthWatcher, live_namespaces, namespaces_hint, node_state
from ...bus.links import PublishedKeys, links_of_statuses, short_of_sent
from ...bus.node_runtime import STATUS_PERIOD_S
from ...bus.pubsub import declare_subscriber, frame_bytes, payload_bytes
from ...bus.schemas import decode, to_plain
from ...bus.session import ZenohSettings, open_session
from ...bus.stats import SequenceGaps
from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)
from ..connect import is_raw_frame, is_remote, open_client_session
from .silence import warn_if_silent


def wait_for(seconds: float | None, done: threading.Event | None = None) -> None:
    """Block for ``seconds`` (None: until Ctrl-C), or until ``done`` is set."""
    deadline = None if seconds is None else time.monotonic() + seconds
    while deadline is None or time.monotonic() < deadline:
        if done is not None and done.is_set():
            return
        time.sleep(0.05)


STATUS_WAIT_S = 2.0  # over a network, topics waits this long for the nodes' first statuses (their keys)


@dataclass
class _KeySeen:
    """What arrived on one key: messages, bytes, type, and per publisher (``header.source``) its first and last
    (seq, pub_ns), which give the rate it publishes at however many the link lost on the way."""

    count: int = 0
    size: int = 0
    type: str = "?"
    lost: int = 0
    ends: dict[str, list[tuple[int, int]]] = field(default_factory=dict)
    arrivals: list[int] = field(default_factory=lambda: [0, 0])  # monotonic ns of the first and last

    def received_hz(self) -> float | None:
        """How fast they arrived here, between the first and the last (None: fewer than two)."""
        span_s = (self.arrivals[1] - self.arrivals[0]) / 1e9
        return (self.count - 1) / span_s if self.count > 1 and span_s > 0 else None

    def publisher_rate_hz(self) -> float | None:
        """The busiest publisher's own rate (None: fewer than two of its messages arrived)."""
        spans = [(last[0] - first[0], (last[1] - first[1]) / 1e9) for first, last in self.ends.values()]
        seqs, seconds = max(spans, default=(0, 0.0))
        return seqs / seconds if seqs > 0 and seconds > 0 else None


class TopicCounts:
    """The keys seen by `topics`, fed from Zenoh's callback thread."""

    def __init__(self) -> None:
        self.keys: dict[str, _KeySeen] = defaultdict(_KeySeen)
        self._gaps = SequenceGaps()
        self._lock = threading.Lock()

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            data = frame_bytes(sample)
            msg = decode(data)
        except DecodeError:
            data, msg = payload_bytes(sample), None
        now = time.monotonic_ns()
        with self._lock:
            seen = self.keys[key]
            seen.arrivals[0] = seen.arrivals[0] or now
            seen.arrivals[1] = now
            seen.count += 1
            seen.size += len(data)
            if msg is None:
                return
            seen.type = msg.TYPE
            h = msg.header
            ends = seen.ends.setdefault(h.source, [(h.seq, h.pub_ns), (h.seq, h.pub_ns)])
            missing = self._gaps.see((key, h.source), h.seq)
            if missing < 0:  # the publisher restarted: its rate from here
                ends[0] = (h.seq, h.pub_ns)
            seen.lost += max(missing, 0)
            ends[1] = (h.seq, h.pub_ns)

    def table(self) -> list[str]:
        with self._lock:
            keys = dict(self.keys)
        lines = [f"{'key':<40} {'type':<15} {'rate Hz':>8} {'recv Hz':>8} {'lost':>6} {'avg bytes':>10}"]
        for key in sorted(keys):
            seen = keys[key]
            rate, received = seen.publisher_rate_hz(), seen.received_hz()
            lines.append(f"{key:<40} {seen.type:<15} {_hz(rate):>8} {_hz(received):>8} {seen.lost:>6} "
                         f"{seen.size / seen.count:>10.0f}")
        return lines


def _hz(rate: float | None) -> str:
    return "-" if rate is None else f"{rate:.1f}"


def cmd_topics(args, settings: ZenohSettings, namespace: str) -> int:
    """Every key with traffic: its publisher's rate (from header.seq and pub_ns, so a slow link that loses
    messages does not lower it), what arrived here, what was lost on the way. Over a network, the keys the nodes'
    statuses announce, raw frames left out unless --raw-frames (bus/links.py PublishedKeys)."""
    counts = TopicCounts()
    started = time.monotonic()
    session = open_client_session(settings)
    announced = PublishedKeys(session, namespace) if is_remote(settings) and not args.raw_frames else None
    if announced is not None and not announced.wait(STATUS_WAIT_S):
        announced.close()
        print(f"no node status under {namespace}/@status in {STATUS_WAIT_S:g} s: no graph there to list "
              f"(--raw-frames subscribes to every key under {namespace}/**)")
        _say_where_graphs_are(session, namespace)
        session.close()
        return 1
    listened_s = _listen(announced, session, counts, namespace, args.seconds)
    listed = announced.announced() if announced is not None else {}
    unannounced = announced.unannounced() if announced is not None else []
    left_out = {k: v for k, v in listed.items() if is_raw_frame(k)}
    silent = {k: v for k, v in listed.items() if k not in left_out and k not in counts.keys}
    if announced is not None:
        announced.close()
    if not counts.keys and not left_out:
        print(f"no messages under {namespace}/** in {args.seconds:.1f} s")
        _say_where_graphs_are(session, namespace)
        session.close()
        _unannounced_note(unannounced, time.monotonic() - started)
        return 1
    session.close()
    print("\n".join(counts.table()))
    _topics_notes(counts, left_out, silent, args.seconds, listened_s)
    _unannounced_note(unannounced, time.monotonic() - started)
    return 0


def _say_where_graphs_are(session: zenoh.Session, namespace: str) -> None:
    """Nothing under ``namespace``: the namespaces whose nodes are alive, if any (a mistyped or defaulted
    --namespace), as `nodes` and `monitor` say."""
    found = live_namespaces(session)
    if found and namespace not in found:  # nodes alive here but silent: the notes below say so
        print(namespaces_hint(namespace, found))


def _unannounced_note(nodes: list[str], waited_s: float) -> None:
    """Nodes up by their liveliness tokens whose status never came: their keys are missing from the table, and a
    user reading it must not take them for nodes that publish nothing."""
    if nodes:
        print(f"no status from {', '.join(nodes)} in {waited_s:.1f} s over this link, though their liveliness "
              "tokens say they are up: their keys are not listed (a link too full for the statuses, or nodes still "
              "starting; `followbus nodes` shows their health)")


def _listen(announced: PublishedKeys | None, session: zenoh.Session, counts: TopicCounts, namespace: str,
            seconds: float) -> dict[str, float]:
    """Count what arrives for ``seconds``: the announced keys, each subscribed to as it is announced, or (nothing
    announced: the local bus) the whole namespace. Returns the seconds each key was listened to."""
    subs: dict[str, tuple[Any, float]] = {}  # key -> its subscriber and when it was declared (time.monotonic)
    if announced is None:
        subs[f"{namespace}/**"] = (declare_subscriber(session, f"{namespace}/**", counts.on_sample), time.monotonic())
    else:
        # Each node announces once a status period, so the window opens once every one of them could have: a key
        # announced late in it (a loaded robot, a slow link) would show nothing.
        _follow_announcements(announced, subs, session, counts, time.monotonic() + STATUS_PERIOD_S + 0.25)
    # A node that starts during the window announces its keys then.
    _follow_announcements(announced, subs, session, counts, time.monotonic() + seconds)
    listened_s = {key: min(seconds, time.monotonic() - since) for key, (_sub, since) in subs.items()}
    for sub, _since in subs.values():
        sub.undeclare()
    return listened_s


def _follow_announcements(announced: PublishedKeys | None, subs: dict[str, tuple[Any, float]], session: zenoh.Session,
                          counts: TopicCounts, until: float) -> None:
    """Subscribe to each key as the nodes announce it (raw frames left out) until ``until`` (time.monotonic); with
    nothing announced (the local bus, subscribed whole) only wait."""
    while time.monotonic() < until:
        for key in announced.announced() if announced is not None else ():
            if key not in subs and not is_raw_frame(key):
                subs[key] = (declare_subscriber(session, key, counts.on_sample), time.monotonic())
        time.sleep(0.05)


def _topics_notes(counts: TopicCounts, left_out: dict[str, Any], silent: dict[str, Any], seconds: float,
                  listened_s: dict[str, float]) -> None:
    """What the table's figures mean where it matters: keys announced but silent here (for as long as they were
    listened to: a key announced late in the window had less), keys not subscribed, rates not measured, losses."""
    for key, info in sorted(silent.items()):
        listened = listened_s.get(key, 0.0)
        span = f"in {seconds:g} s" if listened >= seconds - 0.05 else (
            f"in the {listened:.1f} s since {info.node}'s status announced it")
        print(f"nothing arrived: {key} ({info.rate_hz:.1f} Hz by {info.node}'s status) {span} over this link")
    for key, info in sorted(left_out.items()):
        size = f"{info.mean_bytes / 1e3:.1f} KB a message" if info.mean_bytes else "no message yet"
        print(f"not subscribed: {key} (raw frames, {size}, {info.rate_hz:.1f} Hz by {info.node}'s status; "
              "over this link only with --raw-frames)")
    if any(seen.publisher_rate_hz() is None for seen in counts.keys.values()):
        print(f"-: fewer than two messages (of one publisher) arrived in {seconds:g} s: no rate to show")
    if any(seen.lost for seen in counts.keys.values()):
        print("lost: messages the link did not deliver (header.seq gaps); rate Hz is the publisher's, recv Hz what "
              "arrived here")


def cmd_echo(args, settings: ZenohSettings, namespace: str) -> int:
    done = threading.Event()
    seen = [0]

    def on_sample(sample: zenoh.Sample) -> None:
        if done.is_set():
            return
        try:
            msg = decode(frame_bytes(sample))
            text = json.dumps(to_plain(msg), default=str)
        except DecodeError as exc:
            text = json.dumps({"key": str(sample.key_expr), "decode_error": str(exc)})
        print(f"{sample.key_expr}: {text}", flush=True)
        seen[0] += 1
        if args.count is not None and seen[0] >= args.count:
            done.set()

    session = open_client_session(settings)
    sub = declare_subscriber(session, args.key, on_sample)
    silence = warn_if_silent(session, args.key, namespace, args.graph, lambda: seen[0] > 0, args.timeout)
    first = _wait_first(lambda: seen[0] > 0, args.timeout, args.seconds, done)
    if first:
        wait_for(None if args.seconds is None else max(0.0, args.seconds - first), done)
    silence.cancel()
    sub.undeclare()
    session.close()
    limits = [t for t in (args.timeout, args.seconds) if t is not None]
    if not seen[0] and limits and not done.is_set():
        _no_message(args.key, min(limits))
    return 0 if seen[0] else 1


def _wait_first(arrived: Callable[[], bool], timeout_s: float | None, seconds: float | None,
                done: threading.Event | None = None) -> float:
    """Wait for the first message at most ``timeout_s`` (and ``seconds``); returns the seconds waited, 0 if
    nothing came (or the wait was cut short by ``done``)."""
    limits = [t for t in (timeout_s, seconds) if t is not None]
    deadline = time.monotonic() + min(limits) if limits else None
    start = time.monotonic()
    while not arrived():
        if (deadline is not None and time.monotonic() >= deadline) or (done is not None and done.is_set()):
            return 0.0
        time.sleep(0.05)
    return max(time.monotonic() - start, 1e-9)


def _no_message(key: str, timeout_s: float) -> None:
    print(f"followbus: no message on {key} in {timeout_s:g} s (`followbus topics` lists the keys with traffic)",
          file=sys.stderr)


def cmd_hz(args, settings: ZenohSettings, namespace: str) -> int:
    lock = threading.Lock()
    arrivals: list[int] = []
    latencies: list[float] = []

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.time_ns()
        try:
            stamp = decode(frame_bytes(sample)).header.stamp_ns
        except DecodeError:
            stamp = 0
        with lock:
            arrivals.append(now)
            if stamp > 0:
                latencies.append((now - stamp) / 1e6)

    session = open_client_session(settings)
    sub = declare_subscriber(session, args.key, on_sample)
    silence = warn_if_silent(session, args.key, namespace, args.graph, lambda: bool(arrivals), args.timeout)
    start = time.monotonic()
    if args.timeout is not None and not _wait_first(lambda: bool(arrivals), args.timeout, args.seconds):
        silence.cancel()
        sub.undeclare()
        session.close()
        _no_message(args.key, args.timeout)
        return 1
    try:
        while args.seconds is None or time.monotonic() - start < args.seconds:
            time.sleep(1.0)
            with lock:
                recent = [t for t in arrivals if t > time.time_ns() - 5_000_000_000]
                lat = np.array(latencies[-300:])
            rate = (len(recent) - 1) / ((recent[-1] - recent[0]) / 1e9) if len(recent) > 1 else 0.0
            lat_text = (f"latency p50 {np.percentile(lat, 50):.1f} ms p99 {np.percentile(lat, 99):.1f} ms"
                        if lat.size else "latency n/a")
            print(f"{args.key}: {rate:.1f} Hz ({len(arrivals)} msgs), {lat_text}", flush=True)
    finally:
        silence.cancel()
        sub.undeclare()
        session.close()
    return 0 if arrivals else 1


def cmd_nodes(args, settings: ZenohSettings, namespace: str) -> int:
    session = open_client_session(settings)
    watcher = HealthWatcher(session, namespace)
    wait_for(args.seconds)
    snapshot = watcher.snapshot()
    watcher.close()
    found = live_namespaces(session) if not snapshot else {}
    session.close()
    if not snapshot:
        print(namespaces_hint(namespace, found))
        return 1
    print(f"{'node':<14} {'state':<7} {'pid':>7} {'uptime s':>9} {'handler errs':>12} {'lost in':>8}  check")
    for name in sorted(snapshot):
        h = snapshot[name]
        st = h.status
        lost = sum(int(t.get("lost", 0)) for t in st.topics.values() if t.get("direction") == "in") if st else "-"
        print(f"{name:<14} {node_state(h.alive, st.extra if st else None):<7} {st.pid if st else '-':>7} "
              f"{(f'{st.uptime_s:.0f}' if st else '-'):>9} {(st.extra.get('handler_errors', 0) if st else '-'):>12} "
              f"{lost:>8}  {h.trust}{f' ({h.trust_reason})' if h.trust_reason else ''}")
    _print_links({name: h.status for name, h in snapshot.items() if h.status is not None}, args.links)
    return 0


def _print_links(statuses: dict, every: bool) -> None:
    """The links between nodes (bus/links.py): those that cross hosts, have lost messages or deliver less than
    is sent, or ``every`` one."""
    rows = [link for link in links_of_statuses(statuses)
            if every or link.crosses_hosts or link.lost or short_of_sent(link)]
    if not rows:
        return
    width = max(len(link.route()) for link in rows)
    print(f"\n{'link':<{width}} {'sent Hz':>8} {'delivered Hz':>12} {'lost':>8}")
    for link in rows:
        sent = "-" if link.sent_hz is None else f"{link.sent_hz:.1f}"
        print(f"{link.route():<{width}} {sent:>8} {link.delivered_hz or 0.0:>12.1f} {link.lost:>8}")


def run_router(listen: list[str], duration_s: float | None) -> int:
    settings = ZenohSettings(mode="router", listen=listen, connect=[])
    session = open_session(settings)
    print(f"zenoh router listening on {', '.join(listen)} (Ctrl-C to stop)", flush=True)
    with contextlib.suppress(KeyboardInterrupt):
        wait_for(duration_s)
    session.close()
    return 0
