"""Camera-motion estimate (tracking/egomotion.py) and the warped Kalman prior (seed 002 §3.3)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from followbus.msgs.perception import CameraMotion
from followbus.tracking.egomotion import EgoMotionEstimator, EgoMotionParams, background_mask
from followbus.tracking.kalman import KalmanCV, Predictor
from followbus.tracking.params import KalmanParams

H, W = 480, 640


def textured(seed: int = 0) -> np.ndarray:
    """A 640x480 BGR image with corners everywhere: blurred noise plus random rectangles."""
    rng = np.random.default_rng(seed)
    grey = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 3.0)
    grey = cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX)
    for _ in range(60):
        x, y = int(rng.integers(0, W - 40)), int(rng.integers(0, H - 40))
        cv2.rectangle(grey, (x, y), (x + int(rng.integers(8, 40)), y + int(rng.integers(8, 40))),
                      float(rng.uniform(0, 255)), -1)
    return cv2.cvtColor(grey.astype(np.uint8), cv2.COLOR_GRAY2BGR)


def similarity(angle_deg: float, scale: float, tx: float, ty: float) -> np.ndarray:
    """2x3 similarity about the image centre, then a shift."""
    m = cv2.getRotationMatrix2D((W / 2, H / 2), angle_deg, scale)
    m[:, 2] += (tx, ty)
    return m


def warp(img: np.ndarray, m: np.ndarray) -> np.ndarray:
    return cv2.warpAffine(img, m, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def estimate(img0: np.ndarray, img1: np.ndarray, dets0=None, dets1=None,
             params: EgoMotionParams | None = None) -> tuple[CameraMotion | None, EgoMotionEstimator]:
    est = EgoMotionEstimator(params)
    assert est.step(img0, dets0, 0) is None  # nothing to compare the first frame with
    return est.step(img1, dets1, 33_000_000), est


@pytest.mark.parametrize("angle_deg, scale, tx, ty", [
    (0.0, 1.0, 12.0, -7.0),  # a pan / tilt
    (3.0, 1.0, 0.0, 0.0),  # a roll
    (0.0, 1.05, 0.0, 0.0),  # a zoom (or driving towards the scene)
    (-2.0, 0.97, -9.0, 5.0),  # all at once
])
def test_known_similarity_is_recovered(angle_deg: float, scale: float, tx: float, ty: float) -> None:
    img0 = textured()
    truth = similarity(angle_deg, scale, tx, ty)
    motion, est = estimate(img0, warp(img0, truth))
    assert motion is not None, est.counts
    np.testing.assert_allclose(motion.matrix[:, :2], truth[:, :2], atol=3e-3)
    # The translation column is dominated by where the rotation centre is; compare where points land.
    pts = np.array([[50.0, 60.0, 1.0], [W / 2, H / 2, 1.0], [590.0, 420.0, 1.0]])
    np.testing.assert_allclose(pts @ motion.matrix.T, pts @ truth.T, atol=0.6)
    assert motion.scale == pytest.approx(scale, abs=3e-3)
    assert motion.inliers >= 50 and motion.tracked >= motion.inliers
    assert (motion.from_stamp_ns, motion.header.stamp_ns) == (0, 33_000_000)
    assert est.counts["transform"] == 1


def test_affine_model_recovers_a_shear() -> None:
    img0 = textured(1)
    truth = np.array([[1.02, 0.03, 4.0], [-0.01, 0.99, -3.0]])
    motion, _ = estimate(img0, warp(img0, truth), params=EgoMotionParams(model="affine"))
    assert motion is not None
    np.testing.assert_allclose(motion.matrix[:, :2], truth[:, :2], atol=3e-3)


def test_textureless_image_gives_no_transform() -> None:
    flat = np.full((H, W, 3), 128, np.uint8)
    gradient = np.repeat(np.linspace(0, 255, W, dtype=np.float32)[None, :], H, 0).astype(np.uint8)
    for img in (flat, cv2.cvtColor(gradient, cv2.COLOR_GRAY2BGR)):
        motion, est = estimate(img, warp(img, similarity(0.0, 1.0, 8.0, 0.0)))
        assert motion is None
        assert est.counts["few_corners"] == 1 and est.counts["transform"] == 0


def test_implausible_scale_gives_no_transform() -> None:
    img0 = textured(2)
    truth = similarity(0.0, 1.04, 0.0, 0.0)
    ok, _ = estimate(img0, warp(img0, truth))
    assert ok is not None  # the same zoom is accepted under the default bound
    motion, est = estimate(img0, warp(img0, truth), params=EgoMotionParams(max_scale_change=0.02))
    assert motion is None and est.counts["implausible_scale"] == 1


def test_person_boxes_are_not_background() -> None:
    """A person filling most of the frame walks against the pan: masked, the fit follows the background."""
    bg0 = textured(3)
    bg1 = warp(bg0, similarity(0.0, 1.0, 10.0, 0.0))  # the camera pans: the background moves 10 px right
    person = textured(4)[:380, :440]
    img0, img1 = bg0.copy(), bg1.copy()
    img0[50:430, 100:540] = person
    img1[50:430, 80:520] = person  # the person moves 20 px left
    box0 = np.array([[100.0, 50.0, 440.0, 380.0, 0.9]])
    box1 = np.array([[80.0, 50.0, 440.0, 380.0, 0.9]])
    motion, _ = estimate(img0, img1, box0, box1)
    assert motion is not None
    assert motion.matrix[:, 2] == pytest.approx([10.0, 0.0], abs=0.5)
    # Without the boxes the person's corners outnumber the background's and the fit follows the person:
    # the test fails if the mask is not applied.
    blind, _ = estimate(img0, img1)
    assert blind is not None and blind.matrix[:, 2] == pytest.approx([-20.0, 0.0], abs=0.5)


def test_background_mask_scales_and_grows_boxes() -> None:
    mask = background_mask((240, 320), np.array([[100.0, 40.0, 100.0, 200.0, 0.8]]), (0.5, 0.5), 0.1)
    assert mask.dtype == np.uint8 and mask.shape == (240, 320)
    # box [100, 40, 100, 200] grown by 10 % is x 90-210, y 20-260, i.e. 45-105 x 10-130 at half size
    assert (mask[10:130, 45:105] == 0).all()
    assert mask[5, 40] == 255 and mask[135, 110] == 255
    assert (background_mask((10, 10), None, (1.0, 1.0), 0.1) == 255).all()


def test_kalman_warp_maps_mean_velocity_covariance_and_size() -> None:
    kf = KalmanCV()
    kf.initialise((90.0, 40.0, 20.0, 40.0), t_ns=0)  # centre (100, 60)
    kf.x[2:] = (30.0, 0.0)
    kf.P = np.diag([4.0, 9.0, 100.0, 25.0])
    rot90 = np.array([[0.0, -2.0, 5.0], [2.0, 0.0, -3.0]])  # 90° rotation, scale 2, shift (5, -3)
    kf.warp(rot90)
    assert kf.x == pytest.approx([-115.0, 197.0, 0.0, 60.0])
    # T = diag(M, M): the x/y variances swap and grow by s² = 4
    np.testing.assert_allclose(kf.P, np.diag([36.0, 16.0, 100.0, 400.0]), atol=1e-12)
    assert kf.size == pytest.approx((40.0, 80.0))


def test_warped_prior_lands_on_the_moved_target() -> None:
    """A 60 px pan: the warped prior's gate holds the target's new position; the plain prior's does not."""
    img0 = textured(5)
    pan = similarity(0.0, 1.0, 60.0, 25.0)
    img1 = warp(img0, pan)
    box0 = (200.0, 120.0, 80.0, 200.0)  # a standing person; the camera pans, the person does not walk
    box1 = (260.0, 145.0, 80.0, 200.0)
    est = EgoMotionEstimator()
    est.step(img0, np.array([[*box0, 0.9]]), 0)
    motion = est.step(img1, np.array([[*box1, 0.9]]), 33_000_000)
    assert motion is not None
    target = (300.0, 245.0)

    def prior(params: KalmanParams, m):
        pred = Predictor(params)
        pred.initialise(box0, t_ns=0)
        return pred, pred.predict(33_000_000, (0.0, 0.0), m)

    scene_model = KalmanParams(camera_motion_compensation=True, image_motion_model=False)  # the warp alone
    pred, warped = prior(scene_model, motion)
    assert warped.centre == pytest.approx(target, abs=1.0) and warped.mahalanobis_sq(target) <= warped.gate_chi2
    assert pred.warped == 1
    _, plain = prior(KalmanParams(camera_motion_compensation=False), motion)
    assert plain.centre == pytest.approx((240.0, 220.0)) and plain.mahalanobis_sq(target) > plain.gate_chi2
    # A motion that does not start at the filter's stamp (a frame either side did not see) is not applied.
    stale = _motion_of(motion.matrix, -33_000_000, 33_000_000)
    pred, unwarped = prior(scene_model, stale)
    assert unwarped.centre == pytest.approx((240.0, 220.0)) and pred.motion_mismatched == 1


