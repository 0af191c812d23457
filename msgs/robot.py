"""The robot's side of the loop: the motor command and the odometry the drivers report."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..bus.schemas import Message


@dataclass
class MotorCommand(Message):
    TYPE: ClassVar[str] = "MotorCommand"
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    wz_radps: float = 0.0
    wheel_radps: np.ndarray = field(default_factory=lambda: np.zeros(4))  # fl, fr, rl, rr
    range_m: float | None = None
    bearing_rad: float | None = None
    reason: str = ""


@dataclass
class Odometry(Message):
    """The robot's pose in the odometry frame and its body-frame velocity, stamped (``header.stamp_ns``) when
    the driver measured it (control/drivers.py)."""

    TYPE: ClassVar[str] = "Odometry"
    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    wz_radps: float = 0.0

    @classmethod
    def at(cls, t_ns: int, **pose_and_twist: float) -> Odometry:
        """A sample stamped ``t_ns``."""
        sample = cls(**pose_and_twist)
        sample.header.stamp_ns = int(t_ns)
        return sample
