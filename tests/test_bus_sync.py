"""The frame synchroniser (pure logic, explicit clock)."""

from __future__ import annotations

from followbus.bus.sync import FrameSynchronizer, SyncInput

MS = 1_000_000


def test_joins_inputs_of_the_same_frame():
    sync = FrameSynchronizer([SyncInput("frame"), SyncInput("dets")], timeout_ns=100 * MS)
    sync.add("frame", 1, "f1", 0)
    sync.add("frame", 2, "f2", 1 * MS)
    assert sync.poll(2 * MS) == []
    sync.add("dets", 1, "d1", 3 * MS)
    assert sync.poll(3 * MS) == [(1, {"frame": "f1", "dets": "d1"})]
    sync.add("dets", 2, "d2", 4 * MS)
    assert sync.poll(4 * MS) == [(2, {"frame": "f2", "dets": "d2"})]


def test_feedback_input_comes_from_the_previous_handled_frame():
    sync = FrameSynchronizer([SyncInput("dets"), SyncInput("template", offset=-1, optional=True)], 50 * MS)
    sync.add("dets", 4, "d4", 0)
    assert sync.poll(0) == [(4, {"dets": "d4", "template": None})]  # the first frame waits for nothing
    sync.add("dets", 5, "d5", 1 * MS)
    assert sync.poll(1 * MS) == []  # waits for the template learnt on frame 4
    sync.add("template", 4, "t4", 2 * MS)
    assert sync.poll(2 * MS) == [(5, {"dets": "d5", "template": "t4"})]
    # The detector skipped frames 6 and 7: frame 8 joins the template of frame 5, not of frame 7.
    sync.add("dets", 8, "d8", 3 * MS)
    sync.add("template", 5, "t5", 4 * MS)
    assert sync.poll(4 * MS) == [(8, {"dets": "d8", "template": "t5"})]
    assert sync.timeouts == 0 and sync.dropped == 0


def test_missing_feedback_times_out_when_optional():
    sync = FrameSynchronizer([SyncInput("dets"), SyncInput("meas", offset=-1, optional=True)], 10 * MS)
    sync.add("dets", 1, "d1", 0)
    sync.poll(0)
    sync.add("dets", 2, "d2", 1 * MS)
    assert sync.poll(5 * MS) == []
    assert sync.poll(11 * MS) == [(2, {"dets": "d2", "meas": None})]
    assert sync.timeouts == 1


def test_timeout_emits_without_optional_and_drops_without_required():
    sync = FrameSynchronizer([SyncInput("a"), SyncInput("b", optional=True)], timeout_ns=10 * MS)
    sync.add("a", 1, "a1", 0)
    assert sync.poll(9 * MS) == []
    assert sync.poll(10 * MS) == [(1, {"a": "a1", "b": None})]
    assert sync.timeouts == 1

    sync2 = FrameSynchronizer([SyncInput("a"), SyncInput("b")], timeout_ns=10 * MS)
    sync2.add("b", 1, "b1", 0)
    assert sync2.poll(11 * MS) == []
    assert sync2.dropped == 1 and sync2.pending == 0


def test_newer_complete_frame_supersedes_an_incomplete_one_and_late_data_is_stale():
    sync = FrameSynchronizer([SyncInput("frame"), SyncInput("dets")], timeout_ns=100 * MS)
    sync.add("frame", 1, "f1", 0)  # the detector skips frame 1
    sync.add("frame", 2, "f2", 1 * MS)
    sync.add("dets", 2, "d2", 2 * MS)
    assert sync.poll(2 * MS) == [(2, {"frame": "f2", "dets": "d2"})]
    assert sync.dropped == 1
    sync.add("dets", 1, "d1", 3 * MS)  # too late: frame 2 was already handled
    assert sync.poll(3 * MS) == [] and sync.pending == 0


def test_missing_feedback_does_not_cascade_into_dropping_newer_frames():
    sync = FrameSynchronizer([SyncInput("dets"), SyncInput("meas", offset=-1, optional=True)], 10 * MS)
    sync.add("dets", 1, "d1", 0)
    assert [seq for seq, _ in sync.poll(0)] == [1]
    for seq in (2, 3, 4):  # the measurement of frame 1 is lost; detections keep coming
        sync.add("dets", seq, f"d{seq}", seq * MS)
    assert sync.poll(5 * MS) == [] and sync.dropped == 0
    # Frame 2 goes on without it after the timeout; frame 3 then waits for frame 2's measurement.
    assert sync.poll(12 * MS) == [(2, {"dets": "d2", "meas": None})]
    sync.add("meas", 2, "m2", 13 * MS)
    assert sync.poll(13 * MS) == [(3, {"dets": "d3", "meas": "m2"})]
    sync.add("meas", 3, "m3", 14 * MS)
    assert sync.poll(14 * MS) == [(4, {"dets": "d4", "meas": "m3"})]
    assert sync.dropped == 0 and sync.timeouts == 1
