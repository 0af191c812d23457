"""Adaptive multi-factor re-identification, one frame at a time (paper §2.2, §2.4, Algorithm 1).

Per frame: gate candidates with the Kalman prior (Eq. 8), score each by appearance S_color
(Eq. 1) and geometry S_geo, fuse them with the visibility-driven weight ω(t) (Eq. 2-3), accept
the best one if M_fuse > Thresh_reid (Alg. 1 line 9), and run the track state machine.

Definitions this module fixes (the paper leaves them open):

* Visibility confidence C_t = the highest S_color among this frame's candidates (0 with no
  candidate): "how well can the target's appearance be seen in the search region right now".
  ω(t) is therefore one number per frame, as Eq. 3 writes it.
* S_geo = s_gate · s_dist · s_size (see :func:`geometric_score`).
* Candidates are the detections whose centre is in the gate; only when there is none, the
  frame-difference blobs in the gate (Alg. 1 line 2, background subtraction), and those only while
  the background holds still (less than ``motion_max_changed_fraction`` of the frame changed).
* ``secure`` (Eq. 10 "tracked securely") = accepted, state TRACKING (not within the first
  ``reacquired_hold_frames`` after a re-lock), not ambiguous (no other candidate's M_fuse within
  ``ambiguity_margin`` of the best) and a detector box (a motion blob covers only the moving
  part of the target, so its patch mixes in background).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..msgs.box import Box, box_array, box_centre, box_iou, box_tuple
from ..msgs.tracking import DETECTOR_SOURCES, Measurement, Prior, TrackState
from .appearance import bhattacharyya, colour_contrast, hs_histogram
from .init import changed_fraction, motion_blobs, nearest_to_centre_bottom, to_grey
from .learned_appearance import CROP_H_PX, CROP_W_PX, IdentityParams, PersonEmbedder, TargetClassifier, load_embedder
from .params import ReidParams
from .reacquisition import BystanderTracks, ReacquisitionEvidence
from .redetection import RegionBoxes, merge_region_boxes, search_scale

logger = logging.getLogger(__name__)


def geometric_score(
    candidate_box: Sequence[float],
    predicted_box: Sequence[float],
    maha_sq: float,
    gate_chi2: float,
    geo_scale: float = 0.5,
) -> float:
    """S_geo in [0, 1] of §2.2.2: agreement of a candidate with the predicted centre and size.

    S_geo = s_gate · s_dist · s_size with
      s_gate = max(0, 1 - d²_M / χ²)                  1 at the prediction, 0 on the gate boundary
      s_dist = exp(-(d_px / (geo_scale · diag))²)      diag = predicted box diagonal (px)
      s_size = sqrt(r_w · r_h),  r_w = min(w, ŵ)/max(w, ŵ), r_h likewise
    s_gate normalises the centre distance by the prior uncertainty (the gate). s_dist is the
    paper's Euclidean centroid distance, scaled by the target size: when appearance is weak
    (ω → 0) geometry alone decides, and after a long occlusion the gate is so wide that s_gate
    alone would accept any person-sized object near it. s_size rejects partial or wrong-size
    boxes.
    """
    s_gate = min(max(1.0 - float(maha_sq) / float(gate_chi2), 0.0), 1.0)
    cx, cy = box_centre(candidate_box)
    px, py = box_centre(predicted_box)
    w, h = max(float(candidate_box[2]), 0.0), max(float(candidate_box[3]), 0.0)
    pw, ph = max(float(predicted_box[2]), 0.0), max(float(predicted_box[3]), 0.0)
    diag = math.hypot(pw, ph)
    if geo_scale > 0.0 and diag > 0.0:
        s_dist = math.exp(-((math.hypot(cx - px, cy - py) / (geo_scale * diag)) ** 2))
    else:
        s_dist = 1.0
    if min(w, h, pw, ph) <= 0.0:
        return 0.0
    s_size = math.sqrt((min(w, pw) / max(w, pw)) * (min(h, ph) / max(h, ph)))
    return s_gate * s_dist * s_size


def _anchor_to_agreeing_edge(lo: float, extent: float, prior_lo: float, prior_extent: float,
                             edge_tolerance: float) -> tuple[float, float]:
    """(start, extent) along one axis: the predicted extent from the one edge that agrees with the prediction's
    (within ``edge_tolerance`` of the predicted extent), the other being where someone else or an occluder is; as
    it is when both edges moved (a smaller or a nearer person) or neither agrees: nothing to anchor on. Shared by
    :func:`complete_partial_view` (a box too short) and :func:`trim_merged_view` (a box too long)."""
    tolerance_px = edge_tolerance * prior_extent
    start_agrees = abs(lo - prior_lo) <= tolerance_px
    end_agrees = abs((lo + extent) - (prior_lo + prior_extent)) <= tolerance_px
    if start_agrees and not end_agrees:
        return lo, prior_extent
    if end_agrees and not start_agrees:
        return lo + extent - prior_extent, prior_extent
    return lo, extent


def _complete_extent(lo: float, extent: float, prior_lo: float, prior_extent: float, max_ratio: float,
                     edge_tolerance: float) -> tuple[float, float]:
    """One axis of :func:`complete_partial_view`: (start, extent) along it."""
    if prior_extent <= 0.0 or extent >= max_ratio * prior_extent:
        return lo, extent
    return _anchor_to_agreeing_edge(lo, extent, prior_lo, prior_extent, edge_tolerance)


def complete_partial_view(box: Sequence[float], predicted_box: Sequence[float], max_ratio: float = 0.8,
                          edge_tolerance: float = 0.15, keep_wider_whole: bool = True) -> Box:
    """The whole person behind a partial view: a detector box shorter than the prediction (under ``max_ratio`` of
    its height) whose top or bottom agrees with the prediction's (within ``edge_tolerance`` of the predicted
    height) while the other edge falls short is the visible part of a person cut by an occluder (a car or a table
    hiding the legs) or by the image border. Its height is extended to the predicted one from the agreeing edge;
    otherwise the box is kept.

    Why: the detector boxes what it sees, while the tracker, its ground truth and the motor want the whole
    person. Taken as it is, a cut box drags the Kalman centre towards the visible part and gives it a velocity
    the occlusion then carries on (the prior drifts away while the person is hidden), and its height makes the
    person look farther away than they are. Only the height: a walking person's width changes with every
    stride and swing of the arms, so a narrow box is no evidence of an occluder (completing widths would anchor
    the wrong side of a person walking behind a pillar), while the height of a standing or walking person holds.
    With ``keep_wider_whole``, a box wider than the prediction by more than 1 / ``max_ratio`` is kept as it is: an
    occluder never makes a person wider, a change of pose does (crouching, bending down, tucked), and the short,
    wide box is then the whole person as they now are; completed, it would be measured up to half a height off
    their centre."""
    w, pw, ph = float(box[2]), float(predicted_box[2]), float(predicted_box[3])
    if w <= 0.0 or pw <= 0.0 or float(box[3]) / w >= max_ratio * ph / pw:
        return tuple(float(v) for v in box)  # type: ignore[return-value]  # a whole person's shape
    if keep_wider_whole and w * max_ratio > pw:  # wider than predicted by over 1 / max_ratio: a changed pose
        return tuple(float(v) for v in box)  # type: ignore[return-value]
    y, h = _complete_extent(float(box[1]), float(box[3]), float(predicted_box[1]), ph, max_ratio, edge_tolerance)
    return (float(box[0]), y, w, h)


def trim_merged_view(box: Sequence[float], predicted_box: Sequence[float], min_ratio: float = 1.5,
                     edge_tolerance: float = 0.15) -> Box:
    """The target inside a merged view: a detector box over ``min_ratio`` of the prediction's height (or width) whose
    top or bottom (left or right) edge agrees with the prediction's (within ``edge_tolerance`` of the predicted
    extent) while the other edge reaches well beyond it boxes the target together with someone in line with it (a
    person behind them from a high camera, a group seen from above) or beside it (look-alikes side by side, seen
    too coarsely to be told apart). Along each such axis the target is the predicted extent from the agreeing edge;
    otherwise the box is kept. The mirror of :func:`complete_partial_view`, but on both axes: a stride or a swing
    of the arms widens a person by far less than half.

    Why: taken whole, such a box moves the Kalman centre by half the other person's extent in one frame and gives
    it a velocity of that size; once the two part again the prior runs on in that direction, the gate leaves the
    target behind, and the coasting prediction ends on someone else (uav-group1-3 frames 289-326, EVALUATION.md).
    A person coming closer grows at both edges, so no edge agrees and nothing is trimmed."""
    x, y, w, h = (float(v) for v in box[:4])
    px, py, pw, ph = (float(v) for v in predicted_box[:4])
    if ph > 0.0 and h > min_ratio * ph:
        y, h = _anchor_to_agreeing_edge(y, h, py, ph, edge_tolerance)
    if pw > 0.0 and w > min_ratio * pw:
        x, w = _anchor_to_agreeing_edge(x, w, px, pw, edge_tolerance)
    return (x, y, w, h)


def appearance_weight(c_t: float, tau_occ: float = 0.60, gamma: float = 10.0) -> float:
    """Eq. 3: ω(t) = 1 / (1 + exp(-γ (C_t - τ_occ))); exactly 0.5 at C_t = τ_occ."""
    z = gamma * (float(c_t) - tau_occ)
    if z >= 0.0:
        return 1.0 / (1.0 + math.exp(-z))
    e = math.exp(z)  # same value, no overflow for very negative z
    return e / (1.0 + e)


def fuse(s_color: float, s_geo: float, omega: float) -> float:
    """Eq. 2 with α = ω and β = 1 - ω."""
    return omega * s_color + (1.0 - omega) * s_geo


@dataclass
class Candidate:
    """A box re-ID weighs for the target, with its scores once scored; the box an initialisation chose is one too
    (source "init", "template", "prior", "last" or "nearest", no scores)."""

    box: Box
    source: str  # "detection", "redetection" (seed 002 §3.2's region), "low-score" or "motion"
    maha_sq: float = 0.0
    s_color: float = 0.0
    s_geo: float = 0.0
    m_fuse: float = 0.0
    hist: np.ndarray | None = field(default=None, repr=False)
    # The target's own whole box when the detector box is a partial view (complete_partial_view) or a merged one
    # (trim_merged_view): what is measured and output; the ``box`` is what the appearance is scored on. None: the
    # box is the target's.
    whole: Box | None = None
    # Where S_geo is scored, when not where the candidate is ``located``: a merged view taken as the target's own
    # extent (ReidParams.merged_view_own_extent_after_ms) is measured whole but scored as trimmed.
    scored_at: Box | None = None

    @property
    def merged_view(self) -> bool:
        """Whether the box merges the target with someone (trim_merged_view): trimmed to the target, or measured
        whole once that extent became the target's own. Completion only lengthens a box, trimming only shortens it."""
        w = self.whole
        return self.scored_at is not None or (w is not None and (w[2] < self.box[2] or w[3] < self.box[3]))

    @property
    def located(self) -> Box:
        """Where the candidate puts the whole target."""
        return self.whole if self.whole is not None else self.box


