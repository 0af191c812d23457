"""Every frame of an evaluation run, as files people and other toolkits read (``followbus eval --trace``).

Per sequence and method:

- ``trace/<sequence>/<method>.jsonl``: one JSON object a frame: the output box and state, the ground truth, the
  prior (centre, covariance, innovation covariance, gate ellipse and radius), re-ID's candidates with their colour,
  geometry and fused scores and, where the classifier was asked, its score; every field of the camera-motion
  message (matrix, inliers and whatever uncertainty it carries); re-ID's decision (state, accepted, source) as the
  reason. Methods other than followbus have the box and state only.
- ``tracker_results/<method>/<sequence>.txt``: the OTB / pysot-toolkit result file, ``x,y,w,h`` a frame
  (``0,0,0,0`` without an output), so OTB, UAV123 and LaSOT toolkits score the run as they score theirs.

:func:`worst_episode` finds a run's longest failure (results.md lists it per sequence).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..tracking.kalman import gate_ellipse_from_cov
from .metrics import Box, box_center, box_iou, missed_reacquisition_frames

TAU_PX = 20.0  # an output farther than this from the target's centre is a failure (TSR@20px)


def _plain(value: Any) -> Any:
    """A message field as JSON: arrays as (nested) lists, non-finite floats as None."""
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(float(value)) else None
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    return value


def message_fields(msg: Any, skip: Sequence[str] = ("header",)) -> dict[str, Any] | None:
    """Every dataclass field of a bus message but ``skip``, JSON-ready (None for no message)."""
    if msg is None:
        return None
    return {f.name: _plain(getattr(msg, f.name)) for f in dataclasses.fields(msg) if f.name not in skip}


def gate_of(centre: Sequence[float], innovation_cov: Any, gate_chi2: float) -> dict[str, float] | None:
    """The Eq. 8 gate as an ellipse (tracking/kalman.py's one definition) and its radius (the semi-major axis)."""
    s = np.asarray(innovation_cov, dtype=np.float64).reshape(2, 2)
    if not (np.all(np.isfinite(s)) and math.isfinite(gate_chi2)) or not s.any():
        return None
    cx, cy, a, b, angle = gate_ellipse_from_cov(centre, s, gate_chi2)
    return {"cx": cx, "cy": cy, "a_px": a, "b_px": b, "angle_deg": angle, "chi2": float(gate_chi2), "radius_px": a}


def prior_record(prior: Any, gate_chi2: float | None = None) -> dict[str, Any] | None:
    """The prior's centre, size, covariances and gate; ``gate_chi2`` overrides the prior's own (re-ID's scaled
    gate, when it is known)."""
    if prior is None or not prior.initialised:
        return None
    centre = [float(prior.state[0]), float(prior.state[1])]
    return {"centre": _plain(centre), "velocity_px_s": _plain(prior.state[2:4]), "size": _plain(prior.size),
            "covariance": _plain(prior.covariance), "innovation_cov": _plain(prior.innovation_cov),
            "gate": gate_of(centre, prior.innovation_cov, float(gate_chi2 or prior.gate_chi2))}


def candidate_records(candidates: Sequence[Any], identity: dict[tuple[float, ...], float]) -> list[dict[str, Any]]:
    """Re-ID's scored candidates (tracking/reid.py Candidate): box, source, Mahalanobis², S_color, S_geo, M_fuse
    and the classifier's score where it decided between them."""
    out = []
    for c in candidates:
        box = tuple(float(v) for v in c.box)
        out.append({"box": _plain(box), "source": c.source, "maha_sq": _plain(c.maha_sq), "s_color": _plain(c.s_color),
                    "s_geo": _plain(c.s_geo), "m_fuse": _plain(c.m_fuse), "identity": _plain(identity.get(box))})
    return out


def reason_of(measurement: Any, track: Any) -> str:
    """Why the output is what it is, in a few words, from re-ID's decision."""
    if measurement is None:
        return f"track {track.state}"
    if measurement.accepted:
        return f"{measurement.state}: accepted {measurement.source or 'box'} (M_fuse {measurement.m_fuse:.2f})"
    n = len(measurement.candidates)
    coast = ""
    if measurement.state == "OCCLUDED" and track is not None:
        if track.box is None:
            coast = "; the coasting box withheld (too uncertain)"
        elif measurement.coasting_colours_seen:
            coast = "; the coasting box output (the target's colours are there)"
    if n:
        return f"{measurement.state}: best of {n} candidates rejected (M_fuse {measurement.m_fuse:.2f}){coast}"
    return f"{measurement.state}: no candidate in the gate{coast}"


@dataclass
class ReidCapture:
    """What the in-process re-ID computed for the last frame beyond its message (set by GraphFollower)."""

    candidates: list[Any] = dataclasses.field(default_factory=list)  # ReIdentifier.candidates
    identity: dict[tuple[float, ...], float] = dataclasses.field(default_factory=dict)

    def clear(self) -> None:
        self.candidates, self.identity = [], {}


def frame_record(graph_frame: Any, capture: ReidCapture | None, transform: Any) -> dict[str, Any]:
    """One frame of followbus's trace from what the graph published (GraphFollower's GraphFrame)."""
    track, meas, prior = graph_frame.track, graph_frame.measurement, graph_frame.prior
    # re-ID's own (adaptive) gate when its measurement says it; else the prior's base χ²
    scaled = getattr(meas, "gate_chi2", None) if meas is not None else None
    return {
        "state": track.state, "filtered_box": _plain(track.filtered_box), "velocity_px_s": _plain(track.velocity),
        "prior": prior_record(prior, scaled),
        "candidates": candidate_records(capture.candidates, capture.identity) if capture else [],
        "measurement": None if meas is None else {
            "state": meas.state, "accepted": meas.accepted, "secure": meas.secure, "source": meas.source,
            "box": _plain(meas.box), "m_fuse": _plain(meas.m_fuse), "s_color": _plain(meas.s_color),
            "s_geo": _plain(meas.s_geo), "omega": _plain(meas.omega), "c_t": _plain(meas.c_t)},
        "camera_motion": message_fields(transform),
        "reason": reason_of(meas, track),
    }


# --------------------------------------------------------------------------- files


def file_stem(name: str) -> str:
    """A sequence or method name as a file name (``sot/otb-woman`` → ``sot-otb-woman``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "run"


def write_trace(path: Path, boxes: Sequence[Box | None], infos: Sequence[dict[str, Any]],
                gts: Sequence[Box | None]) -> Path:
    """``path`` (JSON Lines): frame, output box, ground truth and the method's per-frame record."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8") as f:
        for k, (box, info, gt) in enumerate(zip(boxes, infos, gts, strict=True)):
            row = {"frame": k, "box": _plain(box), "gt": _plain(gt), "state": info.get("state")}
            row.update(info.get("trace") or {})
            if missed_reacquisition_frames([box], [gt], [info.get("best_candidate")], TAU_PX):
                row["reason"] = f"{row.get('reason', '')}; MISSED RE-ACQUISITION (the best candidate is the target)"
            f.write(json.dumps(row, ensure_ascii=False) + "\n")
    return path


def write_otb_result(path: Path, boxes: Sequence[Box | None]) -> Path:
    """The OTB toolkit's result file: ``x,y,w,h`` per frame, ``0,0,0,0`` where there is no output."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = ["0,0,0,0" if b is None else ",".join(f"{float(v):.2f}" for v in b) for b in boxes]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------- worst episode


@dataclass(frozen=True)
class Episode:
    """Consecutive target frames where the output failed (no output, or centre error > TAU_PX)."""

    first: int
    length: int
    followed: str  # what the output was on meanwhile


def _failed(box: Box | None, gt: Box | None) -> bool:
    if gt is None:
        return False
    if box is None:
        return True
    (bx, by), (gx, gy) = box_center(box), box_center(gt)
    return math.hypot(bx - gx, by - gy) > TAU_PX


def _followed(boxes: Sequence[Box | None], others: Sequence[Sequence[Box]], first: int, length: int) -> str:
    """The majority of the episode's frames: no output, another annotated person, or something unannotated."""
    counts = {"no output": 0, "another person": 0, "background or an unannotated person": 0}
    for k in range(first, first + length):
        box = boxes[k]
        if box is None:
            counts["no output"] += 1
        elif any(box_iou(box, o) >= 0.3 for o in others[k]):
            counts["another person"] += 1
        else:
            counts["background or an unannotated person"] += 1
    return max(counts, key=lambda key: counts[key])


def worst_episode(boxes: Sequence[Box | None], gts: Sequence[Box | None],
                  others: Sequence[Sequence[Box]]) -> Episode | None:
    """The longest run of failed frames, first to last failed frame (frames without a target neither fail nor
    end a run); None when the output never failed."""
    best: tuple[int, int] | None = None
    start: int | None = None
    for k, (box, gt) in enumerate(zip(boxes, gts, strict=True)):
        if gt is None:
            continue
        if not _failed(box, gt):
            start = None
            continue
        start = k if start is None else start
        if best is None or k - start + 1 > best[1]:
            best = (start, k - start + 1)
    if best is None:
        return None
    return Episode(best[0], best[1], _followed(boxes, others, *best))


def write_run_files(run: Any, out: Path) -> list[Path]:
    """The trace and the OTB result file of every method of one SequenceRun (evaluation/runner.py) under
    ``out``: ``trace/<sequence>/<method>.jsonl`` and ``tracker_results/<method>/<sequence>.txt``."""
    seq = file_stem(run.sequence.name)
    written = []
    for method, mr in run.runs.items():
        written.append(write_trace(out / "trace" / seq / f"{file_stem(method)}.jsonl", mr.boxes, mr.infos,
                                   run.gt_boxes))
        written.append(write_otb_result(out / "tracker_results" / file_stem(method) / f"{seq}.txt", mr.boxes))
    return written


def worst_episodes_markdown(runs: Sequence[Any], methods: Sequence[str]) -> str:
    """results.md's table: per sequence and method, the longest failure (first frame, length, what the output
    followed meanwhile)."""
    lines = [f"### Worst episode per sequence (longest run of frames with the output > {TAU_PX:g} px off the "
             "target or absent)", "", "| Sequence | Method | first frame | frames | the output followed |",
             "|---|---|---:|---:|---|"]
    for r in runs:
        for m in methods:
            if m not in r.runs:
                continue
            ep = worst_episode(r.runs[m].boxes, r.gt_boxes, r.other_gt)
            cells = ("–", "0", "never lost the target") if ep is None else (str(ep.first), str(ep.length),
                                                                              ep.followed)
            lines.append(f"| {r.sequence.name} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
