"""Kalman prediction (seed 000 Eq. 4-8) against hand-computed numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.tracking.kalman import KalmanCV, Predictor, gate_ellipse_from_cov
from followbus.tracking.params import KalmanParams
from followbus.tracking.reid import Candidate, TrackState, measurement


def make_kf(**kw: float) -> KalmanCV:
    # σ_a = 10 px/s², R0 = 4 px², σ_v0 = 1 px/s, Δt fallback 100 ms: small round numbers.
    args = dict(accel_std_px_s2=10.0, r0_px2=4.0, kappa_px2_per_mps2=2.0, init_velocity_std_px_s=1.0,
                dt_ms=100.0, gate_chi2=9.488, size_smoothing=0.5)
    args.update(kw)
    return KalmanCV(**args)


def test_predict_matches_hand_computation() -> None:
    kf = make_kf()
    kf.initialise((90.0, 40.0, 20.0, 20.0), t_ns=0)  # centre (100, 50)
    kf.predict(100_000_000)  # Δt = 0.1 s from stamps
    # Per axis: A P Aᵀ = [[4 + 0.01, 0.1], [0.1, 1]]; Q = 100·[[0.1⁴/4, 0.1³/2], [0.1³/2, 0.1²]]
    #         = [[0.0025, 0.05], [0.05, 1]]  →  P⁻ = [[4.0125, 0.15], [0.15, 2.0]]
    assert kf.x == pytest.approx([100.0, 50.0, 0.0, 0.0])
    assert kf.P[0, 0] == pytest.approx(4.0125)
    assert kf.P[0, 2] == pytest.approx(0.15)
    assert kf.P[2, 2] == pytest.approx(2.0)
    assert kf.P[1, 1] == pytest.approx(4.0125)
    assert kf.P[0, 1] == pytest.approx(0.0)


def test_update_matches_hand_computation() -> None:
    kf = make_kf()
    kf.initialise((90.0, 40.0, 20.0, 20.0), t_ns=0)
    kf.predict(100_000_000)
    kf.update((103.0, 50.0), (30.0, 20.0), R=4.0 * np.eye(2))
    # S = 4.0125 + 4 = 8.0125; K = [4.0125, 0.15] / 8.0125; innovation 3 px in x.
    s = 8.0125
    assert kf.x[0] == pytest.approx(100.0 + 3.0 * 4.0125 / s)
    assert kf.x[2] == pytest.approx(3.0 * 0.15 / s)
    assert kf.x[1] == pytest.approx(50.0)
    assert kf.P[0, 0] == pytest.approx(4.0125 * 4.0 / s)
    assert kf.P[0, 2] == pytest.approx(0.15 * 4.0 / s)
    assert kf.P[2, 2] == pytest.approx(2.0 - 0.15**2 / s)
    assert kf.size == pytest.approx((25.0, 20.0))  # a = 0.5 size smoothing
    # Constant-velocity extrapolation over a 50 ms stamp gap.
    x_post, vx_post = kf.x[0], kf.x[2]
    kf.predict(150_000_000)
    assert kf.x[0] == pytest.approx(x_post + 0.05 * vx_post)


def test_first_step_falls_back_to_dt_ms_and_same_stamp_is_noop() -> None:
    kf = make_kf()
    kf.initialise((90.0, 40.0, 20.0, 20.0), t_ns=None)
    kf.predict(5_000_000_000)  # no previous stamp: Δt = dt_ms = 0.1 s
    assert kf.P[0, 0] == pytest.approx(4.0125)
    P = kf.P.copy()
    kf.predict(5_000_000_000)
    np.testing.assert_array_equal(kf.P, P)


def test_eq7_measurement_noise_grows_with_ego_speed() -> None:
    kf = make_kf(r0_px2=64.0, kappa_px2_per_mps2=400.0)
    np.testing.assert_allclose(kf.measurement_noise((0.0, 0.0)), 64.0 * np.eye(2))
    np.testing.assert_allclose(kf.measurement_noise((1.0, 0.0)), 464.0 * np.eye(2))
    np.testing.assert_allclose(kf.measurement_noise((0.3, 0.4)), (64.0 + 400.0 * 0.25) * np.eye(2))
    speeds = [0.0, 0.5, 1.0, 2.0]
    r = [kf.measurement_noise((v, 0.0))[0, 0] for v in speeds]
    assert all(a < b for a, b in zip(r, r[1:], strict=False))

    # Larger R_k → the filter trusts the same measurement less.
    moves = []
    for v in (0.0, 2.0):
        f = make_kf(r0_px2=64.0, kappa_px2_per_mps2=400.0)
        f.initialise((90.0, 40.0, 20.0, 20.0), t_ns=0)
        f.predict(33_000_000)
        f.update((110.0, 50.0), None, f.measurement_noise((v, 0.0)))
        moves.append(f.x[0] - 100.0)
    assert moves[0] > moves[1] > 0.0


def test_gate_membership_uses_innovation_covariance() -> None:
    kf = make_kf()
    kf.initialise((90.0, 40.0, 20.0, 20.0), t_ns=0)
    kf.P = np.diag([5.0, 12.0, 1.0, 1.0])
    R = 4.0 * np.eye(2)  # S = HPHᵀ + R = diag(9, 16)
    np.testing.assert_allclose(kf.innovation_cov(R), np.diag([9.0, 16.0]))
    inside = (100.0 + math.sqrt(9.0 * 9.0), 50.0)  # d² = 9.0
    outside = (100.0 + math.sqrt(10.0 * 9.0), 50.0)  # d² = 10.0
    assert kf.mahalanobis_sq(inside, R) == pytest.approx(9.0)
    assert kf.mahalanobis_sq(inside, R) <= kf.gate_chi2  # Eq. 8: in the gate
    assert kf.mahalanobis_sq(outside, R) == pytest.approx(10.0)
    assert kf.mahalanobis_sq(outside, R) > kf.gate_chi2
    diag_pt = (100.0 + 3.0 * 2.0, 50.0 + 4.0 * 2.0)  # 2 σ along both axes: d² = 4 + 4
    assert kf.mahalanobis_sq(diag_pt, R) == pytest.approx(8.0)
    assert kf.mahalanobis_sq(diag_pt, R) <= kf.gate_chi2
    assert kf.mahalanobis_sq((100.0, 50.0 + math.sqrt(10.0 * 16.0)), R) > kf.gate_chi2


def test_gate_ellipse_axes() -> None:
    cx, cy, a, b, ang = gate_ellipse_from_cov((10.0, 20.0), np.diag([16.0, 4.0]), 9.488)
    assert (cx, cy) == (10.0, 20.0)
    assert a == pytest.approx(math.sqrt(9.488 * 16.0))
    assert b == pytest.approx(math.sqrt(9.488 * 4.0))
    assert ang == pytest.approx(0.0, abs=1e-9)
    _, _, a, b, ang = gate_ellipse_from_cov((0.0, 0.0), np.diag([4.0, 16.0]), 9.488)
    assert (a, b) == pytest.approx((math.sqrt(9.488 * 16.0), math.sqrt(9.488 * 4.0)))
    assert ang == pytest.approx(90.0)
    th = math.radians(30.0)
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    _, _, a, b, ang = gate_ellipse_from_cov((0.0, 0.0), rot @ np.diag([16.0, 4.0]) @ rot.T, 9.488)
    assert ang == pytest.approx(30.0)
    assert a == pytest.approx(math.sqrt(9.488 * 16.0))


def test_predictor_suspends_without_accepted_match() -> None:
    params = KalmanParams()
    pred = Predictor(params)
    assert pred.predict(0) is None
    init = measurement(0, TrackState.TRACKING, Candidate((90.0, 40.0, 20.0, 40.0), "init"), accepted=True,
                       init_box=(90.0, 40.0, 20.0, 40.0))
    pred.apply(init)
    prior = pred.predict(33_000_000, (1.0, 0.0))
    assert prior is not None
    assert prior.centre == pytest.approx((100.0, 60.0))
    # The gate covariance carries Eq. 7's R_k for the given ego speed.
    expected_S = prior.covariance[:2, :2] + (params.r0_px2 + params.kappa_px2_per_mps2) * np.eye(2)
    np.testing.assert_allclose(prior.innovation_cov, expected_S)
    assert prior.box == pytest.approx((90.0, 40.0, 20.0, 40.0))

    rejected = measurement(33_000_000, TrackState.OCCLUDED, Candidate((130.0, 40.0, 20.0, 40.0), "detection"))
    post = pred.apply(rejected)
    assert post is not None and not post.measured
    np.testing.assert_array_equal(pred.kf.x, prior.state)  # Alg. 1 line 17: no update

    accepted = measurement(66_000_000, TrackState.TRACKING, Candidate((94.0, 40.0, 20.0, 40.0), "detection"),
                           accepted=True)
    pred.predict(66_000_000)
    post = pred.apply(accepted)
    assert post is not None and post.measured
    assert 100.0 < pred.kf.x[0] < 104.0
    assert pred.kf.x[2] > 0.0


def test_predictor_without_suspension_updates_on_best_candidate() -> None:
    pred = Predictor(KalmanParams(suspend_updates=False))
    pred.apply(measurement(0, TrackState.TRACKING, Candidate((90.0, 40.0, 20.0, 40.0), "init"), accepted=True,
                           init_box=(90.0, 40.0, 20.0, 40.0)))
    pred.predict(33_000_000)
    post = pred.apply(measurement(33_000_000, TrackState.OCCLUDED, Candidate((130.0, 40.0, 20.0, 40.0), "detection")))
    assert post is not None and post.measured
    assert pred.kf.x[0] > 110.0


def test_predictor_uses_stamp_gaps_and_learns_size_only_from_detections() -> None:
    params = KalmanParams()
    pred = Predictor(params)
    box = (90.0, 40.0, 20.0, 40.0)
    pred.apply(measurement(0, TrackState.TRACKING, Candidate(box, "init"), accepted=True, init_box=box))
    prior = pred.predict(500_000_000)  # a 0.5 s gap (dropped frames), not dt_ms
    assert prior is not None
    dt = 0.5
    expected = params.r0_px2 + params.init_velocity_std_px_s**2 * dt**2 + params.accel_std_px_s2**2 * dt**4 / 4
    assert prior.covariance[0, 0] == pytest.approx(expected)

    blob = (92.0, 40.0, 6.0, 40.0)  # a motion blob: a sliver of the target
    pred.apply(measurement(500_000_000, TrackState.TRACKING, Candidate(blob, "motion"), accepted=True))
    assert pred.kf.size == (20.0, 40.0)
    assert pred.kf.x[0] < 100.0  # the centre was still measured
    pred.predict(533_000_000)
    det = (90.0, 40.0, 30.0, 40.0)
    pred.apply(measurement(533_000_000, TrackState.TRACKING, Candidate(det, "detection"), accepted=True))
    a = params.size_smoothing
    assert pred.kf.size == pytest.approx(((1 - a) * 20.0 + a * 30.0, 40.0))


@pytest.mark.parametrize("after_ms", [500.0, 0.0])
def test_a_relock_after_a_long_coast_takes_the_velocity_its_measurements_show(after_ms: float) -> None:
    """A person walking right at 300 px/s is lost for a second, in which they stop: the velocity the filter carried
    through the coast is a second old. The re-lock's velocity is the displacement between the two measurements
    over the gap (10 px in 1 s), not the old velocity barely corrected, which would carry the next coast away;
    after one missed frame the filter's own velocity stands (there the displacement is mostly detector jitter)."""
    pred = Predictor(KalmanParams(relock_velocity_after_coast_ms=after_ms))
    box = (90.0, 40.0, 20.0, 40.0)  # centre (100, 60)
    pred.apply(measurement(0, TrackState.TRACKING, Candidate(box, "init"), accepted=True, init_box=box))
    t_ns = 0
    for k in range(1, 11):
        t_ns = k * 33_000_000
        pred.predict(t_ns)
        moved = (90.0 + 10.0 * k, 40.0, 20.0, 40.0)
        pred.apply(measurement(t_ns, TrackState.TRACKING, Candidate(moved, "detection"), accepted=True))
    assert pred.kf.x[2] > 200.0  # walking right
    velocity_before = float(pred.kf.x[2])
    t_ns += 66_000_000  # one frame missed
    last = (90.0 + 10.0 * 12, 40.0, 20.0, 40.0)
    pred.predict(t_ns)
    pred.apply(measurement(t_ns, TrackState.TRACKING, Candidate(last, "detection"), accepted=True))
    assert pred.kf.x[2] == pytest.approx(velocity_before, rel=0.1)
    relock_ns = t_ns + 1_000_000_000  # a second unseen, in which they walked 10 px and stopped
    pred.predict(relock_ns)
    relocked = (last[0] + 10.0, *last[1:])
    pred.apply(measurement(relock_ns, TrackState.REACQUIRED, Candidate(relocked, "detection"), accepted=True))
    if after_ms > 0.0:
        for kf in pred.filters.values():
            assert kf.x[2] == pytest.approx(10.0) and kf.x[3] == pytest.approx(0.0)
    else:
        assert abs(pred.kf.x[2] - 10.0) > 50.0
