"""End-to-end behaviour of the seed-000 tracker (the graph's tracking nodes, in-process) on a synthetic occlusion
sequence."""

from __future__ import annotations

import numpy as np
import pytest

from followbus.evaluation.graph_follower import GraphFollower
from followbus.msgs.tracking import Measurement, Prior
from followbus.tracking.init import frame_difference_roi, motion_blobs, nearest_to_centre_bottom, to_grey
from followbus.tracking.kalman import Predictor, output_box
from followbus.tracking.params import InvalidParam, KalmanParams, ReidParams, TemplateParams
from followbus.tracking.reid import ReIdentifier
from followbus.tracking.template import TemplateUpdater

W, H = 480, 270
BAR_X = (200, 280)  # grey occluder, full height; the target passes behind it
TW, TH = 30, 60
FRAME_NS = 33_333_333
N_FRAMES = 60


def scene(k: int) -> tuple[np.ndarray, np.ndarray, tuple[float, float], float]:
    """Frame k: red target moving right at 5 px/frame behind the bar; a blue distractor walks left
    in front of the bar, 70 px higher, crossing the target's column while it is hidden.
    Detections: the distractor always, the target when ≥ 50 % visible (box of its visible part)."""
    img = np.full((H, W, 3), (40, 90, 40), np.uint8)
    tx, ty = 40 + 5 * k, 170
    dx, dy = 380 - 3 * k, 100
    img[ty:ty + TH, tx:tx + TW] = (30, 30, 220)
    img[:, BAR_X[0]:BAR_X[1]] = (128, 128, 128)
    img[dy:dy + TH, dx:dx + TW] = (220, 60, 30)
    xs = np.arange(tx, tx + TW)
    visible = (xs < BAR_X[0]) | (xs >= BAR_X[1])
    rows = []
    if visible.mean() >= 0.5:
        vx = xs[visible]
        rows.append((vx.min(), ty, vx.max() - vx.min() + 1, TH, 0.9))
    rows.append((dx, dy, TW, TH, 0.8))
    return img, np.array(rows, np.float32), (tx + TW / 2.0, ty + TH / 2.0), float(visible.mean())


def run(follower: GraphFollower) -> list[tuple]:
    """(k, visible fraction, gt centre, what the graph published for frame k) per frame."""
    out = []
    for k in range(N_FRAMES):
        img, dets, gt, vis = scene(k)
        follower.step(img, dets, k * FRAME_NS, v_ego_mps=(0.5, 0.0))
        out.append((k, vis, gt, follower.last))
    return out


def centre_error(box, gt: tuple[float, float]) -> float:
    return float(np.hypot(box[0] + box[2] / 2.0 - gt[0], box[1] + box[3] / 2.0 - gt[1]))


def test_tracker_through_occlusion_with_distractor() -> None:
    """The graph's tracking nodes (run in-process, as `followbus eval` runs them) through an occlusion."""
    frames = run(GraphFollower(details=True))
    # Initialised on frame 0 from the detection nearest the image bottom-centre (the target).
    assert frames[0][3].measurement.init_box is not None
    assert centre_error(frames[0][3].measurement.init_box, frames[0][2]) == 0.0

    hidden = [f for f in frames if f[1] == 0.0]
    assert len(hidden) >= 10
    before = [f for f in frames if f[0] < hidden[0][0] and f[1] >= 0.5]
    after_start = hidden[-1][0] + 1
    assert all(f[3].track.state == "OCCLUDED" for f in hidden)
    # The predicted box is reported while hidden, as long as it more likely overlaps the person than not; then
    # none (the robot stops) rather than a box drifting off them.
    shown = [f for f in hidden if f[3].track.box is not None]
    assert len(shown) >= 3 and shown == hidden[:len(shown)]
    for _, _, gt, out in hidden:
        assert out.track.box is None or centre_error(out.track.box, gt) < 20.0
        assert out.template.eta == 0.0
    for _, _, gt, out in before:
        assert out.track.state == "TRACKING"
        assert centre_error(out.track.box, gt) < 20.0

    after = [f for f in frames if f[0] >= after_start and f[3].measurement.accepted]
    assert after, "target never re-identified"
    first = after[0]
    assert first[3].track.state == "REACQUIRED"
    assert first[0] <= after_start + 3  # re-identified as soon as it is ≥ 50 % visible
    for _, _, gt, out in after:
        assert centre_error(out.track.box, gt) < 20.0
        assert out.measurement.s_color > 0.9  # the red target, never the blue distractor
    assert frames[-1][3].track.state == "TRACKING"
    # The template only learnt while tracked securely.
    assert all(f[3].template.eta == 0.0 for f in frames if f[3].track.state != "TRACKING")
    assert any(f[3].template.eta > 0.0 for f in frames)


