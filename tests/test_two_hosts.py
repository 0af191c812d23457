"""Two computers, one graph: the robot graph (router mode, user/password, access control) in one network namespace,
detection on a "compute" host in another with its own /dev/shm, joined as a client of the robot's router (the
README's recipe). Tracking works (tracks measured from the compute host's detections, which needs every frame
to cross inline: the same-host lane cannot reach a separate /dev/shm), and a restart of either side recovers.
Skipped, with the reason, where ip netns is not permitted."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
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
        argv = pair.argv(index, followbus_argv("launch", str(graph), "--host", host, "--grace", "1", *extra))
        # Each "machine" its own run records (tools/runs/claims.py), as two computers have.
        env = dict(os.environ, FOLLOWBUS_RUNS=str(graph.parent / f"runs-{host}"))
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     stdin=subprocess.DEVNULL, cwd=graph.parent, env=env)
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


class Tracks:
    """`followbus echo` of the robot's tracks in the robot's namespace, for the whole test (a client: it finds a
    restarted robot by itself); ``measured_after(t)``: a track measured from a detection, received after t."""

    def __init__(self, pair: NetnsPair, graph: Path):
        argv = pair.argv(0, followbus_argv("echo", "t/prediction/track", "--graph", str(graph)))
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     stdin=subprocess.DEVNULL, cwd=graph.parent)
        self.seen: list[tuple[float, dict]] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in iter(self.proc.stdout.readline, ""):
            if line.startswith("t/prediction/track: "):
                self.seen.append((time.monotonic(), json.loads(line.split(": ", 1)[1])))

    def measured_after(self, since: float, timeout: float = 20) -> bool:
        return wait_until(lambda: any(t > since and track.get("measured") for t, track in list(self.seen)), timeout)

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()


@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_detection_on_a_second_host_tracks_and_both_sides_recover(tmp_path):
    port = free_port()
    with NetnsPair() as pair:
        robot_file, compute_file = _split_graphs(tmp_path, port, pair.addresses[0])
        settings = ("--set", "capture.source=scene:wall-occlusion", "--set", "capture.loop=true",
                    "--set", "detection.backend=simulated", "--set", f"template.state_file={tmp_path / 't.npz'}")
        robot = Side(pair, 0, robot_file, "robot", *settings)
        compute = tracks = None
        try:
            robot.wait_ready()
            assert not any("[detection" in line for line in robot.lines)  # not started on the robot
            tracks = Tracks(pair, robot_file)
            compute = Side(pair, 1, compute_file, "gpu", *settings)
            compute.wait_ready()
            assert not [line for line in compute.lines if line.startswith("[") and not line.startswith("[detection")]
            assert tracks.measured_after(0.0), "".join(robot.lines[-20:] + compute.lines[-20:])

            compute.stop()  # the compute host restarts: tracking comes back with its detections
            compute = Side(pair, 1, compute_file, "gpu", *settings)
            compute.wait_ready()
            assert tracks.measured_after(time.monotonic()), "".join(compute.lines[-20:])

            robot.stop()  # the robot restarts: the compute host's client finds the new router by itself
            robot = Side(pair, 0, robot_file, "robot", *settings)
            robot.wait_ready()
            assert tracks.measured_after(time.monotonic()), "".join(robot.lines[-20:] + compute.lines[-20:])
        finally:
            for side in (tracks, compute, robot):
                if side is not None:
                    side.stop()
