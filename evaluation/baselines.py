"""Baseline followers run side by side with followbus on the same detections.

* :class:`KalmanFollower` — the paper's "Kalman baseline": a constant-velocity Kalman filter on the
  box centre, associated each frame to the *nearest* detection (Mahalanobis) inside a χ² gate; no
  appearance model, no re-identification. Without a match it coasts on the prediction (its output is
  the predicted box, as followbus does while OCCLUDED) and gives up (outputs None) after
  ``lost_after_ms``; the gate keeps widening with the covariance, so it can re-capture whoever walks
  into it — which is exactly the failure mode appearance-based re-ID is meant to fix.
* :class:`PeerFollower` — a multi-object tracker from Roboflow ``trackers`` used as a target follower:
  on the first frame the track overlapping the init box best is chosen and its id followed; while that
  id's track is alive but unmatched the follower coasts on the tracker's own prediction (as followbus and
  the Kalman baseline coast on theirs); once the tracker deletes it, the output is None.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .metrics import Box, box_iou

log = logging.getLogger(__name__)

PEER_NAMES = ("bytetrack", "ocsort", "botsort")


class KalmanFollower:
    """Plain CV Kalman + nearest-detection χ² gating (state cx, cy, vx, vy; measurement cx, cy)."""

    name = "kalman"

    def __init__(self, *, gate_chi2: float = 9.21, accel_std_px_s2: float = 500.0, r_px2: float = 64.0,
                 init_velocity_std_px_s: float = 300.0, size_smoothing: float = 0.3,
                 lost_after_ms: float = 3000.0, min_score: float = 0.0) -> None:
        # 9.21 = χ²(2 dof, 0.99): the gate is on the 2-D centre innovation
        self.gate_chi2 = gate_chi2
        self.q = accel_std_px_s2 ** 2
        self.r = r_px2
        self.v0 = init_velocity_std_px_s ** 2
        self.alpha = size_smoothing
        self.lost_after_ns = int(lost_after_ms * 1e6)
        self.min_score = min_score
        self.x: np.ndarray | None = None
        self.P = np.zeros((4, 4))
        self.wh = (0.0, 0.0)
        self.t_ns = 0
        self.last_match_ns = 0

    def _init(self, box: Sequence[float], t_ns: int) -> None:
        x, y, w, h = (float(v) for v in box)
        self.x = np.array([x + w / 2, y + h / 2, 0.0, 0.0])
        self.P = np.diag([self.r, self.r, self.v0, self.v0])
        self.wh = (w, h)
        self.t_ns = self.last_match_ns = t_ns

    def _box(self) -> Box:
        assert self.x is not None
        w, h = self.wh
        return (float(self.x[0] - w / 2), float(self.x[1] - h / 2), w, h)

    def step(self, frame_bgr: np.ndarray | None, detections: np.ndarray | None, t_ns: int,
             init_box: Sequence[float] | None = None) -> tuple[Box | None, dict[str, Any]]:
        if init_box is not None:
            self._init(init_box, t_ns)
            return self._box(), {"state": "INIT"}
        if self.x is None:
            return None, {"state": "UNINITIALISED"}
        dt = max(1e-6, (t_ns - self.t_ns) / 1e9)
        self.t_ns = t_ns
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        G = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + self.q * (G @ G.T)
        H = np.zeros((2, 4))
        H[0, 0] = H[1, 1] = 1.0
        S = H @ self.P @ H.T + self.r * np.eye(2)
        S_inv = np.linalg.inv(S)
        best, best_d2 = None, math.inf
        for det in np.asarray(detections if detections is not None else [], dtype=np.float64).reshape(-1, 5):
            if det[4] < self.min_score:
                continue
            nu = np.array([det[0] + det[2] / 2, det[1] + det[3] / 2]) - self.x[:2]
            d2 = float(nu @ S_inv @ nu)
            if d2 <= self.gate_chi2 and d2 < best_d2:
                best, best_d2 = det, d2
        if best is not None:
            nu = np.array([best[0] + best[2] / 2, best[1] + best[3] / 2]) - self.x[:2]
            K = self.P @ H.T @ S_inv
            self.x = self.x + K @ nu
            self.P = (np.eye(4) - K @ H) @ self.P
            a = self.alpha
            self.wh = ((1 - a) * self.wh[0] + a * float(best[2]), (1 - a) * self.wh[1] + a * float(best[3]))
            self.last_match_ns = t_ns
            return self._box(), {"state": "TRACKING"}
        if t_ns - self.last_match_ns > self.lost_after_ns:
            return None, {"state": "LOST"}
        return self._box(), {"state": "COASTING"}


def peer_kind(name: str) -> str:
    """``ByteTrack``, ``oc-sort``, ``bot_sort`` … → a name of PEER_NAMES; ValueError for anything else."""
    kind = name.lower().replace("-", "").replace("_", "")
    if kind not in PEER_NAMES:
        raise ValueError(f"unknown peer tracker {name!r}; known: {', '.join(PEER_NAMES)}")
    return kind


def peer_available() -> str | None:
    """None when Roboflow ``trackers`` can be imported, else the reason it cannot."""
    try:
        import trackers  # noqa: F401
    except Exception as exc:  # ImportError, or a broken dependency chain
        return f"the optional package 'trackers' is not importable ({exc.__class__.__name__}: {exc})"
    return None


class PeerFollower:
    """A Roboflow ``trackers`` MOT tracker, run as shipped, as a follower of one of its track ids.

    On the init frame the confirmed track overlapping the init box best is chosen; while no confirmed track
    overlaps it (trackers confirm after a few frames), later frames keep trying with IoU > 0.3 against the
    target's box *of that frame* (:meth:`update_reference`, given by the evaluation runner while the peer is
    unassigned): against the frame-1 box a later track of a stranger now standing there could win. From then
    on the output is the box the tracker reports for that id; on a frame it reports
    none (no detection matched), the tracker's own Kalman prediction for the id while its track is still
    alive (state COASTING), as followbus and the Kalman baseline coast on theirs; None once the tracker
    has deleted it (the id is lost: a MOT tracker that re-identifies the person under a new id has lost
    the target). ``info["mot"]`` carries the tracker's confirmed output ``(ids, boxes)`` for MOT scoring,
    never the coasted box.

    All three have a ByteTrack-style second association stage for the boxes under their
    ``high_conf_det_threshold`` 0.6, and ByteTrack's design feeds it everything above 0.1 (BoT-SORT keeps > 0.1).
    They are nevertheless given only the boxes above the evaluation's SCORE_THRESHOLD by default: fed the 0.1-0.3
    boxes too (``low_score_boxes=True``; the runner then passes them as ``low_detections``) ByteTrack and BoT-SORT
    do worse and OC-SORT no better (EVALUATION.md; ``trackers`` matches its second stage at IoU 0.1, ByteTrack's
    own code at 0.5), so the default is the stronger peer.
    """

    def __init__(self, kind: str, fps: float = 30.0, low_score_boxes: bool = False) -> None:
        kind = peer_kind(kind)
        reason = peer_available()
        if reason:
            raise RuntimeError(reason)
        import supervision as sv
        import trackers

        self._sv = sv
        cls = {"bytetrack": "ByteTrackTracker", "ocsort": "OCSORTTracker", "botsort": "BoTSORTTracker"}[kind]
        if not hasattr(trackers, cls):
            raise RuntimeError(f"trackers {getattr(trackers, '__version__', '?')} has no {cls}")
        self.tracker = getattr(trackers, cls)(frame_rate=fps)
        self.uses_frame = kind == "botsort"  # camera-motion compensation; the others warn when given a frame
        self.uses_low_scores = bool(low_score_boxes)
        self.name = f"peer:{kind}"
        self.target_id: int | None = None
        self._ref: Box | None = None

    @property
    def wants_reference(self) -> bool:
        """True until a track id is chosen: the runner then passes the target's box of each frame."""
        return self.target_id is None

    def update_reference(self, box: Sequence[float]) -> None:
        """The target's box on the coming frame (ground truth), to choose the id against while unassigned."""
        if self.target_id is None:
            self._ref = tuple(float(v) for v in box)

    def _pick(self, ids: list[int], boxes: list[Box], min_iou: float) -> None:
        assert self._ref is not None
        scored = [(box_iou(b, self._ref), i) for i, b in zip(ids, boxes, strict=True)]
        scored = [s for s in scored if s[0] > min_iou]
        if scored:
            self.target_id = max(scored)[1]

    def step(self, frame_bgr: np.ndarray | None, detections: np.ndarray | None, t_ns: int,
             init_box: Sequence[float] | None = None,
             low_detections: np.ndarray | None = None) -> tuple[Box | None, dict[str, Any]]:
        d = np.asarray(detections if detections is not None else [], dtype=np.float32).reshape(-1, 5)
        if low_detections is not None and self.uses_low_scores:
            d = np.concatenate([d, np.asarray(low_detections, dtype=np.float32).reshape(-1, 5)])
        xyxy = np.column_stack([d[:, 0], d[:, 1], d[:, 0] + d[:, 2], d[:, 1] + d[:, 3]]).reshape(-1, 4)
        sv_dets = self._sv.Detections(xyxy=xyxy.astype(np.float32), confidence=d[:, 4].astype(np.float32),
                                      class_id=np.zeros(len(d), dtype=int))
        out = self.tracker.update(sv_dets, frame_bgr) if self.uses_frame else self.tracker.update(sv_dets)
        all_ids = out.tracker_id if out.tracker_id is not None else np.full(len(out), -1)
        confirmed = [k for k, i in enumerate(all_ids) if int(i) >= 0]  # -1: a track not yet confirmed
        ids = [int(all_ids[k]) for k in confirmed]
        boxes: list[Box] = [(float(a), float(b), float(c - a), float(e - b))
                            for a, b, c, e in (out.xyxy[k] for k in confirmed)]
        info: dict[str, Any] = {"mot": (ids, boxes)}
        if init_box is not None:
            self._ref = tuple(float(v) for v in init_box)
            self.target_id = None
            self._pick(ids, boxes, 0.0)
        elif self.target_id is None and self._ref is not None:
            self._pick(ids, boxes, 0.3)
        if self.target_id is None:
            return None, {**info, "state": "UNASSIGNED"}
        for i, b in zip(ids, boxes, strict=True):
            if i == self.target_id:
                return b, {**info, "state": "TRACKING"}
        coasted = self._predicted_box()
        if coasted is not None:
            return coasted, {**info, "state": "COASTING"}
        return None, {**info, "state": "ID_MISSING"}

    def _predicted_box(self) -> Box | None:
        """The tracker's prediction for the followed id while its track is alive (``trackers`` 2.x keeps its
        tracklets, lost ones included, in ``.tracks``)."""
        for tracklet in getattr(self.tracker, "tracks", ()):
            if getattr(tracklet, "tracker_id", -1) == self.target_id:
                x0, y0, x1, y1 = (float(v) for v in np.asarray(tracklet.get_state_bbox()).reshape(-1)[:4])
                return (x0, y0, x1 - x0, y1 - y0)
        return None
