"""Evaluation sequences on disk: single-target (OTB/UAV123-style) and MOTChallenge layouts.

Recognised by their files (:data:`LAYOUTS`), as users have them:

- followbus SOT: ``<dir>/img/*.jpg`` (sorted), ``groundtruth.txt`` (one ``x,y,w,h`` per image; ``NaN`` rows or a
  non-positive size = target absent → ``None``), ``meta.json`` (``fps``);
- OTB: ``img/`` + ``groundtruth_rect.txt`` (comma, tab or space separated);
- LaSOT: ``img/`` + ``groundtruth.txt`` + ``full_occlusion.txt`` / ``out_of_view.txt`` (flagged frames: absent);
- GOT-10k: frames + ``groundtruth.txt`` + ``absence.label`` in one folder, ``meta_info.ini`` (``anno_fps``);
- MOTChallenge: ``<dir>/img1/*.jpg``, ``gt/gt.txt``, ``seqinfo.ini`` (``frameRate``, ``imWidth``, ``imHeight``,
  ``imExt``; without it 30 fps and the first image's size).

Nothing here reads pixels: image sizes come from seqinfo.ini or the image header.
"""

from __future__ import annotations

import configparser
import json
import logging
import math
import os
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .metrics import Box
from .mot_metrics import PEDESTRIAN_CLASS, load_mot_file, load_mot_regions

log = logging.getLogger(__name__)

__all__ = [
    "LAYOUTS",
    "Sequence",
    "choose_follow_target",
    "detect_layout",
    "find_data_root",
    "list_sequences",
    "load_got10k_sequence",
    "load_lasot_sequence",
    "load_mot_sequence",
    "load_otb_sequence",
    "load_sequence",
    "load_sot_sequence",
    "sequences_in",
]

SOT_TARGET_ID = 1  # the single annotated target of a SOT sequence gets this id in ``all_gt``
DEFAULT_FPS = 30.0  # OTB, LaSOT and a MOTChallenge folder without seqinfo.ini state none
GOT10K_FPS = 10.0
OTB_GROUNDTRUTH = ("groundtruth_rect.txt", "groundtruth_rect.1.txt")
LASOT_FLAGS = ("full_occlusion.txt", "out_of_view.txt")
_IMAGE_EXTS = (".jpg", ".jpeg", ".png")


@dataclass
class Sequence:
    """One evaluation sequence; every per-frame list has ``len(image_paths)`` entries (frame index 0-based)."""

    name: str
    kind: Literal["sot", "mot"]
    path: Path
    image_paths: list[Path]
    fps: float
    width: int
    height: int
    gt_boxes: list[Box | None]  # the follow target per frame (None = absent / not annotated)
    all_gt: list[list[tuple[int, Box]]] = field(default_factory=list)  # every annotated person: (id, box)
    target_id: int | None = None
    # MOT16/17: per frame every gt row, ignored ones included, and which are distractors (MOT scoring
    # preprocessing, mot_metrics.remove_distractor_matches); empty for SOT and MOT15
    gt_regions: list[tuple[np.ndarray, np.ndarray] | None] = field(default_factory=list)
    layout: str = "followbus"  # the on-disk format it was read from (datasets.LAYOUTS)

    @property
    def frames(self) -> int:
        return len(self.image_paths)

    def other_boxes(self) -> list[list[Box]]:
        """Per frame, the boxes of everyone except the target (the ``other_gt`` of evaluate_single_target)."""
        return [[b for i, b in people if i != self.target_id] for people in self.all_gt]


