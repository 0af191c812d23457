"""Single-target (person-following) metrics: precision/recall/F1, CLE, TSR, stability, switches, re-ID latency.

Definitions follow the follower paper's §3.3 where it is explicit and are pinned down here where it is not:

* Box convention: ``(x, y, w, h)`` float pixels, top-left corner. A tracker output may be ``None`` (no output
  on that frame) and a ground-truth box may be ``None`` (target absent / not annotated).
* ``e_t`` = Euclidean distance between output centre and ground-truth centre (defined only when both exist).
* A frame is *successful* iff gt and output exist and ``e_t < tsr_px`` (strict, as in the paper; τ = 20 px).
* precision = successful frames / frames with an output (an output on a frame without gt is a false positive);
  recall = successful frames / frames with gt; F1 = 2·TP / (outputs + gt frames) (= 2PR/(P+R)).
  With this centre-based notion of "correct", recall coincides with TSR by construction.
* TSR = successful frames / frames with gt (a missing output is a failure). Frames without gt are excluded:
  there is nothing to localise.
* CLE (``cle``) = mean ``e_t`` over frames where both gt and output exist; ``missing_outputs`` reports how many
  gt frames had no output. ``cle_all`` averages over *all* gt frames, charging a missing output the image
  diagonal (the worst in-image error); it needs ``image_size`` and is NaN otherwise (unless nothing is missing).
* stability = population std (1/N_succ) of ``e_t`` over the successful frames (§3.3 formula).
* target switch: see :func:`_frame_owner` — a transition of the output from the target onto a distractor.
* re-ID latency: see :func:`_reid_events`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..msgs.box import Box, box_iou  # one box and one IoU for the tracker and its evaluation

log = logging.getLogger(__name__)

__all__ = [
    "Box",
    "ReidEvent",
    "SingleTargetMetrics",
    "aggregate",
    "box_center",
    "box_iou",
    "evaluate_single_target",
    "format_markdown_table",
]


def box_center(box: Box) -> tuple[float, float]:
    x, y, w, h = box
    return x + w / 2.0, y + h / 2.0


def _center_dist(a: Box, b: Box) -> float:
    (ax, ay), (bx, by) = box_center(a), box_center(b)
    return math.hypot(ax - bx, ay - by)


def _point_in_box(px: float, py: float, box: Box) -> bool:
    x, y, w, h = box
    return x <= px <= x + w and y <= py <= y + h


@dataclass(frozen=True)
class ReidEvent:
    """One occlusion → reappearance cycle of the target in the ground truth (frame indices are 0-based)."""

    occlusion_start: int  # first frame of the gt-absent run
    reappear_frame: int  # first gt-visible frame after the run
    occluded_frames: int
    latency_frames: int | None  # None = censored: never re-locked before the next occlusion / end
    latency_ms: float | None
    observed_frames: int  # length of the window searched for the re-lock


@dataclass
class SingleTargetMetrics:
    """Per-sequence (or aggregated) single-target metrics. Rates are fractions in [0, 1], errors in px."""

    frames: int
    frames_with_gt: int
    outputs: int  # frames with a tracker output (gt or not)
    successes: int  # frames with gt, output and e_t < tsr_px
    false_positives: int  # outputs - successes (wrong place, or output while gt absent)
    missing_outputs: int  # gt frames without output
    precision: float
    recall: float
    f1: float
    cle: float  # mean e_t over frames with both gt and output
    cle_frames: int
    cle_all: float  # mean over gt frames, missing output = image diagonal (NaN if unknown)
    tsr: float
    stability: float  # population std of e_t over successful frames
    mean_iou: float  # over frames with both gt and output
    iou_success: float  # fraction of gt frames with IoU >= iou_threshold (OTB success @ threshold)
    iou_hits: int  # numerator of iou_success
    target_switches: int
    frames_on_distractor: int
    reid_events: list[ReidEvent] = field(default_factory=list)
    wrong_relocks: int = 0  # episodes of >= WRONG_RELOCK_FRAMES outputs with zero overlap on the target's box
    # gt frames without an output while re-ID's best-scoring candidate was a detection on the target
    # (missed_reacquisition_frames); None for a method that reports no candidates
    missed_reacquisitions: int | None = None
    center_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per frame, NaN if undefined
    ious: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per frame, NaN if undefined
    tsr_px: float = 20.0
    iou_threshold: float = 0.5
    fps: float = 30.0
    image_diagonal: float | None = None

    @property
    def reid_latencies_frames(self) -> list[int]:
        return [e.latency_frames for e in self.reid_events if e.latency_frames is not None]

    @property
    def reid_latency_frames_mean(self) -> float:
        lat = self.reid_latencies_frames
        return float(np.mean(lat)) if lat else math.nan

    @property
    def reid_latency_ms_mean(self) -> float:
        lat = [e.latency_ms for e in self.reid_events if e.latency_ms is not None]
        return float(np.mean(lat)) if lat else math.nan

    @property
    def reid_censored(self) -> int:
        return sum(1 for e in self.reid_events if e.latency_frames is None)

    def as_dict(self) -> dict[str, float | int]:
        """Scalar summary (for JSON / CSV); arrays and events are left out."""
        return {
            "frames": self.frames, "frames_with_gt": self.frames_with_gt, "outputs": self.outputs,
            "successes": self.successes, "false_positives": self.false_positives,
            "missing_outputs": self.missing_outputs, "precision": self.precision, "recall": self.recall,
            "f1": self.f1, "cle": self.cle, "cle_frames": self.cle_frames, "cle_all": self.cle_all,
            "tsr": self.tsr, "stability": self.stability, "mean_iou": self.mean_iou,
            "iou_success": self.iou_success, "target_switches": self.target_switches,
            "frames_on_distractor": self.frames_on_distractor, "reid_events": len(self.reid_events),
            "reid_latency_frames_mean": self.reid_latency_frames_mean,
            "reid_latency_ms_mean": self.reid_latency_ms_mean, "reid_censored": self.reid_censored,
            "wrong_relocks": self.wrong_relocks, "missed_reacquisitions": self.missed_reacquisitions,
        }


def _ratio(num: float, den: float) -> float:
    return num / den if den > 0 else math.nan


def _frame_owner(pred: Box | None, gt: Box | None, others: Sequence[Box], tsr_px: float,
                 iou_threshold: float) -> str:
    """Whom the output is on: 'target', 'distractor' or 'none'.

    'distractor': some other person's box d has IoU(pred, d) > iou_threshold, or contains the output centre,
    *and* the output centre is closer to d's centre than to the target's (target absent → always closer).
    The closer-than clause matters because people overlap (joggers side by side): a box on the target may
    have its centre inside a neighbour's box. 'target': not on a distractor and a successful frame.
    Anything else (no output, lost in the background) is 'none'.
    """
    if pred is None:
        return "none"
    d_target = _center_dist(pred, gt) if gt is not None else math.inf
    cx, cy = box_center(pred)
    for other in others:
        on_it = box_iou(pred, other) > iou_threshold or _point_in_box(cx, cy, other)
        if on_it and _center_dist(pred, other) < d_target:
            return "distractor"
    if gt is not None and d_target < tsr_px:
        return "target"
    return "none"


WRONG_RELOCK_FRAMES = 10


def wrong_relock_episodes(ious: np.ndarray, has_out: np.ndarray, gt_present: np.ndarray,
                          min_frames: int = WRONG_RELOCK_FRAMES) -> int:
    """Episodes in which the follower keeps outputting a box that does not touch the target's (IoU 0) for at
    least ``min_frames`` frames: it is following someone or something else. Works on single-target clips,
    where no other person is annotated. A frame without ground truth (target hidden) neither extends nor
    ends an episode; a frame without output, or with any overlap, ends it."""
    episodes, run = 0, 0
    for iou, out, gt in zip(ious, has_out, gt_present, strict=True):
        if not gt:
            continue
        if out and iou == 0.0:
            run += 1
            if run == min_frames:
                episodes += 1
        else:
            run = 0
    return episodes


def missed_reacquisition_frames(pred_boxes: Sequence[Box | None], gt_boxes: Sequence[Box | None],
                                best_candidates: Sequence[Box | None], tsr_px: float = 20.0) -> int:
    """Frames where the follower output nothing although the target was in view and re-ID's best-scoring candidate
    was a detection on it (centre within ``tsr_px``): the failure opposite a wrong re-lock, a robot that stops
    while the person it follows is the best thing it sees. ``best_candidates[t]`` is that detection (None: the best
    candidate was no detection, or there was none)."""
    if len(best_candidates) != len(gt_boxes):
        raise ValueError(f"best_candidates has {len(best_candidates)} frames, gt has {len(gt_boxes)}")
    return sum(1 for pred, gt, best in zip(pred_boxes, gt_boxes, best_candidates, strict=True)
               if pred is None and gt is not None and best is not None and _center_dist(best, gt) < tsr_px)


def _reid_events(gt_present: np.ndarray, success: np.ndarray, min_occlusion_frames: int,
                 fps: float) -> list[ReidEvent]:
    """Occlusion spans and re-lock latencies.

    An occlusion span is a run of >= ``min_occlusion_frames`` consecutive gt-absent frames that is preceded
    by a gt-visible frame (a run at the very start is "not yet seen", not an occlusion) and followed by one
    (a run at the end never reappears). Latency = (first successful frame at or after the reappearance) -
    (reappearance frame), in frames and in ms (frames · 1000 / fps); 0 means locked on the reappearance frame.
    The search stops at the start of the next span; if no success happens before it, the event is censored
    (``latency_frames is None``) and reported separately instead of being averaged in.
    """
    n = len(gt_present)
    spans: list[tuple[int, int]] = []  # (start, reappear)
    t = 0
    while t < n:
        if gt_present[t]:
            t += 1
            continue
        start = t
        while t < n and not gt_present[t]:
            t += 1
        if start > 0 and t < n and t - start >= min_occlusion_frames:
            spans.append((start, t))
    events = []
    for k, (start, reappear) in enumerate(spans):
        stop = spans[k + 1][0] if k + 1 < len(spans) else n
        hits = np.flatnonzero(success[reappear:stop])
        lat = int(hits[0]) if hits.size else None
        events.append(ReidEvent(
            occlusion_start=start, reappear_frame=reappear, occluded_frames=reappear - start,
            latency_frames=lat, latency_ms=None if lat is None else lat * 1000.0 / fps,
            observed_frames=stop - reappear))
    return events


def _check_run_shapes(pred_boxes: Sequence[Box | None], gt_boxes: Sequence[Box | None],
                      other_gt: Sequence[Sequence[Box]] | None, fps: float) -> None:
    if len(pred_boxes) != len(gt_boxes):
        raise ValueError(f"pred has {len(pred_boxes)} frames, gt has {len(gt_boxes)}")
    if other_gt is not None and len(other_gt) != len(gt_boxes):
        raise ValueError(f"other_gt has {len(other_gt)} frames, gt has {len(gt_boxes)}")
    if fps <= 0:
        raise ValueError("fps must be positive")


def _per_frame_errors(pred_boxes: Sequence[Box | None],
                      gt_boxes: Sequence[Box | None]) -> tuple[np.ndarray, np.ndarray]:
    """Centre error ``e_t`` and IoU per frame; NaN where the output or the ground truth is missing."""
    errors = np.full(len(gt_boxes), math.nan)
    ious = np.full(len(gt_boxes), math.nan)
    for t, (p, g) in enumerate(zip(pred_boxes, gt_boxes, strict=True)):
        if p is not None and g is not None:
            errors[t] = _center_dist(p, g)
            ious[t] = box_iou(p, g)
    return errors, ious


def _mean_or_nan(values: np.ndarray) -> float:
    return float(values.mean()) if values.size else math.nan


def _std_or_nan(values: np.ndarray) -> float:
    return float(values.std()) if values.size else math.nan  # numpy std is 1/N


def _cle_all(cle: float, errors_scored: np.ndarray, missing: int, n_gt: int, diagonal: float | None) -> float:
    """Mean error over all gt frames, a missing output charged the image diagonal (NaN if that is unknown)."""
    if missing == 0:
        return cle
    if diagonal is None:
        return math.nan
    return float((errors_scored.sum() + missing * diagonal) / n_gt)


def _target_switches(pred_boxes: Sequence[Box | None], gt_boxes: Sequence[Box | None],
                     other_gt: Sequence[Sequence[Box]] | None, tsr_px: float,
                     iou_threshold: float) -> tuple[int, int]:
    """(target → distractor transitions, frames on a distractor); both 0 without ``other_gt``."""
    if other_gt is None:
        return 0, 0
    switches = 0
    on_distractor = 0
    last = "none"
    for t in range(len(gt_boxes)):
        owner = _frame_owner(pred_boxes[t], gt_boxes[t], other_gt[t], tsr_px, iou_threshold)
        if owner == "distractor":
            on_distractor += 1
            if last == "target":
                switches += 1
        if owner != "none":  # a lost/absent frame does not break a target → distractor transition
            last = owner
    return switches, on_distractor


def _rates(n_succ: int, n_out: int, n_gt: int, iou_hits: int) -> dict[str, float]:
    """The rate fields of :class:`SingleTargetMetrics`, from its counts (module docstring)."""
    return {"precision": _ratio(n_succ, n_out), "recall": _ratio(n_succ, n_gt),
            "f1": _ratio(2 * n_succ, n_out + n_gt), "tsr": _ratio(n_succ, n_gt),
            "iou_success": _ratio(iou_hits, n_gt)}


def evaluate_single_target(
    pred_boxes: Sequence[Box | None],
    gt_boxes: Sequence[Box | None],
    *,
    tsr_px: float = 20.0,
    iou_threshold: float = 0.5,
    other_gt: Sequence[Sequence[Box]] | None = None,
    fps: float = 30.0,
    min_occlusion_frames: int = 5,
    image_size: tuple[int, int] | None = None,
    best_candidates: Sequence[Box | None] | None = None,
) -> SingleTargetMetrics:
    """Score one follower run against the per-frame target ground truth.

    ``other_gt[t]`` lists the boxes of the *other* people on frame t (needed for target switches; without it
    the switch count is 0). ``image_size`` = (width, height) enables ``cle_all``. ``best_candidates`` (a follower
    that reports its re-ID's best-scoring detection per frame) enables ``missed_reacquisitions``.
    """
    _check_run_shapes(pred_boxes, gt_boxes, other_gt, fps)
    errors, ious = _per_frame_errors(pred_boxes, gt_boxes)
    gt_present = np.array([g is not None for g in gt_boxes], dtype=bool)
    has_out = np.array([p is not None for p in pred_boxes], dtype=bool)
    both = gt_present & has_out
    # NaN compares False, so frames without an error are never successes.
    with np.errstate(invalid="ignore"):
        success = both & (errors < tsr_px)
        iou_hits = int((both & (ious >= iou_threshold)).sum())
    n_gt = int(gt_present.sum())
    n_out = int(has_out.sum())
    n_succ = int(success.sum())
    missing = int((gt_present & ~has_out).sum())
    cle = _mean_or_nan(errors[both])
    diag = math.hypot(*image_size) if image_size is not None else None
    switches, on_distractor = _target_switches(pred_boxes, gt_boxes, other_gt, tsr_px, iou_threshold)
    return SingleTargetMetrics(
        frames=len(gt_boxes), frames_with_gt=n_gt, outputs=n_out, successes=n_succ,
        false_positives=n_out - n_succ, missing_outputs=missing, **_rates(n_succ, n_out, n_gt, iou_hits),
        cle=cle, cle_frames=int(both.sum()), cle_all=_cle_all(cle, errors[both], missing, n_gt, diag),
        stability=_std_or_nan(errors[success]), mean_iou=_mean_or_nan(ious[both]), iou_hits=iou_hits,
        target_switches=switches, frames_on_distractor=on_distractor,
        reid_events=_reid_events(gt_present, success, min_occlusion_frames, fps),
        wrong_relocks=wrong_relock_episodes(ious, has_out, gt_present),
        missed_reacquisitions=(None if best_candidates is None
                               else missed_reacquisition_frames(pred_boxes, gt_boxes, best_candidates, tsr_px)),
        center_errors=errors, ious=ious, tsr_px=tsr_px, iou_threshold=iou_threshold, fps=fps,
        image_diagonal=diag,
    )


# The counts of SingleTargetMetrics that add up across sequences (the rates are recomputed from them).
_SUMMED_COUNTS = ("frames", "frames_with_gt", "outputs", "successes", "missing_outputs", "cle_frames", "iou_hits",
                  "target_switches", "frames_on_distractor", "wrong_relocks")


def _common_tsr_px(items: Sequence[SingleTargetMetrics]) -> float:
    if not items:
        raise ValueError("aggregate() needs at least one SingleTargetMetrics")
    taus = {m.tsr_px for m in items}
    if len(taus) > 1:
        raise ValueError(f"cannot aggregate runs scored with different tsr_px: {sorted(taus)}")
    return items[0].tsr_px


def _pooled_cle_all(items: Sequence[SingleTargetMetrics], n_gt: int) -> float:
    # cle_all is the gt-frame-weighted mean of the per-sequence values (each already charges its own diagonal).
    parts = [(m.cle_all, m.frames_with_gt) for m in items if m.frames_with_gt]
    return float(sum(v * w for v, w in parts) / n_gt) if parts and n_gt else math.nan


def aggregate(metrics: Iterable[SingleTargetMetrics]) -> SingleTargetMetrics:
    """Frame-weighted overall: counts are summed and rates recomputed from them (so long sequences weigh
    more); CLE / mean IoU pool the per-frame values, stability is the std of the pooled successful errors,
    re-ID events are concatenated (their frame indices stay per-sequence)."""
    items = list(metrics)
    tau = _common_tsr_px(items)
    errors = np.concatenate([m.center_errors for m in items])
    ious = np.concatenate([m.ious for m in items])
    with np.errstate(invalid="ignore"):
        succ_err = errors[errors < tau]
    counts = {name: sum(getattr(m, name) for m in items) for name in _SUMMED_COUNTS}
    missed = [m.missed_reacquisitions for m in items if m.missed_reacquisitions is not None]
    n_gt, n_out, n_succ = counts["frames_with_gt"], counts["outputs"], counts["successes"]
    return SingleTargetMetrics(
        **counts, false_positives=n_out - n_succ, **_rates(n_succ, n_out, n_gt, counts["iou_hits"]),
        cle=_mean_or_nan(errors[np.isfinite(errors)]), cle_all=_pooled_cle_all(items, n_gt),
        stability=_std_or_nan(succ_err), mean_iou=_mean_or_nan(ious[np.isfinite(ious)]),
        reid_events=[e for m in items for e in m.reid_events], center_errors=errors, ious=ious,
        missed_reacquisitions=sum(missed) if missed else None,
        tsr_px=tau, iou_threshold=items[0].iou_threshold, fps=items[0].fps, image_diagonal=None,
    )


def _pct(v: float) -> str:
    return "–" if not math.isfinite(v) else f"{100.0 * v:.1f}"


def _px(v: float) -> str:
    return "–" if not math.isfinite(v) else f"{v:.2f}"


def _reid(m: SingleTargetMetrics) -> str:
    if not m.reid_events:
        return "–"
    mean = m.reid_latency_ms_mean
    text = "–" if not math.isfinite(mean) else f"{mean:.1f}"
    return f"{text} ({len(m.reid_latencies_frames)}/{len(m.reid_events)})"


_COLUMNS: list[tuple[str, Callable[[SingleTargetMetrics], str]]] = [
    ("Prec %", lambda m: _pct(m.precision)),
    ("Rec %", lambda m: _pct(m.recall)),
    ("F1 %", lambda m: _pct(m.f1)),
    ("CLE px", lambda m: _px(m.cle)),
    ("TSR %", lambda m: _pct(m.tsr)),
    ("Stab px", lambda m: _px(m.stability)),
    ("Miss", lambda m: str(m.missing_outputs)),
    ("Switch", lambda m: str(m.target_switches)),
    ("Wrong re-lock", lambda m: str(m.wrong_relocks)),
    ("Missed re-acq.", lambda m: "–" if m.missed_reacquisitions is None else str(m.missed_reacquisitions)),
    ("Re-ID ms (locked/events)", _reid),
]


def format_markdown_table(rows: dict[str, dict[str, SingleTargetMetrics]], *, overall: bool = True) -> str:
    """Markdown report: one methods × metrics table per sequence, then an ``overall`` table per method
    (frame-weighted via :func:`aggregate`). ``rows[method][sequence] -> metrics``; sequences keep first-seen
    order; a method lacking a sequence shows dashes there and is aggregated over what it has."""
    seqs: list[str] = []
    for per_seq in rows.values():
        for s in per_seq:
            if s not in seqs:
                seqs.append(s)
    header = "| Method | " + " | ".join(name for name, _ in _COLUMNS) + " |"
    sep = "|---|" + "|".join("---:" for _ in _COLUMNS) + "|"

    def table(title: str, pick: dict[str, SingleTargetMetrics | None]) -> list[str]:
        lines = [f"### {title}", "", header, sep]
        for method, m in pick.items():
            cells = ["–"] * len(_COLUMNS) if m is None else [fn(m) for _, fn in _COLUMNS]
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        return [*lines, ""]

    out: list[str] = []
    for s in seqs:
        out += table(s, {method: per_seq.get(s) for method, per_seq in rows.items()})
    if overall and seqs:
        out += table("overall (frame-weighted)",
                     {method: aggregate(per_seq.values()) if per_seq else None for method, per_seq in rows.items()})
    out.append(f"τ = {_tau_note(rows)} px; Re-ID = mean re-lock latency over re-locked events "
               "(censored events excluded from the mean, counted in locked/events).")
    return "\n".join(out) + "\n"


def _tau_note(rows: dict[str, dict[str, SingleTargetMetrics]]) -> str:
    taus = sorted({m.tsr_px for per_seq in rows.values() for m in per_seq.values()})
    return "/".join(f"{t:g}" for t in taus) or "20"
