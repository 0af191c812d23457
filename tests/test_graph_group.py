"""Group following (seed 004) launched for real: graph.group.yaml's processes over Zenoh on loopback, the
group-walk scene, the simulated detector. The group node's centre matches the scene's ground truth and the
motor drives towards the group."""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

from followbus.bus.pubsub import Subscriber
from followbus.bus.session import ZenohSettings, open_session
from followbus.msgs.group import GroundPoints, GroupState
from followbus.msgs.robot import MotorCommand
from followbus.vision.scenes import make_scene

from .conftest import REPO, followbus_argv, processes_matching

pytestmark = pytest.mark.slow

FPS = 30.0


def _graph_copies(tmp_path: Path, port: int) -> Path:
    for name in ("graph.yaml", "graph.group.yaml"):
        text = (REPO / name).read_text().replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
        (tmp_path / name).write_text(text.replace("namespace: fb", "namespace: t"))
    return tmp_path / "graph.group.yaml"


def test_the_motor_follows_the_group_centre(tmp_path, port):
    graph = _graph_copies(tmp_path, port)
    session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    lock = threading.Lock()
    groups: dict[int, GroupState] = {}
    points: dict[int, GroundPoints] = {}
    commands: list[MotorCommand] = []

    def keep(store):
        def put(msg):
            with lock:
                store[msg.header.frame_seq] = msg
        return put

    def command(msg):
        with lock:
            commands.append(msg)

    subs = [Subscriber(session, "t/group/group", keep(groups), schema=GroupState),
            Subscriber(session, "t/groundplane/points", keep(points), schema=GroundPoints),
            Subscriber(session, "t/motor/command", command, schema=MotorCommand)]
    try:
        result = subprocess.run(
            # No track-age limit on the motor: this test is about what it follows, not about the staleness rule
            # (tests/test_graph_tracking.py), which a loaded machine's latency would trip for most commands.
            followbus_argv("launch", str(graph), "--duration", "14", "--set", "detection.backend=simulated",
                           "--set", "motor.max_track_age_ms=0"),
            capture_output=True, text=True, timeout=80, stdin=subprocess.DEVNULL)
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert not processes_matching(str(graph))

    scene = make_scene("group-walk")
    valid = {i: g for i, g in groups.items() if g.valid}
    assert len(valid) > 150, f"{len(valid)} valid group states of {len(groups)}"
    # The centre, in the robot frame at each frame's pose, is the mean of the members' true positions; the
    # frames where member 5 is hidden behind member 1 (~6.5-11 s) are included.
    errors = np.array([np.linalg.norm(g.centre_robot_m - scene.group_truth_m(i / FPS)[0]) for i, g in valid.items()])
    assert np.median(errors) < 0.25 and np.percentile(errors, 95) < 0.6, np.percentile(errors, [50, 95, 100])
    # The shape: several ellipses whose weights sum to 1, and the passer-by left out when it is in view.
    assert all(abs(g.ellipse_weights.sum() - 1) < 1e-6 and len(g.ellipse_weights) >= 1 for g in valid.values())
    assert any(len(g.others_m) for g in valid.values()), "the passer-by was never left out of the group"
    # Ground points moved into the odometry frame with the motor's odometry (seed 004 Eq. 4).
    assert any(p.odometry_stamp_ns > 0 and p.robot_x_m > 0.1 for p in points.values()), "odometry never applied"
    # The robot follows: the group starts 3.5 m away, beyond target_distance_m 2.5, so it drives forward.
    following = [c for c in commands if c.reason in ("tracking", "occluded") and c.range_m is not None]
    assert len(following) > 100
    assert max(c.vx_mps for c in following) > 0.2
    assert all(c.range_m == pytest.approx(np.hypot(*valid[c.header.frame_seq].centre_robot_m))
               for c in following if c.header.frame_seq in valid)
