"""Group-target tracking on ground-plane positions (seed 004, ME-CGT-UGV) and its comparison methods.

Everything here works on 2-D points in a fixed odometry frame (metres), one set per frame, each with its
own 2×2 covariance: seed 004 Eq. 4 (robot frame → odometry frame) is done by the caller. Equation numbers
refer to seed 004 (Yu, Li, Wu, Drones 2025, 9, 620):

* Eq. 1-3   single-group task: a selection function h(z) keeps the group's points.
* Eq. 5-7   data selection of the shapeless method (distance to the predicted centre < D_th, weighted
            centroid); used by :class:`CentroidGroupTracker` (CGT-UGV).
* Eq. 8     random-matrix measurement model p(z | x, X) = N(z; Hx, X + R).
* Eq. 9-10  Gaussian motion prior, Inverse-Wishart extent prior.
* Eq. 12    multi-ellipse mixture p(z | x, X^{1:L}, π^{1:L}) = Σ_l π_l N(z; H_l x, X_l + R).
* Eq. 13    state x = [x_c, y_c, ẋ_c, ẏ_c, η_2, …, η_L]: the sub-target offsets ride in the Kalman state;
            c is the mean of the sub-targets' slots (η_1 = −Σ η_l), and the state is extended by a
            mean-reverting weave w_l per sub-target (people sway about their place in the squad).
* Eq. 5-6   the group boundary D_th around the predicted centre also bounds ME-CGT-UGV's selection.
* Eq. 14-21 latent noise-free positions b, responsibilities r, and the mean-field factors q_b, q_r, q_x,
            q_X, q_π updated in turn (variational Bayes, after Tuncer, Orguner & Özkan 2022, seed ref. [34]).
* Eq. 23    Kalman-form update of the motion state.
* Eq. 24-25 temporal propagation: IW forgetting factor λ_IW, Dirichlet forgetting λ_D.
* §4.6      weight thresholds: components under 1 % of the weight are dropped in the first frames, under
            10 % afterwards.
* Alg. 1    group centre = mean of the sub-target centres (weighted here by E[π_l], so a starved
            component cannot pull it).

Pure numpy; no network, no vision. Every tracker has the same API: ``step(t_s, points_m, covs_m2) -> GroupEstimate``
(what the group node publishes of it: :meth:`GroupEstimate.to_message`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from ..msgs.group import GroupState
from .groundplane import to_robot_frame
from .params import check_ranges

log = logging.getLogger(__name__)

D = 2  # ground-plane dimension

# --------------------------------------------------------------------------- small helpers


def _digamma1(x: float) -> float:
    acc = 0.0
    while x < 6.0:
        acc -= 1.0 / x
        x += 1.0
    inv2 = 1.0 / (x * x)
    series = inv2 * (1.0 / 12 - inv2 * (1.0 / 120 - inv2 * (1.0 / 252 - inv2 * (1.0 / 240 - inv2 / 132))))
    return acc + math.log(x) - 0.5 / x - series


def digamma(x: np.ndarray | float) -> np.ndarray:
    """ψ(x) for x > 0 (recurrence up to 6, then the asymptotic series; |error| < 1e-10). numpy has none, and
    the arrays here hold a handful of values, so a scalar loop is the fast way."""
    arr = np.asarray(x, dtype=float)
    return np.array([_digamma1(float(v)) for v in arr.ravel()]).reshape(arr.shape)


def dbscan(points_m: np.ndarray, eps_m: float, min_samples: int) -> np.ndarray:
    """DBSCAN (Ester et al., seed ref. [42], §2.2.1): labels 0..K-1 per point, -1 for noise. O(n²), n is small."""
    pts = np.asarray(points_m, dtype=float).reshape(-1, D)
    n = len(pts)
    labels = np.full(n, -1, dtype=int)
    if n == 0:
        return labels
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    neigh = [np.flatnonzero(dist[i] <= eps_m) for i in range(n)]
    core = np.array([len(nb) >= min_samples for nb in neigh])
    visited = np.zeros(n, dtype=bool)
    k = 0
    for i in range(n):
        if visited[i] or not core[i]:
            continue
        stack = [i]
        visited[i] = True
        while stack:
            j = stack.pop()
            labels[j] = k
            if not core[j]:
                continue  # border point: belongs to the cluster but does not extend it
            for m in neigh[j]:
                if not visited[m]:
                    visited[m] = True
                    stack.append(m)
        k += 1
    return labels


def pick_group(points_m: np.ndarray, eps_m: float, min_samples: int,
               near_m: np.ndarray | None = None) -> np.ndarray:
    """Indices of the group to follow (Alg. 1 line 23, "spatial closeness and size"): the DBSCAN cluster
    with most members, ties to the one nearest ``near_m`` (default the origin). Empty if none."""
    labels = dbscan(points_m, eps_m, min_samples)
    if labels.max(initial=-1) < 0:
        return np.zeros(0, dtype=int)
    ref = np.zeros(D) if near_m is None else np.asarray(near_m, dtype=float)
    best, best_key = -1, None
    for k in range(labels.max() + 1):
        idx = np.flatnonzero(labels == k)
        key = (-len(idx), float(np.linalg.norm(points_m[idx].mean(axis=0) - ref)))
        if best_key is None or key < best_key:
            best, best_key = k, key
    return np.flatnonzero(labels == best)


def kmeans_split(points_m: np.ndarray, n_parts: int, iters: int = 10) -> np.ndarray:
    """Labels splitting a cluster into ``n_parts`` sub-targets (Alg. 1 line 25); farthest-point seeds, so
    it is deterministic."""
    pts = np.asarray(points_m, dtype=float)
    n_parts = max(1, min(n_parts, len(pts)))
    seeds = [int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
    while len(seeds) < n_parts:
        d = np.min(np.linalg.norm(pts[:, None] - pts[seeds][None], axis=-1), axis=1)
        seeds.append(int(np.argmax(d)))
    centres = pts[seeds].copy()
    labels = np.zeros(len(pts), dtype=int)
    for _ in range(iters):
        labels = np.argmin(np.linalg.norm(pts[:, None] - centres[None], axis=-1), axis=1)
        for k in range(n_parts):
            if np.any(labels == k):
                centres[k] = pts[labels == k].mean(axis=0)
    return labels


def cv_transition(dt_s: float) -> np.ndarray:
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt_s
    return F


def cv_process_noise(dt_s: float, accel_std_mps2: float) -> np.ndarray:
    """White-acceleration noise of the constant-velocity model."""
    q = accel_std_mps2 ** 2
    G = np.array([[dt_s ** 2 / 2, 0], [0, dt_s ** 2 / 2], [dt_s, 0], [0, dt_s]])
    return q * G @ G.T


def heading_rad(v_mps: np.ndarray) -> float:
    return math.atan2(float(v_mps[1]), float(v_mps[0]))


# --------------------------------------------------------------------------- outputs


@dataclass
class Ellipse:
    """One sub-target's extent in the odometry frame: centre (m), E[X] (m²) and its mixture weight E[π]."""

    centre_m: np.ndarray
    extent_m2: np.ndarray
    weight: float