# --------------------------------------------------------------------------- helpers


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) from a JPEG or PNG header, without decoding (keeps this module free of OpenCV)."""
    with open(path, "rb") as f:
        head = f.read(24)
        if head[:8] == b"\x89PNG\r\n\x1a\n":
            w, h = struct.unpack(">II", head[16:24])
            return int(w), int(h)
        if head[:2] != b"\xff\xd8":
            raise ValueError(f"{path}: not a JPEG/PNG file")
        f.seek(2)
        while True:
            b = f.read(1)
            while b and b != b"\xff":
                b = f.read(1)
            while b == b"\xff":  # fill bytes
                b = f.read(1)
            if not b:
                break
            marker = b[0]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
                continue
            (length,) = struct.unpack(">H", f.read(2))
            # SOF0..SOF15 carry the frame size; C4 (DHT), C8 (JPG), CC (DAC) share the range but do not
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                _precision, h, w = struct.unpack(">BHH", f.read(5))
                return int(w), int(h)
            f.seek(length - 2, os.SEEK_CUR)
    raise ValueError(f"{path}: no JPEG frame header found")


def _sorted_images(folder: Path, ext: str | None = None) -> list[Path]:
    exts = (ext.lower(),) if ext else _IMAGE_EXTS
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in exts)


_SPLIT = re.compile(r"[,\s]+")


def _parse_sot_groundtruth(path: Path) -> list[Box | None]:
    boxes: list[Box | None] = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            parts = [p for p in _SPLIT.split(line) if p]
            if len(parts) != 4:
                raise ValueError(f"{path}:{lineno}: expected x,y,w,h, got {line!r}")
            x, y, w, h = (float(p) for p in parts)  # float('NaN') parses
            if any(math.isnan(v) for v in (x, y, w, h)) or w <= 0 or h <= 0:
                boxes.append(None)  # absent / not annotated (some OTB files write 0,0,0,0)
            else:
                boxes.append((x, y, w, h))
    return boxes


def choose_follow_target(people: list[tuple[int, Box]], width: int, height: int) -> int | None:
    """The id whose box's bottom-centre (the feet) is nearest the image's bottom-centre.

    Rationale: a following robot starts behind its person, who is then roughly centred and closest to the
    camera, i.e. lowest in the image; ties go to the smaller id so the choice is deterministic.
    """
    if not people:
        return None
    cx, cy = width / 2.0, float(height)

    def key(item: tuple[int, Box]) -> tuple[float, int]:
        pid, (x, y, w, h) = item
        return math.hypot(x + w / 2.0 - cx, y + h - cy), pid

    return min(people, key=key)[0]


# --------------------------------------------------------------------------- loaders


def _sot(d: Path, images: list[Path], gt: list[Box | None], fps: float, name: str, layout: str) -> Sequence:
    """A single-target Sequence from its images and per-image boxes (counts must agree: a silent truncation
    would mis-score)."""
    if not images:
        raise FileNotFoundError(f"{d}: no images ({layout} layout)")
    if len(gt) != len(images):
        raise ValueError(f"{d}: {len(images)} images but {len(gt)} groundtruth rows")
    width, height = _image_size(images[0])
    return Sequence(
        name=name, kind="sot", path=d, image_paths=images, fps=fps, width=width, height=height, gt_boxes=gt,
        all_gt=[[] if b is None else [(SOT_TARGET_ID, b)] for b in gt], target_id=SOT_TARGET_ID, layout=layout)


def load_sot_sequence(directory: str | Path) -> Sequence:
    """followbus's own layout: ``img/`` + ``groundtruth.txt`` + ``meta.json`` (fps, name)."""
    d = Path(directory)
    images = _sorted_images(d / "img")
    if not images:
        raise FileNotFoundError(f"{d}: no images in img/")
    gt = _parse_sot_groundtruth(d / "groundtruth.txt")
    meta_path = d / "meta.json"
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.exists() else {}
    if "fps" not in meta:
        log.warning("%s: no fps in meta.json, assuming 30", d)
    return _sot(d, images, gt, float(meta.get("fps", 30.0)), str(meta.get("name", d.name)), "followbus")


def _absent(gt: list[Box | None], flags: list[bool], d: Path, what: str) -> list[Box | None]:
    """``gt`` with the frames ``flags`` marks (occluded, out of view, absent) as None."""
    if len(flags) != len(gt):
        raise ValueError(f"{d}: {what} has {len(flags)} flags for {len(gt)} groundtruth rows")
    return [None if flag else box for box, flag in zip(gt, flags, strict=True)]


def _read_flags(path: Path) -> list[bool]:
    """0/1 flags separated by commas, spaces or newlines (LaSOT's one-line files, GOT-10k's one per line)."""
    return [bool(int(float(v))) for v in _SPLIT.split(path.read_text(encoding="utf-8").strip()) if v]


def load_otb_sequence(directory: str | Path) -> Sequence:
    """OTB-100: ``img/`` + ``groundtruth_rect.txt`` (comma, tab or space separated; ``groundtruth_rect.1.txt``,
    the first target, when a clip annotates two), 30 fps."""
    d = Path(directory)
    gt_path = next((p for p in OTB_GROUNDTRUTH if (d / p).is_file()), OTB_GROUNDTRUTH[0])
    return _sot(d, _sorted_images(d / "img"), _parse_sot_groundtruth(d / gt_path), DEFAULT_FPS, d.name, "otb")


def load_lasot_sequence(directory: str | Path) -> Sequence:
    """LaSOT: ``img/`` + ``groundtruth.txt`` + ``full_occlusion.txt`` / ``out_of_view.txt`` (frames flagged in
    either have no target: absent), 30 fps."""
    d = Path(directory)
    gt = _parse_sot_groundtruth(d / "groundtruth.txt")
    for flags in LASOT_FLAGS:
        if (d / flags).is_file():
            gt = _absent(gt, _read_flags(d / flags), d, flags)
    return _sot(d, _sorted_images(d / "img"), gt, DEFAULT_FPS, d.name, "lasot")


