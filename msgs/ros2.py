"""followbus's messages as the standard ROS 2 messages a ROS 2 user expects (recordings' ROS 2 channels, the ROS 2
node pair), in REP-103 terms, which are followbus's own (control/kinematics.py): x forward, y left, z up, yaw
counter-clockwise. The type store and CDR are the generic bus/ros2.py's.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..bus import ros2
from ..bus.ros2 import message_class as ros_type
from .perception import Detections
from .robot import MotorCommand, Odometry

ODOMETRY = "nav_msgs/msg/Odometry"
ROBOT_FRAME = "base_link"  # REP-105 names
ODOMETRY_FRAME = "odom"
PERSON_CLASS = "person"


def command_twist(msg: MotorCommand) -> Any:
    """The motor command as ``/cmd_vel``: body-frame velocities (m/s, rad/s)."""
    return ros2.twist(msg.vx_mps, msg.vy_mps, msg.wz_radps)


def target_point(msg: MotorCommand) -> Any | None:
    """The followed target as a point in the robot frame (from the command's range and bearing), None without one."""
    if msg.range_m is None or msg.bearing_rad is None or not math.isfinite(msg.range_m * msg.bearing_rad):
        return None
    point = ros_type("geometry_msgs/msg/Point")(x=msg.range_m * math.cos(msg.bearing_rad),
                                                y=msg.range_m * math.sin(msg.bearing_rad), z=0.0)
    return ros_type(ros2.POINT_STAMPED)(header=ros2.header(msg.header.stamp_ns, ROBOT_FRAME), point=point)


def odometry(msg: Odometry) -> Any:
    """nav_msgs/Odometry: the pose in ``odom``, the body-frame velocities in ``base_link`` (covariances unknown: 0)."""
    g = "geometry_msgs/msg/"
    half = 0.5 * msg.theta_rad
    quat = ros_type(g + "Quaternion")(x=0.0, y=0.0, z=math.sin(half), w=math.cos(half))
    pose = ros_type(g + "Pose")(position=ros_type(g + "Point")(x=msg.x_m, y=msg.y_m, z=0.0), orientation=quat)
    zero = np.zeros(36, np.float64)
    return ros_type(ODOMETRY)(
        header=ros2.header(msg.header.stamp_ns, ODOMETRY_FRAME), child_frame_id=ROBOT_FRAME,
        pose=ros_type(g + "PoseWithCovariance")(pose=pose, covariance=zero),
        twist=ros_type(g + "TwistWithCovariance")(twist=ros2.twist(msg.vx_mps, msg.vy_mps, msg.wz_radps),
                                                  covariance=zero.copy()))


def _detection(hdr: Any, row: np.ndarray) -> Any:
    v = "vision_msgs/msg/"
    x, y, w, h = (float(c) for c in row[:4])
    score = float(row[4]) if row.shape[0] > 4 else 1.0
    centre = ros_type(v + "Pose2D")(position=ros_type(v + "Point2D")(x=x + w / 2, y=y + h / 2), theta=0.0)
    g = "geometry_msgs/msg/"
    no_pose = ros_type(g + "PoseWithCovariance")(
        pose=ros_type(g + "Pose")(position=ros_type(g + "Point")(x=0.0, y=0.0, z=0.0),
                                  orientation=ros_type(g + "Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0)),
        covariance=np.zeros(36, np.float64))
    result = ros_type(v + "ObjectHypothesisWithPose")(
        hypothesis=ros_type(v + "ObjectHypothesis")(class_id=PERSON_CLASS, score=score), pose=no_pose)
    bbox = ros_type(v + "BoundingBox2D")(center=centre, size_x=w, size_y=h)
    return ros_type(v + "Detection2D")(header=hdr, results=[result], bbox=bbox, id="")


def detections(msg: Detections, frame_id: str) -> Any:
    """vision_msgs/Detection2DArray: each box's centre and size in pixels, class ``person`` with its score."""
    hdr = ros2.header(msg.header.stamp_ns, frame_id)
    boxes = np.asarray(msg.boxes, dtype=np.float64)
    rows = boxes if boxes.ndim == 2 and boxes.shape[1] >= 4 else np.zeros((0, 5))
    return ros_type(ros2.DETECTION_2D_ARRAY)(header=hdr, detections=[
        _detection(hdr, row) for row in rows if np.all(np.isfinite(row[:4]))])
