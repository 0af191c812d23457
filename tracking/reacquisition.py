"""Re-acquisition on accumulated evidence (seed 001 §IV's N_id confirmations, counted over a window).

After an occlusion the target often comes back looking a little different (another pose, another side, an aerial
view from another angle), far from where the prior coasted to. Seed 001 confirms a re-lock when the classifier
scores a candidate above δ_id on N_id consecutive frames; a classifier that has learnt a few dozen samples of one
view rarely reaches δ_id on another, and seed 000's T_reid on M_fuse is out of reach for a candidate the gate has
lost (S_geo = 0). A robot that then waits for one high score stops for good while the person it follows is the
best thing it sees.

So a re-lock is also confirmed by evidence that accumulates: one candidate that is, on ``frames_needed`` frames
within ``window_frames``, the best one and clear of every other, with the target's colours and not rejected by the
classifier, and whose boxes move consistently with one another (one person, not a different winner each frame).
Each condition is checked by the re-ID step (tracking/reid.py); this module keeps the one hypothesis and counts.

People seen beside the target are followed (:class:`BystanderTracks`) and never re-acquired this way, except one
whose track went through a merge: hidden with someone else in one box, it may resume on the wrong one of the two,
the target's own box included. Its box then needs twice the evidence, rather than being barred for good (a robot
that stops for good while the person it follows is the clear best thing it sees).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass

from ..msgs.box import Box, box_centre, box_iou


@dataclass
class PersonTrack:
    """One person followed by :meth:`continues`: the last box, its frame, the centre's velocity in px a frame."""

    box: Box
    frame: int
    velocity: tuple[float, float] = (0.0, 0.0)
    moved: bool = False  # velocity measured (two boxes seen)
    merged: bool = False  # since hidden in one box with someone else: which of the two it follows now is unsure

    def continues(self, box: Box, frame: int, max_step_heights: float) -> bool:
        """Whether ``box`` on ``frame`` can be this person: its height within a factor 1.5 of the last, its centre
        within ``max_step_heights`` of that height per frame elapsed from where the velocity carries the last one
        (twice that before a velocity is known: a runner seen at 10 fps moves half a height a frame)."""
        gap = max(frame - self.frame, 1)
        height = max(float(self.box[3]), 1.0)
        if not 1 / 1.5 <= float(box[3]) / height <= 1.5:
            return False
        (cx, cy), (px, py) = box_centre(box), self.carried_to(frame)
        tolerance = max_step_heights * height * gap * (1.0 if self.moved else 2.0)
        return math.hypot(cx - px, cy - py) <= tolerance

    def carried_to(self, frame: int) -> tuple[float, float]:
        """Where the velocity carries the last box's centre by ``frame`` (at least one frame on)."""
        gap = max(frame - self.frame, 1)
        cx, cy = box_centre(self.box)
        return cx + self.velocity[0] * gap, cy + self.velocity[1] * gap

    def moved_to(self, box: Box, frame: int) -> PersonTrack:
        gap = max(frame - self.frame, 1)
        (cx, cy), (px, py) = box_centre(box), box_centre(self.box)
        return PersonTrack(tuple(float(v) for v in box), frame, ((cx - px) / gap, (cy - py) / gap), True, self.merged)

    def merged_into(self, boxes: list[Box], frame: int) -> bool:
        """Whether one of ``boxes`` covers where the velocity carries this person on ``frame`` and is too tall to be
        them alone (over 1.5 times their height, which :meth:`continues` refuses): two people in one box."""
        cx, cy = self.carried_to(frame)
        height = max(float(self.box[3]), 1.0)
        return any(b[0] <= cx <= b[0] + b[2] and b[1] <= cy <= b[1] + b[3] and float(b[3]) > 1.5 * height
                   for b in boxes)


