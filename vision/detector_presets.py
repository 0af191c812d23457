"""Detectors by one name, as `followbus eval --detector` and `followbus bench pipeline --detector` take them.

Each name is a set of the detection node's params (graph.yaml), applied over the graph's own; ``graph`` changes
nothing, so it is the detector the robot runs. Light on purpose (no imports): the CLI's argument tables read it.
"""

from __future__ import annotations

from typing import Any

DETECTOR_PRESETS: dict[str, dict[str, Any]] = {
    "graph": {},
    "yolox": {"backend": "yolox", "input_size_px": 416, "model_file": "", "runtime": "onnxruntime"},
    "yolox512": {"backend": "yolox", "input_size_px": 512, "model_file": "", "runtime": "onnxruntime"},
    "yolox640": {"backend": "yolox", "input_size_px": 640, "model_file": "", "runtime": "onnxruntime"},
    "yolox640-int8": {"backend": "yolox", "input_size_px": 640, "model_file": "yolox_nano_640_int8.onnx",
                      "runtime": "onnxruntime"},
    "yolox416-openvino": {"backend": "yolox", "input_size_px": 416, "model_file": "", "runtime": "openvino"},
    "yolox512-openvino": {"backend": "yolox", "input_size_px": 512, "model_file": "", "runtime": "openvino"},
    "yolox640-openvino": {"backend": "yolox", "input_size_px": 640, "model_file": "", "runtime": "openvino"},
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
    given = {"model_file": "", "runtime": "onnxruntime", "input_size_px": 416, **params}
    if given.get("backend", "auto") == "auto":
        given["backend"] = "yolox"
    for name, preset in DETECTOR_PRESETS.items():
        if name != "graph" and all(given.get(k) == v for k, v in preset.items()):
            return name
    return None
