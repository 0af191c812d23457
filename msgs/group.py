"""Group following (seed 004): people on the floor and the followed group's state."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..bus.schemas import Message, check_shape, require


@dataclass
class GroundPoints(Message):
    """One frame's people on the floor (groundplane node): robot frame (x forward, y left) and the fixed
    odometry frame (seed 004 Eq. 4, with the robot pose used), one row per kept detection."""

    TYPE: ClassVar[str] = "GroundPoints"
    points_robot_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    points_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # odometry frame
    covs_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))  # odometry frame
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))
    robot_x_m: float = 0.0
    robot_y_m: float = 0.0
    robot_theta_rad: float = 0.0
    odometry_stamp_ns: int = -1  # the odometry sample the pose came from (-1: none yet, the origin)

    def check(self) -> None:
        n = len(self.points_m)
        require(self.points_m.shape == (n, 2) and self.points_robot_m.shape == (n, 2)
                and self.covs_m2.shape == (n, 2, 2) and self.scores.shape == (n,), self,
                "points N x 2, covariances N x 2 x 2 and scores N must agree")
        require(not (n and (self.covs_m2[:, [0, 1], [0, 1]] < 0).any()), self, "covs_m2: negative variance")


@dataclass
class GroupState(Message):
    """The followed group for one frame (seed 004 ME-CGT-UGV): odometry frame unless named ``_robot``."""

    TYPE: ClassVar[str] = "GroupState"
    MEASURED: ClassVar[frozenset[str]] = frozenset({"step_ms"})
    valid: bool = False  # False: no group yet (the other fields are zeros)
    lost: bool = False  # no member seen this frame: the state is the prediction
    centre_m: np.ndarray = field(default_factory=lambda: np.zeros(2))
    velocity_mps: np.ndarray = field(default_factory=lambda: np.zeros(2))
    orientation_rad: float = 0.0  # main axis of the group's extent
    centre_robot_m: np.ndarray = field(default_factory=lambda: np.zeros(2))  # at this frame's pose: what motor follows
    ellipse_centres_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    ellipse_extents_m2: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    ellipse_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    members_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the points selected this frame
    others_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # the points left out (disturbers)
    step_ms: float = 0.0  # tracker cost of this frame

    def check(self) -> None:
        n = len(self.ellipse_weights)
        for name, shape in (("centre_m", (2,)), ("velocity_mps", (2,)), ("centre_robot_m", (2,)),
                            ("ellipse_centres_m", (n, 2)), ("ellipse_extents_m2", (n, 2, 2)),
                            ("ellipse_weights", (n,)), ("members_m", (None, 2)), ("others_m", (None, 2))):
            check_shape(self, name, getattr(self, name), shape)
        w = self.ellipse_weights
        require(not (n and ((w < 0).any() or (w > 1).any() or (self.ellipse_extents_m2[:, [0, 1], [0, 1]] < 0).any())),
                self, "ellipse weight outside [0, 1] or negative extent")
