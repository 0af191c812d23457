"""Input synchronisation by camera frame (like ROS message_filters' exact-time policy, keyed on
``header.frame_seq``), with feedback inputs, bounded lag and sequence checks that heal themselves.

**Frame sets.** The same-frame inputs (``offset = 0``) of one frame_seq form a set. A set is emitted
when every input it waits for is present; after ``timeout_ns`` it is emitted without its missing *optional*
inputs, or dropped if a required one is missing (wherever it stands in frame order). Sets are emitted in
frame order; an incomplete set is dropped as soon as a newer set has all the same-frame inputs it waits for.

**Optional same-frame inputs** are waited for only while they are *on time*, so a producer that is not
running (or has stopped) costs one wait per outage, never one per frame. Before its first message ever an
optional input is not on time: sets go on without it. It is on time once one of its messages arrives
before its set's deadline: before the set was emitted, or after a set that did not wait for it went out
(a producer that needs the set's required input, as one reading the same frame's required input, always comes second;
its message is dropped, but the next sets wait for it). A set that reached its deadline without it puts it
off time again. Sets emitted without an optional input they did not wait for are counted
(``without_optional``); the runtime notes each input a set lacked (-1 in the output's ``header.feedback``)
and a replay's hint makes the replayed set lack it too, whatever the replay's arrival order.

**Feedback.** A feedback input (``offset = -1``) contributes to frame k's set the message of the
*previous frame this node handled* (k-1 when no frame was skipped upstream): a node's frame k
waits for the state another node learnt on the frame before it. The first set has no previous frame and does not
wait. When that message has not come by the set's deadline (its producer dropped the frame, restarted,
or is stopped), the set goes on with the newest feedback at or before the previous handled frame, and
from then on sets stop waiting for feedback until an exact one is there in time again: a producer that
lost a frame costs one wait per outage, never one per frame. Which message was used is returned with
the set (the feedback message itself, whose frame_seq the runtime writes into the output's
``header.feedback``), so a replay can reproduce a live fallback exactly.

**Bounded lag.** A set whose capture stamp is more than ``max_lag_ns`` behind the newest set that has
all its same-frame inputs is dropped (``late``): under load the node re-synchronises on the newest
frame instead of working through a backlog. Lag is measured between capture stamps, so it is the same
live, in a fast-paced evaluation and in a replay.

**Sequence checks** on same-frame inputs, against the newest message seen (no trust in either
direction):

- *stale*: frame_seq at or before the last emitted set: dropped;
- *implausible*: a frame_seq further ahead than the elapsed stamp time allows (``MAX_FRAMES_PER_S``
  plus ``MAX_SEQ_AHEAD``), or a stamp that goes back, or runs ahead by more than
  ``MAX_FRAME_INTERVAL_NS`` per frame: rejected (one forged message cannot freeze the node);
- *restart*: a new ``epoch_ns`` with a newer stamp (the capture restarted and counts from 0 again), or
  ``RESYNC_AFTER_REJECTS`` rejected messages in a row (whatever the cause, the stream we trust is not
  the one arriving): the synchroniser starts afresh on the arriving stream (``resyncs``).

Pure logic, no Zenoh: the caller passes the clock, so it is testable and replay-deterministic.
"""

from __future__ import annotations

from bisect import bisect_right, insort
from dataclasses import dataclass, field
from typing import Any

FEEDBACK_KEEP = 64  # feedback messages remembered per input
_NEVER_NS = 2**63  # no set pending: nothing expires
MAX_SEQ_AHEAD = 64  # frames a stream may jump ahead of the newest one with no stamp time passing...
MAX_FRAMES_PER_S = 1000  # ...plus this many per second of stamp time
MAX_FRAME_INTERVAL_NS = 10_000_000_000  # a stamp may not run ahead by more than 10 s per frame
RESYNC_AFTER_REJECTS = 8  # consecutive stale/implausible messages that mean "the source restarted"

# Verdicts of add()
ACCEPTED, STALE, IMPLAUSIBLE, RESYNCED = "accepted", "stale", "implausible", "resynced"


@dataclass
class SyncInput:
    name: str
    offset: int = 0  # 0: same frame; -1: feedback from the previous handled frame
    optional: bool = False


