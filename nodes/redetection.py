"""redetection: seed 002 §3.2's Kalman-guided local re-detection, at the frame's own resolution.

For every frame it decides from the prior (the Kalman prediction, camera-motion compensated) and the frame's
detections whether the region around the prediction needs a second look (tracking/redetection.py: the target
missed on the last frame, none or several detections in the gate, or a person too small for the detector's input
scale); if so it runs the detector on that square region of the full-resolution frame and publishes its boxes, in
frame pixels, for re-ID to merge with the frame's (seed 002's S = k·max(w, h), k from speed and the last detection
score). Otherwise it publishes an empty result at once, so re-ID's join never waits for it.

The detector is the graph's own: that of the node whose ``detections`` this node takes (its model, runtime and
thresholds), on the dynamic-size YOLOX model so a region is inferred at its own size. A simulated detector has no
image to look at: this node then only publishes empty results.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.schemas import Frame, Message
from ..msgs.perception import Detections, RegionDetections
from ..msgs.tracking import Measurement, Prior, TrackState
from ..tracking.params import RedetectionParams
from ..tracking.redetection import (
    finer_than_the_frame,
    input_side_px,
    reason_to_redetect,
    region_cap_px,
    region_of,
    search_scale,
)
from ..vision.detectors import AUTO_SIZES_PX, DYNAMIC_YOLOX_FILE, DetectorUnavailable, SimulatedDetector
from .detection import DetectionParams, detection_params, detector_from_params, split_detections


class Redetection(Node):
    INPUTS = {"frame": In(Frame, required=True), "detections": In(Detections, required=True),
              "prior": In(Prior, required=True), "measurement": In(Measurement)}
    OUTPUTS = {"detections": Out(RegionDetections)}
    Params = RedetectionParams

    def setup(self) -> None:
        self.detection = self._graph_detection_params()
        self.detector = self._region_detector(self.detection)
        # The detector's input side when its detections do not say it (an older recording): the param, or for auto
        # the smallest it chooses.
        size = self.detection.input_size_px
        self._input_px = min(AUTO_SIZES_PX) if isinstance(size, str) else int(size)
        self.redetected: dict[str, int] = {}
        self.skipped_coarse = 0  # regions too large to be seen finer than the frame pass within the budget
        self.infer_ms_total = 0.0

    def _graph_detection_params(self) -> DetectionParams:
        """The params of the node whose detections this one takes: the detector the graph runs."""
        source = self.runtime.spec.inputs["detections"].source_node
        return detection_params(dict(self.runtime.graph.nodes[source].params))

    def _region_detector(self, detection: DetectionParams) -> Any:
        """The graph's detector for regions: YOLOX on its dynamic-size model; None for a simulated one."""
        if not self.params.local_redetection or detection.backend == "simulated":
            return None
        params = DetectionParams(**{**vars(detection), "input_shape": "fit", "model_file": DYNAMIC_YOLOX_FILE,
                                    "input_size_px": 416}) if detection.backend in ("auto", "yolox") else detection
        try:
            detector = detector_from_params(params)
        except DetectorUnavailable as exc:
            self.log.error("%s", exc)
            raise SystemExit(1) from exc
        return None if isinstance(detector, SimulatedDetector) else detector

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        frame, dets, prior = inputs["frame"], inputs["detections"], inputs["prior"]
        assert isinstance(frame, Frame) and isinstance(dets, Detections) and isinstance(prior, Prior)
        measurement = inputs.get("measurement")
        out = RegionDetections()
        if self.detector is not None and frame.encoding == "bgr8" and prior.initialised:
            out = self._redetect(frame.data, dets, prior, measurement if isinstance(measurement, Measurement) else None)
        self.publish("detections", out)

    def _redetect(self, bgr: np.ndarray, dets: Detections, prior: Prior, last: Measurement | None) -> RegionDetections:
        p = self.params
        height, width = bgr.shape[:2]
        score = None if last is None or last.detector_score < 0 else last.detector_score
        k = search_scale(prior, score, p.dt_ms, p)
        occluded = last is not None and not last.accepted and last.state == TrackState.OCCLUDED.value
        input_px = dets.input_px or self._input_px
        input_scale = input_px / max(width, height)
        reason = reason_to_redetect(prior, dets.boxes, k, occluded, input_scale, p.min_resolvable_px)
        if not reason:
            return RegionDetections()
        cap = region_cap_px((width, height), input_px, p.region_budget_fraction)
        rect = region_of(prior, k, (width, height), cap)
        side = input_side_px(rect, cap)
        if not finer_than_the_frame(rect, side, input_scale):
            self.skipped_coarse += 1
            return RegionDetections()
        x0, y0, x1, y1 = rect
        t0 = time.perf_counter()
        detect_at = getattr(self.detector, "detect_at", None)
        crop = bgr[y0:y1, x0:x1]
        rows = np.asarray(detect_at(crop, side) if detect_at else self.detector.detect(crop), np.float32).reshape(-1, 5)
        infer_ms = (time.perf_counter() - t0) * 1e3
        rows[:, 0] += x0
        rows[:, 1] += y0
        high, low = split_detections(self.detection, rows)
        self.redetected[reason] = self.redetected.get(reason, 0) + 1
        self.infer_ms_total += infer_ms
        return RegionDetections(reason=reason, region=np.array(rect, np.int64), boxes=high, low_boxes=low,
                                input_px=side, infer_ms=infer_ms)

    def status(self) -> dict[str, Any]:
        n = sum(self.redetected.values())
        return {"redetected": dict(self.redetected), "skipped_coarse": self.skipped_coarse,
                "infer_ms_mean": round(self.infer_ms_total / n, 2) if n else None,
                "detector": getattr(self.detector, "name", None)}


NODE = Redetection
