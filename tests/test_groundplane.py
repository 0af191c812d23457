"""Ground-plane projection of detections (tracking/groundplane.py): a known camera gives known points."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.tracking.groundplane import (
    CameraGeometry,
    GroundPlaneParams,
    boxes_to_ground,
    floor_to_image,
    to_odometry_frame,
    to_robot_frame,
)


def _box_at(cam: CameraGeometry, forward_m: float, left_m: float, height_m: float = 1.7) -> list[float]:
    """The box a level camera sees of a person standing at (forward, left): the scenes' projection."""
    f = cam.focal_px
    bottom = cam.cy_px + f * cam.camera_height_m / forward_m
    top = cam.cy_px - f * (height_m - cam.camera_height_m) / forward_m
    h = bottom - top
    w = 0.36 * h
    u = cam.cx_px - f * left_m / forward_m
    return [u - w / 2, top, w, h, 0.9]


def test_level_camera_gives_the_true_positions():
    cam = CameraGeometry()
    truth = [(2.5, 0.0), (4.0, 1.2), (6.0, -2.0), (10.0, 0.5)]
    out = boxes_to_ground(np.array([_box_at(cam, *p) for p in truth]), cam, GroundPlaneParams())
    np.testing.assert_allclose(out.points_robot_m, truth, atol=1e-9)  # every box gives a point, in order
    # Range uncertainty grows with range (∝ range² for a monocular camera) and covariances are SPD.
    var_fwd = out.covs_m2[:, 0, 0]
    assert np.all(np.diff(var_fwd[[0, 1, 3]]) > 0)
    assert np.all(np.linalg.eigvalsh(out.covs_m2) > 0)


def test_tilted_camera():
    """A camera pitched down 10° at 1.2 m sees the floor point 3 m ahead at row cy + f·tan(atan(1.2/3) − 10°)."""
    tilt = math.radians(10)
    cam = CameraGeometry(focal_px=500, cx_px=320, cy_px=240, camera_height_m=1.2, camera_tilt_rad=tilt)
    v = 240 + 500 * math.tan(math.atan2(1.2, 3.0) - tilt)
    out = boxes_to_ground(np.array([[300.0, v - 100, 40.0, 100.0, 0.8]]), cam, GroundPlaneParams())
    assert out.points_robot_m[0, 0] == pytest.approx(3.0, abs=1e-9)
    # u = 320 (box centre) is straight ahead.
    assert out.points_robot_m[0, 1] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("tilt_deg", [0.0, 12.0])
def test_floor_to_image_inverts_the_foot_projection(tilt_deg):
    """The web view draws floor shapes into the video: a floor point goes to the pixel whose foot row and
    column project back onto it; a point behind the camera has no pixel."""
    cam = CameraGeometry(focal_px=500, cx_px=320, cy_px=200, camera_height_m=1.2,
                         camera_tilt_rad=math.radians(tilt_deg), camera_forward_m=0.3)
    floor = np.array([[2.5, 0.4], [4.0, -1.1], [9.0, 2.0]])
    uv = floor_to_image(floor, cam)
    boxes = np.array([[u - 20, v - 120, 40.0, 120.0, 0.9] for u, v in uv])  # foot at (u, v)
    np.testing.assert_allclose(boxes_to_ground(boxes, cam, GroundPlaneParams()).points_robot_m, floor, atol=1e-9)
    assert np.isnan(floor_to_image(np.array([[-1.0, 0.0]]), cam)).all()


def test_width_based_range_is_seed_001_eq_1():
    cam = CameraGeometry(focal_px=500)
    params = GroundPlaneParams(range_from="width", person_width_m=0.45)
    # 0.45 m wide at 2 m: 112.5 px (control/kinematics' example); centred 100 px left of cx.
    out = boxes_to_ground(np.array([[320 - 100 - 56.25, 100, 112.5, 300, 0.9]]), cam, params)
    assert out.points_robot_m[0, 0] == pytest.approx(2.0)
    assert out.points_robot_m[0, 1] == pytest.approx(2.0 * 100 / 500)


def test_unusable_boxes_are_dropped():
    cam = CameraGeometry()
    boxes = np.array([
        _box_at(cam, 3.0, 0.0),
        [300, 10, 20, 150, 0.9],          # bottom above the horizon (row 192)
        [300, 300, 60, 180, 0.9],         # feet cut off by the image bottom
        [300, 200, 20, 60, 0.1],          # too weak
        [np.nan, 200, 20, 60, 0.9],       # bad input
        _box_at(cam, 30.0, 0.0),          # farther than max_range_m
    ])
    out = boxes_to_ground(boxes, cam, GroundPlaneParams())
    np.testing.assert_allclose(out.points_robot_m, [[3.0, 0.0]], atol=1e-9)  # the first box alone


