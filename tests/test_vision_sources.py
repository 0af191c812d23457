"""Frame sources: SOT/MOT folders, synthetic scenes, video files, spec parsing, sequence listing."""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.vision.models import REPO_ROOT
from followbus.vision.sources import (
    ImageFolderSource,
    SceneSource,
    VideoFileSource,
    list_sequences,
    open_source,
    read_mot_groundtruth,
)

DATA_ROOT = Path(os.environ.get("FOLLOWBUS_DATA", REPO_ROOT.parent / "shared" / "data"))


def _shared(rel: str) -> Path:
    p = DATA_ROOT / rel
    if not p.is_dir():
        pytest.skip(f"shared data absent: {p} (set FOLLOWBUS_DATA)")
    return p


def _write_sot(root: Path, rows: list[str], fps: int = 12) -> Path:
    (root / "img").mkdir(parents=True)
    for i in range(len(rows)):
        cv2.imwrite(str(root / "img" / f"{i + 1:06d}.png"), np.full((24, 32, 3), 10 * i, np.uint8))
    (root / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    (root / "meta.json").write_text(f'{{"fps": {fps}}}')
    return root


def test_sot_folder_nan_rows_are_absent(tmp_path: Path) -> None:
    seq = _write_sot(tmp_path / "sot" / "toy", ["1,2,3,4", "NaN,NaN,NaN,NaN", "5\t6\t7\t8"])
    src = ImageFolderSource(seq)
    frames = list(src)
    assert src.layout == "sot" and len(src) == 3 and src.fps == 12
    assert [f.gt_box for f in frames] == [(1.0, 2.0, 3.0, 4.0), None, (5.0, 6.0, 7.0, 8.0)]
    assert [f.t_ns for f in frames] == [0, round(1e9 / 12), round(2e9 / 12)]
    assert frames[2].bgr.shape == (24, 32, 3) and int(frames[2].bgr[0, 0, 0]) == 20
    assert ImageFolderSource(seq, fps=50).fps == 50  # explicit fps beats meta.json


def test_real_sot_sequence() -> None:
    seq = _shared("sot/otb-crossing")
    src = ImageFolderSource(seq)
    assert len(src) == 120 and src.fps == 30
    first = next(iter(src))
    assert first.gt_box == (205.0, 151.0, 17.0, 50.0)
    assert first.bgr.shape == (240, 360, 3)
    assert first.extras["path"].endswith("000001.jpg")


def test_real_mot_sequence_exposes_all_boxes() -> None:
    seq = _shared("mot/tud-campus")
    src = ImageFolderSource(seq)
    assert src.layout == "mot" and src.fps == 25 and len(src) == 71
    frames = list(itertools.islice(src, 3))
    gt_rows = [ln.split(",") for ln in (seq / "gt" / "gt.txt").read_text().splitlines()]
    frame1 = sorted((int(r[1]), float(r[2]), float(r[3]), float(r[4]), float(r[5])) for r in gt_rows
                    if int(r[0]) == 1)
    assert sorted(frames[0].extras["gt_all"]) == frame1 and len(frame1) >= 2
    assert frames[1].t_ns == 40_000_000  # 25 fps
    assert frames[0].gt_box is None  # no single target unless asked for
    tid = frame1[0][0]
    assert ImageFolderSource(seq, target_id=tid).ground_truth(0)[0] == frame1[0][1:]


def test_mot_filter_follows_the_evaluation_rules(tmp_path: Path) -> None:
    gt = tmp_path / "gt.txt"
    gt.write_text("1,1,10,20,30,60,1,1,1.0\n"  # pedestrian
                  "1,2,50,20,30,60,0,1,1.0\n"  # flagged "ignore"
                  "1,3,90,20,30,60,1,3,1.0\n"  # a car
                  "2,1,12,20,30,60,-1,-1,-1\n")  # unlabelled class (TUD style) counts as a person
    assert read_mot_groundtruth(gt) == {1: [(1, 10.0, 20.0, 30.0, 60.0)], 2: [(1, 12.0, 20.0, 30.0, 60.0)]}
    assert len(read_mot_groundtruth(gt, all_classes=True)[1]) == 3


def test_mot17_ignore_rows_are_dropped() -> None:
    seq = _shared("mot/mot17-mini-13")
    gt_file = seq / "gt" / "gt.txt"
    kept = sum(len(v) for v in read_mot_groundtruth(gt_file).values())
    everything = sum(len(v) for v in read_mot_groundtruth(gt_file, all_classes=True).values())
    pedestrians = sum(1 for ln in gt_file.read_text().splitlines()
                      if ln.split(",")[6] != "0" and ln.split(",")[7] == "1")
    assert kept == pedestrians < everything


def test_scene_source_stamps_and_truth() -> None:
    src = SceneSource("wall-occlusion", seed=2)
    frames = list(itertools.islice(src, 4))
    assert len(src) == 240 and src.fps == 30
    assert [f.t_ns for f in frames] == [round(i * 1e9 / 30) for i in range(4)]
    assert frames[0].gt_box is not None and frames[0].extras["visible_fraction"] == 1.0
    assert frames[0].extras["people"][0] == (frames[0].gt_box, 1.0)
    assert frames[0].extras["ego_velocity_mps"] == (0.0, 0.0)


def test_video_file_source(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 12.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG/AVI")
    for i in range(5):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    src = open_source(str(path))
    assert isinstance(src, VideoFileSource) and src.fps == 12
    frames = list(src)
    assert len(frames) == 5 and frames[-1].t_ns == round(4e9 / 12)
    assert abs(int(frames[3].bgr.mean()) - 120) < 6


def test_open_source_specs(tmp_path: Path) -> None:
    assert isinstance(open_source("scene:lookalike", seed=1), SceneSource)
    seq = _write_sot(tmp_path / "seq", ["1,2,3,4"])
    assert isinstance(open_source(str(seq)), ImageFolderSource)
    for bad in ("camera:front", "scene:nope", "run.mcap", str(tmp_path / "missing.mp4"), "ftp://x"):
        with pytest.raises(ValueError):
            open_source(bad)


def test_list_sequences(tmp_path: Path) -> None:
    _write_sot(tmp_path / "sot" / "b", ["1,2,3,4"])
    _write_sot(tmp_path / "sot" / "a", ["1,2,3,4"])
    (tmp_path / "sot" / "not-a-seq").mkdir()
    (tmp_path / "mot" / "m1" / "img1").mkdir(parents=True)
    assert [p.relative_to(tmp_path).as_posix() for p in list_sequences(tmp_path)] == ["sot/a", "sot/b", "mot/m1"]
    if DATA_ROOT.is_dir():
        names = {f"{p.parent.name}/{p.name}" for p in list_sequences(DATA_ROOT)}
        assert {"sot/otb-crossing", "mot/tud-campus"} <= names
