"""Global image motion between consecutive frames: the camera-motion half of seed 002 §3.3.

Seed 002 §3.3 ("optical flow-corrected Kalman filter") tracks sparse Lucas–Kanade feature points between
adjacent frames and folds their (median) displacement into the Kalman filter so the state follows
instantaneous motion the constant-velocity model cannot predict. Seed 002 takes those points inside the
detection box (the target's own motion, fused into the measurement); for a follower the motion the
constant-velocity prior misses is the camera's own (a pan, a turning or pitching robot, a zoom), which
moves the whole image. So the points here are background corners, *outside* every person box, and the
robust estimate of their flow is a 2-D similarity (or affine) transform fitted with RANSAC instead of a
median translation: it also covers rotation and zoom, and the consensus set replaces the median as the
outlier rejection. The transform maps frame k-1 pixels to frame k pixels; the prediction warps the
Kalman prior by it before gating (:meth:`followbus.tracking.kalman.KalmanCV.warp`).

Knowing what it does not know. Screen-fixed content (a burned-in clock, the robot's own body or
mount in view, dirt on the lens) is a second consensus set that does not move: RANSAC may take it for the
scene. So each frame fits up to two hypotheses (the largest consensus set, then the largest among the rest)
and picks the one covering more of the image (distinct grid cells), the previous frame's motion breaking a
tie; corners that stay put while the chosen motion does not add evidence to a per-cell static map that decays
each frame, and cells with enough evidence no longer take part in the fit (evidence over time, not one
frame). Every motion carries its uncertainty: the inliers' residual and spread, the rival hypothesis'
disagreement and support, the agreement with the previous frame's motion, and one 1-σ figure (``std_px``)
that prediction turns into covariance (tracking/kalman.py). A frame whose fit fails (a jerk's smeared frame)
does not break the chain: the last fitted frame stays the reference for up to ``max_reference_age_frames``,
so the next motion spans both steps.

Cheap by construction: grey frames halved down to about ``min_work_width_px``, at most ``max_corners`` corners per
frame, one pyramidal LK pass (corners of frame k-1 tracked into frame k). A fit that is not trustworthy
(a textureless or mostly-covered background, too few inliers, an implausible scale change) returns no
transform; callers then use the unwarped prior. Each outcome is counted in :attr:`EgoMotionEstimator.counts`.
Deterministic: the same frames and boxes give the same matrix (OpenCV's RANSAC seeds its own RNG), so
a replay, an in-process run and the launched graph's egomotion node agree bit for bit.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np

from ..msgs.perception import CameraMotion
from .params import InvalidParam, check_ranges

logger = logging.getLogger(__name__)


@dataclass
class EgoMotionParams:
    """Parameters of the camera-motion estimate. Seed 002 gives no values; each is chosen and explained here."""

    # The grey frame is halved (Gaussian pyramid, cv2.pyrDown) while its half is still at least this wide:
    # 640→320, 1280→320, 480→240, 352 stays. Background corners 6 px apart survive at that size, and corner
    # detection and LK cost a quarter per halving; pyrDown is a plain 2:1 map, so no resampling offset.
    min_work_width_px: int = 240
    # Bounded work: the strongest corners only (RANSAC needs tens; more buys little accuracy).
    max_corners: int = 100
    corner_quality: float = 0.01  # goodFeaturesToTrack quality level (fraction of the best corner's response)
    min_corner_distance_px: float = 6.0  # in the downscaled image: spreads corners over the background
    # Person boxes are grown by this fraction of their size before masking: detector boxes are tight,
    # and a walker's limbs and shadow just outside them move with the person, not the camera.
    box_margin: float = 0.1
    lk_window_px: int = 11  # LK window (downscaled px); 3 pyramid levels follow ~11·2³ px of motion
    lk_levels: int = 3
    # RANSAC inlier distance in downscaled px (≈ 2 px at 640x480): LK is sub-pixel on good corners.
    ransac_reproj_px: float = 1.0
    # A fit is trusted only with this many consensus corners and this fraction of the tracked ones.
    min_inliers: int = 15
    min_inlier_fraction: float = 0.1
    # Between two frames 33 ms apart a zoom or a robot driving at a person changes scale by a few % at
    # most; a larger one is a fit to something else (a person filling the background, a cut).
    max_scale_change: float = 0.15
    model: str = "similarity"  # similarity (4 dof: translation, rotation, scale) | affine (6 dof)
    # Static-content map: a grid over the work image; a corner that moves less than static_still_px
    # (work px) while the chosen motion moves the image centre by static_min_motion_px or more adds one to its
    # cell, one that follows the motion takes one off; all evidence decays by static_decay per frame. Cells
    # at static_evidence_min or above are left out of the fit (their corners are still followed, so the
    # evidence stays current). 0.8 decay: 3 frames of evidence mask a cell, ~8 frames without it unmask it.
    static_evidence: bool = True
    static_grid_cols: int = 16
    static_grid_rows: int = 12
    static_still_px: float = 0.35
    static_min_motion_px: float = 1.5
    static_decay: float = 0.8
    static_evidence_min: float = 2.0
    # Temporal consistency: a second hypothesis fitted on the first one's outliers competes with it; the one
    # covering more grid cells wins, unless both cover at least rival_cover_ratio of the larger and the
    # other agrees better with the previous frame's motion.
    temporal_consistency: bool = True
    rival_cover_ratio: float = 0.6
    # A failed fit keeps the last fitted frame as the reference for this many frames: the next motion then
    # spans the failed frame too (a jerk's smeared frame), so prediction misses no step of the camera's motion.
    max_reference_age_frames: int = 3
    # When the reference's corners are lost in a frame, the fit is tried again as on a smeared frame before any
    # fallback: a blurred corner is a streak that LK follows only with a wider window (smeared_lk_window_px), and
    # only to within a few px (smeared_ransac_reproj_px). On the jerks of scene:bumpy and scene:shaky it measures
    # 20 of 21 smeared frames to 5 px, against 10 without (`followbus bench egomotion`). Sharp frames keep the
    # tighter fit: its inlier tolerance is what keeps it sub-pixel.
    smeared_refit: bool = True
    smeared_lk_window_px: int = 21
    smeared_ransac_reproj_px: float = 2.0
    # When that fails too, the translation is measured by phase correlation of the work frames (cv2.phaseCorrelate,
    # people masked out), accepted when its peak response is at least phase_min_response; its 1-σ is phase_std_px or
    # phase_std_fraction of the shift, whichever is larger (a translation of a blurred frame, no rotation, no scale).
    # False: such a frame has no motion.
    phase_fallback: bool = True
    phase_min_response: float = 0.05
    phase_std_px: float = 6.0
    phase_std_fraction: float = 0.1

    def __post_init__(self) -> None:
        check_ranges(self, positive=("corner_quality", "min_corner_distance_px", "ransac_reproj_px",
                                     "max_scale_change", "phase_std_px", "smeared_ransac_reproj_px"),
                     non_negative=("lk_levels", "box_margin", "phase_std_fraction", "static_still_px",
                                   "static_min_motion_px", "static_evidence_min", "max_reference_age_frames"),
                     unit_interval=("min_inlier_fraction", "phase_min_response", "rival_cover_ratio"))
        if self.min_work_width_px < 32:
            raise InvalidParam("min_work_width_px", f"EgoMotionParams.min_work_width_px must be >= 32, got "
                                                    f"{self.min_work_width_px!r}")
        for name in ("max_corners", "lk_window_px", "smeared_lk_window_px", "min_inliers"):
            if getattr(self, name) < 3:
                raise InvalidParam(name, f"EgoMotionParams.{name} must be >= 3, got {getattr(self, name)!r}")
        if not 0.0 <= self.static_decay < 1.0:
            raise InvalidParam("static_decay", f"EgoMotionParams.static_decay must be in [0, 1), got "
                                               f"{self.static_decay!r}")
        check_ranges(self, positive=("static_grid_cols", "static_grid_rows"))
        if self.model not in ("similarity", "affine"):
            raise InvalidParam("model", f"EgoMotionParams.model must be 'similarity' or 'affine', got {self.model!r}")


def transform_scale(matrix: np.ndarray) -> float:
    """Isotropic scale of a 2x3 transform: sqrt|det M| (exact for a similarity)."""
    return math.sqrt(abs(float(np.linalg.det(np.asarray(matrix, dtype=np.float64)[:, :2]))))


def background_mask(shape: tuple[int, int], boxes: np.ndarray | None, scale: tuple[float, float],
                    margin: float) -> np.ndarray:
    """uint8 mask of a ``shape`` (h, w) image, 0 inside every (grown) person box, 255 elsewhere.

    ``boxes`` are [x, y, w, h, ...] rows in full-resolution pixels; ``scale`` (sx, sy) maps them to this image."""
    mask = np.full(shape, 255, np.uint8)
    b = np.zeros((0, 4)) if boxes is None else np.asarray(boxes, dtype=np.float64)
    if b.size == 0:
        return mask
    h, w = shape
    sx, sy = scale
    for x, y, bw, bh in b.reshape(-1, b.shape[-1])[:, :4]:
        x0 = int(math.floor((x - margin * bw) * sx))
        y0 = int(math.floor((y - margin * bh) * sy))
        x1 = int(math.ceil((x + (1.0 + margin) * bw) * sx))
        y1 = int(math.ceil((y + (1.0 + margin) * bh) * sy))
        mask[max(y0, 0):min(y1, h), max(x0, 0):min(x1, w)] = 0
    return mask


class _Prepared(NamedTuple):
    """:meth:`EgoMotionEstimator.prepare`'s work on a frame, for its :meth:`~EgoMotionEstimator.measure`."""

    t_ns: int
    shape: tuple[int, ...]  # the full frame's
    grey: np.ndarray  # the work frame
    scale: tuple[float, float]
    corners: np.ndarray | None  # the reference's corners it followed
    flow: np.ndarray | None  # where LK put them (None: nothing to follow)
    status: np.ndarray | None  # LK's per-corner status


