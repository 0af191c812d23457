"""Learned appearance (seed 001): the ridge-regression target classifier, the OSNet descriptor on real people,
re-ID keeping the target among look-alikes on a real sequence, and the loud fallback without the model."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.evaluation.datasets import find_data_root, load_sequence
from followbus.tracking.learned_appearance import IdentityParams, TargetClassifier, load_embedder


def _data(rel: str) -> Path:
    try:
        root = find_data_root()
    except (FileNotFoundError, NotADirectoryError, ValueError) as exc:
        pytest.skip(f"evaluation data unusable: {exc}")
    if root is None or not (root / rel).is_dir():
        pytest.skip(f"{rel} absent (no $FOLLOWBUS_DATA, no ../shared/data)")
    return root / rel


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_ridge_classifier_scores_the_target_high_and_the_others_low():
    rng = np.random.default_rng(0)
    target_dir, other_dir = _unit(rng.normal(size=512)), _unit(rng.normal(size=512))
    clf = TargetClassifier(IdentityParams())
    assert not clf.ready  # nothing learnt: no opinion
    for _ in range(30):
        clf.add(_unit(target_dir + 0.3 * _unit(rng.normal(size=512))),
                _unit(other_dir + 0.3 * _unit(rng.normal(size=(3, 512)))))
    assert clf.ready
    target = _unit(target_dir + 0.3 * _unit(rng.normal(size=(20, 512))))
    others = _unit(other_dir + 0.3 * _unit(rng.normal(size=(20, 512))))
    p = clf.params
    assert (clf.score(target) > p.delta_id).all() and (clf.score(others) < p.delta_switch).all()


def test_sample_set_keeps_the_latest_and_some_history():
    """Seed 001's short-long-term set: the latest samples, plus one in long_term_every of those that left."""
    clf = TargetClassifier(IdentityParams(short_term_samples=4, long_term_samples=3, long_term_every=2))
    for i in range(20):
        clf.add(np.full(512, float(i)), np.zeros((0, 512)))
    short = [int(x[0]) for x in clf.positives.short]
    long = [int(x[0]) for x in clf.positives.long]
    assert short == [16, 17, 18, 19]
    assert len(long) == 3 and max(long) < 16 and len(set(long)) == 3  # older, thinned, not the latest


def test_osnet_descriptor_tells_two_real_people_apart():
    """tud-campus: the same person two frames apart is closer than two people of the same frame."""
    seq = load_sequence(_data("mot/tud-campus"))
    embedder = load_embedder()
    assert embedder is not None, "models/osnet_x0_25_msmt17.onnx ships with the repository"
    frames = {k: cv2.imread(str(seq.image_paths[k])) for k in (0, 4)}
    people0 = dict(seq.all_gt[0])
    people4 = dict(seq.all_gt[4])
    a, b = [pid for pid in people0 if pid in people4][:2]
    e0 = embedder.embed(frames[0], [people0[a], people0[b]])
    e4 = embedder.embed(frames[4], [people4[a]])
    assert e0.shape == (2, 512) and np.allclose(np.linalg.norm(e0, axis=1), 1.0, atol=1e-4)
    same, other = float(e0[0] @ e4[0]), float(e0[0] @ e0[1])
    assert same > other + 0.1, (same, other)


@pytest.mark.slow
def test_learned_appearance_keeps_the_target_when_a_lookalike_walks_out_of_it():
    """otb-human3, frames 0-110 with the real YOLOX-nano 640: around frame 90 a walker in similar dark clothes
    steps out from behind the target; colour and geometry score both alike (S_color 0.93 vs 0.94) and seed 000
    alone follows the walker from frame 94 on. With the learned appearance the output stays on the target."""
    from followbus.evaluation.graph_follower import GraphFollower
    from followbus.vision.detectors import make_detector

    seq = load_sequence(_data("sot/otb-human3"))
    detector = make_detector("yolox", input_size=640)
    follower = GraphFollower()  # the graph's tracking nodes, in-process
    errors = {}
    for k in range(111):
        bgr = cv2.imread(str(seq.image_paths[k]))
        box, _ = follower.step(bgr, detector.detect(bgr), int(k * 1e9 / seq.fps),
                               init_box=seq.gt_boxes[0] if k == 0 else None)
        gt = seq.gt_boxes[k]
        if k >= 85 and gt is not None and box is not None:
            (x, y, w, h), (gx, gy, gw, gh) = box, gt
            errors[k] = float(np.hypot(x + w / 2 - gx - gw / 2, y + h / 2 - gy - gh / 2))
    assert len(errors) >= 24 and np.mean([e < 20 for e in errors.values()]) >= 0.9, errors
    assert follower.node("reid").reid.identity_decisions > 0


def test_without_the_model_reid_says_so_and_falls_back_to_colour(monkeypatch, caplog):
    import followbus.vision.models as models

    monkeypatch.setattr(models, "find_model", lambda filename, explicit_dir=None: None)
    with caplog.at_level(logging.WARNING, logger="followbus.tracking.learned_appearance"):
        assert load_embedder() is None
    assert any("learned appearance is off" in r.getMessage() and "osnet_x0_25_msmt17.onnx" in r.getMessage()
               for r in caplog.records), caplog.text


def test_crops_are_the_imagenet_normalised_rgb_of_each_box() -> None:
    """The table lookup gives exactly the float32 arithmetic it replaced: (v / 255 - mean) / std, RGB, CHW."""
    import cv2

    from followbus.tracking.learned_appearance import CROP_H_PX, CROP_W_PX, IMAGENET_MEAN, IMAGENET_STD, PersonEmbedder

    frame = np.random.default_rng(3).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    boxes = [(10, 20, 40, 100), (200.5, 50.2, 33, 90), (300, 100, 60, 160), (-5, -5, 8, 8)]
    crops = PersonEmbedder.crops(frame, boxes)
    assert crops.shape == (4, 3, CROP_H_PX, CROP_W_PX) and crops.dtype == np.float32
    patch = cv2.resize(frame[20:120, 10:50], (CROP_W_PX, CROP_H_PX), interpolation=cv2.INTER_LINEAR)
    expected = ((patch[:, :, ::-1].astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)
    np.testing.assert_array_equal(crops[0], expected)