def measurement(t_ns: int, state: TrackState, chosen: Candidate | None = None, *, accepted: bool = False,
                secure: bool = False, c_t: float = 0.0, omega: float = 0.0, candidates: Sequence[Candidate] = (),
                init_box: Box | None = None, detector_score: float | None = None) -> Measurement:
    """Algorithm 1's outcome for one frame as prediction and template update consume it, stamped with the frame:
    the ``chosen`` candidate's place, origin and scores (its box as the measurement when ``accepted``), and the
    scored candidates as x, y, w, h, M_fuse rows in float64, so a value is the same in-process and across the bus."""
    msg = Measurement(
        state=state.value, accepted=bool(accepted), secure=bool(secure),
        box=box_array(chosen.located) if accepted and chosen is not None else None,
        best_box=None if chosen is None else box_array(chosen.located), source="" if chosen is None else chosen.source,
        m_fuse=float(chosen.m_fuse) if chosen else 0.0, s_color=float(chosen.s_color) if chosen else 0.0,
        s_geo=float(chosen.s_geo) if chosen else 0.0, omega=float(omega), c_t=float(c_t),
        candidates=np.array([(*c.box, c.m_fuse) for c in candidates], dtype=np.float64).reshape(-1, 5),
        candidate_sources=[c.source for c in candidates],
        candidate_hist=None if chosen is None or chosen.hist is None else np.asarray(chosen.hist),
        init_box=box_array(init_box), detector_score=-1.0 if detector_score is None else float(detector_score))
    msg.header.stamp_ns = int(t_ns)
    return msg


def _valid_boxes(detections: np.ndarray | None) -> list[Box]:
    if detections is None:
        return []
    dets = np.asarray(detections, dtype=np.float64)
    if dets.size == 0:
        return []
    dets = dets.reshape(-1, dets.shape[-1])
    boxes = []
    for row in dets:
        x, y, w, h = (float(v) for v in row[:4])
        if all(math.isfinite(v) for v in (x, y, w, h)) and w >= 1.0 and h >= 1.0:
            boxes.append((x, y, w, h))
    return boxes


def _detection_score(detections: np.ndarray | None, box: Box) -> float | None:
    """The detector score of the detection row whose box is ``box`` (None if not found)."""
    if detections is None or np.size(detections) == 0:
        return None
    rows = np.asarray(detections, dtype=np.float64).reshape(-1, np.shape(detections)[-1])
    if rows.shape[1] < 5:
        return None
    hit = np.all(np.abs(rows[:, :4] - np.asarray(box, dtype=np.float64)) < 1e-3, axis=1)
    score = float(rows[hit, 4][0]) if hit.any() else None
    return score if score is not None and math.isfinite(score) else None


