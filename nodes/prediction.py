"""prediction: constant-velocity Kalman on the target (seed 000 Eq. 4-8).

For each frame k (ticked by its detections) it publishes the prior: state, P_k, the innovation
covariance and the χ² gate (Eq. 8). Its measurement input is joined with offset -1, so prior k is
computed after frame k-1's re-ID result was folded in.
Each re-ID result is applied as soon as it arrives (measurement update, or suspension when the
target is occluded) and the posterior track is published at once, so motor control is not held
back a frame. An optional same-frame ``transform`` (the egomotion node's camera motion, seed 002 §3.3) warps
the prior before it is published. Odometry feeds the ego-motion-aware measurement noise R_k = R0 + κ‖v_ego‖² I (Eq. 7):
for frame k the newest odometry sample stamped at or before frame k's capture (an input sampled by stamp), never
"whatever arrived last", so a live run and its lockstep replay compute the same R_k.

Self-healing: a frame stamp that goes back, or jumps further ahead than ``max_predict_gap_ms``, or a
filter state that is no longer finite, resets the filter (counted in ``resets``). The prior is then
uninitialised and re-ID re-initialises the target from its template, so the loop recovers by itself
instead of extrapolating a poisoned state forever.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.schemas import Message
from ..msgs.perception import CameraMotion, Detections
from ..msgs.robot import Odometry
from ..msgs.tracking import Measurement, Prior, Track
from ..tracking.kalman import Predictor, output_box
from ..tracking.params import KalmanParams, check_ranges


@dataclass
class PredictionNodeParams:
    use_odometry: bool = True  # False: R_k = R0 (the ablation without ego-motion-aware noise)
    max_predict_gap_ms: float = 5000.0  # a longer jump between frame stamps re-initialises the filter

    def __post_init__(self) -> None:
        check_ranges(self, positive=("max_predict_gap_ms",))


class Prediction(Node):
    # Each measurement is applied as it arrives (on_message); as a feedback input it also holds prior k back until
    # measurement k-1 was applied. Odometry (100 Hz) is read by stamp when a frame or a measurement comes.
    INPUTS = {"detections": In(Detections, required=True),
              "measurement": In(Measurement, required=True, on_arrival=True),
              "odometry": In(Odometry, sample_by_stamp=True), "transform": In(CameraMotion)}
    OUTPUTS = {"prior": Out(Prior), "track": Out(Track)}
    Params = (PredictionNodeParams, KalmanParams)

    def setup(self) -> None:
        self.node_params, kalman_params = self.params
        self.predictor = Predictor(kalman_params)
        self.priors: dict[int, Prior] = {}  # frame_seq -> the published prior, until its measurement arrives
        self.applied_seq = -1
        self.applied_epoch = 0
        self.last_state = "UNINITIALISED"
        self.filter_resets = 0

    def _reset_filter(self, why: str) -> None:
        self.log.warning("resetting the Kalman filter: %s; re-ID will re-initialise the target", why)
        self.filter_resets += 1
        self.predictor.reset()
        self.priors.clear()

    def _filter_ok(self) -> bool:
        kf = self.predictor.kf
        return not kf.initialised or bool(np.isfinite(kf.x).all() and np.isfinite(kf.P).all())

    def _v_ego(self) -> tuple[float, float]:
        """Ego velocity at the capture stamp of what is handled: the newest odometry sample not after it."""
        if not self.node_params.use_odometry:
            return (0.0, 0.0)
        odom = self.runtime.sample("odometry")
        if not isinstance(odom, Odometry):
            return (0.0, 0.0)
        # Eq. 7 needs the ego speed; the filter is in image space, so only its magnitude matters.
        return (odom.vx_mps, odom.vy_mps)

    def on_message(self, name: str, msg: Message) -> None:
        if name != "measurement" or not isinstance(msg, Measurement):
            return
        seq = msg.header.frame_seq
        if msg.header.epoch_ns != self.applied_epoch:
            # The synchroniser followed a restarted capture (new frame numbering): so do we.
            self.applied_epoch, self.applied_seq = msg.header.epoch_ns, -1
            self.priors.clear()
        if seq <= self.applied_seq:
            return
        prior = self.priors.pop(seq, None)
        posterior = self.predictor.apply(msg, self._v_ego())
        if not self._filter_ok():
            self._reset_filter("the measurement update left a non-finite state")
            posterior = None
        self.applied_seq = seq
        self.last_state = msg.state
        self.publish("track", self._track(msg, prior, posterior))
        for old in [s for s in self.priors if s < seq]:
            del self.priors[old]

    def _track(self, msg: Measurement, prior: Prior | None, posterior: Track | None) -> Track:
        """The track of a measurement: the filter's posterior (none: no filtered box, no velocity) with the
        tracker's output box (tracking/kalman.py output_box)."""
        track = posterior or Track(state=msg.state)
        track.box = output_box(msg, prior)
        return track

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        dets = inputs["detections"]
        assert dets is not None
        stamp = dets.header.stamp_ns
        last = self.predictor.kf.t_ns if self.predictor.initialised else None
        if last is not None and not 0 <= stamp - last <= self.node_params.max_predict_gap_ms * 1e6:
            self._reset_filter(f"frame stamp jumped by {(stamp - last) / 1e6:.0f} ms")
        # The egomotion node's transform of this frame, when it came in time: the prior warped by the camera's
        # motion (seed 002 §3.3); without it (no such node, late, no trustworthy fit) the prior is not warped.
        motion = inputs.get("transform")
        assert motion is None or isinstance(motion, CameraMotion)
        prior = self.predictor.predict(stamp, self._v_ego(), motion)
        if not self._filter_ok():
            self._reset_filter("the prediction left a non-finite state")
            prior = None
        prior = prior or Prior()  # uninitialised: re-ID initialises the target
        self.priors[frame_seq] = prior
        self.publish("prior", prior)

    def status(self) -> dict[str, Any]:
        return {"state": self.last_state, "initialised": self.predictor.initialised,
                "filter_resets": self.filter_resets, "priors_warped": self.predictor.warped,
                "camera_motion_mismatched": self.predictor.motion_mismatched,
                "camera_motion_held": self.predictor.motion_held,
                "camera_motion_unfitted": self.predictor.motion_unfitted,
                "image_model_probability": round(self.predictor.image_model_probability, 3)}


NODE = Prediction
