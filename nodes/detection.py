"""detection: person boxes with scores for every frame it keeps up with.

Backends (``backend`` param): ``yolox`` (ONNX, shipped in models/, found on the model search path),
``yolov8`` (a user-supplied ultralytics ONNX export), ``hog`` (OpenCV's people detector),
``simulated`` (synthetic scenes only: ground truth + a documented noise model; never a detection
accuracy), ``auto`` (yolox; a missing or corrupt model stops the node with one line saying what to do).
The frame input should be a 1-deep drop_oldest queue so the detector always works on the newest frame.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.node_params import ParamError, parse_params
from ..bus.schemas import Frame, Message
from ..msgs.perception import Detections, GroundTruth
from ..tracking.params import check_ranges
from ..vision.detectors import (
    AUTO_SIZES_PX,
    BACKENDS,
    INPUT_SHAPES,
    RUNTIMES,
    DetectorUnavailable,
    SimulatedDetector,
    largest_size_within,
    make_detector,
    resolve_detector_model,
    split_by_score,
)

WARM_UP_INFERENCES = 2
# The largest network input accepted: a 4K frame's long side. `check` refuses more (one line) rather than the node
# crash-looping on an allocation no machine has.
MAX_INPUT_SIZE_PX = 4096
log = logging.getLogger(__name__)


@dataclass
class DetectionParams:
    backend: str = "auto"
    model_dir: str = ""  # first place on the model search path
    model_file: str = ""  # default: yolox_nano_<input_size_px>.onnx
    # The network input's side (the long side with input_shape: fit), or auto: the largest of 640, 512, 416, 320 this
    # machine infers a 640x480 frame at in auto_budget_ms or less, measured at start-up and logged (input_shape fit).
    input_size_px: int | Literal["auto"] = field(default=416, metadata={"was": "input_size"})
    auto_budget_ms: float = 12.0  # a third of a 30 Hz frame period: the region's second look and the loop need the rest
    # square: the frame letterboxed into input_size_px x input_size_px (a model per size); fit: the frame's own
    # aspect, long side input_size_px, padded to a multiple of 32 (yolox_nano_dynamic.onnx; 4:3 at 416: 416x320)
    input_shape: str = "square"
    score_threshold: float = 0.3
    # Boxes scoring in [low_score_threshold, score_threshold) are published apart (Detections.low_boxes) for
    # re-ID's second association stage (seed 002 §3.1 / ByteTrack; its 0.1, seed 002 §4.3); every other
    # consumer reads the boxes above score_threshold only. Equal to score_threshold: none published.
    low_score_threshold: float = 0.1
    nms_iou: float = 0.45
    threads: int = 0  # inference threads; 0 = the runtime's default
    runtime: str = "onnxruntime"  # onnxruntime | openvino: what infers the ONNX file (backends yolox, yolov8)
    sim_noise_px: float = 4.0
    sim_miss_rate: float = 0.05
    sim_false_positive_rate: float = 0.02
    # Fault injector (backend simulated): each detection takes at least this long (sleeps), to try the
    # loop against a slow detector (`followbus bench chaos`, detector-delay-80ms).
    sim_delay_ms: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ParamError("backend", f"backend must be one of {', '.join(BACKENDS)}, not {self.backend!r}")
        _check_input_size(self)
        if self.input_shape not in INPUT_SHAPES or (self.input_shape == "fit" and self.backend == "yolov8"):
            raise ParamError("input_shape", f"input_shape must be one of {', '.join(INPUT_SHAPES)} (fit: YOLOX "
                                            f"only), not {self.input_shape!r}")
        if self.runtime not in RUNTIMES:
            raise ParamError("runtime", f"runtime must be one of {', '.join(RUNTIMES)}, not {self.runtime!r}")
        check_ranges(self, positive=("auto_budget_ms",), non_negative=("sim_delay_ms", "threads", "sim_noise_px"),
                     unit_interval=("nms_iou", "sim_miss_rate", "sim_false_positive_rate"))
        if not 0.0 <= self.low_score_threshold <= self.score_threshold:
            raise ParamError("low_score_threshold", "low_score_threshold must be in [0, score_threshold] "
                             f"(= score_threshold: no low-score boxes), not {self.low_score_threshold!r}")
        if self.sim_delay_ms and self.backend != "simulated":
            raise ParamError("sim_delay_ms", "sim_delay_ms only applies to backend 'simulated'")

    def check(self) -> None:
        """The model this node would load is on the search path and intact (SHA-256, no onnxruntime): run by
        `followbus check`, `launch` and `demo` before anything starts, so a missing or corrupt model is one line
        instead of detection and redetection crash-looping until their restart budget is spent."""
        size = AUTO_SIZES_PX[0] if self.input_size_px == AUTO else int(self.input_size_px)
        try:
            resolve_detector_model(self.backend, model_dir=self.model_dir or None, model_file=self.model_file or None,
                                   input_size=size, input_shape=self.input_shape)
        except DetectorUnavailable as exc:
            raise ParamError("backend", str(exc)) from exc


def detection_params(raw: dict[str, Any]) -> DetectionParams:
    """A detection node's params from its graph.yaml mapping (ParamError naming a wrong key)."""
    return parse_params(DetectionParams, raw)


