"""Evaluation sequences on disk: single-target (OTB/UAV123-style) and MOTChallenge layouts.

SOT: ``<dir>/img/*.jpg`` (sorted), ``groundtruth.txt`` (one ``x,y,w,h`` per image; ``NaN`` rows or a
non-positive size = target absent → ``None``), ``meta.json`` (``fps``).
MOT: ``<dir>/img1/*.jpg``, ``gt/gt.txt`` (MOTChallenge), ``seqinfo.ini`` (``frameRate``, ``imWidth``,
``imHeight``, ``imExt``). Nothing here reads pixels: image sizes come from seqinfo.ini or the image header.
"""

from __future__ import annotations

import configparser
import json
import logging
import math
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .metrics import Box
from .mot_metrics import PEDESTRIAN_CLASS, load_mot_file, load_mot_regions

log = logging.getLogger(__name__)

__all__ = [
    "Sequence",
    "choose_follow_target",
    "find_data_root",
    "list_sequences",
    "load_mot_sequence",
    "load_sequence",
    "load_sot_sequence",
]

SOT_TARGET_ID = 1  # the single annotated target of a SOT sequence gets this id in ``all_gt``
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


def load_sot_sequence(directory: str | Path) -> Sequence:
    d = Path(directory)
    images = _sorted_images(d / "img")
    if not images:
        raise FileNotFoundError(f"{d}: no images in img/")
    gt = _parse_sot_groundtruth(d / "groundtruth.txt")
    if len(gt) != len(images):
        # a silent truncation would mis-score; fail instead
        raise ValueError(f"{d}: {len(images)} images but {len(gt)} groundtruth rows")
    meta_path = d / "meta.json"
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.exists() else {}
    fps = float(meta.get("fps", 30.0))
    if "fps" not in meta:
        log.warning("%s: no fps in meta.json, assuming 30", d)
    width, height = _image_size(images[0])
    return Sequence(
        name=str(meta.get("name", d.name)), kind="sot", path=d, image_paths=images, fps=fps, width=width,
        height=height, gt_boxes=gt, all_gt=[[] if b is None else [(SOT_TARGET_ID, b)] for b in gt],
        target_id=SOT_TARGET_ID)


def load_mot_sequence(directory: str | Path) -> Sequence:
    """MOTChallenge sequence; the follow target is chosen by :func:`choose_follow_target` on the first frame
    that has any (non-ignored) gt. gt frame ``f`` maps to image index ``f - 1``."""
    d = Path(directory)
    ini = configparser.ConfigParser()
    if not ini.read(d / "seqinfo.ini", encoding="utf-8"):
        raise FileNotFoundError(f"{d}: no seqinfo.ini")
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
        all_gt=all_gt, target_id=target, gt_regions=[regions.get(k + 1) for k in range(n)] if regions else [])


def _kind_of(path: Path) -> Literal["sot", "mot"] | None:
    if (path / "seqinfo.ini").is_file() and (path / "gt" / "gt.txt").is_file():
        return "mot"
    if (path / "groundtruth.txt").is_file() and (path / "img").is_dir():
        return "sot"
    return None


def load_sequence(directory: str | Path) -> Sequence:
    """Load either layout, recognised by its files."""
    d = Path(directory)
    kind = _kind_of(d)
    if kind == "mot":
        return load_mot_sequence(d)
    if kind == "sot":
        return load_sot_sequence(d)
    raise ValueError(f"{d}: neither a SOT (img/ + groundtruth.txt) nor a MOT (seqinfo.ini + gt/gt.txt) sequence")


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
