"""Issue 34's mechanisms one by one: seed 002 §3.2's local re-detection (tracking/redetection.py, the redetection
node), the prediction's image motion model (an IMM beside the camera-compensated one), the phase-correlation fallback
of a smeared frame, merged views in width, geometry deciding colour ties, the uncontested lone box, and the
missed-re-acquisition count of the evaluation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.evaluation.metrics import evaluate_single_target, missed_reacquisition_frames
from followbus.msgs.perception import CameraMotion
from followbus.msgs.tracking import Measurement, Prior, TrackState
from followbus.tracking.egomotion import EgoMotionEstimator, EgoMotionParams
from followbus.tracking.kalman import IMAGE, SCENE, Predictor, output_box
from followbus.tracking.params import KalmanParams, ReidParams, SearchScaleParams
from followbus.tracking.redetection import (
    MIN_INPUT_PX,
    finer_than_the_frame,
    input_side_px,
    merge_region_boxes,
    reason_to_redetect,
    region_cap_px,
    region_of,
    search_scale,
)
from followbus.tracking.reid import ReIdentifier, trim_merged_view
from followbus.vision.scenes import motion_smear

from .test_tracking_egomotion import similarity, textured, warp

MS = 1_000_000


def prior_at(box: tuple[float, float, float, float], std_px: float = 5.0, v: tuple[float, float] = (0.0, 0.0)) -> Prior:
    x, y, w, h = box
    cov = np.diag([std_px**2, std_px**2, 100.0, 100.0])
    return Prior.of_filter(0, np.array([x + w / 2, y + h / 2, *v]), (w, h), cov, cov[:2, :2] + 64 * np.eye(2), 9.488)


# --------------------------------------------------------------------------- seed 002 §3.2: the region


def test_search_scale_is_the_seeds_k_from_speed_and_last_score() -> None:
    p = SearchScaleParams()
    slow = prior_at((100, 100, 40, 100))
    assert search_scale(slow, 0.9, 33.0, p) == 1.0  # slow, confident: k = 1
    assert search_scale(slow, 0.3, 33.0, p) == pytest.approx(1.5)  # weak last detection: k max
    fast = prior_at((100, 100, 40, 100), v=(200.0, 0.0))  # 6.6 px a frame on a 100 px person: fast
    assert search_scale(fast, 0.9, 33.0, p) == pytest.approx(1.5)
    assert search_scale(fast, 0.9, 33.0, SearchScaleParams(adaptive_gate=False)) == 1.0


def test_the_region_is_the_seeds_square_widened_to_the_gate_kept_in_the_frame_and_budgeted() -> None:
    # 1280x720 at 416: 416 x 234 px; 60 % of them is 240 px square at most (a multiple of 32: 224).
    cap = region_cap_px((1280, 720), 416, 0.6)
    assert cap == 224
    tight = prior_at((600, 300, 40, 100), std_px=1.0)
    x0, y0, x1, y1 = region_of(tight, 1.0, (1280, 720), cap)
    assert x1 - x0 == y1 - y0 and x1 - x0 >= 100  # S = k · max(w, h) at least
    assert x0 < 620 < x1 and y0 < 350 < y1  # around the prediction
    corner = region_of(prior_at((0, 0, 40, 100), std_px=1.0), 1.0, (1280, 720), cap)
    assert corner[0] == 0 and corner[1] == 0  # moved inside the frame
    loose = region_of(prior_at((600, 300, 40, 100), std_px=300.0), 1.5, (1280, 720), cap)
    assert loose[2] - loose[0] == cap  # widened towards the gate only as far as the budget
    assert input_side_px((0, 0, 40, 40), cap) == MIN_INPUT_PX and input_side_px((0, 0, 130, 100), cap) == 160
    assert input_side_px((0, 0, 500, 500), cap) == cap  # a large region is scaled down to the budget
    frame_scale = 416 / 1280
    assert finer_than_the_frame((0, 0, 150, 150), input_side_px((0, 0, 150, 150), cap), frame_scale)
    big = region_of(prior_at((400, 100, 200, 500), std_px=5.0), 1.5, (1280, 720), cap)  # a person near the camera
    assert not finer_than_the_frame(big, input_side_px(big, cap), frame_scale)  # no finer than the frame pass


def test_when_the_region_is_redetected() -> None:
    prior = prior_at((600, 300, 40, 100), std_px=10.0)
    on_target = np.array([[600, 300, 40, 100, 0.9]], np.float32)
    elsewhere = np.array([[100, 100, 40, 100, 0.9]], np.float32)
    twins = np.array([[600, 300, 40, 100, 0.9], [605, 302, 40, 100, 0.8]], np.float32)
    assert reason_to_redetect(prior, on_target, 1.0, False, 1.0, 48.0) == ""  # seen, big enough: no second look
    assert reason_to_redetect(prior, on_target, 1.0, True, 1.0, 48.0) == "occluded"
    assert reason_to_redetect(prior, on_target, 1.0, False, 0.325, 48.0) == "small"  # 100 px at 416/1280: 32
    assert reason_to_redetect(prior, elsewhere, 1.0, False, 1.0, 48.0) == "missed"
    assert reason_to_redetect(prior, twins, 1.0, False, 1.0, 48.0) == "crowded"
    assert reason_to_redetect(Prior(), on_target, 1.0, True, 1.0, 48.0) == ""  # no prior: nowhere to look


def test_region_boxes_replace_what_the_region_saw_again_and_nothing_else() -> None:
    rect, frame_wh = (500, 200, 800, 500), (1280, 720)
    merged = [600, 300, 90, 100, 0.8]  # two people boxed together by the coarse pass
    outside = [100, 100, 40, 100, 0.9]  # not in the region
    unseen = [520, 250, 40, 100, 0.6]  # in the region, but the region pass did not find it
    region = [[600, 300, 40, 100, 0.9], [650, 300, 40, 100, 0.85],  # the two, told apart
              [790, 300, 10, 100, 0.7]]  # cut by the region's right edge: dropped
    rows, from_region = merge_region_boxes(np.array([merged, outside, unseen], np.float32),
                                           np.array(region, np.float32), rect, frame_wh)
    kept = {tuple(r[:4]) for r, f in zip(rows, from_region, strict=True) if not f}
    added = {tuple(r[:4]) for r, f in zip(rows, from_region, strict=True) if f}
    assert kept == {(100, 100, 40, 100), (520, 250, 40, 100)}
    assert added == {(600, 300, 40, 100), (650, 300, 40, 100)}


def test_the_graph_redetects_small_people_at_the_frames_resolution() -> None:
    """scene:runners (look-alikes a coarse detector boxes together): the redetection node looks again at the region
    around the target, and re-ID takes its boxes."""
    from followbus.evaluation.graph_follower import GraphFollower
    from followbus.evaluation.runner import make_eval_detector, open_sequence
    from followbus.vision.detectors import split_by_score

    seq = open_sequence("scene:runners")
    detector = make_eval_detector("graph", 0, 0.1)
    follower = GraphFollower(details=True)
    sources = []
    try:
        for k, item in enumerate(seq.frames()):
            high, low = split_by_score(detector.detect(item.bgr), 0.3, 0.1)
            follower.step(item.bgr, high, item.t_ns, (0.0, 0.0), item.gt_box if k == 0 else None, low_detections=low)
            sources.append(follower.last.measurement.source)
        status = follower.node("redetection").status()
    finally:
        follower.close()
    assert sum(status["redetected"].values()) >= 100 and status["redetected"].get("small", 0) > 0
    assert sources.count("redetection") >= 100  # what re-ID took was mostly the region's finer view


# --------------------------------------------------------------------------- the image motion model (IMM)


def _motion(dx: float, t_from: int, t: int) -> CameraMotion:
    m = CameraMotion(valid=True, matrix=np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0]]), inliers=50, tracked=60,
                     from_stamp_ns=t_from)
    m.header.stamp_ns = t
    return m


def _follow(person_moves_with_camera: bool) -> Predictor:
    """A camera panning by 0-30 px a frame, speeding up and slowing down, for 20 frames; the person either stays
    put in the image (the camera follows them) or in the scene (the camera pans past them). (At a steady pan
    the scene model's velocity cancels the warp and the two models predict alike.)"""
    pred = Predictor(KalmanParams())
    box = (300.0, 200.0, 40.0, 100.0)
    pred.apply(Measurement(state="TRACKING", accepted=True, box=np.array(box), source="init", init_box=np.array(box)))
    x = 300.0
    pans = [0.0, 30.0, 5.0, 25.0, 0.0, 20.0, 10.0, 30.0, 0.0, 15.0] * 2
    for k, pan in enumerate(pans, start=1):
        t = k * 33 * MS
        pred.predict(t, camera_motion=_motion(pan, (k - 1) * 33 * MS, t))
        x = x if person_moves_with_camera else x + pan
        z = Measurement(state="TRACKING", accepted=True, box=np.array([x, 200.0, 40.0, 100.0]), source="detection")
        z.header.stamp_ns = t
        pred.apply(z)
    return pred


def test_the_image_model_wins_when_the_camera_follows_the_person_and_the_scene_model_when_it_does_not() -> None:
    assert _follow(person_moves_with_camera=True).image_model_probability > 0.9
    assert _follow(person_moves_with_camera=False).image_model_probability < 0.1
    assert Predictor(KalmanParams(image_motion_model=False)).models == (SCENE,)
    assert Predictor(KalmanParams(camera_motion_compensation=False)).models == (IMAGE,)


def test_the_coasting_output_is_the_likeliest_models_box() -> None:
    pred = _follow(person_moves_with_camera=True)
    prior = pred.predict(21 * 33 * MS, camera_motion=_motion(40.0, 20 * 33 * MS, 21 * 33 * MS))
    assert prior.likeliest_box is not None and prior.likeliest_box[0] == pytest.approx(300.0, abs=3.0)
    assert prior.box[0] > prior.likeliest_box[0]  # the mixture leans towards the warped scene model


def test_before_any_measurement_the_coasting_output_stays_where_the_person_was_seen() -> None:
    """The models tie until a measurement weighs them: the output is the image model's, not the warped one's."""
    pred = Predictor(KalmanParams())
    box = (300.0, 200.0, 40.0, 100.0)
    pred.apply(Measurement(state="TRACKING", accepted=True, box=np.array(box), source="init", init_box=np.array(box)))
    for k in range(1, 6):
        prior = pred.predict(k * 33 * MS, camera_motion=_motion(-6.0, (k - 1) * 33 * MS, k * 33 * MS))
    # The image model only takes in the 5 % a frame the models mix (model_switch_probability).
    assert prior.likeliest_box is not None and prior.likeliest_box[0] == pytest.approx(300.0, abs=3.0)
    assert pred.filters[SCENE].box[0] < 275.0  # the scene model was warped by the 30 px all along


def _coast_still(pred: Predictor, first_k: int, frames: int) -> None:
    """``frames`` frames with no measurement and a still camera."""
    for k in range(first_k, first_k + frames):
        t = k * 33 * MS
        pred.predict(t, camera_motion=_motion(0.0, (k - 1) * 33 * MS, t))
        miss = Measurement(state="OCCLUDED", accepted=False, source="")
        miss.header.stamp_ns = t
        pred.apply(miss)


@pytest.mark.parametrize("mix", [False, True])
def test_a_coast_keeps_each_models_velocity_unless_mixed(mix: bool) -> None:
    """The two models disagree on the person's velocity (the camera followed them: still in the image, 300 px/s
    against the scene). A 1 s coast with no measurement says nothing of which is right: unmixed, the image model
    keeps its own velocity; the textbook IMM mixes the scene model's into it frame by frame."""
    pred = _follow(person_moves_with_camera=True)
    pred.params.mix_models_while_coasting = mix
    pred.filters[SCENE].x[2:] = (-300.0, 0.0)
    before = pred.filters[IMAGE].x[2:].copy()
    _coast_still(pred, 21, 30)
    drift = float(np.linalg.norm(pred.filters[IMAGE].x[2:] - before))
    assert (drift > 5.0) if mix else (drift < 1.0)  # mixed: 8 px/s, and growing as the models even out


# --------------------------------------------------------------------------- a smeared frame: phase correlation


def _smeared_step(params: EgoMotionParams) -> tuple[EgoMotionEstimator, CameraMotion | None]:
    """A 40 px move right whose frame is smeared over 60 px along it."""
    sharp = textured(7)
    moved = motion_smear(warp(sharp, similarity(0.0, 1.0, 40.0, 0.0)), (1.0, 0.0), 60.0)
    est = EgoMotionEstimator(params)
    est.step(sharp, None, 0)
    return est, est.step(moved, None, 33 * MS)


def test_a_smeared_frame_is_fitted_again_as_smeared() -> None:
    est, motion = _smeared_step(EgoMotionParams())
    assert motion is not None and motion.reason == "" and est.counts["smeared"] == 1
    assert abs(motion.matrix[0, 2] - 40.0) < 4.0 and abs(motion.matrix[1, 2]) < 4.0
    est, motion = _smeared_step(EgoMotionParams(smeared_refit=False, phase_fallback=False))
    assert motion is None and est.last_reason in ("no_fit", "few_inliers", "few_tracked")  # the sharp settings fail


def test_a_smeared_frame_the_refit_misses_still_gives_the_cameras_translation() -> None:
    est, motion = _smeared_step(EgoMotionParams(smeared_lk_window_px=5))  # a window too small for the smear
    assert motion is not None and motion.reason == "phase" and motion.std_px >= 6.0
    assert 10.0 < motion.matrix[0, 2] < 60.0 and abs(motion.matrix[1, 2]) < 5.0  # the smear's centre, rightwards


def test_the_smeared_frame_refit_measures_the_jerks_the_sharp_fit_cannot() -> None:
    """`followbus bench egomotion`'s engine on scene:shaky: five re-aims of three smeared frames each."""
    from followbus.evaluation.camera_motion import score_scene

    refit = score_scene("shaky", EgoMotionParams())
    sharp = score_scene("shaky", EgoMotionParams(smeared_refit=False))
    assert refit.smeared == sharp.smeared == 15
    assert refit.smeared_measured >= 14 > sharp.smeared_measured, (refit.row(), sharp.row())
    assert np.percentile(refit.errors_px, 95) < 4.0  # and the sharp frames stay as precise


def test_a_jerk_loses_the_person_only_on_its_smeared_frames() -> None:
    """scene:shaky (hand-held re-aims by 200 px over 3 smeared frames, simulated detections: the person stays
    detectable): the graph takes the person again within two frames of each jerk's end."""
    from followbus.vision.scenes import SHAKE_FRAMES, SHAKES

    from .test_tracking_camera_doubt import errors

    err = errors("shaky", 300)
    fps = 30.0
    for t_s, _, _ in SHAKES:
        end = int(math.ceil(t_s * fps)) + SHAKE_FRAMES
        assert all(e < 20.0 for e in err[end + 2:end + 12]), (t_s, [round(e) for e in err[end - 4:end + 12]])


# --------------------------------------------------------------------------- look-alikes and lone boxes


def test_a_box_merging_the_target_with_a_neighbour_beside_it_is_trimmed_in_width() -> None:
    predicted = (300.0, 100.0, 40.0, 100.0)
    assert trim_merged_view((300.0, 100.0, 85.0, 100.0), predicted) == (300.0, 100.0, 40.0, 100.0)  # left agrees
    assert trim_merged_view((255.0, 100.0, 85.0, 100.0), predicted) == (300.0, 100.0, 40.0, 100.0)  # right agrees
    assert trim_merged_view((290.0, 100.0, 55.0, 100.0), predicted) == (290.0, 100.0, 55.0, 100.0)  # a stride


def _frame(*boxes: tuple[tuple[float, float, float, float], tuple[int, int, int]]) -> np.ndarray:
    img = np.full((480, 640, 3), 90, np.uint8)
    for (x, y, w, h), bgr in boxes:
        img[int(y):int(y + h), int(x):int(x + w)] = bgr
    return img


def test_geometry_decides_between_candidates_whose_colours_tie() -> None:
    """The target and a look-alike just beside it, both red: colour ties, the one where the target is predicted wins,
    also when the other matches the colours a little better."""
    target, twin = (300.0, 100.0, 40.0, 100.0), (345.0, 110.0, 40.0, 100.0)
    start = _frame((target, (0, 0, 200)))
    for ties in (True, False):
        reid = ReIdentifier(ReidParams(learned_appearance=False, colour_ties_to_geometry=ties))
        template = reid.step(start, np.array([[*target, 0.9]], np.float32), None, None, 0,
                             init_box=target).candidate_hist
        frame = _frame((target, (0, 0, 200)), (twin, (0, 0, 200)))
        frame[int(target[1]):int(target[1] + 6), int(target[0]):int(target[0] + 40)] = (0, 200, 200)  # a cap
        dets = np.array([[*twin, 0.9], [*target, 0.9]], np.float32)
        res = reid.step(frame, dets, prior_at(target, std_px=25.0), template, 33 * MS)
        chosen = res.box if res.accepted else res.best_box
        assert (tuple(chosen) == target) == ties


def test_a_lone_uncontested_box_where_the_target_is_predicted_is_taken_whatever_its_colours() -> None:
    target = (300.0, 100.0, 40.0, 100.0)
    for uncontested in (True, False):
        reid = ReIdentifier(ReidParams(learned_appearance=False, uncontested_lone_candidate=uncontested))
        template = reid.step(_frame((target, (0, 0, 200))), np.array([[*target, 0.9]], np.float32), None, None, 0,
                             init_box=target).candidate_hist
        turned = (312.0, 102.0, 40.0, 100.0)  # the person turned: other colours, where they were predicted
        frame = _frame((turned, (200, 120, 0)))
        frame[102:142, 312:352] = (0, 0, 200)  # only the top 40 % as red as the template: M_fuse under T_reid
        res = reid.step(frame, np.array([[*turned, 0.9]], np.float32), prior_at(target), template, 33 * MS)
        assert res.accepted == uncontested
        assert reid.state is (TrackState.TRACKING if uncontested else TrackState.OCCLUDED)


def test_a_lone_box_just_past_the_predicted_box_is_uncontested_within_the_priors_doubt() -> None:
    """A small person moving fast, seen first without a velocity: on the next frame their box is centred past the
    predicted box, within one standard deviation of the prior's centre."""
    target = (300.0, 100.0, 30.0, 26.0)
    for within_std in (True, False):
        reid = ReIdentifier(ReidParams(learned_appearance=False, uncontested_within_prior_std=within_std))
        template = reid.step(_frame((target, (0, 0, 200))), np.array([[*target, 0.9]], np.float32), None, None, 0,
                             init_box=target).candidate_hist
        moved = (300.0, 84.0, 30.0, 26.0)  # 16 px up: past the predicted box's half height (13), within 13 + 10
        frame = _frame((moved, (200, 120, 0)))
        frame[84:94, 300:330] = (0, 0, 200)  # a little of the template's red: M_fuse under T_reid
        res = reid.step(frame, np.array([[*moved, 0.9]], np.float32), prior_at(target, std_px=10.0), template, 33 * MS)
        assert res.accepted == within_std, res.m_fuse
        # Farther than the doubt too: never taken this way.
        far = (300.0, 70.0, 30.0, 26.0)  # 30 px up: past 13 + 10
        frame = _frame((far, (200, 120, 0)))
        frame[70:80, 300:330] = (0, 0, 200)
        res = reid.step(frame, np.array([[*far, 0.9]], np.float32), prior_at(target, std_px=10.0), template, 66 * MS)
        assert not res.accepted


# --------------------------------------------------------------------------- missed re-acquisitions


def test_missed_reacquisitions_count_frames_without_output_while_the_best_candidate_was_the_target() -> None:
    gt = [(100.0, 100.0, 40.0, 100.0)] * 4
    out = [gt[0], None, None, None]
    best = [gt[0], (102.0, 101.0, 40.0, 100.0), (400.0, 100.0, 40.0, 100.0), None]  # on it, someone else, nobody
    assert missed_reacquisition_frames(out, gt, best) == 1
    m = evaluate_single_target(out, gt, best_candidates=best)
    assert m.missed_reacquisitions == 1 and m.missing_outputs == 3
    assert evaluate_single_target(out, gt).missed_reacquisitions is None  # a method that reports no candidates
    with pytest.raises(ValueError):
        missed_reacquisition_frames(out, gt, best[:2])


# --------------------------------------------------------------------------- the coasting box's colours


TARGET = (300.0, 100.0, 40.0, 100.0)


def _coast(frame: np.ndarray, prior_box: tuple[float, float, float, float], dets: np.ndarray | None = None,
           check: bool = True) -> Measurement:
    """Re-ID initialised on a red person at TARGET, then a frame where the detector sees nobody in the gate."""
    reid = ReIdentifier(ReidParams(learned_appearance=False, coasting_colour_check=check))
    template = reid.step(_frame((TARGET, (0, 0, 200))), np.array([[*TARGET, 0.9]], np.float32), None, None, 0,
                         init_box=TARGET).candidate_hist
    return reid.step(frame, dets, prior_at(prior_box), template, 33 * MS)


def test_the_coasting_box_is_held_where_the_targets_colours_are() -> None:
    still = _frame((TARGET, (0, 0, 200)))  # the person stands where they were, unseen by the detector
    res = _coast(still, TARGET)
    assert res.state == "OCCLUDED" and not res.accepted and res.coasting_colours_seen
    assert not _coast(still, (420.0, 100.0, 40.0, 100.0)).coasting_colours_seen  # the prediction left them
    with_someone = _frame((TARGET, (0, 0, 200)), ((340.0, 100.0, 40.0, 100.0), (200, 0, 0)))
    assert _coast(with_someone, TARGET).coasting_colours_seen
    beside = np.array([[335.0, 100.0, 40.0, 100.0, 0.9]], np.float32)  # their box over its edge, out of the gate
    assert not _coast(with_someone, TARGET, beside).coasting_colours_seen  # no one else's box may be on it
    assert not _coast(still, TARGET, check=False).coasting_colours_seen
    everywhere = np.full((480, 640, 3), (0, 0, 200), np.uint8)  # the target's colours all around: no evidence
    assert not _coast(everywhere, TARGET).coasting_colours_seen


def test_the_colours_seen_keep_the_coasting_box_however_uncertain_the_prior() -> None:
    prior, reid = prior_at(TARGET), Measurement(state="OCCLUDED")
    for seen, locates, shown in ((True, False, True), (False, True, True), (False, False, False)):
        reid.coasting_colours_seen, prior.locates_person = seen, locates
        assert (output_box(reid, prior) is not None) == shown, (seen, locates)
    reid.state, reid.coasting_colours_seen = "LOST", True
    assert output_box(reid, prior) is None
