"""Per-topic statistics: rate, latency from the frame's capture stamp, drops, messages lost on the way, decode
errors, refusals."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from collections.abc import Hashable
from typing import Any

import numpy as np

WINDOW_S = 5.0
MAX_TRACKED_PUBLISHERS = 256  # publishers whose header.seq a SequenceGaps follows (the oldest seen is forgotten)


class SequenceGaps:
    """Messages never received, from the gaps in each publisher's ``header.seq``.

    Every followbus publisher numbers its messages 0, 1, 2, ... (bus/pubsub.py Publisher), so a receiver that
    sees seq 7 after seq 4 from the same publisher never received two messages: lost on the way (a link that
    dropped them, a publisher that refused one). A seq at or below the last one is a restarted publisher: it is
    followed from there, nothing counted. ``publisher`` is anything naming one (key and ``header.source``).
    """

    def __init__(self, max_publishers: int = MAX_TRACKED_PUBLISHERS):
        self.max_publishers = max_publishers
        self._last: OrderedDict[Hashable, int] = OrderedDict()

    def see(self, publisher: Hashable, seq: int) -> int:
        """The messages missing right before this one (0 when none), or -1 when the publisher restarted."""
        last = self._last.get(publisher)
        self._last[publisher] = seq
        self._last.move_to_end(publisher)
        if last is None:
            while len(self._last) > self.max_publishers:
                self._last.popitem(last=False)
            return 0
        if seq <= last:
            return -1
        return seq - last - 1


class TopicStats:
    """Thread-safe counters for one topic as seen by one node (direction 'in' or 'out')."""

    def __init__(self, key: str, direction: str):
        self.key = key
        self.direction = direction
        self.count = 0
        self.drops = 0
        self.lost = 0  # messages that never arrived (header.seq gaps; inputs only)
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

    def lose(self, n: int) -> None:
        with self._lock:
            self.lost += n

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
                "lost": self.lost,
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
