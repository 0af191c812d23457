"""Appearance model: H-S histograms, Bhattacharyya similarity and the specular penalty (§2.2.1, §2.4).

HSV values follow OpenCV's 8-bit convention: H in [0, 180), S and V in [0, 256).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import cv2
import numpy as np

logger = logging.getLogger(__name__)


def clip_box(box: Sequence[float], width: int, height: int) -> tuple[int, int, int, int]:
    """Integer pixel bounds (x0, y0, x1, y1) of a float box, clipped to the image; may be empty."""
    x, y, w, h = (float(v) for v in box[:4])
    if not all(math.isfinite(v) for v in (x, y, w, h)):
        return (0, 0, 0, 0)
    x0 = min(max(int(math.floor(x)), 0), width)
    y0 = min(max(int(math.floor(y)), 0), height)
    x1 = min(max(int(math.ceil(x + w)), 0), width)
    y1 = min(max(int(math.ceil(y + h)), 0), height)
    return (x0, y0, max(x1, x0), max(y1, y0))


def _roi_hsv(bgr: np.ndarray, box: Sequence[float]) -> np.ndarray | None:
    height, width = bgr.shape[:2]
    x0, y0, x1, y1 = clip_box(box, width, height)
    if x1 <= x0 or y1 <= y0:
        return None
    # Convert only the ROI: the cost stays O(w·h), not O(W·H).
    return cv2.cvtColor(np.ascontiguousarray(bgr[y0:y1, x0:x1]), cv2.COLOR_BGR2HSV)


def hs_histogram(bgr: np.ndarray, box: Sequence[float], bins_h: int = 16, bins_s: int = 8) -> np.ndarray:
    """Normalised (bins_h x bins_s) float32 H-S histogram of the box clipped to the frame (§2.2.1).

    V is left out on purpose: it carries the illumination the paper wants to be robust to. A box
    entirely outside the frame yields the uniform histogram (no information, still sums to 1).
    """
    hsv = _roi_hsv(bgr, box)
    if hsv is None:
        logger.debug("hs_histogram: empty box %s", tuple(box[:4]))
        return np.full((bins_h, bins_s), 1.0 / (bins_h * bins_s), dtype=np.float32)
    hist = cv2.calcHist([hsv], [0, 1], None, [bins_h, bins_s], [0, 180, 0, 256])
    return (hist / float(hist.sum())).astype(np.float32)


def colour_contrast(bgr: np.ndarray, box: Sequence[float], template: np.ndarray, bins_h: int = 16,
                    bins_s: int = 8) -> tuple[float, float | None]:
    """(S_color of ``box``, the highest S_color of the boxes around it): Eq. 1 against ``template`` at the box and at
    boxes of its size beside it (left and right by 1.5 widths, above and below by one height) whose centre is in the
    frame; None when none is. The target's colours at a box and not around it locate the target; colours no more
    the target's than its surroundings' do not."""
    x, y, w, h = (float(v) for v in box[:4])
    at_box = bhattacharyya(hs_histogram(bgr, box, bins_h, bins_s), template)
    height, width = bgr.shape[:2]
    around = [(x + dx, y + dy, w, h) for dx, dy in ((-1.5 * w, 0.0), (1.5 * w, 0.0), (0.0, -h), (0.0, h))]
    inside = [b for b in around if 0.0 <= b[0] + w / 2.0 < width and 0.0 <= b[1] + h / 2.0 < height]
    if not inside:
        return at_box, None
    return at_box, max(bhattacharyya(hs_histogram(bgr, b, bins_h, bins_s), template) for b in inside)


def bhattacharyya(p: np.ndarray, q: np.ndarray) -> float:
    """Eq. 1: ρ(p, q) = Σ_u sqrt(p_u q_u); 1 for identical, 0 for disjoint distributions."""
    p64 = np.asarray(p, dtype=np.float64).ravel()
    q64 = np.asarray(q, dtype=np.float64).ravel()
    if p64.shape != q64.shape:
        raise ValueError(f"histogram shapes differ: {np.shape(p)} vs {np.shape(q)}")
    rho = float(np.sqrt(np.clip(p64, 0.0, None) * np.clip(q64, 0.0, None)).sum())
    return min(max(rho, 0.0), 1.0)  # rounding can push identical histograms to 1 + ε


def specular_penalty(bgr: np.ndarray, box: Sequence[float], tau_v: int = 220, tau_s: int = 45) -> float:
    """Eq. 9: fraction of ROI pixels with V > τ_v and S < τ_s (bright, colourless: reflections)."""
    hsv = _roi_hsv(bgr, box)
    if hsv is None:
        return 0.0
    mask = (hsv[:, :, 2] > tau_v) & (hsv[:, :, 1] < tau_s)
    return float(np.count_nonzero(mask)) / float(mask.size)


def learning_rate(p_specular: float, secure: bool, eta_base: float = 0.02, lambda_specular: float = 10.0) -> float:
    """Eq. 10: η_k = η_base·exp(-λ·P_specular) when tracked securely, else 0 (template frozen)."""
    if not secure:
        return 0.0
    return float(eta_base * math.exp(-lambda_specular * float(p_specular)))