def test_tracker_keeps_a_still_person_through_camera_shake() -> None:
    """A person standing still while the camera shakes 60 px left and right every frame: with compensation the
    prior follows the image and every frame is matched; without it the jumps leave the gate."""
    from followbus.evaluation.graph_follower import GraphFollower

    world = np.concatenate([textured(6), textured(7)[:, :160]], axis=1)  # 800 px wide scene
    person = (500, 200, 60, 150)  # world x, y, w, h: a red figure that never moves
    cv2.rectangle(world, (person[0], person[1]), (person[0] + person[2], person[1] + person[3]), (30, 30, 200), -1)
    offsets = [0, 60, 0, 60, 0, 60, 0, 60, 10, 70, 20, 80, 30]

    def run(cmc: bool) -> tuple[list, int]:
        follower = GraphFollower({"camera_motion_compensation": cmc}, details=True)  # the graph, in-process
        out = []
        for k, o in enumerate(offsets):
            frame = np.ascontiguousarray(world[:, o:o + W])
            box = (float(person[0] - o), float(person[1]), float(person[2]), float(person[3]))
            follower.step(frame, np.array([[*box, 0.9]], np.float32), k * 33_000_000,
                          init_box=box if k == 0 else None)
            out.append((follower.last, box))
        warped = follower.graph.status("prediction")["extra"]["priors_warped"]
        return out, warped

    with_cmc, warped = run(True)
    assert all(o.track.state == "TRACKING" and o.measurement.accepted for o, _ in with_cmc)
    assert all(o.track.box is not None and np.allclose(o.track.box, box) for o, box in with_cmc)
    assert warped == len(offsets) - 1
    without, _ = run(False)
    assert sum(not o.measurement.accepted for o, _ in without) >= 3