CORNER_REGIONS = (4, 3)  # columns, rows of the corner budget's regions
FALLBACK_REASONS = ("few_tracked", "few_inliers", "no_fit")  # corner-fit failures phase correlation stands in for


class EgoMotionEstimator:
    """Stateful per-stream estimator: call :meth:`step` on every frame in order."""

    def __init__(self, params: EgoMotionParams | None = None) -> None:
        self.params = params or EgoMotionParams()
        self.counts: Counter[str] = Counter()  # "transform", "no_previous", and one key per degenerate reason
        self.last_reason = ""  # why the last step gave no transform ("" when it gave one)
        self.reset()

    def reset(self) -> None:
        p = self.params
        self._prev_shape: tuple[int, ...] | None = None
        self._prev_t_ns = 0
        self._prev_grey: np.ndarray | None = None
        self._prev_corners: np.ndarray | None = None  # (N, 1, 2) float32, downscaled px, outside person boxes
        self._ref_age = 0  # frames the reference has been kept after failed fits
        self._prev_shift: np.ndarray | None = None  # last fitted displacement of the work image's centre
        self.static_map = np.zeros((p.static_grid_rows, p.static_grid_cols))  # evidence per cell
        # measure()'s frame waiting for advance(): (grey, mask, full shape, stamp), None when it keeps the old one
        self._pending: tuple[np.ndarray, np.ndarray, tuple[int, ...], int] | None = None
        self._prepared: _Prepared | None = None  # prepare()'s work on a frame before its detections came

    def _downscale(self, frame_bgr: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
        """Grey work frame and the (sx, sy) that maps full-resolution px to it."""
        grey = frame_bgr if frame_bgr.ndim == 2 else cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
        s = 1.0
        while grey.shape[1] // 2 >= self.params.min_work_width_px:
            grey = cv2.pyrDown(grey)
            s *= 0.5
        return grey, (s, s)

    def _corners(self, grey: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
        """The strongest corners outside the static cells, plus a few inside them (they keep the static
        evidence current but must not spend the corner budget: screen-fixed text is all corners)."""
        p = self.params
        static = self._static_mask(grey.shape)
        if static is None:
            return self._good_corners(grey, mask, p.max_corners)
        scene = self._good_corners(grey, cv2.bitwise_and(mask, cv2.bitwise_not(static)), p.max_corners)
        fixed = self._good_corners(grey, cv2.bitwise_and(mask, static), max(p.max_corners // 5, 3))
        parts = [c for c in (scene, fixed) if c is not None]
        return np.concatenate(parts) if parts else None

    def _good_corners(self, grey: np.ndarray, mask: np.ndarray, n: int) -> np.ndarray | None:
        """Up to ``n`` corners, an equal share from each of CORNER_REGIONS regions: a patch of strong corners
        (screen-fixed text, a checkered logo) cannot take the whole budget before the map knows it is fixed."""
        p = self.params
        h, w = grey.shape[:2]
        cols, rows = CORNER_REGIONS
        share = max(-(-n // (cols * rows)), 1)
        found = []
        for r in range(rows):
            for c in range(cols):
                y0, y1, x0, x1 = r * h // rows, (r + 1) * h // rows, c * w // cols, (c + 1) * w // cols
                pts = cv2.goodFeaturesToTrack(grey[y0:y1, x0:x1], maxCorners=share, qualityLevel=p.corner_quality,
                                              minDistance=p.min_corner_distance_px, mask=mask[y0:y1, x0:x1],
                                              blockSize=3)
                if pts is not None:
                    found.append(pts + np.array([x0, y0], np.float32))
        return np.concatenate(found) if found else None

    def _static_mask(self, shape: tuple[int, ...]) -> np.ndarray | None:
        """uint8 mask (255) of the work image's static cells; None when there is none."""
        p = self.params
        cells = (self.static_map >= p.static_evidence_min).astype(np.uint8) * 255
        if not p.static_evidence or not cells.any():
            return None
        return cv2.resize(cells, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)

    def step(self, frame_bgr: np.ndarray, detections: np.ndarray | None, t_ns: int) -> CameraMotion | None:
        """Motion from the reference frame (the previous one, or the last fitted one after a failed fit) to
        this one, stamped ``t_ns``; None when there is none to trust (:attr:`last_reason` says why).

        ``detections``: this frame's person boxes (N x 4+, full-resolution px); corners are taken
        outside them on both frames (the previous frame's corners were masked with its own boxes).
        :meth:`measure` then :meth:`advance`, in one call.
        """
        motion = self.measure(frame_bgr, detections, t_ns)
        self.advance()
        return motion

    def measure(self, frame_bgr: np.ndarray, detections: np.ndarray | None, t_ns: int) -> CameraMotion | None:
        """The motion of :meth:`step` without preparing the next step: a node publishes it, then calls
        :meth:`advance` (the next frame's corners, about a third of a step, are then off the loop's path)."""
        p = self.params
        grey, s = self._work_frame(frame_bgr, int(t_ns))
        mask = background_mask(grey.shape[:2], detections, s, p.box_margin)
        result: CameraMotion | None = None
        fresh = self._prev_grey is None or self._prev_shape != frame_bgr.shape or int(t_ns) <= self._prev_t_ns
        if fresh:
            # the first frame, a new resolution or a stamp that did not advance (a restarted source)
            self.counts["no_previous"] += 1
            self.last_reason = "no_previous"
            self._prev_shift = None
        else:
            result = self._fit(grey, mask, s, t_ns)
        self._pending = None
        if result is None and not fresh and self._ref_age < p.max_reference_age_frames:
            self._ref_age += 1  # keep the last fitted frame: the next motion spans this one too
            return None
        self._pending = (grey, mask, frame_bgr.shape, int(t_ns))
        return result

    def prepare(self, frame_bgr: np.ndarray, t_ns: int) -> None:
        """Optional, on a frame's arrival, before its person boxes: the grey work frame and the reference's
        corners followed into it by LK (what needs no boxes, most of :meth:`measure`). :meth:`measure` of the
        same frame then starts from there, if the reference has not changed since; the motion is the same."""
        grey, s = self._downscale(frame_bgr)
        p0, p1, status = self._prev_corners, None, None
        if p0 is not None and len(p0) >= self.params.min_inliers and self._prev_grey is not None \
                and self._prev_grey.shape == grey.shape:
            p1, status = self._flow(grey, p0)
        self._prepared = _Prepared(int(t_ns), frame_bgr.shape, grey, s, p0, p1, status)

    def _work_frame(self, frame_bgr: np.ndarray, t_ns: int) -> tuple[np.ndarray, tuple[float, float]]:
        """The grey work frame, from :meth:`prepare` when it saw this frame."""
        prepared = self._prepared
        if prepared is not None and (prepared.t_ns, prepared.shape) == (t_ns, frame_bgr.shape):
            return prepared.grey, prepared.scale
        return self._downscale(frame_bgr)  # not prepared, or prepared for a later frame: kept for that one

    def _flow(self, grey: np.ndarray, p0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where LK puts the reference's corners ``p0`` in ``grey``, and its per-corner status."""
        p = self.params
        win = (p.lk_window_px, p.lk_window_px)
        p1, status, _err = cv2.calcOpticalFlowPyrLK(self._prev_grey, grey, p0, None, winSize=win,
                                                    maxLevel=p.lk_levels)
        return p1, status

    def advance(self) -> None:
        """Make the frame :meth:`measure` just saw the reference of the next one (unless it kept the old one)."""
        if self._pending is None:
            return
        grey, mask, shape, t_ns = self._pending
        self._pending = None
        self._ref_age = 0
        self._prev_grey, self._prev_shape, self._prev_t_ns = grey, shape, t_ns
        self._prev_corners = self._corners(grey, mask)

    def _degenerate(self, reason: str) -> None:
        self.counts[reason] += 1
        self.last_reason = reason
        logger.debug("no camera motion this frame: %s", reason)

    def _track(self, grey: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The reference's corners followed into this frame by LK, kept where they land on background."""
        p = self.params
        p0 = self._prev_corners
        if p0 is None or len(p0) < p.min_inliers:
            self._degenerate("few_corners")
            return None
        prepared = self._prepared
        if prepared is not None and prepared.corners is p0 and prepared.flow is not None and prepared.grey is grey:
            p1, status = prepared.flow, prepared.status  # prepare() followed these very corners into this frame
            self._prepared = None
        else:
            p1, status = self._flow(grey, p0)
        ok = status.reshape(-1) == 1
        a, b = p0.reshape(-1, 2)[ok], p1.reshape(-1, 2)[ok]
        # A corner that lands on a person in frame k is not background there (a walker stepped over it).
        h, w = grey.shape[:2]
        xi = np.clip(np.round(b[:, 0]).astype(int), 0, w - 1)
        yi = np.clip(np.round(b[:, 1]).astype(int), 0, h - 1)
        inside = (b[:, 0] >= 0) & (b[:, 0] < w) & (b[:, 1] >= 0) & (b[:, 1] < h) & (mask[yi, xi] > 0)
        return a[inside], b[inside]

    def _cells(self, pts: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        """Flat static-grid cell index of each (x, y) work-image point (computed once a frame: _fit's helpers
        take them, not the points)."""
        p = self.params
        h, w = shape[:2]
        # np.minimum/np.maximum rather than np.clip: the same values, without np.clip's per-call cost
        cx = np.minimum(np.maximum((pts[:, 0] * p.static_grid_cols / w).astype(int), 0), p.static_grid_cols - 1)
        cy = np.minimum(np.maximum((pts[:, 1] * p.static_grid_rows / h).astype(int), 0), p.static_grid_rows - 1)
        return cy * p.static_grid_cols + cx

    def _cover(self, cells: np.ndarray) -> int:
        """How many distinct grid cells ``cells`` fall in."""
        p = self.params
        return int(np.count_nonzero(np.bincount(cells, minlength=p.static_grid_cols * p.static_grid_rows)))

    def _hypotheses(self, a: np.ndarray, b: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Up to two (matrix, inlier mask) fits: RANSAC's consensus, then the largest among its outliers."""
        p = self.params
        fit = cv2.estimateAffinePartial2D if p.model == "similarity" else cv2.estimateAffine2D
        out: list[tuple[np.ndarray, np.ndarray]] = []
        rest = np.ones(len(a), bool)
        for _ in range(2 if p.temporal_consistency else 1):
            if rest.sum() < p.min_inliers:
                break
            m, inl = fit(a[rest], b[rest], method=cv2.RANSAC, ransacReprojThreshold=p.ransac_reproj_px,
                         maxIters=2000, confidence=0.99, refineIters=10)
            if m is None or inl is None or int(inl.sum()) < p.min_inliers:
                break
            mask = np.zeros(len(a), bool)
            mask[np.flatnonzero(rest)[inl.reshape(-1) == 1]] = True
            out.append((m, mask))
            rest &= ~mask
        return out

    def _choose(self, hyps: list[tuple[np.ndarray, np.ndarray]], cover: list[int],
                shape: tuple[int, ...]) -> tuple[int, int | None]:
        """Index of the chosen hypothesis and of its rival (None): the one covering more grid cells (``cover``,
        one count per hypothesis), unless both cover rival_cover_ratio of the larger and the other agrees
        better with the previous motion."""
        if len(hyps) < 2:
            return 0, None
        best, other = (0, 1) if cover[0] >= cover[1] else (1, 0)
        close = cover[other] >= self.params.rival_cover_ratio * cover[best]
        if close and self._prev_shift is not None:
            centre = _image_centre(shape)
            dev = [np.linalg.norm(_shift(m, centre) - self._prev_shift) for m, _ in hyps]
            if dev[other] < dev[best]:
                best, other = other, best
        return best, other

    def _moving_cover(self, hyps: list[tuple[np.ndarray, np.ndarray]], cover: list[int],
                      shape: tuple[int, ...]) -> int:
        """Grid cells covered by the widest hypothesis that moves the image centre (0: none moves)."""
        centre = _image_centre(shape)
        moving = [n for (mat, _), n in zip(hyps, cover, strict=True)
                  if float(np.linalg.norm(_shift(mat, centre))) >= self.params.static_min_motion_px]
        return max(moving, default=0)

    def _update_static(self, a: np.ndarray, b: np.ndarray, cells: np.ndarray, moving_cover: int) -> None:
        """Decay the static map; then, when a hypothesis moves the image, the corners that stayed put add to
        their cells and those that moved take off, provided the moving hypothesis covers at least
        rival_cover_ratio as many cells as the still corners (a walker the detector missed, moving over a
        still background, is not evidence that the background is screen-fixed)."""
        p = self.params
        self.static_map *= p.static_decay
        if not p.static_evidence or not moving_cover or not len(a):
            return
        still = np.linalg.norm(b - a, axis=1) < p.static_still_px
        if moving_cover < p.rival_cover_ratio * self._cover(cells[still]):
            return
        flat = self.static_map.reshape(-1)
        np.add.at(flat, cells[still], 1.0)
        np.add.at(flat, cells[~still], -1.0)
        np.clip(flat, 0.0, None, out=flat)

    def _fit(self, grey: np.ndarray, mask: np.ndarray, s: tuple[float, float], t_ns: int) -> CameraMotion | None:
        """The corner fit, or when it fails the phase-correlation fallback (EgoMotionParams.phase_fallback)."""
        motion = self._corner_fit(grey, mask, s, t_ns)
        # Only when the reference had corners and they were lost in this frame (smeared): a textureless view has
        # no motion to measure, and a fit refused for its scale was refused on purpose.
        if motion is None and self.params.smeared_refit and self.last_reason in FALLBACK_REASONS:
            motion = self._smeared_fit(grey, mask, s, t_ns)
        if motion is None and self.params.phase_fallback and self.last_reason in FALLBACK_REASONS:
            motion = self._phase_motion(grey, mask, s, t_ns)
        return motion

    def _smeared_fit(self, grey: np.ndarray, mask: np.ndarray, s: tuple[float, float],
                     t_ns: int) -> CameraMotion | None:
        """The corner fit again with the smeared-frame window and inlier tolerance (EgoMotionParams.smeared_refit)."""
        sharp = self.params
        self.params = replace(sharp, lk_window_px=sharp.smeared_lk_window_px,
                              ransac_reproj_px=sharp.smeared_ransac_reproj_px)
        try:
            motion = self._corner_fit(grey, mask, s, t_ns)
        finally:
            self.params = sharp
        if motion is not None:
            self.counts["smeared"] += 1
        return motion

    def _phase_motion(self, grey: np.ndarray, mask: np.ndarray, s: tuple[float, float],
                      t_ns: int) -> CameraMotion | None:
        """The reference-to-frame translation by phase correlation: the whole image's motion survives a smear that
        leaves no corner to follow. People (``mask`` 0) are filled with the frame's mean so they do not pull it."""
        p = self.params
        ref = self._prev_grey
        if ref is None or ref.shape != grey.shape:
            return None
        a, b = (np.where(mask > 0, g, g.mean()).astype(np.float32) for g in (ref, grey))
        window = cv2.createHanningWindow((grey.shape[1], grey.shape[0]), cv2.CV_32F)
        (dx, dy), response = cv2.phaseCorrelate(a, b, window)
        if not response >= p.phase_min_response:
            return None
        shift = np.array([dx / s[0], dy / s[1]])
        std = max(p.phase_std_px, p.phase_std_fraction * float(np.linalg.norm(shift)))
        motion = CameraMotion(valid=True, matrix=np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]]),
                              from_stamp_ns=self._prev_t_ns, reason="phase", std_px=std)
        motion.header.stamp_ns = int(t_ns)
        self._prev_shift = np.array([dx, dy])
        self.counts["phase"] += 1
        self.last_reason = ""
        return motion

    def _corner_fit(self, grey: np.ndarray, mask: np.ndarray, s: tuple[float, float],
                    t_ns: int) -> CameraMotion | None:
        p = self.params
        tracked = self._track(grey, mask)
        if tracked is None:
            return None
        a, b = tracked
        cells = self._cells(a, grey.shape)
        static = self.static_map.reshape(-1)[cells] >= p.static_evidence_min
        if not p.static_evidence:
            static[:] = False
        fa, fb, fcells = a[~static], b[~static], cells[~static]
        if len(fa) < p.min_inliers:
            self._degenerate("few_tracked")
            return None
        hyps = self._hypotheses(fa, fb)
        if not hyps or len(np.flatnonzero(hyps[0][1])) < p.min_inlier_fraction * len(fa):
            self._degenerate("few_inliers" if hyps else "no_fit")
            return None
        return self._fitted(hyps, a, b, cells, fa, fb, fcells, s, t_ns, grey.shape)
    def _fitted(self, hyps: list[tuple[np.ndarray, np.ndarray]], a: np.ndarray, b: np.ndarray, cells: np.ndarray,
                fa: np.ndarray, fb: np.ndarray, fcells: np.ndarray, s: tuple[float, float], t_ns: int,
                shape: tuple[int, ...]) -> CameraMotion | None:
        """The chosen hypothesis as the frame's motion (None: an implausible scale)."""
        p = self.params
        cover = [self._cover(fcells[mask]) for _, mask in hyps]
        best, rival = self._choose(hyps, cover, shape)
        m, inl = hyps[best]
        det = float(np.linalg.det(m[:, :2]))
        if det <= 0.0 or abs(math.sqrt(det) - 1.0) > p.max_scale_change:
            self._degenerate("implausible_scale")
            return None
        centre = _image_centre(shape)
        shift = _shift(m, centre)
        self._update_static(a, b, cells, self._moving_cover(hyps, cover, shape))
        motion = self._motion(m, fa, fb, inl, hyps[rival] if rival is not None else None, s, t_ns, shape,
                              cover[best])
        motion = _replace_static(motion, int((self.static_map >= p.static_evidence_min).sum()))
        self._prev_shift = shift
        self.counts["transform"] += 1
        self.last_reason = ""
        return motion

    def _motion(self, m: np.ndarray, a: np.ndarray, b: np.ndarray, inl: np.ndarray,
                rival: tuple[np.ndarray, np.ndarray] | None, s: tuple[float, float], t_ns: int,
                shape: tuple[int, ...], cover: int) -> CameraMotion:
        """The chosen fit in full-resolution px with its uncertainty; ``cover``: the grid cells its inliers span."""
        d = np.array(s, dtype=np.float64)
        full = _to_full(m, d)
        unit = 1.0 / float(d[0])  # work px -> full px
        n_in = int(inl.sum())
        resid = b[inl] - (a[inl] @ m[:, :2].T + m[:, 2])
        residual = float(np.sqrt(np.mean(np.sum(resid**2, axis=1)))) * unit
        p = self.params
        spread = cover / float(p.static_grid_cols * p.static_grid_rows)
        centre = _image_centre(shape)
        shift = _shift(m, centre)
        rival_px, rival_n, var = 0.0, 0, residual**2 * 2.0 / max(n_in, 1)  # the fitted shift's own variance
        if rival is not None:
            rival_n = int(rival[1].sum())
            rival_px = float(np.linalg.norm(_shift(rival[0], centre) - shift)) * unit
            w = rival_n / float(rival_n + n_in)
            var += w * (1.0 - w) * rival_px**2  # the variance of the two-hypothesis mixture's shift
        agreement = -1.0 if self._prev_shift is None else float(np.linalg.norm(shift - self._prev_shift)) * unit
        motion = CameraMotion(valid=True, matrix=full, inliers=n_in, tracked=int(len(a)),
                              from_stamp_ns=self._prev_t_ns, residual_px=residual, spread=spread, rival_px=rival_px,
                              rival_inliers=rival_n, agreement_px=agreement, std_px=math.sqrt(var))
        motion.header.stamp_ns = int(t_ns)
        return motion


def _image_centre(shape: tuple[int, ...]) -> np.ndarray:
    """(x, y) of the centre of an image of ``shape``: where a hypothesis's shift is read."""
    return np.array([shape[1] / 2.0, shape[0] / 2.0])


def _shift(m: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Displacement the 2x3 transform gives ``point``."""
    return m[:, :2] @ point + m[:, 2] - point


def _to_full(m: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Back to full resolution: p_work = D p_full with D = diag(sx, sy), so M_full = D⁻¹ M D, t_full = D⁻¹ t."""
    full = np.empty((2, 3))
    full[:, :2] = m[:, :2] * d[None, :] / d[:, None]
    full[:, 2] = m[:, 2] / d
    return full


def _replace_static(motion: CameraMotion, cells: int) -> CameraMotion:
    from dataclasses import replace

    return replace(motion, static_cells=cells)
