"""Replay's parts without processes: the chunk reader against the mcap package's reader, the diff's measured
fields, and the feed's replay hints (a frame skipped live, the feedback a set joined) handed over before the
frame they concern. Hand-made recordings in tmp_path."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.reader import make_reader

from followbus.bus.recording import is_bus_channel, iter_bus_messages, stored_frame
from followbus.bus.schemas import Tick
from followbus.msgs.perception import Detections
from followbus.msgs.tracking import Measurement, Prior
from followbus.replay.diff import Tolerance, diff_messages
from followbus.replay.feed import Feed
from followbus.replay.plan import ReplayOptions, ReplayPlan
from followbus.tools.recording.mcap_io import RecordingWriter

from .conftest import REPO

T0 = 1_700_000_000_000_000_000
DT = 33_333_333


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_chunk_reader_gives_what_the_mcap_reader_gives(tmp_path, compression):
    """Same messages, same order (log time, ties by position), same filtering, whatever the compression; log
    times out of order across small chunks make the merge do work."""
    path = tmp_path / "r.mcap"
    writer = RecordingWriter(path, compression=compression, chunk_bytes=300)
    channels = [writer.bus_channel(f"t/n{i}/tick", "Tick") for i in range(3)]
    fox = writer.foxglove_channel("t/n0/tick/annotations", "foxglove.ImageAnnotations", "t/n0/tick")
    rng = np.random.default_rng(1)
    for k in range(200):
        tick = Tick(value=k)
        tick.header.seq, tick.header.stamp_ns = k, T0 + int(rng.integers(0, 50)) * DT  # ties and disorder
        writer.write(channels[k % 3], tick.header.stamp_ns, tick.encode(), sequence=k)
        if k % 10 == 0:
            writer.write(fox, tick.header.stamp_ns, b"{}")
    writer.finish()

    def reference(topics):
        with open(path, "rb") as f:
            return [(c.topic, m.log_time, m.sequence, stored_frame(m.data)) for _s, c, m in
                    make_reader(f).iter_messages(topics=topics, log_time_order=True) if is_bus_channel(c)]

    ours = [(m.key, m.log_time, m.sequence, m.data) for m in iter_bus_messages(path)]
    assert len(ours) == 200 and ours == reference(["t/n0/tick", "t/n1/tick", "t/n2/tick"])
    some = [(m.key, m.log_time, m.sequence, m.data) for m in iter_bus_messages(path, {"t/n1/tick"})]
    assert len(some) == 67 and some == reference(["t/n1/tick"])


def test_measured_fields_are_not_compared():
    recorded = Detections(boxes=np.array([[1, 2, 3, 4, 0.9]], np.float32), backend="yolox", infer_ms=12.5)
    same = Detections(boxes=recorded.boxes.copy(), backend="yolox", infer_ms=3.1)
    assert diff_messages(recorded, same, Tolerance()) is None  # the inference time of another run
    moved = Detections(boxes=np.array([[1, 2, 3, 5, 0.9]], np.float32), backend="yolox", infer_ms=12.5)
    diff = diff_messages(recorded, moved, Tolerance())
    assert diff is not None and diff.field == "boxes[0][3]"


def _stamped(msg, k: int, feedback: dict[str, int] | None = None):
    msg.header.frame_seq, msg.header.stamp_ns, msg.header.epoch_ns = k, T0 + k * DT, T0
    msg.header.pub_ns = T0 + k * DT + 5_000_000
    if feedback is not None:
        msg.header.feedback = feedback
    return msg


def _graph_recording(path) -> RecordingWriter:
    """A recording of graph.yaml's graph in namespace fb, to be written to."""
    writer = RecordingWriter(path)
    writer.metadata("graph", {"yaml": (REPO / "graph.yaml").read_text()})
    writer.metadata("followbus", {"namespace": "fb"})
    return writer


def _measurement(k: int, accepted: bool) -> bytes:
    from followbus.bus.schemas import encode

    return encode(_stamped(Measurement(state="TRACKING", accepted=accepted), k))