def _got10k_fps(d: Path) -> float:
    """``anno_fps: 10Hz`` of meta_info.ini (GOT-10k annotates at 10 Hz), else 10."""
    meta = d / "meta_info.ini"
    text = meta.read_text(encoding="utf-8", errors="replace") if meta.is_file() else ""
    m = re.search(r"anno_fps:\s*([0-9.]+)", text)
    return float(m.group(1)) if m else GOT10K_FPS


def load_got10k_sequence(directory: str | Path) -> Sequence:
    """GOT-10k: the frames beside ``groundtruth.txt`` (``00000001.jpg``...), ``absence.label`` (1 = absent);
    a test-split clip annotates its first frame only and cannot be scored."""
    d = Path(directory)
    images = _sorted_images(d)
    gt = _parse_sot_groundtruth(d / "groundtruth.txt")
    if len(gt) == 1 and len(images) > 1:
        raise ValueError(f"{d}: groundtruth.txt annotates 1 of {len(images)} frames (a GOT-10k test clip): "
                         "nothing to score against")
    if (d / "absence.label").is_file():
        gt = _absent(gt, _read_flags(d / "absence.label"), d, "absence.label")
    return _sot(d, images, gt, _got10k_fps(d), d.name, "got10k")


def load_mot_sequence(directory: str | Path) -> Sequence:
    """MOTChallenge sequence; the follow target is chosen by :func:`choose_follow_target` on the first frame
    that has any (non-ignored) gt. gt frame ``f`` maps to image index ``f - 1``."""
    d = Path(directory)
    ini = configparser.ConfigParser()
    if not ini.read(d / "seqinfo.ini", encoding="utf-8"):
        log.warning("%s: no seqinfo.ini: img1/, %g fps, the size of the first image", d, DEFAULT_FPS)
        ini.read_dict({"Sequence": {"frameRate": str(DEFAULT_FPS)}})
    info = ini["Sequence"]
    images = _sorted_images(d / info.get("imDir", "img1"), info.get("imExt"))
    n = info.getint("seqLength", fallback=len(images))
    if n != len(images):
        log.warning("%s: seqLength=%d but %d images; using the images", d, n, len(images))
        n = len(images)
    # is_gt: rows flagged conf = 0 (MOT16/17 ignore regions, non-pedestrians) are dropped, conf -1 kept;
    # classes: pedestrians only where a class column exists (MOT16/17), as MOTChallenge scores them
    # (TrackEval's gt_to_keep_mask)
    gt = load_mot_file(d / "gt" / "gt.txt", is_gt=True, classes=(PEDESTRIAN_CLASS,))
    regions = load_mot_regions(d / "gt" / "gt.txt")
    all_gt: list[list[tuple[int, Box]]] = [[] for _ in range(n)]
    for frame, (ids, boxes) in gt.items():
        if not 1 <= frame <= n:
            log.warning("%s: gt frame %d outside 1..%d, ignored", d, frame, n)
            continue
        all_gt[frame - 1] = [(int(i), (float(b[0]), float(b[1]), float(b[2]), float(b[3])))
                             for i, b in zip(ids, boxes, strict=True)]
    width = info.getint("imWidth", fallback=0)
    height = info.getint("imHeight", fallback=0)
    if (width <= 0 or height <= 0) and images:
        width, height = _image_size(images[0])
    first = next((people for people in all_gt if people), [])
    target = choose_follow_target(first, width, height)
    gt_boxes: list[Box | None] = [dict(people).get(target) if target is not None else None
                                  for people in all_gt]
    return Sequence(
        name=info.get("name", d.name), kind="mot", path=d, image_paths=images,
        fps=float(info.get("frameRate", "30")), width=width, height=height, gt_boxes=gt_boxes,
        all_gt=all_gt, target_id=target, gt_regions=[regions.get(k + 1) for k in range(n)] if regions else [],
        layout="mot")


# The layouts, in the order they are recognised: (name, kind, test on the folder, loader). LaSOT before the
# followbus layout it contains (img/ + groundtruth.txt), which comes before GOT-10k (groundtruth.txt beside the
# frames).
def _is_mot(d: Path) -> bool:
    return (d / "gt" / "gt.txt").is_file() and ((d / "seqinfo.ini").is_file() or (d / "img1").is_dir())


def _is_lasot(d: Path) -> bool:
    return _is_followbus_sot(d) and any((d / f).is_file() for f in LASOT_FLAGS)