@dataclass
class GroupEstimate:
    """What every method outputs each frame. ``valid`` is False before initialisation."""

    valid: bool
    centre_m: np.ndarray = field(default_factory=lambda: np.full(D, math.nan))
    velocity_mps: np.ndarray = field(default_factory=lambda: np.full(D, math.nan))
    orientation_rad: float = math.nan  # main axis of the group's extent (§4.5.3: largest eigenvalue)
    ellipses: list[Ellipse] = field(default_factory=list)
    selected: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # per input point
    lost: bool = False

    @property
    def heading_rad(self) -> float:
        return heading_rad(self.velocity_mps) if self.valid else math.nan

    def is_finite(self) -> bool:
        """Every number of the estimate finite (a diverged tracker gives NaN or inf)."""
        numbers = [self.centre_m, self.velocity_mps, np.array([self.orientation_rad])]
        numbers += [np.concatenate([e.centre_m, e.extent_m2.ravel(), [e.weight]]) for e in self.ellipses]
        return all(np.isfinite(a).all() for a in numbers)

    def to_message(self, points_m: np.ndarray, pose: tuple[float, float, float]) -> GroupState:
        """The estimate as the group node publishes it (the one mapping): the input points it selected and left
        out and, when valid, the group's state, its centre also in the robot frame at robot pose ``pose``."""
        selected = self.selected if len(self.selected) == len(points_m) else np.zeros(len(points_m), dtype=bool)
        out = GroupState(members_m=points_m[selected].reshape(-1, 2), others_m=points_m[~selected].reshape(-1, 2))
        if not self.valid:
            return out
        out.valid, out.lost = True, bool(self.lost)
        out.centre_m = np.asarray(self.centre_m, dtype=np.float64)
        out.velocity_mps = np.asarray(self.velocity_mps, dtype=np.float64)
        out.orientation_rad = float(self.orientation_rad)
        out.centre_robot_m = to_robot_frame(out.centre_m, *pose)[0]
        out.ellipse_centres_m = np.array([e.centre_m for e in self.ellipses], dtype=np.float64).reshape(-1, 2)
        out.ellipse_extents_m2 = np.array([e.extent_m2 for e in self.ellipses], dtype=np.float64).reshape(-1, 2, 2)
        out.ellipse_weights = np.clip(np.array([e.weight for e in self.ellipses], dtype=np.float64), 0, 1)
        return out


def _as_points(points_m: np.ndarray, covs_m2: np.ndarray | None, default_std_m: float
               ) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points_m, dtype=float).reshape(-1, D)
    if covs_m2 is None:
        covs = np.broadcast_to(np.eye(D) * default_std_m ** 2, (len(pts), D, D)).copy()
    else:
        covs = np.asarray(covs_m2, dtype=float).reshape(-1, D, D)
    # Bad input is dropped, not propagated: a NaN would poison every later frame.
    ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(covs), axis=(1, 2))
    return pts[ok], covs[ok]


def _principal_angle(cov: np.ndarray) -> float:
    w, v = np.linalg.eigh(cov)
    a = v[:, int(np.argmax(w))]
    return math.atan2(float(a[1]), float(a[0]))


# --------------------------------------------------------------------------- ME-CGT-UGV


def _state_size(L: int) -> int:
    """[c, ċ] + slot offsets η_2..η_L + a weave w_1..w_L per sub-target."""
    return 4 + 2 * (L - 1) + 2 * L


def _slot(k: int) -> slice:
    """State indices of η_k, k = 2..L (1-based as in Eq. 13; η_1 is not in the state)."""
    return slice(4 + 2 * (k - 2), 6 + 2 * (k - 2))