def test_odometry_frame_round_trip_and_covariance_rotation():
    pts = np.array([[2.0, 0.0], [3.0, 1.0]])
    covs = np.array([np.diag([0.4, 0.01])] * 2)
    odom, odom_covs = to_odometry_frame(pts, covs, 1.0, 2.0, math.pi / 2)
    # Facing +y from (1, 2): 2 m ahead is (1, 4); 3 m ahead, 1 m left is (0, 5).
    np.testing.assert_allclose(odom, [[1.0, 4.0], [0.0, 5.0]], atol=1e-12)
    # The range uncertainty (robot x) now lies along the odometry y axis.
    np.testing.assert_allclose(odom_covs[0], np.diag([0.01, 0.4]), atol=1e-12)
    np.testing.assert_allclose(to_robot_frame(odom, 1.0, 2.0, math.pi / 2), pts, atol=1e-12)


def test_bad_geometry_is_rejected():
    with pytest.raises(ValueError, match="focal_px"):
        CameraGeometry(focal_px=0)
    with pytest.raises(ValueError, match="range_from"):
        GroundPlaneParams(range_from="sonar")


def test_scene_group_walk_through_ground_plane_and_group_trackers():
    """The pure chain graph.group.yaml runs (simulated detector -> ground points -> group tracker) on
    scene:group-walk: the multi-ellipse tracker keeps the group's centre within 0.4 m of the truth all along
    (member 5 hidden, the passer-by beside them); the shapeless CGT takes the passer-by in and the mean of
    the detected positions is pulled further still."""
    import time

    from followbus.tracking.group import CentroidGroupTracker, MeanPositionTracker, MultiEllipseGroupTracker
    from followbus.vision.detectors import SimulatedDetector
    from followbus.vision.scenes import make_scene

    scene = make_scene("group-walk")
    frames = [(f.t_ns, f.bgr, f.people()) for f in scene.frames()]
    cam, params = CameraGeometry(), GroundPlaneParams()
    worst = []
    for tracker in (MultiEllipseGroupTracker(), CentroidGroupTracker(), MeanPositionTracker()):
        det = SimulatedDetector(seed=0)
        errors, cost_ms = [], []
        for t_ns, bgr, people in frames:
            ground = boxes_to_ground(np.asarray(det.detect(bgr, people)).reshape(-1, 5), cam, params)
            t0 = time.perf_counter()
            est = tracker.step(t_ns * 1e-9, ground.points_m, ground.covs_m2)
            cost_ms.append((time.perf_counter() - t0) * 1e3)
            assert est.valid
            errors.append(float(np.linalg.norm(est.centre_m - scene.group_truth_m(t_ns * 1e-9)[0])))
        worst.append(max(errors))
        print(f"{type(tracker).__name__}: centre error median {np.median(errors):.3f} m, worst {max(errors):.3f} m; "
              f"{np.mean(cost_ms):.2f} ms/frame mean, {np.percentile(cost_ms, 99):.2f} p99")
    me, cgt, mean = worst
    assert me < 0.4 and me < cgt and me < mean, worst


@pytest.mark.parametrize("detector_seed", [0, 3])
def test_group_tracker_keeps_a_passer_by_out_when_frames_are_skipped(detector_seed):
    """A loaded machine's detector delivers every second frame: the passer-by walking 1.4 m beside the group's
    outer member stays out (with the χ²₂ 99 % gate, one noisy range let it in and the shape stretched to keep
    it: 0.7 m of centre error for the rest of the walk, seen in a CI run of tests/test_graph_group.py)."""
    from followbus.tracking.group import MultiEllipseGroupTracker
    from followbus.vision.detectors import SimulatedDetector
    from followbus.vision.scenes import make_scene

    scene = make_scene("group-walk")
    cam, params = CameraGeometry(), GroundPlaneParams()
    tracker, det = MultiEllipseGroupTracker(), SimulatedDetector(seed=detector_seed)
    errors = []
    for k, frame in enumerate(scene.frames()):
        if k % 2:
            continue
        if k > 420:
            break
        ground = boxes_to_ground(np.asarray(det.detect(frame.bgr, frame.people())).reshape(-1, 5), cam, params)
        est = tracker.step(frame.t_ns * 1e-9, ground.points_m, ground.covs_m2)
        errors.append(float(np.linalg.norm(est.centre_m - scene.group_truth_m(frame.t_ns * 1e-9)[0])))
    assert max(errors) < 0.4, (np.argmax(errors) * 2, max(errors))
