"""The replay itself: the recording fed into the nodes (in-process here, or the deployed process:
replay/isolated.py) in the live order with the live run's hints, and what they produce diffed with what was
recorded (replay/diff.py). ``followbus replay`` (tools/recording/replay.py) is its command."""

from __future__ import annotations

import bisect
import logging
import sys
import tempfile
import time
from collections import defaultdict, deque
from pathlib import Path
from typing import Any

from ..bus.inproc import InProcessError
from ..bus.recording import (
    is_bus_channel,
    iter_bus_messages,
    read_summary,
)
from ..bus.schemas import ReplayHint
from .diff import compare_output, show_value
from .feed import Feed, frame_and_stamp, recording_first_frame
from .plan import ReplayOptions, ReplayPlan, ReplayReport
from .targets import InProcessTarget, Target

log = logging.getLogger("followbus.replay")

MAX_REPORTED = 1000  # mismatch details kept in the report (the count is always exact)
# After a frame the recording lacks inputs of, the nodes' outputs may differ for a while (re-ID compares each frame
# with the previous one; the filter took that frame's measurement): differences are forgiven for this many frames.
# An output that matches once may differ again inside them: a node's state can carry the missing frame longer than
# its outputs show (re-ID's re-acquisition evidence spans 20 frames). A second at 30 Hz. Past it, an output key
# that has not matched on RESYNC_SETTLE_FRAMES frames in a row since the gap is still re-converging, for up to
# RESYNC_MAX_FRAMES: the prediction's model probabilities forget a difference by a tenth a frame, so its outputs
# reach the float tolerance some 130 frames later (and, hovering at it, match on a frame here and there before).
# Once such a key has settled, what differs is a mismatch.
RESYNC_FRAMES = 30
RESYNC_SETTLE_FRAMES = 10
RESYNC_MAX_FRAMES = 300


# --- the replay ------------------------------------------------------------------------------------

