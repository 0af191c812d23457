"""Detectors: YOLOX on a real frame, letterbox geometry, YOLOv8 decode, NMS, HOG, factory, search path."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.vision.detectors import (
    Detector,
    DetectorUnavailable,
    HogDetector,
    SimulatedDetector,
    YoloxDetector,
    best_iou,
    decode_yolox,
    letterbox,
    make_detector,
    nms,
    unletterbox_boxes,
    yolov8_postprocess,
)
from followbus.vision.models import MODELS_ENV, REPO_ROOT, find_model, search_path
from followbus.vision.scenes import make_scene

DATA_ROOT = Path(os.environ.get("FOLLOWBUS_DATA", REPO_ROOT.parent / "shared" / "data"))
YOLOX_416 = "yolox_nano_416.onnx"


def _yolox_path() -> Path:
    path = find_model(YOLOX_416)
    # Shipped in models/ (tests/test_models.py checks the files): missing is a broken checkout, not a skip.
    assert path is not None, f"{YOLOX_416} not on the model search path ({', '.join(map(str, search_path()))})"
    return path


def _models_dir() -> Path:
    return _yolox_path().parent


# ----------------------------------------------------------------------------- YOLOX


def test_yolox_detects_person_on_real_frame() -> None:
    model = _yolox_path()
    seq = DATA_ROOT / "sot" / "otb-crossing"
    img_path = seq / "img" / "000001.jpg"
    if not img_path.is_file():
        pytest.skip(f"real data absent: {img_path} (set FOLLOWBUS_DATA)")
    gt = [float(v) for v in (seq / "groundtruth.txt").read_text().splitlines()[0].split(",")]
    bgr = cv2.imread(str(img_path))
    det = YoloxDetector(model)
    assert det.input_size == 416  # read from the model's input shape
    dets = det.detect(bgr)
    assert dets.dtype == np.float32 and dets.ndim == 2 and dets.shape[1] == 5
    assert best_iou(dets, gt) > 0.5, f"no person box near gt {gt}: {dets}"
    assert det.last_infer_ms > 0
    # Boxes are clipped to the image.
    assert np.all(dets[:, 0] >= 0) and np.all(dets[:, 0] + dets[:, 2] <= bgr.shape[1] + 1e-3)


def test_yolox_decode_grid_and_stride() -> None:
    size = 416
    n_anchors = sum((size // s) ** 2 for s in (8, 16, 32))
    raw = np.zeros((1, n_anchors, 85), np.float32)
    # Stride-16 level starts after the 52x52 stride-8 grid; pick cell (x=5, y=3) on it.
    a = 52 * 52 + 3 * 26 + 5
    raw[0, a, :4] = (0.5, 0.25, np.log(2.0), np.log(4.0))
    raw[0, a, 4] = 0.9  # objectness
    raw[0, a, 5] = 0.8  # person
    raw[0, a + 1, 4:7] = (0.9, 0.05, 0.95)  # a confident non-person: must not come out
    out = decode_yolox(raw, size, score_threshold=0.3)
    assert out.shape == (1, 5)
    cx, cy, w, h = (5 + 0.5) * 16, (3 + 0.25) * 16, 2.0 * 16, 4.0 * 16
    np.testing.assert_allclose(out[0], [cx - w / 2, cy - h / 2, w, h, 0.72], rtol=1e-5)


# ----------------------------------------------------------------------------- letterbox


@pytest.mark.parametrize("centered", [False, True])
def test_letterbox_maps_boxes_back(centered: bool) -> None:
    img = np.zeros((240, 360, 3), np.uint8)
    box = (100.0, 60.0, 40.0, 120.0)
    cv2.rectangle(img, (100, 60), (139, 179), (255, 255, 255), -1)
    canvas, ratio, pad = letterbox(img, 416, centered=centered)
    assert canvas.shape == (416, 416, 3)
    assert ratio == pytest.approx(416 / 360)
    if centered:
        assert pad[0] == 0 and pad[1] > 0  # padding split top/bottom like ultralytics
    else:
        assert pad == (0.0, 0.0)
        assert np.all(canvas[-10:, :, :] == 114)  # YOLOX pads bottom/right only
    # The white block in the canvas is where the forward mapping says it is...
    ys, xs = np.nonzero(canvas[:, :, 0] > 128)
    found = np.array([[xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]], np.float32)
    expected = [box[0] * ratio + pad[0], box[1] * ratio + pad[1], box[2] * ratio, box[3] * ratio]
    np.testing.assert_allclose(found[0], expected, atol=2.0)
    # ...and mapping it back recovers the original box.
    np.testing.assert_allclose(unletterbox_boxes(found, ratio, pad)[0], box, atol=2.0)


# ----------------------------------------------------------------------------- YOLOv8 decode + NMS


def test_yolov8_decode_hand_made_tensor() -> None:
    image_shape = (480, 640, 3)
    _, ratio, pad = letterbox(np.zeros(image_shape, np.uint8), 640, centered=True)
    assert pad == (0.0, 80.0) and ratio == 1.0
    raw = np.zeros((1, 84, 5), np.float32)
    # anchor 0: person at input-pixel centre (320, 300), 60x180 -> image (290, 130, 60, 180)
    raw[0, :4, 0] = (320, 300, 60, 180)
    raw[0, 4, 0] = 0.9
    # anchor 1: near-duplicate of 0 with a lower score: NMS must drop it
    raw[0, :4, 1] = (322, 302, 60, 176)
    raw[0, 4, 1] = 0.7
    # anchor 2: a confident car, weak person: filtered by the person score
    raw[0, :4, 2] = (100, 200, 80, 40)
    raw[0, 4, 2], raw[0, 6, 2] = 0.05, 0.95
    # anchor 3: second person, partly outside the image at the left: clipped
    raw[0, :4, 3] = (10, 320, 40, 100)
    raw[0, 4, 3] = 0.6
    dets = yolov8_postprocess(raw, ratio, pad, image_shape, score_threshold=0.3, nms_iou=0.45)
    assert dets.shape == (2, 5)
    np.testing.assert_allclose(dets[0], [290, 130, 60, 180, 0.9], atol=1e-4)
    np.testing.assert_allclose(dets[1], [0, 190, 30, 100, 0.6], atol=1e-4)


def test_nms_removes_duplicate() -> None:
    dets = np.array([[10, 10, 50, 100, 0.8], [12, 11, 50, 100, 0.9], [200, 50, 40, 90, 0.5]], np.float32)
    kept = nms(dets, iou_threshold=0.45)
    assert kept.shape == (2, 5)
    np.testing.assert_allclose(kept[:, 4], [0.9, 0.5])
    assert nms(np.zeros((0, 5), np.float32), 0.45).shape == (0, 5)


# ----------------------------------------------------------------------------- HOG


def test_hog_returns_n_by_5_and_finds_synthetic_walker() -> None:
    frame = next(iter(make_scene("wall-occlusion").frames()))  # target fully visible, 220 px tall
    hog = HogDetector()
    dets = hog.detect(frame.bgr)
    assert isinstance(hog, Detector)
    assert dets.dtype == np.float32 and dets.ndim == 2 and dets.shape[1] == 5
    assert np.all((dets[:, 4] >= 0) & (dets[:, 4] <= 1))
    assert best_iou(dets, frame.target_box) > 0.3
    assert hog.detect(np.zeros((120, 160, 3), np.uint8)).shape == (0, 5)


# ----------------------------------------------------------------------------- factory / search path


def test_make_detector_auto_picks_yolox_when_model_found(caplog: pytest.LogCaptureFixture) -> None:
    models = _models_dir()
    with caplog.at_level(logging.INFO, logger="followbus.vision.detectors"):
        det = make_detector("auto", model_dir=str(models))
    assert isinstance(det, YoloxDetector)
    assert any("auto -> yolox" in r.getMessage() for r in caplog.records)


def test_make_detector_explicit_backends_without_model_raise(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # `auto` without a model is an error too (tests/test_models.py); here the explicit backends.
    monkeypatch.chdir(tmp_path)  # cwd/../shared/models must not rescue it...
    monkeypatch.setattr("followbus.vision.models.REPO_ROOT", tmp_path / "repo")  # ...nor the repo's
    monkeypatch.delenv(MODELS_ENV, raising=False)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DetectorUnavailable) as err:
        make_detector("yolox", model_dir=str(empty))
    assert str(empty) in str(err.value) and err.value.search_path[0] == empty.resolve()
    with pytest.raises(DetectorUnavailable):
        make_detector("yolov8", model_dir=str(empty))
    with pytest.raises(ValueError):
        make_detector("resnet")


def test_find_model_honours_env_and_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    a, b, explicit = tmp_path / "a", tmp_path / "b", tmp_path / "explicit"
    for d in (a, b, explicit):
        d.mkdir()
    (b / "m.onnx").write_bytes(b"x")
    monkeypatch.setenv(MODELS_ENV, os.pathsep.join([str(a), str(b)]))
    assert find_model("m.onnx") == b.resolve() / "m.onnx"
    path = search_path(str(explicit))
    assert path[:3] == [explicit.resolve(), a.resolve(), b.resolve()]
    resolved = [p.resolve() for p in path]  # ../shared may be a link (a CI checkout's, say)
    assert (REPO_ROOT / "models").resolve() in resolved
    assert (REPO_ROOT.parent / "shared" / "models").resolve() in resolved
    (explicit / "m.onnx").write_bytes(b"y")
    assert find_model("m.onnx", str(explicit)) == explicit.resolve() / "m.onnx"  # explicit dir wins
    assert find_model("m.onnx", str(b / "m.onnx")) == (b / "m.onnx").resolve()  # explicit file
    assert find_model("followbus-no-such-model.onnx", str(explicit)) is None
    monkeypatch.delenv(MODELS_ENV)
    assert find_model("m.onnx") is None  # only the environment pointed at a/ and b/


# ----------------------------------------------------------------------------- simulated


def test_simulated_detector_noise_model_and_determinism() -> None:
    img = np.zeros((480, 640, 3), np.uint8)
    truth = [((100.0, 100.0, 60.0, 160.0), 1.0), ((400.0, 120.0, 50.0, 140.0), 0.2), (None, 0.0)]

    def run(seed: int) -> list[np.ndarray]:
        det = make_detector("simulated", noise_px=3.0, miss_rate=0.1, false_positive_rate=0.0, seed=seed)
        return [det.detect(img, truth) for _ in range(200)]

    a, b = run(1), run(1)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    n = np.array([len(d) for d in a])
    assert n.max() == 1  # the 20 %-visible person is never detected
    assert 0.8 < n.mean() < 0.97  # about 10 % misses
    kept = np.concatenate(a)
    centres = kept[:, :2] + kept[:, 2:4] / 2
    assert np.std(centres[:, 0]) == pytest.approx(3.0, rel=0.25)
    assert abs(np.mean(centres[:, 0]) - 130.0) < 1.0
    sim = SimulatedDetector(false_positive_rate=2.0, seed=0)
    sim.set_truth([])
    assert sum(len(sim.detect(img)) for _ in range(50)) > 50  # false positives appear
    assert "not a detection accuracy" in sim.name


# ----------------------------------------------------------------------------- runtimes, presets, INT8


def _street_frame() -> np.ndarray:
    for k, frame in enumerate(make_scene("lookalike", seed=0).frames()):
        if k == 30:  # the target and its look-alike both in view
            return frame.bgr
    raise AssertionError("scene too short")


@pytest.mark.slow
def test_openvino_runtime_gives_the_onnxruntime_boxes() -> None:
    pytest.importorskip("openvino", reason="openvino not installed (pip install openvino)")
    bgr = _street_frame()
    ort = make_detector("yolox", model_dir=str(_models_dir()), threads=1)
    ov = make_detector("yolox", model_dir=str(_models_dir()), threads=1, runtime="openvino")
    a, b = ort.detect(bgr), ov.detect(bgr)
    assert ov.name.endswith("(openvino)") and len(a) == len(b) >= 2
    np.testing.assert_allclose(b[:, :4], a[:, :4], atol=1.0)  # float kernels differ in the last digits only
    np.testing.assert_allclose(b[:, 4], a[:, 4], atol=0.01)


def test_unknown_runtime_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown runtime 'tensorrt'; choose one of onnxruntime, openvino"):
        make_detector("yolox", runtime="tensorrt")


@pytest.mark.slow
def test_int8_and_512_models_find_the_people_the_640_model_finds() -> None:
    bgr = _street_frame()
    ref = make_detector("yolox", input_size=640, threads=1).detect(bgr)
    for kwargs in ({"input_size": 640, "model_file": "yolox_nano_640_int8.onnx"}, {"input_size": 512}):
        dets = make_detector("yolox", threads=1, **kwargs).detect(bgr)
        assert len(ref) >= 2 and all(best_iou(dets, r[:4]) > 0.7 for r in ref if r[4] >= 0.5), (kwargs, dets, ref)


def test_presets_name_what_graph_params_amount_to() -> None:
    from followbus.vision.detector_presets import DETECTOR_PRESETS, apply_detector_preset, preset_of

    graph_like = {"backend": "auto", "input_size_px": 416, "threads": 1}
    assert preset_of(graph_like) == "yolox"
    assert apply_detector_preset(dict(graph_like), "graph") == graph_like
    for name in DETECTOR_PRESETS:
        if name != "graph":
            assert preset_of(apply_detector_preset(dict(graph_like), name)) == name
    with pytest.raises(ValueError, match="unknown detector 'yolo9'"):
        apply_detector_preset({}, "yolo9")


# ----------------------------------------------------------------------------- input_shape: fit


def test_letterbox_with_stride_pads_to_the_stride_not_to_a_square() -> None:
    canvas, ratio, pad = letterbox(np.zeros((480, 640, 3), np.uint8), 416, stride=32)
    assert canvas.shape == (320, 416, 3) and ratio == pytest.approx(0.65) and pad == (0.0, 0.0)
    assert np.all(canvas[312:] == 114)  # 480 * 0.65 = 312 rows of image, 8 of padding
    assert letterbox(np.zeros((720, 1280, 3), np.uint8), 640, stride=32)[0].shape == (384, 640, 3)
    assert letterbox(np.zeros((640, 480, 3), np.uint8), 416, stride=32)[0].shape == (416, 320, 3)  # portrait


def test_yolox_decode_of_a_rectangular_input() -> None:
    height, width = 320, 416
    n_anchors = sum((height // s) * (width // s) for s in (8, 16, 32))
    assert n_anchors == 2730
    raw = np.zeros((1, n_anchors, 85), np.float32)
    a = 40 * 52 + 3 * 26 + 5  # the stride-16 level starts after the 40x52 stride-8 grid; cell (x=5, y=3)
    raw[0, a, :4] = (0.5, 0.25, np.log(2.0), np.log(4.0))
    raw[0, a, 4:6] = (0.9, 0.8)
    out = decode_yolox(raw, (height, width), score_threshold=0.3)
    cx, cy, w, h = (5 + 0.5) * 16, (3 + 0.25) * 16, 2.0 * 16, 4.0 * 16
    np.testing.assert_allclose(out[0], [cx - w / 2, cy - h / 2, w, h, 0.72], rtol=1e-5)
    with pytest.raises(ValueError, match="anchors"):
        decode_yolox(raw, 416)


@pytest.mark.slow
def test_fit_input_finds_the_square_inputs_people_with_less_work() -> None:
    bgr = _street_frame()  # 640x480
    square = make_detector("yolox", threads=1)
    fit = make_detector("yolox", threads=1, input_shape="fit")
    assert fit.name == "yolox:yolox_nano_dynamic.onnx@416 fit"
    assert fit.preprocess(bgr)[0].shape == (1, 3, 320, 416)
    ref, dets = square.detect(bgr), fit.detect(bgr)
    assert len(ref) >= 2 and all(best_iou(dets, r[:4]) > 0.9 for r in ref if r[4] >= 0.5), (dets, ref)
    # The dynamic model is the 640 file's weights: square inputs give that file's raw output exactly.
    blob = square.preprocess(bgr)[0]
    np.testing.assert_array_equal(fit._infer(blob), square._infer(blob))


def test_fit_needs_a_model_that_takes_any_shape() -> None:
    with pytest.raises(DetectorUnavailable, match="input_shape 'fit' needs a model that takes any height and width"):
        make_detector("yolox", input_shape="fit", model_file=YOLOX_416)


def test_detection_node_refuses_an_unknown_input_shape() -> None:
    from followbus.bus.node_params import ParamError
    from followbus.nodes.detection import detection_params

    assert detection_params({"input_shape": "fit"}).input_shape == "fit"
    for raw in ({"input_shape": "round"}, {"backend": "yolov8", "input_shape": "fit"}):
        with pytest.raises(ParamError, match="input_shape must be one of square, fit"):
            detection_params(raw)
