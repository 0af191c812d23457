"""Two computers, one graph: the robot graph (router mode, user/password, access control) in one network namespace,
detection on a "compute" host in another with its own /dev/shm, joined as a client of the robot's router (the
README's recipe). Tracking works (tracks measured from the compute host's detections, which needs every frame
to cross inline: the same-host lane cannot reach a separate /dev/shm), each launcher reports the delivered rate of
the links between the hosts and `nodes` lists them, and a restart of either side recovers. Over a link too slow
for the frames, the frames detection never received are counted (nodes, the launcher's report). Peer mode across
the hosts (which splits: Zenoh peers do not forward each other's messages) is named by both launchers within
10 s. Skipped, with the reason, where ip netns is not permitted."""

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

from .conftest import REPO, followbus_argv, free_port, wait_until
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


SETTINGS = ("--set", "capture.source=scene:wall-occlusion", "--set", "capture.loop=true",
            "--set", "detection.backend=simulated")
FRAME_LINK = "t/capture/frame capture (robot) -> detection (gpu)"


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

    def line_with(self, *parts: str, timeout: float) -> str | None:
        """The first line holding every part, waited for at most ``timeout`` seconds."""
        def found() -> str | None:
            return next((line for line in list(self.lines) if all(p in line for p in parts)), None)

        wait_until(lambda: found() is not None, timeout)
        return found()

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


def _links(pair: NetnsPair, side: int, graph: Path) -> dict[str, list[str]]:
    """`followbus nodes` on one side: its links table, by route (key, from, to)."""
    out = subprocess.run(pair.argv(side, followbus_argv("nodes", "--graph", str(graph))), capture_output=True,
                         text=True, timeout=60, cwd=graph.parent, stdin=subprocess.DEVNULL)
    assert out.returncode == 0, out.stdout + out.stderr
    table = out.stdout.split("\nlink ", 1)[1] if "\nlink " in out.stdout else ""
    rows = {}
    for line in table.splitlines()[1:]:
        route, _, figures = line.rpartition(")")
        rows[route + ")"] = figures.split()  # sent Hz, delivered Hz, lost
    return {"nodes": out.stdout.splitlines(), **rows}


@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_detection_on_a_second_host_tracks_and_both_sides_recover(tmp_path):
    port = free_port()
    with NetnsPair() as pair:
        robot_file, compute_file = _split_graphs(tmp_path, port, pair.addresses[0])
        settings = (*SETTINGS, "--set", f"template.state_file={tmp_path / 't.npz'}")
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
            # Both launchers report the links between the hosts, with their delivered rates; `nodes` lists them.
            for side in (robot, compute):
                report = side.line_with(f"link {FRAME_LINK}: ", " Hz delivered, ", timeout=20)
                assert report is not None, "".join(side.lines[-30:])
                print(report)
            links = _links(pair, 0, robot_file)
            sent, delivered, lost = links[FRAME_LINK]
            assert float(sent) > 0 and float(delivered) > 0 and int(lost) >= 0, links
            assert "t/detection/detections detection (gpu) -> prediction (robot)" in links, links
            print(f"{FRAME_LINK}: sent {sent} Hz, delivered {delivered} Hz, lost {lost}")

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


@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_frames_a_slow_link_never_delivered_are_counted(tmp_path):
    """Over 20 Mbit/s the compute host gets a few of the 30 raw frames a second (BLOCK_FIRST: whole ones); the rest
    never reach detection, and that is said where the operator looks: the launchers' link reports, detection's
    `lost in`, the links table. (Before, detection received 19.7 of 30 a second with every counter at 0.)"""
    port = free_port()
    with NetnsPair(rate_mbit=20.0) as pair:
        robot_file, compute_file = _split_graphs(tmp_path, port, pair.addresses[0])
        settings = (*SETTINGS, "--set", f"template.state_file={tmp_path / 't.npz'}")
        robot = Side(pair, 0, robot_file, "robot", *settings)
        compute = None
        try:
            robot.wait_ready()
            compute = Side(pair, 1, compute_file, "gpu", *settings)
            compute.wait_ready()
            for side in (robot, compute):
                report = side.line_with(f"link {FRAME_LINK}: ", "the link does not carry all of it", timeout=30)
                assert report is not None, "".join(side.lines[-30:])
                print(report)
            links = _links(pair, 0, robot_file)
        finally:
            for side in (compute, robot):
                if side is not None:
                    side.stop()
    sent, delivered, lost = links[FRAME_LINK]
    assert float(delivered) < float(sent) and int(lost) > 0, links
    detection = next(line.split() for line in links["nodes"] if line.startswith("detection "))
    assert int(detection[5]) >= int(lost) > 0, links["nodes"]  # lost in: every input of detection
    print(f"{FRAME_LINK}: sent {sent} Hz, delivered {delivered} Hz, lost {lost}")


def _peer_graphs(tmp: Path, port: int, robot_ip: str) -> tuple[Path, Path]:
    """graph.yaml's peer mode spread over two hosts: the robot's peers listen on the veth address too, the compute
    host's connect to it (what the README's recipe is not)."""
    base = (REPO / "graph.yaml").read_text()
    for old, new in (("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}"), ("namespace: fb", "namespace: t")):
        assert old in base
        base = base.replace(old, new)
    (tmp / "graph.yaml").write_text(base)
    robot = tmp / "graph.split.yaml"
    robot.write_text(f"extends: graph.yaml\ndefault_host: robot\nzenoh:\n"
                     f"  listen: [tcp/127.0.0.1:{port}, tcp/{robot_ip}:{port}]\nnodes:\n  detection: {{host: gpu}}\n")
    compute = tmp / "graph.split.gpu.yaml"
    compute.write_text(f"extends: graph.split.yaml\nzenoh:\n  listen: [tcp/127.0.0.1:{port}]\n"
                       f"  connect: [tcp/{robot_ip}:{port}]\n")
    return robot, compute


@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_peer_mode_across_two_hosts_is_named_within_10_s(tmp_path):
    """Peers on two hosts split: each hears only the sessions it connected to, so detection is "up" (its status
    reaches the robot's launcher) while capture never sees it and no frame reaches it. Before, nothing said so
    (monitor showed detection up, verified, 0.0 Hz input); now each launcher names the split within 10 s of the
    second host coming up."""
    port = free_port()
    with NetnsPair() as pair:
        robot_file, compute_file = _peer_graphs(tmp_path, port, pair.addresses[0])
        settings = (*SETTINGS, "--set", f"template.state_file={tmp_path / 't.npz'}")
        robot = Side(pair, 0, robot_file, "robot", *settings)
        compute = None
        try:
            robot.wait_ready(60)
            compute = Side(pair, 1, compute_file, "gpu", *settings)
            compute.wait_ready(60)
            up = time.monotonic()
            robot_says = robot.line_with("capture (robot) -> detection (gpu)", "peer mode", timeout=10)
            robot_s = time.monotonic() - up
            compute_says = compute.line_with("no status from capture", "(host robot)", timeout=max(0.0, 10 - robot_s))
            compute_s = time.monotonic() - up
        finally:
            for side in (compute, robot):
                if side is not None:
                    side.stop()
    assert robot_says is not None, "".join(robot.lines[-40:])
    assert "does not see detection" in robot_says or "nothing delivered" in robot_says, robot_says
    assert compute_says is not None, "".join(compute.lines[-40:])
    print(f"named after {robot_s:.1f} s on the robot: {robot_says}\nafter {compute_s:.1f} s on the compute host: "
          f"{compute_says}")
