"""Input synchronisation by camera frame (like ROS message_filters' exact-time policy, keyed on
``header.frame_seq``), with feedback inputs and a timeout.

A feedback input (``offset = -1``) contributes to frame k's set the message of the *previous frame
this node handled* (k-1 when no frame was skipped upstream): the re-ID of frame k waits for the
template learnt on the frame before it. The first set has no previous frame and does not wait.

A set is emitted when every input is present; after ``timeout_ns`` it is emitted without its
missing *optional* inputs, or dropped if a required one is missing. Sets are emitted in frame
order; an incomplete set is dropped as soon as a newer set is complete, and anything older than
an emitted set is stale. Pure logic, no Zenoh: the caller passes the clock, so it is testable and
replay-deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

FEEDBACK_KEEP = 64  # feedback messages remembered per input


@dataclass
class SyncInput:
    name: str
    offset: int = 0  # 0: same frame; -1: feedback from the previous handled frame
    optional: bool = False


@dataclass
class _Slot:
    first_ns: int
    msgs: dict[str, Any] = field(default_factory=dict)


class FrameSynchronizer:
    def __init__(self, inputs: list[SyncInput], timeout_ns: int, max_pending: int = 64):
        if not inputs:
            raise ValueError("a synchroniser needs at least one input")
        if any(i.offset not in (0, -1) for i in inputs):
            raise ValueError("offset must be 0 or -1")
        if all(i.optional or i.offset for i in inputs):
            raise ValueError("at least one same-frame synchronised input must be required")
        self.inputs = {i.name: i for i in inputs}
        self.timeout_ns = timeout_ns
        self.max_pending = max_pending
        self._slots: dict[int, _Slot] = {}
        self._feedback: dict[str, dict[int, Any]] = {i.name: {} for i in inputs if i.offset}
        self._last_emitted: int | None = None
        self._last_emit_ns = 0
        self.timeouts = 0  # sets emitted without an optional input
        self.dropped = 0  # sets dropped: required input missing at timeout, stale, or overflow

    def add(self, name: str, frame_seq: int, msg: Any, now_ns: int) -> None:
        if name in self._feedback:
            store = self._feedback[name]
            store[frame_seq] = msg
            while len(store) > FEEDBACK_KEEP:
                del store[min(store)]
            return
        if self._last_emitted is not None and frame_seq <= self._last_emitted:
            return  # that frame was already handled
        slot = self._slots.get(frame_seq)
        if slot is None:
            slot = self._slots[frame_seq] = _Slot(first_ns=now_ns)
        slot.msgs[name] = msg
        while len(self._slots) > self.max_pending:
            del self._slots[min(self._slots)]
            self.dropped += 1

    def _gather(self, slot: _Slot) -> tuple[dict[str, Any], bool, bool]:
        """(messages, complete, required present) of a slot, feedback inputs included."""
        msgs = dict(slot.msgs)
        complete = required = True
        for name, spec in self.inputs.items():
            if spec.offset:
                if self._last_emitted is None:
                    msgs[name] = None  # the first set has no previous frame to wait for
                    continue
                if self._last_emitted in self._feedback[name]:
                    msgs[name] = self._feedback[name][self._last_emitted]
                    continue
            elif name in msgs:
                continue
            complete = False
            required = required and spec.optional
        return msgs, complete, required

    def poll(self, now_ns: int) -> list[tuple[int, dict[str, Any]]]:
        """Sets ready to be handled, in frame order."""
        ready: list[tuple[int, dict[str, Any]]] = []
        for seq in sorted(self._slots):
            slot = self._slots[seq]
            msgs, complete, required = self._gather(slot)
            expired = now_ns >= self._deadline(slot)
            if complete:
                pass
            elif expired and required:
                self.timeouts += 1
            elif expired or (self._missing_same_frame(slot) and self._newer_complete(seq)):
                # Dropped: a required input never came, or this frame lost an input upstream (a
                # detector that skipped it) while a newer frame is complete: waiting would only add
                # latency. A frame missing only its feedback is not dropped this way: every newer
                # frame waits for the same feedback.
                del self._slots[seq]
                self.dropped += 1
                continue
            else:
                break  # wait for it, bounded by its timeout
            del self._slots[seq]
            ready.append((seq, {name: msgs.get(name) for name in self.inputs}))
            self._last_emitted = seq
            self._last_emit_ns = now_ns
        return ready

    def _deadline(self, slot: _Slot) -> int:
        # A set cannot be handled before its predecessor went out, so its wait starts then.
        return max(slot.first_ns, self._last_emit_ns) + self.timeout_ns

    def _missing_same_frame(self, slot: _Slot) -> bool:
        return any(name not in slot.msgs for name, spec in self.inputs.items() if not spec.offset)

    def _newer_complete(self, seq: int) -> bool:
        return any(not self._missing_same_frame(self._slots[later]) for later in self._slots if later > seq)

    def next_deadline_ns(self) -> int | None:
        if not self._slots:
            return None
        return min(self._deadline(s) for s in self._slots.values())

    @property
    def pending(self) -> int:
        return len(self._slots)