def _weave(l: int, L: int) -> slice:
    """State indices of sub-target l's weave w_l (0-based l)."""
    return slice(4 + 2 * (L - 1) + 2 * l, 6 + 2 * (L - 1) + 2 * l)


def _sub_target_matrix(l: int, L: int) -> np.ndarray:
    """H_l: sub-target l's centre = c + η_l + w_l in the state of Eq. 13, extended by a weave per sub-target.

    c is the centre of the formation, the mean of the sub-targets' slots (Alg. 1 line 43), so the slot
    offsets sum to zero: η_1 = −(η_2 + … + η_L). With sub-target 1 as the reference instead (η_1 ≡ 0), the
    velocity in the state would be that of the 2-3 people of one ellipse; referenced to the mean, each
    sub-target's own motion is averaged over all L of them.

    w_l is where the sub-target's people are relative to their slot right now: people in a squad sway and
    weave around their place (the S-curves of seed 004 §4.3) and come back to it. Without it, Eq. 13's slow
    random-walk offsets cannot follow a weave, so when occlusion leaves only a few people visible their
    weave goes into the group's shared velocity (the heading swings with the weave), while faster offsets let a
    passing non-member drag its sub-target off. A mean-reverting w_l follows the weave and cannot wander."""
    H = np.zeros((D, _state_size(L)))
    H[:, 0:2] = np.eye(D)
    if l > 0:
        H[:, _slot(l + 1)] = np.eye(D)
    else:
        for k in range(2, L + 1):
            H[:, _slot(k)] = -np.eye(D)
    H[:, _weave(l, L)] = np.eye(D)
    return H


@dataclass
class GroupParams:
    """Tuning of the multi-ellipse tracker (and of RM-CGT-UGV with n_ellipses = 1)."""

    n_ellipses: int = 3                # L at initialisation (§4.6: converges whatever the start)
    dbscan_eps_m: float = 4.5          # neighbourhood radius of the initial clustering (§2.2.1): joins a
                                       # double column 4 m apart (§5.3)
    dbscan_min_samples: int = 2
    accel_std_mps2: float = 0.6        # group-centre process noise (constant-velocity Kalman, §2.2.3)
    offset_std_mps: float = 0.1        # random walk of the sub-target offsets η_l (Eq. 13)
    weave_std_m: float = 0.3           # stationary std of a sub-target's weave about its slot (people sway 0.2-0.5 m)
    weave_tau_s: float = 1.0           # time constant of the weave's return to its slot (Ornstein-Uhlenbeck)
    lambda_iw: float = 0.95            # Eq. 24 forgetting factor of the extents
    lambda_dirichlet: float = 0.95     # Eq. 25 forgetting factor of the weights
    nu_min: float = 8.0                # IW degrees of freedom kept above d+1 so E[X] stays finite
    extent_floor_m2: float = 0.09      # a sub-target is never thinner than a person (0.3 m std) …
    extent_ceiling_m2: float = 2.25    # … nor wider than 1.5 m std: an unbounded extent widens its own gate,
                                       # takes in a passing disturber, widens again
    weight_threshold_early: float = 0.01  # §4.6: 1 % in the initial stage …
    weight_threshold_late: float = 0.10   # … then 10 %
    early_frames: int = 10
    d_th_m: float = 4.0                # Eq. 6 boundary around the predicted group centre (as CGT-UGV's)
    gate_chi2: float = 7.38            # data selection: squared Mahalanobis distance to a predicted
                                       # sub-target (χ²₂ 97.5 %). At 9.21 (99 %) a passer-by 1.4 m beside a
                                       # one-person sub-target gets in on one noisy range, stretches it and
                                       # stays, when the detector delivers every 2nd-3rd frame (EVALUATION.md)
    selection_passes: int = 2          # predict → select → refine → reselect (§2.2.2)
    vb_iterations: int = 6             # Eq. 17-21 fixed-point iterations per pass
    max_lost_frames: int = 30          # frames without a selected point before re-initialising
    default_point_std_m: float = 0.2   # when the caller gives no per-point covariance

    def __post_init__(self) -> None:
        check_ranges(
            self,
            positive=("n_ellipses", "dbscan_eps_m", "dbscan_min_samples", "weave_tau_s", "nu_min",
                      "extent_floor_m2", "extent_ceiling_m2", "d_th_m", "gate_chi2", "selection_passes",
                      "vb_iterations", "max_lost_frames", "default_point_std_m"),
            non_negative=("accel_std_mps2", "offset_std_mps", "weave_std_m", "early_frames"),
            unit_interval=("lambda_iw", "lambda_dirichlet", "weight_threshold_early", "weight_threshold_late"))


