"""groundplane: each frame's person detections → points on the floor, robot frame and odometry frame.

Range from the box's foot row with the documented camera height and tilt (or from the box width, seed 001
Eq. 1), bearing from the box centre and the focal length, a covariance per point
(:mod:`followbus.tracking.groundplane`). Seed 004 Eq. 4 moves them into the fixed odometry frame with the
robot pose of the newest odometry sample stamped at or before the frame's capture (an input sampled by stamp:
never "whatever arrived last", and the runtime notes the choice, so a live run and its lockstep replay use the same
pose). Before any odometry the robot is at the odometry origin, where motor starts it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.schemas import Message
from ..msgs.group import GroundPoints
from ..msgs.perception import Detections
from ..msgs.robot import Odometry
from ..tracking.groundplane import CameraGeometry, GroundPlaneParams, boxes_to_ground


class GroundPlane(Node):
    INPUTS = {"detections": In(Detections, required=True), "odometry": In(Odometry, sample_by_stamp=True)}
    OUTPUTS = {"points": Out(GroundPoints)}
    Params = (GroundPlaneParams, CameraGeometry)

    def setup(self) -> None:
        self.plane, self.camera = self.params
        self.frames = 0
        self.points = 0
        self.dropped_boxes = 0  # above the horizon, feet cut off, too weak, too far, not finite
        self.without_odometry = 0

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        dets = inputs["detections"]
        assert isinstance(dets, Detections)
        odom = inputs["odometry"]
        assert odom is None or isinstance(odom, Odometry)
        if odom is None:
            self.without_odometry += 1
        pose = (odom.x_m, odom.y_m, odom.theta_rad) if odom is not None else (0.0, 0.0, 0.0)
        ground = boxes_to_ground(dets.boxes, self.camera, self.plane, pose)  # seed 004 Eq. 4 at this pose
        ground.odometry_stamp_ns = -1 if odom is None else odom.header.stamp_ns
        self.frames += 1
        self.points += len(ground.points_m)
        self.dropped_boxes += len(np.asarray(dets.boxes).reshape(-1, 5)) - len(ground.points_m)
        self.publish("points", ground)

    def status(self) -> dict[str, Any]:
        return {"frames": self.frames, "points": self.points, "dropped_boxes": self.dropped_boxes,
                "without_odometry": self.without_odometry}


NODE = GroundPlane
