"""Bus introspection: topics, echo, hz, nodes, and a plain router."""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable

import numpy as np
import zenoh

from ...bus.codec import DecodeError
from ...bus.health import HealthWatcher, live_namespaces, namespaces_hint, node_state
from ...bus.pubsub import declare_subscriber, frame_bytes, payload_bytes
from ...bus.schemas import decode, to_plain
from ...bus.session import ZenohSettings, open_session
from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)
from ..connect import open_client_session
from .silence import warn_if_silent


def wait_for(seconds: float | None, done: threading.Event | None = None) -> None:
    """Block for ``seconds`` (None: until Ctrl-C), or until ``done`` is set."""
    deadline = None if seconds is None else time.monotonic() + seconds
    while deadline is None or time.monotonic() < deadline:
        if done is not None and done.is_set():
            return
        time.sleep(0.05)


def cmd_topics(args, settings: ZenohSettings, namespace: str) -> int:
    counts: dict[str, list[int]] = defaultdict(list)
    sizes: dict[str, int] = defaultdict(int)
    types: dict[str, str] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            data = frame_bytes(sample)
            msg_type = decode(data).TYPE
        except DecodeError:
            data, msg_type = payload_bytes(sample), "?"
        with lock:
            counts[key].append(time.monotonic_ns())
            sizes[key] += len(data)
            types[key] = msg_type

    session = open_client_session(settings)
    sub = declare_subscriber(session, f"{namespace}/**", on_sample)
    wait_for(args.seconds)
    sub.undeclare()
    session.close()
    if not counts:
        print(f"no messages under {namespace}/** in {args.seconds:.1f} s")
        return 1
    print(f"{'key':<40} {'type':<13} {'rate Hz':>8} {'avg bytes':>10}")
    for key in sorted(counts):
        stamps = counts[key]
        span = (stamps[-1] - stamps[0]) / 1e9
        rate = (len(stamps) - 1) / span if span > 0 else 0.0
        print(f"{key:<40} {types[key]:<13} {rate:>8.1f} {sizes[key] / len(stamps):>10.0f}")
    return 0


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
    print(f"{'node':<14} {'state':<7} {'pid':>7} {'uptime s':>9} {'handler errs':>12}  check")
    for name in sorted(snapshot):
        h = snapshot[name]
        st = h.status
        print(f"{name:<14} {node_state(h.alive, st.extra if st else None):<7} {st.pid if st else '-':>7} "
              f"{(f'{st.uptime_s:.0f}' if st else '-'):>9} {(st.extra.get('handler_errors', 0) if st else '-'):>12}  "
              f"{h.trust}{f' ({h.trust_reason})' if h.trust_reason else ''}")
    return 0


def run_router(listen: list[str], duration_s: float | None) -> int:
    settings = ZenohSettings(mode="router", listen=listen, connect=[])
    session = open_session(settings)
    print(f"zenoh router listening on {', '.join(listen)} (Ctrl-C to stop)", flush=True)
    with contextlib.suppress(KeyboardInterrupt):
        wait_for(duration_s)
    session.close()
    return 0
