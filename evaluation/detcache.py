"""Per-sequence detection cache: every method of an evaluation run sees the same detections, and a
repeated run does not re-run YOLOX.

One ``.npz`` per (sequence, detector) under ``<out>/cache/``: all boxes concatenated (``boxes``, N×5
float32 x,y,w,h,score), per-frame row ``offsets`` (frames+1), per-frame inference ``ms``. The key
includes the sequence's identity (path or scene name + seed + size), its frame count and the detector
spec, so a changed sequence or detector misses the cache instead of returning stale boxes.
"""

from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

CACHE_VERSION = 1


@dataclass
class CachedDetections:
    per_frame: list[np.ndarray]  # each (n_k, 5) float32
    ms: np.ndarray  # per-frame inference time in ms (as measured when the cache was filled)

    @property
    def frames(self) -> int:
        return len(self.per_frame)


def cache_path(cache_dir: Path, sequence_key: str, detector_key: str, frames: int) -> Path:
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{sequence_key.rsplit('/', 1)[-1]}-{detector_key}")[:80]
    digest = hashlib.sha1(f"v{CACHE_VERSION}|{sequence_key}|{detector_key}|{frames}".encode()).hexdigest()[:10]
    return cache_dir / f"{slug}-{digest}.npz"


def load(path: Path, frames: int) -> CachedDetections | None:
    """The cached detections, or None when absent, unreadable or for another frame count."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            boxes, offsets, ms = z["boxes"], z["offsets"], z["ms"]
    except (OSError, KeyError, ValueError) as exc:
        log.warning("ignoring unreadable detection cache %s (%s)", path, exc)
        return None
    if len(offsets) != frames + 1 or len(ms) != frames:
        log.warning("ignoring detection cache %s: %d frames, expected %d", path, len(ms), frames)
        return None
    per_frame = [boxes[offsets[i]:offsets[i + 1]].reshape(-1, 5) for i in range(frames)]
    return CachedDetections(per_frame, np.asarray(ms, dtype=np.float64))


def save(path: Path, dets: CachedDetections) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    counts = [len(d) for d in dets.per_frame]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    boxes = (np.concatenate([np.asarray(d, np.float32).reshape(-1, 5) for d in dets.per_frame])
             if dets.per_frame else np.zeros((0, 5), np.float32))
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, boxes=boxes, offsets=offsets, ms=np.asarray(dets.ms, np.float64))
    tmp.replace(path)  # atomic: an interrupted run never leaves a half-written cache behind
