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
from dataclasses import dataclass

import cv2
import numpy as np

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
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

    def __post_init__(self) -> None:
        if self.min_work_width_px < 32:
            raise ValueError(f"EgoMotionParams.min_work_width_px must be >= 32, got {self.min_work_width_px!r}")
        for name in ("max_corners", "lk_window_px", "min_inliers"):
            if getattr(self, name) < 3:
                raise ValueError(f"EgoMotionParams.{name} must be >= 3, got {getattr(self, name)!r}")
        for name in ("corner_quality", "min_corner_distance_px", "ransac_reproj_px", "max_scale_change"):
            if not getattr(self, name) > 0:
                raise ValueError(f"EgoMotionParams.{name} must be > 0, got {getattr(self, name)!r}")
        if self.lk_levels < 0 or self.box_margin < 0 or not 0.0 <= self.min_inlier_fraction <= 1.0:
            raise ValueError("EgoMotionParams: lk_levels and box_margin must be >= 0, min_inlier_fraction in [0, 1]")
        if self.model not in ("similarity", "affine"):
            raise ValueError(f"EgoMotionParams.model must be 'similarity' or 'affine', got {self.model!r}")


@dataclass(frozen=True)
class CameraMotion:
    """Image motion from the frame stamped ``from_t_ns`` to the frame stamped ``t_ns``.

    ``matrix`` is the 2x3 [M | t] with p_k = M p_{k-1} + t in full-resolution pixels.
    """

    matrix: np.ndarray
    inliers: int
    tracked: int  # corners LK followed into frame k (outside person boxes); the RANSAC input
    from_t_ns: int
    t_ns: int

    @property
    def scale(self) -> float:
        return math.sqrt(abs(float(np.linalg.det(self.matrix[:, :2]))))


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


class EgoMotionEstimator:
    """Stateful per-stream estimator: call :meth:`step` on every frame in order."""

    def __init__(self, params: EgoMotionParams | None = None) -> None:
        self.params = params or EgoMotionParams()
        self.counts: Counter[str] = Counter()  # "transform", "no_previous", and one key per degenerate reason
        self.last_reason = ""  # why the last step gave no transform ("" when it gave one)
        self._prev_shape: tuple[int, ...] | None = None
        self._prev_t_ns = 0
        self._prev_grey: np.ndarray | None = None
        self._prev_corners: np.ndarray | None = None  # (N, 1, 2) float32, downscaled px, outside person boxes

    def reset(self) -> None:
        self._prev_shape = self._prev_grey = self._prev_corners = None

    def _downscale(self, frame_bgr: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
        """Grey work frame and the (sx, sy) that maps full-resolution px to it."""
        grey = frame_bgr if frame_bgr.ndim == 2 else cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
        s = 1.0
        while grey.shape[1] // 2 >= self.params.min_work_width_px:
            grey = cv2.pyrDown(grey)
            s *= 0.5
        return grey, (s, s)

    def _corners(self, grey: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
        p = self.params
        return cv2.goodFeaturesToTrack(grey, maxCorners=p.max_corners, qualityLevel=p.corner_quality,
                                       minDistance=p.min_corner_distance_px, mask=mask, blockSize=3)

    def step(self, frame_bgr: np.ndarray, detections: np.ndarray | None, t_ns: int) -> CameraMotion | None:
        """Motion from the previous frame given to :meth:`step` to this one; None when there is none to trust.

        ``detections``: this frame's person boxes (N x 4+, full-resolution px); corners are taken
        outside them on both frames (the previous frame's corners were masked with its own boxes).
        """
        p = self.params
        grey, s = self._downscale(frame_bgr)
        mask = background_mask(grey.shape[:2], detections, s, p.box_margin)
        result: CameraMotion | None = None
        if self._prev_grey is None or self._prev_shape != frame_bgr.shape or int(t_ns) <= self._prev_t_ns:
            # the first frame, a new resolution or a stamp that did not advance (a restarted source)
            self.counts["no_previous"] += 1
            self.last_reason = "no_previous"
        else:
            result = self._fit(grey, mask, s, t_ns)
        self._prev_grey, self._prev_shape, self._prev_t_ns = grey, frame_bgr.shape, int(t_ns)
        self._prev_corners = self._corners(grey, mask)
        return result

    def _degenerate(self, reason: str) -> None:
        self.counts[reason] += 1
        self.last_reason = reason
        logger.debug("no camera motion this frame: %s", reason)

    def _fit(self, grey: np.ndarray, mask: np.ndarray, s: tuple[float, float], t_ns: int) -> CameraMotion | None:
        p = self.params
        p0 = self._prev_corners
        if p0 is None or len(p0) < p.min_inliers:
            self._degenerate("few_corners")
            return None
        win = (p.lk_window_px, p.lk_window_px)
        p1, status, _err = cv2.calcOpticalFlowPyrLK(self._prev_grey, grey, p0, None, winSize=win,
                                                    maxLevel=p.lk_levels)
        ok = status.reshape(-1) == 1
        a, b = p0.reshape(-1, 2)[ok], p1.reshape(-1, 2)[ok]
        # A corner that lands on a person in frame k is not background there (a walker stepped over it).
        h, w = grey.shape[:2]
        xi = np.clip(np.round(b[:, 0]).astype(int), 0, w - 1)
        yi = np.clip(np.round(b[:, 1]).astype(int), 0, h - 1)
        inside = (b[:, 0] >= 0) & (b[:, 0] < w) & (b[:, 1] >= 0) & (b[:, 1] < h) & (mask[yi, xi] > 0)
        a, b = a[inside], b[inside]
        if len(a) < p.min_inliers:
            self._degenerate("few_tracked")
            return None
        fit = cv2.estimateAffinePartial2D if p.model == "similarity" else cv2.estimateAffine2D
        m, inl = fit(a, b, method=cv2.RANSAC, ransacReprojThreshold=p.ransac_reproj_px, maxIters=2000,
                     confidence=0.99, refineIters=10)
        if m is None or inl is None:
            self._degenerate("no_fit")
            return None
        n_in = int(inl.sum())
        if n_in < p.min_inliers or n_in < p.min_inlier_fraction * len(a):
            self._degenerate("few_inliers")
            return None
        det = float(np.linalg.det(m[:, :2]))
        if det <= 0.0 or abs(math.sqrt(det) - 1.0) > p.max_scale_change:
            self._degenerate("implausible_scale")
            return None
        # Back to full resolution: p_work = D p_full with D = diag(sx, sy), so M_full = D⁻¹ M D, t_full = D⁻¹ t.
        d = np.array(s, dtype=np.float64)
        full = np.empty((2, 3))
        full[:, :2] = m[:, :2] * d[None, :] / d[:, None]
        full[:, 2] = m[:, 2] / d
        self.counts["transform"] += 1
        self.last_reason = ""
        return CameraMotion(full, n_in, int(len(a)), self._prev_t_ns, int(t_ns))