def _is_followbus_sot(d: Path) -> bool:
    return (d / "groundtruth.txt").is_file() and (d / "img").is_dir()


def _is_otb(d: Path) -> bool:
    return (d / "img").is_dir() and any((d / f).is_file() for f in OTB_GROUNDTRUTH)


def _is_got10k(d: Path) -> bool:
    return (d / "groundtruth.txt").is_file() and any(p.suffix.lower() in _IMAGE_EXTS for p in d.iterdir())


LAYOUTS: tuple[tuple[str, Literal["sot", "mot"], Callable[[Path], bool], Callable[[Path], Sequence]], ...] = (
    ("mot", "mot", _is_mot, load_mot_sequence),
    ("lasot", "sot", _is_lasot, load_lasot_sequence),
    ("followbus", "sot", _is_followbus_sot, load_sot_sequence),
    ("otb", "sot", _is_otb, load_otb_sequence),
    ("got10k", "sot", _is_got10k, load_got10k_sequence),
)
LAYOUT_HELP = ("followbus/LaSOT: img/ + groundtruth.txt; OTB: img/ + groundtruth_rect.txt; GOT-10k: frames + "
               "groundtruth.txt; MOTChallenge: img1/ + gt/gt.txt")


def detect_layout(path: Path) -> str | None:
    """The name of the layout ``path`` holds (a key of :data:`LAYOUTS`), or None."""
    if not path.is_dir():
        return None
    return next((name for name, _, test, _ in LAYOUTS if test(path)), None)


def _kind_of(path: Path) -> Literal["sot", "mot"] | None:
    name = detect_layout(path)
    return next((kind for n, kind, _, _ in LAYOUTS if n == name), None)


def what_is_missing(d: Path) -> str:
    """One line: why ``d`` is not a sequence folder of any layout, naming the file that is missing."""
    if (d / "img1").is_dir() or (d / "gt").is_dir():
        missing = "gt/gt.txt" if (d / "img1").is_dir() else "img1/"
        return f"{d}: a MOTChallenge folder needs img1/ and gt/gt.txt; {missing} is missing"
    if (d / "img").is_dir():
        return (f"{d}: img/ has no ground truth beside it: groundtruth.txt (followbus, LaSOT) or "
                "groundtruth_rect.txt (OTB) is missing")
    if (d / "groundtruth.txt").is_file():
        return (f"{d}: groundtruth.txt has no frames: img/ (followbus, LaSOT) or the images beside it "
                "(GOT-10k) are missing")
    return f"{d}: not a sequence folder ({LAYOUT_HELP})"


def load_sequence(directory: str | Path) -> Sequence:
    """Load any layout of :data:`LAYOUTS`, recognised by its files; a ValueError naming what is missing else."""
    d = Path(directory)
    name = detect_layout(d)
    for layout, _, _, loader in LAYOUTS:
        if layout == name:
            return loader(d)
    raise ValueError(what_is_missing(d))


# --------------------------------------------------------------------------- discovery


def _is_data_root(p: Path) -> bool:
    return (p / "sot").is_dir() or (p / "mot").is_dir()


def find_data_root() -> Path | None:
    """The evaluation data directory, or None when there is none.

    Order: ``$FOLLOWBUS_DATA`` (an error if set but not a data root — a typo should not silently fall back),
    ``<repo root>/../shared/data``, then ``<cwd>/../shared/data``.
    """
    env = os.environ.get("FOLLOWBUS_DATA")
    if env:
        p = Path(env).expanduser().resolve()
        if not _is_data_root(p):
            raise FileNotFoundError(f"FOLLOWBUS_DATA={env!r} has no sot/ or mot/ directory")
        return p
    repo_root = Path(__file__).resolve().parents[1]
    for cand in (repo_root.parent / "shared" / "data", Path.cwd().resolve().parent / "shared" / "data"):
        if _is_data_root(cand):
            return cand
    return None


def list_sequences(root: str | Path, kind: Literal["sot", "mot"] | None = None) -> list[Path]:
    """Sequence directories under ``root/sot`` and ``root/mot`` (sorted; SOT first), optionally one kind."""
    r = Path(root)
    out: list[Path] = []
    for sub in ("sot", "mot"):
        if kind not in (None, sub) or not (r / sub).is_dir():
            continue
        out += sorted(p for p in (r / sub).iterdir() if p.is_dir() and _kind_of(p) == sub)
    return out


def sequences_in(folder: str | Path) -> list[Path]:
    """The sequence folders directly inside ``folder`` (a benchmark's root: OTB-100, a LaSOT class, GOT-10k's
    val/), sorted; empty when there is none."""
    f = Path(folder)
    return sorted(p for p in f.iterdir() if detect_layout(p) is not None) if f.is_dir() else []