def test_egomotion_node_publishes_the_transform_and_prediction_warps_by_it(tmp_path) -> None:
    """graph.yaml plus the egomotion node (how it is meant to be wired), in the in-process runtime: the node's
    transform of a 60 px pan is valid, checked on the wire, and prediction's prior lands on the moved target."""
    from followbus.bus.graph import load_graph
    from followbus.bus.inproc import InProcessGraph
    from followbus.bus.schemas import Frame, decode, validate
    from followbus.msgs import CameraMotion as CameraMotionMsg
    from followbus.msgs.perception import Detections
    from followbus.msgs.tracking import Measurement

    from .conftest import REPO

    (tmp_path / "g.yaml").write_text(f"""
extends: {REPO / 'graph.yaml'}
nodes:
  egomotion:
    run: followbus.nodes.egomotion
    inputs:
      frame: {{from: capture/frame, queue: 16}}
      detections: {{from: detection/detections, queue: 32}}
    outputs: [transform]
  prediction:
    inputs:
      transform: {{from: egomotion/transform, queue: 32, optional: true}}
    params: {{camera_motion_compensation: true, image_motion_model: false}}   # the scene model's warp alone
""")
    graph = load_graph(tmp_path / "g.yaml")
    img0 = textured(8)
    img1 = warp(img0, similarity(0.0, 1.0, 60.0, 25.0))
    box0, box1 = (200.0, 120.0, 80.0, 200.0), (260.0, 145.0, 80.0, 200.0)

    def stamp(msg, k):
        msg.header.frame_seq, msg.header.stamp_ns, msg.header.epoch_ns = k, 1_000_000_000 + k * 33_000_000, 7
        return msg

    with InProcessGraph(graph, nodes=["egomotion", "prediction"]) as g:
        for k, (img, box) in enumerate([(img0, box0), (img1, box1)]):
            g.inject("capture/frame", stamp(Frame(width=W, height=H, encoding="bgr8", data=img), k))
            g.inject("detection/detections", stamp(Detections(boxes=np.array([[*box, 0.9]], np.float32)), k))
            g.deliver()
            if k == 0:
                m = stamp(Measurement(state="TRACKING", accepted=True, secure=True, box=np.array(box0),
                                      best_box=np.array(box0), source="init", init_box=np.array(box0)), 0)
                g.inject("reid/measurement", m)
                g.deliver()
        transforms = g.outputs("egomotion", "transform")
        priors = g.outputs("prediction", "prior")
    assert [t.valid for t in transforms] == [False, True] and transforms[0].reason == "no_previous"
    t = validate(decode(transforms[1].encode(), CameraMotionMsg))
    assert t.matrix[:, 2] == pytest.approx([60.0, 25.0], abs=0.5) and t.inliers >= 15
    assert priors[1].initialised and priors[1].state[:2] == pytest.approx([300.0, 245.0], abs=1.0)
    bad = CameraMotionMsg(valid=True, matrix=np.eye(2, 3), inliers=5, tracked=3)
    with pytest.raises(Exception, match="inliers"):
        validate(decode(bad.encode(), CameraMotionMsg))


