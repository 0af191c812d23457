"""The tracking graph launched for real (six processes over Zenoh on loopback): the target is
re-acquired after a complete occlusion, and the motor stops when the target is lost."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from followbus.bus.pubsub import Subscriber
from followbus.bus.session import ZenohSettings, open_session
from followbus.msgs.perception import GroundTruth
from followbus.msgs.robot import MotorCommand
from followbus.msgs.tracking import Track

from .conftest import REPO, followbus_argv, processes_matching, wait_until

pytestmark = pytest.mark.slow


def _graph_copy(tmp_path: Path, port: int) -> Path:
    text = (REPO / "graph.yaml").read_text().replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    text = text.replace("namespace: fb", "namespace: t")
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    return path


class Collector:
    def __init__(self, port: int):
        self.session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
        self.lock = threading.Lock()
        self.tracks: dict[int, Track] = {}
        self.truth: dict[int, GroundTruth] = {}
        self.commands: list[MotorCommand] = []
        self.subs = [
            Subscriber(self.session, "t/prediction/track", self._put(self.tracks), schema=Track),
            Subscriber(self.session, "t/capture/ground_truth", self._put(self.truth), schema=GroundTruth),
            Subscriber(self.session, "t/motor/command", self._append, schema=MotorCommand),
        ]

    def _put(self, store):
        def put(msg):
            with self.lock:
                store[msg.header.frame_seq] = msg
        return put

    def _append(self, msg):
        with self.lock:
            self.commands.append(msg)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def _launch(graph: Path, scene: str, duration_s: float, tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    argv = followbus_argv("launch", str(graph), "--duration", str(duration_s),
                          "--set", f"capture.source=scene:{scene}", "--set", "detection.backend=simulated",
                          "--set", f"template.state_file={tmp_path / 'template.npz'}", *extra)
    return subprocess.run(argv, capture_output=True, text=True, timeout=duration_s + 60, stdin=subprocess.DEVNULL)


def _centre_error(track: Track, truth: GroundTruth) -> float:
    a, b = np.asarray(track.box), np.asarray(truth.box)
    return float(np.hypot(a[0] + a[2] / 2 - b[0] - b[2] / 2, a[1] + a[3] / 2 - b[1] - b[3] / 2))


def test_target_is_reacquired_after_a_complete_occlusion(tmp_path, port):
    graph = _graph_copy(tmp_path, port)
    collector = Collector(port)
    try:
        result = _launch(graph, "wall-occlusion", 10.5, tmp_path)
    finally:
        collector.close()
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    hidden = sorted(i for i, gt in collector.truth.items() if gt.box is None)
    assert hidden, "the scene should hide the target completely for a while"
    start, end = hidden[0], hidden[-1]
    states = {i: t.state for i, t in collector.tracks.items()}
    assert any(states.get(i) == "OCCLUDED" for i in range(start, end + 1)), "occlusion was not reported"
    after = [i for i in sorted(states) if i > end]
    reacquired = [i for i in after if states[i] == "REACQUIRED"]
    assert reacquired, f"never REACQUIRED after frame {end}: {[states[i] for i in after][:40]}"
    # Once re-acquired, the output follows the real person again.
    locked = [i for i in after if i > reacquired[0] and states[i] in ("TRACKING", "REACQUIRED")
              and collector.truth.get(i) is not None and collector.truth[i].box is not None]
    assert len(locked) > 20
    errors = [_centre_error(collector.tracks[i], collector.truth[i]) for i in locked]
    assert np.median(errors) < 20, errors
    assert not processes_matching(str(graph))
    # The template node saved the reference model at shutdown, in a form it can restore.
    from followbus.tracking.params import TemplateParams
    from followbus.tracking.template import TemplateUpdater

    restored = TemplateUpdater(TemplateParams())
    restored.load(tmp_path / "template.npz")
    assert restored.initialised and abs(float(restored.hist.sum()) - 1.0) < 1e-5


def test_motor_stops_when_the_target_is_lost(tmp_path, port):
    graph = _graph_copy(tmp_path, port)
    collector = Collector(port)
    try:
        # No age limit on tracks: beside two burners and another test worker the LOST track arrived over 500 ms
        # after its capture, the motor rightly did not act on it (the watchdog stopped the robot), and this test,
        # which is about the target-lost stop, had no command to look at.
        result = _launch(graph, "lost-target", 9.0, tmp_path, "--set", "reid.lost_after_ms=1000",
                         "--set", "motor.max_track_age_ms=0")
    finally:
        collector.close()
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    moving = [c for c in collector.commands if c.reason == "tracking" and abs(c.vx_mps) + abs(c.wz_radps) > 0]
    assert moving, "the robot never followed the target before it left"
    lost_frames = sorted(i for i, t in collector.tracks.items() if t.state == "LOST")
    assert lost_frames, "the target was never declared LOST"
    # The target leaves for good: judged from the LOST that lasts to the end. A slow start can lose the target for
    # a second while it is still in view, and re-acquiring it then is right (a fresh clone's first run did, frame
    # 86, bearing -0.48 rad: the target's side, not the bystander's).
    found_after = [i for i, t in collector.tracks.items() if t.state != "LOST" and i > lost_frames[0]]
    last_lost = [i for i in lost_frames if i > max(found_after, default=-1)]
    assert last_lost, f"the track left LOST at frame {max(found_after)} and never went back: it followed someone"
    final_lost = last_lost[0]
    after_lost = [c for c in collector.commands if c.header.frame_seq >= final_lost]
    assert after_lost, "no command answered the LOST track"
    assert after_lost[0].reason == "target-lost"
    for cmd in after_lost:
        assert cmd.vx_mps == 0 and cmd.vy_mps == 0 and cmd.wz_radps == 0, cmd
        assert not np.any(cmd.wheel_radps)


def test_watchdog_stops_the_motor_when_tracks_stop(tmp_path, port):
    from followbus.bus.health import HealthWatcher

    graph = _graph_copy(tmp_path, port)
    collector = Collector(port)
    watcher = HealthWatcher(collector.session, "t")
    argv = followbus_argv("launch", str(graph), "--duration", "12", "--set", "capture.source=scene:corridor-occlusion",
                          "--set", "detection.backend=simulated",
                          "--set", f"template.state_file={tmp_path / 'template.npz'}")
    launcher = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    try:
        def following() -> bool:
            with collector.lock:
                return sum(c.reason == "tracking" for c in collector.commands) > 30

        assert wait_until(following, 30), "the robot never started following"
        assert wait_until(lambda: (h := watcher.snapshot().get("prediction")) is not None and h.status, 5)
        os.kill(watcher.snapshot()["prediction"].status.pid, signal.SIGKILL)
        killed_ns = time.time_ns()
        assert wait_until(lambda: any(c.reason == "watchdog" for c in collector.commands), 5)
        with collector.lock:
            last_track_pub = max(t.header.pub_ns for t in collector.tracks.values() if t.header.pub_ns < killed_ns)
            stop = next(c for c in collector.commands if c.reason == "watchdog")
        assert stop.vx_mps == 0 and stop.wz_radps == 0 and not np.any(stop.wheel_radps)
        # 200 ms watchdog + one 20 ms tick, plus scheduling slack on a loaded 2-core machine.
        assert (stop.header.pub_ns - last_track_pub) / 1e6 < 300
    finally:
        launcher.send_signal(signal.SIGINT)
        launcher.wait(30)
        watcher.close()
        collector.close()
