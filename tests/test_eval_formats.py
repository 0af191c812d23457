"""Users' data as it comes: OTB, LaSOT, GOT-10k and MOTChallenge folders read directly, recognised by their files,
and a folder of none of them refused with one line naming what is missing (tiny folders built here)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.evaluation.datasets import detect_layout, load_sequence, sequences_in


def _images(folder: Path, n: int, name: str = "{:08d}.jpg", w: int = 40, h: int = 30) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        assert cv2.imwrite(str(folder / name.format(i + 1)), np.full((h, w, 3), 40 * i, np.uint8))


def make_otb(root: Path, sep: str = ",") -> Path:
    d = root / "Human3"
    _images(d / "img", 3, "{:04d}.jpg")
    (d / "groundtruth_rect.txt").write_text("\n".join(sep.join(map(str, (1 + i, 2, 10, 20))) for i in range(3)))
    return d


def make_lasot(root: Path) -> Path:
    d = root / "person-1"
    _images(d / "img", 4)
    (d / "groundtruth.txt").write_text("1,2,10,20\n2,2,10,20\n3,2,10,20\n4,2,10,20\n")
    (d / "full_occlusion.txt").write_text("0,0,1,0")
    (d / "out_of_view.txt").write_text("0,0,0,1")
    (d / "nlp.txt").write_text("the person in red")
    return d


def make_got10k(root: Path) -> Path:
    d = root / "GOT-10k_Val_000001"
    _images(d, 3)
    (d / "groundtruth.txt").write_text("1,2,10,20\n2,2,10,20\n3,2,10,20\n")
    (d / "absence.label").write_text("0\n1\n0\n")
    (d / "meta_info.ini").write_text("[METAINFO]\nurl: x\nanno_fps: 10Hz\nobject_class: person\n")
    return d


def make_mot(root: Path, seqinfo: bool = True) -> Path:
    d = root / "MOT17-02"
    _images(d / "img1", 2, "{:06d}.jpg")
    (d / "gt").mkdir()
    (d / "gt" / "gt.txt").write_text("1,1,5,5,10,20,1,1,1\n1,2,20,8,10,20,1,1,1\n2,1,6,5,10,20,1,1,1\n")
    if seqinfo:
        (d / "seqinfo.ini").write_text("[Sequence]\nname=MOT17-02\nimDir=img1\nframeRate=25\nseqLength=2\n"
                                       "imWidth=40\nimHeight=30\nimExt=.jpg\n")
    return d


@pytest.mark.parametrize("sep", [",", "\t", " "])
def test_otb_groundtruth_rect_any_separator(tmp_path: Path, sep: str) -> None:
    seq = load_sequence(make_otb(tmp_path, sep))
    assert (seq.layout, seq.kind, seq.frames, seq.fps, seq.width, seq.height) == ("otb", "sot", 3, 30.0, 40, 30)
    assert seq.gt_boxes == [(1, 2, 10, 20), (2, 2, 10, 20), (3, 2, 10, 20)]


def test_lasot_occluded_and_out_of_view_frames_are_absent(tmp_path: Path) -> None:
    seq = load_sequence(make_lasot(tmp_path))
    assert seq.layout == "lasot" and seq.frames == 4
    assert seq.gt_boxes == [(1, 2, 10, 20), (2, 2, 10, 20), None, None]


def test_got10k_frames_beside_groundtruth_absence_and_fps(tmp_path: Path) -> None:
    seq = load_sequence(make_got10k(tmp_path))
    assert (seq.layout, seq.frames, seq.fps) == ("got10k", 3, 10.0)
    assert seq.gt_boxes == [(1, 2, 10, 20), None, (3, 2, 10, 20)]


def test_got10k_test_clip_with_only_the_first_box_is_refused(tmp_path: Path) -> None:
    d = make_got10k(tmp_path)
    (d / "groundtruth.txt").write_text("1,2,10,20\n")
    with pytest.raises(ValueError, match="annotates 1 of 3 frames"):
        load_sequence(d)


@pytest.mark.parametrize("seqinfo", [True, False])
def test_mot_with_and_without_seqinfo(tmp_path: Path, seqinfo: bool) -> None:
    seq = load_sequence(make_mot(tmp_path, seqinfo))
    assert (seq.layout, seq.kind, seq.frames, seq.width, seq.height) == ("mot", "mot", 2, 40, 30)
    assert seq.fps == (25.0 if seqinfo else 30.0)
    assert [len(p) for p in seq.all_gt] == [2, 1]


def test_a_benchmark_root_lists_its_sequences(tmp_path: Path) -> None:
    made = [make_otb(tmp_path), make_lasot(tmp_path), make_got10k(tmp_path), make_mot(tmp_path)]
    (tmp_path / "notes").mkdir()
    assert sequences_in(tmp_path) == sorted(made)
    assert [detect_layout(p) for p in sorted(made)] == ["got10k", "otb", "mot", "lasot"]


@pytest.mark.parametrize(("build", "missing"), [
    (lambda d: _images(d / "img", 2), "groundtruth.txt (followbus, LaSOT) or groundtruth_rect.txt (OTB) is missing"),
    (lambda d: (d / "groundtruth.txt").write_text("1,2,3,4\n"),
     "img/ (followbus, LaSOT) or the images beside it (GOT-10k) are missing"),
    (lambda d: _images(d / "img1", 2), "gt/gt.txt is missing"),
    (lambda d: (d / "gt").mkdir(), "img1/ is missing"),
    (lambda d: None, "not a sequence folder (followbus/LaSOT: img/ + groundtruth.txt; OTB:"),
])
def test_what_is_missing_is_named(tmp_path: Path, build, missing: str) -> None:
    d = tmp_path / "clip"
    d.mkdir()
    build(d)
    with pytest.raises(ValueError, match=None) as info:
        load_sequence(d)
    assert str(info.value).startswith(f"{d}: ") and missing in str(info.value)
    assert "\n" not in str(info.value)
