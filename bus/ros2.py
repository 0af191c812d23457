"""ROS 2 messages: the one CDR home of followbus (recordings' ROS 2 channels, the ROS 2 node pair).

Types, CDR (de)serialisation, ``ros2msg`` schema texts and RIHS01 type hashes all come from ``rosbags``' type
store (ROS 2 Jazzy definitions); ``vision_msgs`` 4.1.1 (the Humble/Jazzy release, ros-perception/vision_msgs tag
4.1.1), which rosbags does not ship, is registered below from its .msg definitions. Nothing here writes CDR by
hand. This module is generic (the type store, CDR, headers, images); the mapping of followbus's own messages to
ROS 2 types lives with the messages (msgs/ros2.py).
"""

from __future__ import annotations

from functools import cache, lru_cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from .schemas import Frame

TWIST = "geometry_msgs/msg/Twist"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
DETECTION_2D_ARRAY = "vision_msgs/msg/Detection2DArray"


# vision_msgs 4.1.1 (Apache-2.0), comments left out; dependencies before the types that use them.
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "ObjectHypothesis hypothesis\n"
                                                "geometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/Detection2D": "std_msgs/Header header\nObjectHypothesisWithPose[] results\n"
                                   "BoundingBox2D bbox\nstring id\n",
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nDetection2D[] detections\n",
}


@lru_cache(maxsize=1)
def typestore() -> Any:
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in VISION_MSGS.items():
        store.register(get_types_from_msg(text, name))
    return store


def message_class(type_name: str) -> Any:
    return typestore().types[type_name]


def serialize(msg: Any, type_name: str) -> bytes:
    """CDR (little-endian, with its 4-byte encapsulation header), as rmw and rosbag2 store it."""
    return bytes(typestore().serialize_cdr(msg, type_name))


def deserialize(data: bytes | memoryview, type_name: str) -> Any:
    return typestore().deserialize_cdr(data, type_name)


@cache
def msgdef(type_name: str) -> str:
    """The ``ros2msg`` schema text (the type and its dependencies, ``MSG:``-separated) MCAP readers decode by."""
    return typestore().generate_msgdef(type_name, ros_version=2)[0]


@cache
def type_hash(type_name: str) -> str:
    """REP-2016 type hash, ``RIHS01_<sha256 hex>``, as rosidl generates it (rmw_zenoh puts it in its keys)."""
    return typestore().hash_rihs01(type_name)


def dds_type_name(type_name: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_`` (the name rmw_zenoh keys carry)."""
    package, kind, name = type_name.split("/")
    return f"{package}::{kind}::dds_::{name}_"


# --- builders --------------------------------------------------------------------------------------

def header(stamp_ns: int, frame_id: str) -> Any:
    time_cls, header_cls = message_class("builtin_interfaces/msg/Time"), message_class("std_msgs/msg/Header")
    stamp_ns = max(0, int(stamp_ns))
    return header_cls(stamp=time_cls(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
                      frame_id=frame_id)


def stamp_ns(ros_header: Any) -> int:
    return int(ros_header.stamp.sec) * 1_000_000_000 + int(ros_header.stamp.nanosec)


def _vector3(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
    return message_class("geometry_msgs/msg/Vector3")(x=float(x), y=float(y), z=float(z))


def twist(vx_mps: float, vy_mps: float, wz_radps: float) -> Any:
    return message_class(TWIST)(linear=_vector3(vx_mps, vy_mps), angular=_vector3(z=wz_radps))


def compressed_image(stamp: int, frame_id: str, jpeg: bytes) -> Any:
    return message_class(COMPRESSED_IMAGE)(header=header(stamp, frame_id), format="jpeg",
                                           data=np.frombuffer(jpeg, np.uint8))


def image(frame: Frame, frame_id: str) -> Any:
    """A bgr8 frame as sensor_msgs/Image (the pixels as they are: step = width * 3)."""
    data = np.ascontiguousarray(frame.data, np.uint8)
    height, width = data.shape[:2]
    return message_class(IMAGE)(header=header(frame.header.stamp_ns, frame_id), height=height, width=width,
                                encoding="bgr8", is_bigendian=0, step=width * 3, data=data.reshape(-1))


def image_pixels(msg: Any) -> np.ndarray:
    """A sensor_msgs/Image (bgr8 / rgb8 / mono8, any step) as a BGR array; ValueError for other encodings."""
    channels = {"bgr8": 3, "rgb8": 3, "mono8": 1}.get(msg.encoding)
    if channels is None:
        raise ValueError(f"image encoding {msg.encoding!r}: bgr8, rgb8 or mono8 expected")
    if msg.step < msg.width * channels or len(msg.data) < msg.step * msg.height:
        raise ValueError(f"image of {msg.width}x{msg.height} with step {msg.step} and {len(msg.data)} bytes")
    rows = np.asarray(msg.data, np.uint8)[: msg.step * msg.height].reshape(msg.height, msg.step)
    pixels = rows[:, : msg.width * channels].reshape(msg.height, msg.width, channels)
    if msg.encoding == "rgb8":
        return np.ascontiguousarray(pixels[:, :, ::-1])
    if channels == 1:
        return np.repeat(pixels, 3, axis=2)
    return np.ascontiguousarray(pixels)
