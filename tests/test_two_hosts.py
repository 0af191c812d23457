"""Two computers, one graph: the robot graph (router mode, user/password, access control) in one network namespace,
detection on a "compute" host in another with its own /dev/shm, joined as a client of the robot's router (the
README's recipe). Tracking works (tracks measured from the compute host's detections, which needs every frame
to cross inline: the same-host lane cannot reach a separate /dev/shm), and a restart of either side recovers.
Skipped, with the reason, where ip netns is not permitted."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
from pathlib import Path

import pytest

from followbus.tools.bench.netns import NetnsPair, netns_unavailable

from .conftest import followbus_argv, free_port, wait_until
from .test_monitor import robot_graph

pytestmark = pytest.mark.slow

REASON = netns_unavailable()


def _split_graphs(tmp: Path, port: int, robot_ip: str) -> tuple[Path, Path]:
    """The robot graph with detection on host gpu (default_host robot), listening on the veth address too,
    and the compute host's file: the same graph, joined as a client of the robot's router."""
    robot = robot_graph(tmp, port)
    text = robot.read_text().replace("zenoh:\n  mode: router\n",
                                     f"default_host: robot\nzenoh:\n  mode: router\n"
                                     f"  listen: [tcp/127.0.0.1:{port}, tcp/{robot_ip}:{port}]\n", 1)
    text += "nodes:\n  detection: {host: gpu}\n"
    robot.write_text(text)
    compute = tmp / "graph.gpu.yaml"
    compute.write_text(f"extends: graph.robot.yaml\nzenoh:\n  mode: client\n  listen: []\n"
                       f"  connect: [tcp/{robot_ip}:{port}]\n")
    return robot, compute


class Side:
    """`followbus launch GRAPH --host HOST` in one namespace, its output collected."""

    def __init__(self, pair: NetnsPair, index: int, graph: Path, host: str, *extra: str):
        argv = pair.argv(index, followbus_argv("launch", str(graph), "--host", host, *extra))
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     stdin=subprocess.DEVNULL, cwd=graph.parent)
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")), daemon=True).start()

    def wait_ready(self, timeout: float = 40) -> None:
        assert wait_until(lambda: any("ready:" in line for line in self.lines), timeout), "".join(self.lines[-30:])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _measured_tracks(pair: NetnsPair, graph: Path, seconds: float = 3.0) -> list[dict]:
    """Tracks published on the robot over ``seconds`` that a detection measured."""
    argv = pair.argv(0, followbus_argv("echo", "t/prediction/track", "--graph", str(graph), "--seconds",
                                       str(seconds), "--timeout", "15"))
    out = subprocess.run(argv, capture_output=True, text=True, timeout=60, cwd=graph.parent).stdout
    tracks = [json.loads(line.split(": ", 1)[1]) for line in out.splitlines() if line.startswith("t/prediction/")]
    return [t for t in tracks if t.get("measured")]


@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_detection_on_a_second_host_tracks_and_both_sides_recover(tmp_path):
    port = free_port()
    with NetnsPair() as pair:
        robot_file, compute_file = _split_graphs(tmp_path, port, pair.addresses[0])
        settings = ("--set", "capture.source=scene:wall-occlusion", "--set", "capture.loop=true",
                    "--set", "detection.backend=simulated", "--set", f"template.state_file={tmp_path / 't.npz'}")
        robot = Side(pair, 0, robot_file, "robot", *settings)
        compute = None
        try:
            robot.wait_ready()
            assert not any("[detection" in line for line in robot.lines)  # not started on the robot
            compute = Side(pair, 1, compute_file, "gpu", *settings)
            compute.wait_ready()
            started = [line for line in compute.lines if "started" in line or "ready:" in line]
            assert "detection" in "".join(started) and "capture" not in "".join(compute.lines[:20]), compute.lines
            assert _measured_tracks(pair, robot_file), "".join(robot.lines[-20:] + compute.lines[-20:])

            compute.stop()  # the compute host restarts: tracking comes back with its detections
            compute = Side(pair, 1, compute_file, "gpu", *settings)
            compute.wait_ready()
            assert _measured_tracks(pair, robot_file), "".join(compute.lines[-20:])

            robot.stop()  # the robot restarts: the compute host's client finds the new router by itself
            robot = Side(pair, 0, robot_file, "robot", *settings)
            robot.wait_ready()
            assert wait_until(lambda: bool(_measured_tracks(pair, robot_file, 2.0)), 20), "".join(
                robot.lines[-20:] + compute.lines[-20:])
        finally:
            for side in (compute, robot):
                if side is not None:
                    side.stop()
