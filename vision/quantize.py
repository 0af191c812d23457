"""Static INT8 quantization of the YOLOX-nano detector with onnxruntime.quantization (the recipe of
models/yolox_nano_640_int8.onnx; `followbus models --build-int8` runs it).

Recipe: calibration frames are letterboxed exactly as :class:`~followbus.vision.detectors.YoloxDetector` feeds
them; the model is converted to opset 13 (per-channel QDQ needs it), then onnxruntime's ``quant_pre_process``
(shape inference, graph optimisation) and ``quantize_static`` in QDQ format: weights int8 per channel,
activations uint8, MinMax calibration, only ``Conv`` quantized; the three 1x1 prediction convs of each head
level (box, objectness, class) stay fp32 with everything after them, so the decoded boxes and scores keep
their float range.

``onnx`` is needed only here (pip install 'followbus[quantize]'); the INT8 file runs on onnxruntime alone.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import cv2
import numpy as np

from .detectors import letterbox

log = logging.getLogger(__name__)

CALIBRATION_FRAMES = 64
QDQ_MIN_OPSET = 13
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
# The head's last convs: their outputs are the boxes/scores themselves (kept fp32).
HEAD_PREDICTION_PREFIXES = ("head.reg_preds.", "head.obj_preds.", "head.cls_preds.")


def calibration_images(folders: Iterable[Path], count: int = CALIBRATION_FRAMES) -> list[Path]:
    """``count`` images spread evenly over every image below ``folders`` (sorted, so the choice is
    reproducible)."""
    found = sorted(p for f in folders for p in Path(f).rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(found) <= count:
        return found
    step = len(found) / count
    return [found[int(i * step)] for i in range(count)]


def scene_frames(count: int = CALIBRATION_FRAMES) -> Iterator[np.ndarray]:
    """Frames of the built-in synthetic scenes, for a build with no images at hand."""
    from .scenes import SCENES
    from .sources import SceneSource

    names = sorted(SCENES)
    per_scene = max(1, count // len(names))
    for name in names:
        src = SceneSource(name, seed=0)
        for i, frame in enumerate(src):
            if i >= per_scene * 10:
                break
            if i % 10 == 0:
                yield frame.bgr
        src.close()


def _blob(bgr: np.ndarray, input_size: int) -> np.ndarray:
    canvas, _, _ = letterbox(bgr, input_size, centered=False)
    return np.ascontiguousarray(canvas.transpose(2, 0, 1)[None], dtype=np.float32)


class _FrameReader:
    """onnxruntime's CalibrationDataReader protocol over preprocessed frames."""

    def __init__(self, input_name: str, blobs: list[np.ndarray]) -> None:
        self._feeds = iter([{input_name: b} for b in blobs])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def _head_nodes(model_path: Path) -> list[str]:
    """Names of the head's prediction convs (kept fp32)."""
    import onnx

    model = onnx.load(str(model_path))
    return [n.name for n in model.graph.node
            if n.op_type == "Conv" and any(i.startswith(HEAD_PREDICTION_PREFIXES) for i in n.input)]


def _opset13(model_path: Path, tmp: Path) -> Path:
    """The model converted to opset 13 when older (per-channel QDQ needs DequantizeLinear's ``axis``)."""
    import onnx
    from onnx import version_converter

    model = onnx.load(str(model_path))
    opset = next((o.version for o in model.opset_import if o.domain in ("", "ai.onnx")), 13)
    if opset >= QDQ_MIN_OPSET:
        return model_path
    out = tmp / "opset13.onnx"
    onnx.save(version_converter.convert_version(model, QDQ_MIN_OPSET), str(out))
    return out


def quantize_yolox(fp32_model: Path, out_path: Path, frames: Iterable[np.ndarray], input_size: int) -> Path:
    """Write the INT8 (QDQ) model of ``fp32_model`` calibrated on ``frames`` (BGR uint8) to ``out_path``."""
    import onnxruntime as ort
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    blobs = [_blob(f, input_size) for f in frames]
    if not blobs:
        raise ValueError("no calibration frames")
    input_name = ort.InferenceSession(str(fp32_model), providers=["CPUExecutionProvider"]).get_inputs()[0].name
    with tempfile.TemporaryDirectory(prefix="followbus-quant-") as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        quant_pre_process(str(_opset13(fp32_model, Path(tmp))), str(prepared), skip_symbolic_shape=True)
        quantize_static(
            str(prepared), str(out_path), _FrameReader(input_name, blobs),
            quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
            per_channel=True, calibrate_method=CalibrationMethod.MinMax, op_types_to_quantize=["Conv"],
            nodes_to_exclude=_head_nodes(prepared))
    log.info("quantized %s -> %s on %d frames", fp32_model, out_path, len(blobs))
    return out_path


def read_frames(paths: Iterable[Path]) -> Iterator[np.ndarray]:
    for p in paths:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is not None:
            yield bgr