class MultiEllipseGroupTracker:
    """ME-CGT-UGV (seed 004 §3.2): multi-ellipse random-matrix shape + group-centre Kalman + data selection.

    State (Eq. 13): mean ``mu`` / covariance ``P`` of [c, v, η_2..η_L]; per sub-target IW(ν_l, V_l) (Eq. 21)
    and Dirichlet α (Eq. 21).
    """

    name = "ME-CGT-UGV"

    def __init__(self, params: GroupParams | None = None) -> None:
        self.p = params or GroupParams()
        self.mu = np.zeros(0)
        self.P = np.zeros((0, 0))
        self.V: list[np.ndarray] = []
        self.nu = np.zeros(0)
        self.alpha = np.zeros(0)
        self.t_s: float | None = None
        self.frames = 0
        self.lost_frames = 0
        self.initialised = False

    # ---- structure
    @property
    def n_components(self) -> int:
        return len(self.nu)

    def _H(self, l: int) -> np.ndarray:
        """Measurement matrix of sub-target l: position = c + η_l (Eq. 13)."""
        return _sub_target_matrix(l, self.n_components)

    def _weave_var(self) -> float:
        # Kept above (1 mm)²: a zero block would make P singular, and the VB update inverts it.
        return max(self.p.weave_std_m, 1e-3) ** 2

    def expected_extent(self, l: int) -> np.ndarray:
        """E[X_l] = V_l / (ν_l − d − 1) (IW mean)."""
        return self.V[l] / (self.nu[l] - D - 1)

    def weights(self) -> np.ndarray:
        """E[π] of the Dirichlet (Eq. 21)."""
        return self.alpha / self.alpha.sum()

    # ---- initialisation (§2.2.1, Alg. 1 lines 22-30)
    def initialise(self, pts: np.ndarray, t_s: float, near_m: np.ndarray | None = None) -> bool:
        idx = pick_group(pts, self.p.dbscan_eps_m, self.p.dbscan_min_samples, near_m)
        if len(idx) == 0:
            return False
        members = pts[idx]
        L = max(1, min(self.p.n_ellipses, len(members)))
        labels = kmeans_split(members, L)
        centres = np.array([members[labels == k].mean(axis=0) for k in range(L)])
        self.mu = np.zeros(_state_size(L))
        self.mu[0:2] = centres.mean(axis=0)                                  # Alg. 1 line 43
        for k in range(2, L + 1):
            self.mu[_slot(k)] = centres[k - 1] - self.mu[0:2]
        self.P = np.eye(len(self.mu)) * 0.25
        self.P[2:4, 2:4] = np.eye(D) * 1.0  # velocity unknown: ~1 m/s std
        for k in range(L):
            self.P[_weave(k, L), _weave(k, L)] = np.eye(D) * self._weave_var()   # its stationary spread
        self.V, nus = [], []
        for k in range(L):
            sub = members[labels == k]
            cov = np.cov(sub.T) if len(sub) > 1 else np.zeros((D, D))
            cov = cov + np.eye(D) * self.p.extent_floor_m2 * 4
            nu = self.p.nu_min
            self.V.append(cov * (nu - D - 1))
            nus.append(nu)
        self.nu = np.array(nus, dtype=float)
        self.alpha = np.array([max(1.0, float(np.sum(labels == k))) for k in range(L)])
        self.t_s = t_s
        self.frames = 0
        self.lost_frames = 0
        self.initialised = True
        log.debug("group initialised: %d members, %d sub-targets", len(members), L)
        return True

    # ---- prediction (§2.2.3 and Eq. 24-25)
    def _predict(self, dt_s: float) -> None:
        n = len(self.mu)
        F = np.eye(n)
        F[0:4, 0:4] = cv_transition(dt_s)
        Q = np.zeros((n, n))
        Q[0:4, 0:4] = cv_process_noise(dt_s, self.p.accel_std_mps2)
        L = self.n_components
        Q[4:_weave(0, L).start, 4:_weave(0, L).start] = np.eye(2 * (L - 1)) * (self.p.offset_std_mps ** 2) * dt_s
        # Weave: Ornstein-Uhlenbeck, w ← a w + noise, a = exp(−dt/τ), stationary variance weave_std².
        a = math.exp(-dt_s / self.p.weave_tau_s) if self.p.weave_tau_s > 0 else 0.0
        for k in range(L):
            F[_weave(k, L), _weave(k, L)] = np.eye(D) * a
            Q[_weave(k, L), _weave(k, L)] = np.eye(D) * (1 - a * a) * self._weave_var()
        self.mu = F @ self.mu
        self.P = F @ self.P @ F.T + Q
        # Eq. 24: V ← λ_IW V, ν ← λ_IW ν (older points count less). Below nu_min the mean E[X] would blow
        # up, so there ν is held and V rescaled to keep E[X] where Eq. 24 put it.
        for l in range(self.n_components):
            ex = self.expected_extent(l)
            nu = self.p.lambda_iw * self.nu[l]
            V = self.p.lambda_iw * self.V[l]
            if nu < self.p.nu_min:
                nu = self.p.nu_min
                V = ex * (nu - D - 1)
            self.nu[l], self.V[l] = nu, V
        self.alpha = self.p.lambda_dirichlet * self.alpha  # Eq. 25

    # ---- data selection (§2.2.2, generalised from Eq. 5-6 to the predicted shape)
    def _select(self, pts: np.ndarray, covs: np.ndarray, mu: np.ndarray, P: np.ndarray,
                V: list[np.ndarray], nu: np.ndarray) -> np.ndarray:
        keep = np.zeros(len(pts), dtype=bool)
        for l in range(len(nu)):
            H = self._H(l)
            m = H @ mu
            ex = V[l] / (nu[l] - D - 1)
            S = ex + H @ P @ H.T + covs                       # (n,2,2): Eq. 8 predictive covariance
            d = pts - m
            m2 = np.einsum("ni,nij,nj->n", d, np.linalg.inv(S), d)
            keep |= m2 < self.p.gate_chi2
        if self.p.d_th_m > 0:
            # Eq. 5-6 as well: a member is within D_th of the predicted group centre (Alg. 1 line 43). The
            # sub-target gates alone let a leaver take its sub-target along (the weave and the slot follow
            # it step by step and it never leaves that gate); the group's boundary cuts it loose.
            centre = np.mean([self._H(l) @ mu for l in range(len(nu))], axis=0)
            keep &= np.linalg.norm(pts - centre, axis=1) < self.p.d_th_m
        return keep

    # ---- variational-Bayes update (Eq. 14-21, 23)
    def _vb_update(self, pts: np.ndarray, covs: np.ndarray, mu0: np.ndarray, P0: np.ndarray,
                   V0: list[np.ndarray], nu0: np.ndarray, alpha0: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
        L, n = len(nu0), len(pts)
        Hs = [self._H(l) for l in range(L)]
        P0inv = np.linalg.inv(P0)
        Rinv = np.linalg.inv(covs)                                            # (n,2,2)
        mu, P = mu0.copy(), P0.copy()
        V, nu, alpha = [v.copy() for v in V0], nu0.copy(), alpha0.copy()
        # Responsibilities start from the predictive mixture (Eq. 12).
        logr = np.zeros((n, L))
        for l in range(L):
            m = Hs[l] @ mu
            S = V[l] / (nu[l] - D - 1) + Hs[l] @ P @ Hs[l].T + covs
            d = pts - m
            logr[:, l] = (math.log(alpha[l] / alpha.sum()) - 0.5 * np.linalg.slogdet(S)[1]
                          - 0.5 * np.einsum("ni,nij,nj->n", d, np.linalg.inv(S), d))
        gamma = _softmax(logr)
        b, Pn = pts.copy(), covs.copy()
        for _ in range(self.p.vb_iterations):
            EXinv = np.array([nu[l] * np.linalg.inv(V[l]) for l in range(L)])   # E[X_l⁻¹]
            ms = np.array([Hs[l] @ mu for l in range(L)])                        # sub-target centres
            Ss = np.array([Hs[l] @ P @ Hs[l].T for l in range(L)])
            # Eq. 17 q_b: each latent point fuses its measurement (Eq. 14, noise R) with the sub-targets.
            Lam = Rinv + np.einsum("nl,lij->nij", gamma, EXinv)
            Pn = np.linalg.inv(Lam)
            rhs = np.einsum("nij,nj->ni", Rinv, pts) + np.einsum("nl,lij,lj->ni", gamma, EXinv, ms)
            b = np.einsum("nij,nj->ni", Pn, rhs)
            # Eq. 18 q_r (responsibilities, Eq. 15): E[ln π_l] − ½E[ln|X_l|] − ½tr(E[X_l⁻¹]·E[(b−Hx)(b−Hx)ᵀ]).
            elogpi = digamma(alpha) - digamma(alpha.sum())
            for l in range(L):
                sign, logdetV = np.linalg.slogdet(V[l])
                elogdet = logdetV - float(np.sum(digamma((nu[l] - np.arange(D)) / 2))) - D * math.log(2)
                d = b - ms[l]
                quad = (np.einsum("ni,ij,nj->n", d, EXinv[l], d)
                        + np.einsum("ij,nji->n", EXinv[l], Pn) + float(np.trace(EXinv[l] @ Ss[l])))
                logr[:, l] = elogpi[l] - 0.5 * elogdet - 0.5 * quad
            gamma = _softmax(logr)
            Nl = gamma.sum(axis=0)
            # Eq. 19 / Eq. 23 q_x: Kalman update in information form, the b's as measurements of c + η_l.
            # Persistent members: Eq. 8 draws each point afresh from the extent every frame, so N_l points
            # would measure the sub-target's centre with covariance X_l / N_l. But the points are the same
            # few people frame after frame, each holding its place in the sub-target: the offset of the
            # visible members' centroid from the sub-target's centre persists while the same ones are seen
            # and jumps when occlusion changes who is seen; it does not average out as 1/N_l within a frame,
            # and a filter that believes it does follows those jumps into the velocity. So each sub-target
            # measures its centre once per frame, with the posterior centroid of its points and the
            # covariance of one member, E[X_l⁻¹]⁻¹: its responsibility-weighted information is divided by
            # max(N_l, 1). Shapes (Eq. 20) and weights (Eq. 21) still count every point.
            info = P0inv.copy()
            vec = P0inv @ mu0
            for l in range(L):
                HtE = Hs[l].T @ EXinv[l]
                once = 1.0 / max(float(Nl[l]), 1.0)
                info += once * Nl[l] * HtE @ Hs[l]
                vec += once * HtE @ (gamma[:, l] @ b)
            P = np.linalg.inv(info)
            P = 0.5 * (P + P.T)
            mu = P @ vec
            # Eq. 20 q_X: IW scatter update; Eq. 21 q_π: Dirichlet counts.
            for l in range(L):
                m = Hs[l] @ mu
                d = b - m
                scatter = (np.einsum("n,ni,nj->ij", gamma[:, l], d, d)
                           + np.einsum("n,nij->ij", gamma[:, l], Pn) + Nl[l] * (Hs[l] @ P @ Hs[l].T))
                V[l] = V0[l] + scatter
                nu[l] = nu0[l] + Nl[l]
            alpha = alpha0 + Nl
        return mu, P, V, nu, alpha, gamma

    def _prune(self) -> None:
        """§4.6 weight thresholds; the group centre and offsets are re-based on the kept sub-targets."""
        thr = self.p.weight_threshold_early if self.frames < self.p.early_frames else self.p.weight_threshold_late
        w = self.weights()
        keep = [l for l in range(self.n_components) if w[l] >= thr]
        if len(keep) == self.n_components or not keep:
            return
        # x' = T x: the kept sub-targets' slots c + η_l and weaves stay where they are; the new c is the
        # mean of their slots (Alg. 1 line 43) and the slot offsets are re-expressed relative to it.
        L, L2 = self.n_components, len(keep)
        slots = []
        for l in keep:
            Hs = self._H(l).copy()
            Hs[:, _weave(l, L)] = 0.0
            slots.append(Hs)
        S = np.array(slots)                                                     # (L2, 2, n)
        c_new = S.mean(axis=0)
        T = np.zeros((_state_size(L2), len(self.mu)))
        T[0:2] = c_new
        T[2:4, 2:4] = np.eye(D)
        for k in range(2, L2 + 1):
            T[_slot(k)] = S[k - 1] - c_new
        for k, l in enumerate(keep):
            T[_weave(k, L2), _weave(l, L)] = np.eye(D)
        self.mu = T @ self.mu
        self.P = T @ self.P @ T.T
        self.V = [self.V[l] for l in keep]
        self.nu = self.nu[keep]
        self.alpha = self.alpha[keep]
        log.debug("pruned sub-targets under %.0f %%: %d left", 100 * thr, L2)

    def _floor_extents(self) -> None:
        for l in range(self.n_components):
            ex = self.expected_extent(l)
            w, v = np.linalg.eigh(0.5 * (ex + ex.T))
            w = np.clip(w, self.p.extent_floor_m2, self.p.extent_ceiling_m2)
            self.V[l] = (v * w) @ v.T * (self.nu[l] - D - 1)

    def estimate(self, selected: np.ndarray | None = None) -> GroupEstimate:
        if not self.initialised:
            return GroupEstimate(valid=False, selected=selected if selected is not None else np.zeros(0, bool))
        w = self.weights()
        ells = [Ellipse(self._H(l) @ self.mu, self.expected_extent(l), float(w[l])) for l in range(self.n_components)]
        centre = sum(e.weight * e.centre_m for e in ells)                      # Alg. 1 line 43
        cov = sum(e.weight * (e.extent_m2 + np.outer(e.centre_m - centre, e.centre_m - centre)) for e in ells)
        return GroupEstimate(True, np.asarray(centre), self.mu[2:4].copy(), _principal_angle(cov), ells,
                             selected if selected is not None else np.zeros(0, bool),
                             lost=self.lost_frames > 0)

    def step(self, t_s: float, points_m: np.ndarray, covs_m2: np.ndarray | None = None) -> GroupEstimate:
        """One frame: predict (§2.2.3, Eq. 24-25), select (§2.2.2), VB-update (Eq. 17-23), prune (§4.6)."""
        pts, covs = _as_points(points_m, covs_m2, self.p.default_point_std_m)
        selected = np.zeros(len(pts), dtype=bool)
        if not self.initialised or self.lost_frames > self.p.max_lost_frames:
            near = self.estimate().centre_m if self.initialised else None
            self.initialised = False
            if self.initialise(pts, t_s, near):
                self.frames += 1
                return self.estimate(self._select(pts, covs, self.mu, self.P, self.V, self.nu))
            return GroupEstimate(valid=False, selected=selected)
        dt = max(0.0, t_s - (self.t_s if self.t_s is not None else t_s))
        self.t_s = t_s
        self._predict(dt)
        mu0, P0, V0, nu0, a0 = self.mu, self.P, self.V, self.nu, self.alpha
        # Predict the shape → keep the points inside it → refine the shape → select again (§2.2.2).
        sel = self._select(pts, covs, mu0, P0, V0, nu0) if len(pts) else selected
        for _ in range(self.p.selection_passes):
            if not sel.any():
                break
            mu, P, V, nu, alpha, _ = self._vb_update(pts[sel], covs[sel], mu0, P0, V0, nu0, a0)
            new_sel = self._select(pts, covs, mu, P, V, nu)
            self.mu, self.P, self.V, self.nu, self.alpha = mu, P, V, nu, alpha
            if np.array_equal(new_sel, sel):
                break
            sel = new_sel
        if sel.any():
            self.lost_frames = 0
            self._floor_extents()
            self._prune()
        else:
            self.lost_frames += 1  # Eq. 7: no associated measurement → the group is lost (coasting)
        self.frames += 1
        return self.estimate(sel)


def _softmax(logr: np.ndarray) -> np.ndarray:
    z = logr - logr.max(axis=1, keepdims=True)
    e = np.exp(z)
    return e / e.sum(axis=1, keepdims=True)


class SingleEllipseGroupTracker(MultiEllipseGroupTracker):
    """RM-CGT-UGV: the random-matrix model of Feldmann/Koch (seed ref. [12], Eq. 8-10) — one ellipse."""

    name = "RM-CGT-UGV"

    def __init__(self, params: GroupParams | None = None) -> None:
        p = params or GroupParams()
        super().__init__(GroupParams(**{**p.__dict__, "n_ellipses": 1}))


# --------------------------------------------------------------------------- comparison methods


class _CentreKalman:
    """Constant-velocity Kalman on a 2-D position (§2.2.3, Eq. 23)."""

    def __init__(self, z_m: np.ndarray, t_s: float, accel_std_mps2: float, pos_std_m: float = 0.5) -> None:
        self.x = np.array([z_m[0], z_m[1], 0.0, 0.0])
        self.P = np.diag([pos_std_m ** 2, pos_std_m ** 2, 1.0, 1.0])
        self.t_s = t_s
        self.accel = accel_std_mps2

    def predict(self, t_s: float) -> None:
        dt = max(0.0, t_s - self.t_s)
        self.t_s = t_s
        F = cv_transition(dt)
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + cv_process_noise(dt, self.accel)

    def update(self, z_m: np.ndarray, R_m2: np.ndarray) -> None:
        H = np.eye(2, 4)
        S = H @ self.P @ H.T + R_m2
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ (z_m - H @ self.x)       # Eq. 23
        self.P = (np.eye(4) - K @ H) @ self.P

    def mahalanobis_sq(self, z_m: np.ndarray, R_m2: np.ndarray) -> float:
        H = np.eye(2, 4)
        S = H @ self.P @ H.T + R_m2
        d = z_m - self.x[:2]
        return float(d @ np.linalg.solve(S, d))


@dataclass
class CgtParams:
    dbscan_eps_m: float = 4.5
    dbscan_min_samples: int = 2
    d_th_m: float = 4.0                # Eq. 6 boundary around the predicted centre
    accel_std_mps2: float = 0.6
    centroid_std_m: float = 0.5        # measurement noise of the centroid (members' spread / √n)
    max_lost_frames: int = 30


class CentroidGroupTracker:
    """CGT-UGV, the shapeless method of seed 004 (Table 2): Eq. 5-7 selection + centroid Kalman."""

    name = "CGT-UGV"

    def __init__(self, params: CgtParams | None = None) -> None:
        self.p = params or CgtParams()
        self.kf: _CentreKalman | None = None
        self.lost_frames = 0

    def step(self, t_s: float, points_m: np.ndarray, covs_m2: np.ndarray | None = None) -> GroupEstimate:
        pts, _ = _as_points(points_m, covs_m2, 0.2)
        if self.kf is None or self.lost_frames > self.p.max_lost_frames:
            idx = pick_group(pts, self.p.dbscan_eps_m, self.p.dbscan_min_samples,
                             None if self.kf is None else self.kf.x[:2])
            if len(idx) == 0:
                return GroupEstimate(valid=False, selected=np.zeros(len(pts), bool))
            self.kf = _CentreKalman(pts[idx].mean(axis=0), t_s, self.p.accel_std_mps2)
            self.lost_frames = 0
        else:
            self.kf.predict(t_s)
        c = self.kf.x[:2]
        d = np.linalg.norm(pts - c, axis=1) if len(pts) else np.zeros(0)   # Eq. 5
        f = (d < self.p.d_th_m).astype(float)                                # Eq. 6, uniform g
        if f.sum() > 0:
            centroid = (f[:, None] * pts).sum(axis=0) / f.sum()                # Eq. 7
            self.kf.update(centroid, np.eye(2) * self.p.centroid_std_m ** 2)
            self.lost_frames = 0
        else:
            self.lost_frames += 1
        sel = f > 0
        members = pts[sel]
        # §4.5.3: the shapeless method's "shape" is the ellipse enveloping its selected points.
        cov = np.cov(members.T) if len(members) > 2 else np.eye(2) * 0.25
        return GroupEstimate(True, self.kf.x[:2].copy(), self.kf.x[2:4].copy(), _principal_angle(cov),
                             [Ellipse(self.kf.x[:2].copy(), cov, 1.0)], sel, lost=self.lost_frames > 0)


class MeanPositionTracker:
    """CGT-Mean (Table 1): the mean of every detected position; velocity by finite difference."""

    name = "CGT-Mean"

    def __init__(self) -> None:
        self.prev: tuple[float, np.ndarray] | None = None
        self.v = np.zeros(2)

    def step(self, t_s: float, points_m: np.ndarray, covs_m2: np.ndarray | None = None) -> GroupEstimate:
        pts, _ = _as_points(points_m, covs_m2, 0.2)
        if len(pts) == 0:
            if self.prev is None:
                return GroupEstimate(valid=False)
            return GroupEstimate(True, self.prev[1].copy(), self.v.copy(), lost=True)
        c = pts.mean(axis=0)
        if self.prev is not None and t_s > self.prev[0]:
            self.v = (c - self.prev[1]) / (t_s - self.prev[0])
        self.prev = (t_s, c)
        return GroupEstimate(True, c, self.v.copy(), selected=np.ones(len(pts), bool))


@dataclass
class PersonTrackParams:
    accel_std_mps2: float = 1.5       # a person turns and weaves: more manoeuvre than the group centre
    gate_chi2: float = 9.21            # χ²₂ 99 %
    max_coast_frames: int = 10


class SingleTargetFollower:
    """SOT (Table 1): follow one member — the detection nearest the group's initial centre — with a
    Kalman filter and gated nearest-neighbour association; after a loss it re-acquires the detection
    nearest its prediction (which may be someone else, as a real SOT would)."""

    name = "SOT"

    def __init__(self, params: PersonTrackParams | None = None, dbscan_eps_m: float = 4.5) -> None:
        self.p = params or PersonTrackParams()
        self.eps = dbscan_eps_m
        self.kf: _CentreKalman | None = None
        self.missed = 0

    def step(self, t_s: float, points_m: np.ndarray, covs_m2: np.ndarray | None = None) -> GroupEstimate:
        pts, covs = _as_points(points_m, covs_m2, 0.2)
        sel = np.zeros(len(pts), bool)
        if self.kf is None:
            idx = pick_group(pts, self.eps, 2)
            if len(idx) == 0:
                return GroupEstimate(valid=False, selected=sel)
            c = pts[idx].mean(axis=0)
            j = idx[int(np.argmin(np.linalg.norm(pts[idx] - c, axis=1)))]
            self.kf = _CentreKalman(pts[j], t_s, self.p.accel_std_mps2, pos_std_m=0.3)
            sel[j] = True
            return GroupEstimate(True, self.kf.x[:2].copy(), self.kf.x[2:4].copy(), selected=sel)
        self.kf.predict(t_s)
        if len(pts):
            m2 = np.array([self.kf.mahalanobis_sq(pts[i], covs[i]) for i in range(len(pts))])
            j = int(np.argmin(m2))
            if m2[j] < self.p.gate_chi2 or self.missed > self.p.max_coast_frames:
                self.kf.update(pts[j], covs[j])
                self.missed = 0
                sel[j] = True
            else:
                self.missed += 1
        else:
            self.missed += 1
        return GroupEstimate(True, self.kf.x[:2].copy(), self.kf.x[2:4].copy(), selected=sel,
                             lost=self.missed > 0)


@dataclass
class _PersonTrack:
    """One person's track in :class:`MotFusionTracker`."""

    kf: _CentreKalman
    hits: int = 1
    missed: int = 0  # frames in a row without an associated point


class MotFusionTracker:
    """MOT with decision-level fusion (Table 1): one Kalman track per person (greedy gated nearest-neighbour
    association, births from unassigned points, deaths after a coast), then the group = the mean position
    and velocity of the confirmed tracks within D_th of the previous group centre."""

    name = "MOT"

    def __init__(self, params: PersonTrackParams | None = None, d_th_m: float = 4.0, confirm_hits: int = 3,
                 dbscan_eps_m: float = 4.5) -> None:
        self.p = params or PersonTrackParams()
        self.d_th = d_th_m
        self.confirm = confirm_hits
        self.eps = dbscan_eps_m
        self.tracks: list[_PersonTrack] = []
        self.centre: np.ndarray | None = None
        self.v = np.zeros(2)

    def step(self, t_s: float, points_m: np.ndarray, covs_m2: np.ndarray | None = None) -> GroupEstimate:
        pts, covs = _as_points(points_m, covs_m2, 0.2)
        for tr in self.tracks:
            tr.kf.predict(t_s)
        hit, free = self._associate(pts, covs)
        self._age_and_prune(hit)
        for i in sorted(free):
            self.tracks.append(_PersonTrack(_CentreKalman(pts[i], t_s, self.p.accel_std_mps2, 0.3)))
        members = self._group_members()
        if members is None:
            return GroupEstimate(valid=False)
        if members:
            xs = np.array([tr.kf.x for tr in members])
            self.centre = xs[:, :2].mean(axis=0)
            self.v = xs[:, 2:4].mean(axis=0)
        assert self.centre is not None
        sel = np.zeros(len(pts), bool)
        return GroupEstimate(True, self.centre.copy(), self.v.copy(), selected=sel, lost=not members)

    def _associate(self, pts: np.ndarray, covs: np.ndarray) -> tuple[set[int], set[int]]:
        """Greedy gated nearest neighbour: (track, point) pairs cheapest first, each track and each point used
        once, each pair's track updated. Returns (indices of the updated tracks, indices of the unused points)."""
        hit: set[int] = set()
        free = set(range(len(pts)))
        if not self.tracks or not len(pts):
            return hit, free
        cost = np.array([[tr.kf.mahalanobis_sq(pts[i], covs[i]) for i in range(len(pts))] for tr in self.tracks])
        for flat in np.argsort(cost, axis=None):
            ti, pi = divmod(int(flat), len(pts))
            if cost[ti, pi] >= self.p.gate_chi2:
                break
            if ti in hit or pi not in free:
                continue
            self.tracks[ti].kf.update(pts[pi], covs[pi])
            hit.add(ti)
            free.discard(pi)
        return hit, free

    def _age_and_prune(self, hit: set[int]) -> None:
        for ti, tr in enumerate(self.tracks):
            if ti in hit:
                tr.hits += 1
                tr.missed = 0
            else:
                tr.missed += 1
        self.tracks = [tr for tr in self.tracks if tr.missed <= self.p.max_coast_frames]

    def _group_members(self) -> list[_PersonTrack] | None:
        """The tracks the group is made of: the confirmed ones within D_th of the previous centre; before there
        is a centre, the DBSCAN-picked cluster of all tracks (None while there is no cluster)."""
        confirmed = [tr for tr in self.tracks if tr.hits >= self.confirm or self.centre is None]
        if self.centre is not None:
            return [tr for tr in confirmed if np.linalg.norm(tr.kf.x[:2] - self.centre) < self.d_th]
        xs = np.array([tr.kf.x[:2] for tr in confirmed]).reshape(-1, 2)
        idx = pick_group(xs, self.eps, 2)
        if len(idx) == 0:
            return None
        return [confirmed[i] for i in idx]


METHODS = {
    "ME-CGT-UGV": MultiEllipseGroupTracker,
    "RM-CGT-UGV": SingleEllipseGroupTracker,
    "CGT-UGV": CentroidGroupTracker,
    "CGT-Mean": MeanPositionTracker,
    "SOT": SingleTargetFollower,
    "MOT": MotFusionTracker,
}
