"""Reference model M of seed 000: Eq. 9-10 learning rate and Alg. 1 line 12 update."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from followbus.msgs.tracking import Measurement
from followbus.tracking.appearance import hs_histogram
from followbus.tracking.params import TemplateParams
from followbus.tracking.reid import Candidate, TrackState, measurement
from followbus.tracking.template import TemplateUpdater

BOX = (10.0, 10.0, 20.0, 20.0)


def frame_with(colour: tuple[int, int, int], specular_rows: int = 0) -> np.ndarray:
    img = np.zeros((40, 40, 3), np.uint8)
    img[10:30, 10:30] = colour
    if specular_rows:
        img[10:10 + specular_rows, 10:30] = (255, 255, 255)  # V > 220, S < 45
    return img


def result(frame: np.ndarray, state: TrackState, accepted: bool, secure: bool) -> Measurement:
    return measurement(0, state, Candidate(BOX, "detection", hist=hs_histogram(frame, BOX)), accepted=accepted,
                       secure=secure)


def initialised(params: TemplateParams) -> tuple[TemplateUpdater, np.ndarray]:
    tu = TemplateUpdater(params)
    red = frame_with((0, 0, 255))
    hist, eta, _ = tu.step(red, measurement(0, TrackState.TRACKING, Candidate(BOX, "init"), accepted=True,
                                            init_box=BOX))
    assert hist is not None and eta == 0.0
    return tu, hist


def test_update_follows_alg1_line12() -> None:
    tu, m0 = initialised(TemplateParams())
    blue = frame_with((255, 0, 0))
    m1, eta, p = tu.step(blue, result(blue, TrackState.TRACKING, True, True))
    assert p == 0.0 and eta == pytest.approx(0.02)
    c_star = hs_histogram(blue, BOX)
    np.testing.assert_allclose(m1, 0.98 * m0 + 0.02 * c_star, atol=1e-7)
    assert m1[0, 7] == pytest.approx(0.98)  # red bin
    assert m1[10, 7] == pytest.approx(0.02)  # blue bin
    assert float(m1.sum()) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize(
    ("state", "accepted", "secure"),
    [(TrackState.OCCLUDED, False, False), (TrackState.LOST, False, False),
     (TrackState.REACQUIRED, True, False), (TrackState.TRACKING, True, False)],
)
def test_eta_zero_when_not_secure(state: TrackState, accepted: bool, secure: bool) -> None:
    tu, m0 = initialised(TemplateParams())
    blue = frame_with((255, 0, 0))
    m1, eta, _ = tu.step(blue, result(blue, state, accepted, secure))
    assert eta == 0.0
    np.testing.assert_array_equal(m1, m0)


def test_eta_decreases_with_specular_penalty() -> None:
    etas, ps = [], []
    for rows in (0, 2, 5, 10, 20):
        tu, _ = initialised(TemplateParams())
        frame = frame_with((0, 0, 255), specular_rows=rows)
        _, eta, p = tu.step(frame, result(frame, TrackState.TRACKING, True, True))
        etas.append(eta)
        ps.append(p)
    assert ps == pytest.approx([0.0, 0.1, 0.25, 0.5, 1.0])
    assert etas[2] == pytest.approx(0.02 * math.exp(-10.0 * 0.25))
    assert all(a > b for a, b in zip(etas, etas[1:], strict=False))


def test_ablations() -> None:
    frame = frame_with((0, 0, 255), specular_rows=10)  # P = 0.5
    tu, _ = initialised(TemplateParams(adaptive_eta=False))
    _, eta, p = tu.step(frame, result(frame, TrackState.TRACKING, True, True))
    assert p == pytest.approx(0.5) and eta == pytest.approx(0.02)  # fixed η_base
    tu, m0 = initialised(TemplateParams(suspend_updates=False))
    blue = frame_with((255, 0, 0))
    m1, eta, _ = tu.step(blue, result(blue, TrackState.OCCLUDED, False, False))
    assert eta == pytest.approx(0.02)  # the rejected best candidate is blended in anyway
    assert m1[10, 7] == pytest.approx(0.02)


def test_save_load_roundtrip(tmp_path: Path) -> None:
    tu, _ = initialised(TemplateParams())
    blue = frame_with((255, 0, 0))
    m1, _, _ = tu.step(blue, result(blue, TrackState.TRACKING, True, True))
    path = tmp_path / "template.npz"
    tu.save(path)
    restored = TemplateUpdater(TemplateParams())
    assert not restored.initialised
    np.testing.assert_array_equal(restored.load(path), m1)
    assert restored.initialised
    with pytest.raises(ValueError, match="shape"):
        TemplateUpdater(TemplateParams(bins_h=8)).load(path)
    with pytest.raises(ValueError):
        TemplateUpdater(TemplateParams()).save(tmp_path / "x.npz")


def test_before_initialisation_only_a_secure_lock_teaches_the_target() -> None:
    # A template node restarted without M, while re-ID follows on with the M it sent before: re-ID's secure lock
    # is the target as that M recognised it. Anything less (occluded, accepted but not secure) teaches nothing.
    frame = frame_with((0, 0, 255))
    for state, accepted, secure in [(TrackState.OCCLUDED, False, False), (TrackState.REACQUIRED, True, False)]:
        assert TemplateUpdater(TemplateParams()).step(frame, result(frame, state, accepted, secure)) == (None, 0.0, 0.0)
    tu = TemplateUpdater(TemplateParams())
    hist, eta, _ = tu.step(frame, result(frame, TrackState.TRACKING, True, True))
    assert hist is not None and eta == 0.0 and tu.initialised
    np.testing.assert_allclose(hist, hs_histogram(frame, BOX))


def test_relock_with_existing_template_keeps_it() -> None:
    tu, m0 = initialised(TemplateParams())
    blue = frame_with((255, 0, 0))
    relock = measurement(0, TrackState.TRACKING, Candidate(BOX, "template"), accepted=True, init_box=BOX)
    m1, eta, _ = tu.step(blue, relock)
    np.testing.assert_array_equal(m1, m0)
    fresh = measurement(0, TrackState.TRACKING, Candidate(BOX, "init"), accepted=True, init_box=BOX)
    m2, _, _ = tu.step(blue, fresh)
    assert m2[10, 7] == pytest.approx(1.0)  # a new target restarts the model
