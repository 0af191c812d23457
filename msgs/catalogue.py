"""Every followbus message type. A program that decodes whatever the bus or a recording carries (record, replay,
introspection) imports this module: a type is decodable once its class is imported (bus/schemas.py registry)."""

from __future__ import annotations

from ..bus.schemas import Message
from .group import GroundPoints, GroupState
from .perception import CameraMotion, Detections, GroundTruth, RegionDetections
from .robot import MotorCommand, Odometry
from .tracking import Measurement, Prior, Template, Track

APPLICATION_TYPES: tuple[type[Message], ...] = (
    GroundTruth, Detections, RegionDetections, CameraMotion, Prior, Measurement, Track, Template, MotorCommand,
    Odometry, GroundPoints, GroupState)
