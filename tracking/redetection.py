"""Kalman-guided local re-detection (seed 002 §3.2): when to run the detector again on a square region around the
prediction, where that region is, and how its boxes join the frame's.

The full-frame detector sees a 1280x720 frame at its input size (416: a third of the pixels across), so a 60 px
person is 20 px to it: it misses the person, or boxes them together with a neighbour. Seed 002 runs the detector
again on a region of interest around the Kalman prediction when the target is missed; here the region is inferred
at the frame's own resolution, where the 20 px person is 60 px again. Every decision below is a pure function; the
redetection node (nodes/redetection.py) runs the detector, re-ID (tracking/reid.py) associates its boxes.

* Search scale k (seed 002 §3.2): 1 for a slow target last seen on a confident detection, up to ``scale_max`` for
  a fast one (``fast_height_fraction`` of its height a frame) or one last seen on a weak detection. Re-ID's
  adaptive gate scales its χ² by k²; the region's side is k · max(w, h) (the seed's S), widened towards that gate
  as far as a cap (a budgeted fraction of the frame pass's pixels) and inferred at its own resolution. A person so
  large that the seed's S exceeds the cap is scaled down to it; when that would not see them finer than the frame
  pass (1.25 times its scale), there is no second look: it would find what the first found, at a frame's cost.
* Trigger: the target missed on the last frame (OCCLUDED), no detection centre in the gate ("missed"), two or
  more in it ("crowded": look-alikes a coarse view merges), or a person smaller than ``min_resolvable_px`` at the
  detector's input scale ("small"). LOST is not a trigger: the prior no longer says where the person is, and
  re-ID searches the whole frame.
* Merging: a frame box the region saw again (a region box overlapping it by IoU 0.5, or centred inside it: the same
  person seen finer, or people the coarse view merged) is replaced by what the region saw; a frame box the region
  did not see stays (the region pass can miss what the frame pass found). A region box cut by the region's inner
  edge is dropped (the frame box has that person whole).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..msgs.box import box_iou
from ..msgs.tracking import Prior
from .params import SearchScaleParams

Rect = tuple[int, int, int, int]  # x0, y0, x1, y1 in frame pixels, x1/y1 exclusive


@dataclass
class RegionBoxes:
    """What the re-detection of one region found (x, y, w, h, score rows in frame pixels), as re-ID takes it."""

    rect: Rect
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
    low_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
EDGE_PX = 2.0  # a region box within this of an inner edge of the region is cut by it
SAME_BOX_IOU = 0.5  # a frame box and a region box overlapping this much box the same person
MIN_INPUT_PX = 96  # a smaller region is enlarged to this for the detector (its coarsest stride is 32 px)
FINER_THAN_FRAME = 1.25  # a region is looked at again only at this many times the frame pass's scale, or finer
STRIDE_PX = 32


def search_scale(prior: Prior, last_score: float | None, dt_ms: float, p: SearchScaleParams) -> float:
    """Seed 002 §3.2's k in [1, gate_scale_max]: the larger of the speed's and the last detection's doubt
    (``last_score`` None: an initial box, nothing to doubt; a motion blob is passed as gate_low_score)."""
    if not p.adaptive_gate:
        return 1.0
    speed_px = math.hypot(*prior.velocity_px_s) * dt_ms / 1000.0
    fast = speed_px / max(float(prior.size[1]), 1.0) / p.gate_fast_height_fraction
    weak = 0.0 if last_score is None else (p.gate_high_score - last_score) / max(p.gate_high_score - p.gate_low_score,
                                                                               1e-6)
    urgency = min(max(max(fast, weak), 0.0), 1.0)
    return 1.0 + (p.gate_scale_max - 1.0) * urgency


def gate_radius_px(prior: Prior, k: float) -> float:
    """The semi-major axis of the gate at χ² · k² (Eq. 8), px."""
    largest = max(float(np.linalg.eigvalsh(np.asarray(prior.innovation_cov, dtype=np.float64)).max()), 0.0)
    return math.sqrt(prior.gate_chi2 * k * k * largest)


def region_of(prior: Prior, k: float, frame_wh: tuple[int, int], cap_px: int) -> Rect:
    """The square region around the prediction: side S = k · max(w, h) (seed 002 §3.2), widened towards the gate's
    diameter plus the box as far as ``cap_px`` (what can be inferred at the frame's resolution within the budget);
    moved inside the frame where it can be, clipped where not."""
    w, h = float(prior.size[0]), float(prior.size[1])
    side = max(k * max(w, h), min(2.0 * gate_radius_px(prior, k) + max(w, h), float(cap_px)))
    side = min(side, float(max(frame_wh)))
    cx, cy = prior.centre
    width, height = frame_wh
    x0 = min(max(cx - side / 2.0, 0.0), max(width - side, 0.0))
    y0 = min(max(cy - side / 2.0, 0.0), max(height - side, 0.0))
    x1, y1 = min(x0 + side, float(width)), min(y0 + side, float(height))
    return int(math.floor(x0)), int(math.floor(y0)), int(math.ceil(x1)), int(math.ceil(y1))


def input_side_px(rect: Rect, cap_px: int) -> int:
    """The detector's input side for a region: its own size (native resolution) up to the next stride, at least
    MIN_INPUT_PX, at most ``cap_px`` (a larger region is scaled down to it)."""
    side = max(rect[2] - rect[0], rect[3] - rect[1])
    return max(MIN_INPUT_PX, min(int(math.ceil(side / STRIDE_PX)) * STRIDE_PX, cap_px))


def region_cap_px(frame_wh: tuple[int, int], frame_input_px: int, budget_fraction: float) -> int:
    """The largest region input side whose pixels are ``budget_fraction`` of the frame pass's (its long side
    ``frame_input_px``, the short side in the frame's aspect): what one second look may cost."""
    long_side, short_side = max(frame_wh), min(frame_wh)
    frame_pixels = frame_input_px * frame_input_px * short_side / long_side
    return max(MIN_INPUT_PX, int(math.sqrt(budget_fraction * frame_pixels) // STRIDE_PX) * STRIDE_PX)


def finer_than_the_frame(rect: Rect, input_px: int, frame_scale: float) -> bool:
    """Whether the region inferred at ``input_px`` sees its pixels at least FINER_THAN_FRAME times the frame pass's
    scale: a second look at the same scale finds what the first found."""
    side = max(rect[2] - rect[0], rect[3] - rect[1])
    return input_px / max(side, 1) >= FINER_THAN_FRAME * frame_scale


def _in_gate(boxes: np.ndarray, prior: Prior, k: float) -> int:
    """How many of ``boxes`` (rows x, y, w, h, ...) have their centre in the gate at χ² · k²."""
    return sum(1 for b in np.asarray(boxes, np.float64).reshape(-1, np.shape(boxes)[-1] if np.size(boxes) else 5)
               if prior.mahalanobis_sq((b[0] + b[2] / 2.0, b[1] + b[3] / 2.0)) <= prior.gate_chi2 * k * k)


def reason_to_redetect(prior: Prior, boxes: np.ndarray, k: float, occluded: bool, input_scale: float,
                       min_resolvable_px: float) -> str:
    """Why the region must be re-detected on this frame ("" : it need not): "occluded" (the target was missed on
    the last frame), "small" (its predicted height at the detector's input scale is under ``min_resolvable_px``),
    "missed" (no detection in the gate), "crowded" (two or more)."""
    if not prior.initialised:
        return ""
    if occluded:
        return "occluded"
    if float(prior.size[1]) * input_scale < min_resolvable_px:
        return "small"
    gated = _in_gate(boxes, prior, k)
    if gated == 0:
        return "missed"
    return "crowded" if gated >= 2 else ""


def _superseded(frame_box: np.ndarray, region_boxes: list[np.ndarray]) -> bool:
    """A frame box the region saw again: a region box overlapping it by SAME_BOX_IOU or centred inside it (the same
    person seen finer, or people it merged)."""
    x, y, w, h = (float(v) for v in frame_box[:4])
    return any(box_iou(frame_box[:4], r[:4]) >= SAME_BOX_IOU
               or (x <= r[0] + r[2] / 2.0 <= x + w and y <= r[1] + r[3] / 2.0 <= y + h) for r in region_boxes)


def _cut_by_region(box: np.ndarray, rect: Rect, frame_wh: tuple[int, int]) -> bool:
    """A region box touching an edge of the region that is not the frame's edge: the person goes on beyond it."""
    x, y, w, h = (float(v) for v in box[:4])
    width, height = frame_wh
    return ((rect[0] > 0 and x <= rect[0] + EDGE_PX) or (rect[1] > 0 and y <= rect[1] + EDGE_PX)
            or (rect[2] < width and x + w >= rect[2] - EDGE_PX) or (rect[3] < height and y + h >= rect[3] - EDGE_PX))


def merge_region_boxes(frame_rows: np.ndarray, region_rows: np.ndarray, rect: Rect,
                       frame_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The frame's rows (x, y, w, h, score) less those the region saw again, with the region's own rows less its cut
    ones. Returns (rows, from_region) with ``from_region`` a bool per row."""
    frame_rows = np.asarray(frame_rows, np.float32).reshape(-1, 5)
    region_rows = np.asarray(region_rows, np.float32).reshape(-1, 5)
    added = [r for r in region_rows if not _cut_by_region(r, rect, frame_wh)]
    kept = [r for r in frame_rows if not _superseded(r, added)]
    rows = np.array([*kept, *added], np.float32).reshape(-1, 5)
    return rows, np.array([False] * len(kept) + [True] * len(added), bool)
