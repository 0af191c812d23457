"""Constant-velocity Kalman prediction of the target centre (paper §2.3, Eq. 4-8).

State X = [x, y, vx, vy] (px, px/s) of the box centre. The box size (w, h) is not part of the
Kalman state: it is carried by a separate exponential smoother (constant under prediction,
w,h ← (1-a)·w,h + a·z_wh on update) because the paper's filter (Eq. 5) only models the centroid
and a size that lags a little is harmless for gating and drawing.

Time comes only from message stamps (``t_ns``), so replays are bit-identical.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from ..msgs.box import Box, box_array, box_centre, centre_size_to_box
from ..msgs.perception import CameraMotion
from ..msgs.tracking import DETECTOR_SOURCES, Measurement, Prior, Track, TrackState, mahalanobis_sq_from_cov
from .params import KalmanParams

logger = logging.getLogger(__name__)

# Eq. 5 measurement matrix: only the centre is observed.
H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])


def transition_matrix(dt_s: float) -> np.ndarray:
    """Eq. 5 state transition A for a constant-velocity model."""
    return np.array(
        [[1.0, 0.0, dt_s, 0.0], [0.0, 1.0, 0.0, dt_s], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    )


def process_noise(dt_s: float, accel_std_px_s2: float) -> np.ndarray:
    """Q of W_k (Eq. 4): discretised white acceleration, independent per axis."""
    q = accel_std_px_s2**2
    a, b, c = dt_s**4 / 4.0, dt_s**3 / 2.0, dt_s**2
    return q * np.array([[a, 0.0, b, 0.0], [0.0, a, 0.0, b], [b, 0.0, c, 0.0], [0.0, b, 0.0, c]])


def gate_ellipse_from_cov(
    centre: Sequence[float], S: np.ndarray, gate_chi2: float
) -> tuple[float, float, float, float, float]:
    """The Eq. 8 region dᵀS⁻¹d ≤ χ² as (cx, cy, semi_axis_a, semi_axis_b, angle_deg).

    a ≥ b; angle is the direction of the a axis in image coordinates (x right, y down), in
    (-90, 90] degrees, as expected by cv2.ellipse (which takes the full axes 2a, 2b).
    """
    evals, evecs = np.linalg.eigh(np.asarray(S, dtype=np.float64))  # ascending eigenvalues
    evals = np.clip(evals, 0.0, None)
    a = math.sqrt(gate_chi2 * evals[1])
    b = math.sqrt(gate_chi2 * evals[0])
    if evals[1] - evals[0] <= 1e-12 * max(float(evals[1]), 1e-300):
        return (float(centre[0]), float(centre[1]), a, b, 0.0)  # a circle: any angle; report 0
    vx, vy = float(evecs[0, 1]), float(evecs[1, 1])
    angle = math.degrees(math.atan2(vy, vx))
    # An eigenvector's sign is arbitrary; fold to (-90, 90] so the output is unique.
    if angle <= -90.0:
        angle += 180.0
    elif angle > 90.0:
        angle -= 180.0
    return (float(centre[0]), float(centre[1]), a, b, angle)


class KalmanCV:
    """Eq. 4-8 constant-velocity filter on the box centre, plus a smoothed box size."""

    def __init__(
        self,
        accel_std_px_s2: float = 500.0,
        r0_px2: float = 64.0,
        kappa_px2_per_mps2: float = 400.0,
        init_velocity_std_px_s: float = 300.0,
        dt_ms: float = 33.0,
        gate_chi2: float = 9.488,
        size_smoothing: float = 0.3,
    ) -> None:
        self.accel_std_px_s2 = float(accel_std_px_s2)
        self.r0_px2 = float(r0_px2)
        self.kappa_px2_per_mps2 = float(kappa_px2_per_mps2)
        self.init_velocity_std_px_s = float(init_velocity_std_px_s)
        self.dt_ms = float(dt_ms)
        self.gate_chi2 = float(gate_chi2)
        self.size_smoothing = float(size_smoothing)
        self.x = np.zeros(4)
        self.P = np.eye(4)
        self.size = (0.0, 0.0)
        self.R = self.r0_px2 * np.eye(2)  # last measurement noise used; default for gating
        self.t_ns: int | None = None  # stamp the state refers to
        self.initialised = False

    @classmethod
    def from_params(cls, params: KalmanParams) -> KalmanCV:
        return cls(
            accel_std_px_s2=params.accel_std_px_s2,
            r0_px2=params.r0_px2,
            kappa_px2_per_mps2=params.kappa_px2_per_mps2,
            init_velocity_std_px_s=params.init_velocity_std_px_s,
            dt_ms=params.dt_ms,
            gate_chi2=params.gate_chi2,
            size_smoothing=params.size_smoothing,
        )

    def initialise(self, box: Sequence[float], t_ns: int | None = None) -> None:
        """Start at the box centre with zero velocity; position variance R0, velocity variance wide."""
        cx, cy = box_centre(box)
        self.x = np.array([cx, cy, 0.0, 0.0])
        v2 = self.init_velocity_std_px_s**2
        self.P = np.diag([self.r0_px2, self.r0_px2, v2, v2])
        self.size = (float(box[2]), float(box[3]))
        self.R = self.r0_px2 * np.eye(2)
        self.t_ns = None if t_ns is None else int(t_ns)
        self.initialised = True

    def predict(self, t_ns: int | None = None) -> None:
        """Time update X⁻ = A X, P⁻ = A P Aᵀ + Q (Eq. 4-5) up to stamp ``t_ns``.

        Δt comes from consecutive stamps; with no previous stamp (or ``t_ns`` None) it falls back
        to ``dt_ms``. Predicting to the same stamp twice is a no-op (Δt = 0), so a repeated call
        for one frame is harmless; an older stamp is treated as Δt = 0.
        """
        if not self.initialised:
            raise RuntimeError("KalmanCV.predict() before initialise()")
        if t_ns is None or self.t_ns is None:
            dt_s = self.dt_ms / 1000.0
        else:
            dt_ns = int(t_ns) - self.t_ns
            if dt_ns < 0:
                logger.warning("predict: stamp %d older than state stamp %d; holding state", t_ns, self.t_ns)
                dt_ns = 0
            dt_s = dt_ns / 1e9
        if t_ns is not None:
            self.t_ns = max(int(t_ns), self.t_ns) if self.t_ns is not None else int(t_ns)
        elif self.t_ns is not None:
            self.t_ns += int(round(self.dt_ms * 1e6))
        if dt_s == 0.0:
            return
        A = transition_matrix(dt_s)
        self.x = A @ self.x
        P = A @ self.P @ A.T + process_noise(dt_s, self.accel_std_px_s2)
        self.P = 0.5 * (P + P.T)

    def warp(self, matrix: np.ndarray) -> None:
        """Carry the state into the next frame's pixels after the camera moved: p' = M p + t (2x3 [M | t]).

        The centre is mapped by the full transform, the velocity (a difference of positions) by M only, the
        covariance by T P Tᵀ with T = diag(M, M) (the linear map of the state), the box size by the scale
        sqrt|det M|: the prior then sits where the background-stabilised target is (seed 002 §3.3, with the
        image motion measured on the background, tracking/egomotion.py).
        """
        A = np.asarray(matrix, dtype=np.float64)
        M, t = A[:, :2], A[:, 2]
        T = np.zeros((4, 4))
        T[:2, :2] = M
        T[2:, 2:] = M
        self.x = T @ self.x
        self.x[:2] += t
        P = T @ self.P @ T.T
        self.P = 0.5 * (P + P.T)
        s = math.sqrt(abs(float(np.linalg.det(M))))
        self.size = (self.size[0] * s, self.size[1] * s)

    def widen(self, cov_px2: np.ndarray) -> None:
        """Add a 2x2 position covariance (px²): an uncertain camera motion moves the target by an unknown amount
        (tracking/egomotion.py's std_px), so the prior, and with it the gate (Eq. 8's S = H P Hᵀ + R), grows."""
        self.P[:2, :2] += np.asarray(cov_px2, dtype=np.float64)
        self.P = 0.5 * (self.P + self.P.T)

    def measurement_noise(self, v_ego_mps: Sequence[float] = (0.0, 0.0)) -> np.ndarray:
        """Eq. 7: R_k = R0 + κ‖v_ego‖² I — vibration at speed makes the image centre less reliable."""
        speed2 = float(v_ego_mps[0]) ** 2 + float(v_ego_mps[1]) ** 2
        return (self.r0_px2 + self.kappa_px2_per_mps2 * speed2) * np.eye(2)

    def innovation_cov(self, R: np.ndarray | None = None) -> np.ndarray:
        """S = H P⁻ Hᵀ + R.

        The paper writes the gate (Eq. 8) with P_k; the covariance of the innovation Z - ẐK is S,
        which is the principled form (it also counts measurement noise, so the gate widens with
        ego speed via Eq. 7).
        """
        R = self.R if R is None else np.asarray(R, dtype=np.float64)
        S = H @ self.P @ H.T + R
        return 0.5 * (S + S.T)

    def mahalanobis_sq(self, z: Sequence[float], R: np.ndarray | None = None) -> float:
        return mahalanobis_sq_from_cov(z, self.x[:2], self.innovation_cov(R))

    def gate_ellipse(self, R: np.ndarray | None = None) -> tuple[float, float, float, float, float]:
        return gate_ellipse_from_cov(self.x[:2], self.innovation_cov(R), self.gate_chi2)

    def update(
        self,
        z_xy: Sequence[float],
        wh: Sequence[float] | None = None,
        R: np.ndarray | None = None,
    ) -> None:
        """Measurement update with Z = H X + V (Eq. 6); ``wh`` None keeps the size unchanged."""
        if not self.initialised:
            raise RuntimeError("KalmanCV.update() before initialise()")
        if R is not None:
            self.R = np.asarray(R, dtype=np.float64)
        z = np.array([float(z_xy[0]), float(z_xy[1])])
        S = self.innovation_cov(self.R)
        K = np.linalg.solve(S, H @ self.P).T  # P Hᵀ S⁻¹ (S and P symmetric)
        self.x = self.x + K @ (z - H @ self.x)
        # Joseph form keeps P symmetric positive definite under rounding.
        IKH = np.eye(4) - K @ H
        P = IKH @ self.P @ IKH.T + K @ self.R @ K.T
        self.P = 0.5 * (P + P.T)
        if wh is not None:
            a = self.size_smoothing
            self.size = (
                (1.0 - a) * self.size[0] + a * float(wh[0]),
                (1.0 - a) * self.size[1] + a * float(wh[1]),
            )

    @property
    def box(self) -> Box:
        return centre_size_to_box(float(self.x[0]), float(self.x[1]), *self.size)


# The two motion models of the prediction (an interacting multiple model filter, Blom & Bar-Shalom 1988):
# "scene": the target moves at constant velocity in the scene, so its prior is carried by the camera's own image
# motion (seed 002 §3.3's compensation); "image": it keeps its course in the image, the camera's motion aside (a
# camera that follows the person: a robot turning towards them, a drone tracking a boat, a panning camera). Which
# holds is weighed frame by frame by how well each predicted the target's measured position.
SCENE, IMAGE = "scene", "image"


class Predictor:
    """The prediction process: owns the Kalman filters and the Eq. 7 noise, consumes re-ID results.

    Per frame k the graph calls ``predict(t_k, v_ego)`` → Prior (published to re-ID), then
    ``apply(reid_k, v_ego)`` once the measurement of frame k arrives. Suspension of the
    measurement update (§2.3, Alg. 1 line 17) is simply not updating when nothing was accepted.

    With camera-motion compensation the prior is an interacting multiple model (IMM) of the "scene" and "image"
    models above: each frame the two filters are mixed by the model probabilities (switching with
    ``model_switch_probability`` a frame), predicted (only "scene" warped by the camera motion), combined into the
    published prior, whose covariance includes how far the two disagree (a wider gate while it is unclear whether
    the camera follows the target), and on a measurement each is updated and reweighed by its likelihood.
    """

    def __init__(self, params: KalmanParams | None = None) -> None:
        self.params = params or KalmanParams()
        p = self.params
        if not p.camera_motion_compensation:
            self.models: tuple[str, ...] = (IMAGE,)
        else:
            self.models = (SCENE, IMAGE) if p.image_motion_model else (SCENE,)
        self.filters = {m: KalmanCV.from_params(p) for m in self.models}
        self.mode = np.full(len(self.models), 1.0 / len(self.models))  # model probabilities
        # Priors warped by the camera motion, and motions not applied because they do not start at the
        # filter's stamp (a frame the motion estimate or this filter did not see).
        self.warped = 0
        self.motion_mismatched = 0
        self.motion_held = 0  # doubtful motions that only widened a coasting prior
        self._motion_t_ns: int | None = None  # the stamp up to which the camera's motion has been applied
        self._coasting = False  # no detection matched on the last applied frame
        self.recent_shift_px2 = 0.0  # running mean of the camera's squared displacement at the target (px²)
        self.motion_unfitted = 0  # frames whose camera motion could not be measured: the prior widened instead
        # Per model, the last measured centre in the current frame's pixels (the "scene" model's carried by the
        # camera's motion), and its stamp: a re-lock's velocity after a long coast (_relock_velocity).
        self._last_measured: dict[str, np.ndarray] = {}
        self._last_measured_t_ns: int | None = None

    @property
    def initialised(self) -> bool:
        return self.filters[self.models[0]].initialised

    @property
    def kf(self) -> KalmanCV:
        """The combined estimate as one filter's state (read it, do not step it)."""
        first = self.filters[self.models[0]]
        if len(self.models) == 1:
            return first
        combined = KalmanCV.from_params(self.params)
        combined.x, combined.P = self._combined(self.mode)
        combined.size = self._combined_size(self.mode)
        combined.R, combined.t_ns, combined.initialised = first.R, first.t_ns, first.initialised
        return combined

    @property
    def image_model_probability(self) -> float:
        return float(self.mode[self.models.index(IMAGE)]) if IMAGE in self.models else 0.0

    def reset(self) -> None:
        self.filters = {m: KalmanCV.from_params(self.params) for m in self.models}
        self.mode = np.full(len(self.models), 1.0 / len(self.models))
        self._last_measured, self._last_measured_t_ns = {}, None

    def initialise(self, box: Sequence[float], t_ns: int | None = None) -> None:
        """Every model starts at ``box`` (no velocity), both equally likely."""
        for kf in self.filters.values():
            kf.initialise(box, t_ns)
        self.mode = np.full(len(self.models), 1.0 / len(self.models))
        self._motion_t_ns = None if t_ns is None else int(t_ns)
        self._last_measured = {m: np.asarray(box_centre(box), dtype=np.float64) for m in self.models}
        self._last_measured_t_ns = None if t_ns is None else int(t_ns)

    def _combined(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The moment-matched mixture of the filters' states: mean, and covariance including their spread."""
        xs = [self.filters[m].x for m in self.models]
        x = sum(w * xi for w, xi in zip(weights, xs, strict=True))
        P = sum(w * (self.filters[m].P + np.outer(xi - x, xi - x))
                for w, m, xi in zip(weights, self.models, xs, strict=True))
        return np.asarray(x, dtype=np.float64), 0.5 * (P + P.T)

    def _combined_size(self, weights: np.ndarray) -> tuple[float, float]:
        sizes = np.array([self.filters[m].size for m in self.models], dtype=np.float64)
        w, h = (weights[:, None] * sizes).sum(axis=0)
        return float(w), float(h)

    def _switch_matrix(self) -> np.ndarray:
        """The models' Markov switching probabilities [from, to]: model_switch_probability a frame."""
        n = len(self.models)
        q = self.params.model_switch_probability
        switch = np.full((n, n), q / (n - 1))
        np.fill_diagonal(switch, 1.0 - q)
        return switch

    def _mix(self) -> np.ndarray:
        """IMM step 1: each filter restarts from the mixture of all, weighted by how likely the system was in
        each model given it is now in this one. Returns the predicted model probabilities."""
        n = len(self.models)
        if n == 1:
            return self.mode
        switch = self._switch_matrix()
        predicted = switch.T @ self.mode
        if self._coasting and not self.params.mix_models_while_coasting:
            return predicted  # no measurement to say which model is right: their states stay apart
        mixing = switch * self.mode[:, None] / np.maximum(predicted[None, :], 1e-300)  # [from, to]
        states = [(self.filters[m].x.copy(), self.filters[m].P.copy(), self.filters[m].size) for m in self.models]
        for j, m in enumerate(self.models):
            kf = self.filters[m]
            kf.x = sum(mixing[i, j] * states[i][0] for i in range(n))
            kf.P = sum(mixing[i, j] * (states[i][1] + np.outer(states[i][0] - kf.x, states[i][0] - kf.x))
                       for i in range(n))
            kf.P = 0.5 * (kf.P + kf.P.T)
            kf.size = tuple(float(v) for v in sum(mixing[i, j] * np.asarray(states[i][2]) for i in range(n)))
        return predicted

    def predict(self, t_ns: int, v_ego_mps: Sequence[float] = (0.0, 0.0),
                camera_motion: CameraMotion | None = None) -> Prior | None:
        """Prior of frame ``t_ns``; None before initialisation.

        ``camera_motion`` (frame k-1 → k image motion) warps the "scene" model's prediction when it starts at the
        filter's stamp; one marked not valid (no trustworthy fit) is as none.
        """
        if not self.initialised:
            return None
        unfitted = camera_motion is not None and not camera_motion.valid and camera_motion.header.stamp_ns == t_ns
        if camera_motion is not None and not camera_motion.valid:
            camera_motion = None
        from_t_ns = self.filters[self.models[0]].t_ns
        self.mode = self._mix()
        for m in self.models:
            self.filters[m].predict(t_ns)
        if SCENE in self.models:
            self._compensate(self.filters[SCENE], camera_motion, from_t_ns, int(t_ns))
            if unfitted and self.params.camera_motion_uncertainty:
                # The camera moved by an unknown amount: as much as it has lately, in any direction (a jerk
                # blurred the frame past fitting), not by nothing.
                self.motion_unfitted += 1
                self.filters[SCENE].widen(self.recent_shift_px2 * np.eye(2))
        first = self.filters[self.models[0]]
        R = first.measurement_noise(v_ego_mps)  # Eq. 7 with the current ego speed
        x, P = self._combined(self.mode)
        prior = Prior.of_filter(int(t_ns), x, self._combined_size(self.mode), P, H @ P @ H.T + R, first.gate_chi2)
        if len(self.models) > 1:
            # Ties (no measurement since the start yet) go to the last model, "image": until one says otherwise,
            # a camera that follows a person keeps them where they were seen, while the camera's motion estimate
            # can be the background's alone (parallax: a near person, far stands).
            likeliest = len(self.models) - 1 - int(np.argmax(self.mode[::-1]))
            prior.likeliest_box = box_array(self.filters[self.models[likeliest]].box)
        limit = self.params.occluded_output_min_overlap_probability
        prior.locates_person = limit <= 0.0 or prior.overlap_probability() >= limit
        return prior

    def _compensate(self, kf: KalmanCV, motion: CameraMotion | None, from_t_ns: int | None, t_ns: int) -> None:
        """Seed 002 §3.3's warp with the motion's doubt (its std_px), on the "scene" model. A motion that starts where
        the applied chain ends (the filter's last stamp, or an earlier frame whose fit failed: egomotion then spans
        both steps) warps the prior and widens it by its std²; a doubtful one (std above camera_motion_doubt_px)
        leaves a coasting prior in place, widened by the displacement it would have applied. No motion: the prior
        as predicted."""
        p = self.params
        chained = (motion is not None and motion.header.stamp_ns == t_ns
                   and motion.from_stamp_ns in (from_t_ns, self._motion_t_ns))
        if motion is not None and not chained:
            self.motion_mismatched += 1
        if not chained:
            # No widening here: whether a transform came in time depends on the live timing (an optional
            # input), and the launched graph, its replay and the in-process run must compute the same prior.
            return
        assert motion is not None
        self._motion_t_ns = t_ns
        centre = kf.x[:2].copy()
        shift = motion.matrix[:, :2] @ centre + motion.matrix[:, 2] - centre
        self.recent_shift_px2 = 0.9 * self.recent_shift_px2 + 0.1 * float(shift @ shift)
        if SCENE in self._last_measured:  # where the last measured centre lies in this frame's pixels
            self._last_measured[SCENE] = motion.matrix[:, :2] @ self._last_measured[SCENE] + motion.matrix[:, 2]
        if not p.camera_motion_uncertainty:
            kf.warp(motion.matrix)
            self.warped += 1
            return
        if self._coasting and motion.std_px > p.camera_motion_doubt_px:
            self.motion_held += 1
            kf.widen(np.outer(shift, shift) + motion.std_px**2 * np.eye(2))
            return
        kf.warp(motion.matrix)
        kf.widen(motion.std_px**2 * np.eye(2))
        self.warped += 1

    def apply(self, reid: Measurement, v_ego_mps: Sequence[float] = (0.0, 0.0)) -> Track | None:
        """Fold frame k's re-ID measurement into the filters (Alg. 1 lines 11/13 and 16/17) and reweigh the models
        by how well each predicted it; the posterior as a track (its output ``box`` is the caller's:
        :func:`output_box`), None before initialisation."""
        t_ns = reid.header.stamp_ns
        self._coasting = not reid.accepted and reid.init_box is None
        if reid.init_box is not None:
            self.initialise(reid.init_box, t_ns)
            logger.info("predictor initialised at %s", tuple(round(float(v), 1) for v in reid.init_box))
            return self._posterior(reid, measured=True)
        if not self.initialised:
            return None
        box = reid.box if reid.accepted else None
        if box is None and not self.params.suspend_updates:
            box = reid.best_box  # ablation "w/o update suspension": trust the best candidate anyway
        if box is None:
            return self._posterior(reid, measured=False)
        # Motion-blob boxes cover only the moving part of the target, so they locate it but do
        # not measure its extent: only detector boxes update the size.
        wh = (box[2], box[3]) if reid.source in DETECTOR_SOURCES else None
        R = self.filters[self.models[0]].measurement_noise(v_ego_mps)
        z = np.asarray(box_centre(box), dtype=np.float64)
        likelihood = np.array([self._likelihood(self.filters[m], z, R) for m in self.models])
        for m in self.models:
            self.filters[m].update(z, wh, R)
        self._relock_velocity(z, t_ns)
        weighted = self.mode * likelihood
        if weighted.sum() > 0.0 and np.isfinite(weighted).all():
            self.mode = weighted / weighted.sum()
        return self._posterior(reid, measured=True)

    def _relock_velocity(self, z: np.ndarray, t_ns: int) -> None:
        """After a coast of relock_velocity_after_coast_ms or more, each model's velocity is the displacement from
        its last measured centre to ``z`` over the gap (KalmanParams.relock_velocity_after_coast_ms); ``z`` is then
        the last measured centre."""
        limit_ms = self.params.relock_velocity_after_coast_ms
        gap_s = None if self._last_measured_t_ns is None else (t_ns - self._last_measured_t_ns) / 1e9
        for m in self.models:
            last = self._last_measured.get(m)
            if last is not None and gap_s is not None and 0.0 < limit_ms <= gap_s * 1e3:
                self.filters[m].x[2:] = (z - last) / gap_s
            self._last_measured[m] = z.copy()
        self._last_measured_t_ns = int(t_ns)

    @staticmethod
    def _likelihood(kf: KalmanCV, z: Sequence[float], R: np.ndarray) -> float:
        """N(z; H x⁻, S): how well a model predicted the measured centre."""
        S = kf.innovation_cov(R)
        d2 = kf.mahalanobis_sq(z, R)
        return math.exp(-0.5 * d2) / (2.0 * math.pi * math.sqrt(max(float(np.linalg.det(S)), 1e-300)))

    def _posterior(self, reid: Measurement, measured: bool) -> Track:
        combined = self.kf
        track = Track(state=reid.state, filtered_box=box_array(combined.box),
                      velocity=np.array([float(combined.x[2]), float(combined.x[3])]), measured=measured)
        track.header.stamp_ns = int(reid.header.stamp_ns)
        return track


def output_box(reid: Measurement, prior: Prior | None) -> np.ndarray | None:
    """The tracker's output for a frame: the accepted box; while OCCLUDED the predicted box (§2.3:
    keep following the hidden trajectory: Prior.coasting_box) as long as it still locates the person: it more likely
    overlaps them than not (Prior.locates_person, KalmanParams.occluded_output_min_overlap_probability), or re-ID
    saw the target's colours there (Measurement.coasting_colours_seen: a person the detector does not see in an odd
    pose is still where their colours are, however uncertain the prediction). None when LOST, before
    initialisation or when the prediction no longer locates the person. The prediction node publishes exactly this
    as its Track message's ``box``."""
    if reid.accepted:
        return reid.box
    if reid.state != TrackState.OCCLUDED or prior is None or not prior.initialised:
        return None
    if not (prior.locates_person or reid.coasting_colours_seen):
        return None
    return prior.coasting_box()