def test_the_graph_is_deterministic_and_is_the_seeds_order_of_the_pure_modules() -> None:
    """Two runs of the graph's nodes are identical, and equal the pure modules driven by hand in seed 000's
    order (prior k after measurement k-1, re-ID against the template of k-1), bit for bit. (No region is re-detected:
    the hand-driven modules have no detector.)"""
    a = run(GraphFollower({"local_redetection": False}, details=True))
    b = run(GraphFollower({"local_redetection": False}, details=True))
    predictor, reid, template = Predictor(KalmanParams()), ReIdentifier(ReidParams()), TemplateUpdater(TemplateParams())
    hist = None
    for k in range(N_FRAMES):
        img, dets, _, _ = scene(k)
        prior = predictor.predict(k * FRAME_NS, (0.5, 0.0))
        r = reid.step(img, dets, prior, hist, k * FRAME_NS)  # what the re-ID node publishes
        predictor.apply(r, (0.5, 0.0))
        hist, eta, _ = template.step(img, r)
        ta, tb = a[k][3], b[k][3]
        assert ta.track.state == tb.track.state == r.state
        assert ta.measurement.m_fuse == tb.measurement.m_fuse == r.m_fuse
        expected = output_box(r, prior)
        assert (ta.track.box is None) == (expected is None)
        assert ta.track.box is None or tuple(ta.track.box) == tuple(expected)
        assert ta.template.eta == tb.template.eta == eta
        if hist is None:
            assert ta.template.hist is None
        else:
            np.testing.assert_array_equal(ta.template.hist, hist)
        assert ta.prior.initialised == (prior is not None)
        if prior is not None:
            np.testing.assert_array_equal(ta.prior.state, prior.state)
            np.testing.assert_array_equal(ta.prior.innovation_cov, prior.innovation_cov)


def test_explicit_init_box_and_lost() -> None:
    follower = GraphFollower({"lost_after_ms": 200.0}, details=True)
    img, dets, _, _ = scene(0)
    box, info = follower.step(img, dets, 0, init_box=(40.0, 170.0, 30.0, 60.0))
    assert info["state"] == "TRACKING" and box == (40.0, 170.0, 30.0, 60.0)
    empty = np.full((H, W, 3), (40, 90, 40), np.uint8)
    none = np.zeros((0, 5), np.float32)
    states = [follower.step(empty, none, k * FRAME_NS)[1]["state"] for k in range(1, 10)]
    assert states[:6] == ["OCCLUDED"] * 6  # ≤ 200 ms since the last match
    assert states[6:] == ["LOST"] * 3
    assert follower.step(empty, none, 10 * FRAME_NS)[0] is None  # no output box when LOST


def test_an_uncertain_coast_is_not_output() -> None:
    """While OCCLUDED the coasting prediction is the output only while it more likely overlaps the person than not
    (P(|dx| < w, |dy| < h) under the prior's covariance, occluded_output_min_overlap_probability); then none (the
    controller stops), the state stays OCCLUDED."""
    occluded = Measurement(state="OCCLUDED")

    def prior_of(std_px: float, limit: float = 0.5) -> Prior:
        params = KalmanParams(occluded_output_min_overlap_probability=limit, image_motion_model=False)
        predictor = Predictor(params)
        predictor.initialise((85.0, 70.0, 30.0, 60.0), 0)
        predictor.filters["scene"].P = np.diag([std_px**2, 1.0, 1.0, 1.0])
        return predictor.predict(0)

    # σx = w / 0.6745 puts |dx| < w at probability 0.5 (the normal's quartile); |dy| < 60 with σy = 1: certain.
    assert prior_of(30.0 / 0.6745).overlap_probability() == pytest.approx(0.5, abs=1e-3)
    np.testing.assert_array_equal(output_box(occluded, prior_of(43.0)), prior_of(43.0).box)
    assert output_box(occluded, prior_of(46.0)) is None
    assert output_box(occluded, prior_of(20.0, limit=0.9)) is None
    assert output_box(occluded, prior_of(1e4, limit=0.0)) is not None  # 0: no limit (the ablation)
    accepted = Measurement(state="REACQUIRED", accepted=True, box=np.array([1.0, 2.0, 3.0, 4.0]))
    np.testing.assert_array_equal(output_box(accepted, prior_of(1e4)), accepted.box)

    follower = GraphFollower({"lost_after_ms": 5000.0}, details=True)
    img, dets, _, _ = scene(0)
    follower.step(img, dets, 0, init_box=(40.0, 170.0, 30.0, 60.0))
    empty, none = np.full((H, W, 3), (40, 90, 40), np.uint8), np.zeros((0, 5), np.float32)
    coast = []
    for k in range(1, 40):
        follower.step(empty, none, k * FRAME_NS)
        last = follower.last
        assert last.track.state == "OCCLUDED"
        coast.append((last.track.box is not None, last.prior.overlap_probability()))
    shown = [p for out, p in coast if out]
    withheld = [p for out, p in coast if not out]
    assert shown and withheld and coast.index((False, withheld[0])) == len(shown)  # output first, then none
    limit = KalmanParams().occluded_output_min_overlap_probability
    assert min(shown) >= limit > max(withheld)