@dataclass
class _Slot:
    first_ns: int
    stamp_ns: int | None = None
    msgs: dict[str, Any] = field(default_factory=dict)


# What FrameSynchronizer._verdict decides for the first pending set.
_EMIT, _DROP, _WAIT = "emit", "drop", "wait"


@dataclass
class _Candidate:
    """The first pending set, as it stands at a poll: its messages, what it lacks, and its deadline."""

    seq: int
    msgs: dict[str, Any]
    required: bool  # every required same-frame input present
    awaited: bool  # every optional same-frame input it waits for present
    exact: bool  # the feedback of the previous handled frame (or, in a replay, the live set's) present
    deadline: int
    forced: bool  # replay: a frame the live run handled
    expired: bool


class SequenceGuard:
    """The sequence checks of one stream of frame-numbered messages (see the module docstring).

    ``check`` judges a message against the newest accepted one and ``floor`` (the last frame handled:
    anything at or before it is stale); after ``RESYNC_AFTER_REJECTS`` rejections in a row, or on a new
    epoch with a newer stamp, it answers ``resynced``: the caller forgets its state and follows the stream.
    """

    def __init__(self) -> None:
        self.epoch: int | None = None
        self.newest_seq: int | None = None
        self.newest_stamp: int | None = None
        self._reject_streak = 0
        self.stale = 0
        self.implausible = 0
        self.resyncs = 0

    def check(self, seq: int, stamp_ns: int | None, epoch_ns: int, floor: int | None) -> str:
        verdict = self._judge(seq, stamp_ns, epoch_ns, floor)
        if verdict in (STALE, IMPLAUSIBLE):
            self._reject_streak += 1
            if self._reject_streak < RESYNC_AFTER_REJECTS:
                return verdict
            verdict = RESYNCED
        if verdict == RESYNCED:
            self.resyncs += 1
            self.epoch = epoch_ns or None
            self.newest_seq = self.newest_stamp = None
        self._reject_streak = 0
        if epoch_ns and self.epoch is None:
            self.epoch = epoch_ns
        if self.newest_seq is None or seq >= self.newest_seq:
            self.newest_seq = seq
            if stamp_ns is not None:
                self.newest_stamp = stamp_ns
        return verdict

    def _judge(self, seq: int, stamp_ns: int | None, epoch_ns: int, floor: int | None) -> str:
        if epoch_ns and self.epoch is not None and epoch_ns != self.epoch:
            if stamp_ns is None or self.newest_stamp is None or stamp_ns > self.newest_stamp:
                return RESYNCED  # the source restarted: follow it
            self.stale += 1  # in flight from before the restart
            return STALE
        if floor is not None and seq <= floor:
            self.stale += 1
            return STALE
        if self.newest_seq is not None and seq > self.newest_seq and stamp_ns is not None \
                and self.newest_stamp is not None:
            frames_ahead = seq - self.newest_seq
            dt_ns = stamp_ns - self.newest_stamp
            if dt_ns < 0 or frames_ahead > MAX_SEQ_AHEAD + dt_ns * MAX_FRAMES_PER_S // 1_000_000_000 \
                    or dt_ns > frames_ahead * MAX_FRAME_INTERVAL_NS:
                self.implausible += 1
                return IMPLAUSIBLE
        return ACCEPTED

    def epoch_mismatch(self, epoch_ns: int) -> bool:
        return bool(epoch_ns) and self.epoch is not None and epoch_ns != self.epoch