def _people_among(boxes: list[Box]) -> int:
    """How many people ``boxes`` show: a box centred inside a larger one is a part of that person (a detector's
    second box on a legs, a board, a torso), not someone else."""
    people: list[Box] = []
    for box in sorted(boxes, key=lambda b: -b[2] * b[3]):
        cx, cy = box_centre(box)
        if not any(x <= cx <= x + w and y <= cy <= y + h for x, y, w, h in people):
            people.append(box)
    return len(people)


@dataclass
class _FrameBoxes:
    """The frame's detector boxes: the whole frame's and the re-detected region's (merged, tracking/redetection.py),
    and every row with its score, high and low."""

    frame: list[Box]
    region: list[Box]
    rows: np.ndarray
    low_rows: np.ndarray

    @property
    def all(self) -> list[Box]:
        return self.frame + self.region


def alone_in_view(box: Sequence[float], frame_boxes: Sequence[Sequence[float]]) -> bool:
    """Whether ``box`` is the only confident person detection of the frame (a box overlapping it by IoU 0.5 or more
    is the same person, seen by the whole-frame pass and by the re-detection of its region)."""
    return all(box_iou(other, box) >= 0.5 for other in frame_boxes)


def _rows(detections: np.ndarray | None) -> np.ndarray:
    return np.zeros((0, 5), np.float32) if detections is None else np.asarray(detections, np.float32).reshape(-1, 5)


def _frame_boxes(detections: np.ndarray | None, low_detections: np.ndarray | None, region: RegionBoxes | None,
                 frame_wh: tuple[int, int]) -> _FrameBoxes:
    if region is None:
        return _FrameBoxes(_valid_boxes(detections), [], _rows(detections), _rows(low_detections))
    rows, from_region = merge_region_boxes(_rows(detections), region.boxes, region.rect, frame_wh)
    low_rows, _ = merge_region_boxes(_rows(low_detections), region.low_boxes, region.rect, frame_wh)
    return _FrameBoxes(_valid_boxes(rows[~from_region]), _valid_boxes(rows[from_region]), rows, low_rows)


@dataclass
class _Match:
    """One association stage's outcome: every candidate so far, the best, whether it was accepted, C_t and ω."""

    candidates: list[Candidate]
    best: Candidate | None
    accepted: bool
    c_t: float
    omega: float


