"""Synthetic scenes: determinism, ground truth vs rendered pixels, scene-specific properties."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest

from followbus.vision.detectors import SimulatedDetector, best_iou
from followbus.vision.scenes import (
    SCENES,
    SceneFrame,
    hidden_ranges,
    make_scene,
    render_figure,
    torso_region,
)


def _first(name: str, n: int, seed: int = 0) -> list[SceneFrame]:
    return list(itertools.islice(make_scene(name, seed=seed).frames(), n))


def _torso_mean(frame: SceneFrame) -> np.ndarray:
    x0, y0, x1, y1 = torso_region(frame.target_box)
    return frame.bgr[y0:y1, x0:x1].reshape(-1, 3).mean(axis=0)


def test_catalogue_is_complete_and_unknown_names_fail() -> None:
    assert set(SCENES) == {"corridor-occlusion", "lookalike", "wall-occlusion", "night-puddles", "sun-shadow",
                           "ego-motion", "lost-target", "group-walk", "overlay", "bumpy", "runners", "shaky"}
    assert make_scene("corridor-occlusion").n_frames == 600
    assert make_scene("wall-occlusion").n_frames == 240
    assert make_scene("wall-occlusion", fps=10).n_frames == 80
    with pytest.raises(ValueError, match="corridor-occlusion"):
        make_scene("no-such-scene")


def test_deterministic_for_a_seed() -> None:
    a, b = _first("lookalike", 8, seed=3), _first("lookalike", 8, seed=3)
    for fa, fb in zip(a, b, strict=True):
        assert np.array_equal(fa.bgr, fb.bgr)
        assert fa.target_box == fb.target_box and fa.distractor_boxes == fb.distractor_boxes
        assert fa.t_ns == fb.t_ns
    c = _first("lookalike", 8, seed=4)
    assert not np.array_equal(a[5].bgr, c[5].bgr)  # texture and noise follow the seed...
    ta, tc = a[5].target_box, c[5].target_box  # ...trajectories do not (gait bob only moves the head top)
    assert (ta[0], ta[1] + ta[3]) == (tc[0], tc[1] + tc[3])
    assert [f.t_ns for f in a[:3]] == [0, round(1e9 / 30), round(2e9 / 30)]
    # Sensor noise is fresh every frame: consecutive frames of a static region differ a little.
    diff = np.abs(a[1].bgr[:40].astype(int) - a[2].bgr[:40].astype(int))
    assert 0.5 < diff.mean() < 6


def test_ground_truth_box_matches_rendered_figure() -> None:
    scene = make_scene("corridor-occlusion")
    frame = next(iter(scene.frames()))
    shirt = np.array(scene.target_style.shirt_bgr, float)
    assert np.abs(_torso_mean(frame) - shirt).max() < 15
    x, y, w, h = (int(v) for v in frame.target_box)
    # Just outside the box (left strip, torso height) there is no shirt colour.
    outside = frame.bgr[y + h // 4 : y + h // 2, max(0, x - 12) : x - 2].reshape(-1, 3).astype(float)
    assert np.abs(outside - shirt).max(axis=1).min() > 40
    # Head top and feet: hair at the top-centre, shoes at the bottom, floor just below.
    assert frame.bgr[y + 2, x + w // 2].max() < 90
    assert frame.bgr[min(y + h + 3, 479), x + w // 2].mean() > 90


@pytest.mark.parametrize("h_px", [20, 90, 300])
def test_figure_fills_its_box_exactly(h_px: int) -> None:
    w_px = round(0.36 * h_px)
    for phase, lateral in itertools.product(np.linspace(0, 2 * math.pi, 7), (0.0, 1.0)):
        _, mask = render_figure(h_px, w_px, make_scene("wall-occlusion").target_style, phase, lateral)
        ys, xs = np.nonzero(mask)
        assert (ys.min(), ys.max(), xs.min(), xs.max()) == (0, h_px - 1, 0, w_px - 1)


def test_wall_occlusion_hides_then_reveals_target() -> None:
    frames = list(make_scene("wall-occlusion").frames())
    ranges = hidden_ranges(frames)
    assert len(ranges) == 1
    start, end = ranges[0]
    assert 30 <= end - start + 1 <= 50  # ~1.0-1.7 s fully hidden at 30 fps
    assert all(f.target_box is not None for f in frames[end + 1 : end + 30])
    assert frames[start - 1].target_visible_fraction < 0.2  # fades out behind the wall edge
    assert frames[0].target_visible_fraction == 1.0
    assert any(0.3 < f.target_visible_fraction < 0.9 for f in frames[end + 1 : end + 30])


def test_corridor_occlusion_demo_scene() -> None:
    frames = list(make_scene("corridor-occlusion").frames())
    (start, end), *rest = hidden_ranges(frames)
    assert not rest
    assert 1.2 <= (end - start + 1) / 30 <= 1.8
    heights = [f.target_box[3] for f in frames if f.target_box is not None]
    assert heights[-1] < 0.6 * heights[0]  # walks away
    assert any(f.distractor_boxes for f in frames)
    passer = next(f for f in frames if f.distractor_boxes and f.distractor_boxes[0][3] > 100)
    x0, y0, x1, y1 = torso_region(passer.distractor_boxes[0])
    passer_shirt = passer.bgr[y0:y1, x0:x1].reshape(-1, 3).mean(axis=0)
    assert np.abs(passer_shirt - np.array(make_scene("corridor-occlusion").target_style.shirt_bgr)).max() > 60


def test_lookalike_distractor_is_similar_and_close() -> None:
    frames = list(make_scene("lookalike").frames())
    both = [f for f in frames if f.distractor_boxes]
    assert len(both) > 0.9 * len(frames)
    t_shirt = _torso_mean(both[-1])
    x0, y0, x1, y1 = torso_region(both[-1].distractor_boxes[0])
    d_shirt = both[-1].bgr[y0:y1, x0:x1].reshape(-1, 3).mean(axis=0)
    assert np.abs(t_shirt - d_shirt).max() < 30  # dressed alike
    gaps = [abs((f.target_box[0] + f.target_box[2] / 2) - (d[0] + d[2] / 2)) for f in both
            for d in f.distractor_boxes]
    assert min(gaps) < 10  # crosses right behind the target...
    crossing = both[int(np.argmin(gaps))]
    assert crossing.distractor_visible_fractions[0] < 0.3  # ...which hides most of it
    assert crossing.target_visible_fraction > 0.99


def test_night_puddles_has_specular_pixels_and_is_dark() -> None:
    frames = _first("night-puddles", 60)
    for f in frames[::20]:
        hsv = cv2.cvtColor(f.bgr, cv2.COLOR_BGR2HSV)
        specular = (hsv[..., 2] > 220) & (hsv[..., 1] < 45)
        assert specular.sum() > 2000
        assert np.median(hsv[..., 2]) < 70  # a night scene
        x, y, w, h = (int(v) for v in f.target_box)
        # The person walks over the puddles: specular pixels right around the feet.
        assert specular[y + int(0.8 * h) : y + h + 4, max(0, x - 8) : x + w + 8].any()


def test_sun_shadow_changes_target_brightness_abruptly() -> None:
    frames = list(make_scene("sun-shadow").frames())
    v = np.array([_torso_mean(f).mean() for f in frames])
    steps = v[1:] / v[:-1]
    assert steps.min() < 0.6 and steps.max() > 1.6  # into the shadow and back out, frame to frame
    assert v.min() < 0.55 * v.max()


def test_ego_motion_shifts_whole_image_and_reports_velocity() -> None:
    frames = _first("ego-motion", 60)
    assert all(f.ego_velocity_mps[0] > 0 for f in frames)
    assert max(abs(f.ego_velocity_mps[1]) for f in frames) > 0.1
    offsets = np.array([f.camera_offset_px for f in frames])
    assert np.ptp(offsets[:, 0]) > 15
    # The static corridor really moves in the image: large background differences.
    a, b = frames[10].bgr, frames[50].bgr
    assert np.abs(a[:60].astype(int) - b[:60].astype(int)).mean() > 8
    assert all(f.target_box is not None for f in frames)
    still = _first("wall-occlusion", 3)
    assert all(f.ego_velocity_mps == (0.0, 0.0) for f in still)


def test_lost_target_never_returns() -> None:
    frames = list(make_scene("lost-target").frames())
    ranges = hidden_ranges(frames)
    assert len(ranges) == 1 and ranges[0][1] == len(frames) - 1
    assert ranges[0][0] < len(frames) // 2
    assert frames[0].target_box is not None


def test_people_feed_the_simulated_detector() -> None:
    det = SimulatedDetector(noise_px=2.0, miss_rate=0.0, false_positive_rate=0.0, seed=1)
    for f in _first("lookalike", 5):
        dets = det.detect(f.bgr, f.people())
        assert len(dets) == 1 + len(f.distractor_boxes)
        assert best_iou(dets, f.target_box) > 0.8


def test_group_walk_ground_truth_and_the_hidden_member() -> None:
    """group-walk: the ground truth is the members' floor positions (a level camera 1.1 m up sees each one's
    feet at row cy + f·1.1/forward), the centre their mean; member 5 is hidden ~6.5-11 s, the others never."""
    scene = make_scene("group-walk", fps=10)
    assert scene.target_style is not None and make_scene("wall-occlusion").group_truth_m(1.0) is None
    cam = scene.camera
    hidden = []
    for f in scene.frames():
        centre, members = scene.group_truth_m(f.t_ns * 1e-9)
        assert members.shape == (5, 2) and np.allclose(centre, members.mean(axis=0))
        # Boxes are clipped to the image; the first four are members 1-4 (sorted by actor), all in view.
        feet = sorted(b[1] + b[3] for b in f.distractor_boxes[:4])
        expected = sorted(cam.cy + cam.f_px * cam.height_m / members[:4, 0])
        assert np.allclose(feet, expected, atol=2.0)
        vis = f.distractor_visible_fractions
        assert min(vis[:4]) > 0.8
        if len(vis) < 5 or vis[4] < 0.3:
            hidden.append(f.t_ns * 1e-9)
    assert hidden and 6.0 < min(hidden) < 7.0 and 10.5 < max(hidden) < 12.0, (min(hidden), max(hidden))
    assert 0.5 * len(hidden) / 10 < max(hidden) - min(hidden) < 1.1 * len(hidden) / 10  # one contiguous stretch


def test_overlay_stays_put_while_the_scene_pans() -> None:
    frames = [f for _, f in zip(range(6), make_scene("overlay").frames(), strict=False)]
    a, b = frames[1], frames[5]
    assert abs(b.camera_offset_px[0] - a.camera_offset_px[0]) > 40  # the scene moved
    strip = slice(455, 480)  # the robot's body strip, drawn after the pan
    diff = np.abs(a.bgr[strip].astype(int) - b.bgr[strip].astype(int)).mean()
    assert diff < 4.0  # only sensor noise
    clock = np.abs(a.bgr[:44, 40:200].astype(int) - b.bgr[:44, 40:200].astype(int)).mean()
    assert 0.5 < clock < 40  # the digits change, their place does not


def test_bumpy_jerk_frames_are_smeared_and_undetectable() -> None:
    from followbus.vision.scenes import BUMPS

    frames = [f for _, f in zip(range(40), make_scene("bumpy").frames(), strict=False)]
    jerk = next(f for f in frames if f.motion_blur_px > 0)
    assert jerk.index == round(BUMPS[0][0] * 30)
    before = frames[jerk.index - 1]
    shift = np.subtract(jerk.camera_offset_px, before.camera_offset_px)
    assert 40 <= float(np.hypot(*shift)) <= 60
    assert jerk.target_box is not None and jerk.target_visible_fraction < 0.3  # below the simulated detector's floor
    assert all(v < 0.3 for v in jerk.distractor_visible_fractions)
    assert frames[jerk.index + 1].motion_blur_px == 0 and frames[jerk.index + 1].target_visible_fraction > 0.9
