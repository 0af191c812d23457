"""How well the egomotion estimate (tracking/egomotion.py) measures the camera's motion, on the built-in scenes whose
camera moves the whole image by a known shift (a pan, a robot's bumps, a hand-held camera's re-aims).

Each frame's estimate is read at the image centre and compared with the scene's own shift between the frames the
estimate spans. Smeared frames (the scene blurred them along a jerk) are counted apart: they are where a corner fit
fails and the estimate falls back (EgoMotionParams.smeared_refit, phase_fallback)."""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..tracking.egomotion import EgoMotionEstimator, EgoMotionParams
from ..vision.scenes import SceneFrame, make_scene

# Scenes whose camera motion is a pure image shift (no parallax): the truth is one vector a frame.
SHIFT_SCENES = ("bumpy", "shaky", "overlay")
SMEARED_OK_PX = 5.0  # a smeared frame's estimate within this of the truth counts as measured


@dataclass
class CameraMotionScore:
    scene: str
    frames: int = 0  # frames with an estimate
    errors_px: list[float] = field(default_factory=list)
    smeared: int = 0  # frames the scene smeared
    smeared_measured: int = 0  # ... whose estimate is within SMEARED_OK_PX
    smeared_unmeasured: int = 0  # ... with no estimate at all
    cpu_ms: list[float] = field(default_factory=list)
    counts: Counter[str] = field(default_factory=Counter)

    def row(self) -> dict[str, Any]:
        err = np.asarray(self.errors_px or [0.0])
        return {"scene": self.scene, "frames": self.frames, "mean_err_px": round(float(err.mean()), 2),
                "p95_err_px": round(float(np.percentile(err, 95)), 2), "smeared": self.smeared,
                "smeared_measured": self.smeared_measured, "smeared_unmeasured": self.smeared_unmeasured,
                "cpu_ms_median": round(float(np.median(self.cpu_ms or [0.0])), 2),
                "cpu_ms_p99": round(float(np.percentile(self.cpu_ms or [0.0], 99)), 2), "counts": dict(self.counts)}


def _person_boxes(frame: SceneFrame) -> np.ndarray:
    """Every person's true box as a detection row (x, y, w, h, score 1)."""
    boxes = [box for box, _ in frame.people() if box is not None]
    return np.array([[*box[:4], 1.0] for box in boxes], dtype=np.float32).reshape(-1, 5)


def score_scene(name: str, params: EgoMotionParams) -> CameraMotionScore:
    """The estimate against the scene's shift on every frame (people masked by their true boxes, as a detector
    that sees them would)."""
    scene = make_scene(name)
    est = EgoMotionEstimator(params)
    score = CameraMotionScore(name)
    shift_at: dict[int, tuple[float, float]] = {}
    centre = np.array([scene.width / 2.0, scene.height / 2.0])
    for frame in scene.frames():
        shift_at[frame.t_ns] = frame.camera_offset_px
        c0 = time.process_time()
        motion = est.step(frame.bgr, _person_boxes(frame), frame.t_ns)
        score.cpu_ms.append((time.process_time() - c0) * 1e3)
        smeared = frame.motion_blur_px > 0.0
        score.smeared += smeared
        if motion is None or motion.from_stamp_ns not in shift_at:
            score.smeared_unmeasured += smeared
            continue
        moved = motion.matrix[:, :2] @ centre + motion.matrix[:, 2] - centre
        (x0, y0), (x1, y1) = shift_at[motion.from_stamp_ns], shift_at[frame.t_ns]
        err = math.hypot(moved[0] - (x1 - x0), moved[1] - (y1 - y0))
        score.frames += 1
        score.errors_px.append(err)
        score.smeared_measured += smeared and err <= SMEARED_OK_PX
    score.counts = Counter(est.counts)
    return score


def score_settings(settings: dict[str, dict[str, Any]], scenes: tuple[str, ...] = SHIFT_SCENES,
                   progress: Any = None) -> dict[str, list[dict[str, Any]]]:
    """Each named set of EgoMotionParams overrides on each scene: {name: [row per scene]}."""
    out: dict[str, list[dict[str, Any]]] = {}
    for label, overrides in settings.items():
        rows = []
        for name in scenes:
            rows.append(score_scene(name, EgoMotionParams(**overrides)).row())
            if progress is not None:
                progress(label, rows[-1])
        out[label] = rows
    return out
