"""egomotion: the camera's image motion between consecutive frames (seed 002 §3.3, tracking/egomotion.py).

For each frame that has detections it fits a similarity to Lucas–Kanade flow of background corners (outside
the frame's person boxes) between the previous frame it handled and this one, and publishes it as
``transform`` (2x3 matrix, inlier count, the previous frame's stamp), or ``valid: false`` with the reason when
the fit is not trustworthy. Prediction warps its prior by it (an optional same-frame input): without this node
the prior is simply not warped. Ticked by frame + detections, like prediction, so it sees the frames prediction
sees and the transform spans exactly prediction's step.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.schemas import Frame, Message
from ..msgs.perception import CameraMotion, Detections
from ..tracking.egomotion import EgoMotionEstimator, EgoMotionParams


class EgoMotion(Node):
    # A frame comes a detector's inference before its boxes: on_message follows the corners into it at once.
    INPUTS = {"frame": In(Frame, required=True, on_arrival=True), "detections": In(Detections, required=True)}
    OUTPUTS = {"transform": Out(CameraMotion)}
    Params = EgoMotionParams

    def setup(self) -> None:
        self.estimator = EgoMotionEstimator(self.params)
        self.epoch_ns = 0
        self.step_ms_total = 0.0  # measure, publish and advance
        self.measure_ms_total = 0.0  # measure only: what the loop waits for
        self.prepare_ms_total = 0.0  # on the frame's arrival, before its boxes
        self.prepared = 0
        self.steps = 0

    def on_message(self, name: str, msg: Message) -> None:
        # The transform is then out soon after the boxes (EgoMotionEstimator.prepare; the motion is the same).
        if name == "frame" and isinstance(msg, Frame) and msg.encoding == "bgr8" \
                and msg.header.epoch_ns == self.epoch_ns:
            t0 = time.perf_counter()
            self.estimator.prepare(msg.data, msg.header.stamp_ns)
            self.prepare_ms_total += (time.perf_counter() - t0) * 1e3
            self.prepared += 1

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        frame, dets = inputs["frame"], inputs["detections"]
        assert isinstance(frame, Frame) and isinstance(dets, Detections)
        if frame.encoding != "bgr8":
            self.log.warning("frame %d is %s, not bgr8: no camera motion", frame_seq, frame.encoding)
            self.publish("transform", CameraMotion(valid=False, reason="not_bgr8"))
            return
        if frame.header.epoch_ns != self.epoch_ns:
            self.epoch_ns = frame.header.epoch_ns  # a restarted capture: its first frame has no predecessor
            self.estimator.reset()
        t0 = time.perf_counter()
        motion = self.estimator.measure(frame.data, np.asarray(dets.boxes), frame.header.stamp_ns)
        self.measure_ms_total += (time.perf_counter() - t0) * 1e3
        try:  # prediction waits for this; the next frame's corners do not need to hold it up
            self.publish("transform", motion or CameraMotion(valid=False, reason=self.estimator.last_reason))
        finally:
            self.estimator.advance()
        self.step_ms_total += (time.perf_counter() - t0) * 1e3
        self.steps += 1

    def status(self) -> dict[str, Any]:
        return {"counts": dict(self.estimator.counts),
                "step_ms_mean": round(self.step_ms_total / self.steps, 3) if self.steps else None,
                "measure_ms_mean": round(self.measure_ms_total / self.steps, 3) if self.steps else None,
                "prepare_ms_mean": round(self.prepare_ms_total / self.prepared, 3) if self.prepared else None,
                "frames_prepared": self.prepared}


NODE = EgoMotion