class Replayer:
    def __init__(self, path: Path, options: ReplayOptions):
        self.path = path
        self.opts = options
        self.plan = ReplayPlan(path, options)
        params: dict[str, Any] = (self.plan.params[self.plan.nodes[0]] if len(self.plan.nodes) == 1
                                  else dict(self.plan.params))
        self.report = ReplayReport(file=str(path), node=",".join(self.plan.nodes),
                                   mode="isolated" if options.isolated else "in-process", params=params)
        if options.isolated and len(self.plan.nodes) != 1:
            raise ValueError("--isolated replays one node (several run in-process only)")
        # Built now: a --param the node does not take is the user's mistake, said before anything runs.
        # (--isolated: the in-process run that steps the process.)
        self._inproc = InProcessTarget(self.plan)

    def run(self) -> ReplayReport:
        with tempfile.TemporaryDirectory(prefix="followbus-replay-") as tmp:
            target: Target = self._inproc
            if self.opts.isolated:
                from .isolated import IsolatedTarget

                target = IsolatedTarget(self._inproc, self.report, self.opts, Path(tmp))
            try:
                target.start()
                self.report.recording_first_frame = recording_first_frame(self.path, self.plan.skip_chunks)
                self._feed(target)
            except (RuntimeError, InProcessError) as exc:
                self.report.error = str(exc)
            finally:
                target.close()
        return self.report

    def _feed(self, target: Target) -> None:
        feed = Feed(self.plan)
        bar = self._progress()
        started = time.perf_counter()
        stamps: list[int] = []  # the first and the last input stamp seen
        done_frames: set[int] = set()
        sent: dict[int, set[str]] = defaultdict(set)  # frame -> recorded input keys fed for it
        waiting: deque[int] = deque()  # frames fed, not yet checked for inputs the recording lacks
        present = self._recorded_inputs() if any(self.plan.internal_outputs.values()) else {}
        try:
            for hints, frame_seq, messages in feed.groups():
                if self.opts.max_frames and frame_seq >= 0 and self.report.frames >= self.opts.max_frames:
                    break
                for node, hint in hints:
                    target.hint(node, hint)
                self._send(target, messages, frame_seq, sent, stamps)
                if frame_seq >= 0:
                    self.report.frames += 1
                    done_frames.add(frame_seq)
                    bar.update(1)
                    waiting.append(frame_seq)
                while waiting and present.get(waiting[0], set()) <= sent.get(waiting[0], set()):
                    self._stand_in(target, feed, waiting.popleft(), present)
            while waiting:
                self._stand_in(target, feed, waiting.popleft(), present)
        finally:
            bar.close()
            self._compare(feed.expected, target.produced(), done_frames, self._incomplete(feed, sent))
            self.report.wall_s = time.perf_counter() - started
            self.report.outputs_expected = feed.outputs_expected
            self.report.hints, self.report.late_inputs = feed.hints_reproduced, feed.late_inputs
        if isinstance(target, InProcessTarget):
            self.report.handler_s, self.report.decode_s = target.handler_s, target.decode_s
        if stamps:
            self.report.recorded_span_s = (stamps[-1] - stamps[0]) / 1e9
        if self.report.wall_s > 0:
            self.report.speed_x = self.report.recorded_span_s / self.report.wall_s

    def _send(self, target: Target, messages: Any, frame_seq: int, sent: dict[int, set[str]],
              stamps: list[int]) -> None:
        """One frame's inputs to the target; ``stamps`` keeps the lowest and the highest stamp seen."""
        for item in messages:
            stamp = item.stamp_ns
            target.send(self.plan.inputs[item.msg.key], item.msg.data, stamp, frame_seq)
            self.report.inputs_sent += 1
            sent[item.frame_seq].add(item.msg.key)
            if stamp:
                stamps[:] = [min(stamps[0], stamp), max(stamps[-1], stamp)] if stamps else [stamp, stamp]

    def _unable(self, feed: Feed, frame_seq: int, have: set[str]) -> list[str]:
        """The replayed nodes that handled frame ``frame_seq`` live but cannot here: of their required inputs of that
        frame, the recording lacks one (``have``: the keys it holds of that frame; a recorder dropped it under load)."""
        return [node for node, required in self.plan.required_by_node.items()
                if required and not required <= have and self.plan.internal_outputs[node]
                and any((t, frame_seq) in feed.expected for t in self.plan.internal_outputs[node])]

    def _recorded_inputs(self) -> dict[int, set[str]]:
        """frame -> the input keys the recording holds a message of that frame on (one pass over the inputs)."""
        present: dict[int, set[str]] = defaultdict(set)
        for msg in iter_bus_messages(self.path, list(self.plan.inputs), self.plan.skip_chunks):
            frame_seq = frame_and_stamp(msg.data)[0]
            if frame_seq >= 0:
                present[frame_seq].add(msg.key)
        return present

    def _stand_in(self, target: Target, feed: Feed, frame_seq: int, present: dict[int, set[str]]) -> None:
        """Once every recorded input of the frame has been fed (under load some come out of the recording behind
        the next frame's, and the other nodes must have done their part of the frame, prediction its prior): a node
        that cannot handle it skips it, and what it sent the other replayed nodes live comes from the recording
        instead; a two-node replay must not leave prediction waiting for a measurement re-ID cannot make."""
        unable = self._unable(feed, frame_seq, present.get(frame_seq, set()))
        for node in unable:
            target.hint(node, _skip_hint(frame_seq))
            for topic in self.plan.internal_outputs[node]:
                for data in feed.expected.get((topic, frame_seq), ()):
                    target.stand_in(topic, data, frame_and_stamp(data)[1])
                    self.report.stand_ins += 1

    def _incomplete(self, feed: Feed, sent: dict[int, set[str]]) -> set[int]:
        """Frames the node cannot reproduce from this recording: a required input of the frame is not in it, the
        feedback the frame joined live is not, nor the message of a sampled input it chose (the odometry
        sample prediction took, dropped by the recorder), a frame input's message of it was lost by the recorder
        (a header.seq gap, Feed.lost_frames), or an input's stream ends before the frame (the recorder stopped
        first: prediction's track k comes from re-ID's measurement k, say)."""
        required = self.plan.required_inputs
        stream_end: dict[str, int] = {}
        for fs, keys in sent.items():
            for key in keys & self.plan.frame_inputs:
                stream_end[key] = max(stream_end.get(key, -1), fs)
        last_end = min(stream_end.values(), default=None)
        return {fs for _topic, fs in feed.expected if fs >= 0 and (
            fs in feed.lost_frames
            or (required and not required <= sent.get(fs, set()))
            or any(key not in sent.get(joined, set()) for key, joined in feed.joined.get(fs, ()))
            or any(stamp not in feed.stamps_recorded[key] for key, stamp in feed.noted.get(fs, ()))
            or (last_end is not None and last_end < fs))}

    def _compare(self, expected: dict[tuple[str, int], list[bytes]], produced: dict[str, list[bytes]],
                 done_frames: set[int], incomplete: set[int] = frozenset()) -> None:
        """Diff what was produced with what was recorded, frame by frame and output by output; then list
        recorded-but-never-produced and produced-but-not-recorded outputs."""
        by_frame: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        for topic, items in produced.items():
            self.report.outputs_received += len(items)
            for data in items:
                by_frame[(topic, frame_and_stamp(data)[0])].append(data)
        gaps = sorted(incomplete)
        streaks: dict[str, tuple[int, int]] = {}  # output key -> (latest gap, frames matched in a row since it)
        for (topic, fs), recorded in sorted(expected.items()):  # each key's frames in order
            if fs < 0 and topic in self.plan.timer_topics:
                self.report.timer_outputs += len(recorded)
                continue
            if self.opts.max_frames and fs not in done_frames:  # beyond --max-frames
                continue
            before = bisect.bisect_right(gaps, fs)
            gap = gaps[before - 1] if before else None  # the latest frame the recording lacks inputs of
            since, streak = streaks.get(topic, (gap, 0))
            streak = streak if since == gap else 0
            forgive = "incomplete" if fs in incomplete else "after_gap" if _re_converging(fs, gap, streak) else ""
            matched = self._compare_frame(topic, fs, recorded, by_frame.get((topic, fs), []), forgive)
            settled = streak >= RESYNC_SETTLE_FRAMES
            streaks[topic] = (gap, streak if settled else streak + 1 if matched else 0)
        self._list_extra(expected, by_frame, incomplete)

    def _compare_frame(self, topic: str, fs: int, recorded: list[bytes], replayed: list[bytes],
                       forgive: str = "") -> bool:
        """One output key's recorded and replayed messages of frame ``fs``, in order; True when all match.
        ``forgive``: "incomplete" (the frame lacks an input the live run had) or "after_gap" (the nodes are
        re-converging after such a frame): differences are counted apart, not as mismatches."""
        key = self.plan.key(topic)
        all_match = len(replayed) == len(recorded)
        for i in range(min(len(recorded), len(replayed))):
            diff = compare_output(recorded[i], replayed[i], self.opts.tolerance)
            all_match = all_match and diff is None
            if diff is not None and forgive == "incomplete":  # made without a message the live run had
                self.report.unverifiable += 1
                continue
            if diff is not None and forgive == "after_gap":
                self.report.after_gap += 1
                continue
            self.report.outputs_compared += 1
            if diff is None:
                self.report.matched += 1
                continue
            self.report.mismatch_count += 1
            if len(self.report.mismatches) < MAX_REPORTED:
                self.report.mismatches.append({"frame_seq": fs, "key": key, "index": i, "field": diff.field,
                                               "recorded": show_value(diff.recorded),
                                               "replayed": show_value(diff.replayed)})
        if forgive and len(replayed) < len(recorded):
            if forgive == "incomplete":
                self.report.unverifiable += len(recorded) - len(replayed)
            else:
                self.report.after_gap += len(recorded) - len(replayed)
            return False
        self.report.missing += [{"frame_seq": fs, "key": key, "index": i} for i in range(len(replayed), len(recorded))]
        return all_match

    def _list_extra(self, expected: dict[tuple[str, int], list[bytes]],
                    by_frame: dict[tuple[str, int], list[bytes]], incomplete: set[int] = frozenset()) -> None:
        """Produced but not recorded: extra, unless the recording stopped before that frame's outputs, or the frame
        is not verifiable (``incomplete``: the recorder lost what the node published for it)."""
        last_recorded: dict[str, int] = {}
        for topic, fs in expected:
            last_recorded[topic] = max(last_recorded.get(topic, -1), fs)
        for (topic, fs), replayed in sorted(by_frame.items()):
            if fs < 0 and topic in self.plan.timer_topics:
                continue
            n_exp = len(expected.get((topic, fs), []))
            if fs > last_recorded.get(topic, -1):
                # The recording stopped between this frame's inputs and its outputs: nothing to compare.
                self.report.beyond_end += len(replayed) - n_exp
                continue
            if fs in incomplete:
                self.report.unverifiable += max(len(replayed) - n_exp, 0)
                continue
            self.report.extra += [{"frame_seq": fs, "key": self.plan.key(topic), "index": i}
                                  for i in range(n_exp, len(replayed))]

    def _progress(self):
        from tqdm import tqdm

        summary = read_summary(self.path)
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        primary = next((f"{self.plan.recorded_ns}/{i.topic}" for n in self.plan.nodes
                        for i in self.plan.graph.nodes[n].inputs.values()
                        if i.sync == "frame" and not i.offset and not i.optional
                        and f"{self.plan.recorded_ns}/{i.topic}" in self.plan.inputs), None)
        total = sum(counts.get(ch.id, 0) for ch in summary.channels.values()
                    if ch.topic == primary and is_bus_channel(ch))
        if self.opts.max_frames:
            total = min(total, self.opts.max_frames) if total else self.opts.max_frames
        return tqdm(total=total or None, unit="frame", desc=f"replay {self.report.node}", file=sys.stderr,
                    disable=None if self.opts.progress else True, dynamic_ncols=True)  # None: TTY only


def _re_converging(fs: int, gap: int | None, streak: int) -> bool:
    """Are differences at frame ``fs`` the re-convergence after ``gap`` (the latest frame before it the recording
    lacks inputs of)? Within RESYNC_FRAMES of it always; then until the key has matched on RESYNC_SETTLE_FRAMES
    frames in a row since the gap (``streak``; once reached it stays), at most RESYNC_MAX_FRAMES."""
    if gap is None:
        return False
    return fs <= gap + RESYNC_FRAMES or (streak < RESYNC_SETTLE_FRAMES and fs <= gap + RESYNC_MAX_FRAMES)


def _skip_hint(frame_seq: int) -> ReplayHint:
    hint = ReplayHint(skip=True, feedback={})
    hint.header.frame_seq = frame_seq
    return hint
