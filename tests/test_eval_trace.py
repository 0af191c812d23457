"""followbus eval --trace / --video: every frame of a run as files (JSON Lines, OTB result files, an MP4)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from followbus.evaluation.render import render_run
from followbus.evaluation.runner import method_factories, open_sequence, run_sequence
from followbus.evaluation.trace import Episode, worst_episode, write_otb_result, write_run_files

FRAMES = 12


def test_worst_episode_is_the_longest_failure_and_says_what_was_followed() -> None:
    gt = [(0.0, 0.0, 10.0, 20.0)] * 10
    other = (100.0, 0.0, 10.0, 20.0)
    boxes = [gt[0], None, None, gt[0], other, other, other, None, gt[0], gt[0]]
    others = [[other]] * 10
    assert worst_episode(boxes, gt, others) == Episode(4, 4, "another person")
    # frames without a target neither fail nor end the run
    gt_gap = [*gt[:5], None, *gt[6:]]
    assert worst_episode(boxes, gt_gap, others) == Episode(4, 4, "another person")
    assert worst_episode(gt, gt, others) is None
    assert worst_episode([None] * 3, gt[:3], [[]] * 3) == Episode(0, 3, "no output")


def test_otb_result_file_rows(tmp_path: Path) -> None:
    path = write_otb_result(tmp_path / "r.txt", [(1.0, 2.0, 3.0, 4.0), None])
    assert path.read_text().splitlines() == ["1.00,2.00,3.00,4.00", "0,0,0,0"]


@pytest.fixture(scope="module")
def traced_run():
    seq = open_sequence("scene:lookalike", max_frames=FRAMES)
    return run_sequence(seq, method_factories(["followbus", "kalman"], trace=True), "simulated")


def test_trace_has_every_frame_with_prior_gate_candidates_and_camera_motion(traced_run, tmp_path: Path) -> None:
    written = write_run_files(traced_run, tmp_path)
    trace = tmp_path / "trace" / "scene-lookalike" / "followbus.jsonl"
    assert trace in written
    rows = [json.loads(line) for line in trace.read_text().splitlines()]
    assert [r["frame"] for r in rows] == list(range(FRAMES))
    later = rows[-1]
    assert later["state"] == "TRACKING" and later["box"] is not None and later["gt"] is not None
    gate = later["prior"]["gate"]
    assert gate["radius_px"] >= gate["b_px"] > 0 and len(later["prior"]["covariance"]) == 4
    assert later["candidates"] and {"s_color", "s_geo", "m_fuse", "identity", "source"} <= set(later["candidates"][0])
    assert later["camera_motion"]["valid"] and later["camera_motion"]["inliers"] > 0
    assert later["reason"].startswith("TRACKING: accepted detection")
    kalman = [json.loads(line) for line in (trace.parent / "kalman.jsonl").read_text().splitlines()]
    assert len(kalman) == FRAMES and "prior" not in kalman[-1]
    otb = (tmp_path / "tracker_results" / "followbus" / "scene-lookalike.txt").read_text().splitlines()
    assert len(otb) == FRAMES and all(len(r.split(",")) == 4 for r in otb)


def test_video_decodes_with_every_frame(traced_run, tmp_path: Path) -> None:
    path = tmp_path / "run.mp4"
    assert render_run(traced_run, "followbus", path) == FRAMES
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while (frame := cap.read())[0]:
        decoded.append(frame[1])
    cap.release()
    assert len(decoded) == FRAMES
    assert decoded[0].shape == (traced_run.sequence.height, traced_run.sequence.width, 3)