class FrameSynchronizer:
    def __init__(self, inputs: list[SyncInput], timeout_ns: int, max_pending: int = 64,
                 max_lag_ns: int | None = None):
        if not inputs:
            raise ValueError("a synchroniser needs at least one input")
        if any(i.offset not in (0, -1) for i in inputs):
            raise ValueError("offset must be 0 or -1")
        if all(i.optional or i.offset for i in inputs):
            raise ValueError("at least one same-frame synchronised input must be required")
        self.inputs = {i.name: i for i in inputs}
        self.timeout_ns = timeout_ns
        self.max_pending = max_pending
        self.max_lag_ns = max_lag_ns
        self._slots: dict[int, _Slot] = {}
        self._feedback: dict[str, dict[int, Any]] = {i.name: {} for i in inputs if i.offset}
        self._last_emitted: int | None = None
        self._last_emit_ns = 0
        self.guard = SequenceGuard()  # on the same-frame inputs
        self._feedback_lost = False
        self._forced: dict[int, dict[str, int]] = {}  # replay: feedback a live run used for a frame
        self._forced_frames: list[int] = []  # its keys, sorted: a replay hints every frame up front
        self._skipped: set[int] = set()  # replay: frames the live run did not handle
        # Optional same-frame inputs, and those not on time (not waited for): all of them until a first message.
        self.optional = [i.name for i in inputs if i.optional and not i.offset]
        self._off_time: set[str] = set(self.optional)
        self._newest_optional: dict[str, int] = {}  # optional same-frame input -> newest frame_seq accepted
        # Recent sets that went out without an optional input: frame -> (their deadline, the inputs they lacked).
        self._lacked: dict[int, tuple[int, frozenset[str]]] = {}
        self.timeouts = 0  # sets emitted without an input they waited for (feedback included)
        self.without_optional = 0  # sets emitted without an optional same-frame input they did not wait for
        self.dropped = 0  # sets dropped: required input missing at timeout, superseded, or overflow
        self.late = 0  # sets dropped for lagging more than max_lag_ns behind a complete newer one
        self.feedback_fallbacks = 0  # sets that went on with older (or no) feedback
        # A poll's outcome changes only with what was offered (or hinted) since, or once a set's deadline passes:
        # until then polling again returns nothing at once (a node polls after every message it handles).
        self._dirty = True
        self._wake_ns = 0

    # --- input ----------------------------------------------------------------------------------
    def add(self, name: str, frame_seq: int, msg: Any, now_ns: int, *, stamp_ns: int | None = None,
            epoch_ns: int = 0) -> str:
        """Offer one message; returns the verdict (``accepted``, ``stale``, ``implausible``, ``resynced``)."""
        self._dirty = True
        if name in self._feedback:
            return self._add_feedback(name, frame_seq, msg, epoch_ns)
        lacked = self._lacked.get(frame_seq)
        if lacked is not None and name in lacked[1] and not self.guard.epoch_mismatch(epoch_ns):
            # Its set already went out without it: too late for that set, but in time, the next ones wait for it.
            if now_ns <= lacked[0]:
                self._off_time.discard(name)
            return STALE
        verdict = self.guard.check(frame_seq, stamp_ns, epoch_ns, self._last_emitted)
        if verdict in (STALE, IMPLAUSIBLE):
            return verdict
        if verdict == RESYNCED:
            self._restart()
        if name in self.optional:
            self._newest_optional[name] = max(self._newest_optional.get(name, -1), frame_seq)
        slot = self._slots.get(frame_seq)
        if slot is None:
            slot = self._slots[frame_seq] = _Slot(first_ns=now_ns, stamp_ns=stamp_ns)
        slot.msgs[name] = msg
        self._off_time.discard(name)  # arrived before its set went out: on time (a no-op for the others)
        while len(self._slots) > self.max_pending:
            del self._slots[min(self._slots)]
            self.dropped += 1
        return verdict

    def _add_feedback(self, name: str, seq: int, msg: Any, epoch_ns: int) -> str:
        if self.guard.epoch_mismatch(epoch_ns):
            self.guard.stale += 1
            return STALE
        newest = self.guard.newest_seq
        if newest is not None and seq > newest + MAX_SEQ_AHEAD:
            self.guard.implausible += 1  # feedback for a frame nobody has seen: forged or from another run
            return IMPLAUSIBLE
        store = self._feedback[name]
        store[seq] = msg
        while len(store) > FEEDBACK_KEEP:
            del store[min(store)]
        return ACCEPTED

    def _restart(self) -> None:
        self._dirty = True
        self.dropped += len(self._slots)
        self._slots.clear()
        for store in self._feedback.values():
            store.clear()
        self._last_emitted = None
        self._feedback_lost = False
        self._lacked.clear()
        self._newest_optional.clear()
        self._forced.clear()
        self._forced_frames.clear()

    def force_feedback(self, frame_seq: int, used: dict[str, int]) -> None:
        """Replay: frame ``frame_seq`` takes exactly these feedback frames (-1: none), as the live run did."""
        self._dirty = True
        if frame_seq not in self._forced:
            insort(self._forced_frames, frame_seq)
        self._forced[frame_seq] = dict(used)

    def holds_back(self, name: str, seq: int) -> bool:
        """Replay: did the live node receive feedback ``seq`` only after handling a set that joined an older one?
        (A pending set s that joined j < seq < s: had seq been there, s would have joined it.)"""
        # Within a run the feedback a set joins never goes back (newest at or before the previous frame), so
        # the first pending set after seq that joined this input decides: later ones joined the same or newer.
        frames = self._forced_frames
        for i in range(bisect_right(frames, seq), len(frames)):  # indices: no copy of a long list
            j = self._forced[frames[i]].get(name)
            if j is not None and not self._doomed(frames[i]):
                return j < seq
        return False

    def _doomed(self, seq: int) -> bool:
        """Replay: will the handled set of frame ``seq`` never go out? It lacks a required input (the recorder
        lost it) while a newer handled set has all of its own. Such a set must not hold feedback back: the newer
        set may be waiting for exactly that feedback before it can supersede it (a wait on each other until
        max_pending pushed them out, the newer set's outputs missing or made with no feedback)."""
        slot = self._slots.get(seq)
        if slot is None or not self._missing_required(slot):
            return False
        return any(later > seq and later in self._forced and not self._missing_required(other)
                   for later, other in self._slots.items())

    def skip(self, frame_seq: int) -> None:
        """Replay: frame ``frame_seq`` is not handled, as the live run did not handle it."""
        self._dirty = True
        self._skipped.add(frame_seq)

    # --- output ---------------------------------------------------------------------------------
    def _feedback_for(self, name: str, seq: int) -> tuple[Any, bool]:
        """(message, exact) of feedback input ``name`` for the set of frame ``seq``."""
        store = self._feedback[name]
        forced = self._forced.get(seq, {}).get(name)
        if forced is not None:
            return (store.get(forced), forced in store or forced < 0)
        assert self._last_emitted is not None
        if self._last_emitted in store:
            return store[self._last_emitted], True
        older = [s for s in store if s <= self._last_emitted]
        return (store[max(older)] if older else None), False

    def _awaited(self, name: str, seq: int) -> bool:
        """Does the set of frame ``seq`` wait for same-frame input ``name``?"""
        if not self.inputs[name].optional:
            return True
        forced = self._forced.get(seq)
        if forced is not None:  # replay: exactly when the live set had it (an older recording: always)
            return forced.get(name) != -1
        return name not in self._off_time

    def _gather(self, seq: int, slot: _Slot) -> tuple[dict[str, Any], bool, bool, bool]:
        """(messages, required same-frame inputs present, awaited optional ones present, exact feedback) of a slot."""
        msgs = dict(slot.msgs)
        required = awaited = exact = True
        for name, spec in self.inputs.items():
            if spec.offset:
                if self._last_emitted is None and seq not in self._forced:
                    msgs[name] = None  # the first set has no previous frame to wait for
                    continue
                msgs[name], ok = self._feedback_for(name, seq)
                exact = exact and ok
            elif not spec.optional:
                required = required and name in msgs
            elif self._forced.get(seq, {}).get(name) == -1:
                msgs.pop(name, None)  # replay: the live set went out without it
            elif name not in msgs and self._awaited(name, seq):
                awaited = False
        return msgs, required, awaited, exact

    def poll(self, now_ns: int) -> list[tuple[int, dict[str, Any]]]:
        """Sets ready to be handled, in frame order, as (frame_seq, {input: message or None})."""
        if not self._dirty and now_ns < self._wake_ns:
            return []
        ready = self._poll(now_ns)
        self._dirty = False
        self._wake_ns = min((self._deadline(slot) for slot in self._slots.values()), default=_NEVER_NS)
        return ready

    def _poll(self, now_ns: int) -> list[tuple[int, dict[str, Any]]]:
        ready: list[tuple[int, dict[str, Any]]] = []
        if not self._slots:
            return ready
        newest_complete = self._newest_complete_stamp()
        self._drop_expired_incomplete(now_ns)
        behind = False  # a set was skipped for lag: waiting any longer for feedback only adds to it
        for seq in sorted(self._slots):
            slot = self._slots[seq]
            if seq in self._skipped:
                del self._slots[seq]
                self._skipped.discard(seq)
                self.dropped += 1
                continue
            if self._lagging(slot, newest_complete):
                del self._slots[seq]
                self.late += 1
                behind = True
                continue
            candidate = self._candidate(seq, slot, now_ns)
            verdict = self._verdict(candidate, behind)
            if verdict == _WAIT:
                break
            if verdict == _DROP:
                del self._slots[seq]
                self.dropped += 1
                continue
            ready.append(self._emit(candidate, now_ns))
        return ready

    def _newest_complete_stamp(self) -> int | None:
        """The capture stamp of the newest set with all its same-frame inputs (None: no lag bound, or fewer than
        two sets pending: one pending set cannot lag behind another)."""
        if self.max_lag_ns is None or len(self._slots) < 2:
            return None
        return max((s.stamp_ns for seq, s in self._slots.items()
                    if s.stamp_ns is not None and not self._missing_same_frame(s, seq)), default=None)

    def _drop_expired_incomplete(self, now_ns: int) -> None:
        """Drop every set still without a required input at its deadline, wherever it stands.

        Not only once it is first in line: a set waiting for its feedback must not shield sets numbered ahead of
        the stream that will never complete (a flood): they would fill the table, and the overflow would evict the
        stream's own sets (the oldest numbers) before their wait ends, until its numbering caught up. A replay
        knows which frames the live run handled (force_feedback): their inputs are in the recording and come in
        the order they were published, so such a set waits for them whatever the replay clock says (its stamps
        can run far ahead of a live run's arrival times when the whole graph lagged behind the camera); only a
        newer complete set ends its wait (an input the recorder lost)."""
        for seq in [s for s, slot in self._slots.items()
                    if self._missing_required(slot) and now_ns >= self._deadline(slot) and s not in self._forced]:
            del self._slots[seq]
            self._skipped.discard(seq)
            self.dropped += 1

    def _candidate(self, seq: int, slot: _Slot, now_ns: int) -> _Candidate:
        msgs, required, awaited, exact = self._gather(seq, slot)
        deadline = self._deadline(slot)
        # A set the live run handled (replay) does not expire: the inputs it had live are still to come in the
        # recording's order, whatever the replay clock says. It stops waiting only when a newer handled set is
        # ready in full (an input the recorder lost).
        forced = seq in self._forced
        return _Candidate(seq, msgs, required, awaited, exact, deadline, forced,
                          expired=now_ns >= deadline and not forced)

    def _verdict(self, c: _Candidate, behind: bool) -> str:
        """Whether the first pending set goes out now (_EMIT), is dropped (_DROP) or is waited for (_WAIT)."""
        if not c.required:
            # A required input never came, or this frame lost an input upstream (a detector that skipped it)
            # while a newer frame is complete: waiting would only add latency. Else wait, bounded by the timeout.
            return _DROP if c.expired or self._superseded(c.seq, c.forced) else _WAIT
        if not c.awaited and not c.expired and not self._superseded(c.seq, c.forced):
            return _WAIT  # an optional same-frame input that is on time may still come
        if not c.exact and c.forced and not self._superseded(c.seq, c.forced):
            return _WAIT  # replay: the feedback the live set joined is still to come
        if not c.exact and not c.forced and not self._feedback_lost and not (c.expired or behind):
            return _WAIT  # wait for the feedback of the previous frame, bounded by the timeout and the lag
        return _EMIT

    def _emit(self, c: _Candidate, now_ns: int) -> tuple[int, dict[str, Any]]:
        """Hand out the set ``c`` (the first pending one), with the counters and state its going out changes."""
        if c.exact:
            self._feedback_lost = False
        else:
            if not c.forced:
                self._feedback_lost = True  # stop waiting until exact feedback is back in time
            self.feedback_fallbacks += 1
        self._account_optional(c)
        del self._slots[c.seq]
        done = bisect_right(self._forced_frames, c.seq)  # emitted, or never to be (dropped)
        for s in self._forced_frames[:done]:
            del self._forced[s]
        del self._forced_frames[:done]
        self._last_emitted = c.seq
        self._last_emit_ns = now_ns
        return c.seq, {name: c.msgs.get(name) for name in self.inputs}

    def _account_optional(self, c: _Candidate) -> None:
        """Count and remember the optional same-frame inputs the set ``c`` goes out without."""
        lacking = frozenset(name for name in self.optional if name not in c.msgs)
        waited = {name for name in lacking if self._awaited(name, c.seq)}
        if waited and c.expired and not c.forced:
            self._off_time |= waited  # missed its deadline: not waited for until on time again
        if waited or not c.exact:
            self.timeouts += 1
        if lacking - waited:
            self.without_optional += 1
        if lacking:
            self._lacked[c.seq] = (c.deadline, lacking)
            while len(self._lacked) > FEEDBACK_KEEP:
                del self._lacked[min(self._lacked)]

    def _lagging(self, slot: _Slot, newest_complete_ns: int | None) -> bool:
        """Is this set more than max_lag_ns (capture time) behind the newest set with all its inputs?"""
        if self.max_lag_ns is None or slot.stamp_ns is None or newest_complete_ns is None:
            return False
        return newest_complete_ns - slot.stamp_ns > self.max_lag_ns

    def _deadline(self, slot: _Slot) -> int:
        # A set cannot be handled before its predecessor went out, so its wait starts then.
        return max(slot.first_ns, self._last_emit_ns) + self.timeout_ns

    def _missing_required(self, slot: _Slot) -> bool:
        return any(name not in slot.msgs for name, spec in self.inputs.items() if not spec.offset and not spec.optional)

    def _missing_same_frame(self, slot: _Slot, seq: int) -> bool:
        return any(name not in slot.msgs and self._awaited(name, seq)
                   for name, spec in self.inputs.items() if not spec.offset)

    def _superseded(self, seq: int, forced: bool) -> bool:
        """Should the set of frame ``seq`` stop waiting because a newer one can go? Live: a newer set has its
        same-frame inputs. Replay (a set the live run handled): a newer handled set is ready in full, as it
        went out live (its feedback included), and no optional input this set had live is still to come."""
        if not forced:
            return self._newer_complete(seq)
        if self._optional_still_coming(seq, self._slots[seq]):
            return False
        return any(later > seq and later in self._forced and all(self._gather(later, slot)[1:])
                   for later, slot in self._slots.items())

    def _optional_still_coming(self, seq: int, slot: _Slot) -> bool:
        """Replay: does the handled set of frame ``seq`` lack an optional input it had live whose own stream has
        not reached the frame yet? Its producer lagged live and published it after newer frames' inputs (the
        feed's publication order), so it is still to come, however far the other inputs ran ahead. One the
        recorder lost shows as its stream passing the frame; with nothing after it at all, the set waits until
        ``max_pending`` newer sets push it out (its outputs are then missing, as they would differ if made)."""
        return any(name not in slot.msgs and self._awaited(name, seq) and self._newest_optional.get(name, -1) < seq
                   for name in self.optional)

    def _newer_complete(self, seq: int) -> bool:
        return any(not self._missing_same_frame(self._slots[later], later) for later in self._slots if later > seq)

    def next_deadline_ns(self) -> int | None:
        if not self._slots:
            return None
        return min(self._deadline(s) for s in self._slots.values())

    @property
    def pending(self) -> int:
        return len(self._slots)

    @property
    def feedback_lost(self) -> bool:
        return self._feedback_lost

    def counters(self) -> dict[str, int]:
        return {"sync_timeouts": self.timeouts, "sync_dropped": self.dropped, "sync_late": self.late,
                "sync_stale": self.guard.stale, "sync_implausible": self.guard.implausible,
                "sync_resyncs": self.guard.resyncs,
                "sync_feedback_fallbacks": self.feedback_fallbacks, "sync_without_optional": self.without_optional}