class ReacquisitionEvidence:
    """Counts the frames on which one moving person was the clear best candidate (see the module docstring)."""

    def __init__(self, frames_needed: int, window_frames: int, max_step_heights: float) -> None:
        self.frames_needed = int(frames_needed)
        self.window_frames = int(window_frames)
        self.max_step_heights = float(max_step_heights)
        self.person: PersonTrack | None = None
        self.counted: deque[int] = deque()  # the frames on which the person counted

    def reset(self) -> None:
        self.person = None
        self.counted.clear()

    @property
    def count(self) -> int:
        return len(self.counted)

    def observe(self, box: Box, frame: int, scale: int = 1) -> bool:
        """``box`` was the clear best candidate on ``frame``: count it for its person (a new count if it is
        someone else) and say whether the re-lock is now confirmed: ``scale`` times the frames needed within
        ``scale`` times the window (2 for the box of an unsure bystander)."""
        person = self.person
        if person is None or frame - person.frame > self.window_frames \
                or not person.continues(box, frame, self.max_step_heights):
            self.person, self.counted = PersonTrack(tuple(float(v) for v in box), frame), deque()
        else:
            self.person = person.moved_to(box, frame)
        self.counted.append(frame)
        while self.counted and self.counted[0] <= frame - scale * self.window_frames:
            self.counted.popleft()
        return len(self.counted) >= scale * self.frames_needed


class BystanderTracks:
    """The people seen beside the target, followed from frame to frame (:class:`PersonTrack`), so that none of them
    is re-acquired as the target by accumulated evidence: whoever was in view at the same time as the target is
    someone else. Only a detection seen while the target is tracked starts such a track; one that first appears
    while the target is hidden may be the target coming back. A track not seen for ``max_age_frames`` ends. With
    ``merges_unsure``, a track missing on a frame where a box too tall for its person covers where it should be
    (:meth:`PersonTrack.merged_into`) is unsure from then on, and so are the boxes it continues on (:attr:`unsure`)."""

    def __init__(self, max_age_frames: int, max_step_heights: float, merges_unsure: bool = True) -> None:
        self.max_age_frames = int(max_age_frames)
        self.max_step_heights = float(max_step_heights)
        self.merges_unsure = bool(merges_unsure)
        self.tracks: list[PersonTrack] = []
        self.unsure: list[bool] = []  # per box of the last link(): continued by a track that went through a merge

    def reset(self) -> None:
        self.tracks = []

    def link(self, boxes: list[Box], frame: int) -> list[bool]:
        """Continue each track with the nearest unclaimed box that can be its person; which boxes are bystanders."""
        claimed = [False] * len(boxes)
        self.unsure = [False] * len(boxes)
        kept: list[PersonTrack] = []
        for track in sorted(self.tracks, key=lambda t: -t.frame):
            if frame - track.frame > self.max_age_frames:
                continue
            options = [i for i, box in enumerate(boxes)
                       if not claimed[i] and track.continues(box, frame, self.max_step_heights)]
            if not options:
                if self.merges_unsure and not track.merged and track.merged_into(boxes, frame):
                    track = dataclasses.replace(track, merged=True)
                kept.append(track)
                continue
            lx, ly = box_centre(track.box)
            i = min(options, key=lambda j: math.hypot(box_centre(boxes[j])[0] - lx, box_centre(boxes[j])[1] - ly))
            claimed[i], self.unsure[i] = True, track.merged
            kept.append(track.moved_to(boxes[i], frame))
        self.tracks = kept
        return claimed

    def adopt(self, boxes: list[Box], bystander: list[bool], target: Box, frame: int) -> None:
        """The target is tracked on ``frame`` at ``target``: every other box there starts a bystander track, and a
        track that was on the target (the two met) is the target's and ends."""
        self.tracks = [t for t in self.tracks if box_iou(t.box, target) < 0.5]
        self.tracks += [PersonTrack(tuple(float(v) for v in box), frame)
                        for box, flag in zip(boxes, bystander, strict=True)
                        if not flag and box_iou(box, target) < 0.5]
