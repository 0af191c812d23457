"""Seed 004's group tracker (tracking/group.py): VB update, shape, weight thresholds, Kalman, data selection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.tracking.group import (
    METHODS,
    GroupParams,
    MultiEllipseGroupTracker,
    _weave,
    dbscan,
    digamma,
)


def two_columns(rng: np.random.Generator, centre: np.ndarray, n_per: int = 5) -> np.ndarray:
    """Two clusters 3.6 m apart across the x axis, long along x (std 1.0 m) and thin across (0.3 m)."""
    up = centre + np.array([0.0, 1.8]) + rng.normal(0, [1.0, 0.3], (n_per, 2))
    down = centre + np.array([0.0, -1.8]) + rng.normal(0, [1.0, 0.3], (n_per, 2))
    return np.vstack([up, down])


def test_digamma_matches_known_values() -> None:
    euler = 0.5772156649015329
    assert digamma(1.0) == pytest.approx(-euler, abs=1e-9)
    assert digamma(0.5) == pytest.approx(-euler - 2 * math.log(2), abs=1e-9)
    assert digamma(10.0) == pytest.approx(sum(1 / k for k in range(1, 10)) - euler, abs=1e-9)


def test_dbscan_finds_two_clusters_and_noise() -> None:
    rng = np.random.default_rng(0)
    pts = np.vstack([rng.normal([0, 0], 0.3, (6, 2)), rng.normal([10, 0], 0.3, (5, 2)), [[5.0, 8.0]]])
    labels = dbscan(pts, eps_m=1.5, min_samples=2)
    assert labels[-1] == -1
    assert len(set(labels[:6])) == 1 and len(set(labels[6:11])) == 1 and labels[0] != labels[6]


def test_responsibilities_sum_to_one() -> None:
    rng = np.random.default_rng(1)
    tr = MultiEllipseGroupTracker(GroupParams(n_ellipses=3))
    pts = two_columns(rng, np.zeros(2))
    tr.step(0.0, pts)
    tr._predict(0.1)
    covs = np.broadcast_to(np.eye(2) * 0.04, (len(pts), 2, 2)).copy()
    *_, gamma = tr._vb_update(pts, covs, tr.mu, tr.P, tr.V, tr.nu, tr.alpha)
    assert gamma.shape == (len(pts), tr.n_components)
    assert np.all(gamma >= 0)
    np.testing.assert_allclose(gamma.sum(axis=1), 1.0, atol=1e-12)


def test_shape_converges_on_two_clusters() -> None:
    """Started with 3 ellipses, the shape ends as 2 sub-targets over the two columns, each elongated
    along x like its data (§4.6: 'regardless of the initial number … converges to 2')."""
    rng = np.random.default_rng(2)
    tr = MultiEllipseGroupTracker(GroupParams(n_ellipses=3))
    for k in range(80):
        t = 0.1 * k
        est = tr.step(t, two_columns(rng, np.array([1.2 * t, 0.0])))
    assert tr.n_components == 2
    ys = sorted(float(e.centre_m[1]) for e in est.ellipses)
    assert ys[0] == pytest.approx(-1.8, abs=0.4) and ys[1] == pytest.approx(1.8, abs=0.4)
    for e in est.ellipses:
        w, v = np.linalg.eigh(e.extent_m2)
        assert w[1] > 3 * w[0]                      # elongated
        assert abs(v[0, 1]) > 0.9                   # along x
        assert e.weight == pytest.approx(0.5, abs=0.15)
    assert est.centre_m[1] == pytest.approx(0.0, abs=0.4)


def test_weight_threshold_removes_a_starved_component() -> None:
    """A sub-target that stops receiving points loses its Dirichlet weight (Eq. 25 forgetting) and is
    dropped once under 10 %; the state shrinks with it."""
    rng = np.random.default_rng(3)
    tr = MultiEllipseGroupTracker(GroupParams(n_ellipses=2, early_frames=5))
    pts = two_columns(rng, np.zeros(2))
    tr.step(0.0, pts)
    assert tr.n_components == 2
    dims = len(tr.mu)
    # Only the upper column keeps being seen.
    seen_weights = []
    for k in range(1, 60):
        tr.step(0.1 * k, np.array([0.0, 1.8]) + rng.normal(0, [1.0, 0.3], (5, 2)))
        seen_weights.append(tr.weights().min())
        if tr.n_components == 1:
            break
    assert tr.n_components == 1
    assert len(tr.mu) == dims - 4          # its slot offset η and its weave w went with it
    assert len(seen_weights) > 2 and seen_weights[-2] < seen_weights[0]   # it starved before it went
    assert tr.estimate().centre_m[1] == pytest.approx(1.8, abs=0.4)


def _slots(tr: MultiEllipseGroupTracker) -> np.ndarray:
    """Each sub-target's slot c + η_l: its centre without its current weave w_l."""
    L = tr.n_components
    return np.array([tr._H(l) @ tr.mu - tr.mu[_weave(l, L)] for l in range(L)])


