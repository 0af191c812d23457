"""The recording as a replay reads it: once, outputs of the replayed nodes kept as the expected outputs and
turned into replay hints, inputs handed out in the order they were published, frame by frame. Shared by
the in-process and the ``--isolated`` replay (replay/engine.py)."""

from __future__ import annotations

import heapq
import logging
import queue
import threading
from collections import defaultdict, deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..bus.codec import DecodeError, Peeked, peek
from ..bus.recording import BusMessage, iter_bus_messages
from ..bus.schemas import ReplayHint
from ..bus.stats import SequenceGaps

if TYPE_CHECKING:
    from .plan import ReplayPlan

log = logging.getLogger("followbus.replay")

PREFETCH = 8  # batches of recorded messages read ahead by the reading thread
PREFETCH_BATCH = 32
LOOKAHEAD_BYTES = 256 * 1024 * 1024  # inputs held back while reading ahead for what live did with a frame


def _peekframe_and_stamp(data: bytes) -> Peeked | None:
    """Type and header of a stored bus message without decoding its fields (None: not a followbus frame)."""
    try:
        return peek(data)
    except DecodeError:
        return None


def frame_and_stamp(data: bytes) -> tuple[int, int]:
    """(frame_seq, stamp_ns) of a stored bus message."""
    head = _peekframe_and_stamp(data)
    return (head.header.frame_seq, head.header.stamp_ns) if head is not None else (-1, 0)


def recording_first_frame(path: Path, skip_chunks: frozenset[int] = frozenset(), look_at: int = 200) -> int | None:
    """The lowest frame_seq among the recording's first ``look_at`` messages that carry a frame (log time =
    capture stamp, so the run's first recorded frame is among them); None when none carries a frame.

    Messages of no frame are passed over, however many: on a loaded machine the motor's 100 Hz odometry fills
    the first seconds of a recording before the camera's first frame (hundreds of messages at a load of 20)."""
    seqs = []
    for msg in iter_bus_messages(path, skip_chunks=skip_chunks):
        frame_seq = frame_and_stamp(msg.data)[0]
        if frame_seq >= 0:
            seqs.append(frame_seq)
            if len(seqs) >= look_at:
                break
    return min(seqs) if seqs else None


@dataclass
class Input:
    """A recorded input message and its header, peeked once."""

    msg: BusMessage
    frame_seq: int
    stamp_ns: int
    pub_ns: int


def causal_order(messages: Iterable[Input]) -> Iterator[Input]:
    """Messages in the order they were published (header.pub_ns, one host's clock).

    The recording is in log-time order, log time being the capture stamp of the frame a message derives
    from; the order a node saw its inputs is the order they were published (the odometry sample sent
    5 ms after frame k's capture comes before the measurement of frame k sent 22 ms after it). A message
    is published after its capture (pub_ns >= log_time), so once the stream reaches log time L every
    buffered message published before L is final: the reorder buffer holds only the in-flight window.

    Messages of no frame (odometry) keep their stamp order instead: a node picks among them by stamp and
    a replay repeats the live choice (provenance notes), so handing each over at the earliest moment it
    could have existed is safe, whereas its publication time under load could make it late.
    """
    heap: list[tuple[int, int, int, Input]] = []
    for counter, item in enumerate(messages):
        msg = item.msg
        while heap and heap[0][0] < msg.log_time:
            yield heapq.heappop(heap)[3]
        pub = msg.log_time if item.frame_seq < 0 else (item.pub_ns or msg.log_time)
        heapq.heappush(heap, (max(pub, msg.log_time), msg.sequence, counter, item))
    while heap:
        yield heapq.heappop(heap)[3]


