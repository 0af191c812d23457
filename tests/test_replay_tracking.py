"""A recording of the tracking graph is a regression test: replay of the re-ID and prediction nodes (in-process,
both together, and re-ID as its own process) reproduces every recorded output, and a changed parameter is
reported as a mismatch."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import pytest

from followbus.bus.recording import read_metadata

from .conftest import REPO, copy_recording, followbus_argv, processes_matching, run_followbus

pytestmark = pytest.mark.slow


def _record(tmp, namespace: str, frames: int, during=None, *extra: str):
    """Launch the tracking graph with ``--record`` until re-ID has handled ``frames`` frames (after
    ``during(graph)`` returned, when given), then stop it as a user would (SIGINT). Counting frames rather
    than seconds keeps the recording the same size on a loaded machine, where start-up can take seconds."""
    from followbus.bus.pubsub import Subscriber
    from followbus.bus.session import ZenohSettings, open_session
    from followbus.msgs.tracking import Measurement

    from .conftest import free_port, wait_until

    port = free_port()
    text = (REPO / "graph.yaml").read_text().replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    graph = tmp / "graph.yaml"
    graph.write_text(text.replace("namespace: fb", f"namespace: {namespace}"))
    path = tmp / "run.mcap"
    session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    seen: list[int] = []
    sub = Subscriber(session, f"{namespace}/reid/measurement", lambda m: seen.append(m.header.frame_seq),
                     schema=Measurement)
    proc = subprocess.Popen(
        followbus_argv("launch", str(graph), "--duration", "120", "--record", str(path),
                       "--set", "capture.source=scene:wall-occlusion", "--set", "capture.loop=true",
                       "--set", "detection.backend=simulated", "--set", "template.state_file=", *extra),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    try:
        if during is not None:
            assert wait_until(lambda: len(seen) >= 60, timeout=90), "the graph did not start tracking"
            during(graph)
        target = len(seen) + frames - (60 if during is None else 0)
        assert wait_until(lambda: len(seen) >= target, timeout=120), f"re-ID handled only {len(seen)} frames"
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.undeclare()
        session.close()
    (tmp / "launch.log").write_text(out)  # for a test's failure message: who started when, what was dropped
    assert path.exists(), out[-3000:]
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    # 330 frames: beside two CPU burners the recorder drops some of them under its queue bound and the live nodes
    # skip some, and the tests below compare more than 100 outputs (220 left 42-98 under load).
    # A recording that lost messages upstream (Zenoh drops frames to a recorder that falls behind) is made again,
    # up to twice: these tests are about exact replay; what a lossy recording replays as is tested below with
    # messages removed on purpose (test_two_nodes_replay_through_a_frame_the_recorder_dropped and others).
    for _attempt in range(3):
        path = _record(tmp_path_factory.mktemp("rec"), "rt", 330)
        if read_metadata(path)["recording_stats"]["seq_gaps"] == "0":
            break
    return path


@pytest.mark.parametrize("node", ["reid", "prediction"])
def test_replay_verifies_with_zero_mismatches(recording, node, tmp_path):
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(recording), "--node", node, "--verify", "--report", str(report_path),
                           timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    report = json.loads(report_path.read_text())
    assert report["frames"] > 100 and report["recording_first_frame"] == 0 and "mid-run" not in result.stdout
    assert report["outputs_compared"] > 100 and report["mismatch_count"] == 0
    assert not report["missing"] and not report["extra"] and not report["timeouts"]


def test_isolated_replay_of_the_deployed_node_verifies(recording, tmp_path):
    """--isolated: reid as its own process on a private loopback port, stepped in lockstep with the in-process
    run of the same node; same verdict, no frame waited for in vain."""
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(recording), "--node", "reid", "--isolated", "--verify", "--report",
                           str(report_path), timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    report = json.loads(report_path.read_text())
    assert report["mode"] == "isolated" and report["node_exit"] == 0 and not report["timeouts"]
    assert report["outputs_compared"] > 100 and report["mismatch_count"] == 0
    assert not report["missing"] and not report["extra"]


def test_two_nodes_replay_together(recording, tmp_path):
    """reid and prediction in one replay: the prior and the measurement go between them in-process, only
    detections, frames and templates come from the recording; every output of both is reproduced."""
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(recording), "--node", "reid,prediction", "--verify", "--report",
                           str(report_path), timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    report = json.loads(report_path.read_text())
    assert set(report["params"]) == {"reid", "prediction"}
    assert report["outputs_compared"] > 300 and report["mismatch_count"] == 0
    assert not report["missing"] and not report["extra"]
    changed = run_followbus("replay", str(recording), "--node", "reid,prediction", "--verify", "--param",
                            "prediction.gate_chi2=0.5", timeout=180)
    assert changed.returncode == 1, changed.stdout


def test_two_nodes_replay_through_a_frame_the_recorder_dropped(recording, tmp_path):
    """A recorder under load dropped capture frame k: re-ID cannot handle k, so its recorded measurement k stands
    in for prediction (which else waited for it, and every later output went missing), and re-ID's next outputs,
    which compare frame k+1 with k, may differ while it re-converges; the replay passes."""
    from followbus.bus.recording import stored_frame
    from followbus.replay.feed import frame_and_stamp as _header

    measured = sorted(_header(m.data)[0] for m in _bus(recording, "rt/reid/measurement"))
    dropped = measured[len(measured) // 2]
    lacking = tmp_path / "lacking.mcap"
    copy_recording(recording, lacking, library="test: the recorder dropped a frame",
                   keep=lambda channel, message: not (channel.topic == "rt/capture/frame"
                                                      and _header(stored_frame(message.data))[0] == dropped))
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(lacking), "--node", "reid,prediction", "--verify", "--report",
                           str(report_path), timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    report = json.loads(report_path.read_text())
    assert report["stand_ins"] >= 1 and report["unverifiable"] >= 1 and "stood in:" in result.stdout
    assert report["outputs_compared"] > 300 and report["mismatch_count"] == 0
    assert not report["missing"] and not report["extra"]


def test_two_nodes_replay_with_detections_late_in_the_recording(recording, tmp_path):
    """On a loaded machine the detector answers frame k after frame k+1 was captured: its detections come out of the
    recording behind the next frame's inputs. That is no lost frame: nothing stands in for re-ID, and the replay
    passes (a replay that judged by the frame's group told re-ID to skip such frames: 357 mismatches, a CI run)."""
    import followbus.msgs.perception  # noqa: F401  (Detections decodes)
    from followbus.bus.codec import frame_to_record, record_to_frame
    from followbus.bus.schemas import decode, encode

    late = set(_steady_frames(recording, 10))

    def rewrite(channel, data: bytes) -> bytes:
        if channel.topic != "rt/detection/detections":
            return data
        msg = decode(record_to_frame(data))
        if msg.header.frame_seq not in late:
            return data
        msg.header.pub_ns = msg.header.stamp_ns + 83_000_000  # published 2.5 frame periods after its capture
        return frame_to_record(encode(msg))

    delayed = tmp_path / "late.mcap"
    copy_recording(recording, delayed, rewrite=rewrite, library="test: detections published late")
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(delayed), "--node", "reid,prediction", "--verify", "--report",
                           str(report_path), timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    report = json.loads(report_path.read_text())
    assert report["late_inputs"] >= 5 and report["stand_ins"] == 0
    assert report["mismatch_count"] == 0 and not report["missing"] and report["outputs_compared"] > 300


def test_changed_parameter_is_reported_as_a_mismatch(recording, tmp_path):
    result = run_followbus("replay", str(recording), "--node", "reid", "--verify", "--param", "gamma=3.0",
                           timeout=120)
    assert result.returncode == 1, result.stdout
    first = result.stdout.split("first mismatch: frame", 1)[1].splitlines()[0]
    assert "rt/reid/measurement" in first and "field" in first, first


def test_frames_whose_joined_feedback_the_recorder_missed_are_not_verifiable(recording, tmp_path):
    """The recorder stopped between re-ID's last measurements and prediction's last tracks (SIGINT does that):
    the frames that joined a measurement absent from the recording cannot be reproduced, so they are counted as
    not verifiable, not as missing (the flake of the fallback test below was this)."""
    from followbus.bus.recording import stored_frame
    from followbus.replay.feed import frame_and_stamp as _header

    # From the fifth-last recorded track on: under load the recorder can stop before prediction's last tracks as
    # well (beside a second graph the last two were missing), and a frame without a recorded track has nothing to
    # verify.
    cut = sorted(_header(m.data)[0] for m in _bus(recording, "rt/prediction/track"))[-5]

    def keep(channel, message) -> bool:
        return not (channel.topic == "rt/reid/measurement" and _header(stored_frame(message.data))[0] >= cut)

    result, report = _verify_prediction_without(recording, tmp_path, keep,
                                                "test: the recorder stopped before re-ID's last outputs")
    assert report["unverifiable"] >= 5 and not report["missing"] and report["mismatch_count"] == 0
    assert "not verifiable:" in result.stdout


def test_frames_whose_chosen_odometry_the_recorder_dropped_are_not_verifiable(recording, tmp_path):
    """Prediction notes which odometry sample (by stamp) each frame used; when the recorder dropped that sample
    under load (a CI run: two samples missing from a 100 Hz stream), the replay cannot repeat the choice, and
    calls the frame not verifiable instead of a mismatch."""
    from followbus.bus.codec import peek
    from followbus.bus.recording import stored_frame

    chosen = set()
    for message in _bus(recording, "rt/prediction/prior"):
        head = peek(message.data)
        if 100 <= head.header.frame_seq < 104 and head.header.feedback.get("odometry", -1) >= 0:
            chosen.add(head.header.feedback["odometry"])
    assert chosen, "no prior noted an odometry sample"

    def keep(channel, message) -> bool:
        return not (channel.topic == "rt/motor/odometry"
                    and peek(stored_frame(message.data)).header.stamp_ns in chosen)

    _result, report = _verify_prediction_without(recording, tmp_path, keep,
                                                 "test: the recorder dropped odometry samples")
    assert report["unverifiable"] >= 1 and not report["missing"] and report["mismatch_count"] == 0


def _verify_prediction_without(recording, tmp_path, keep, library: str) -> tuple[subprocess.CompletedProcess, dict]:
    """`replay --node prediction --verify` of a copy of ``recording`` holding only what ``keep`` keeps (messages a
    recorder lost): it must pass; returns the run and its report."""

    lacking = tmp_path / "lacking.mcap"
    copy_recording(recording, lacking, keep=keep, library=library)
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(lacking), "--node", "prediction", "--verify", "--report",
                           str(report_path), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    return result, json.loads(report_path.read_text())


def _steady_frames(path, count: int) -> list[int]:
    """``count`` consecutive frames, from the middle of the recording on (else before it), on which the live loop
    kept pace: each prior joined the measurement of the frame before. On a loaded machine a live run also has
    stretches in which priors joined an older measurement while re-ID fell behind
    (test_a_live_fallback_is_replayed_exactly). Here the detections alone are late: delayed inside such a stretch
    they can reorder prediction's inputs against the live run's, and its outputs then differ in the last digits (a
    known limitation: docs/recording-and-replay.md)."""
    import followbus.msgs.tracking  # noqa: F401  (Prior decodes)
    from followbus.bus.codec import record_to_frame
    from followbus.bus.schemas import decode

    steady = sorted(msg.header.frame_seq for msg in (decode(record_to_frame(m.data))
                                                     for m in _bus(path, "rt/prediction/prior"))
                    if msg.header.feedback.get("measurement") == msg.header.frame_seq - 1)
    start = len(steady) // 2
    for i in [*range(start, len(steady) - count - 2), *range(start)]:
        window = steady[i:i + count + 4]  # two steady frames on each side too
        if len(window) == count + 4 and window[-1] - window[0] == count + 3:
            return window[2:2 + count]
    pytest.skip("the live run never kept pace for 14 frames in a row: nothing to delay")


def _bus(path, key: str):
    from followbus.bus.recording import iter_bus_messages

    return list(iter_bus_messages(path, [key]))


def test_a_recording_started_mid_run_is_named_as_such(recording, tmp_path):
    """A recorder attached to a running graph misses the node's history: replay says so instead of leaving
    the user with an unexplained mismatch."""
    from followbus.bus.recording import bus_channels, iter_bus_messages, read_metadata
    from followbus.replay.feed import frame_and_stamp as _header
    from followbus.tools.recording.mcap_io import RecordingWriter

    cut = 40
    late = tmp_path / "late.mcap"
    writer = RecordingWriter(late)
    for name, data in read_metadata(recording).items():
        writer.metadata(name, data)
    types = bus_channels(recording)
    for msg in iter_bus_messages(recording):
        if _header(msg.data)[0] >= cut:
            writer.write(writer.bus_channel(msg.key, types[msg.key] or None), msg.log_time, msg.data)
    writer.finish()
    report_path = tmp_path / "report.json"
    result = run_followbus("replay", str(late), "--node", "prediction", "--report", str(report_path), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    assert json.loads(report_path.read_text())["recording_first_frame"] == cut
    assert f"starts at frame {cut} of the run (recorded mid-run)" in result.stdout


def _stopper(node: str, seconds: float = 1.0):
    """``during`` for :func:`_record`: SIGSTOP the node's process for ``seconds``, then SIGCONT."""

    def stop(graph) -> None:
        pids = processes_matching(f"node {node} --graph {graph}")
        assert pids, f"{node} is not running"
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
        time.sleep(seconds)
        for pid in pids:
            os.kill(pid, signal.SIGCONT)

    return stop


def test_a_live_fallback_is_replayed_exactly(tmp_path):
    """reid stopped for a second live: prediction goes on without its measurements (one timeout, then no
    waiting), reid then skips its backlog to the newest frame. The outputs carry which feedback each frame
    joined, the recording keeps which frames were skipped, and a lockstep replay of either node does the
    same, with zero mismatches."""

    path = _record(tmp_path, "rf", 60, _stopper("reid"))
    for node in ("prediction", "reid"):
        report_path = tmp_path / f"{node}.json"
        result = run_followbus("replay", str(path), "--node", node, "--verify", "--report", str(report_path),
                               timeout=180)
        assert result.returncode == 0, result.stdout + result.stderr[-2000:]
        report = json.loads(report_path.read_text())
        assert report["mismatch_count"] == 0 and report["outputs_compared"] > 100
        if node == "prediction":
            assert report["hints"] > 0, "the stop should have made prediction fall back live"


def test_a_lost_optional_input_is_replayed_exactly(tmp_path):
    """egomotion stopped for a second live: prediction waits for its transform once, then goes on without it
    (bus/sync.py: an optional input that missed a deadline is not waited for) until egomotion is on time again.
    The priors note which sets lacked the transform (-1), and a lockstep replay of prediction lacks exactly
    those, whatever its own arrival order, with zero mismatches."""
    from followbus.bus.recording import iter_bus_messages
    from followbus.bus.schemas import decode
    from followbus.msgs.tracking import Prior

    path = _record(tmp_path, "ro", 60, _stopper("egomotion"))
    priors = [decode(m.data, Prior) for m in iter_bus_messages(path, ["ro/prediction/prior"])]
    lacked = [p.header.frame_seq for p in priors if p.header.feedback.get("transform") == -1]
    assert len(lacked) > 10, "the stop should have made prediction go on without transforms"
    assert len(lacked) < len(priors) - 30, "prediction should wait for transforms again once egomotion is back"
    report_path = tmp_path / "prediction.json"
    result = run_followbus("replay", str(path), "--node", "prediction", "--verify", "--report", str(report_path),
                           timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    report = json.loads(report_path.read_text())
    assert report["mismatch_count"] == 0 and report["outputs_compared"] > 100


def test_the_first_recorded_frame_is_found_behind_seconds_of_frameless_messages(tmp_path):
    """On a loaded machine the motor's 100 Hz odometry fills a recording's first seconds before the camera's
    frame 0: the replay must still find frame 0 there, not call the recording "started mid-run"."""
    from followbus.bus.schemas import Tick, encode
    from followbus.replay.feed import recording_first_frame
    from followbus.tools.recording.mcap_io import RecordingWriter

    path = tmp_path / "late-camera.mcap"
    writer = RecordingWriter(path)
    odometry, frames = writer.bus_channel("t/motor/odometry", "Tick"), writer.bus_channel("t/capture/frame", "Tick")
    stamp = 1_000_000_000
    for _ in range(500):  # 5 s of frameless messages first
        stamp += 10_000_000
        msg = Tick(value=0)
        msg.header.stamp_ns = stamp
        writer.write(odometry, stamp, encode(msg))
    for seq in range(4):
        msg = Tick(value=seq)
        msg.header.stamp_ns, msg.header.frame_seq = stamp + 1 + seq, seq
        writer.write(frames, stamp + 1 + seq, encode(msg))
    writer.finish()
    assert recording_first_frame(path) == 0
