"""Detectors by one name, as `followbus eval --detector` and `followbus bench pipeline --detector` take them.

Each name is a set of the detection node's params (graph.yaml), applied over the graph's own; ``graph`` changes
nothing, so it is the detector the robot runs. Light on purpose (no imports): the CLI's argument tables read it.
"""

from __future__ import annotations

from typing import Any


def _yolox(size_px: int, *, runtime: str = "onnxruntime", shape: str = "square", model_file: str = "") -> dict:
    return {"backend": "yolox", "input_size_px": size_px, "model_file": model_file, "runtime": runtime,
            "input_shape": shape}


DETECTOR_PRESETS: dict[str, dict[str, Any]] = {
    "graph": {},
    "yolox": _yolox(416),
    "yolox416-fit": _yolox(416, shape="fit"),  # the frame's aspect, padded to 32 (4:3: 416x320)
    "yolox512": _yolox(512),
    "yolox512-fit": _yolox(512, shape="fit"),  # 4:3: 512x384, 14 % more inference than 416x416
    "yolox640": _yolox(640),
    "yolox640-fit": _yolox(640, shape="fit"),
    "yolox640-int8": _yolox(640, model_file="yolox_nano_640_int8.onnx"),
    "yolox416-openvino": _yolox(416, runtime="openvino"),
    "yolox512-openvino": _yolox(512, runtime="openvino"),
    "yolox640-openvino": _yolox(640, runtime="openvino"),
    "hog": {"backend": "hog"},
    "simulated": {"backend": "simulated"},
}


def apply_detector_preset(params: dict[str, Any], name: str) -> dict[str, Any]:
    """The detection node's ``params`` switched to the detector ``name`` (a key of :data:`DETECTOR_PRESETS`)."""
    if name not in DETECTOR_PRESETS:
        raise ValueError(f"unknown detector {name!r}; choose one of {', '.join(DETECTOR_PRESETS)}")
    params.update(DETECTOR_PRESETS[name])
    return params


def preset_of(params: dict[str, Any]) -> str | None:
    """The preset name (other than ``graph``) that these detection params amount to, or None."""
    # the node's defaults; backend auto is YOLOX
    given = {"model_file": "", "runtime": "onnxruntime", "input_size_px": 416, "input_shape": "square", **params}
    if given.get("backend", "auto") == "auto":
        given["backend"] = "yolox"
    for name, preset in DETECTOR_PRESETS.items():
        if name != "graph" and all(given.get(k) == v for k, v in preset.items()):
            return name
    return None
