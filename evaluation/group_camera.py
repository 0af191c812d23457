"""``followbus eval --group --camera``: the group trackers of seed 004 on real camera sequences.

What is measured: the **image-plane** group-centre error (pixels) of every method of
:data:`followbus.tracking.group.METHODS`, fed the same YOLOX detections.

* Ground truth per frame: the centroid of the centres of the annotated people's boxes. On the MOT clips the
  "group" is every annotated pedestrian of the frame (MOT17: class 1, not ignored; TUD-Campus: everyone);
  they are passers-by more than a squad, so the figure says how well each method follows the crowd's centre,
  nothing about membership. ``sot/uav-group1-3`` annotates only one walker of a group of three (the other two
  have no boxes), so there the truth is that walker's box centre: a method that follows the whole group is
  off by the walker's place in the group (about a body length), which SOT is not. The table says which.
* Points for the trackers: the centre of every detection at or above the evaluation's score threshold, in
  the image plane. The camera's pose and intrinsics are not known for these clips (the UAV's camera moves and
  tilts; TUD/MOT17 ship no calibration), so tracking/groundplane.py cannot put them on the ground; the
  trackers' parameters are in metres, so pixels are scaled by 1.7 m over the median height of the first
  frame's detections (a standing person), one factor per sequence, fixed from the first frame (causal).
  Each point's covariance: 10 % of its box's height, standard deviation, per axis.
* Detections are cached exactly as ``followbus eval`` caches them (evaluation/detcache.py, same key: boxes
  down to the low-score threshold), so both evaluations share one cache directory.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..tracking.group import METHODS
from . import detcache
from .datasets import Sequence, list_sequences, load_sequence

log = logging.getLogger(__name__)

PERSON_HEIGHT_M = 1.7
POINT_STD_OF_HEIGHT = 0.10
WARMUP_FRAMES = 3          # every method needs a couple of frames for its first estimate


@dataclass
class CameraSequence:
    name: str
    fps: float
    width: int
    height: int
    truth: str                            # what the ground truth is, for the table
    gt_centre_px: np.ndarray              # (T, 2), NaN where nobody is annotated
    gt_height_px: np.ndarray              # (T,) median annotated box height, NaN where none
    detections: list[np.ndarray]          # per frame (n, 5) x, y, w, h, score above the threshold
    from_cache: bool = False


@dataclass
class CameraResult:
    rmse_px: float
    mean_px: float
    rmse_heights: float                   # RMSE in units of the annotated people's median box height
    frames_scored: int
    frames_without_estimate: int
    ms_mean: float
    centres_px: np.ndarray = field(repr=False)

    def as_dict(self) -> dict[str, Any]:
        def r(v: float) -> float | None:
            return None if not math.isfinite(v) else round(float(v), 3)

        return {"rmse_px": r(self.rmse_px), "mean_px": r(self.mean_px), "rmse_heights": r(self.rmse_heights),
                "frames_scored": self.frames_scored, "frames_without_estimate": self.frames_without_estimate,
                "ms_per_frame_mean": r(self.ms_mean)}


def group_truth(people_per_frame: list[list[tuple[int, tuple[float, float, float, float]]]]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the centroid of the annotated boxes' centres (px) and their median height (px); NaN if none."""
    n = len(people_per_frame)
    centre = np.full((n, 2), math.nan)
    height = np.full(n, math.nan)
    for k, people in enumerate(people_per_frame):
        if not people:
            continue
        b = np.array([box for _, box in people], dtype=float).reshape(-1, 4)
        centre[k] = (b[:, :2] + b[:, 2:4] / 2).mean(axis=0)
        height[k] = float(np.median(b[:, 3]))
    return centre, height