# --- issue 22: screen-fixed content, failed fits, the fit's uncertainty -------------------------------------


def with_overlay(img: np.ndarray) -> np.ndarray:
    """Screen-fixed content full of corners (a checker strip at the bottom, a block at the top left)."""
    out = img.copy()
    for x in range(0, W, 16):
        for y in range(H - 48, H, 16):
            out[y:y + 16, x:x + 16] = 255 if (x + y) // 16 % 2 else 0
    for x in range(0, 160, 12):
        for y in range(0, 60, 12):
            out[y:y + 12, x:x + 12] = 255 if (x + y) // 12 % 2 else 0
    return out


def panning_frames(n: int, step_px: float) -> list[np.ndarray]:
    base = textured(3)
    return [with_overlay(warp(base, similarity(0.0, 1.0, -step_px * k, 0.0))) for k in range(n)]


def run(frames: list[np.ndarray], params: EgoMotionParams | None = None) -> tuple[list, EgoMotionEstimator]:
    est = EgoMotionEstimator(params)
    return [est.step(f, None, (k + 1) * 33_000_000) for k, f in enumerate(frames)], est


def test_screen_fixed_content_is_learnt_and_left_out() -> None:
    motions, est = run(panning_frames(8, 10.0))
    shifts = [None if m is None else float(m.matrix[0, 2]) for m in motions[1:]]
    assert all(s is not None and abs(s + 10.0) < 0.6 for s in shifts[3:]), shifts
    assert est.static_map.max() >= est.params.static_evidence_min  # the overlay's cells are known
    assert motions[-1].static_cells > 0


def test_a_failed_fit_keeps_the_reference_so_the_next_motion_spans_it() -> None:
    base = textured(4)
    blank = np.full_like(base, 128)  # a smeared frame: nothing to follow
    frames = [base, warp(base, similarity(0, 1, 5, 0)), blank, warp(base, similarity(0, 1, 5, 40))]
    motions, est = run(frames)
    assert motions[2] is None and est.counts["transform"] == 2
    m = motions[3]
    assert m is not None and m.from_stamp_ns == 2 * 33_000_000  # from the last fitted frame, across the blank one
    np.testing.assert_allclose(m.matrix[:, 2], (0.0, 40.0), atol=0.6)


def test_a_rival_hypothesis_raises_the_published_uncertainty() -> None:
    motions, _ = run(panning_frames(3, 10.0), EgoMotionParams(static_evidence=False))
    m = motions[1]
    assert m is not None and m.rival_inliers > 0 and m.rival_px > 5.0 and m.std_px > 1.0
    clean, _ = run([textured(3), warp(textured(3), similarity(0, 1, -10, 0))])
    assert clean[1] is not None and clean[1].std_px < 0.5 and clean[1].rival_inliers == 0


def _prior_after(motion: CameraMotion, coasting: bool, params: KalmanParams | None = None):
    from followbus.tracking.reid import TrackState, measurement

    pred = Predictor(params or KalmanParams(image_motion_model=False))  # the scene model's warp alone
    pred.apply(measurement(0, TrackState.TRACKING, accepted=True, init_box=(300, 200, 40, 100)))
    if coasting:
        pred.apply(measurement(33_000_000, TrackState.OCCLUDED))
        pred.predict(33_000_000)
    start = pred.kf.x[:2].copy()
    prior = pred.predict(66_000_000 if coasting else 33_000_000, camera_motion=motion)
    return prior, start


