"""Shapes every viewer draws (the monitor's web view, the Foxglove bridge, the recordings' Foxglove views), computed
here once: the Kalman gate as tracking/kalman.py's gate_ellipse_from_cov gives it (centre, semi-axes, angle), as
a polygon; the group's floor ellipses; floor points projected into the image."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..tracking.groundplane import CameraGeometry, floor_to_image
from ..tracking.kalman import gate_ellipse_from_cov

ELLIPSE_POINTS = 48  # polygon points of an ellipse
GROUP_SIGMA = 2.0  # the group's ellipses are drawn at 2 standard deviations of their extent (~86 % of members)


def gate_ellipse(centre: Any, innovation_cov: Any, gate_chi2: float) -> dict[str, Any] | None:
    """The Eq. 8 gate of a prior as a viewer draws it: {"centre": [x, y], "axes": [a, b] (semi-axes, a >= b),
    "angle_deg": direction of a}; None when it cannot be drawn (not finite)."""
    c = np.asarray(centre, dtype=np.float64).reshape(-1)[:2]
    s = np.asarray(innovation_cov, dtype=np.float64).reshape(2, 2)
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(s)) and math.isfinite(gate_chi2)):
        return None
    cx, cy, a, b, angle = gate_ellipse_from_cov(c, 0.5 * (s + s.T), max(float(gate_chi2), 0.0))
    return {"centre": [cx, cy], "axes": [a, b], "angle_deg": angle}


def ellipse_points(ellipse: dict[str, Any], n: int = ELLIPSE_POINTS, scale: float = 1.0) -> list[tuple[float, float]]:
    """An ellipse of :func:`gate_ellipse` as ``n`` polygon points, starting at the end of its major axis."""
    (cx, cy), (a, b) = ellipse["centre"], ellipse["axes"]
    theta = math.radians(ellipse["angle_deg"])
    major, minor = np.array([math.cos(theta), math.sin(theta)]), np.array([-math.sin(theta), math.cos(theta)])
    t = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    pts = np.array([cx, cy]) + np.outer(a * np.cos(t), major) + np.outer(b * np.sin(t), minor)
    return [(float(x) * scale, float(y) * scale) for x, y in pts]


def gate_polygon(centre: Any, innovation_cov: Any, gate_chi2: float, n: int = ELLIPSE_POINTS,
                 scale: float = 1.0) -> list[tuple[float, float]]:
    """The gate {z : (z-c)^T S^-1 (z-c) = chi2} as a polygon (empty when it cannot be drawn)."""
    ellipse = gate_ellipse(centre, innovation_cov, gate_chi2)
    return [] if ellipse is None else ellipse_points(ellipse, n, scale)


def ellipse_outline(centre: np.ndarray, extent: np.ndarray, n: int = 32) -> np.ndarray:
    """GROUP_SIGMA times the extent's standard ellipse {c + L u : |u| = 1}, L Lᵀ = extent, as n floor points."""
    w, v = np.linalg.eigh(0.5 * (extent + extent.T))
    axes = v * (GROUP_SIGMA * np.sqrt(np.clip(w, 0.0, None)))
    t = np.linspace(0.0, 2 * math.pi, n)
    return centre + np.stack([np.cos(t), np.sin(t)], axis=1) @ axes.T


def floor_pixels(points_m: Sequence[Any] | np.ndarray, camera: CameraGeometry | None) -> list | None:
    """Floor points (robot frame, m) in image pixels through ``camera`` (None: no camera; a point behind it:
    None)."""
    if camera is None:
        return None
    uv = floor_to_image(points_m, camera)
    return [None if not np.isfinite(p).all() else [round(float(p[0]), 1), round(float(p[1]), 1)] for p in uv]