def _compared(node: str, expected: dict, produced: dict, incomplete: set[int]):
    """The report of the replay's comparison of ``node``'s ``expected`` and ``produced`` outputs alone."""
    from types import SimpleNamespace

    from followbus.replay.engine import Replayer
    from followbus.replay.plan import ReplayReport

    replayer = Replayer.__new__(Replayer)
    replayer.plan = SimpleNamespace(timer_topics=set(), key=lambda t: f"rt/{t}")
    replayer.opts = ReplayOptions(nodes=[node])
    replayer.report = ReplayReport(file="-", node=node)
    replayer._compare(expected, produced, set(), incomplete=incomplete)
    return replayer.report


def test_feed_hands_each_hint_over_before_its_frame(tmp_path):
    """prediction live: frame 2 skipped (no output), frame 4 joined the measurement of frame 1 (a late one).
    The feed says so before the inputs of those frames, and counts both as live fallbacks."""
    path = tmp_path / "p.mcap"
    writer = _graph_recording(path)
    dets = writer.bus_channel("fb/detection/detections", "Detections")
    meas = writer.bus_channel("fb/reid/measurement", "Measurement")
    prior = writer.bus_channel("fb/prediction/prior", "Prior")
    joined = {0: -1, 1: 0, 3: 1, 4: 1, 5: 4}  # frame -> measurement joined live
    for k in range(6):
        writer.write(dets, T0 + k * DT, _stamped(Detections(), k).encode())
        if k in joined:
            writer.write(prior, T0 + k * DT, _stamped(Prior(), k, {"measurement": joined[k]}).encode())
            writer.write(meas, T0 + k * DT, _stamped(Measurement(state="TRACKING"), k).encode())
    writer.finish()

    plan = ReplayPlan(path, ReplayOptions(nodes=["prediction"]))
    assert set(plan.inputs.values()) == {"detection/detections", "reid/measurement", "motor/odometry",
                                         "egomotion/transform"}
    feed = Feed(plan)
    told: dict[int, tuple[bool, dict[str, int]]] = {}
    for hints, frame_seq, _messages in feed.groups():
        told.update({h.header.frame_seq: (h.skip, dict(h.feedback)) for _node, h in hints})
        # What live did with this frame and with the next one it handled is known before its inputs.
        assert frame_seq in told or frame_seq == 0
        assert any(f > frame_seq for f in told) or frame_seq == 5
    assert told[2] == (True, {}) and told[4] == (False, {"measurement": 1})
    assert told[3] == (False, {"measurement": 1}) and told[5] == (False, {"measurement": 4})
    assert feed.hints_reproduced == 2  # the skip of 2, and 4 joining 1 instead of 3
    assert feed.outputs_expected == 5


def test_a_hint_to_join_a_measurement_the_recorder_lost_joins_none(tmp_path):
    """prediction live: each frame joined the measurement of the frame before; the recorder lost measurement 2.
    Told to join it, the replayed prediction would wait for a message that never comes, holding its sets back
    until they are pushed out (a demo recording, measurements 300-304 removed: 65 outputs never made). Frame 3 joins
    none instead; the feed still notes what it joined live, so the frame is not verifiable."""
    path = tmp_path / "p.mcap"
    writer = _graph_recording(path)
    dets = writer.bus_channel("fb/detection/detections", "Detections")
    meas = writer.bus_channel("fb/reid/measurement", "Measurement")
    prior = writer.bus_channel("fb/prediction/prior", "Prior")
    for k in range(6):
        writer.write(dets, T0 + k * DT, _stamped(Detections(), k).encode())
        writer.write(prior, T0 + k * DT, _stamped(Prior(), k, {"measurement": k - 1}).encode())
        if k != 2:
            writer.write(meas, T0 + k * DT, _stamped(Measurement(state="TRACKING"), k).encode())
    writer.finish()

    feed = Feed(ReplayPlan(path, ReplayOptions(nodes=["prediction"])))
    told: dict[int, dict[str, int]] = {}
    for hints, _frame_seq, _messages in feed.groups():
        told.update({h.header.frame_seq: dict(h.feedback) for _node, h in hints})
    assert told[3] == {"measurement": -1} and told[4] == {"measurement": 3} and told[2] == {"measurement": 1}
    assert ("fb/reid/measurement", 2) in feed.joined[3]  # what it joined live: the frame is not verifiable


