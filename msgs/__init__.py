"""followbus's messages: the application's own types, one module per concern, each class with its own checks.

The bus (bus/) is generic: it carries any :class:`~followbus.bus.schemas.Message` subclass and knows no
tracking word. This package is followbus's interface package (as ROS 2 keeps messages in interface packages
beside a type-agnostic rclpy): the algorithms (tracking/, control/) read and write these types themselves, the
nodes publish them. Importing it registers every type with the bus's codec, so a program that reads recordings
or the live bus imports it once (tools/cli.py does).

Layering: bus/ ← msgs/ ← tracking/, control/, vision/ ← nodes/ ← tools/.

"Seed NNN" names a method paper (glossary: tracking/__init__.py).
"""

from __future__ import annotations

from . import catalogue  # noqa: F401  (every type registered on import)
from .box import Box
from .group import GroundPoints, GroupState
from .perception import CameraMotion, Detections, GroundTruth, RegionDetections
from .robot import MotorCommand, Odometry
from .tracking import TRACK_STATES, Measurement, Prior, Template, Track, TrackState

__all__ = ["TRACK_STATES", "Box", "CameraMotion", "Detections", "GroundPoints", "GroundTruth", "GroupState",
           "Measurement", "MotorCommand", "Odometry", "Prior", "RegionDetections", "Template", "Track", "TrackState"]
