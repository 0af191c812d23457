"""A source failure is a node failure (issue 36): a source that raised was taken for exhausted (its generator was
finished, so the retry found no next frame): one unreadable image and capture published nothing more, or with
``loop`` replayed the frames before it for ever, while every table said "up"; a camera whose read failed ended the
same way. Now the same frame is tried again (a camera is reopened), a source that keeps failing fails the node,
and node tables show a source that publishes nothing as stalled. Real image folders, real video files read
through OpenCV's capture (a file stands for the camera device), real launches."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.bus.graph import load_graph
from followbus.bus.inproc import InProcessGraph
from followbus.bus.liveness import (
    SOURCE_FINISHED,
    SOURCE_PRODUCING,
    SOURCE_STALLED,
    NodeStoppedWorking,
    ProductionWatch,
    SourceActivity,
)

from .conftest import followbus_argv, run_followbus

CAPTURE = """\
  capture:
    run: followbus.nodes.capture
    outputs: [frame, preview, ground_truth]
    params: {{source: "{source}", loop: {loop}, start_delay_s: 0, wait_for_consumers_s: 0}}
"""


def _folder(path: Path, n: int = 12, bad: int | None = 5) -> Path:
    path.mkdir()
    for i in range(n):
        cv2.imwrite(str(path / f"{i:04d}.png"), np.full((48, 64, 3), 10 * i, np.uint8))
    if bad is not None:
        (path / f"{bad:04d}.png").write_bytes(b"not an image: a file half copied")
    return path


def _video(path: Path, n: int = 10) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG/AVI")
    for i in range(n):
        writer.write(np.full((48, 64, 3), 20 * i, np.uint8))
    writer.release()
    return path


def _capture(graph_file, source: str, loop: bool = False) -> InProcessGraph:
    return InProcessGraph(load_graph(graph_file(CAPTURE.format(source=source, loop=str(loop).lower()))))


def _seqs(graph: InProcessGraph) -> list[int]:
    return [f.header.frame_seq for f in graph.outputs("capture", "frame")]


@pytest.mark.parametrize("loop", [False, True])
def test_an_unreadable_image_fails_the_node_instead_of_ending_the_source(graph_file, tmp_path, loop):
    """On d899b0d: frames 0-4, then "source exhausted" and silence (loop: frames 0-4 again and again)."""
    folder = _folder(tmp_path / "seq")
    with _capture(graph_file, str(folder), loop) as graph:
        with pytest.raises(NodeStoppedWorking, match=r"poll failed 6 times in a row .*cannot read image .*0005\.png"):
            graph.run_for(30_000_000_000)
        assert _seqs(graph) == [0, 1, 2, 3, 4]


def test_an_image_readable_again_is_published_in_its_place(graph_file, tmp_path):
    """A file still being copied: the same frame is read again, and nothing is skipped or repeated."""
    folder = _folder(tmp_path / "seq")
    with _capture(graph_file, str(folder)) as graph:
        while graph.status("capture")["extra"]["handler_errors"] == 0:
            graph.run_for(50_000_000)
        cv2.imwrite(str(folder / "0005.png"), np.full((48, 64, 3), 50, np.uint8))
        graph.run_for(5_000_000_000)
        frames = graph.outputs("capture", "frame")
        status = graph.status("capture")["extra"]
    assert [f.header.frame_seq for f in frames] == list(range(12)), _seqs(graph)
    assert [int(f.data.mean()) for f in frames] == [10 * i for i in range(12)]
    assert status["done"] and status["poll_failures"] == 0, status


def test_a_camera_that_stops_delivering_is_reopened(graph_file, tmp_path):
    """The camera device (a video file through OpenCV's capture, as a device is read) delivers 10 frames, then
    nothing: reopened, it delivers again and the frame numbers go on (on d899b0d: a failed read ended the
    camera for good; its spec took only an index)."""
    camera = _video(tmp_path / "camera.avi")
    with _capture(graph_file, f"camera:{camera}") as graph:
        graph.run_for(3_000_000_000)
        seqs = _seqs(graph)
        status = graph.status("capture")["extra"]
    assert len(seqs) > 20 and seqs == list(range(len(seqs))), seqs
    assert status["handler_errors"] >= 1 and not status["done"], status


def test_an_unplugged_camera_fails_the_node(graph_file, tmp_path):
    camera = _video(tmp_path / "camera.avi")
    with _capture(graph_file, f"camera:{camera}") as graph:
        graph.run_for(100_000_000)
        assert _seqs(graph), "the camera delivered nothing before it was unplugged"
        camera.unlink()  # what is open still reads to its end; reopening finds no device
        with pytest.raises(NodeStoppedWorking, match=f"cannot open camera:{camera}"):
            graph.run_for(10_000_000_000)


def test_a_source_is_stalled_when_silent_or_stuck_and_finished_when_done():
    watch, activity = ProductionWatch(), SourceActivity()
    assert activity.state(watch, 0.0) is None  # not polled yet: no source
    activity.poll_started(0.0)
    activity.poll_ended(0.05, 0.0, holding=True)  # waiting for its consumers: not a stall
    assert activity.state(watch, 0.9) == SOURCE_PRODUCING
    activity.poll_started(10.0)
    activity.poll_ended(0.05, 10.0)
    assert activity.state(watch, 10.5) == SOURCE_STALLED  # has not published since its hold ended, at 0.0
    for t in range(20):
        watch.published(11.0 + t * 0.033)
    activity.poll_started(11.7)
    assert activity.state(watch, 11.9) == SOURCE_PRODUCING
    assert activity.state(watch, 13.0) == SOURCE_STALLED  # one poll (a camera read) that has not returned
    activity.poll_ended(None, 13.0)
    assert activity.state(watch, 13.1) == SOURCE_FINISHED


@pytest.mark.slow
def test_launch_exits_nonzero_naming_the_source_and_its_error(graph_file, tmp_path):
    """On d899b0d `launch --duration` exited 0 after the source went silent."""
    folder = _folder(tmp_path / "seq")
    graph = graph_file(CAPTURE.format(source=folder, loop="true")
                       + "    restart: {policy: on-failure, max_restarts: 1, backoff_ms: 100}\n")
    result = run_followbus("launch", str(graph), "--duration", "30", timeout=120)
    assert result.returncode == 1, result.stdout[-3000:] + result.stderr[-3000:]
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith("followbus launch: capture failed for good"), line
    assert f"cannot read image {folder}/0005.png" in line, line


@pytest.mark.slow
def test_nodes_and_monitor_show_a_silent_source_stalled_and_an_ended_one_done(graph_file, tmp_path):
    """A camera topic nobody publishes (ROS 2 source) and a folder played to its end: on d899b0d both "up"."""
    folder = _folder(tmp_path / "seq", n=3, bad=None)
    graph = graph_file(CAPTURE.format(source="ros2:/camera/image_raw", loop="false")
                       + CAPTURE.replace("capture", "folder", 1).format(source=folder, loop="false"))
    launch = subprocess.Popen(followbus_argv("launch", str(graph), "--duration", "25"), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    try:
        deadline, states = time.monotonic() + 40, {}
        while time.monotonic() < deadline and states != {"capture": "stalled", "folder": "done"}:
            time.sleep(1.0)
            nodes = run_followbus("nodes", "--graph", str(graph), "--seconds", "1.5", timeout=30)
            states = {line.split()[0]: line.split()[1] for line in nodes.stdout.splitlines()[1:] if line.strip()}
        assert states == {"capture": "stalled", "folder": "done"}, nodes.stdout + nodes.stderr
        monitor = run_followbus("monitor", "--graph", str(graph), "--once", "--seconds", "5", timeout=30)
        rows = {line.split()[0]: line.split()[1] for line in monitor.stdout.splitlines()
                if line.split()[:1] in (["capture"], ["folder"])}
        assert rows == {"capture": "stalled", "folder": "done"}, monitor.stdout
    finally:
        launch.terminate()
        launch.communicate(timeout=60)
