"""``followbus eval --group --camera`` (evaluation/group_camera.py): seed 004's group trackers on camera data."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from followbus.evaluation.group_camera import (
    PERSON_HEIGHT_M,
    CameraSequence,
    boxes_to_points,
    format_camera_table,
    group_truth,
    run_camera_method,
    scale_from_first_frame,
)
from followbus.tracking.group import METHODS
from tests.conftest import REPO, SHARED, run_followbus

TUD = SHARED / "data" / "mot" / "tud-campus"


def test_group_truth_is_the_centroid_of_the_annotated_box_centres() -> None:
    people = [[(1, (0.0, 0.0, 10.0, 20.0)), (2, (100.0, 50.0, 20.0, 40.0))], []]
    c, h = group_truth(people)
    np.testing.assert_allclose(c[0], [(5 + 110) / 2, (10 + 70) / 2])
    assert h[0] == pytest.approx(30.0)
    assert np.all(np.isnan(c[1])) and math.isnan(h[1])


def test_points_are_box_centres_scaled_by_a_person_height() -> None:
    dets = [np.zeros((0, 5)), np.array([[10.0, 20.0, 40.0, 170.0, 0.9], [50.0, 20.0, 40.0, 170.0, 0.8]])]
    m_per_px = scale_from_first_frame(dets)
    assert m_per_px == pytest.approx(PERSON_HEIGHT_M / 170.0)
    pts, covs = boxes_to_points(dets[1], m_per_px)
    np.testing.assert_allclose(pts[0], [30.0 * m_per_px, 105.0 * m_per_px])
    assert covs.shape == (2, 2, 2) and covs[0, 0, 0] == pytest.approx((0.1 * 1.7) ** 2)


def _walking_group(n_frames: int, rng: np.random.Generator) -> CameraSequence:
    """Five people 150 px tall walking right at 6 px/frame in a loose row, each detection jittered, one
    of them missed at random; a passer-by far away from frame 10 on; truth = the centroid of the five."""
    slots = np.array([[-120.0, 0.0], [-60.0, 10.0], [0.0, -10.0], [60.0, 5.0], [120.0, 0.0]])
    dets, gt = [], []
    for k in range(n_frames):
        centres = np.array([200.0 + 6 * k, 300.0]) + slots
        gt.append(centres.mean(axis=0))
        visible = centres[rng.random(5) > 0.2]
        seen = visible + rng.normal(0, 4.0, visible.shape)
        if k >= 10:
            seen = np.vstack([seen, [[1100.0, 100.0]]])
        boxes = np.column_stack([seen[:, 0] - 25, seen[:, 1] - 75, np.full(len(seen), 50.0),
                                 np.full(len(seen), 150.0), np.full(len(seen), 0.9)])
        dets.append(boxes)
    return CameraSequence("test/walking", 10.0, 1280, 720, "synthetic", np.array(gt), np.full(n_frames, 150.0), dets)


def test_group_trackers_follow_the_group_centre_in_the_image() -> None:
    cs = _walking_group(60, np.random.default_rng(0))
    res = {m: run_camera_method(m, cs) for m in METHODS}
    for m in ("ME-CGT-UGV", "RM-CGT-UGV", "CGT-UGV"):
        # A missed member moves the centroid of the seen ones by up to ~30 px; the shape trackers stay within
        # a fifth of a person height, and ignore the far passer-by.
        assert res[m].frames_scored == 57 and res[m].frames_without_estimate == 0
        assert res[m].rmse_heights < 0.2, (m, res[m])
    # Following one member is off by that member's place in the row; averaging everything takes in the
    # passer-by.
    assert res["SOT"].rmse_px > res["ME-CGT-UGV"].rmse_px
    assert res["CGT-Mean"].rmse_px > res["ME-CGT-UGV"].rmse_px
    table = format_camera_table({cs.name: (cs, res)})
    assert table.count("| test/walking |") == len(METHODS)


def _need_real_excerpt() -> None:
    if not (TUD / "gt" / "gt.txt").is_file():
        pytest.skip(f"{TUD} absent (camera data lives in ../shared/data, never in the repo)")
    if not (REPO / "models" / "yolox_nano_416.onnx").is_file():
        pytest.skip("models/yolox_nano_416.onnx absent")


def test_eval_group_camera_on_a_real_excerpt(tmp_path) -> None:
    """The command as a user runs it, on the first 12 frames of TUD-Campus with real YOLOX detections."""
    _need_real_excerpt()
    out = tmp_path / "cam"
    res = run_followbus("eval", "--group", "--camera", str(TUD), "--max-frames", "12", "--out", str(out),
                        timeout=120)
    assert res.returncode == 0, res.stderr
    rows = [line for line in res.stdout.splitlines() if line.startswith("| mot/tud-campus |")]
    assert [r.split("|")[4].strip() for r in rows] == list(METHODS)
    data = json.loads((out / "group_camera.json").read_text())
    seq = data["sequences"]["mot/tud-campus"]
    assert seq["frames"] == 12 and not seq["detections_from_cache"]
    for m, v in seq["methods"].items():
        assert v["frames_scored"] == 9 and v["frames_without_estimate"] == 0, m
        # Eight people walk through a 640x480 frame: every method's centre stays within one person height
        # of the annotated people's centroid over these frames.
        assert 0 < v["rmse_heights"] < 1.0, (m, v)
    # A second run reads the detections from the cache it wrote.
    again = run_followbus("eval", "--group", "--camera", str(TUD), "--max-frames", "12", "--out", str(out))
    assert again.returncode == 0
    assert json.loads((out / "group_camera.json").read_text())["sequences"]["mot/tud-campus"]["detections_from_cache"]


def test_eval_group_camera_mistakes_are_one_line(tmp_path) -> None:
    res = run_followbus("eval", "--group", "--camera", str(tmp_path / "nowhere"), "--out", str(tmp_path))
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0 and "nowhere" in res.stderr
    res = run_followbus("eval", "--camera", "--out", str(tmp_path))
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0
