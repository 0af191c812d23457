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


def test_offset_input_feeds_the_next_frame():
    sync = FrameSynchronizer([SyncInput("dets"), SyncInput("template", offset=-1, optional=True)], 50 * MS)
    sync.add("dets", 5, "d5", 0)
    sync.add("template", 4, "t4", 1 * MS)
    assert sync.poll(1 * MS) == [(5, {"dets": "d5", "template": "t4"})]


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