def _centres(tr: MultiEllipseGroupTracker) -> np.ndarray:
    return np.array([tr._H(l) @ tr.mu for l in range(tr.n_components)])


def test_state_centre_is_the_mean_of_the_sub_target_slots() -> None:
    """Eq. 13 with Alg. 1 line 43 as the reference: c in the state is the mean of the sub-targets' slots,
    at initialisation, after updates, and after a sub-target is pruned (the kept ones do not move)."""
    rng = np.random.default_rng(7)
    tr = MultiEllipseGroupTracker(GroupParams(n_ellipses=3, early_frames=5))
    tr.step(0.0, two_columns(rng, np.zeros(2)))
    np.testing.assert_allclose(tr.mu[0:2], _slots(tr).mean(axis=0), atol=1e-9)
    n_before = tr.n_components
    for k in range(1, 60):
        # Only the upper column is seen from now on: the other sub-targets starve and go.
        tr.step(0.1 * k, np.array([0.0, 1.8]) + rng.normal(0, [1.0, 0.3], (5, 2)))
        np.testing.assert_allclose(tr.mu[0:2], _slots(tr).mean(axis=0), atol=1e-9)
        if tr.n_components < n_before:
            break
    assert tr.n_components < n_before
    # Pruning itself moves no kept sub-target: re-basing the same state on the kept ones.
    tr2 = MultiEllipseGroupTracker(GroupParams(n_ellipses=3, early_frames=0))
    tr2.step(0.0, two_columns(rng, np.zeros(2)))
    tr2._predict(0.1)
    tr2.mu[_weave(1, 3)] = [0.2, -0.1]                 # some weave, so the re-basing has to carry it
    centres, slots = _centres(tr2), _slots(tr2)
    tr2.alpha = np.array([1.0, 100.0, 100.0])
    tr2.frames = 100
    tr2._prune()
    assert tr2.n_components == 2
    np.testing.assert_allclose(_centres(tr2), centres[1:], atol=1e-9)
    np.testing.assert_allclose(tr2.mu[0:2], slots[1:].mean(axis=0), atol=1e-9)


def test_a_sub_target_measures_its_centre_once_per_frame() -> None:
    """Persistent members (the q_x step of Eq. 19/23): eight points of one sub-target tell the centre about as
    much as one does, not eight times as much; the centre still goes to their centroid."""
    post_var = {}
    for n in (1, 8):
        tr = MultiEllipseGroupTracker(GroupParams(n_ellipses=1))
        tr.step(0.0, np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5], [-0.5, 0.0], [0.0, -0.5]]))
        tr._predict(0.1)
        mu0, P0, V0, nu0, a0 = tr.mu, tr.P, tr.V, tr.nu, tr.alpha
        rng = np.random.default_rng(8)
        pts = np.array([1.0, 0.0]) + rng.normal(0, 0.3, (n, 2))
        covs = np.broadcast_to(np.eye(2) * 0.01, (n, 2, 2)).copy()
        mu, P, *_ = tr._vb_update(pts, covs, mu0, P0, V0, nu0, a0)
        post_var[n] = float(P[0, 0])
        assert mu0[0] < mu[0] < pts[:, 0].mean() + 0.05      # pulled towards the points' centroid
    # With each point an independent draw (X/n) the 8-point variance would be several times smaller.
    assert post_var[8] > 0.6 * post_var[1]


def _swaying_squad(t: float, rng: np.random.Generator) -> np.ndarray:
    """Two sub-groups walking along x at 1.2 m/s, 2.5 m apart; the visible one of the back pair sways 0.5 m
    either side of its place with a 4 s period (the front three are steady)."""
    front = np.array([1.2 * t + 1.5, 0.0]) + np.array([[0.0, -0.8], [0.0, 0.0], [0.0, 0.8]])
    back = np.array([[1.2 * t - 1.0, 0.5 * math.sin(2 * math.pi * t / 4.0)]])
    return np.vstack([front, back]) + rng.normal(0, 0.05, (4, 2))