def test_an_output_the_recorder_lost_is_not_taken_for_a_skipped_frame(tmp_path):
    """re-ID live: it handled frames 0-3, skipped 4, handled 5 and 6; the recorder lost its measurement of frame 2
    (header.seq 2). Frame 4 is a skip (no seq is missing there); frame 2 is not: a two-node replay told to skip it
    would leave prediction waiting for that measurement (a demo recording: 638 outputs missing from there on). It is
    not hinted, and not verifiable."""
    path = tmp_path / "r.mcap"
    writer = _graph_recording(path)
    meas = writer.bus_channel("fb/reid/measurement", "Measurement")
    dets = writer.bus_channel("fb/detection/detections", "Detections")
    for seq, k in enumerate((0, 1, 2, 3, 5, 6)):
        writer.write(dets, T0 + k * DT, _stamped(Detections(), k).encode())
        if k == 2:
            continue
        msg = _stamped(Measurement(state="TRACKING"), k, {"prior": k - 1})
        msg.header.seq = seq
        writer.write(meas, T0 + k * DT, msg.encode())
    writer.finish()

    feed = Feed(ReplayPlan(path, ReplayOptions(nodes=["reid", "prediction"])))
    told: dict[int, bool] = {}
    for hints, _frame_seq, _messages in feed.groups():
        told.update({h.header.frame_seq: h.skip for node, h in hints if node == "reid"})
    assert told.get(4) is True and 2 not in told and feed.lost_frames == {2}


def test_a_frame_input_the_recorder_lost_makes_its_frames_not_verifiable(tmp_path):
    """Beside a second graph the recorder dropped five of re-ID's measurements (header.seq 241-245) whose frames'
    tracks it kept: the replay called those tracks missing. A gap in a frame input's header.seq names the frames
    between the two messages read as lost; a publisher that restarted (another epoch) starts its seq again."""
    path = tmp_path / "p.mcap"
    writer = _graph_recording(path)
    meas = writer.bus_channel("fb/reid/measurement", "Measurement")
    for seq, k in enumerate((0, 1, 2, 3, 4, 5, 6, 9, 10)):
        if k in (3, 4):  # lost by the recorder; re-ID skipped 7 and 8 live
            continue
        msg = _stamped(Measurement(state="TRACKING"), k)
        msg.header.seq = seq
        if k == 10:  # re-ID restarted: a new epoch, its seq from 0
            msg.header.seq, msg.header.epoch_ns = 0, T0 + 1
        writer.write(meas, T0 + k * DT, msg.encode())
    writer.finish()

    feed = Feed(ReplayPlan(path, ReplayOptions(nodes=["prediction"])))
    for _group in feed.groups():
        pass
    assert feed.lost_frames == {3, 4}


def test_a_replay_keeps_off_the_live_graphs_state_file(tmp_path):
    """graph.yaml's template persists its state in state/{namespace}/template.npz: a replay of it neither starts
    from that file nor overwrites it (issue 23), unless --param names a state file."""
    path = tmp_path / "t.mcap"
    writer = _graph_recording(path)
    meas = writer.bus_channel("fb/reid/measurement", "Measurement")
    writer.write(meas, T0, _stamped(Measurement(state="TRACKING"), 0).encode())
    writer.finish()
    assert "state/{namespace}/template.npz" in (REPO / "graph.yaml").read_text()
    assert ReplayPlan(path, ReplayOptions(nodes=["template"])).params["template"]["state_file"] == ""
    given = ReplayPlan(path, ReplayOptions(nodes=["template"], params={"template": {"state_file": "mine.npz"}}))
    assert given.params["template"]["state_file"] == "mine.npz"


def test_differences_after_a_gap_are_forgiven_for_resync_frames():
    """A frame the recording lacks inputs of (frame 10) also shapes the next ones: differences there count as
    re-converging, not as mismatches, for RESYNC_FRAMES, also after an output that matched (a CI run: re-ID's
    state, TRACKING live, was REACQUIRED in the replay a few frames after matching states)."""

    from followbus.replay.engine import RESYNC_FRAMES

    topic = "reid/measurement"
    differs = {11, 13, 10 + RESYNC_FRAMES + 5}  # 11: re-converging; 13: after a match, still; the last: past it
    expected = {(topic, k): [_measurement(k, True)] for k in range(10, 10 + RESYNC_FRAMES + 10)}
    produced = {topic: [_measurement(k, k not in differs) for k in range(11, 10 + RESYNC_FRAMES + 10)]}
    report = _compared("reid", expected, produced, {10})
    assert report.unverifiable == 1 and report.after_gap == 2  # frame 10 itself, then frames 11 and 13
    assert report.mismatch_count == 1 and {m["frame_seq"] for m in report.mismatches} == {10 + RESYNC_FRAMES + 5}


