"""Input synchronisation by camera frame (like ROS message_filters' exact-time policy, keyed on
``header.frame_seq``), with per-input offsets for feedback loops and a timeout.

An input with ``offset = -1`` contributes its message for frame k-1 to frame k's set: the re-ID of
frame k waits for the template learnt at frame k-1. A set is emitted when every input is present;
after ``timeout_ns`` it is emitted without its missing *optional* inputs, or dropped if a required
one is missing. Sets are emitted in frame order; an incomplete set is dropped as soon as a newer
set is complete, and anything older than an emitted set is stale.
Pure logic, no Zenoh: the caller passes the clock, so it is testable and replay-deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass
class SyncInput:
    name: str
    offset: int = 0
    optional: bool = False


@dataclass
class _Slot:
    first_ns: int
    msgs: dict[str, Any] = field(default_factory=dict)


class FrameSynchronizer:
    def __init__(self, inputs: list[SyncInput], timeout_ns: int, max_pending: int = 64):
        if not inputs:
            raise ValueError("a synchroniser needs at least one input")
        if all(i.optional for i in inputs):
            raise ValueError("at least one synchronised input must be required")
        self.inputs = {i.name: i for i in inputs}
        self.timeout_ns = timeout_ns
        self.max_pending = max_pending
        self._slots: dict[int, _Slot] = {}
        self._last_emitted = -(2**62)
        self.timeouts = 0  # sets emitted without an optional input
        self.dropped = 0  # sets dropped: required input missing at timeout, stale, or overflow

    def add(self, name: str, frame_seq: int, msg: Any, now_ns: int) -> None:
        spec = self.inputs[name]
        slot_seq = frame_seq - spec.offset
        if slot_seq <= self._last_emitted:
            return  # that frame was already handled
        slot = self._slots.get(slot_seq)
        if slot is None:
            slot = self._slots[slot_seq] = _Slot(first_ns=now_ns)
        slot.msgs[name] = msg
        while len(self._slots) > self.max_pending:
            del self._slots[min(self._slots)]
            self.dropped += 1

    def _complete(self, slot: _Slot) -> bool:
        return all(name in slot.msgs for name in self.inputs)

    def _required_present(self, slot: _Slot) -> bool:
        return all(name in slot.msgs for name, spec in self.inputs.items() if not spec.optional)

    def poll(self, now_ns: int) -> list[tuple[int, dict[str, Any]]]:
        """Sets ready to be handled, in frame order."""
        ready: list[tuple[int, dict[str, Any]]] = []
        for seq in sorted(self._slots):
            slot = self._slots[seq]
            expired = now_ns - slot.first_ns >= self.timeout_ns
            if self._complete(slot):
                pass
            elif expired and self._required_present(slot):
                self.timeouts += 1
            elif expired:
                del self._slots[seq]
                self.dropped += 1
                continue
            elif any(self._complete(self._slots[later]) for later in self._slots if later > seq):
                # A newer frame is complete: this one lost an input upstream (a detector that
                # skipped it, say). Waiting would only add latency to the live path.
                del self._slots[seq]
                self.dropped += 1
                continue
            else:
                break  # wait for it, bounded by its timeout
            del self._slots[seq]
            ready.append((seq, {name: slot.msgs.get(name) for name in self.inputs}))
            self._last_emitted = seq
        for seq in [s for s in self._slots if s <= self._last_emitted]:
            del self._slots[seq]
            self.dropped += 1
        return ready

    def next_deadline_ns(self) -> int | None:
        if not self._slots:
            return None
        return min(s.first_ns for s in self._slots.values()) + self.timeout_ns

    @property
    def pending(self) -> int:
        return len(self._slots)
