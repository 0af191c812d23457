"""Re-identification of seed 000: Eq. 2-3, S_geo, Algorithm 1 and the track state machine."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.msgs.box import box_tuple
from followbus.msgs.tracking import Prior
from followbus.tracking.appearance import hs_histogram
from followbus.tracking.params import InvalidParam, KalmanParams, ReidParams
from followbus.tracking.reid import (
    Candidate,
    ReIdentifier,
    TrackState,
    appearance_weight,
    complete_partial_view,
    fuse,
    geometric_score,
    measurement,
    trim_merged_view,
)

W, H = 320, 240
BG = (40, 90, 40)
RED = (30, 30, 220)
BLUE = (220, 60, 30)
TARGET = (100.0, 100.0, 30.0, 60.0)  # centre (115, 130)
MS = 1_000_000


def draw(*boxes_colours: tuple[tuple[float, float, float, float], tuple[int, int, int]],
         bg: tuple[int, int, int] = BG) -> np.ndarray:
    img = np.full((H, W, 3), bg, np.uint8)
    for (x, y, w, h), colour in boxes_colours:
        img[int(y):int(y + h), int(x):int(x + w)] = colour
    return img


def dets(*boxes: tuple[float, float, float, float]) -> np.ndarray:
    return np.array([(*b, 0.9) for b in boxes], np.float32).reshape(-1, 5)


def prior_at(box: tuple[float, float, float, float], t_ns: int, var_px2: float = 400.0) -> Prior:
    """A prior centred on ``box`` with S = var·I: gate radius sqrt(9.488·400) ≈ 61.6 px."""
    cx, cy = box[0] + box[2] / 2.0, box[1] + box[3] / 2.0
    return Prior.of_filter(t_ns=t_ns, state=np.array([cx, cy, 0.0, 0.0]), size=(box[2], box[3]),
                 covariance=np.diag([var_px2, var_px2, 1.0, 1.0]), innovation_cov=var_px2 * np.eye(2),
                 gate_chi2=9.488)


def started(params: ReidParams) -> tuple[ReIdentifier, np.ndarray]:
    reid = ReIdentifier(params)
    frame = draw((TARGET, RED))
    res = reid.step(frame, dets(TARGET), None, None, 0, init_box=TARGET)
    assert res.state == TrackState.TRACKING and box_tuple(res.init_box) == TARGET
    return reid, hs_histogram(frame, TARGET, params.bins_h, params.bins_s)


def test_appearance_weight_eq3() -> None:
    assert appearance_weight(0.6, 0.6, 10.0) == 0.5
    assert appearance_weight(0.35, 0.35, 3.0) == 0.5
    ws = [appearance_weight(c, 0.6, 10.0) for c in np.linspace(0.0, 1.0, 21)]
    assert all(a < b for a, b in zip(ws, ws[1:], strict=False))
    assert appearance_weight(0.9, 0.6, 10.0) == pytest.approx(1.0 / (1.0 + math.exp(-3.0)))
    assert appearance_weight(0.0, 0.6, 10.0) == pytest.approx(1.0 / (1.0 + math.exp(6.0)))
    assert appearance_weight(-1e6, 0.6, 10.0) == 0.0  # no overflow far below τ_occ


def test_fuse_eq2() -> None:
    assert fuse(0.9, 0.5, 0.8) == pytest.approx(0.8 * 0.9 + 0.2 * 0.5)
    assert fuse(0.9, 0.5, 1.0) == 0.9
    assert fuse(0.9, 0.5, 0.0) == 0.5


def test_geometric_score_formula() -> None:
    pred = (100.0, 100.0, 30.0, 40.0)  # diagonal 50 px
    assert geometric_score(pred, pred, 0.0, 9.488) == 1.0
    assert geometric_score(pred, pred, 9.488, 9.488) == 0.0  # on the gate boundary
    cand = (110.0, 100.0, 30.0, 40.0)  # 10 px right, same size
    expected = (1.0 - 2.0 / 9.488) * math.exp(-((10.0 / 25.0) ** 2))
    assert geometric_score(cand, pred, 2.0, 9.488, geo_scale=0.5) == pytest.approx(expected)
    half = (100.0, 110.0, 30.0, 20.0)  # same centre, half height
    assert geometric_score(half, pred, 0.0, 9.488) == pytest.approx(math.sqrt(0.5))
    assert geometric_score((100.0, 100.0, 0.0, 40.0), pred, 0.0, 9.488) == 0.0


def test_accepts_target_and_rejects_distractor() -> None:
    params = ReidParams()
    reid, template = started(params)
    distractor = (140.0, 100.0, 30.0, 60.0)  # 40 px right of the prediction: inside the gate
    frame = draw((TARGET, RED), (distractor, BLUE))
    res = reid.step(frame, dets(distractor, TARGET), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.accepted and res.state == TrackState.TRACKING
    assert box_tuple(res.box) == TARGET
    assert res.secure
    assert len(reid.candidates) == 2
    by_box = {c.box: c for c in reid.candidates}
    assert by_box[TARGET].s_color == pytest.approx(1.0, abs=1e-6)
    assert by_box[distractor].s_color < 0.1
    assert by_box[distractor].m_fuse < params.reid_threshold < by_box[TARGET].m_fuse
    assert res.c_t == pytest.approx(1.0, abs=1e-6)  # C_t = best S_color
    assert res.omega == pytest.approx(appearance_weight(1.0, 0.6, 10.0), abs=1e-6)
    assert res.candidates.shape == (2, 5) and res.candidate_sources == ["detection", "detection"]
    assert {tuple(row[:4]): row[4] for row in res.candidates} == {c.box: c.m_fuse for c in reid.candidates}
    assert res.candidate_hist is not None and res.candidate_hist.shape == (16, 8)


def test_distractor_alone_is_rejected_and_state_goes_occluded_then_lost_then_reacquired() -> None:
    params = ReidParams(lost_after_ms=100.0, reacquired_hold_frames=2)
    reid, template = started(params)
    distractor = (140.0, 100.0, 30.0, 60.0)
    states, ms = [], [33, 66, 99, 132, 165]
    for t in ms:
        frame = draw((distractor, BLUE))
        res = reid.step(frame, dets(distractor), prior_at(TARGET, t * MS), template, t * MS)
        assert not res.accepted and res.box is None and not res.secure
        assert box_tuple(res.best_box) == distractor and res.m_fuse < params.reid_threshold
        states.append(res.state)
    # Occluded for 33..99 ms since the last accepted frame (t = 0); > 100 ms → LOST.
    assert states == [TrackState.OCCLUDED] * 3 + [TrackState.LOST] * 2

    results = []
    for t in (198, 231, 264):
        frame = draw((TARGET, RED), (distractor, BLUE))
        results.append(reid.step(frame, dets(TARGET, distractor), prior_at(TARGET, t * MS), template, t * MS))
    assert [r.state for r in results] == [TrackState.REACQUIRED, TrackState.REACQUIRED, TrackState.TRACKING]
    assert all(r.accepted and box_tuple(r.box) == TARGET for r in results)
    assert [r.secure for r in results] == [False, False, True]  # template frozen until re-lock confirmed


def test_empty_frame_suspends() -> None:
    params = ReidParams()
    reid, template = started(params)
    res = reid.step(draw(), dets(), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.state == TrackState.OCCLUDED
    assert not res.accepted and reid.candidates == [] and len(res.candidates) == 0 and res.c_t == 0.0
    assert res.best_box is None


def test_geometry_decides_when_appearance_is_unreliable() -> None:
    # Eq. 3: with C_t far below τ_occ, ω → 0 and a box matching the predicted position and
    # size is accepted on geometry alone (the paper's behaviour under degraded appearance).
    params = ReidParams()
    reid, template = started(params)
    frame = draw((TARGET, (90, 90, 90)))  # same place, colour washed out
    res = reid.step(frame, dets(TARGET), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.omega < 0.01
    assert res.s_geo == pytest.approx(1.0)
    assert res.accepted
    # Without the geometric cue (ablation) ω = 1 and the washed-out box is rejected (by Eq. 2-3: the uncontested
    # lone box, which would take it, is off here).
    reid2, template2 = started(ReidParams(use_geometry=False, uncontested_lone_candidate=False))
    res2 = reid2.step(frame, dets(TARGET), prior_at(TARGET, 33 * MS), template2, 33 * MS)
    assert res2.omega == 1.0 and res2.s_geo == 0.0 and not res2.accepted


def test_motion_blob_candidates_when_no_detection_in_gate() -> None:
    params = ReidParams()
    reid = ReIdentifier(params)
    black = (0, 0, 0)
    f0 = draw((TARGET, RED), bg=black)
    reid.step(f0, dets(TARGET), None, None, 0, init_box=TARGET)
    template = hs_histogram(f0, TARGET)
    moved = (110.0, 100.0, 30.0, 60.0)
    f1 = draw((moved, RED), bg=black)
    far = (5.0, 5.0, 30.0, 60.0)  # a detection outside the gate does not count
    res = reid.step(f1, dets(far), prior_at(moved, 33 * MS), template, 33 * MS)
    assert reid.candidates and all(c.source == "motion" for c in reid.candidates)
    assert res.accepted and res.source == "motion"
    assert not res.secure  # a motion blob is never a secure template source
    x, y, w, h = res.box
    assert x >= 128.0 and x + w <= 141.0 and y == 100.0 and h == 60.0  # the newly covered strip


@pytest.mark.parametrize("min_fraction", [0.25, 0.0])
def test_a_moving_part_of_the_person_is_no_motion_candidate(min_fraction: float) -> None:
    """Only a hand moves (a 12x12 px patch inside the 30x60 predicted box, 8 % of it): by default that fragment is no
    candidate, its centre could be anywhere in the person's box (the target stays OCCLUDED on its prior); with no
    minimum fraction it is one."""
    reid = ReIdentifier(ReidParams(motion_min_area_fraction=min_fraction))
    black = (0, 0, 0)
    f0 = draw((TARGET, RED), bg=black)
    reid.step(f0, dets(TARGET), None, None, 0, init_box=TARGET)
    template = hs_histogram(f0, TARGET)
    f1 = f0.copy()
    f1[100:112, 100:112] = (255, 255, 255)  # the hand raised at the top-left corner of the box
    reid.step(f1, dets(), prior_at(TARGET, 33 * MS), template, 33 * MS)
    if min_fraction > 0.0:
        assert reid.candidates == []
    else:
        assert reid.candidates and all(c.source == "motion" for c in reid.candidates)


@pytest.mark.parametrize("max_changed", [0.2, 1.0])
def test_no_motion_blob_candidates_while_the_camera_pans(max_changed: float) -> None:
    """Frame differencing on a panning camera marks the whole background as moving: with the default
    limit those blobs are not candidates (the target is held OCCLUDED on its prior); without it (1.0) a
    background blob gets accepted as the target."""
    params = ReidParams(motion_max_changed_fraction=max_changed)
    reid = ReIdentifier(params)
    blocks = np.random.default_rng(3).integers(0, 256, (H // 16, (W + 48) // 16, 3), dtype=np.uint8)
    texture = np.kron(blocks, np.ones((16, 16, 1), np.uint8))  # a cluttered background of 16-px patches
    f0 = texture[:, :W].copy()
    f0[100:160, 100:130] = RED
    reid.step(f0, dets(TARGET), None, None, 0, init_box=TARGET)
    template = hs_histogram(f0, TARGET)
    f1 = texture[:, 12:W + 12].copy()  # the camera pans 12 px; the target stays where it was in the image
    f1[100:160, 100:130] = RED
    res = reid.step(f1, dets(), prior_at(TARGET, 33 * MS), template, 33 * MS)
    if max_changed < 1.0:
        assert reid.candidates == [] and not res.accepted and res.state == TrackState.OCCLUDED
    else:
        assert reid.candidates and all(c.source == "motion" for c in reid.candidates)


def test_gate_excludes_far_detection_unless_disabled() -> None:
    far = (250.0, 20.0, 30.0, 60.0)  # ~170 px from the prediction, gate radius ~62 px
    frame = draw((far, RED))
    reid, template = started(ReidParams())
    res = reid.step(frame, dets(far), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert all(c.source == "motion" for c in reid.candidates)
    assert not res.accepted
    reid, template = started(ReidParams(use_gate=False))
    res = reid.step(frame, dets(far), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.accepted and box_tuple(res.box) == far
    assert reid.candidates[0].maha_sq > 9.488


def test_a_far_relock_between_look_alikes_nothing_tells_apart_waits() -> None:
    """Re-locking far from the prior onto one of two boxes with the target's colours, 45 px either side of it (S_geo
    alike), with no classifier to ask: colour alone would toss a coin, so the target stays occluded. One such box
    alone is taken."""
    left, right = (55.0, 100.0, 30.0, 60.0), (145.0, 100.0, 30.0, 60.0)  # 45 px from the prior, 30 px is far

    def relock(params: ReidParams, *boxes: tuple[float, float, float, float]) -> list:
        reid, template = started(params)
        assert reid.step(draw(), dets(), prior_at(TARGET, 33 * MS), template, 33 * MS).state == TrackState.OCCLUDED
        frame = draw(*((b, RED) for b in boxes))
        return [reid.step(frame, dets(*boxes), prior_at(TARGET, t * MS), template, t * MS) for t in (66, 99, 132)]

    params = ReidParams(learned_appearance=False)
    assert not any(r.accepted for r in relock(params, left, right))
    assert relock(params, right)[0].accepted
    taken = relock(ReidParams(learned_appearance=False, far_relock_tie_waits=False), left, right)
    assert taken[0].accepted and box_tuple(taken[0].box) in (left, right)


def test_two_equal_matches_are_ambiguous() -> None:
    params = ReidParams()
    reid, template = started(params)
    a = (100.0, 100.0, 30.0, 60.0)
    b = (100.0, 100.0, 30.0, 60.0)
    frame = draw((a, RED))
    res = reid.step(frame, dets(a, b), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.accepted and not res.secure


def test_initialisation_without_init_box() -> None:
    params = ReidParams()
    reid = ReIdentifier(params)
    low = (150.0, 170.0, 30.0, 60.0)  # bottom-centre nearest the image bottom-centre
    high = (145.0, 10.0, 30.0, 60.0)
    res = reid.step(draw((low, RED), (high, BLUE)), dets(high, low), None, None, 0)
    assert res.state == TrackState.TRACKING and box_tuple(res.init_box) == low
    # No detection: the frame-difference ROI of §2.1 (needs a previous frame and enough contrast).
    reid = ReIdentifier(params)
    black = (0, 0, 0)
    assert reid.step(draw(bg=black), dets(), None, None, 0).state == TrackState.UNINITIALISED
    res = reid.step(draw((TARGET, RED), bg=black), dets(), None, None, 33 * MS)
    assert res.state == TrackState.TRACKING and box_tuple(res.init_box) == TARGET


def test_restored_template_relocks_onto_matching_detection() -> None:
    # Prediction restarted (no prior) but the template was restored: the red target is chosen
    # although the blue person is nearer the image bottom-centre.
    params = ReidParams()
    template = hs_histogram(draw((TARGET, RED)), TARGET)
    near = (145.0, 175.0, 30.0, 60.0)
    reid = ReIdentifier(params)
    res = reid.step(draw((TARGET, RED), (near, BLUE)), dets(near, TARGET), None, template, 0)
    assert box_tuple(res.init_box) == TARGET and res.source == "template"
    # Nobody matches the template: fall back to the §2.1 rule (nearest bottom-centre).
    res = ReIdentifier(params).step(draw((near, BLUE)), dets(near), None, template, 0)
    assert box_tuple(res.init_box) == near and res.source == "nearest"


@pytest.mark.parametrize("global_search", [True, False])
def test_lost_target_is_re_detected_outside_the_gate_only_with_global_search(global_search: bool) -> None:
    params = ReidParams(lost_after_ms=100.0, global_search_when_lost=global_search)
    reid, template = started(params)
    for t in (33, 66, 99, 132):  # nothing visible: OCCLUDED, then LOST after 100 ms
        res = reid.step(draw(), dets(), prior_at(TARGET, t * MS), template, t * MS)
    assert res.state == TrackState.LOST
    far = (250.0, 20.0, 30.0, 60.0)  # reappears ~170 px away (a panning camera), gate radius ~62 px
    res = reid.step(draw((far, RED)), dets(far), prior_at(TARGET, 165 * MS), template, 165 * MS)
    if global_search:
        assert res.accepted and box_tuple(res.box) == far and res.state == TrackState.REACQUIRED
    else:
        assert not res.accepted and res.state == TrackState.LOST


def test_a_restarted_reid_initialises_on_the_detection_the_prior_expects() -> None:
    """re-ID restarted mid-run: no template yet, but prediction still has the track. The target is the
    gated detection nearest the prior, not whoever stands nearest the image centre."""
    from followbus.tracking.kalman import Predictor

    pred = Predictor(KalmanParams())
    left, centre = (40.0, 60.0, 40.0, 100.0), (140.0, 60.0, 40.0, 100.0)
    pred.apply(measurement(0, TrackState.TRACKING, Candidate(left, "init"), accepted=True, init_box=left))
    prior = pred.predict(33_000_000)
    frame = np.zeros((240, 320, 3), np.uint8)
    res = ReIdentifier(ReidParams()).step(frame, dets(left, centre), prior, None, 33_000_000)
    assert box_tuple(res.init_box) == left and res.source == "prior"


def test_after_a_prediction_restart_reid_reinitialises_where_its_target_just_was() -> None:
    """prediction restarted mid-run: no prior, no template feedback yet, but this re-ID was following the target.
    It re-initialises on the detection overlapping its last accepted box, not on a passer-by nearer the
    image's bottom centre (the chaos suite's future-stamp-track run latched onto one); once that box is older
    than lost_after_ms it falls back to bottom-centre."""
    frame = np.zeros((240, 320, 3), np.uint8)
    target, passer = (40.0, 60.0, 40.0, 100.0), (140.0, 120.0, 50.0, 115.0)  # the passer-by: nearer, centred
    reid = ReIdentifier(ReidParams(lost_after_ms=500.0))
    assert reid.step(frame, dets(target), None, None, 0, init_box=target).accepted
    moved = (44.0, 61.0, 40.0, 100.0)
    res = reid.step(frame, dets(moved, passer), None, None, 100 * MS)
    assert res.accepted and box_tuple(res.box) == moved and res.source == "last"
    # Frames shown without the target for longer than lost_after_ms: too old to trust.
    later = ReIdentifier(ReidParams(lost_after_ms=500.0))
    later.step(frame, dets(target), None, None, 0, init_box=target)
    for t_ms in range(33, 600, 33):
        later.step(frame, dets(), None, None, t_ms * MS)
    assert box_tuple(later.step(frame, dets(moved, passer), None, None, 627 * MS).box) == passer
    # But no frame at all for 900 ms (prediction restarting: no prior, so re-ID is given no input set) is no
    # evidence against the box: re-ID re-locks where its target just was.
    starved = ReIdentifier(ReidParams(lost_after_ms=500.0))
    starved.step(frame, dets(target), None, None, 0, init_box=target)
    res = starved.step(frame, dets(moved, passer), None, None, 900 * MS)
    assert box_tuple(res.box) == moved and res.source == "last"
    # Nor when the first frame after the gap shows no one: the gap still does not count, the shown frame does.
    gap = ReIdentifier(ReidParams(lost_after_ms=500.0))
    gap.step(frame, dets(target), None, None, 0, init_box=target)
    gap.step(frame, dets(), None, None, 900 * MS)
    res = gap.step(frame, dets(moved, passer), None, None, 933 * MS)
    assert box_tuple(res.box) == moved and res.source == "last"


@pytest.mark.parametrize("only_on_the_target", [True, False])
def test_a_reinitialisation_waits_for_the_target_it_follows(only_on_the_target: bool) -> None:
    """Prediction reset mid-run (a flood of frames made the stamps go back): no prior, the target hidden, a passer-by
    nearer the image bottom-centre. A re-ID that followed the target and has its template waits for it (LOST, the
    motor holds still) instead of starting to follow the passer-by, and re-locks when the target shows again away
    from where it was lost. A re-ID that never followed anyone still starts on the nearest person (§2.1)."""
    params = ReidParams(lost_after_ms=500.0, reinitialise_only_on_the_target=only_on_the_target)
    template = hs_histogram(draw((TARGET, RED)), TARGET)
    passer = (145.0, 175.0, 30.0, 60.0)
    reid = ReIdentifier(params)
    assert reid.step(draw((TARGET, RED)), dets(TARGET), None, template, 0, init_box=TARGET).accepted
    for t_ms in range(33, 700, 33):  # the target hidden: its last box goes stale
        reid.step(draw(), dets(), None, template, t_ms * MS)
    res = reid.step(draw((passer, BLUE)), dets(passer), None, template, 700 * MS)
    if not only_on_the_target:
        assert res.accepted and box_tuple(res.box) == passer
        return
    assert not res.accepted and res.state == TrackState.LOST
    back = (60.0, 40.0, 30.0, 60.0)  # the target again, away from its last box
    res = reid.step(draw((back, RED), (passer, BLUE)), dets(back, passer), None, template, 733 * MS)
    assert res.accepted and box_tuple(res.box) == back and res.source == "template"
    # Starting up, with a template restored from an earlier run: the §2.1 rule as before.
    fresh = ReIdentifier(params).step(draw((passer, BLUE)), dets(passer), None, template, 0)
    assert box_tuple(fresh.box) == passer and fresh.source == "nearest"


@pytest.mark.parametrize("only_on_the_target", [True, False])
def test_a_restarted_camera_takes_init_box_only_where_the_target_stands(only_on_the_target: bool) -> None:
    """A live camera restarted mid-run with init_box set: the source starts again, so init_box is offered again,
    but it says where the target stood when the run began. A re-ID that followed the target takes it only when
    what stands there looks like the target; a passer-by there is not followed, the target is re-acquired by its
    template where it now is. Where the target does stand at init_box (a scene or recording started again), it is
    taken as before."""
    params = ReidParams(reinitialise_only_on_the_target=only_on_the_target)
    template = hs_histogram(draw((TARGET, RED)), TARGET)
    reid = ReIdentifier(params)
    assert reid.step(draw((TARGET, RED)), dets(TARGET), None, template, 0, init_box=TARGET).accepted
    elsewhere = (220.0, 60.0, 30.0, 60.0)
    res = reid.step(draw((TARGET, BLUE), (elsewhere, RED)), dets(TARGET, elsewhere), None, template, 33 * MS,
                    init_box=TARGET)
    if not only_on_the_target:
        assert res.accepted and box_tuple(res.box) == TARGET and res.source == "init"
        return
    assert res.accepted and box_tuple(res.box) == elsewhere and res.source == "template"
    res = reid.step(draw((TARGET, BLUE)), dets(TARGET), None, template, 66 * MS, init_box=TARGET)
    assert not res.accepted and res.state == TrackState.LOST  # the target out of view: it waits
    res = reid.step(draw((TARGET, RED)), dets(TARGET), None, template, 99 * MS, init_box=TARGET)
    assert res.accepted and res.source == "init"  # the source started again with the target where it began


def test_adaptive_gate_grows_for_fast_or_weakly_detected_targets() -> None:
    """Seed 002 §3.2: k = 1 for a slow target last seen on a confident detection, up to 1.5 (the gate's χ²
    × 2.25) when it moves fast in the image or its last detection was weak; a candidate just outside the base
    gate is then taken in."""
    params = ReidParams()
    reid, template = started(params)
    slow = prior_at(TARGET, 33_000_000)
    assert reid.gate_scale(slow) == 1.0  # the initial box: nothing to doubt
    h = TARGET[3]
    fast = Prior.of_filter(t_ns=33_000_000, state=np.array([slow.state[0], slow.state[1], 0.06 * h / 0.033, 0.0]),
                 size=slow.size, covariance=slow.covariance, innovation_cov=slow.innovation_cov, gate_chi2=9.488)
    assert reid.gate_scale(fast) == pytest.approx(params.gate_scale_max)
    # accepted on a weak detection (score 0.3): the next gate is the widest
    frame = draw((TARGET, RED))
    weak = np.array([(*TARGET, 0.3)], np.float32)
    assert reid.step(frame, weak, slow, template, 33_000_000).accepted
    assert reid.gate_scale(slow) == pytest.approx(params.gate_scale_max)
    # ... and a target that jumped just beyond the base gate (d² ≈ 12 > 9.488) is still a candidate
    moved = (TARGET[0] + math.sqrt(12.0 * 400.0), TARGET[1], TARGET[2], TARGET[3])
    result = reid.step(draw((moved, RED)), dets(moved), prior_at(TARGET, 66_000_000), template, 66_000_000)
    assert result.accepted and result.box == pytest.approx(moved, abs=1e-3)
    off = ReIdentifier(ReidParams(adaptive_gate=False))
    assert off.gate_scale(fast) == 1.0


def test_low_score_detections_are_a_second_stage_never_a_training_sample() -> None:
    """Seed 002 / ByteTrack: the partly hidden target scores under the detector's threshold; with no detection
    in the gate matching, re-ID takes the low-score box that matches (not secure: the template and the
    classifier learn nothing from it); with a matching detection the low-score boxes are not looked at."""
    params = ReidParams()
    reid, template = started(params)
    frame = draw((TARGET, RED))
    low = np.array([(*TARGET, 0.15)], np.float32)
    result = reid.step(frame, dets(), prior_at(TARGET, 33_000_000), template, 33_000_000, low_detections=low)
    assert result.accepted and result.source == "low-score" and not result.secure
    assert result.box == pytest.approx(TARGET)
    # a detection that matches wins; the low-score box is not even a candidate then
    result = reid.step(frame, dets(TARGET), prior_at(TARGET, 66_000_000), template, 66_000_000,
                       low_detections=np.array([(TARGET[0] + 5, TARGET[1], TARGET[2], TARGET[3], 0.2)], np.float32))
    assert result.accepted and result.source == "detection" and len(reid.candidates) == 1
    off, template_off = started(ReidParams(low_score_stage=False))
    result = off.step(frame, dets(), prior_at(TARGET, 33_000_000), template_off, 33_000_000, low_detections=low)
    assert "low-score" not in result.candidate_sources


def test_low_score_stage_keeps_bytetracks_caution() -> None:
    """ByteTrack's second stage (seed 002): only for a target matched on the previous frame and only a low-score
    box overlapping the predicted box by low_score_min_iou: an occluded target's gate may hold a stranger's weak
    box, and a weak box inside the gate but beside the prediction is someone else."""
    params = ReidParams()
    reid, template = started(params)
    frame = draw((TARGET, RED))
    beside = (TARGET[0] + 18.0, TARGET[1], TARGET[2], TARGET[3])  # in the gate, IoU 0.25 with the prediction
    weak = np.array([(*beside, 0.2)], np.float32)
    result = reid.step(draw((beside, RED)), dets(), prior_at(TARGET, 33 * MS), template, 33 * MS, low_detections=weak)
    assert not result.accepted and result.state == TrackState.OCCLUDED
    # now occluded: not even a weak box right on the prediction is taken (the target was not matched last frame)
    on = np.array([(*TARGET, 0.2)], np.float32)
    result = reid.step(frame, dets(), prior_at(TARGET, 66 * MS), template, 66 * MS, low_detections=on)
    assert not result.accepted and result.state == TrackState.OCCLUDED
    # a confident detection brings it back; then the weak box on the prediction is taken again
    assert reid.step(frame, dets(TARGET), prior_at(TARGET, 99 * MS), template, 99 * MS).accepted
    result = reid.step(frame, dets(), prior_at(TARGET, 132 * MS), template, 132 * MS, low_detections=on)
    assert result.accepted and result.source == "low-score"
    loose = ReIdentifier(ReidParams(low_score_min_iou=0.0))
    loose.step(frame, dets(TARGET), None, None, 0, init_box=TARGET)
    assert loose.step(draw((beside, RED)), dets(), prior_at(TARGET, 33 * MS), template, 33 * MS,
                      low_detections=weak).accepted


def test_a_box_cut_at_the_legs_or_the_head_is_completed_to_the_predicted_height() -> None:
    predicted = (100.0, 100.0, 30.0, 90.0)  # top 100, bottom 190, aspect 3
    # legs hidden (a car): the top agrees, the bottom falls short; completed downwards, width kept
    assert complete_partial_view((102.0, 103.0, 28.0, 45.0), predicted) == (102.0, 103.0, 28.0, 90.0)
    # head and shoulders hidden: the bottom agrees; completed upwards
    assert complete_partial_view((101.0, 140.0, 29.0, 48.0), predicted) == (101.0, 98.0, 29.0, 90.0)


@pytest.mark.parametrize("box, why", [
    ((102.0, 103.0, 28.0, 80.0), "at 0.8 of the predicted height or more: not cut"),
    ((98.0, 110.0, 35.0, 70.0), "both edges moved in: nothing to anchor on"),
    ((100.0, 130.0, 25.0, 40.0), "neither edge agrees"),
    ((104.0, 101.0, 20.0, 60.0), "a whole person's shape (aspect 3): the prediction's height was wrong"),
    ((92.0, 145.0, 45.0, 45.0), "wider than predicted (crouching, tucked): a changed pose, no occluder"),
])
def test_what_is_not_a_partial_view_is_kept(box: tuple[float, float, float, float], why: str) -> None:
    assert complete_partial_view(box, (100.0, 100.0, 30.0, 90.0)) == box, why


def test_a_wider_pose_is_completed_only_when_told_to() -> None:
    """The ablation's switch: without keep_wider_whole, a tucked 45x45 box with its bottom on the prediction's is
    completed to the predicted 90 px from that edge."""
    tucked = (92.0, 145.0, 45.0, 45.0)
    completed = complete_partial_view(tucked, (100.0, 100.0, 30.0, 90.0), keep_wider_whole=False)
    assert completed == (92.0, 100.0, 45.0, 90.0)


def test_a_partial_view_is_measured_and_output_whole_and_never_learnt_from() -> None:
    """The target walks behind a car: its detection covers the upper half. Re-ID scores the colour on what is seen,
    the geometry on the whole person, accepts it as the whole person (the prediction node then measures that centre
    and height, and outputs it), and takes no training sample from it (its box covers the car)."""
    params = ReidParams()
    reid, template = started(params)
    upper = (TARGET[0], TARGET[1], TARGET[2], 28.0)
    frame = draw((upper, RED))
    res = reid.step(frame, dets(upper), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.accepted and res.box == pytest.approx(TARGET)
    assert not res.secure
    assert reid.candidates[0].box == upper and reid.candidates[0].whole == pytest.approx(TARGET)
    off, template_off = started(ReidParams(partial_view_completion=False))
    res = off.step(frame, dets(upper), prior_at(TARGET, 33 * MS), template_off, 33 * MS)
    assert res.box is None or res.box == pytest.approx(upper)


def test_a_box_merging_the_target_with_someone_in_line_is_trimmed_to_the_predicted_height() -> None:
    """From a high camera, the person behind the target is boxed with it: one edge agrees with the prediction, the
    other reaches far beyond; the target is the predicted height from the agreeing edge (width kept)."""
    predicted = (100.0, 100.0, 30.0, 90.0)  # top 100, bottom 190
    assert trim_merged_view((98.0, 102.0, 40.0, 170.0), predicted) == (98.0, 102.0, 40.0, 90.0)  # someone below
    assert trim_merged_view((97.0, 40.0, 45.0, 148.0), predicted) == (97.0, 98.0, 45.0, 90.0)  # someone above


@pytest.mark.parametrize("box, why", [
    ((100.0, 101.0, 30.0, 110.0), "under the ratio: a stride, raised arms, a detector's jitter"),
    ((95.0, 80.0, 40.0, 130.0), "both edges moved out: the person came closer"),
    ((100.0, 130.0, 30.0, 150.0), "neither edge agrees"),
])
def test_what_is_not_a_merged_view_is_kept(box: tuple[float, float, float, float], why: str) -> None:
    assert trim_merged_view(box, (100.0, 100.0, 30.0, 90.0), min_ratio=1.3) == box, why


def test_a_merged_view_is_measured_as_the_target_and_never_learnt_from() -> None:
    params = ReidParams()
    reid, template = started(params)
    merged = (TARGET[0], TARGET[1], TARGET[2], TARGET[3] * 1.8)  # someone below the target, boxed with it
    res = reid.step(draw((TARGET, RED)), dets(merged), prior_at(TARGET, 33 * MS), template, 33 * MS)
    assert res.accepted and res.box == pytest.approx(TARGET) and not res.secure
    with pytest.raises(InvalidParam, match="merged_min_extent_ratio"):
        ReidParams(merged_min_extent_ratio=1.0)


@pytest.mark.parametrize("neighbour, own_extent", [(False, True), (True, True), (False, False)])
def test_a_lone_merged_view_that_lasts_becomes_the_targets_own_extent(neighbour: bool, own_extent: bool) -> None:
    """The target turns and is boxed 1.8x as wide from then on, its left edge where predicted. Trimmed, the box
    measures the old width back for good; alone in the gate for merged_view_own_extent_after_ms it is measured
    whole. With someone else in the gate each frame it stays a merged view."""
    params = ReidParams(learned_appearance=False, merged_view_own_extent=own_extent)
    reid, template = started(params)
    wide = (TARGET[0], TARGET[1], TARGET[2] * 1.8, TARGET[3])
    other = (TARGET[0] + 50.0, TARGET[1], TARGET[2], TARGET[3])  # in the gate, centred outside the wide box
    frames = int(params.merged_view_own_extent_after_ms / params.dt_ms) + 3
    widths = []
    for k in range(1, frames):
        boxes = (wide, other) if neighbour else (wide,)
        frame = draw((wide, RED), *([(other, (200, 120, 0))] if neighbour else []))
        res = reid.step(frame, dets(*boxes), prior_at(TARGET, k * 33 * MS), template, k * 33 * MS)
        assert res.accepted, k
        widths.append(float(res.box[2]))
    assert widths[0] == pytest.approx(TARGET[2])
    assert widths[-1] == pytest.approx(wide[2] if own_extent and not neighbour else TARGET[2])
