"""group: the group-target tracker of seed 004 (ME-CGT-UGV, :mod:`followbus.tracking.group`) on the bus.

Each frame's ground points (odometry frame, groundplane node) go through one tracker step: DBSCAN
initialisation, data selection against the predicted multi-ellipse shape, the variational-Bayes shape and
group-centre Kalman update. The node publishes the group centre, velocity, main orientation, the ellipses,
which points were taken as members and which were left out, and the centre in the robot frame at that
frame's pose (what motor follows). ``step_ms`` is the tracker's wall time on that frame; ``status`` reports
its mean and worst, and the mean CPU time (``step_cpu_ms_mean``: the cost without other processes' share).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from ..bus.node import In, Node, Out
from ..bus.node_params import ParamError
from ..bus.schemas import Message
from ..msgs.group import GroundPoints, GroupState
from ..tracking.group import GroupEstimate, GroupParams, MultiEllipseGroupTracker, SingleEllipseGroupTracker


@dataclass
class GroupNodeParams:
    shape: str = "multi"  # multi: ME-CGT-UGV | single: one ellipse (RM-CGT-UGV), the ablation

    def __post_init__(self) -> None:
        if self.shape not in ("multi", "single"):
            raise ParamError("shape", f"shape must be 'multi' or 'single', not {self.shape!r}")


class Group(Node):
    INPUTS = {"points": In(GroundPoints, required=True)}
    OUTPUTS = {"group": Out(GroupState)}
    Params = (GroupNodeParams, GroupParams)  # GroupParams checks n_ellipses and dbscan_min_samples >= 1

    def setup(self) -> None:
        node, group = self.params
        self.tracker = (MultiEllipseGroupTracker if node.shape == "multi" else SingleEllipseGroupTracker)(group)
        self.frames = 0
        self.valid_frames = 0
        self.step_ms_total = 0.0
        self.step_ms_max = 0.0
        self.step_cpu_ms_total = 0.0
        self.rejected = 0  # estimates that came out non-finite (dropped, the tracker restarts)

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        msg = inputs["points"]
        assert isinstance(msg, GroundPoints)
        t0, cpu0 = time.perf_counter(), time.thread_time()
        est = self.tracker.step(msg.header.stamp_ns * 1e-9, msg.points_m, msg.covs_m2)
        step_ms = (time.perf_counter() - t0) * 1e3
        # CPU time too: on a shared machine the wall time also counts the time other processes held the core.
        self.step_cpu_ms_total += (time.thread_time() - cpu0) * 1e3
        self.frames += 1
        self.step_ms_total += step_ms
        self.step_ms_max = max(self.step_ms_max, step_ms)
        if est.valid and not est.is_finite():
            self.rejected += 1
            self.log.warning("the group estimate is not finite; restarting the tracker")
            self.tracker = type(self.tracker)(self.tracker.p)
            est = GroupEstimate(valid=False, selected=est.selected)
        elif est.valid:
            self.valid_frames += 1
        out = est.to_message(msg.points_m, (msg.robot_x_m, msg.robot_y_m, msg.robot_theta_rad))
        out.step_ms = step_ms
        self.publish("group", out)

    def status(self) -> dict[str, Any]:
        mean = self.step_ms_total / self.frames if self.frames else 0.0
        return {"frames": self.frames, "valid_frames": self.valid_frames, "rejected": self.rejected,
                "step_ms_mean": round(mean, 3), "step_ms_max": round(self.step_ms_max, 3),
                "step_cpu_ms_mean": round(self.step_cpu_ms_total / self.frames, 3) if self.frames else 0.0,
                "components": self.tracker.n_components if self.tracker.initialised else 0,
                "orientation_deg": None if not self.tracker.initialised
                else round(math.degrees(self.tracker.estimate().orientation_rad), 1)}


NODE = Group
