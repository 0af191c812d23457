"""The capture node's MCAP source: raw frames and ground truth of a recording, in order, with the
original frame spacing."""

from __future__ import annotations

import numpy as np
import pytest

from followbus.bus.schemas import Frame
from followbus.msgs.perception import Detections, GroundTruth
from followbus.nodes.capture import McapFrameSource
from followbus.tools.recording.mcap_io import RecordingWriter

T0 = 1_700_000_000_000_000_000
DT = 33_333_333


def _record(path, frames: int) -> None:
    writer = RecordingWriter(path)
    frame_ch = writer.bus_channel("fb/capture/frame", "Frame")
    truth_ch = writer.bus_channel("fb/capture/ground_truth", "GroundTruth")
    dets_ch = writer.bus_channel("fb/detection/detections", "Detections")
    for k in range(frames):
        stamp = T0 + k * DT
        gt = GroundTruth(available=True, box=np.array([10.0 + k, 20.0, 30.0, 60.0]) if k != 2 else None,
                         visible_fraction=0.0 if k == 2 else 1.0, others=np.array([[100.0, 20, 30, 60]]),
                         others_visible=np.array([0.5]))
        frame = Frame(width=8, height=6, data=np.full((6, 8, 3), k, np.uint8))
        for msg in (gt, frame, Detections()):
            msg.header.stamp_ns, msg.header.frame_seq = stamp, 100 + k
        writer.write(truth_ch, stamp, gt.encode())
        writer.write(frame_ch, stamp, frame.encode())
        writer.write(dets_ch, stamp, Detections().encode())
    writer.finish()


def test_mcap_source_replays_frames_and_ground_truth(tmp_path):
    path = tmp_path / "run.mcap"
    _record(path, 5)
    source = McapFrameSource(str(path))
    assert source.frame_key == "fb/capture/frame" and source.has_ground_truth
    assert source.fps == pytest.approx(30.0, rel=1e-3)
    items = list(source)
    assert [i.index for i in items] == [0, 1, 2, 3, 4]
    assert [i.t_ns for i in items] == [k * DT for k in range(5)]
    assert [int(i.bgr[0, 0, 0]) for i in items] == [0, 1, 2, 3, 4]
    assert items[0].gt_box == (10.0, 20.0, 30.0, 60.0) and items[2].gt_box is None
    assert items[1].extras["distractor_boxes"] == [[100.0, 20.0, 30.0, 60.0]]
    assert items[3].extras["recorded_frame_seq"] == 103


def test_mcap_source_rejects_a_recording_without_frames(tmp_path):
    path = tmp_path / "noframes.mcap"
    writer = RecordingWriter(path)
    writer.write(writer.bus_channel("fb/detection/detections", "Detections"), T0, Detections().encode())
    writer.finish()
    with pytest.raises(ValueError, match="no frame channel"):
        McapFrameSource(str(path))