def _check_input_size(p: DetectionParams) -> None:
    if p.input_size_px == AUTO:
        if p.input_shape != "fit" or p.backend not in ("auto", "yolox"):
            raise ParamError("input_size_px", "input_size_px: auto needs YOLOX with input_shape: fit (the model "
                                              "that takes any size)")
        return
    if isinstance(p.input_size_px, str) or p.input_size_px < 32 or p.input_size_px % 32:
        raise ParamError("input_size_px", "input_size_px must be a positive multiple of 32 (the detector's "
                                          f"largest stride), e.g. 416 or 640, or auto, not {p.input_size_px!r}")
    if p.input_size_px > MAX_INPUT_SIZE_PX:
        raise ParamError("input_size_px", f"input_size_px must be at most {MAX_INPUT_SIZE_PX} (a 4K frame's long "
                                          "side: a larger input only scales the frame up, and its tensors take "
                                          f"gigabytes), not {p.input_size_px!r}")


AUTO = "auto"


def detector_from_params(p: DetectionParams):
    """The detector this node runs for these params (also what `followbus eval --graph-check` runs
    in-process, so both paths infer the same way). ``input_size_px: auto`` is measured here (logged)."""
    auto = p.input_size_px == AUTO
    detector = make_detector(
        p.backend, model_dir=p.model_dir or None, model_file=p.model_file or None,
        input_size=max(AUTO_SIZES_PX) if auto else int(p.input_size_px), input_shape=p.input_shape,
        score_threshold=min(p.low_score_threshold, p.score_threshold), nms_iou=p.nms_iou,
        threads=p.threads or None, runtime=p.runtime, noise_px=p.sim_noise_px, miss_rate=p.sim_miss_rate,
        false_positive_rate=p.sim_false_positive_rate, seed=p.seed,
    )
    if isinstance(detector, SimulatedDetector):
        detector.delay_ms = p.sim_delay_ms
    if auto:
        size, timings = largest_size_within(detector, p.auto_budget_ms)
        detector.input_size = size
        detector.name = detector.name.replace(f"@{max(AUTO_SIZES_PX)}", f"@{size}")
        log.info("input_size_px auto: %d (ms a 640x480 frame on this machine: %s; budget %.0f ms)", size,
                 ", ".join(f"{k} {v:.1f}" for k, v in timings.items()), p.auto_budget_ms)
    return detector


_RESOLVED: dict[tuple[Any, ...], int] = {}


def resolve_input_size(params: dict[str, Any]) -> dict[str, Any]:
    """``params`` (a detection node's graph.yaml params) with ``input_size_px: auto`` replaced by the size this
    machine chooses (measured once a process): what evaluation runs and names, so the cache, the report and the
    redetection node all see one size."""
    if params.get("input_size_px") != AUTO:
        return params
    p = detection_params(params)
    key = (p.backend, p.model_dir, p.runtime, p.threads, p.auto_budget_ms)
    if key not in _RESOLVED:
        _RESOLVED[key] = int(detector_from_params(p).input_size)
    return {**params, "input_size_px": _RESOLVED[key]}


def split_detections(p: DetectionParams, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The detector's rows (run at the low threshold) as (boxes, low_boxes) of the Detections message."""
    return split_by_score(rows, p.score_threshold, min(p.low_score_threshold, p.score_threshold))


class Detection(Node):
    # Only the simulated backend reads ground truth (a real one looks at the image): capture then need not send it.
    INPUTS = {"frame": In(Frame, required=True),
              "ground_truth": In(GroundTruth, read_if=lambda p: p.backend == "simulated")}
    OUTPUTS = {"detections": Out(Detections)}
    Params = DetectionParams

    def setup(self) -> None:
        try:
            self.detector = detector_from_params(self.params)
        except DetectorUnavailable as exc:
            self.log.error("%s", exc)
            raise SystemExit(1) from exc
        self.simulated = isinstance(self.detector, SimulatedDetector)
        if self.simulated and "ground_truth" not in self.runtime.spec.inputs:
            self.log.error("backend 'simulated' needs the ground_truth input wired (capture/ground_truth)")
            raise SystemExit(1)
        self.log.info("detector backend: %s", self.detector.name)
        self.input_px = int(getattr(self.detector, "input_size", 0) or 0)
        if not self.simulated:
            # The first inferences allocate the runtime's buffers (2x a frame's time): on a blank VGA frame here,
            # before the node is up, not on the camera's first frames.
            for _ in range(WARM_UP_INFERENCES):
                self.detector.detect(np.zeros((480, 640, 3), np.uint8))
        self.frames = 0
        self.infer_ms_total = 0.0

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        frame = inputs["frame"]
        assert isinstance(frame, Frame)
        if frame.encoding != "bgr8":
            self.log.warning("skipping frame %d with encoding %s (need bgr8)", frame_seq, frame.encoding)
            return
        t0 = time.perf_counter()
        if self.simulated:
            gt = inputs.get("ground_truth")
            truth = []
            if isinstance(gt, GroundTruth) and gt.available:
                if gt.box is not None:
                    truth.append((gt.box.tolist(), gt.visible_fraction))
                vis = gt.others_visible if gt.others_visible.size == len(gt.others) else np.ones(len(gt.others))
                truth.extend((box.tolist(), float(v)) for box, v in zip(gt.others, vis, strict=True))
            boxes = self.detector.detect(frame.data, truth)
        else:
            boxes = self.detector.detect(frame.data)
        infer_ms = (time.perf_counter() - t0) * 1e3
        self.frames += 1
        self.infer_ms_total += infer_ms
        high, low = split_detections(self.params, boxes)
        self.publish("detections", Detections(boxes=high, low_boxes=low, backend=self.detector.name,
                                              infer_ms=infer_ms, input_px=self.input_px))

    def status(self) -> dict[str, Any]:
        mean = self.infer_ms_total / self.frames if self.frames else 0.0
        return {"backend": self.detector.name, "frames": self.frames, "infer_ms_mean": round(mean, 2),
                "input_size_px": self.input_px}


NODE = Detection