def prefetch(items: Iterable[Any], depth: int) -> Iterator[Any]:
    """Iterate in a thread ``depth`` items ahead: reading and decompressing the recording overlaps with
    the node's work (lz4 releases the GIL)."""
    box: queue.Queue[Any] = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def put(batch: list[Any]) -> bool:
        while not stop.is_set():
            try:
                box.put(batch, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run() -> None:
        batch: list[Any] = []
        try:
            for item in items:
                batch.append(item)
                if len(batch) >= PREFETCH_BATCH:  # a handover per batch, not per message: the locks cost
                    if not put(batch):
                        return
                    batch = []
            if batch and not put(batch):
                return
        except BaseException as exc:  # handed to the consumer
            box.put([exc])
        box.put(done)

    thread = threading.Thread(target=run, name="replay-read", daemon=True)
    thread.start()
    try:
        while True:
            got = box.get()
            if got is done:
                return
            for item in got:
                if isinstance(item, BaseException):
                    raise item
                yield item
    finally:
        stop.set()


class Feed:
    """The recording read once. Outputs of the replayed nodes become the expected outputs and the replay
    hints as they are read (log-time order: once the reader is past a frame's stamp, every output of that
    frame has been seen); inputs come out in publication order (:func:`causal_order`), grouped by frame,
    each group only once the reader knows what the live run did up to the next frame each node handled
    (a skipped frame is one with no output before a later handled one; whether a feedback message came
    late depends on that next frame's hint)."""

    def __init__(self, plan: ReplayPlan):
        self.plan = plan
        self.outputs_expected = 0
        self.hints_reproduced = 0  # frames skipped, or joining other feedback than the previous handled frame
        self.late_inputs = 0  # inputs out of stamp order (handed over with the frame being assembled)
        self.expected: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        self.hints: list[tuple[str, ReplayHint]] = []  # ready to be handed over
        self.eof = False
        self._log_time = -1  # of the newest message read
        self._open: dict[str, tuple[int, int, dict[str, int] | None]] = {}  # node -> (frame, stamp, provenance)
        self._handled: dict[str, int] = {}  # node -> newest frame whose hint is final
        self._previous: dict[str, int] = {}  # node -> newest frame handled live (for counting fallbacks)
        self._warned = False
        # frame -> (recorded input key, frame it joined) of the outside feedback each handled frame joined live
        self.joined: dict[int, set[tuple[str, int]]] = defaultdict(set)
        # frame -> (recorded key, stamp) of each message of a sampled input a handled frame chose live, and the
        # stamps of those keys' messages the recording holds
        self.noted: dict[int, set[tuple[str, int]]] = defaultdict(set)
        self.stamps_recorded: dict[str, set[int]] = defaultdict(set)
        self._noted_keys = set(plan.sampled_keys.values())
        # Frames for which the recorder lost a frame input's message (a header.seq gap between two recorded
        # messages of one publisher): the live node had it, the replay cannot have it.
        self.lost_frames: set[int] = set()
        self._seq_gaps = SequenceGaps()
        self._last_frame: dict[str, int] = {}  # frame input or output key -> frame_seq of the last message read
        # The frames of each outside feedback key's messages read so far; a hint to join one the recording lacks
        # joins none instead (waiting for it would hold the node's sets back until they are pushed out).
        self._feedback_read: dict[str, set[int]] = defaultdict(set)
        self._outside_feedback = set(plan.feedback_keys.values())
        # node -> frames between two of its recorded outputs that a header.seq gap says it may have handled live
        # (the recorder lost the outputs): not hinted as skipped, and not verifiable.
        self._unsure: dict[str, set[int]] = defaultdict(set)

    # outputs -> expected and hints
    def _read(self, messages: Iterable[BusMessage]) -> Iterator[Input]:
        for msg in messages:
            if msg.log_time > self._log_time:
                self._log_time = msg.log_time
                self._close_frames(msg.log_time)
            head = _peekframe_and_stamp(msg.data)
            frame_seq = head.header.frame_seq if head is not None else -1
            if msg.key in self._noted_keys and head is not None:
                self.stamps_recorded[msg.key].add(head.header.stamp_ns)
            if msg.key in self.plan.frame_inputs and head is not None:
                self._note_seq(msg.key, head.header)
            if msg.key in self._outside_feedback:
                self._feedback_read[msg.key].add(frame_seq)
            if msg.key not in self.plan.outputs:
                yield (Input(msg, frame_seq, head.header.stamp_ns, head.header.pub_ns) if head is not None
                       else Input(msg, -1, 0, 0))
                continue
            self.expected[(self.plan.outputs[msg.key], frame_seq)].append(msg.data)
            self.outputs_expected += 1
            if head is not None:
                self._note_output_seq(self.plan.output_node(msg.key), msg.key, head.header)
                self._output_seen(self.plan.output_node(msg.key), frame_seq, head)
        self.eof = True
        for node, open_ in list(self._open.items()):
            self._finish(node, *open_)
        self._open.clear()

    def _seq_gap(self, key: str, header: Any) -> range | None:
        """The frames between this message of ``key`` and the last one read, when a gap in header.seq (one publisher:
        source and epoch) says the recorder lost messages there (an empty range: none lies between); else None."""
        last_frame = self._last_frame.get(key, -1)
        self._last_frame[key] = header.frame_seq
        lost = self._seq_gaps.see((key, header.source, header.epoch_ns), header.seq)
        return range(last_frame + 1, header.frame_seq) if lost > 0 and min(last_frame, header.frame_seq) >= 0 else None

    def _note_seq(self, key: str, header: Any) -> None:
        """A gap in a frame input's header.seq lost the messages of the frames between the two read (all of them:
        which ones a node skipped live is not known), or of the later one's frame when none lies between."""
        between = self._seq_gap(key, header)
        if between is not None:
            self.lost_frames.update(between or (header.frame_seq,))

    def _note_output_seq(self, node: str, key: str, header: Any) -> None:
        """A gap in an output's header.seq between two frames apart: the node handled one or more of the frames
        between live and the recorder lost what it published (re-ID's measurement k: a two-node replay told to
        skip k would leave prediction waiting for it). Which of them it handled is not known."""
        between = self._seq_gap(key, header)
        if between:
            self._unsure[node].update(between)
            self.lost_frames.update(between)

    def _output_seen(self, node: str, frame_seq: int, head: Any) -> None:
        """A recorded output of ``node``: it opens the frame's hint, or adds its notes to the open one."""
        if frame_seq < 0 or node not in self.plan.hinted:
            return
        used = dict(head.header.feedback) if head.provenance else None
        open_ = self._open.get(node)
        if open_ is not None and open_[0] == frame_seq:
            if used:  # a frame's outputs together: the prior's feedback and notes, the track's notes
                self._open[node] = (frame_seq, open_[1], {**(open_[2] or {}), **used})
        elif frame_seq > self._handled.get(node, -1) and (open_ is None or frame_seq > open_[0]):
            if open_ is not None:
                self._finish(node, *open_)
            self._open[node] = (frame_seq, head.header.stamp_ns, used or None)

    def _close_frames(self, log_time: int) -> None:
        for node, open_ in list(self._open.items()):
            if open_[1] < log_time:
                self._finish(node, *open_)
                del self._open[node]

    def _finish(self, node: str, frame_seq: int, _stamp: int, used: dict[str, int] | None) -> None:
        """The hints of the frames up to ``frame_seq``: those in between were skipped live."""
        last = self._handled.get(node)
        if last is not None:
            for skipped in range(last + 1, frame_seq):
                if skipped not in self._unsure[node]:
                    self._hint(node, skipped, True, None)
        self._hint(node, frame_seq, False, used)
        self._handled[node] = frame_seq

    def _hint(self, node: str, frame_seq: int, skip: bool, used: dict[str, int] | None) -> None:
        if not (skip or used):
            return
        hint = ReplayHint(skip=skip, feedback=self._recorded_feedback(node, used or {}))
        hint.header.frame_seq = frame_seq
        self.hints.append((node, hint))
        previous = self._previous.get(node)
        fallback = used is not None and previous is not None and any(
            used.get(name, previous) != previous for name in self.plan.feedback_inputs.get(node, ()))
        self.hints_reproduced += skip or fallback
        if not skip:
            self._previous[node] = frame_seq
            for name, joined in (used or {}).items():
                key = self.plan.feedback_keys.get((node, name))
                if key is not None and joined >= 0:
                    self.joined[frame_seq].add((key, joined))
                noted_key = self.plan.noted_key(node, name)
                if noted_key is not None and joined >= 0:
                    self.noted[frame_seq].add((noted_key, joined))

    def _recorded_feedback(self, node: str, used: dict[str, int]) -> dict[str, int]:
        """``used`` (the feedback frames a handled frame joined live), with -1 (none) for an outside feedback message
        the recording lacks: the recorder dropped it, and a frame's hint comes once the reader is past that frame's
        stamp, so past the feedback's own. The frame is not verifiable (Replayer._incomplete, from ``joined``)."""
        out = dict(used)
        for name, joined in used.items():
            key = self.plan.feedback_keys.get((node, name))
            if key is not None and joined >= 0 and joined not in self._feedback_read[key]:
                out[name] = -1
        return out

    def _known(self, frame_seq: int) -> bool:
        """Does the reader know what each node did up to the next frame after ``frame_seq`` it handled?"""
        return self.eof or all(self._handled.get(node, -1) > frame_seq for node in self.plan.hinted)

    # inputs -> frame groups
    def groups(self) -> Iterator[tuple[list[tuple[str, ReplayHint]], int, list[Input]]]:
        """(hints to hand over first, frame_seq, the group's input messages: no-frame ones first)."""
        keys = set(self.plan.inputs) | set(self.plan.outputs)
        messages = iter_bus_messages(self.plan.path, keys, self.plan.skip_chunks)
        stream = causal_order(self._read(prefetch(messages, PREFETCH)))
        ready: deque[tuple[int, list[Input], int]] = deque()  # (frame_seq, messages, bytes)
        held = 0
        group: list[Input] = []
        group_seq: int | None = None
        done: set[int] = set()

        def release(force: bool):
            nonlocal held
            while ready and (force or self._known(ready[0][0]) or held > LOOKAHEAD_BYTES):
                if held > LOOKAHEAD_BYTES and not self._known(ready[0][0]) and not self._warned:
                    self._warned = True
                    log.warning("no output of the replayed node for %d MB of recording after frame %d: going "
                                "on without knowing whether live skipped the frames in between",
                                LOOKAHEAD_BYTES >> 20, ready[0][0])
                frame_seq, messages, size = ready.popleft()
                held -= size
                hints, self.hints = self.hints, []
                # Messages of no frame (odometry) first: a node picks among them by stamp, and what it picked
                # live is replayed from the hint, which needs the sample there before the frame's set.
                yield hints, frame_seq, sorted(messages, key=lambda m: m.frame_seq >= 0)

        for item in stream:
            frame_seq = item.frame_seq
            if frame_seq >= 0:
                if group_seq is not None and frame_seq > group_seq:
                    ready.append((group_seq, group, sum(len(m.msg.data) for m in group)))
                    held += ready[-1][2]
                    done.add(group_seq)
                    group, group_seq = [], None
                if group_seq is not None and frame_seq < group_seq or frame_seq in done:
                    self.late_inputs += 1  # out of stamp order: goes with the frame being assembled
                if group_seq is None:
                    group_seq = frame_seq
            group.append(item)  # messages of no frame (-1) go with the frame being assembled
            yield from release(False)
        if group:
            ready.append((group_seq if group_seq is not None else -1, group, 0))
        yield from release(True)
