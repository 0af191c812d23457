"""graph.group.yaml's nodes (groundplane, group, group_motor) through the in-process runtime (bus/inproc.py):
hand-made messages in, published messages out, on a simulated clock."""

from __future__ import annotations

import numpy as np
import pytest

from followbus.bus.graph import apply_overrides, load_graph
from followbus.bus.inproc import InProcessGraph
from followbus.bus.schemas import Message
from followbus.msgs.group import GroupState
from followbus.msgs.perception import Detections
from followbus.msgs.robot import Odometry
from followbus.tracking.groundplane import CameraGeometry
from followbus.vision.scenes import make_scene

from .conftest import REPO

DT_NS = 33_333_333
MS = 1_000_000
EPOCH_NS = 1_600_000_000_000_000_000


def group_graph(*overrides: str):
    graph = load_graph(REPO / "graph.group.yaml")
    apply_overrides(graph, list(overrides))
    return graph


def stamped(msg: Message, k: int, stamp_ns: int) -> Message:
    msg.header.frame_seq, msg.header.stamp_ns, msg.header.epoch_ns = k, stamp_ns, EPOCH_NS
    return msg


def _is_zero(cmd) -> bool:
    return cmd.vx_mps == 0.0 and cmd.vy_mps == 0.0 and cmd.wz_radps == 0.0 and not np.any(cmd.wheel_radps)


def test_groundplane_moves_points_with_the_odometry_sample_by_stamp():
    cam = CameraGeometry()
    # A person 4 m straight ahead: feet at row cy + f·h/4.
    bottom = cam.cy_px + cam.focal_px * cam.camera_height_m / 4.0
    box = [cam.cx_px - 30, bottom - 170, 60, 170, 0.9]
    with InProcessGraph(group_graph(), nodes=["groundplane"]) as g:
        t0 = g.now_ns
        for stamp, x in ((t0 - 20 * MS, 1.0), (t0 + 10 * MS, 2.0)):  # the second is after the frame's capture
            g.inject("motor/odometry", stamped(Odometry(x_m=x, theta_rad=np.pi / 2), -1, stamp))
        g.deliver()
        g.inject("detection/detections", stamped(Detections(boxes=np.array([box], np.float32)), 0, t0))
        g.deliver()
        (out,) = g.outputs("groundplane", "points")
    np.testing.assert_allclose(out.points_robot_m, [[4.0, 0.0]], atol=1e-6)
    # Seed 004 Eq. 4 with the pose stamped before the frame (x = 1, facing +y): 4 m ahead is (1, 4).
    assert out.odometry_stamp_ns == t0 - 20 * MS and out.robot_x_m == 1.0
    np.testing.assert_allclose(out.points_m, [[1.0, 4.0]], atol=1e-6)


def _group(k: int, stamp_ns: int, valid: bool = True, lost: bool = False) -> GroupState:
    msg = GroupState(valid=valid, lost=lost)
    if valid:
        msg.centre_robot_m = np.array([4.0, 0.5])
        msg.centre_m = msg.centre_robot_m.copy()
    return stamped(msg, k, stamp_ns)


def test_group_motor_follows_the_centre_stops_at_once_without_a_group_and_on_the_watchdog():
    with InProcessGraph(group_graph(), nodes=["motor"]) as g:
        t0 = g.now_ns
        for k in range(5):
            g.run_until(t0 + k * DT_NS)
            g.inject("group/group", _group(k, g.now_ns))
            g.deliver()
        g.run_until(t0 + 5 * DT_NS)
        g.inject("group/group", _group(5, g.now_ns, valid=False))
        g.deliver()
        invalid_at = g.now_ns
        g.inject("group/group", _group(6, g.now_ns))
        g.deliver()
        last_rx = g.now_ns
        g.run_until(last_rx + 400 * MS)
        cmds = g.outputs("motor", "command")
    follow = [c for c in cmds if c.reason == "tracking"]
    # Ahead and to the left; the answer right after the stop ramps up from zero (same instant: still zero).
    assert len(follow) == 6 and all(c.vx_mps > 0 and c.wz_radps > 0 for c in follow[:5])
    assert follow[5].header.frame_seq == 6 and _is_zero(follow[5])
    assert follow[0].range_m == pytest.approx(np.hypot(4.0, 0.5))
    lost = [c for c in cmds if c.reason == "target-lost"]
    assert lost and _is_zero(lost[0]) and lost[0].header.frame_seq == 5 and lost[0].header.pub_ns == invalid_at
    stops = [c for c in cmds if c.reason == "watchdog"]
    assert stops and 130 * MS <= stops[0].header.pub_ns - last_rx <= 200 * MS and _is_zero(stops[0])


def test_group_graph_in_process_follows_the_scene_group():
    """capture (scene:group-walk) → simulated detection → groundplane → group → motor in one process."""
    graph = group_graph("detection.backend=simulated", "capture.max_frames=90", "capture.pace=fast")
    with InProcessGraph(graph) as g:
        assert g.run_frames(90) == 90
        groups = g.outputs("group", "group")
        cmds = g.outputs("motor", "command")
    scene = make_scene("group-walk")
    assert len(groups) == 90 and all(s.valid for s in groups)
    errors = [np.linalg.norm(s.centre_robot_m - scene.group_truth_m(s.header.frame_seq / 30.0)[0]) for s in groups]
    assert max(errors) < 0.3, max(errors)
    assert np.median([len(s.members_m) for s in groups]) == 5  # all five (the detector misses 5 % of boxes)
    assert any(c.reason == "tracking" and c.vx_mps > 0 for c in cmds)