def test_past_resync_frames_an_output_that_never_matched_since_the_gap_is_still_re_converging():
    """prediction after a measurement the recorder lost (a prior had joined it): its model probabilities forget the
    difference by a tenth a frame, so its outputs differ by 1e-4 px for some 100 frames, matching on a frame here and
    there. They re-converge until the key has matched on RESYNC_SETTLE_FRAMES frames in a row (at most
    RESYNC_MAX_FRAMES); a difference after that is a mismatch, and so is one past RESYNC_MAX_FRAMES."""

    from followbus.replay.engine import RESYNC_FRAMES, RESYNC_MAX_FRAMES, RESYNC_SETTLE_FRAMES
    from followbus.replay.plan import ReplayReport

    def compare(differs: set[int], last: int) -> ReplayReport:
        topic = "reid/measurement"
        expected = {(topic, k): [_measurement(k, True)] for k in range(10, last)}
        produced = {topic: [_measurement(k, k not in differs) for k in range(11, last)]}
        return _compared("prediction", expected, produced, {10})

    settles = 10 + 4 * RESYNC_FRAMES  # every frame before it differs but one
    after = settles + RESYNC_SETTLE_FRAMES + 2
    report = compare((set(range(11, settles)) - {settles - 20}) | {after}, after + 5)
    assert report.after_gap == settles - 12 and report.mismatch_count == 1
    assert report.mismatches[0]["frame_seq"] == after
    never = compare(set(range(11, 10 + RESYNC_MAX_FRAMES + 5)), 10 + RESYNC_MAX_FRAMES + 5)
    assert never.after_gap == RESYNC_MAX_FRAMES and never.mismatch_count == 4


def test_a_node_sampling_odometry_by_stamp_replays_the_sample_it_took_live(tmp_path):
    """groundplane live (graph.group.yaml), in-process: the odometry sample stamped just before frame k arrives after
    frame k's detections on odd frames, so those frames use the sample before it. The recording's odometry comes out
    of a replay in stamp order, ahead of each frame: only the sample the runtime noted live makes the replay take
    the same pose. The node keeps no buffer and writes no note of its own (In(..., sample_by_stamp=True))."""
    from followbus.bus.graph import load_graph
    from followbus.bus.inproc import InProcessGraph
    from followbus.msgs.robot import Odometry
    from followbus.replay.engine import Replayer

    graph = load_graph(REPO / "graph.group.yaml")
    frames = 8
    inputs: list[tuple[str, int, bytes]] = []  # (key, log time, message)
    with InProcessGraph(graph, nodes=["groundplane"], clock_start_ns=T0) as g:
        for k in range(frames):
            odom = Odometry(x_m=0.5 * k, y_m=0.1 * k, theta_rad=0.05 * k)
            odom.header.stamp_ns = odom.header.pub_ns = T0 + k * DT - 20_000_000
            dets = _stamped(Detections(boxes=np.array([[300, 200, 60, 180, 0.9]], np.float32)), k)
            late = k % 2 == 1
            for topic, msg in ([("detection/detections", dets), ("motor/odometry", odom)] if late else
                               [("motor/odometry", odom), ("detection/detections", dets)]):
                g.inject(topic, msg)
                g.deliver()
                inputs.append((f"fb/{topic}", msg.header.stamp_ns, msg.encode()))
        points = g.payloads("groundplane", "points")
    path = tmp_path / "g.mcap"
    writer = RecordingWriter(path)
    writer.metadata("graph", {"yaml": graph.text})
    writer.metadata("followbus", {"namespace": "fb"})
    channels = {key: writer.bus_channel(key, type_name) for key, type_name in (
        ("fb/detection/detections", "Detections"), ("fb/motor/odometry", "Odometry"),
        ("fb/groundplane/points", "GroundPoints"))}
    for key, log_time, data in inputs:
        writer.write(channels[key], log_time, data)
    for k, data in enumerate(points):
        writer.write(channels["fb/groundplane/points"], T0 + k * DT + 1, data)
    writer.finish()

    report = Replayer(path, ReplayOptions(nodes=["groundplane"], verify=True, progress=False)).run()
    assert report.outputs_compared == frames and report.matched == frames, report.mismatches[:3]
    assert report.ok(verify=True)
