"""In-process composition of prediction, re-identification and template update.

The data order is exactly the process graph's, so evaluation in one process and the running
graph produce identical numbers. For frame k:

    C_k        = egomotion.step(frame_k, dets_k, t_k)      # camera motion k-1 → k (seed 002 §3.3), or None
    prior_k    = predictor.predict(t_k, v_ego_k, C_k)      # after frame k-1's measurement, warped by C_k
    reid_k     = reid.step(frame_k, dets_k, prior_k, M_{k-1}, t_k)
    predictor.apply(reid_k, v_ego_k)                        # update only if accepted (Eq. 7 R_k)
    M_k, η_k   = template.step(frame_k, reid_k)
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .egomotion import CameraMotion, EgoMotionEstimator, EgoMotionParams
from .kalman import Box, Posterior, Predictor, Prior
from .params import TrackerParams
from .reid import ReIdentifier, ReidResult, TrackState
from .template import TemplateUpdater

logger = logging.getLogger(__name__)


@dataclass
class FrameResult:
    t_ns: int
    state: TrackState
    box: Box | None  # accepted box; predicted box while OCCLUDED; None when LOST/uninitialised
    prior: Prior | None
    reid: ReidResult
    posterior: Posterior | None
    template_hist: np.ndarray | None
    eta_k: float
    p_specular: float
    camera_motion: CameraMotion | None = None


def output_box(reid: ReidResult, prior: Prior | None) -> Box | None:
    """The tracker's output for a frame: the accepted box; while OCCLUDED the predicted box (§2.3:
    keep following the hidden trajectory); None when LOST or before initialisation. The prediction
    node publishes exactly this in its Track message."""
    if reid.accepted:
        return reid.box
    if reid.state is TrackState.OCCLUDED and prior is not None:
        return prior.box
    return None


class TargetTracker:
    def __init__(self, params: TrackerParams | None = None, egomotion: EgoMotionParams | None = None) -> None:
        self.params = params or TrackerParams()
        self.predictor = Predictor(self.params)
        self.reid = ReIdentifier(self.params)
        self.template = TemplateUpdater(self.params)
        # The graph's egomotion node; not run at all when compensation is off (it would cost for nothing).
        self.egomotion = EgoMotionEstimator(egomotion) if self.params.camera_motion_compensation else None

    def step(
        self,
        frame_bgr: np.ndarray,
        detections: np.ndarray | None,
        t_ns: int,
        v_ego_mps: Sequence[float] = (0.0, 0.0),
        init_box: Sequence[float] | None = None,
        low_detections: np.ndarray | None = None,
    ) -> FrameResult:
        motion = None if self.egomotion is None else self.egomotion.step(frame_bgr, detections, t_ns)
        prior = self.predictor.predict(t_ns, v_ego_mps, motion)
        reid = self.reid.step(frame_bgr, detections, prior, self.template.hist, t_ns, init_box=init_box,
                              low_detections=low_detections)
        posterior = self.predictor.apply(reid, v_ego_mps)
        hist, eta, p_specular = self.template.step(frame_bgr, reid)
        return FrameResult(
            t_ns=int(t_ns),
            state=reid.state,
            box=output_box(reid, prior),
            prior=prior,
            reid=reid,
            posterior=posterior,
            template_hist=hist,
            eta_k=eta,
            p_specular=p_specular,
            camera_motion=motion,
        )
