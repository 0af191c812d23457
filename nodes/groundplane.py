"""groundplane: each frame's person detections → points on the floor, robot frame and odometry frame.

Range from the box's foot row with the documented camera height and tilt (or from the box width, seed 001
Eq. 1), bearing from the box centre and the focal length, a covariance per point
(:mod:`followbus.tracking.groundplane`). Seed 004 Eq. 4 moves them into the fixed odometry frame with the
robot pose of the newest odometry sample stamped at or before the frame's capture (never "whatever arrived
last", so a live run and its lockstep replay use the same pose; the choice is noted for the replay, as
prediction does). Before any odometry the robot is at the odometry origin, where motor starts it.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ..bus.node import Node
from ..bus.schemas import Message
from ..msgs.group import GroundPoints
from ..msgs.perception import Detections
from ..msgs.robot import Odometry
from ..tracking.groundplane import CameraGeometry, GroundPlaneParams, boxes_to_ground


class GroundPlane(Node):
    INPUTS = {"detections": Detections, "odometry": Odometry}
    REQUIRED_INPUTS = frozenset({"detections"})
    OUTPUTS = {"points": GroundPoints}
    Params = (GroundPlaneParams, CameraGeometry)

    def setup(self) -> None:
        self.plane, self.camera = self.params
        self.odometry: deque[Odometry] = deque(maxlen=512)  # ~5 s at 100 Hz, in stamp order
        self.frames = 0
        self.points = 0
        self.dropped_boxes = 0  # above the horizon, feet cut off, too weak, too far, not finite
        self.without_odometry = 0

    def _pose(self, stamp_ns: int, frame_seq: int) -> Odometry | None:
        forced = self.replayed_choice(frame_seq, "odometry")
        chosen = None
        for odom in reversed(self.odometry):
            if (odom.header.stamp_ns == forced) if forced is not None else (odom.header.stamp_ns <= stamp_ns):
                chosen = odom
                break
        self.note("odometry", -1 if chosen is None else chosen.header.stamp_ns)
        return chosen

    def on_message(self, name: str, msg: Message) -> None:
        if name == "odometry" and isinstance(msg, Odometry) and (
                not self.odometry or msg.header.stamp_ns >= self.odometry[-1].header.stamp_ns):
            self.odometry.append(msg)

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        dets = inputs["detections"]
        assert isinstance(dets, Detections)
        odom = self._pose(dets.header.stamp_ns, frame_seq)
        if odom is None:
            self.without_odometry += 1
        pose = (odom.x_m, odom.y_m, odom.theta_rad) if odom is not None else (0.0, 0.0, 0.0)
        ground = boxes_to_ground(dets.boxes, self.camera, self.plane, pose)  # seed 004 Eq. 4 at this pose
        ground.odometry_stamp_ns = -1 if odom is None else odom.header.stamp_ns
        self.frames += 1
        self.points += len(ground.points_m)
        self.dropped_boxes += len(np.asarray(dets.boxes).reshape(-1, 5)) - len(ground.points_m)
        self.publish("points", ground, like=dets)

    def status_extra(self) -> dict[str, Any]:
        return {"frames": self.frames, "points": self.points, "dropped_boxes": self.dropped_boxes,
                "without_odometry": self.without_odometry}


NODE = GroundPlane