def boxes_to_points(dets: np.ndarray, m_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Box centres scaled to metre-like units, and their covariances (POINT_STD_OF_HEIGHT of the box height)."""
    d = np.asarray(dets, dtype=float).reshape(-1, 5)
    pts = (d[:, :2] + d[:, 2:4] / 2) * m_per_px
    std = POINT_STD_OF_HEIGHT * d[:, 3] * m_per_px
    covs = np.zeros((len(d), 2, 2))
    covs[:, 0, 0] = covs[:, 1, 1] = std ** 2
    return pts, covs


def scale_from_first_frame(detections: list[np.ndarray]) -> float:
    """Metres per pixel: PERSON_HEIGHT_M over the median box height of the first frame with a detection."""
    for d in detections:
        if len(d):
            return PERSON_HEIGHT_M / max(1.0, float(np.median(np.asarray(d)[:, 3])))
    return PERSON_HEIGHT_M / 100.0


def detect_sequence(seq: Sequence, detector: str, cache_dir: Path | None, n_frames: int
                    ) -> tuple[list[np.ndarray], bool]:
    """The detections above the evaluation's score threshold for the first ``n_frames`` frames, from
    ``followbus eval``'s cache when it has them (the same key), else by running ``detector`` (and caching)."""
    import cv2

    from ..vision.detectors import split_by_score
    from .runner import LOW_SCORE_THRESHOLD, SCORE_THRESHOLD, detector_key, make_eval_detector

    key = str(Path(seq.path).resolve())
    # as evaluation/runner.py: the low-score boxes too
    det_key = f"{detector_key(detector)}-low{LOW_SCORE_THRESHOLD:g}"
    path = detcache.cache_path(cache_dir, key, det_key, n_frames) if cache_dir is not None else None
    cached = detcache.load(path, n_frames) if path is not None else None
    from_cache = cached is not None
    if cached is None:
        det = make_eval_detector(detector, 0, LOW_SCORE_THRESHOLD)
        frames, ms = [], []
        for i in range(n_frames):
            bgr = cv2.imread(str(seq.image_paths[i]), cv2.IMREAD_COLOR)
            if bgr is None:
                raise OSError(f"cannot read {seq.image_paths[i]}")
            t0 = time.perf_counter()
            frames.append(np.asarray(det.detect(bgr), dtype=np.float32).reshape(-1, 5))
            ms.append((time.perf_counter() - t0) * 1e3)
        cached = detcache.CachedDetections(frames, np.asarray(ms))
        if path is not None:
            detcache.save(path, cached)
    return [split_by_score(d, SCORE_THRESHOLD, LOW_SCORE_THRESHOLD)[0] for d in cached.per_frame], from_cache


def open_camera_sequence(directory: str | Path, detector: str = "graph", cache_dir: Path | None = None,
                         max_frames: int = 0) -> CameraSequence:
    seq = load_sequence(directory)
    n = seq.frames if not max_frames else min(max_frames, seq.frames)
    gt_c, gt_h = group_truth(seq.all_gt[:n])
    dets, from_cache = detect_sequence(seq, detector, cache_dir, n)
    if seq.kind == "sot":
        truth = "the one annotated person's box centre (the rest of the group is not annotated)"
    else:
        truth = "centroid of every annotated pedestrian's box centre"
    return CameraSequence(f"{seq.kind}/{Path(directory).name}", seq.fps, seq.width, seq.height, truth, gt_c, gt_h,
                          dets, from_cache)


def run_camera_method(method: str, cs: CameraSequence) -> CameraResult:
    """Step ``method`` over the sequence's detections; score the image-plane centre against the truth."""
    tracker = METHODS[method]()
    m_per_px = scale_from_first_frame(cs.detections)
    n = len(cs.detections)
    centres = np.full((n, 2), math.nan)
    ms = np.zeros(n)
    for k, dets in enumerate(cs.detections):
        pts, covs = boxes_to_points(dets, m_per_px)
        t0 = time.perf_counter()
        est = tracker.step(k / cs.fps, pts, covs)
        ms[k] = (time.perf_counter() - t0) * 1e3
        if est.valid and np.all(np.isfinite(est.centre_m)):
            centres[k] = np.asarray(est.centre_m) / m_per_px
    scored = np.arange(n) >= min(WARMUP_FRAMES, max(0, n - 1))
    has_gt = np.all(np.isfinite(cs.gt_centre_px), axis=1) & scored
    has_est = np.all(np.isfinite(centres), axis=1)
    ok = has_gt & has_est
    if ok.any():
        err = np.linalg.norm(centres[ok] - cs.gt_centre_px[ok], axis=1)
        rmse = float(np.sqrt(np.mean(err ** 2)))
        mean = float(np.mean(err))
        rmse_h = float(np.sqrt(np.mean((err / cs.gt_height_px[ok]) ** 2)))
    else:
        rmse = mean = rmse_h = math.nan
    return CameraResult(rmse, mean, rmse_h, int(ok.sum()), int(np.sum(has_gt & ~has_est)), float(ms.mean()), centres)


def default_sequences(root: Path) -> list[Path]:
    """The group sequences of the data: sot/uav-group* and every MOT clip."""
    return [p for p in list_sequences(root) if p.parent.name == "mot" or p.name.startswith("uav-group")]


def format_camera_table(results: dict[str, tuple[CameraSequence, dict[str, CameraResult]]]) -> str:
    lines = ["| Sequence | Frames | Ground truth | Method | RMSE px | mean px | RMSE / person height | "
             "frames without estimate | ms/frame |", "|---|---:|---|---|---:|---:|---:|---:|---:|"]
    for name, (cs, res) in results.items():
        truth = "1 annotated member" if cs.name.startswith("sot/") else "all annotated"
        for m, r in res.items():
            lines.append(f"| {name} | {r.frames_scored} | {truth} | {m} | {r.rmse_px:.1f} | {r.mean_px:.1f} | "
                         f"{r.rmse_heights:.2f} | {r.frames_without_estimate} | {r.ms_mean:.2f} |")
    # A mean only over sequences with the same kind of truth: the SOT clip's one member is not a group centre.
    mot = [res for cs, res in results.values() if not cs.name.startswith("sot/")]
    methods = list(mot[0]) if mot else []
    if methods:
        lines += ["", "| MOT clips, frame-weighted mean | RMSE / person height | mean px |", "|---|---:|---:|"]
        for m in methods:
            w = np.array([res[m].frames_scored for res in mot], dtype=float)
            rh = np.array([res[m].rmse_heights for res in mot])
            mp = np.array([res[m].mean_px for res in mot])
            ok = np.isfinite(rh) & np.isfinite(mp) & (w > 0)
            if ok.any():
                lines.append(f"| {m} | {np.average(rh[ok], weights=w[ok]):.2f} | "
                             f"{np.average(mp[ok], weights=w[ok]):.1f} |")
    return "\n".join(lines) + "\n"


def run_camera(sequences: list[Path], detector: str = "graph", cache_dir: Path | None = None, max_frames: int = 0,
               methods: list[str] | None = None) -> dict[str, tuple[CameraSequence, dict[str, CameraResult]]]:
    out: dict[str, tuple[CameraSequence, dict[str, CameraResult]]] = {}
    for d in sequences:
        cs = open_camera_sequence(d, detector, cache_dir, max_frames)
        out[cs.name] = (cs, {m: run_camera_method(m, cs) for m in (methods or list(METHODS))})
    return out


def cmd_eval_group_camera(out: Path, command: str, sequences: list[str] | None = None, detector: str = "graph",
                          max_frames: int = 0) -> int:
    """Print the per-sequence table; write group_camera.md and group_camera.json under ``out``. Exit 2 with one
    line when there is no data."""
    from .datasets import find_data_root

    if sequences:
        paths = [Path(s) for s in sequences]
        missing = [p for p in paths if not p.is_dir()]
        if missing:
            print(f"followbus: no sequence directory {str(missing[0])!r}", file=sys.stderr)
            return 2
    else:
        root = find_data_root()
        if root is None:
            print("followbus: no evaluation data (set FOLLOWBUS_DATA or put it at ../shared/data)", file=sys.stderr)
            return 2
        paths = default_sequences(root)
    t0 = time.perf_counter()
    try:
        results = run_camera(paths, detector, out / "cache", max_frames)
    except (ValueError, FileNotFoundError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - t0
    table = format_camera_table(results)
    out.mkdir(parents=True, exist_ok=True)
    doc = {"command": command, "detector": detector, "wall_s": round(wall, 1),
           "sequences": {name: {"truth": cs.truth, "frames": len(cs.detections), "detections_from_cache": cs.from_cache,
                                "methods": {m: r.as_dict() for m, r in res.items()}}
                         for name, (cs, res) in results.items()}}
    (out / "group_camera.json").write_text(json.dumps(doc, indent=1))
    (out / "group_camera.md").write_text(f"# Group trackers on camera data (image plane)\n\n```\n{command}\n```\n\n"
                                         f"{table}")
    print(table, end="")
    print(f"\nwrote {out / 'group_camera.md'} and {out / 'group_camera.json'} ({wall:.1f} s)")
    return 0