class ReIdentifier:
    """Stateful Algorithm 1: keeps the previous grey frame (for motion blobs) and the track state."""

    def __init__(self, params: ReidParams | None = None) -> None:
        self.params = params or ReidParams()
        p = self.params
        self._embedder: PersonEmbedder | None = None
        self._embedder_loaded = False  # loaded at the first decision that needs it (absent: logged once)
        self.identity = TargetClassifier(IdentityParams(ridge_lambda=p.ridge_lambda, delta_id=p.delta_id,
                                                        delta_switch=p.delta_switch))
        self.identity_decisions = 0  # frames where the learned appearance chose or vetoed (diagnostics)
        self._pending: tuple[np.ndarray, Box, list[Box]] | None = None  # a training sample not yet taken
        self.reset()

    def reset(self) -> None:
        self.identity.reset()
        self._last_score: float | None = None  # detector score of the last accepted box (adaptive gate)
        self._secure_frames = 0
        self.state = TrackState.UNINITIALISED
        self._prev_grey: np.ndarray | None = None
        self._t_last_accept_ns = 0
        self._t_last_frame_ns: int | None = None  # the last frame this re-ID was given (any outcome)
        # Since the last accept: time in which it was given no frame at all (its inputs were down)
        self._unseen_since_accept_ns = 0
        self._reacquired_count = 0
        self._last_box: Box | None = None  # the last accepted box: where a re-initialisation looks first
        self._confirming: tuple[Box, int] | None = None  # a far re-lock candidate and its δ_id confirmations
        self._frames_since_crowd: int | None = None  # frames since another detection shared the gate (None: never)
        self._crowd_told_apart = False  # in that crowd, the classifier scored its choice among several δ_id or more
        p = self.params
        self._frame = 0  # frames stepped: the clock of the re-acquisition evidence
        self._evidence = ReacquisitionEvidence(p.reacquire_frames, p.reacquire_window_frames,
                                               p.reacquire_max_step_heights)
        self._bystanders = BystanderTracks(p.reacquire_window_frames, p.reacquire_max_step_heights,
                                           p.unsure_bystanders_after_merge)
        self._frame_boxes: list[Box] = []  # this frame's detections and which of them are bystanders
        self._frame_bystanders: list[bool] = []
        self.candidates: list[Candidate] = []  # the last frame's scored candidates (step)
        self._lone_merged_frames = 0  # accepted frames on end whose box was a merged view with no one else gated
        self._evidence_hold = False  # re-acquired on evidence and REACQUIRED since: see _reacquire_on_evidence
        self._waiting = False  # re-initialising, and waiting for the target it follows (_wait_for_target)

    def step(self, frame_bgr: np.ndarray, detections: np.ndarray | None, prior: Prior | None,
             template_hist: np.ndarray | None, t_ns: int, init_box: Sequence[float] | None = None,
             defer_learning: bool = False, low_detections: np.ndarray | None = None,
             region: RegionBoxes | None = None) -> Measurement:
        """Run one frame (see :meth:`_step`); remembers the accepted box, and in :attr:`candidates` the frame's
        scored candidates (the measurement carries their boxes and M_fuse; tests and ``eval --trace`` read the
        rest). The learned appearance's training sample of the frame (descriptors: a few ms) is taken at the end,
        or with ``defer_learning`` when the caller calls :meth:`learn_pending` (the node: after publishing the
        measurement, off the motor's path).
        ``region``: what the re-detection of the region around the prediction found (seed 002 §3.2), merged with
        the frame's detections (tracking/redetection.py)."""
        self._pending = None
        self._frame += 1
        previous, self._t_last_frame_ns = self._t_last_frame_ns, int(t_ns)
        if previous is not None:
            self._unseen_since_accept_ns += max(int(t_ns) - previous - int(self.params.dt_ms * 1e6), 0)
        boxes = _frame_boxes(detections, low_detections, region, (frame_bgr.shape[1], frame_bgr.shape[0]))
        result = self._step(frame_bgr, boxes, prior, template_hist, t_ns, init_box)
        if result.accepted and result.box is not None:
            self._last_box = box_tuple(result.box)
            self._bystanders.adopt(self._frame_boxes, self._frame_bystanders, self._last_box, self._frame)
        if not defer_learning:
            self.learn_pending()
        return result

    def learn_pending(self) -> None:
        """Take the training sample :meth:`step` left for later, if any (the same result either way)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            self._learn_identity(*pending)

    def _step(
        self,
        frame_bgr: np.ndarray,
        dets: _FrameBoxes,
        prior: Prior | None,
        template_hist: np.ndarray | None,
        t_ns: int,
        init_box: Sequence[float] | None = None,
    ) -> Measurement:
        """Run one frame. The low-score rows (under the detector's threshold) are a second stage when no
        detection in the gate matched (seed 002's ByteTrack association).
        Without a prior or a template (or with an explicit ``init_box``) this initialises the target
        instead: ``init_box``, else (when a template exists, e.g. restored after a restart) the detection
        best matching it if above Thresh_reid, else (when a prior exists: this re-ID was restarted while
        prediction kept the track) the gated detection nearest the prior, else (prediction was restarted
        while this re-ID kept its track) the detection overlapping this re-ID's last accepted box, if it
        was accepted within ``lost_after_ms``, else the detection nearest the image bottom-centre, else the
        frame-difference ROI (§2.1)."""
        t_ns = int(t_ns)
        grey = to_grey(frame_bgr)
        prev_grey, self._prev_grey = self._prev_grey, grey
        boxes = dets.all
        self._frame_boxes, self._frame_bystanders = boxes, self._bystanders.link(boxes, self._frame)
        self.candidates = []
        if init_box is not None or prior is None or template_hist is None:
            return self._initialise(frame_bgr, boxes, prev_grey, grey, t_ns, init_box, template_hist, prior)

        prior = self._scaled_gate(prior)
        # Stage 1: the detections (score >= the detector's threshold) in the gate, the frame's and the region's.
        candidates = (self._gate_candidates(dets.frame, prior, "detection")
                      + self._gate_candidates(dets.region, prior, "redetection"))
        gated_people = _people_among([c.box for c in candidates])
        self._note_crowd(gated_people)
        match = self._match(frame_bgr, candidates, prior, template_hist)
        match = self._second_stage(frame_bgr, dets.low_rows, prior, template_hist, match)
        if not match.candidates and self._background_still(prev_grey, grey):
            match = self._motion_stage(frame_bgr, prev_grey, grey, prior, template_hist)
        match = self._reacquire_on_evidence(frame_bgr, match)
        self._advance_state(match.accepted, t_ns)
        self._note_lone_merged_view(match, gated_people)
        if match.accepted and match.best is not None:
            scored = {"detection": dets.rows, "redetection": dets.rows, "low-score": dets.low_rows}.get(
                match.best.source)
            self._last_score = (_detection_score(scored, match.best.box) if scored is not None
                                else self.params.gate_low_score)  # a motion blob: as weak as a detection can be
        self.candidates = match.candidates
        result = self._result(t_ns, match)
        if self.state is TrackState.OCCLUDED and not result.accepted and self.params.coasting_colour_check:
            result.coasting_colours_seen = self._coasting_colours_seen(frame_bgr, prior, template_hist, boxes)
        if result.secure and match.best is not None:
            self._pending = (frame_bgr, match.best.located, boxes)
        logger.debug(
            "reid t=%d state=%s n=%d C_t=%.3f ω=%.3f M=%.3f", t_ns, self.state.value, len(match.candidates),
            match.c_t, match.omega, result.m_fuse,
        )
        return result

    def _match(self, frame_bgr: np.ndarray, candidates: list[Candidate], prior: Prior,
               template_hist: np.ndarray) -> _Match:
        """Score ``candidates`` and accept the best above Thresh_reid (Alg. 1 line 9), as the learned appearance
        decides between look-alikes."""
        best, c_t, omega = self._score(frame_bgr, candidates, prior, template_hist)
        accepted = best is not None and best.m_fuse > self.params.reid_threshold
        if accepted and best is not None:
            best, accepted = self._identity_decision(frame_bgr, candidates, best, prior)
        elif best is not None and self._uncontested(candidates, best, prior):
            accepted = True
        return _Match(candidates, best, accepted, c_t, omega)

    def _uncontested(self, candidates: list[Candidate], best: Candidate, prior: Prior) -> bool:
        """A lone detector box centred inside the predicted box (grown by the prior centre's standard deviation, to
        twice its size at most), with nobody else near it: the target, whatever its colours now say (it turned, the
        light changed, spray hides it). ByteTrack's caution, widened to the coast: only while the prediction still
        locates the person (matched on the last frame, or OCCLUDED with a prior that still locates them,
        Prior.locates_person); and only while no other detection has shared the gate for
        identity_veto_after_crowd_frames (an occluder walking in front is such a detection before it hides the
        target)."""
        p = self.params
        fresh = self.state in (TrackState.TRACKING, TrackState.REACQUIRED) or (
            self.state is TrackState.OCCLUDED and prior.locates_person)
        if not p.uncontested_lone_candidate or not fresh:
            return False
        detections = [c for c in candidates if c.source in DETECTOR_SOURCES]
        alone = self._frames_since_crowd is None or self._frames_since_crowd > p.identity_veto_after_crowd_frames
        return detections == [best] and alone and self._where_predicted(best.located, prior)

    def _where_predicted(self, box: Box, prior: Prior) -> bool:
        """Whether ``box`` is centred inside the predicted box, grown by the prior centre's standard deviation on
        each axis (uncontested_within_prior_std) to twice its size at most: a prior that unsure no longer says where
        the person is."""
        (cx, cy), (px, py) = box_centre(box), prior.centre
        half_w, half_h = prior.size[0] / 2.0, prior.size[1] / 2.0
        sx, sy = (min(math.sqrt(max(float(prior.covariance[i, i]), 0.0)), half)
                  if self.params.uncontested_within_prior_std else 0.0 for i, half in ((0, half_w), (1, half_h)))
        return abs(cx - px) <= half_w + sx and abs(cy - py) <= half_h + sy

    def _second_stage(self, frame_bgr: np.ndarray, low_detections: np.ndarray | None, prior: Prior,
                      template_hist: np.ndarray, first: _Match) -> _Match:
        """Stage 2 (seed 002 / ByteTrack): nothing in the gate matched, so the low-score detections, where a partly
        hidden target still is; scored alike, never a training sample (not secure). ByteTrack's second association
        takes only the tracks matched on the previous frame (its T_remain holds tracked, not lost, tracks) and only
        boxes overlapping their prediction (IoU 0.5): not while OCCLUDED."""
        p = self.params
        tracked = self.state in (TrackState.TRACKING, TrackState.REACQUIRED)
        low = _valid_boxes(low_detections) if p.low_score_stage and tracked else []
        if first.accepted or not low:
            return first
        second = [c for c in self._gate_candidates(low, prior, "low-score")
                  if box_iou(c.located, prior.box) >= p.low_score_min_iou]
        match = self._match(frame_bgr, second, prior, template_hist)
        candidates = first.candidates + second
        if match.accepted:
            return _Match(candidates, match.best, True, match.c_t, match.omega)
        return dataclasses.replace(first, candidates=candidates)

    def _reacquire_on_evidence(self, frame_bgr: np.ndarray, match: _Match) -> _Match:
        """While OCCLUDED or LOST, count the frames on which one detection is the clear best candidate
        (tracking/reacquisition.py) and re-acquire it once they are enough; any accepted match ends the count. Just
        re-acquired that way (REACQUIRED), a frame whose best is refused still takes it if it is the clear best and
        continues the person the evidence followed (reacquire_hold_on_evidence): the prior has one measurement and no
        velocity yet, and a moving person's next box falls just under T_reid."""
        p = self.params
        holding = p.reacquire_hold_on_evidence and self.state is TrackState.REACQUIRED and self._evidence_hold
        if match.accepted or (self.state not in (TrackState.OCCLUDED, TrackState.LOST) and not holding):
            self._evidence.reset()
            self._evidence_hold = False
            return match
        best, vetted = self._clear_best(frame_bgr, match) if p.reacquire_on_evidence else (None, False)
        if best is None:
            return match
        if not vetted and self._rejected_by_classifier(frame_bgr, best):
            self._evidence.reset()  # whoever the evidence was on, this frame's best is someone else
            return match
        if holding:
            return self._hold_on_evidence(match, best)
        if self._evidence.observe(best.located, self._frame, 2 if self._bystander(best.box, unsure=True) else 1):
            self._evidence_hold = True
            logger.info("re-acquired on %d frames of evidence at %s", self._evidence.count,
                        tuple(round(v, 1) for v in best.located))
            return dataclasses.replace(match, best=best, accepted=True)
        return match

    def _hold_on_evidence(self, match: _Match, best: Candidate) -> _Match:
        """Accept ``best`` if it continues the person the evidence followed; else the hold ends."""
        person = self._evidence.person
        if person is not None and person.continues(best.located, self._frame, self._evidence.max_step_heights):
            self._evidence.observe(best.located, self._frame)
            return dataclasses.replace(match, best=best, accepted=True)
        self._evidence.reset()
        self._evidence_hold = False
        return match

    def _clear_best(self, frame_bgr: np.ndarray, match: _Match) -> tuple[Candidate | None, bool]:
        """The frame's best plausible detection (none of the people seen beside the target, BystanderTracks, but for
        an unsure one) when it has the target's colours (S_color >= τ_occ) and leads every other detection that is no
        bystander by identity_margin in M_fuse, or, failing that, in the classifier's score
        (reacquire_classifier_breaks_ties); else None. And whether the classifier already scored it δ_switch or more
        (no need to ask it again)."""
        p = self.params
        detections = [c for c in match.candidates if c.source in DETECTOR_SOURCES]
        plausible = [c for c in detections if not self._bystander(c.box) or self._bystander(c.box, unsure=True)]
        if not plausible:
            return None, False
        best = max(plausible, key=lambda c: c.m_fuse)
        if best.s_color < p.tau_occ:
            return None, False
        close = [c for c in detections
                 if c is not best and c.m_fuse > best.m_fuse - p.identity_margin and not self._bystander(c.box)]
        if not close:
            return best, False
        if p.reacquire_classifier_breaks_ties and self._classifier_prefers(frame_bgr, best, close):
            return best, True
        return None, False

    def _classifier_prefers(self, frame_bgr: np.ndarray, best: Candidate, close: list[Candidate]) -> bool:
        """Whether the classifier, when it has learnt the target, scores ``best`` δ_switch or more and ahead of each
        of ``close`` by identity_margin (seed 001: it decides where colour and geometry do not)."""
        p = self.params
        scores = self._identity_scores(frame_bgr, [best.box] + [c.box for c in close])
        if scores is None or len(scores) != 1 + len(close):
            return False
        return float(scores[0]) >= p.delta_switch and float(scores[0]) - float(np.max(scores[1:])) >= p.identity_margin

    def _bystander(self, box: Box, unsure: bool = False) -> bool:
        """Whether ``box`` is one of this frame's detections that continues a bystander track (``unsure``: one that
        went through a merge)."""
        flags = self._bystanders.unsure if unsure else self._frame_bystanders
        return any(flag and b == tuple(box) for b, flag in zip(self._frame_boxes, flags, strict=True))

    def _rejected_by_classifier(self, frame_bgr: np.ndarray, candidate: Candidate) -> bool:
        """The classifier, when it has learnt the target, takes ``candidate`` for someone else (below δ_switch)."""
        scores = self._identity_scores(frame_bgr, [candidate.box])
        return scores is not None and float(scores[0]) < self.params.delta_switch

    def _identity_scores(self, frame_bgr: np.ndarray, boxes: list[Box]) -> np.ndarray | None:
        """The classifier's scores of ``boxes`` (the first identity_max_crops), or None when it has no say: off, not
        trained on the target and someone else yet, or no descriptor."""
        if not (self.params.learned_appearance and self.identity.ready):
            return None
        embs = self._embed(frame_bgr, boxes)
        return self.identity.score(embs) if embs is not None and len(embs) else None

    def _background_still(self, prev_grey: np.ndarray | None, grey: np.ndarray) -> bool:
        """Alg. 1 line 2's background subtraction presumes a still background: see
        ReidParams.motion_max_changed_fraction."""
        p = self.params
        return prev_grey is not None and changed_fraction(prev_grey, grey, p.diff_threshold) <= \
            p.motion_max_changed_fraction

    def _motion_stage(self, frame_bgr: np.ndarray, prev_grey: np.ndarray, grey: np.ndarray, prior: Prior,
                      template_hist: np.ndarray) -> _Match:
        """Alg. 1 line 2: nothing detected in R, look for moving regions inside it instead."""
        p = self.params
        roi = self._search_window(prior, grey.shape) if p.use_gate else None
        blobs = motion_blobs(prev_grey, grey, p.diff_threshold, p.morph_kernel_px, p.min_blob_area_px, roi)
        min_area = p.motion_min_area_fraction * prior.size[0] * prior.size[1]
        candidates = self._gate_candidates([b for b, _ in blobs if b[2] * b[3] >= min_area], prior, "motion")
        return self._match(frame_bgr, candidates, prior, template_hist)

    def _result(self, t_ns: int, match: _Match) -> Measurement:
        """The frame's measurement once the state has advanced: the best candidate's scores, and its box if accepted
        (secure: TRACKING on an unambiguous detection)."""
        return measurement(t_ns, self.state, match.best, accepted=match.accepted, secure=self._secure(match),
                           c_t=match.c_t, omega=match.omega, candidates=match.candidates,
                           detector_score=self._last_score)

    def _coasting_colours_seen(self, frame_bgr: np.ndarray, prior: Prior, template_hist: np.ndarray,
                               boxes: list[Box]) -> bool:
        """The target's colours at the coasting box (ReidParams.coasting_colour_check): S_color above Thresh_reid
        and by coasting_colour_margin above every box around it, with no one else's detector box on it."""
        box = prior.coasting_box()
        if box is None or any(box_iou(b, box) > 0.0 for b in boxes):
            return False
        p = self.params
        at_box, around = colour_contrast(frame_bgr, box, template_hist, p.bins_h, p.bins_s)
        return around is not None and at_box > p.reid_threshold and at_box - around >= p.coasting_colour_margin

    def _secure(self, match: _Match) -> bool:
        """Eq. 10's "tracked securely": accepted while TRACKING, on a detector box no other candidate comes within
        ambiguity_margin of, and not a partial view (its whole box covers the occluder: no training sample)."""
        best = match.best
        if best is None or not match.accepted:
            return False
        ambiguous = any(
            c is not best and c.m_fuse >= best.m_fuse - self.params.ambiguity_margin for c in match.candidates
        )
        return (self.state is TrackState.TRACKING and not ambiguous and best.source in DETECTOR_SOURCES
                and best.whole is None)

    def _score(self, frame_bgr: np.ndarray, candidates: list[Candidate], prior: Prior,
               template_hist: np.ndarray) -> tuple[Candidate | None, float, float]:
        """Alg. 1 lines 4-6 on ``candidates`` (in place): S_color, S_geo, ω(t) and M_fuse; returns the best
        (first on ties), C_t and ω."""
        p = self.params
        for c in candidates:
            c.hist = hs_histogram(frame_bgr, c.box, p.bins_h, p.bins_s)
            c.s_color = bhattacharyya(c.hist, template_hist)  # Eq. 1, Alg. 1 line 4
            c.s_geo = (geometric_score(c.scored_at or c.located, prior.box, c.maha_sq, prior.gate_chi2, p.geo_scale)
                       if p.use_geometry else 0.0)  # Alg. 1 line 5
        c_t = max((c.s_color for c in candidates), default=0.0)
        omega = appearance_weight(c_t, p.tau_occ, p.gamma) if p.use_geometry else 1.0  # Eq. 3
        for c in candidates:
            c.m_fuse = fuse(c.s_color, c.s_geo, omega)  # Eq. 2, Alg. 1 line 6
        # The choice between candidates: Eq. 2 with ω scaled by how far colour tells them apart
        ranking = omega * self._colour_separation(candidates)
        best = max(candidates, key=lambda c: fuse(c.s_color, c.s_geo, ranking)) if candidates else None
        return best, c_t, omega

    def _colour_separation(self, candidates: list[Candidate]) -> float:
        """How far colour tells the two likeliest-looking candidates apart, in [0, 1]: their S_color gap over
        ambiguity_margin. Eq. 3's ω weighs appearance by how visible the target is (C_t), and among look-alikes
        every candidate is visible: two boxes of similar colours (the target, and a box merging it with a
        neighbour) tie at 0.94, and with ω 0.97 geometry, which tells them apart, would count for 3 %. Scaling ω
        by this gap lets geometry decide what colour cannot (Eq. 2 with β = 1 - ω); one candidate, or colours
        apart by the margin: the seed's ω."""
        p = self.params
        if not p.colour_ties_to_geometry or len(candidates) < 2:
            return 1.0
        low, high = sorted(c.s_color for c in candidates)[-2:]
        return min(max(high - low, 0.0) / max(p.ambiguity_margin, 1e-6), 1.0)

    def gate_scale(self, prior: Prior) -> float:
        """Seed 002 §3.2's search scale k for this target (tracking/redetection.py search_scale; a motion blob's
        last match counts as weak)."""
        return search_scale(prior, self._last_score, self.params.dt_ms, self.params)

    def _scaled_gate(self, prior: Prior) -> Prior:
        k = self.gate_scale(prior)
        return prior if k == 1.0 else dataclasses.replace(prior, gate_chi2=prior.gate_chi2 * k * k)

    # --- learned appearance (seed 001, tracking/learned_appearance.py) ------------------------------------------------

    def prepare(self) -> bool:
        """Load the descriptor model now rather than at the first decision that needs it (a live node: the
        load must not delay a frame). True when the learned appearance is on and its model loaded."""
        if self.params.learned_appearance and not self._embedder_loaded:
            self._embedder, self._embedder_loaded = load_embedder(), True
            if self._embedder is not None:  # the first inference allocates: not on a frame's time
                self._embedder.embed(np.zeros((CROP_H_PX, CROP_W_PX, 3), np.uint8), [(0.0, 0.0, CROP_W_PX, CROP_H_PX)])
        return self._embedder is not None

    def _embed(self, frame_bgr: np.ndarray, boxes: list[Box]) -> np.ndarray | None:
        if not self.prepare():
            return None
        return self._embedder.embed(frame_bgr, boxes[: self.params.identity_max_crops])

    def _identity_decision(self, frame_bgr: np.ndarray, candidates: list[Candidate],
                           best: Candidate, prior: Prior) -> tuple[Candidate, bool]:
        """Colour + geometry chose ``best``; the classifier decides when that choice is not clear (seed 001
        §III-D): among the contenders within ``identity_margin`` of it, the one it scores highest, if that
        one clears δ_switch; on a re-lock after an occlusion, a lone contender scoring below δ_switch is taken
        for someone else and rejected (the target stays occluded), and a contender far from the prior
        must score δ_id on ``n_id_frames`` consecutive frames (seed 001's Re-ID state), unless it is alone in view
        (far_relock_alone_in_view); with no classifier to ask, a far re-lock among candidates M_fuse does not tell
        apart waits (far_relock_tie_waits). Returns (chosen, accepted)."""
        p = self.params
        relock = self.state in (TrackState.OCCLUDED, TrackState.LOST)
        if not relock:
            self._confirming = None
        scored = self._score_contenders(frame_bgr, candidates, best, relock)
        if scored is None:
            return best, not (relock and self._far_tie(candidates, best, prior))
        contenders, scores = scored
        i = int(np.argmax(scores))
        if scores[i] < p.delta_switch:
            # Nobody here looks like the target: on a re-lock, wait; while tracking, keep colour's choice, unless
            # the classifier just told these people apart (a crossing: the target is hidden behind them): wait.
            return best, not (relock or self._crowded_recently())
        alone = p.far_relock_alone_in_view and alone_in_view(contenders[i].box, self._frame_boxes)
        if relock and p.far_relock_needs_identity and self._far(contenders[i].located, prior) and not alone:
            return contenders[i], self._confirmed(contenders[i].located, float(scores[i]))
        return contenders[i], True

    def _score_contenders(self, frame_bgr: np.ndarray, candidates: list[Candidate], best: Candidate,
                          relock: bool) -> tuple[list[Candidate], np.ndarray] | None:
        """The classifier's scores of the contenders within ``identity_margin`` of ``best`` (best first), or None
        when it has no say: not ready or off, a lone contender while tracking outside a crowd's aftermath, no
        descriptor. Notes a crowd the classifier told apart (its choice among several at δ_id or more)."""
        p = self.params
        contenders = sorted((c for c in candidates if c.m_fuse > p.reid_threshold
                             and c.m_fuse >= best.m_fuse - p.identity_margin), key=lambda c: -c.m_fuse)
        lone_check = len(contenders) < 2 and not relock
        if lone_check and not self._crowded_recently():  # a lone contender is scored only just after a crowd
            return None
        scores = self._identity_scores(frame_bgr, [c.box for c in contenders])
        if scores is None:
            return None
        self.identity_decisions += 1
        if not relock and not lone_check and scores[int(np.argmax(scores))] >= p.delta_id:
            self._crowd_told_apart = True
        return contenders, scores

    def _note_crowd(self, gated_people: int) -> None:
        """Count the frames since another person's detection shared the gate with the target; a crowd over forgets
        whether the classifier told its people apart."""
        if gated_people >= 2:
            self._frames_since_crowd = 0
        elif self._frames_since_crowd is not None:
            self._frames_since_crowd += 1
            if self._frames_since_crowd > self.params.identity_veto_after_crowd_frames:
                self._frames_since_crowd, self._crowd_told_apart = None, False

    def _crowded_recently(self) -> bool:
        """Another detection shared the gate within identity_veto_after_crowd_frames frames and the classifier told
        them apart then: only a classifier that separates these people may veto colour's choice (early on, or
        between look-alikes it has not learnt, it scores everyone alike, the target too)."""
        return (self.params.identity_veto_after_crowd_frames > 0 and self._frames_since_crowd is not None
                and self._crowd_told_apart)

    def _far_tie(self, candidates: list[Candidate], best: Candidate, prior: Prior) -> bool:
        """A far re-lock (_far) with another candidate within identity_margin of ``best`` in M_fuse, which only
        the classifier could decide (far_relock_tie_waits)."""
        p = self.params
        return (p.far_relock_tie_waits and self._far(best.located, prior)
                and any(c is not best and c.m_fuse >= best.m_fuse - p.identity_margin for c in candidates))

    def _far(self, box: Box, prior: Prior) -> bool:
        """A re-lock candidate farther than relock_far_height_fraction of the target's height from where the prior
        puts it: its centre, and the likeliest motion model's box when the prior mixes several (the mixture's mean
        can lie between two places the person may be)."""
        cx, cy = box_centre(box)
        centres = [prior.centre] + ([box_centre(prior.likeliest_box)] if prior.likeliest_box is not None else [])
        limit = self.params.relock_far_height_fraction * max(prior.size[1], 1.0)
        return all(math.hypot(cx - px, cy - py) > limit for px, py in centres)

    def _confirmed(self, box: Box, score: float) -> bool:
        """Seed 001's N_id: a far re-lock needs δ_id on n_id_frames consecutive frames, on the same person (overlapping
        the box confirmed on the frame before)."""
        p = self.params
        if score < p.delta_id:
            self._confirming = None
            return False
        count = 1
        if self._confirming is not None and box_iou(self._confirming[0], box) > 0.3:
            count = self._confirming[1] + 1
        self._confirming = (box, count)
        return count >= p.n_id_frames

    def _learn_identity(self, frame_bgr: np.ndarray, target: Box, boxes: list[Box]) -> None:
        """Every ``identity_sample_every_frames``-th secure frame: the target's descriptor as a positive and
        the other detections' as negatives, only while the target overlaps no one above δ_iou (a mixed crop
        would teach the classifier both people, seed 001 §IV)."""
        p = self.params
        if not p.learned_appearance:
            return
        self._secure_frames += 1
        if (self._secure_frames - 1) % p.identity_sample_every_frames:
            return
        others = [b for b in boxes if box_iou(b, target) < 0.9]  # the target's own detection is not another
        if any(box_iou(b, target) > p.delta_iou for b in others):
            return
        tx, ty = box_centre(target)
        others.sort(key=lambda b: (box_centre(b)[0] - tx) ** 2 + (box_centre(b)[1] - ty) ** 2)
        embs = self._embed(frame_bgr, [target, *others[: max(p.identity_max_crops - 1, 0)]])
        if embs is not None and len(embs):
            self.identity.add(embs[0], embs[1:])

    def _initialise(
        self,
        frame_bgr: np.ndarray,
        boxes: list[Box],
        prev_grey: np.ndarray | None,
        grey: np.ndarray,
        t_ns: int,
        init_box: Sequence[float] | None,
        template_hist: np.ndarray | None,
        prior: Prior | None = None,
    ) -> Measurement:
        p = self.params
        height, width = grey.shape[:2]
        box: Box | None = None
        source = "init"
        given = box_tuple(init_box)
        if given is not None and self._init_box_holds_the_target(frame_bgr, given, template_hist):
            box = given
        elif template_hist is not None and (match := self._template_match(frame_bgr, boxes, template_hist)):
            box, source = match, "template"
        elif prior is not None and (gated := self._gate_candidates(boxes, prior, "detection")):
            box, source = min(gated, key=lambda c: c.maha_sq).box, "prior"  # Eq. 8: the track still known
        elif (last := self._recent_last_box(t_ns)) is not None and boxes \
                and max(box_iou(b, last) for b in boxes) > 0.0:
            # Not the nearest-to-bottom person (a passer-by may be nearer): the one where the target just was.
            box, source = max(boxes, key=lambda b: box_iou(b, last)), "last"
        elif self._follows_someone(template_hist):
            return self._wait_for_target(t_ns)
        elif boxes:
            box, source = nearest_to_centre_bottom(np.array(boxes), width, height), "nearest"
        elif prev_grey is not None:
            blobs = motion_blobs(prev_grey, grey, p.diff_threshold, p.morph_kernel_px, p.min_blob_area_px)
            box = blobs[0][0] if blobs else None
        if box is None:
            self.state = TrackState.UNINITIALISED
            return measurement(t_ns, self.state)
        self._waiting = False
        self._last_score = None
        if source in ("init", "nearest"):  # a new target: what the classifier learnt was someone else
            self.identity.reset()
            self._secure_frames = 0
            self._frames_since_crowd, self._crowd_told_apart = None, False
        self.state = TrackState.TRACKING
        self._t_last_accept_ns, self._unseen_since_accept_ns = t_ns, 0
        self._reacquired_count = 0
        self._lone_merged_frames = 0  # the new prior's extent is this box's
        logger.info("target initialised at %s (%s)", tuple(round(v, 1) for v in box), source)
        chosen = Candidate(box, source, hist=hs_histogram(frame_bgr, box, p.bins_h, p.bins_s))
        return measurement(t_ns, self.state, chosen, accepted=True, init_box=box)

    def _follows_someone(self, template_hist: np.ndarray | None) -> bool:
        """This re-ID has followed a target and has its template: a re-initialisation (prediction reset or
        restarted) is about that person, and the §2.1 start-up rules (the person nearest the image bottom-centre, a
        motion blob) would choose whoever stands nearest instead."""
        return self.params.reinitialise_only_on_the_target and template_hist is not None \
            and self._last_box is not None

    def _init_box_holds_the_target(self, frame_bgr: np.ndarray, init_box: Box,
                                   template_hist: np.ndarray | None) -> bool:
        """Whether to take ``init_box``: always at start-up; once this re-ID follows someone (a camera restarted
        with init_box set), only when what stands there matches the template, for init_box says where the target
        stood when the source started, and after a live camera's restart a passer-by may stand there."""
        if not self._follows_someone(template_hist):
            return True
        if template_hist is not None and self._template_match(frame_bgr, [init_box], template_hist) is not None:
            return True
        logger.warning("init_box %s does not look like the target followed so far: re-acquiring it by its template",
                       tuple(round(v, 1) for v in init_box))
        return False

    def _wait_for_target(self, t_ns: int) -> Measurement:
        """LOST until a detection matches the template or lies where the target just was: the motor holds still."""
        if not self._waiting:
            logger.warning("re-initialising: no detection looks like the target or lies where it just was; "
                           "waiting for it instead of taking whoever is nearest")
        self._waiting = True
        self.state = TrackState.LOST
        return measurement(t_ns, self.state)

    def _recent_last_box(self, t_ns: int) -> Box | None:
        """The last accepted box, if accepted within lost_after_ms of the frames this re-ID was shown: a gap in
        which it was given no frame at all (prediction restarting: no prior, so no input set) is not time the
        target was looked for and not seen (a slow restart of prediction would make the box look stale, and re-ID
        re-initialise on the person nearest the image bottom instead)."""
        seen_ns = t_ns - self._t_last_accept_ns - self._unseen_since_accept_ns
        if self._last_box is None or seen_ns > self.params.lost_after_ms * 1e6:
            return None
        return self._last_box

    def _template_match(self, frame_bgr: np.ndarray, boxes: list[Box], template_hist: np.ndarray) -> Box | None:
        """A template survived a restart of the prediction side: re-lock onto the detection that
        looks like it (if any clears Thresh_reid) rather than onto whoever is nearest."""
        p = self.params
        scores = [bhattacharyya(hs_histogram(frame_bgr, b, p.bins_h, p.bins_s), template_hist) for b in boxes]
        if not scores:
            return None
        i = int(np.argmax(scores))
        return boxes[i] if scores[i] > p.reid_threshold else None

    def _gate_candidates(self, boxes: list[Box], prior: Prior, source: str) -> list[Candidate]:
        p = self.params
        out = []
        for box in boxes:
            whole, scored_at = self._whole(box, prior, source)
            d2 = prior.mahalanobis_sq(box_centre(scored_at or whole or box))
            gated = p.use_gate and not (p.global_search_when_lost and self.state is TrackState.LOST)
            if gated and not d2 <= prior.gate_chi2:  # Eq. 8 (also drops NaN)
                continue
            out.append(Candidate(box=box, source=source, maha_sq=d2, whole=whole, scored_at=scored_at))
        return out

    def _whole(self, box: Box, prior: Prior, source: str) -> tuple[Box | None, Box | None]:
        """(whole, scored_at) of a box: the whole person when it is a partial or a merged view
        (complete_partial_view, trim_merged_view), else None; and, for a merged view whose extent has become the
        target's own (_own_extent_settled), the trimmed box its geometry is scored on while it is measured whole. A
        motion blob is partial by nature (the moving limbs) and says nothing of where the edges are: never reshaped."""
        p = self.params
        if source == "motion":
            return None, None
        as_is = tuple(float(v) for v in box)
        whole = as_is
        if p.partial_view_completion:
            whole = complete_partial_view(box, prior.box, p.partial_max_extent_ratio, p.partial_edge_tolerance,
                                          p.partial_view_keeps_wider_whole)
        if whole == as_is and p.merged_view_trimming:
            whole = trim_merged_view(box, prior.box, p.merged_min_extent_ratio, p.partial_edge_tolerance)
            if whole != as_is and self._own_extent_settled():
                return None, whole
        return (whole if whole != as_is else None), None

    def _note_lone_merged_view(self, match: _Match, gated_people: int) -> None:
        """Count the accepted frames on end whose box is a merged view (trimmed or, once settled, not) while no one
        else shares the gate; any other accepted box ends the count, a frame without one leaves it."""
        if not match.accepted or match.best is None or match.best.source == "motion":
            return  # a motion blob is never reshaped: it says nothing of the extent
        lone_merged = match.best.merged_view and gated_people <= 1
        self._lone_merged_frames = self._lone_merged_frames + 1 if lone_merged else 0

    def _own_extent_settled(self) -> bool:
        """A merged view alone in the gate for merged_view_own_extent_after_ms: the extent is the target's own."""
        p = self.params
        return p.merged_view_own_extent and self._lone_merged_frames * p.dt_ms >= p.merged_view_own_extent_after_ms

    @staticmethod
    def _search_window(prior: Prior, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
        """Bounding rectangle of the gate ellipse, padded by half the predicted box so blobs of a
        target centred near the boundary are not cut; the motion search costs O(w·h) (§2.3)."""
        S = prior.innovation_cov
        cx, cy = prior.centre
        rx = math.sqrt(max(prior.gate_chi2 * float(S[0, 0]), 0.0)) + prior.size[0] / 2.0
        ry = math.sqrt(max(prior.gate_chi2 * float(S[1, 1]), 0.0)) + prior.size[1] / 2.0
        height, width = shape[:2]

        def clamp(v: float, hi: int) -> int:
            return int(min(max(v, 0.0), float(hi)))

        return (clamp(math.floor(cx - rx), width), clamp(math.floor(cy - ry), height),
                clamp(math.ceil(cx + rx), width), clamp(math.ceil(cy + ry), height))

    def _advance_state(self, accepted: bool, t_ns: int) -> None:
        previous = self.state
        if accepted:
            if previous in (TrackState.OCCLUDED, TrackState.LOST):
                self.state, self._reacquired_count = TrackState.REACQUIRED, 1
            elif previous is TrackState.REACQUIRED and self._reacquired_count < self.params.reacquired_hold_frames:
                self._reacquired_count += 1
            else:
                self.state = TrackState.TRACKING
            self._t_last_accept_ns, self._unseen_since_accept_ns = t_ns, 0
        else:
            lost_after_ns = int(round(self.params.lost_after_ms * 1e6))
            occluded_ns = t_ns - self._t_last_accept_ns
            self.state = TrackState.LOST if occluded_ns > lost_after_ns else TrackState.OCCLUDED
        if self.state is not previous:
            logger.info("track state %s -> %s at t=%d", previous.value, self.state.value, t_ns)

