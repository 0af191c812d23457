"""Appearance model of seed 000: H-S histogram, Eq. 1, Eq. 9, Eq. 10."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.tracking.appearance import bhattacharyya, hs_histogram, learning_rate, specular_penalty

RED = (0, 0, 255)  # BGR → H = 0, S = 255


def test_hs_histogram_shape_sum_and_red_bin() -> None:
    img = np.zeros((40, 60, 3), np.uint8)
    img[10:30, 20:40] = RED
    hist = hs_histogram(img, (20.0, 10.0, 20.0, 20.0), 16, 8)
    assert hist.shape == (16, 8)
    assert hist.dtype == np.float32
    assert float(hist.sum()) == pytest.approx(1.0, abs=1e-6)
    assert hist[0, 7] == pytest.approx(1.0)  # hue bin 0, top saturation bin


def test_hs_histogram_clips_box_and_handles_empty() -> None:
    img = np.zeros((40, 60, 3), np.uint8)
    img[:, 50:] = (255, 0, 0)  # blue: H = 120 → bin 10 of 16
    hist = hs_histogram(img, (50.0, -10.0, 30.0, 100.0))  # mostly outside the frame
    assert hist[10, 7] == pytest.approx(1.0)
    empty = hs_histogram(img, (100.0, 100.0, 10.0, 10.0))
    assert float(empty.sum()) == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(empty, 1.0 / 128.0)


def test_bhattacharyya_identical_disjoint_and_known_pair() -> None:
    rng_free = np.arange(128, dtype=np.float64) + 1.0
    p = (rng_free / rng_free.sum()).reshape(16, 8)
    assert bhattacharyya(p, p) == pytest.approx(1.0)
    a = np.zeros(128)
    b = np.zeros(128)
    a[:64] = 1.0 / 64
    b[64:] = 1.0 / 64
    assert bhattacharyya(a, b) == 0.0
    p = np.zeros(128)
    q = np.zeros(128)
    p[:2] = [0.5, 0.5]
    q[:2] = [0.25, 0.75]
    # sqrt(0.5·0.25) + sqrt(0.5·0.75) = 0.353553 + 0.612372
    assert bhattacharyya(p, q) == pytest.approx(math.sqrt(0.125) + math.sqrt(0.375))
    assert bhattacharyya(p, q) == pytest.approx(0.965926, abs=1e-6)
    with pytest.raises(ValueError):
        bhattacharyya(np.ones(4), np.ones(5))


def test_specular_penalty_known_fraction() -> None:
    img = np.zeros((20, 20, 3), np.uint8)
    img[:] = (30, 30, 200)  # saturated red: not specular
    img[:5, :] = (255, 255, 255)  # V = 255 > 220, S = 0 < 45: specular, 25 % of the ROI
    img[5:7, :] = (230, 230, 230)  # V = 230, S = 0: specular, another 10 %
    img[7:9, :] = (210, 210, 210)  # V = 210 ≤ 220: not specular
    img[9:11, :] = (120, 200, 255)  # V = 255 but S = 135 ≥ 45: not specular
    p = specular_penalty(img, (0.0, 0.0, 20.0, 20.0), 220, 45)
    assert p == pytest.approx(0.35)
    assert specular_penalty(img, (0.0, 0.0, 20.0, 5.0)) == pytest.approx(1.0)
    assert specular_penalty(img, (0.0, 15.0, 20.0, 5.0)) == 0.0


def test_learning_rate_eq10() -> None:
    assert learning_rate(0.0, False, 0.02, 10.0) == 0.0
    assert learning_rate(0.3, False, 0.02, 10.0) == 0.0
    assert learning_rate(0.0, True, 0.02, 10.0) == pytest.approx(0.02)
    assert learning_rate(0.25, True, 0.02, 10.0) == pytest.approx(0.02 * math.exp(-2.5))
    etas = [learning_rate(p, True, 0.02, 10.0) for p in (0.0, 0.05, 0.1, 0.3, 0.6, 1.0)]
    assert all(a > b for a, b in zip(etas, etas[1:], strict=False))
    assert etas[-1] < 1e-5