def test_no_target_before_initialisation() -> None:
    follower = GraphFollower(details=True)
    empty = np.full((H, W, 3), (40, 90, 40), np.uint8)
    box, info = follower.step(empty, np.zeros((0, 5), np.float32), 0)
    assert info["state"] == "UNINITIALISED" and box is None and not follower.last.prior.initialised


def test_init_helpers() -> None:
    dets = np.array([[10, 10, 20, 40, 0.9], [300, 200, 20, 40, 0.9], [150, 150, 30, 60, 0.5]], np.float32)
    # Bottom-centres: (20, 50), (310, 240), (165, 210); image bottom-centre (160, 240).
    assert nearest_to_centre_bottom(dets, 320, 240) == (150.0, 150.0, 30.0, 60.0)
    assert nearest_to_centre_bottom(np.zeros((0, 5), np.float32), 320, 240) is None
    prev = np.zeros((120, 160, 3), np.uint8)
    cur = prev.copy()
    cur[40:80, 60:80] = (200, 200, 200)  # big mover
    cur[5:8, 5:8] = (255, 255, 255)  # 3x3 speck: removed by the 5x5 opening
    assert frame_difference_roi(prev, cur, 25, 5) == (60.0, 40.0, 20.0, 40.0)
    assert frame_difference_roi(prev, prev, 25, 5) is None
    blobs = motion_blobs(to_grey(prev), to_grey(cur), 25, 5, min_area_px=0)
    assert [b for b, _ in blobs] == [(60.0, 40.0, 20.0, 40.0)]  # the speck did not survive the opening
    faint = prev.copy()
    faint[40:80, 60:80] = 20  # below Thresh_diff = 25
    assert frame_difference_roi(prev, faint, 25, 5) is None


def test_params_table1_defaults_each_node_its_own() -> None:
    kalman, reid, template = KalmanParams(), ReidParams(), TemplateParams()
    assert (reid.diff_threshold, reid.morph_kernel_px, reid.bins_h, reid.bins_s) == (25, 5, 16, 8)
    assert (kalman.dt_ms, kalman.gate_chi2, reid.reid_threshold, reid.tau_occ) == (33.0, 9.488, 0.75, 0.60)
    assert (template.tau_v, template.tau_s, template.eta_base) == (220, 45, 0.02)
    # A node declares only what it reads: re-ID gates with the prior's χ², so it has no gate_chi2 of its own.
    assert not hasattr(reid, "gate_chi2") and not hasattr(kalman, "reid_threshold")
    # A value two nodes read is declared once (a shared base), so their defaults cannot drift apart.
    for name, classes in (("dt_ms", (KalmanParams, ReidParams)), ("bins_h", (ReidParams, TemplateParams)),
                          ("suspend_updates", (KalmanParams, TemplateParams))):
        owners = {next(b for b in c.__mro__ if name in b.__dict__.get("__annotations__", {})) for c in classes}
        assert len(owners) == 1, (name, owners)
    with pytest.raises(InvalidParam, match="reid_threshold") as raised:
        ReidParams(reid_threshold=1.5)
    assert raised.value.key == "reid_threshold"  # graph validation points at that parameter's line
