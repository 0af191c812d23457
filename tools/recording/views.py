"""The views a recording stores beside each bus message, so every message decodes without followbus.

A bus channel keeps the followbus frame losslessly (``msgpack``, [head, blob area]: what replay and play use,
bit-exact). Beside it, per bus key:

- ``<key>/image``: a Frame as ``sensor_msgs/msg/CompressedImage`` (JPEG; a jpeg Frame's own bytes), or with
  ``raw_images`` a bgr8 Frame as ``sensor_msgs/msg/Image`` (lossless, as many bytes again as the frame);
- ``<key>/twist`` (MotorCommand, ``geometry_msgs/msg/Twist``), ``<key>/odometry`` (``nav_msgs/msg/Odometry``),
  ``<key>/detections2d`` (Detections, ``vision_msgs/msg/Detection2DArray``): ROS 2 CDR with ``ros2msg``
  schemas, readable by Foxglove, ``mcap-ros2-support``, rosbags and ``ros2 bag`` (bus/ros2.py encodes);
- ``<key>/json``: every field of every other message (and of MotorCommand, Odometry, Detections too, for what
  the standard message has no field for), JSON with a JSON Schema (``jsonschema``) built from the type;
- ``<key>/annotations``: Foxglove ImageAnnotations of Detections, Prior and Track (foxglove_schemas.py).
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from dataclasses import dataclass
from functools import cache
from typing import Any

import cv2
import numpy as np

from ...bus import ros2
from ...bus.schemas import SCHEMAS, Frame, Message
from ...msgs import ros2 as msgs_ros2
from ...msgs.perception import Detections
from ...msgs.robot import MotorCommand, Odometry
from . import foxglove_schemas as fox

ROS2_SCHEMA_ENCODING = "ros2msg"
ROS2_MESSAGE_ENCODING = "cdr"
JSON_SCHEMA_PREFIX = "followbus.json."


@dataclass(frozen=True)
class ViewSchema:
    name: str
    encoding: str  # schema encoding
    data: bytes
    message_encoding: str


@dataclass
class View:
    topic: str
    schema: ViewSchema
    payload: bytes


@cache
def ros2_schema(type_name: str) -> ViewSchema:
    return ViewSchema(type_name, ROS2_SCHEMA_ENCODING, ros2.msgdef(type_name).encode(), ROS2_MESSAGE_ENCODING)


@cache
def foxglove_schema(name: str) -> ViewSchema:
    return ViewSchema(name, fox.SCHEMA_ENCODING, fox.schema_bytes(name), fox.MESSAGE_ENCODING)


# --- JSON views --------------------------------------------------------------------------------------

_NUMBER = {"type": ["number", "null"]}  # null: a non-finite float (JSON has no NaN)
_DEFS = {"ndarray": {"description": "a numpy array as nested lists",
                     "type": "array", "items": {"anyOf": [_NUMBER, {"$ref": "#/$defs/ndarray"}]}}}


def _json_type(hint: Any) -> dict[str, Any]:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Union or type(hint).__name__ == "UnionType":
        options = [_json_type(a) for a in args if a is not type(None)]
        return {"anyOf": [*options, {"type": "null"}]} if type(None) in args else {"anyOf": options}
    if origin is list:
        return {"type": "array", "items": _json_type(args[0]) if args else {}}
    if origin is dict:
        return {"type": "object"}
    if dataclasses.is_dataclass(hint):
        return _object_schema(hint)
    simple = {int: {"type": "integer"}, float: _NUMBER, bool: {"type": "boolean"}, str: {"type": "string"}}
    if hint in simple:
        return simple[hint]
    return {"$ref": "#/$defs/ndarray"} if getattr(hint, "__name__", "") == "ndarray" else {}


def _object_schema(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    return {"type": "object", "properties": {n: _json_type(hints[n]) for n in names}, "required": names}


@cache
def json_schema(type_name: str) -> ViewSchema:
    """A JSON Schema of a bus message type, from its fields' annotations (bus/schemas.py)."""
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": JSON_SCHEMA_PREFIX + type_name,
              "description": f"followbus {type_name}: every field of the bus message", "$defs": _DEFS,
              **_object_schema(SCHEMAS[type_name])}
    return ViewSchema(JSON_SCHEMA_PREFIX + type_name, fox.SCHEMA_ENCODING, json.dumps(schema).encode(), "json")


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "iub" or (value.dtype.kind == "f" and np.isfinite(value).all()):
            return value.tolist()  # the common case, without a Python step per element
        value = value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return value


@cache
def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def json_view(msg: Message) -> bytes:
    return json.dumps({name: _plain(getattr(msg, name)) for name in _field_names(type(msg))},
                      allow_nan=False, separators=(",", ":")).encode()


# --- per message ---------------------------------------------------------------------------------------

def _cdr(topic: str, msg: Any, type_name: str) -> View:
    return View(topic, ros2_schema(type_name), ros2.serialize(msg, type_name))


def frame_views(key: str, frame: Frame, stamp_ns: int, jpeg_quality: int, raw_images: bool) -> list[View]:
    if raw_images and frame.encoding == "bgr8" and frame.data.size:
        return [_cdr(f"{key}/image", ros2.image(frame, key), ros2.IMAGE)]
    jpeg = _jpeg(frame, jpeg_quality)
    if jpeg is None:
        return []
    return [_cdr(f"{key}/image", ros2.compressed_image(stamp_ns, key, jpeg), ros2.COMPRESSED_IMAGE)]


def _jpeg(frame: Frame, quality: int) -> bytes | None:
    if frame.encoding == "jpeg":
        return np.asarray(frame.data, np.uint8).tobytes()
    if frame.encoding == "bgr8" and frame.data.size:
        ok, buf = cv2.imencode(".jpg", frame.data, [cv2.IMWRITE_JPEG_QUALITY, quality])
        return buf.tobytes() if ok else None
    return None


def standard_view(key: str, msg: Message) -> View | None:
    """The ROS 2 standard message of a bus message, where one exists."""
    if isinstance(msg, MotorCommand):
        return _cdr(f"{key}/twist", msgs_ros2.command_twist(msg), ros2.TWIST)
    if isinstance(msg, Odometry):
        return _cdr(f"{key}/odometry", msgs_ros2.odometry(msg), msgs_ros2.ODOMETRY)
    if isinstance(msg, Detections):
        return _cdr(f"{key}/detections2d", msgs_ros2.detections(msg, key), ros2.DETECTION_2D_ARRAY)
    return None


def message_views(key: str, msg: Message, stamp_ns: int, jpeg_quality: int = 80,
                  raw_images: bool = False) -> list[View]:
    """Every view of one decoded bus message (see the module doc)."""
    if isinstance(msg, Frame):
        return frame_views(key, msg, stamp_ns, jpeg_quality, raw_images)
    views = [View(f"{key}/json", json_schema(msg.TYPE), json_view(msg))]
    standard = standard_view(key, msg)
    if standard is not None:
        views.append(standard)
    annotate = fox.ANNOTATORS.get(msg.TYPE)
    if annotate is not None:
        views.append(View(f"{key}/annotations", foxglove_schema(fox.IMAGE_ANNOTATIONS), annotate(msg)))
    return views