def _lateral_speed_swing(params: GroupParams) -> float:
    rng = np.random.default_rng(9)
    tr = MultiEllipseGroupTracker(params)
    vy = []
    for k in range(200):
        est = tr.step(0.1 * k, _swaying_squad(0.1 * k, rng))
        if k >= 40:
            vy.append(est.velocity_mps[1])
    return float(np.std(vy))


def test_a_sub_targets_weave_stays_out_of_the_group_velocity() -> None:
    """The weave w_l (Ornstein-Uhlenbeck about the slot) takes up one person's sway; without it (a weave of
    ~0) the sway goes into the shared velocity, i.e. into the heading the robot follows."""
    p = GroupParams(n_ellipses=2)
    with_weave = _lateral_speed_swing(p)
    without = _lateral_speed_swing(GroupParams(**{**p.__dict__, "weave_std_m": 0.0}))
    assert with_weave < 0.6 * without, (with_weave, without)
    assert with_weave < 0.15


def test_a_leaver_is_cut_loose_at_the_group_boundary() -> None:
    """Eq. 5-6 on top of the sub-target gates: a member walking off sideways is dropped once D_th from the
    group centre, and the centre stays with the rest."""
    rng = np.random.default_rng(10)
    tr = MultiEllipseGroupTracker()
    for k in range(105):
        t = 0.1 * k
        group = np.array([1.2 * t, 0.0]) + np.array([[0, -1], [0, 0], [0, 1], [-1.4, -0.6], [-1.4, 0.6]])
        leaver = np.array([[1.2 * t - 1.4, 0.6 + max(0.0, t - 3.0) * 0.8]])    # off to the left from 3 s
        est = tr.step(t, np.vstack([group + rng.normal(0, 0.05, (5, 2)), leaver]))
    # 6 m to the side by now: outside D_th (the sub-target gate alone still held it, and the centre 0.9 m
    # towards it).
    assert not est.selected[5]
    assert abs(est.centre_m[1]) < 0.4, est.centre_m


def test_kalman_follows_a_constant_velocity_centre() -> None:
    rng = np.random.default_rng(4)
    tr = MultiEllipseGroupTracker()
    v = np.array([1.0, 0.5])
    for k in range(100):
        t = 0.1 * k
        est = tr.step(t, v * t + rng.normal(0, 0.8, (8, 2)))
    np.testing.assert_allclose(est.velocity_mps, v, atol=0.2)
    assert np.linalg.norm(est.centre_m - v * 9.9) < 0.5


def test_disturbers_outside_the_region_are_rejected() -> None:
    rng = np.random.default_rng(5)
    tr = MultiEllipseGroupTracker()
    for k in range(40):
        t = 0.1 * k
        group = np.array([1.2 * t, 0.0]) + rng.normal(0, 0.7, (7, 2))
        # Two non-members walking parallel 7 m to each side, one obstacle far ahead.
        others = np.array([[1.2 * t, 7.0], [1.2 * t + 1, -7.0], [30.0, 0.0]])
        est = tr.step(t, np.vstack([group, others]))
    assert est.selected[:7].sum() >= 6
    assert not est.selected[7:].any()
    assert abs(est.centre_m[1]) < 0.5


def test_bad_points_are_dropped_not_propagated() -> None:
    tr = MultiEllipseGroupTracker()
    rng = np.random.default_rng(6)
    tr.step(0.0, rng.normal(0, 0.7, (6, 2)))
    pts = np.vstack([rng.normal(0, 0.7, (6, 2)), [[math.nan, 1.0]]])
    est = tr.step(0.1, pts)
    assert np.all(np.isfinite(est.centre_m)) and np.all(np.isfinite(tr.mu))


@pytest.mark.parametrize("name", list(METHODS))
def test_every_method_has_the_same_api(name: str) -> None:
    rng = np.random.default_rng(7)
    tr = METHODS[name]()
    est = None
    for k in range(20):
        t = 0.1 * k
        est = tr.step(t, np.array([1.2 * t, 0.0]) + rng.normal(0, 0.7, (7, 2)),
                      np.broadcast_to(np.eye(2) * 0.04, (7, 2, 2)))
    assert est is not None and est.valid
    assert np.linalg.norm(est.centre_m - [1.2 * 1.9, 0.0]) < 1.5
    assert math.isfinite(est.heading_rad)
