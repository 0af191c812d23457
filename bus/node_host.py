"""NodeHost: what hosting one node takes, whatever carries its messages (see :class:`NodeHost`)."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from .barrier import DownstreamBarrier
from .clock import Clock
from .graph import Graph, GraphError
from .liveness import (
    HANDLER_FAILURE_LIMIT,
    POLL_FAILURE_LIMIT,
    FailureBudget,
    NodeStoppedWorking,
    ProductionWatch,
    SourceActivity,
)
from .node import Node
from .pubsub import RateLimitedLog
from .schemas import Message, ReplayHint
from .sync import IMPLAUSIBLE, RESYNCED, STALE, FrameSynchronizer, SequenceGuard, SyncInput

RESET_AFTER_FAILURES = 5  # consecutive on_frame failures after which a node's state is rebuilt
REPLAY_NOTES_KEEP = 512  # frames of live provenance a replayed node keeps
SAMPLES_KEEP = 512  # messages kept of each input sampled by stamp (~5 s at 100 Hz)


def note_key(sampled: str, trigger: str | None) -> str:
    """The note (``header.feedback`` key) of the message sampled from input ``sampled`` while handling a frame set
    (``trigger`` None) or a message of input ``trigger``: a replay reads it back to repeat the choice."""
    return sampled if trigger is None else f"{sampled}@{trigger}"


def sampled_input(note: str) -> str:
    """The sampled input a note (:func:`note_key`) names."""
    return note.partition("@")[0]


@dataclass
class _Handling:
    """What the node is handling now: its header goes to what it publishes, its stamp picks the samples."""

    like: Message | None  # the message whose stamp, frame_seq and epoch an output inherits
    frame_seq: int
    stamp_ns: int
    trigger: str | None  # the input of the message handled; None: a frame set


class FrameInputs(dict):
    """One frame set's messages by input name; an input sampled by stamp is looked up on first reading
    (``NodeHost.sample``), so a node that never reads it notes nothing."""

    def __init__(self, msgs: dict[str, Message | None], host: NodeHost):
        super().__init__(msgs)
        self._host = host

    def __missing__(self, name: str) -> Message | None:
        if name not in self._host.samples:
            raise KeyError(name)
        self[name] = msg = self._host.sample(name)
        return msg

    def get(self, name: str, default: Any = None) -> Any:
        try:
            return self[name]
        except KeyError:
            return default


class NodeHost:
    """What hosting one node takes, whatever carries its messages: its class and params, its clock, the frame
    synchroniser and sequence guards of its inputs, the samples of its inputs read by stamp, and handing it
    messages, frame sets, timer ticks and replay hints. :class:`bus.node_runtime.NodeRuntime` carries the messages
    over Zenoh (one process per node); ``bus.inproc.InProcessGraph`` between nodes in one process on a simulated
    clock. Both run this code, so a node behaves the same in either. A subclass fills ``publishers`` (output ->
    object with ``put(msg)``) and then calls :meth:`create_node`. What a node may use of it: bus.node.Runtime.
    """

    session: Any = None  # NodeRuntime's Zenoh session; None in-process

    def __init__(self, graph: Graph, name: str, clock: Clock, validated: tuple[type[Node], Any]):
        if name not in graph.nodes:
            raise GraphError(graph.path, None, f"no node named {name!r} (nodes: {', '.join(graph.nodes)})")
        self.graph = graph
        self.spec = graph.nodes[name]
        self.cls, self.params = validated
        self.clock = clock
        self.stop_event = threading.Event()
        self.log = logging.getLogger(f"followbus.{name}")
        self.publishers: dict[str, Any] = {}
        self.latest: dict[str, Message] = {}
        self.handler_errors = 0
        self.resets = 0
        self.barrier: DownstreamBarrier | None = None  # a source's start-up barrier (wait_for_consumers)
        # Working, not just alive (bus/liveness.py): consecutive failures of poll and of the handlers, and
        # when this node last published.
        self.poll_failures = FailureBudget(POLL_FAILURE_LIMIT)
        self.handler_failures = FailureBudget(HANDLER_FAILURE_LIMIT)
        self.production = ProductionWatch()
        self.activity = SourceActivity()
        self._frame_failures = 0  # consecutive
        self.provenance: dict[str, int] | None = None  # feedback used by the set being handled, and the notes
        self._handling: _Handling | None = None
        self._warn = RateLimitedLog(self.log)
        self._init_sync(graph, name, clock)
        # Inputs not joined by frame are still frame-numbered streams (a consumer's inputs, capture's acks): the
        # same sequence checks keep a forged or stale message from reaching the node.
        self._guards = {i.name: SequenceGuard() for i in self.spec.inputs.values() if i.sync != "frame"}
        # Inputs read by stamp: their messages in stamp order (an unwired one stays empty: nothing to sample).
        self.samples: dict[str, deque[Message]] = {
            name: deque(maxlen=SAMPLES_KEEP) for name, port in self.cls.INPUTS.items() if port.sample_by_stamp}
        self._held: list[tuple[str, Message]] = []  # replay: feedback the live node received later
        self.replay_notes: dict[int, dict[str, int]] = {}  # replay: frame -> provenance of the live outputs
        self.timer_ns = int(self.cls.TIMER_PERIOD_MS * 1e6) if self.cls.TIMER_PERIOD_MS else None
        self.next_timer_ns: int | None = None

    def _init_sync(self, graph: Graph, name: str, clock: Clock) -> None:
        frame_inputs = [SyncInput(i.name, i.offset, i.optional) for i in self.spec.inputs.values()
                        if i.sync == "frame"]
        # The lag bound is a live policy: a lockstep replay never builds a backlog, and skipping there
        # would depend on how fast the replayer feeds the node.
        lag_ms = graph.lag_bound_ms(name) if clock.live else None
        self.sync = (FrameSynchronizer(frame_inputs, int(self.spec.sync_timeout_ms * 1e6),
                                       max_lag_ns=None if lag_ms is None else int(lag_ms * 1e6))
                     if frame_inputs else None)
        self._feedback_inputs = [i.name for i in frame_inputs if i.offset]
        self._same_frame_inputs = {i.name for i in frame_inputs if not i.offset}

    def create_node(self) -> None:
        self.node = self.cls(self.params, self)

    def start(self) -> None:
        """Set the node up and start its timer."""
        self.node.setup()
        self.next_timer_ns = self.clock.now_ns() + self.timer_ns if self.timer_ns else None

    def close_node(self) -> None:
        """Tear the node down (its state saved, a device closed) and what the runtime opened for it."""
        self._guarded("teardown", self.node.teardown)
        if self.barrier is not None:
            self.barrier.close()

    # --- what a node uses (bus.node.Runtime) ------------------------------------------------------
    def publish(self, output: str, msg: Message, like: Message | None = None) -> None:
        """Publish on an output. The stamp, frame_seq and epoch come from ``like``, else from what is being handled
        (the frame set, or the message); outside a handler a message without a stamp gets the node clock's time.
        Inside a handler the output also carries the set's provenance (the feedback it joined) and the samples'
        notes."""
        if like is None and self._handling is not None:
            like = self._handling.like
        if like is not None:
            msg.header.stamp_ns = like.header.stamp_ns
            msg.header.frame_seq = like.header.frame_seq
            msg.header.epoch_ns = like.header.epoch_ns
        elif not msg.header.stamp_ns:
            msg.header.stamp_ns = self.clock.now_ns()
        if self.provenance is not None:
            msg.header.feedback = dict(self.provenance)
        self.publishers[output].put(msg)
        self.production.published(time.monotonic())

    def sample(self, name: str) -> Message | None:
        """The newest message of sampled input ``name`` stamped at or before what is being handled (None: none
        yet). Which one it was depends on when messages arrived, so it is noted in what the handler publishes
        (:func:`note_key`), and a lockstep replay takes the one the live run noted."""
        handling = self._handling
        if handling is None:
            raise RuntimeError(f"sample({name!r}): only while a frame set or a message is handled")
        if name not in self.samples:
            raise KeyError(f"{name!r} is not an input of {self.spec.name} sampled by stamp "
                           f"(In(..., sample_by_stamp=True))")
        key = note_key(name, handling.trigger)
        forced = self.replay_notes.get(handling.frame_seq, {}).get(key)
        chosen = None
        for msg in reversed(self.samples[name]):
            stamp = msg.header.stamp_ns
            if (stamp == forced) if forced is not None else (stamp <= handling.stamp_ns):
                chosen = msg
                break
        if self.provenance is not None:
            self.provenance[key] = -1 if chosen is None else chosen.header.stamp_ns
        return chosen

    def listened(self, output: str) -> bool:
        """Whether anyone subscribes to this output now (a publisher without ``listened``, in-process: always)."""
        publisher = self.publishers.get(output)
        return publisher is not None and getattr(publisher, "listened", True)

    def stop(self) -> None:
        self.stop_event.set()

    def wait_for_consumers(self, timeout_s: float, settle_s: float) -> DownstreamBarrier:
        """The start-up barrier of a source (bus/barrier.py): until it opens, the node holds its first message on
        purpose, and its silence is no stall."""
        self.barrier = DownstreamBarrier(self.graph, self.spec.name, self.session, timeout_s, settle_s, self.log)
        return self.barrier

    def holding(self) -> bool:
        """Whether the source holds its first publication on purpose (its start-up barrier is not open yet)."""
        return self.barrier is not None and not self.barrier.opened and self.production.count == 0

    @property
    def awaiting(self) -> set[str]:
        """The consumers the start-up barrier still waits for."""
        return self.barrier.missing if self.barrier is not None else set()

    # --- the runtime's side -----------------------------------------------------------------------
    def sync_counters(self) -> dict[str, Any]:
        extra: dict[str, Any] = {"handler_errors": self.handler_errors, "resets": self.resets,
                                 "poll_failures": self.poll_failures.streak}
        if self.sync is not None:
            extra.update(self.sync.counters())
        if self._guards:
            extra.update(seq_stale=sum(g.stale for g in self._guards.values()),
                         seq_implausible=sum(g.implausible for g in self._guards.values()),
                         seq_resyncs=sum(g.resyncs for g in self._guards.values()))
        return extra

    def _guarded(self, what: str, fn, *args) -> Any:
        try:
            result = fn(*args)
        except Exception:
            # A bug or an unexpected message must not take the robot down: count, log, go on. Past
            # HANDLER_FAILURE_LIMIT failures in a row the node stops working (check_working).
            self.handler_errors += 1
            self.handler_failures.failed()
            if self.handler_errors <= 3 or self.handler_errors % 100 == 0:
                self.log.exception("%s failed (%d errors so far)", what, self.handler_errors)
            return None
        self.handler_failures.succeeded()
        return result

    def poll_once(self, now_ns: int) -> float | None:
        """Poll the node: seconds until the next poll, None for "never again" (the source is done).

        A poll that raises is retried after a backoff (0.05 s doubling to 1 s), never dropped for good: one
        failed camera read must not silence a source while its process looks up. POLL_FAILURE_LIMIT failures
        in a row raise NodeStoppedWorking (the process exits, the launcher restarts it)."""
        try:
            delay = self.node.poll(now_ns)
        except Exception as exc:
            self.handler_errors += 1
            backoff_s = self.poll_failures.failed()
            if self.poll_failures.exhausted:
                raise NodeStoppedWorking(f"poll failed {self.poll_failures.streak} times in a row "
                                         f"(last: {type(exc).__name__}: {exc})") from exc
            self.log.exception("poll failed (%d in a row); retrying in %.2f s", self.poll_failures.streak,
                               backoff_s)
            return backoff_s
        self.poll_failures.succeeded()
        return delay

    def check_working(self, polling: bool) -> None:
        """Raise NodeStoppedWorking when the handlers keep failing, or a source (``polling``: its poll is still
        scheduled) that has published before has been silent for many of its own periods."""
        if self.handler_failures.exhausted:
            raise NodeStoppedWorking(f"{self.handler_failures.streak} handler calls failed in a row")
        silent_s = self.production.silent_s(time.monotonic()) if polling else None
        if silent_s is not None:
            raise NodeStoppedWorking(f"published nothing for {silent_s:.1f} s (bound "
                                     f"{self.production.bound_s():.1f} s: its period x {self.production.periods})")

    def apply_hints(self, hints: list[Message]) -> None:
        """Replay: what the live run did with some frames (ReplayHint), handed over before those frames' inputs."""
        for hint in hints:
            assert isinstance(hint, ReplayHint)
            self.replay_notes[hint.header.frame_seq] = dict(hint.feedback)
            while len(self.replay_notes) > REPLAY_NOTES_KEEP:
                del self.replay_notes[min(self.replay_notes)]
            if self.sync is not None and hint.skip:
                self.sync.skip(hint.header.frame_seq)
            elif self.sync is not None:
                self.sync.force_feedback(hint.header.frame_seq, hint.feedback)

    def run_timer(self, now_ns: int) -> bool:
        """Tick the node's timer if it is due at ``now_ns``; True if it ticked."""
        if self.next_timer_ns is None or self.timer_ns is None or now_ns < self.next_timer_ns:
            return False
        self._guarded("on_timer", self.node.on_timer, now_ns)
        self.next_timer_ns = max(self.next_timer_ns + self.timer_ns, now_ns - self.timer_ns)
        return True


    def _dispatch(self, name: str, msg: Message) -> None:
        spec = self.spec.inputs[name]
        h = msg.header
        if not self._in_sequence(name, msg):
            return
        if (spec.offset and self.sync is not None and self.clock.mode == "stamps"
                and self.sync.holds_back(name, h.frame_seq)):
            # Live, this feedback arrived after a set that joined an older one: hand it to the node after that
            # set, as live, or on_message (a feedback update) runs in an order that never was.
            self._held.append((name, msg))
            return
        self.clock.observe(h.stamp_ns)
        samples = self.samples.get(name)
        if samples is not None:  # read by stamp when another input comes: kept in stamp order, no hook
            if not samples or h.stamp_ns >= samples[-1].header.stamp_ns:
                samples.append(msg)
            return
        if spec.sync == "frame" and not self._joined(name, msg):
            return
        if spec.sync != "frame" or self.cls.INPUTS[name].on_arrival:
            self._handle_message(name, msg)
        if spec.sync == "latest":
            self.latest[name] = msg
        elif spec.sync == "frame":
            self._emit_ready()

    def _in_sequence(self, name: str, msg: Message) -> bool:
        """The sequence checks of an input not joined by frame (a frame-joined one: the synchroniser's)."""
        guard = self._guards.get(name)
        h = msg.header
        if guard is None or h.frame_seq < 0:
            return True
        verdict = guard.check(h.frame_seq, h.stamp_ns, h.epoch_ns, floor=guard.newest_seq)
        if verdict in (STALE, IMPLAUSIBLE):
            self._warn.warning("dropped %s %s frame %d (stamp %d): out of sequence with the stream",
                               verdict, name, h.frame_seq, h.stamp_ns)
            return False
        if verdict == RESYNCED:
            self.log.warning("input %s: the source restarted or was replaced (frame %d); following it",
                             name, h.frame_seq)
        return True

    def _joined(self, name: str, msg: Message) -> bool:
        """Offer a frame-joined message to the synchroniser: False when it is rejected (judged before the node
        sees it: a forged or stale message must not reach on_message either)."""
        assert self.sync is not None  # the node has a frame-joined input
        h = msg.header
        verdict = self.sync.add(name, h.frame_seq, msg, self._sync_now(), stamp_ns=h.stamp_ns, epoch_ns=h.epoch_ns)
        if verdict == IMPLAUSIBLE:
            self._warn.warning("rejected %s frame %d (stamp %d): out of sequence with the stream",
                               name, h.frame_seq, h.stamp_ns)
            return False
        if verdict == STALE:
            self.log.debug("stale %s frame %d dropped", name, h.frame_seq)
            return False
        if verdict == RESYNCED:
            self.log.warning("input %s: the source restarted or was replaced (frame %d, epoch %d); "
                             "re-synchronising on it", name, h.frame_seq, h.epoch_ns)
        return True

    def _handle_message(self, name: str, msg: Message) -> None:
        h = msg.header
        self.provenance = {}  # what on_message publishes carries its own notes
        self._handling = _Handling(msg, h.frame_seq, h.stamp_ns, name)
        try:
            self._guarded(f"on_message({name})", self.node.on_message, name, msg)
        finally:
            self.provenance = self._handling = None

    def _sync_now(self) -> int:
        return self.clock.wall_ns() if self.clock.live else self.clock.now_ns()

    def _emit_ready(self) -> None:
        if self.sync is None:
            return
        for frame_seq, inputs in self.sync.poll(self._sync_now()):
            self._handle_frame(frame_seq, inputs)
        if self._held:
            held, self._held = self._held, []
            for name, msg in held:
                self._dispatch(name, msg)  # held again if it still must wait

    def _handle_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        assert self.sync is not None  # frame sets come from it
        used = {name: inputs.get(name) for name in self._feedback_inputs}
        self.provenance = {name: (m.header.frame_seq if m is not None else -1) for name, m in used.items()}
        # An optional same-frame input the set went on without (not on time, or late): a replay lacks it too.
        self.provenance.update({name: -1 for name in self.sync.optional if inputs.get(name) is None})
        like = next((m for name, m in inputs.items() if m is not None and name in self._same_frame_inputs), None)
        self._handling = _Handling(like, frame_seq, like.header.stamp_ns if like is not None else 0, None)
        errors = self.handler_errors
        try:
            self._guarded("on_frame", self.node.on_frame, frame_seq, FrameInputs(inputs, self))
        finally:
            self.provenance = self._handling = None
        self._frame_failures = self._frame_failures + 1 if self.handler_errors > errors else 0
        if self._frame_failures >= RESET_AFTER_FAILURES:
            # Whatever the cause (a poisoned filter, a state no input can repair), staying dead is the worst
            # outcome: rebuild the node's state and let it re-initialise from the next frames.
            self.log.error("on_frame failed %d times in a row; resetting the node's state", self._frame_failures)
            self._frame_failures = 0
            self.resets += 1
            self._guarded("reset", self.node.setup)
