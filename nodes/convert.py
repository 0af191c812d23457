"""Lossless conversions between the pure tracking types and bus messages.

Floats travel as float64 (msgpack doubles or float64 arrays), so a value that crosses a process
boundary is bit-identical to the in-process one: the launched graph and ``followbus eval`` agree.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bus import schemas
from ..tracking.egomotion import CameraMotion
from ..tracking.kalman import Posterior, Prior
from ..tracking.reid import Candidate, ReidResult, TrackState

# Track states as the re-ID node publishes them; "UNINITIALISED" before a target is chosen.
STATES = tuple(s.value for s in TrackState)


def _box(value: Any) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64).reshape(4)


def _tuple_box(value: np.ndarray | None) -> tuple[float, float, float, float] | None:
    return None if value is None else tuple(float(v) for v in np.asarray(value).reshape(4))  # type: ignore[return-value]


def prior_to_msg(prior: Prior | None) -> schemas.Prior:
    if prior is None:
        return schemas.Prior(initialised=False)
    return schemas.Prior(
        initialised=True,
        state=np.asarray(prior.state, dtype=np.float64),
        size=np.asarray(prior.size, dtype=np.float64),
        covariance=np.asarray(prior.covariance, dtype=np.float64),
        innovation_cov=np.asarray(prior.innovation_cov, dtype=np.float64),
        gate_chi2=float(prior.gate_chi2),
        box=_box(prior.box),
    )


def msg_to_prior(msg: schemas.Prior | None) -> Prior | None:
    if msg is None or not msg.initialised:
        return None
    return Prior(
        t_ns=msg.header.stamp_ns,
        state=np.array(msg.state, dtype=np.float64),
        size=(float(msg.size[0]), float(msg.size[1])),
        covariance=np.array(msg.covariance, dtype=np.float64),
        innovation_cov=np.array(msg.innovation_cov, dtype=np.float64),
        gate_chi2=float(msg.gate_chi2),
    )


def reid_to_msg(result: ReidResult) -> schemas.Measurement:
    return schemas.Measurement(
        state=result.state.value,
        accepted=bool(result.accepted),
        secure=bool(result.secure),
        box=_box(result.box),
        best_box=_box(result.best_box),
        source=result.source,
        m_fuse=float(result.m_fuse),
        s_color=float(result.s_color),
        s_geo=float(result.s_geo),
        omega=float(result.omega),
        c_t=float(result.c_t),
        candidates=np.array([(*c.box, c.m_fuse) for c in result.candidates], dtype=np.float64).reshape(-1, 5),
        candidate_sources=[c.source for c in result.candidates],
        candidate_hist=None if result.candidate_hist is None else np.asarray(result.candidate_hist),
        init_box=_box(result.init_box),
    )


def msg_to_reid(msg: schemas.Measurement) -> ReidResult:
    """What prediction and template update need of a re-ID result (candidate details are not rebuilt
    beyond their boxes and scores)."""
    candidates = [
        Candidate(box=_tuple_box(row[:4]), source=src, maha_sq=float("nan"), s_color=float("nan"),
                  s_geo=float("nan"), m_fuse=float(row[4]))
        for row, src in zip(np.asarray(msg.candidates).reshape(-1, 5), msg.candidate_sources, strict=False)
    ]
    return ReidResult(
        t_ns=msg.header.stamp_ns,
        state=TrackState(msg.state),
        accepted=msg.accepted,
        secure=msg.secure,
        box=_tuple_box(msg.box),
        best_box=_tuple_box(msg.best_box),
        source=msg.source,
        m_fuse=msg.m_fuse,
        s_color=msg.s_color,
        s_geo=msg.s_geo,
        omega=msg.omega,
        c_t=msg.c_t,
        candidates=candidates,
        candidate_hist=None if msg.candidate_hist is None else np.array(msg.candidate_hist),
        init_box=_tuple_box(msg.init_box),
    )


def make_track(state: str, output_box: Any, posterior: Posterior | None) -> schemas.Track:
    return schemas.Track(
        state=state,
        box=_box(output_box),
        filtered_box=None if posterior is None else _box(posterior.box),
        velocity=np.zeros(2) if posterior is None else np.asarray(posterior.velocity_px_s, dtype=np.float64),
        measured=bool(posterior is not None and posterior.measured),
    )


def camera_motion_to_msg(motion: CameraMotion | None, reason: str = "") -> schemas.CameraMotion:
    if motion is None:
        return schemas.CameraMotion(valid=False, reason=reason)
    return schemas.CameraMotion(valid=True, matrix=np.asarray(motion.matrix, dtype=np.float64),
                                inliers=int(motion.inliers), tracked=int(motion.tracked),
                                from_stamp_ns=int(motion.from_t_ns), residual_px=float(motion.residual_px),
                                spread=float(motion.spread), rival_px=float(motion.rival_px),
                                rival_inliers=int(motion.rival_inliers), agreement_px=float(motion.agreement_px),
                                std_px=float(motion.std_px), static_cells=int(motion.static_cells))


def msg_to_camera_motion(msg: schemas.CameraMotion | None) -> CameraMotion | None:
    if msg is None or not msg.valid:
        return None
    return CameraMotion(np.array(msg.matrix, dtype=np.float64), int(msg.inliers), int(msg.tracked),
                        int(msg.from_stamp_ns), int(msg.header.stamp_ns), residual_px=float(msg.residual_px),
                        spread=float(msg.spread), rival_px=float(msg.rival_px), rival_inliers=int(msg.rival_inliers),
                        agreement_px=float(msg.agreement_px), std_px=float(msg.std_px),
                        static_cells=int(msg.static_cells))
