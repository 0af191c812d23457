"""Dataset loaders: synthetic sequences always, the real evaluation data when it is present."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.evaluation.datasets import (
    choose_follow_target,
    find_data_root,
    list_sequences,
    load_mot_sequence,
    load_sequence,
    load_sot_sequence,
)


def _data_root() -> Path:
    try:
        root = find_data_root()
    except FileNotFoundError as exc:
        pytest.skip(f"FOLLOWBUS_DATA is set but unusable: {exc}")
    if root is None:
        pytest.skip("evaluation data absent (no $FOLLOWBUS_DATA, no ../shared/data next to the repo or cwd)")
    return root


def _write_image(path: Path, w: int, h: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.zeros((h, w, 3), np.uint8))


def _make_sot(root: Path, gt_lines: list[str], n_images: int | None = None, w: int = 64, h: int = 48) -> Path:
    d = root / "sot" / "toy"
    for i in range(n_images if n_images is not None else len(gt_lines)):
        _write_image(d / "img" / f"{i + 1:06d}.jpg", w, h)
    (d / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    (d / "meta.json").write_text('{"fps": 12.5, "name": "toy"}')
    return d


def test_synthetic_sot_nan_rows_become_none(tmp_path: Path) -> None:
    d = _make_sot(tmp_path, ["1,2,10,20", "NaN,NaN,NaN,NaN", "3\t4\t10\t20", "0,0,0,0", "5.5,6,10,20"])
    seq = load_sot_sequence(d)
    assert (seq.kind, seq.name, seq.frames, seq.fps, seq.width, seq.height) == ("sot", "toy", 5, 12.5, 64, 48)
    assert seq.gt_boxes == [(1, 2, 10, 20), None, (3, 4, 10, 20), None, (5.5, 6, 10, 20)]
    assert [len(p) for p in seq.all_gt] == [1, 0, 1, 0, 1]
    assert seq.other_boxes() == [[]] * 5
    assert [p.name for p in seq.image_paths] == [f"{i:06d}.jpg" for i in range(1, 6)]


def test_sot_image_gt_mismatch_fails(tmp_path: Path) -> None:
    d = _make_sot(tmp_path, ["1,2,10,20"] * 3, n_images=4)
    with pytest.raises(ValueError, match="4 images but 3"):
        load_sot_sequence(d)


def test_synthetic_mot_target_choice(tmp_path: Path) -> None:
    d = tmp_path / "mot" / "toy"
    for i in range(3):
        _write_image(d / "img1" / f"{i + 1:06d}.jpg", 100, 80)
    (d / "seqinfo.ini").write_text("[Sequence]\nname=toy\nimDir=img1\nframeRate=15\nseqLength=3\n"
                                   "imWidth=100\nimHeight=80\nimExt=.jpg\n")
    (d / "gt").mkdir()
    # frame 1 has no usable gt (conf 0 only); on frame 2 id 7 stands bottom-centre, id 3 far left, id 5 high up
    (d / "gt" / "gt.txt").write_text(
        "1,9,40,30,20,50,0,1,1\n"
        "2,3,0,30,20,50,1,1,1\n2,7,42,28,16,50,1,1,1\n2,5,40,0,20,40,1,1,1\n"
        "3,3,1,30,20,50,1,1,1\n")
    seq = load_mot_sequence(d)
    assert (seq.kind, seq.frames, seq.fps, seq.width, seq.height) == ("mot", 3, 15.0, 100, 80)
    assert seq.target_id == 7
    assert seq.gt_boxes == [None, (42, 28, 16, 50), None]
    assert seq.all_gt[0] == [] and len(seq.all_gt[1]) == 3
    assert sorted(seq.other_boxes()[1]) == [(0, 30, 20, 50), (40, 0, 20, 40)]
    assert load_sequence(d).target_id == 7
    assert choose_follow_target([], 10, 10) is None


def test_find_data_root_env_and_listing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _make_sot(tmp_path, ["1,2,10,20"])
    (tmp_path / "mot" / "not-a-seq").mkdir(parents=True)
    monkeypatch.setenv("FOLLOWBUS_DATA", str(tmp_path))
    assert find_data_root() == tmp_path.resolve()
    assert list_sequences(tmp_path) == [tmp_path / "sot" / "toy"]
    assert list_sequences(tmp_path, kind="mot") == []
    monkeypatch.setenv("FOLLOWBUS_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError):
        find_data_root()


def test_real_otb_jogging() -> None:
    d = _data_root() / "sot" / "otb-jogging"
    if not d.is_dir():
        pytest.skip(f"{d} absent")
    seq = load_sot_sequence(d)
    assert seq.frames == 307 == len(seq.gt_boxes)
    assert (seq.fps, seq.width, seq.height) == (30.0, 352, 288)
    rows = (d / "groundtruth.txt").read_text().split()
    nan_rows = sum(1 for r in rows if "nan" in r.lower())
    assert sum(b is None for b in seq.gt_boxes) == nan_rows  # this copy annotates the pole occlusion: 0 NaN
    assert seq.gt_boxes[0] == (111.0, 98.0, 25.0, 101.0)
    assert all(b is None or (b[2] > 0 and b[3] > 0) for b in seq.gt_boxes)


def test_real_tud_campus() -> None:
    d = _data_root() / "mot" / "tud-campus"
    if not d.is_dir():
        pytest.skip(f"{d} absent")
    seq = load_mot_sequence(d)
    assert (seq.frames, seq.fps, seq.width, seq.height) == (71, 25.0, 640, 480)
    assert sum(len(p) for p in seq.all_gt) == 359
    first = seq.all_gt[0]
    def feet_dist(box):
        return math.hypot(box[0] + box[2] / 2 - 320, box[1] + box[3] - 480)
    assert seq.target_id == min(first, key=lambda ib: feet_dist(ib[1]))[0]
    present = [any(i == seq.target_id for i, _ in p) for p in seq.all_gt]
    assert [b is not None for b in seq.gt_boxes] == present
    assert 0 < sum(present) < 71  # the chosen target leaves the view: occlusion spans exist


def test_real_sequences_all_load() -> None:
    root = _data_root()
    seqs = [load_sequence(p) for p in list_sequences(root)]
    assert {s.kind for s in seqs} <= {"sot", "mot"} and len(seqs) >= 2
    for s in seqs:
        assert len(s.gt_boxes) == len(s.all_gt) == s.frames > 0
        img = cv2.imread(str(s.image_paths[0]))
        assert img.shape[:2] == (s.height, s.width), s.name
