"""Person detectors behind one small protocol: ``detect(bgr) -> float32 (N, 5)`` of x, y, w, h, score.

Boxes are top-left-origin pixel boxes in the coordinates of the image passed in; only the
COCO ``person`` class is returned. Backends:

* :class:`YoloxDetector`   - YOLOX ONNX (raw head output, grid/stride decode done here),
* :class:`YoloV8Detector`  - ultralytics YOLOv8 ONNX export (``[1, 84, A]`` layout),
* :class:`HogDetector`     - OpenCV's HOG + linear SVM people detector (no weights needed),
* :class:`SimulatedDetector` - ground truth + noise, for synthetic scenes only.

:func:`make_detector` builds one by name and resolves model files through
:mod:`followbus.vision.models`.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from .models import MODELS_ENV, ModelError, ModelNotFound, resolve_model, search_path, verify_model

log = logging.getLogger(__name__)

BACKENDS = ("auto", "yolox", "yolov8", "hog", "simulated")
PERSON_CLASS = 0
YOLOX_STRIDES = (8, 16, 32)
LETTERBOX_PAD = 114
DEFAULT_YOLOV8_FILE = "yolov8n.onnx"
DYNAMIC_YOLOX_FILE = "yolox_nano_dynamic.onnx"  # any input height and width (input_shape: fit)



class DetectorUnavailable(ModelError):
    """A backend cannot be built (model missing or corrupt, runtime error, ...); one line: what, where, the fix."""

    def __init__(self, message: str, tried: Sequence[Path] = (), hint: str = "") -> None:
        self.search_path = list(tried)
        if tried:
            message = f"{message}; model search path tried: {', '.join(str(p) for p in tried)}"
        if hint:
            message = f"{message}; {hint}"
        super().__init__(message)


@runtime_checkable
class Detector(Protocol):
    """What every backend provides."""

    name: str
    last_infer_ms: float

    def detect(self, bgr: np.ndarray) -> np.ndarray:
        """Person detections for a BGR uint8 (H, W, 3) frame: float32 (N, 5) x, y, w, h, score."""
        ...


def empty_detections() -> np.ndarray:
    return np.zeros((0, 5), dtype=np.float32)


# ----------------------------------------------------------------------------- geometry helpers


def letterbox(
    bgr: np.ndarray, size: int, *, centered: bool = False, pad_value: int = LETTERBOX_PAD, stride: int = 0
) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Resize keeping aspect ratio into a ``size x size`` canvas filled with ``pad_value``.

    ``centered=False`` reproduces YOLOX (image in the top-left corner, ``int()`` truncated size);
    ``centered=True`` reproduces ultralytics (image centred, rounded size, the odd pixel of padding
    going to the bottom/right). ``stride`` > 0 (top-left only): the canvas is the resized image padded only up
    to the next multiple of ``stride`` on each side, not to a square (a 640x480 frame at 416: 416x320, not
    416x416). Returns ``(canvas, ratio, (pad_x_px, pad_y_px))`` where an input pixel p maps to ``p * ratio + pad``.
    """
    h, w = bgr.shape[:2]
    ratio = min(size / h, size / w)
    if centered:
        new_w, new_h = round(w * ratio), round(h * ratio)
        dw, dh = (size - new_w) / 2.0, (size - new_h) / 2.0
        left, top = round(dw - 0.1), round(dh - 0.1)
    else:
        new_w, new_h = int(w * ratio), int(h * ratio)
        left = top = 0
    canvas_h = canvas_w = size
    if stride and not centered:
        canvas_h, canvas_w = -(-new_h // stride) * stride, -(-new_w // stride) * stride
    canvas = np.full((canvas_h, canvas_w, 3), pad_value, dtype=np.uint8)
    resized = bgr if (new_w, new_h) == (w, h) else cv2.resize(bgr, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    canvas[top : top + new_h, left : left + new_w] = resized
    return canvas, ratio, (float(left), float(top))


def unletterbox_boxes(boxes_xywh: np.ndarray, ratio: float, pad_xy: tuple[float, float]) -> np.ndarray:
    """Map x, y, w, h boxes from letterboxed input pixels back to original image pixels."""
    out = np.asarray(boxes_xywh, dtype=np.float32).copy()
    if out.size:
        out[:, 0] = (out[:, 0] - pad_xy[0]) / ratio
        out[:, 1] = (out[:, 1] - pad_xy[1]) / ratio
        out[:, 2:4] /= ratio
    return out


def clip_detections(dets: np.ndarray, width: int, height: int, min_size_px: float = 1.0) -> np.ndarray:
    """Clip x, y, w, h(, score) rows to the image and drop boxes that collapse below ``min_size_px``."""
    if dets.size == 0:
        return dets.reshape(0, dets.shape[1] if dets.ndim == 2 else 5).astype(np.float32)
    out = dets.astype(np.float32, copy=True)
    x0 = np.clip(out[:, 0], 0, width)
    y0 = np.clip(out[:, 1], 0, height)
    x1 = np.clip(out[:, 0] + out[:, 2], 0, width)
    y1 = np.clip(out[:, 1] + out[:, 3], 0, height)
    out[:, 0], out[:, 1], out[:, 2], out[:, 3] = x0, y0, x1 - x0, y1 - y0
    keep = (out[:, 2] >= min_size_px) & (out[:, 3] >= min_size_px)
    return out[keep]


def nms(dets: np.ndarray, iou_threshold: float, score_threshold: float = 0.0) -> np.ndarray:
    """Greedy non-maximum suppression (cv2.dnn.NMSBoxes) on x, y, w, h, score rows, best first."""
    if dets.shape[0] == 0:
        return empty_detections()
    idx = cv2.dnn.NMSBoxes(dets[:, :4].tolist(), dets[:, 4].tolist(), float(score_threshold), float(iou_threshold))
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    out = dets[idx].astype(np.float32)
    return out[np.argsort(-out[:, 4], kind="stable")]


def split_by_score(dets: np.ndarray, score_threshold: float,
                   low_score_threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """(high, low) rows of x, y, w, h, score detections: score >= ``score_threshold``, and the rest scoring at
    least ``low_score_threshold`` (ByteTrack's D_high / D_low, seed 002 §3.1), each in the given order.

    A detector run at ``low_score_threshold`` yields the same high rows as one run at ``score_threshold``:
    greedy NMS lets a box be suppressed only by a kept box of a higher score, so the extra low boxes
    suppress none of them."""
    d = np.asarray(dets, dtype=np.float32).reshape(-1, 5)
    high = d[:, 4] >= score_threshold
    low = ~high & (d[:, 4] >= low_score_threshold)
    return d[high], d[low]


def iou_xywh(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union of two x, y, w, h boxes."""
    ax1, ay1, bx1, by1 = a[0] + a[2], a[1] + a[3], b[0] + b[2], b[1] + b[3]
    iw = max(0.0, min(ax1, bx1) - max(a[0], b[0]))
    ih = max(0.0, min(ay1, by1) - max(a[1], b[1]))
    inter = iw * ih
    union = a[2] * a[3] + b[2] * b[3] - inter
    return float(inter / union) if union > 0 else 0.0


# ----------------------------------------------------------------------------- YOLOX


def _input_hw(input_size: int | tuple[int, int]) -> tuple[int, int]:
    """(height, width) of the network input: a side (square) or the pair."""
    return (input_size, input_size) if isinstance(input_size, int) else (int(input_size[0]), int(input_size[1]))


def _yolox_grids(input_size: int | tuple[int, int],
                 strides: Sequence[int] = YOLOX_STRIDES) -> tuple[np.ndarray, np.ndarray]:
    height, width = _input_hw(input_size)
    grids, expanded = [], []
    for s in strides:
        ny, nx = height // s, width // s
        xv, yv = np.meshgrid(np.arange(nx), np.arange(ny))  # row-major: y outer, x inner, as YOLOX
        grids.append(np.stack((xv, yv), axis=2).reshape(-1, 2))
        expanded.append(np.full((ny * nx, 1), s))
    return np.concatenate(grids).astype(np.float32), np.concatenate(expanded).astype(np.float32)


def decode_yolox(raw: np.ndarray, input_size: int | tuple[int, int], score_threshold: float = 0.0) -> np.ndarray:
    """Decode a raw YOLOX head output ``[1, A, 5 + C]`` into person boxes in input pixels (``input_size``: the
    side of a square input, or its (height, width)).

    Per anchor: ``xy = (raw_xy + grid) * stride``, ``wh = exp(raw_wh) * stride`` (centre form),
    ``score = objectness * person score`` (the exported head already applied the sigmoids).
    Returns float32 (N, 5) x, y, w, h, score for scores >= ``score_threshold``, not yet NMS-ed.
    """
    pred = np.asarray(raw, dtype=np.float32).reshape(-1, raw.shape[-1])
    grids, strides = _yolox_grids(input_size)
    if grids.shape[0] != pred.shape[0]:
        raise ValueError(f"YOLOX output has {pred.shape[0]} anchors, input {input_size} implies {grids.shape[0]}")
    scores = pred[:, 4] * pred[:, 5 + PERSON_CLASS]
    keep = scores >= score_threshold
    p, g, s = pred[keep], grids[keep], strides[keep]
    cxy = (p[:, 0:2] + g) * s
    # Clamp before exp: garbage anchors can overflow float32 otherwise.
    wh = np.exp(np.minimum(p[:, 2:4], 10.0)) * s
    out = np.empty((p.shape[0], 5), dtype=np.float32)
    out[:, 0:2] = cxy - wh / 2.0
    out[:, 2:4] = wh
    out[:, 4] = scores[keep]
    return out


def yolox_postprocess(
    raw: np.ndarray,
    input_size: int | tuple[int, int],
    ratio: float,
    image_shape: tuple[int, ...],
    score_threshold: float = 0.3,
    nms_iou: float = 0.45,
) -> np.ndarray:
    """Decode, NMS, map back through the top-left letterbox and clip to the image."""
    dets = nms(decode_yolox(raw, input_size, score_threshold), nms_iou, score_threshold)
    dets[:, :4] = unletterbox_boxes(dets[:, :4], ratio, (0.0, 0.0))
    return clip_detections(dets, image_shape[1], image_shape[0])


def _ort_session(model_path: Path, threads: int | None) -> Any:
    import onnxruntime as ort  # deferred: HOG/simulated users need not pay the import

    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    if threads:
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
    # Idle inference threads spin by default, burning a core the other nodes of the graph need: on two
    # cores that alone doubles the end-to-end p50 (BENCHMARKS.md, pipeline).
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(str(model_path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own Fail/InvalidProtobuf/... types, multi-line
        lines = str(exc).strip().splitlines()
        raise ModelError(f"model file {model_path} cannot be loaded by onnxruntime "
                         f"({lines[0] if lines else type(exc).__name__}); replace it with a valid ONNX model "
                         "(run `followbus models` to check the shipped ones)") from exc


RUNTIMES = ("onnxruntime", "openvino")


class _OpenVinoSession:
    """An OpenVINO compiled model behind the two calls :class:`_OnnxDetector` makes of an onnxruntime session
    (``get_inputs()[0].name/.shape`` and ``run(None, feeds)``), so either runtime infers the same ONNX file."""

    class _Input:
        def __init__(self, name: str, shape: list[Any]) -> None:
            self.name, self.shape = name, shape

    def __init__(self, model_path: Path, threads: int | None) -> None:
        import openvino as ov  # deferred: only this runtime needs it

        core = ov.Core()
        # f32 as onnxruntime: on a CPU with AVX-512 BF16 (AMD EPYC here) OpenVINO infers in bfloat16 by default,
        # which moved boxes by 2 px and swapped two near-equal scores against onnxruntime's.
        config: dict[str, Any] = {"PERFORMANCE_HINT": "LATENCY", "NUM_STREAMS": "1", "INFERENCE_PRECISION_HINT": "f32"}
        if threads:
            config["INFERENCE_NUM_THREADS"] = int(threads)
        try:
            self._compiled = core.compile_model(core.read_model(str(model_path)), "CPU", config)
        except Exception as exc:  # OpenVINO raises RuntimeError with multi-line text
            lines = str(exc).strip().splitlines()
            raise ModelError(f"model file {model_path} cannot be loaded by OpenVINO "
                             f"({lines[0] if lines else type(exc).__name__})") from exc
        port = self._compiled.inputs[0]
        shape = [d.get_length() if d.is_static else None for d in port.get_partial_shape()]
        self._input = self._Input(port.get_any_name(), shape)
        self._request = self._compiled.create_infer_request()

    def get_inputs(self) -> list[Any]:
        return [self._input]

    def run(self, _outputs: Any, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        result = self._request.infer(feeds)
        return [np.asarray(result[self._compiled.outputs[0]])]


def _inference_session(model_path: Path, threads: int | None, runtime: str) -> Any:
    if runtime == "openvino":
        try:
            return _OpenVinoSession(model_path, threads)
        except ImportError as exc:
            raise ModelError("runtime 'openvino' needs the openvino package (pip install openvino); "
                             "or set `runtime: onnxruntime`") from exc
    return _ort_session(model_path, threads)


def _static_square_size(shape: Sequence[Any]) -> int | None:
    """Input side of an NCHW model when both H and W are fixed and equal, else None."""
    if len(shape) == 4 and isinstance(shape[2], int) and isinstance(shape[3], int) and shape[2] == shape[3]:
        return int(shape[2])
    return None


def _free_spatial_dims(shape: Sequence[Any]) -> bool:
    """Whether an NCHW model takes any height and width (both dims symbolic)."""
    return len(shape) == 4 and not isinstance(shape[2], int) and not isinstance(shape[3], int)


INPUT_SHAPES = ("square", "fit")  # the network input: input_size_px square, or the frame's shape fitted to it


class _OnnxDetector:
    """Shared set-up of the ONNX person detectors: session, input name and side, thresholds."""

    kind = ""
    default_size = 416

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        input_size: int | None = None,
        score_threshold: float = 0.3,
        nms_iou: float = 0.45,
        threads: int | None = None,
        runtime: str = "onnxruntime",
        input_shape: str = "square",
    ) -> None:
        self.model_path = Path(model_path)
        verify_model(self.model_path)  # a corrupt file must not reach onnxruntime (or worse, load and misdetect)
        self.session = _inference_session(self.model_path, threads, runtime)
        inp = self.session.get_inputs()[0]
        self.input_name = inp.name
        if input_shape == "fit" and not _free_spatial_dims(inp.shape):
            raise ModelError(f"input_shape 'fit' needs a model that takes any height and width "
                             f"(yolox_nano_dynamic.onnx); {self.model_path.name} takes {inp.shape[2:]}")
        model_size = _static_square_size(inp.shape)
        if model_size is not None and input_size is not None and input_size != model_size:
            log.warning("%s has fixed input %d; ignoring requested input_size=%d",
                        self.model_path.name, model_size, input_size)
        self.input_size = model_size or input_size or self.default_size
        self.input_shape = input_shape
        self.score_threshold = float(score_threshold)
        self.nms_iou = float(nms_iou)
        suffix = "" if runtime == "onnxruntime" else f" ({runtime})"
        fit = " fit" if input_shape == "fit" else ""
        self.name = f"{self.kind}:{self.model_path.name}@{self.input_size}{fit}{suffix}"
        self.last_infer_ms = 0.0

    def _infer(self, blob: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        raw = self.session.run(None, {self.input_name: blob})[0]
        self.last_infer_ms = (time.perf_counter() - t0) * 1e3
        return raw


class YoloxDetector(_OnnxDetector):
    """YOLOX (e.g. YOLOX-nano) ONNX model with raw ``[1, A, 85]`` output; see models/README.md.

    Pre-processing as YOLOX: top-left letterbox padded with 114, BGR 0-255 float, NCHW, no
    normalisation. The input side is read from the model (416 or 640 for the shipped files).
    """

    kind = "yolox"
    default_size = 416

    def preprocess(self, bgr: np.ndarray) -> tuple[np.ndarray, float]:
        # "fit": the frame's own aspect padded to the largest stride (32), not to a square: a 4:3 frame at 416
        # infers 416x320, 23 % less work than 416x416, with the same scale and the same boxes but at the border.
        stride = max(YOLOX_STRIDES) if self.input_shape == "fit" else 0
        canvas, ratio, _ = letterbox(bgr, self.input_size, centered=False, stride=stride)
        blob = np.ascontiguousarray(canvas.transpose(2, 0, 1)[None], dtype=np.float32)
        return blob, ratio

    def detect(self, bgr: np.ndarray) -> np.ndarray:
        blob, ratio = self.preprocess(bgr)
        raw = self._infer(blob)
        return yolox_postprocess(raw, (blob.shape[2], blob.shape[3]), ratio, bgr.shape, self.score_threshold,
                                 self.nms_iou)

    def detect_at(self, bgr: np.ndarray, input_size: int) -> np.ndarray:
        """:meth:`detect` with the long side inferred at ``input_size`` px (a multiple of 32; a model that takes
        any height and width, input_shape fit): a region inferred at its own resolution (seed 002 §3.2)."""
        if self.input_shape != "fit":
            raise ModelError(f"{self.name}: detect_at needs input_shape 'fit' (a model of free height and width)")
        size, self.input_size = self.input_size, int(input_size)
        try:
            return self.detect(bgr)
        finally:
            self.input_size = size


# ----------------------------------------------------------------------------- YOLOv8


def decode_yolov8(raw: np.ndarray, score_threshold: float = 0.0) -> np.ndarray:
    """Decode an ultralytics detection export ``[1, 4 + C, A]`` into person boxes in input pixels.

    Rows 0-3 are cx, cy, w, h in input pixels, rows 4.. are per-class scores (sigmoid applied,
    no objectness). Returns float32 (N, 5) x, y, w, h, score (person score), not yet NMS-ed.
    """
    arr = np.asarray(raw, dtype=np.float32)
    if arr.ndim == 3:
        arr = arr[0]
    if arr.ndim != 2 or arr.shape[0] < 5:
        raise ValueError(f"expected a [1, 4 + C, A] YOLOv8 output, got shape {np.shape(raw)}")
    scores = arr[4 + PERSON_CLASS]
    keep = scores >= score_threshold
    cx, cy, w, h = arr[0, keep], arr[1, keep], arr[2, keep], arr[3, keep]
    return np.stack([cx - w / 2.0, cy - h / 2.0, w, h, scores[keep]], axis=1).astype(np.float32)


def yolov8_postprocess(
    raw: np.ndarray,
    ratio: float,
    pad_xy: tuple[float, float],
    image_shape: tuple[int, ...],
    score_threshold: float = 0.3,
    nms_iou: float = 0.45,
) -> np.ndarray:
    """Decode, NMS, map back through the centred letterbox and clip to the image."""
    dets = nms(decode_yolov8(raw, score_threshold), nms_iou, score_threshold)
    dets[:, :4] = unletterbox_boxes(dets[:, :4], ratio, pad_xy)
    return clip_detections(dets, image_shape[1], image_shape[0])


class YoloV8Detector(_OnnxDetector):
    """ultralytics YOLOv8 ONNX export (``yolo export format=onnx``): centred letterbox, RGB / 255."""

    kind = "yolov8"
    default_size = 640

    def detect(self, bgr: np.ndarray) -> np.ndarray:
        canvas, ratio, pad = letterbox(bgr, self.input_size, centered=True)
        blob = np.ascontiguousarray(canvas[:, :, ::-1].transpose(2, 0, 1)[None], dtype=np.float32) / 255.0
        raw = self._infer(blob)
        return yolov8_postprocess(raw, ratio, pad, bgr.shape, self.score_threshold, self.nms_iou)


# ----------------------------------------------------------------------------- HOG


class HogDetector:
    """OpenCV HOG + linear-SVM people detector (Dalal-Triggs, 64x128 window); needs no weights.

    Scores: ``detectMultiScale`` returns the SVM margin m of each window (m > 0 means "person";
    typical hits 0..3). It is squashed monotonically into 0..1 as ``sigmoid(3 * (m - 0.5))``
    (m = 0 -> 0.18, 0.5 -> 0.5, 1 -> 0.82, 2 -> 0.99). This is a ranking, not a calibrated
    probability. Boxes are shrunk to the person inside the window (the INRIA training windows
    carry a margin around the body: ~20 % each side horizontally, ~7 % vertically).
    Frames wider than ``max_width_px`` are downscaled first to bound run time.
    """

    SHRINK_X = 0.20
    SHRINK_Y = 0.07

    def __init__(
        self,
        score_threshold: float = 0.3,
        nms_iou: float = 0.45,
        max_width_px: int | None = 640,
        win_stride_px: int = 8,
        scale: float = 1.05,
    ) -> None:
        self.hog = cv2.HOGDescriptor()
        self.hog.setSVMDetector(cv2.HOGDescriptor_getDefaultPeopleDetector())
        self.score_threshold = float(score_threshold)
        self.nms_iou = float(nms_iou)
        self.max_width_px = max_width_px
        self.win_stride_px = int(win_stride_px)
        self.scale = float(scale)
        self.name = "hog"
        self.last_infer_ms = 0.0

    @staticmethod
    def margin_to_score(margin: np.ndarray) -> np.ndarray:
        return (1.0 / (1.0 + np.exp(-3.0 * (np.asarray(margin, dtype=np.float64) - 0.5)))).astype(np.float32)

    def detect(self, bgr: np.ndarray) -> np.ndarray:
        h, w = bgr.shape[:2]
        factor = 1.0
        img = bgr
        if self.max_width_px and w > self.max_width_px:
            factor = self.max_width_px / w
            img = cv2.resize(bgr, (self.max_width_px, round(h * factor)), interpolation=cv2.INTER_AREA)
        t0 = time.perf_counter()
        rects, weights = self.hog.detectMultiScale(
            img, winStride=(self.win_stride_px, self.win_stride_px), padding=(8, 8), scale=self.scale
        )
        self.last_infer_ms = (time.perf_counter() - t0) * 1e3
        if len(rects) == 0:
            return empty_detections()
        r = np.asarray(rects, dtype=np.float32).reshape(-1, 4) / factor
        dets = np.empty((r.shape[0], 5), dtype=np.float32)
        dets[:, 0] = r[:, 0] + self.SHRINK_X * r[:, 2]
        dets[:, 1] = r[:, 1] + self.SHRINK_Y * r[:, 3]
        dets[:, 2] = r[:, 2] * (1.0 - 2 * self.SHRINK_X)
        dets[:, 3] = r[:, 3] * (1.0 - 2 * self.SHRINK_Y)
        dets[:, 4] = self.margin_to_score(np.asarray(weights).reshape(-1))
        dets = dets[dets[:, 4] >= self.score_threshold]
        return clip_detections(nms(dets, self.nms_iou, self.score_threshold), w, h)


# ----------------------------------------------------------------------------- simulated


TruthLike = tuple[Sequence[float] | None, float]


class SimulatedDetector:
    """Synthetic-scene stand-in for a detector: ground-truth boxes plus a simple noise model.

    NOT A DETECTOR. Its output quality is whatever the parameters say, so nothing computed
    from it may be reported as detection accuracy; it exists so trackers and the control loop
    can be exercised deterministically on :mod:`followbus.vision.scenes` without weights.

    Model, per ground-truth person ``(box, visible_fraction)`` (target and distractors alike):

    * visible fraction < 0.3 -> always missed (a real detector rarely fires on a sliver);
    * otherwise missed with probability ``miss_rate``;
    * a kept box gets Gaussian jitter: centre x/y ``N(0, noise_px)``, width/height
      ``N(0, noise_px)`` (pixels, additive; sizes floored at 4 px); it is the full (amodal) box,
      so partial occlusion does not shrink it;
    * score ``clip(0.5 + 0.45 * visible_fraction + N(0, 0.05), 0.05, 0.99)``;
    * false positives: ``Poisson(false_positive_rate)`` boxes per frame, person-shaped
      (w = 0.4 h, h uniform in [0.1, 0.6] image height), uniformly placed, score U(0.3, 0.6).

    Output is clipped to the image, not NMS-ed, and in shuffled order (backends guarantee no order).
    Deterministic for a seed and the same call sequence (:meth:`reset` restarts the stream).
    Truth is passed per call (``detect(bgr, truth)``) or beforehand via :meth:`set_truth`.

    ``delay_ms`` is a load/latency fault injector (``followbus bench chaos``): every :meth:`detect`
    call sleeps until it has taken at least that long, like a slow detector on a busy CPU, without
    changing the boxes.
    """

    MIN_VISIBLE_FRACTION = 0.3
    is_simulated = True

    def __init__(
        self, noise_px: float = 4.0, miss_rate: float = 0.05, false_positive_rate: float = 0.02, seed: int = 0,
        delay_ms: float = 0.0,
    ) -> None:
        if not 0.0 <= miss_rate <= 1.0:
            raise ValueError("miss_rate must be in [0, 1]")
        if not delay_ms >= 0.0:
            raise ValueError("delay_ms must be >= 0")
        self.delay_ms = float(delay_ms)
        self.noise_px = float(noise_px)
        self.miss_rate = float(miss_rate)
        self.false_positive_rate = float(false_positive_rate)
        self.seed = int(seed)
        self.name = "simulated (ground truth + noise; not a detection accuracy)"
        self.last_infer_ms = 0.0
        self._truth: list[TruthLike] = []
        self.reset()

    def reset(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def set_truth(self, truth: Iterable[TruthLike]) -> None:
        """Ground truth for the next :meth:`detect` calls: ``(box or None, visible_fraction)`` pairs."""
        self._truth = list(truth)

    def detect(self, bgr: np.ndarray, truth: Iterable[TruthLike] | None = None) -> np.ndarray:
        t0 = time.perf_counter()
        h_img, w_img = bgr.shape[:2]
        rng = self._rng
        rows: list[list[float]] = []
        for box, vis in self._truth if truth is None else truth:
            # Draw the random numbers unconditionally so one person's miss does not shift the
            # noise stream of the others (keeps runs comparable across parameter changes).
            u_miss = rng.random()
            jit = rng.normal(0.0, 1.0, size=5)
            if box is None or vis < self.MIN_VISIBLE_FRACTION or u_miss < self.miss_rate:
                continue
            x, y, w, h = (float(v) for v in box)
            cx = x + w / 2 + jit[0] * self.noise_px
            cy = y + h / 2 + jit[1] * self.noise_px
            w2 = max(4.0, w + jit[2] * self.noise_px)
            h2 = max(4.0, h + jit[3] * self.noise_px)
            score = float(np.clip(0.5 + 0.45 * vis + 0.05 * jit[4], 0.05, 0.99))
            rows.append([cx - w2 / 2, cy - h2 / 2, w2, h2, score])
        for _ in range(int(rng.poisson(self.false_positive_rate))):
            h = rng.uniform(0.1, 0.6) * h_img
            w = 0.4 * h
            rows.append([rng.uniform(0, w_img - w), rng.uniform(0, h_img - h), w, h, rng.uniform(0.3, 0.6)])
        dets = np.asarray(rows, dtype=np.float32).reshape(-1, 5)
        if dets.shape[0] > 1:
            dets = dets[rng.permutation(dets.shape[0])]
        if self.delay_ms > 0:
            time.sleep(max(0.0, t0 + self.delay_ms / 1e3 - time.perf_counter()))
        self.last_infer_ms = (time.perf_counter() - t0) * 1e3
        return clip_detections(dets, w_img, h_img)


# ----------------------------------------------------------------------------- factory


def _default_model_file(backend: str, input_size: int, input_shape: str = "square") -> str:
    if backend != "yolox":
        return DEFAULT_YOLOV8_FILE
    return DYNAMIC_YOLOX_FILE if input_shape == "fit" else f"yolox_nano_{input_size}.onnx"


def resolve_detector_model(
    backend: str,
    *,
    model_dir: str | os.PathLike[str] | None = None,
    model_file: str | None = None,
    input_size: int = 416,
    input_shape: str = "square",
) -> Path | None:
    """The checked model file an ONNX backend would load (``None`` for ``hog``/``simulated``).

    Raises :class:`DetectorUnavailable` with a one-line message naming the search path or the
    corrupt file and the fix. Cheap (no onnxruntime): the demo checks with it before launching.
    """
    backend = backend.strip().lower()
    if backend in ("hog", "simulated"):
        return None
    kind = "yolox" if backend == "auto" else backend
    filename = model_file or _default_model_file(kind, input_size, input_shape)
    try:
        return resolve_model(filename, model_dir)
    except ModelNotFound as exc:
        if kind == "yolox":
            where = (f"restore the shipped models/ (`git checkout -- models`) or point model_dir or ${MODELS_ENV} "
                     f"at a folder holding {filename}")
            if backend == "auto":
                raise DetectorUnavailable(
                    f"detector backend 'auto' needs the YOLOX model {filename}, which is missing", exc.tried,
                    f"{where}, or set `backend: hog` explicitly (far less accurate)") from exc
            raise DetectorUnavailable(f"yolox model {filename} not found", exc.tried, where) from exc
        raise DetectorUnavailable(
            f"{kind} model {filename} not found", exc.tried,
            "export one (`yolo export model=yolov8n.pt format=onnx`) and set model_dir/model_file to it") from exc
    except ModelError as exc:
        raise DetectorUnavailable(str(exc)) from exc


def make_detector(
    backend: str,
    *,
    model_dir: str | os.PathLike[str] | None = None,
    model_file: str | None = None,
    input_size: int = 416,
    score_threshold: float = 0.3,
    nms_iou: float = 0.45,
    threads: int | None = None,
    runtime: str = "onnxruntime",
    input_shape: str = "square",
    noise_px: float = 4.0,
    miss_rate: float = 0.05,
    false_positive_rate: float = 0.02,
    seed: int = 0,
) -> Detector:
    """Build a detector by backend name (one of :data:`BACKENDS`).

    ``auto`` is YOLOX with ``model_file`` (default ``yolox_nano_<input_size>.onnx``, shipped in
    models/). A model that is missing from the search path, fails its SHA-256 check or does not
    load raises :class:`DetectorUnavailable`, for ``auto`` too: there is no silent fallback to HOG,
    whose detections are far worse; ``hog`` is an explicit choice. ``simulated`` ignores the image
    and needs ground truth (see :class:`SimulatedDetector`). ``runtime`` (one of :data:`RUNTIMES`) infers
    the ONNX backends' file with onnxruntime or OpenVINO.
    """
    backend = backend.strip().lower()
    if backend not in BACKENDS:
        raise ValueError(f"unknown detector backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if runtime not in RUNTIMES:
        raise ValueError(f"unknown runtime {runtime!r}; choose one of {', '.join(RUNTIMES)}")
    if backend == "hog":
        return HogDetector(score_threshold=score_threshold, nms_iou=nms_iou)
    if backend == "simulated":
        return SimulatedDetector(noise_px, miss_rate, false_positive_rate, seed)

    path = resolve_detector_model(backend, model_dir=model_dir, model_file=model_file, input_size=input_size,
                                  input_shape=input_shape)
    assert path is not None
    cls = YoloV8Detector if backend == "yolov8" else YoloxDetector
    try:
        det = cls(path, input_size=input_size, score_threshold=score_threshold, nms_iou=nms_iou, threads=threads,
                  runtime=runtime, input_shape=input_shape)
    except ModelError as exc:
        raise DetectorUnavailable(str(exc)) from exc
    log.info("detector %s -> %s (model %s; search path: %s)",
             backend, det.name, path, ", ".join(map(str, search_path(model_dir))))
    return det


AUTO_SIZES_PX = (640, 512, 416, 320)  # input_size_px: auto chooses among these, largest first


def largest_size_within(detector: YoloxDetector, budget_ms: float, frame_wh: tuple[int, int] = (640, 480),
                        sizes: Sequence[int] = AUTO_SIZES_PX, repeats: int = 5) -> tuple[int, dict[int, float]]:
    """The largest of ``sizes`` at which ``detector`` (a model of free height and width) infers a ``frame_wh`` frame
    in ``budget_ms`` or less (median of ``repeats``, after one warm-up), the smallest when none fits; and each size's
    median ms. On this machine, now: what the robot's detector can afford (input_size_px: auto)."""
    frame = np.zeros((frame_wh[1], frame_wh[0], 3), np.uint8)
    timings: dict[int, float] = {}
    for size in sorted(sizes, reverse=True):
        detector.detect_at(frame, size)
        runs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            detector.detect_at(frame, size)
            runs.append((time.perf_counter() - t0) * 1e3)
        timings[size] = float(np.median(runs))
        if timings[size] <= budget_ms:
            return size, timings
    return min(sizes), timings


def best_iou(dets: np.ndarray, box: Sequence[float]) -> float:
    """Best IoU of any detection row with ``box`` (0 when there is none)."""
    return max((iou_xywh(d[:4], box) for d in dets), default=0.0)


__all__ = [
    "BACKENDS",
    "RUNTIMES",
    "Detector",
    "DetectorUnavailable",
    "HogDetector",
    "SimulatedDetector",
    "best_iou",
    "largest_size_within",
    "YoloV8Detector",
    "YoloxDetector",
    "clip_detections",
    "decode_yolov8",
    "decode_yolox",
    "empty_detections",
    "iou_xywh",
    "letterbox",
    "make_detector",
    "resolve_detector_model",
    "nms",
    "split_by_score",
    "unletterbox_boxes",
    "yolov8_postprocess",
    "yolox_postprocess",
]
