"""Target initialisation and motion blobs by frame differencing (paper §2.1, Alg. 1 line 2)."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import cv2
import numpy as np

from ..msgs.box import Box

logger = logging.getLogger(__name__)



def to_grey(bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)


def motion_blobs(
    prev_grey: np.ndarray,
    grey: np.ndarray,
    threshold: int = 25,
    kernel_px: int = 5,
    min_area_px: int = 64,
    roi: Sequence[int] | None = None,
) -> list[tuple[Box, float]]:
    """Moving regions between two grey frames as (box, contour_area), largest first.

    |I_k - I_{k-1}| > threshold, then a kernel_px² opening (drops isolated noise pixels) and
    closing (joins fragments of one body), then external contours → bounding boxes. ``roi``
    (x0, y0, x1, y1) restricts the work to a search window, in frame coordinates.
    """
    if prev_grey.shape != grey.shape:
        return []
    ox, oy = 0, 0
    if roi is not None:
        x0, y0, x1, y1 = (int(v) for v in roi)
        if x1 <= x0 or y1 <= y0:
            return []
        prev_grey, grey, ox, oy = prev_grey[y0:y1, x0:x1], grey[y0:y1, x0:x1], x0, y0
    diff = cv2.absdiff(prev_grey, grey)
    _, mask = cv2.threshold(diff, threshold, 255, cv2.THRESH_BINARY)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (kernel_px, kernel_px))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    blobs: list[tuple[Box, float]] = []
    for contour in contours:
        x, y, w, h = cv2.boundingRect(contour)
        area = float(cv2.contourArea(contour))
        if w * h < min_area_px:
            continue
        blobs.append(((float(x + ox), float(y + oy), float(w), float(h)), area))
    # Largest first, ties broken by position, so the order never depends on contour tracing order.
    blobs.sort(key=lambda b: (-b[1], -b[0][2] * b[0][3], b[0][1], b[0][0]))
    return blobs


def changed_fraction(prev_grey: np.ndarray, grey: np.ndarray, threshold: int = 25) -> float:
    """Fraction of the pixels whose grey level changed by more than ``threshold`` between two frames (1.0
    when the shapes differ). Frame differencing finds moving objects only against a still background: a
    large fraction means the camera itself moved."""
    if prev_grey.shape != grey.shape:
        return 1.0
    return float(np.count_nonzero(cv2.absdiff(prev_grey, grey) > threshold)) / float(grey.size)


def frame_difference_roi(
    prev_bgr: np.ndarray, bgr: np.ndarray, threshold: int = 25, kernel_px: int = 5, min_area_px: int = 64
) -> Box | None:
    """Initial ROI of §2.1: bounding box of the largest moving blob, or None if nothing moves."""
    blobs = motion_blobs(to_grey(prev_bgr), to_grey(bgr), threshold, kernel_px, min_area_px)
    return blobs[0][0] if blobs else None


def nearest_to_centre_bottom(detections: np.ndarray, frame_w: int, frame_h: int) -> Box | None:
    """The detection whose bottom-centre is nearest the image's bottom-centre, or None.

    A rear-view follower starts behind the person it follows, who is therefore the closest
    person to the robot: lowest in the image and near the optical axis.
    """
    dets = np.asarray(detections, dtype=np.float64)
    if dets.size == 0:
        return None
    dets = dets.reshape(-1, dets.shape[-1])
    foot_x = dets[:, 0] + dets[:, 2] / 2.0
    foot_y = dets[:, 1] + dets[:, 3]
    dist2 = (foot_x - frame_w / 2.0) ** 2 + (foot_y - float(frame_h)) ** 2
    i = int(np.argmin(dist2))  # first index on ties: deterministic
    return (float(dets[i, 0]), float(dets[i, 1]), float(dets[i, 2]), float(dets[i, 3]))
