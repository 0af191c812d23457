"""An MP4 of one evaluation run (``followbus eval --video``): on every frame the ground truth, the method's
output, its gate ellipse and re-ID's candidates with their fused scores, and a line saying the state and why.

Colours (BGR): ground truth green, output red (orange while coasting), gate cyan, candidates grey with M_fuse,
the accepted candidate white. OpenCV's VideoWriter (mp4v) writes the file; nothing else is needed to play it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .metrics import Box

GT_COLOUR = (0, 200, 0)
OUTPUT_COLOUR = (0, 0, 230)
COASTING_COLOUR = (0, 140, 255)
GATE_COLOUR = (230, 200, 0)
CANDIDATE_COLOUR = (170, 170, 170)
CHOSEN_COLOUR = (255, 255, 255)
FOURCC = "mp4v"
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _rect(img: np.ndarray, box: Sequence[float] | None, colour: tuple[int, int, int], thickness: int = 2) -> None:
    if box is None or not all(math.isfinite(float(v)) for v in box):
        return
    x, y, w, h = (float(v) for v in box)
    cv2.rectangle(img, (round(x), round(y)), (round(x + w), round(y + h)), colour, thickness)


def _label(img: np.ndarray, text: str, org: tuple[int, int], colour: tuple[int, int, int], scale: float = 0.4) -> None:
    cv2.putText(img, text, org, FONT, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, FONT, scale, colour, 1, cv2.LINE_AA)


def _gate(img: np.ndarray, gate: dict[str, float] | None) -> None:
    """The gate as tracking/kalman.py's gate_ellipse_from_cov gives it (semi-axes; cv2 wants them whole)."""
    if not gate:
        return
    centre = (round(gate["cx"]), round(gate["cy"]))
    axes = (max(1, round(gate["a_px"])), max(1, round(gate["b_px"])))
    cv2.ellipse(img, centre, axes, gate["angle_deg"], 0, 360, GATE_COLOUR, 1, cv2.LINE_AA)


def draw_frame(bgr: np.ndarray, k: int, gt: Box | None, box: Box | None, info: dict[str, Any]) -> np.ndarray:
    """A copy of ``bgr`` with frame ``k``'s ground truth, output, gate, candidates and reason drawn."""
    img = np.array(bgr, copy=True)
    trace = info.get("trace") or {}
    _gate(img, (trace.get("prior") or {}).get("gate"))
    chosen = (trace.get("measurement") or {}).get("box")
    for c in trace.get("candidates") or []:
        accepted = chosen is not None and np.allclose(c["box"], chosen)
        colour = CHOSEN_COLOUR if accepted else CANDIDATE_COLOUR
        _rect(img, c["box"], colour, 1)
        x, y = c["box"][0], c["box"][1] + c["box"][3]
        _label(img, f"{c['m_fuse']:.2f}" if c.get("m_fuse") is not None else "?", (round(x), round(y) + 10), colour)
    _rect(img, gt, GT_COLOUR, 1)
    state = str(info.get("state", ""))
    _rect(img, box, OUTPUT_COLOUR if state in ("TRACKING", "REACQUIRED") else COASTING_COLOUR, 2)
    _label(img, f"{k}  {trace.get('reason') or state}", (4, 14), (255, 255, 255))
    return img


def write_video(path: Path, frames: Any, boxes: Sequence[Box | None], infos: Sequence[dict[str, Any]],
                gts: Sequence[Box | None], fps: float) -> int:
    """Draw every frame of ``frames`` (BGR arrays, in order) and write them to ``path`` (MP4); returns the
    number of frames written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = None
    n = 0
    try:
        for k, bgr in enumerate(frames):
            if k >= len(boxes):
                break
            img = draw_frame(bgr, k, gts[k], boxes[k], infos[k])
            if writer is None:
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*FOURCC), float(fps),
                                         (img.shape[1], img.shape[0]))
                if not writer.isOpened():
                    raise OSError(f"{path}: OpenCV cannot write {FOURCC} video here")
            writer.write(img)
            n += 1
    finally:
        if writer is not None:
            writer.release()
    return n


def render_run(run: Any, method: str, path: Path) -> int:
    """The MP4 of ``method``'s run in a SequenceRun (evaluation/runner.py); the frames are read (or rendered)
    again from the sequence."""
    mr = run.runs[method]
    frames = (item.bgr for item in run.sequence.frames())
    return write_video(path, frames, mr.boxes, mr.infos, run.gt_boxes, run.sequence.fps)
