"""Per-topic statistics: rate, latency from the frame's capture stamp, drops, decode errors, refusals."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import numpy as np

WINDOW_S = 5.0


class TopicStats:
    """Thread-safe counters for one topic as seen by one node (direction 'in' or 'out')."""

    def __init__(self, key: str, direction: str):
        self.key = key
        self.direction = direction
        self.count = 0
        self.drops = 0
        self.decode_errors = 0
        self.refused = 0  # publications refused before sending (payload over the size limit)
        self.bytes = 0
        self._events: deque[tuple[int, float]] = deque()  # (wall ns, latency ms)
        self._lock = threading.Lock()

    def record(self, stamp_ns: int, size: int = 0, now_ns: int | None = None) -> None:
        now_ns = time.time_ns() if now_ns is None else now_ns
        latency_ms = (now_ns - stamp_ns) / 1e6 if stamp_ns > 0 else float("nan")
        with self._lock:
            self.count += 1
            self.bytes += size
            self._events.append((now_ns, latency_ms))
            self._trim(now_ns)

    def drop(self, n: int = 1) -> None:
        with self._lock:
            self.drops += n

    def decode_error(self) -> None:
        with self._lock:
            self.decode_errors += 1

    def refuse(self) -> None:
        with self._lock:
            self.refused += 1

    def _trim(self, now_ns: int) -> None:
        horizon = now_ns - int(WINDOW_S * 1e9)
        while self._events and self._events[0][0] < horizon:
            self._events.popleft()

    def snapshot(self, now_ns: int | None = None) -> dict[str, Any]:
        now_ns = time.time_ns() if now_ns is None else now_ns
        with self._lock:
            self._trim(now_ns)
            events = list(self._events)
            out: dict[str, Any] = {
                "direction": self.direction,
                "count": self.count,
                "drops": self.drops,
                "decode_errors": self.decode_errors,
                "refused": self.refused,
                "bytes": self.bytes,
            }
        if len(events) >= 2:
            span_s = (events[-1][0] - events[0][0]) / 1e9
            out["rate_hz"] = (len(events) - 1) / span_s if span_s > 0 else 0.0
        else:
            out["rate_hz"] = 0.0
        lat = np.array([e[1] for e in events if e[1] == e[1]], dtype=float)
        out["latency_p50_ms"] = float(np.percentile(lat, 50)) if lat.size else None
        out["latency_p99_ms"] = float(np.percentile(lat, 99)) if lat.size else None
        return out
