"""What the camera side sees: detections, the camera's own image motion, and a source's ground truth."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..bus.schemas import Message, check_shape, require
from .box import check_box_rows, check_boxes


@dataclass
class GroundTruth(Message):
    """Ground truth of the followed person for one frame, when the source has it."""

    TYPE: ClassVar[str] = "GroundTruth"
    available: bool = False  # False: this source has no ground truth (published anyway, so joins never wait)
    box: np.ndarray | None = None  # [x, y, w, h]; None when the target is absent
    visible_fraction: float = 1.0
    others: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # other people's boxes
    others_visible: np.ndarray = field(default_factory=lambda: np.zeros(0))  # their visible fractions

    def check(self) -> None:
        check_boxes(self, "box")


@dataclass
class Detections(Message):
    TYPE: ClassVar[str] = "Detections"
    MEASURED: ClassVar[frozenset[str]] = frozenset({"infer_ms"})
    ADDED: ClassVar[frozenset[str]] = frozenset({"low_boxes", "input_px"})
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))  # x,y,w,h,score
    backend: str = ""
    infer_ms: float = 0.0
    # Boxes scoring below the detection node's score_threshold but at least its low_score_threshold (same
    # layout): only for a consumer that opts in (re-ID's second association stage, seed 002 / ByteTrack);
    # everything else reads ``boxes`` alone.
    low_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
    input_px: int = 0  # the detector's input side (the long side): its scale on the frame; 0: not an image detector

    def check(self) -> None:
        check_box_rows(self, "boxes")
        check_box_rows(self, "low_boxes")


@dataclass
class RegionDetections(Message):
    """Seed 002 §3.2's local re-detection of one frame (nodes/redetection.py): the detector run again on the square
    ``region`` (x0, y0, x1, y1 frame pixels) around the Kalman prediction, at the frame's own resolution. ``reason``
    says why ("occluded", "small", "missed", "crowded"); "" : no region was needed, published all the same so that
    re-ID's join of the frame never waits for it. Boxes as in Detections, in frame pixels."""

    TYPE: ClassVar[str] = "RegionDetections"
    MEASURED: ClassVar[frozenset[str]] = frozenset({"infer_ms"})
    reason: str = ""
    region: np.ndarray = field(default_factory=lambda: np.zeros(4, np.int64))
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
    low_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
    input_px: int = 0  # the detector's input side for the region
    infer_ms: float = 0.0

    def check(self) -> None:
        check_shape(self, "region", self.region, (4,))
        require(not self.reason or (self.region[2] > self.region[0] and self.region[3] > self.region[1]), self,
                f"empty region {self.region.tolist()}")
        check_box_rows(self, "boxes")
        check_box_rows(self, "low_boxes")


@dataclass
class CameraMotion(Message):
    """Global image motion from the frame stamped ``from_stamp_ns`` to this one (``header.stamp_ns``):
    p_k = M p_prev + t in full-resolution pixels (tracking/egomotion.py estimates it, seed 002 §3.3).

    ``valid`` False: no trustworthy estimate for this frame (``reason`` says why); consumers go without."""

    TYPE: ClassVar[str] = "CameraMotion"
    valid: bool = False
    matrix: np.ndarray = field(default_factory=lambda: np.eye(2, 3))  # 2x3 [M | t]
    inliers: int = 0  # points consistent with the matrix
    tracked: int = 0  # points the fit was made from (corners LK followed, outside person boxes)
    from_stamp_ns: int = 0
    reason: str = ""
    # The fit's uncertainty (tracking/egomotion.py), px at full resolution.
    residual_px: float = 0.0  # RMS distance of the inliers from the fit
    spread: float = 0.0  # fraction of the image's grid cells holding an inlier
    rival_px: float = 0.0  # how far the competing hypothesis moves the image centre from this one
    rival_inliers: int = 0
    agreement_px: float = -1.0  # distance from the previous frame's motion at the image centre; -1: none
    std_px: float = 0.0  # 1-σ of the displacement a point gets (prediction widens its prior by it)
    static_cells: int = 0  # grid cells taken for screen-fixed content and left out of the fit

    @property
    def scale(self) -> float:
        """Isotropic scale sqrt|det M| (exact for a similarity)."""
        return math.sqrt(abs(float(np.linalg.det(self.matrix[:, :2]))))

    def check(self) -> None:
        check_shape(self, "matrix", self.matrix, (2, 3))
        require(0 <= self.inliers <= self.tracked, self, "0 <= inliers <= tracked")
        require(not self.valid or 0 <= self.from_stamp_ns < self.header.stamp_ns, self,
                f"from_stamp_ns {self.from_stamp_ns} is not before the frame's stamp")