def _motion(tx: float, std: float, from_t: int, t: int) -> CameraMotion:
    return _motion_of(np.array([[1.0, 0, tx], [0, 1.0, 0]]), from_t, t, std_px=std)


def _motion_of(matrix: np.ndarray, from_t: int, t: int, std_px: float = 0.0) -> CameraMotion:
    """A valid camera motion from stamp ``from_t`` to ``t`` (50 of 60 corners agree)."""
    motion = CameraMotion(valid=True, matrix=matrix, inliers=50, tracked=60, from_stamp_ns=from_t, std_px=std_px)
    motion.header.stamp_ns = t
    return motion


def test_a_doubtful_motion_widens_a_coasting_prior_instead_of_dragging_it() -> None:
    sure, start = _prior_after(_motion(30.0, 0.5, 33_000_000, 66_000_000), coasting=True)
    doubt, _ = _prior_after(_motion(30.0, 12.0, 33_000_000, 66_000_000), coasting=True)
    assert sure.centre[0] == pytest.approx(start[0] + 30.0, abs=1e-6)
    assert doubt.centre[0] == pytest.approx(start[0], abs=1e-6)  # not dragged
    assert doubt.innovation_cov[0, 0] > sure.innovation_cov[0, 0] + 30.0**2  # the gate covers both
    off, _ = _prior_after(_motion(30.0, 12.0, 33_000_000, 66_000_000), coasting=True,
                          params=KalmanParams(camera_motion_uncertainty=False, image_motion_model=False))
    assert off.centre[0] == pytest.approx(start[0] + 30.0, abs=1e-6)  # the ablation moves it with confidence


def test_a_motion_spanning_a_frame_without_one_is_applied() -> None:
    from followbus.tracking.reid import TrackState, measurement

    pred = Predictor(KalmanParams(image_motion_model=False))  # the scene model's warp alone
    pred.apply(measurement(0, TrackState.TRACKING, accepted=True, init_box=(300, 200, 40, 100)))
    pred.predict(33_000_000)  # the jerk's frame: no motion came
    pred.apply(measurement(33_000_000, TrackState.OCCLUDED))
    prior = pred.predict(66_000_000, camera_motion=_motion_of(np.array([[1.0, 0, 0], [0, 1.0, 45.0]]), 0, 66_000_000))
    assert prior.centre[1] == pytest.approx(250.0 + 45.0, abs=1e-6) and pred.motion_mismatched == 0


def test_measure_then_advance_is_step_and_measure_alone_keeps_the_reference() -> None:
    """The node publishes between measure() and advance(): the split must not change a motion."""
    base = textured(4)
    blank = np.full_like(base, 128)
    frames = [*panning_frames(4, 10.0), blank, warp(base, similarity(0, 1, 5, 40))]
    stepped, _ = run(frames)
    est = EgoMotionEstimator()
    split = []
    for k, f in enumerate(frames):
        split.append(est.measure(f, None, (k + 1) * 33_000_000))
        est.advance()
    for a, b in zip(stepped, split, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a.matrix, b.matrix)
    est = EgoMotionEstimator()
    est.step(base, None, 33_000_000)
    first = est.measure(warp(base, similarity(0, 1, 5, 0)), None, 66_000_000)
    again = est.measure(warp(base, similarity(0, 1, 5, 0)), None, 99_000_000)  # no advance in between
    assert first is not None and again is not None and again.from_stamp_ns == first.from_stamp_ns == 33_000_000


@pytest.mark.parametrize("early", [0, 1])
def test_prepared_frames_give_the_same_motions(early: int) -> None:
    """prepare() on a frame's arrival (the node, before its boxes) changes no motion: also when the next frame
    arrives before this one is measured (early=1: its preparation follows a reference that is then replaced)."""
    base = textured(4)
    frames = [*panning_frames(5, 10.0), np.full_like(base, 128), warp(base, similarity(0, 1, 5, 40))]
    plain, _ = run(frames)
    est = EgoMotionEstimator()
    stamps = [(k + 1) * 33_000_000 for k in range(len(frames))]
    prepared = []
    for k, f in enumerate(frames):
        est.prepare(f, stamps[k])
        if early and k + 1 < len(frames):
            est.prepare(frames[k + 1], stamps[k + 1])
        prepared.append(est.measure(f, None, stamps[k]))
        est.advance()
    for a, b in zip(plain, prepared, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a.matrix, b.matrix)
            assert a.inliers == b.inliers and a.std_px == b.std_px
