"""Seeded simulator of seed 004's group scenarios (§4.1, Fig. 2; §4.5): a squad of 7-10 pedestrians ahead
of (or around) a robot, seen by a range sensor as noisy, incomplete ground-plane points.

What is simulated, per frame (dt 0.1 s, the paper's LiDAR rate):

* Members hold formation slots around a nominal group path (straight, turning, contracting/expanding),
  each weaving laterally on its own (amplitude 0.2-0.5 m, period 4-8 s: the S-curves a followed person
  draws, §4.3) with a little jitter along the path.
* Non-members: joiners and leavers (§5.2), disturbers (§4.5.1) crossing, walking against, standing by or
  overtaken by the group, and static false positives (obstacles detected as pedestrians, §5.2).
* The robot follows the nominal group path at a set distance behind the centre (0 = among the group, the
  double column of §5.3) with perfect odometry, so points arrive in the fixed odometry frame (Eq. 4 is
  identity here; the graph's ground-plane node does the real transform).
* Occlusion (§4.5.2): a person is hidden when someone nearer the sensor lies within ``occlusion_deg`` of
  its bearing. Visible people are missed with probability ``p_miss``; range noise grows with range
  (σ_r = 0.05 m + 2 % of range, σ_bearing = 0.6°), and each point carries that covariance. A 360° sensor
  (the paper's LiDAR), 25 m range. A few clutter points per second appear anywhere in range.

Ground truth: the centre is the mean of the true positions of the current members (occluded ones
included); the orientation is the heading of the nominal group path, its velocity the path's velocity.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

DT_S = 0.1
SPEED_MPS = 1.2  # §5.1: pedestrians and UGV at 1.2 m/s


@dataclass
class SimFrame:
    t_s: float
    points_m: np.ndarray          # (n, 2) odometry frame
    covs_m2: np.ndarray           # (n, 2, 2)
    source: np.ndarray            # (n,) person index, -1 for clutter
    is_member: np.ndarray         # (n,) bool: the point belongs to a current group member


@dataclass
class Scenario:
    name: str
    description: str
    t_s: np.ndarray                       # (T,)
    gt_centre_m: np.ndarray               # (T, 2)
    gt_velocity_mps: np.ndarray           # (T, 2)
    robot_m: np.ndarray                   # (T, 2)
    people_m: np.ndarray                  # (P, T, 2) true positions
    member: np.ndarray                    # (P, T) bool: part of the group at t
    present: np.ndarray                   # (P, T) bool: in the scene at t
    frames: list[SimFrame] = field(default_factory=list)
    occlusion_rate: float = 0.0           # share of present members hidden by someone nearer

    @property
    def gt_heading_rad(self) -> np.ndarray:
        return np.arctan2(self.gt_velocity_mps[:, 1], self.gt_velocity_mps[:, 0])


# --------------------------------------------------------------------------- nominal paths


def _straight(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.stack([SPEED_MPS * t, np.zeros_like(t)], axis=1)
    vel = np.tile([SPEED_MPS, 0.0], (len(t), 1))
    return pos, vel


def _turning(t: np.ndarray, t_turn_s: float = 8.0, radius_m: float = 6.0, angle_rad: float = math.pi / 2
             ) -> tuple[np.ndarray, np.ndarray]:
    """Straight, a left turn of ``angle_rad`` on a circle of ``radius_m`` (Fig. 2d), straight again."""
    w = SPEED_MPS / radius_m
    t_end = t_turn_s + angle_rad / w
    pos, vel = np.zeros((len(t), 2)), np.zeros((len(t), 2))
    for k, tk in enumerate(t):
        if tk <= t_turn_s:
            pos[k] = [SPEED_MPS * tk, 0.0]
            heading = 0.0
        elif tk <= t_end:
            a = w * (tk - t_turn_s)
            pos[k] = [SPEED_MPS * t_turn_s + radius_m * math.sin(a), radius_m * (1 - math.cos(a))]
            heading = a
        else:
            p_end = [SPEED_MPS * t_turn_s + radius_m * math.sin(angle_rad), radius_m * (1 - math.cos(angle_rad))]
            pos[k] = np.array(p_end) + SPEED_MPS * (tk - t_end) * np.array([math.cos(angle_rad),
                                                                           math.sin(angle_rad)])
            heading = angle_rad
        vel[k] = SPEED_MPS * np.array([math.cos(heading), math.sin(heading)])
    return pos, vel


# --------------------------------------------------------------------------- formations (forward, left) m


def _blob(n: int, rng: np.random.Generator) -> np.ndarray:
    """A loose squad: rows of 3 about 1.4 m apart, 1.2 m between neighbours, slots jittered."""
    slots = []
    for i in range(n):
        row, col = divmod(i, 3)
        slots.append([-1.4 * row, 1.2 * (col - 1)])
    s = np.array(slots, dtype=float)
    s += rng.normal(0, 0.2, s.shape)
    return s - s.mean(axis=0)


def _double_column(n: int) -> np.ndarray:
    rows = (n + 1) // 2
    s = np.array([[-1.5 * (i // 2), 2.0 if i % 2 == 0 else -2.0] for i in range(n)], dtype=float)
    s[:, 0] += 1.5 * (rows - 1) / 2
    return s


@dataclass
class _Walker:
    """One person: a function of time to a world position, and when they are in the scene / a member."""

    pos: Callable[[np.ndarray], np.ndarray]
    present: Callable[[np.ndarray], np.ndarray]
    member: Callable[[np.ndarray], np.ndarray]


def _slot_walker(path_pos: np.ndarray, path_vel: np.ndarray, slot: np.ndarray, scale: np.ndarray,
                 rng: np.random.Generator) -> np.ndarray:
    """World positions of a member holding ``slot`` (forward, left) with its own lateral weave."""
    t = np.arange(len(path_pos)) * DT_S
    head = np.arctan2(path_vel[:, 1], path_vel[:, 0])
    fwd = np.stack([np.cos(head), np.sin(head)], axis=1)
    left = np.stack([-np.sin(head), np.cos(head)], axis=1)
    amp, period, phase = rng.uniform(0.2, 0.5), rng.uniform(4.0, 8.0), rng.uniform(0, 2 * math.pi)
    weave = amp * np.sin(2 * math.pi * t / period + phase)
    surge = 0.15 * np.sin(2 * math.pi * t / rng.uniform(5, 9) + rng.uniform(0, 2 * math.pi))
    return (path_pos + fwd * (slot[0] * scale + surge)[:, None] + left * (slot[1] * scale + weave)[:, None])


# --------------------------------------------------------------------------- scenarios


SCENARIOS = ("straight", "formation", "turning", "double-column", "disturbance", "occlusion")

_DESCRIPTIONS = {
    "straight": "8 walk straight; one joins from the side at 8-12 s, one leaves at 18 s (Fig. 2a, §5.2)",
    "formation": "8 walk straight, contract to half spacing (8-12 s), expand to 1.5× (16-22 s) (Fig. 2b,c)",
    "turning": "8 walk straight, turn 90° left on a 6 m radius, walk on (Fig. 2d)",
    "double-column": "8 in two columns 4 m apart, the robot between them (Fig. 2e, §5.3)",
    "disturbance": "straight (Fig. 2a: join at 8-12 s, leave at 18 s) plus 5 non-members crossing, oncoming, "
                   "standing by, overtaken (§4.5.1, Table 3 n = 5)",
    "occlusion": "straight (Fig. 2a: join at 8-12 s, leave at 18 s) with a 10° occlusion angle (§4.5.2, Table 3)",
}


def make_scenario(name: str, seed: int = 0, duration_s: float = 30.0, p_miss: float = 0.1,
                  clutter_per_s: float = 2.0, occlusion_deg: float | None = None) -> Scenario:
    """Build one scenario with all its frames. Same (name, seed) → same numbers."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown group scenario {name!r}; available: {', '.join(SCENARIOS)}")
    rng = np.random.default_rng([seed, SCENARIOS.index(name)])
    n_t = int(round(duration_s / DT_S))
    t = np.arange(n_t) * DT_S
    always = np.ones(n_t, bool)
    follow_m = 4.0
    occ = 3.0 if occlusion_deg is None else occlusion_deg
    scale = np.ones(n_t)
    if name == "turning":
        path_pos, path_vel = _turning(t)
    else:
        path_pos, path_vel = _straight(t)
    head = np.arctan2(path_vel[:, 1], path_vel[:, 0])
    fwd = np.stack([np.cos(head), np.sin(head)], axis=1)
    left = np.stack([-np.sin(head), np.cos(head)], axis=1)

    n_members = 8
    # Seed 004 runs its disturbance and occlusion experiments on the Fig. 2a scenario (Table 3's n = 2 / 5° rows
    # are Table 2's numbers): the same squad, joiner and leaver, with disturbers added or the angle widened.
    base_straight = name in ("straight", "disturbance", "occlusion")
    if name == "occlusion":
        occ = 10.0 if occlusion_deg is None else occlusion_deg
    if name == "double-column":
        slots = _double_column(n_members)
        follow_m = 0.0
    else:
        slots = _blob(n_members, rng)
    if name == "formation":
        scale = np.interp(t, [0, 8, 12, 16, 22, 60], [1.0, 1.0, 0.5, 0.5, 1.5, 1.5])

    positions: list[np.ndarray] = []
    member: list[np.ndarray] = []
    present: list[np.ndarray] = []
    for s in slots:
        positions.append(_slot_walker(path_pos, path_vel, s, scale, rng))
        member.append(always.copy())
        present.append(always.copy())

    if base_straight:
        # Joiner: walks in from 9 m to the left, reaches its slot (rear-left) at 12 s, member from then.
        slot = np.array([-3.6, 1.4])
        own = _slot_walker(path_pos, path_vel, slot, scale, rng)
        lateral = np.interp(t, [0, 8, 12, 60], [9.0, 9.0, 0.0, 0.0])
        positions.append(own + left * lateral[:, None])
        member.append(t >= 12.0)
        present.append(t >= 4.0)
        # Leaver: member 2 peels off to the right from 18 s, at 1 m/s sideways and slowing down.
        k = 2
        off = np.clip(t - 18.0, 0, None)
        positions[k] = positions[k] - left * (1.0 * off)[:, None] - fwd * (0.6 * off)[:, None]
        member[k] = t < 18.0
    if name == "disturbance":
        def add(pos: np.ndarray) -> None:
            positions.append(pos)
            member.append(np.zeros(n_t, bool))
            present.append(always.copy())
        # Two crossing the path through the group's front and rear at 1.3 m/s.
        for t_cross, dx in ((9.0, 2.5), (19.0, -2.0)):
            x0 = SPEED_MPS * t_cross + dx
            add(np.stack([np.full(n_t, x0), 1.3 * (t - t_cross) * (1 if dx > 0 else -1)], axis=1))
        # Oncoming at 3.5 m to the right.
        add(np.stack([40.0 - 1.1 * t, np.full(n_t, -3.5)], axis=1))
        # A bystander standing 4 m left of the path.
        add(np.tile([16.0, 4.0], (n_t, 1)))
        # Walking the same way at 0.6 m/s, 4.5 m to the right: overtaken.
        add(np.stack([6.0 + 0.6 * t, np.full(n_t, -4.5)], axis=1))

    people = np.stack(positions)                     # (P, T, 2)
    member_a = np.stack(member)
    present_a = np.stack(present)
    robot = path_pos - fwd * follow_m

    gt_centre = np.array([people[member_a[:, k], k].mean(axis=0) for k in range(n_t)])
    sc = Scenario(name, _DESCRIPTIONS[name], t, gt_centre, path_vel.copy(), robot, people, member_a, present_a)

    # Static false positives: obstacles beside the path detected as people half of the time (§5.2).
    path_len = float(np.sum(np.linalg.norm(np.diff(path_pos, axis=0), axis=1)))
    obstacles = []
    for s_m in np.linspace(10, max(12.0, path_len - 5), 3):
        k = int(np.argmin(np.abs(np.cumsum(np.r_[0, np.linalg.norm(np.diff(path_pos, axis=0), axis=1)]) - s_m)))
        side = rng.choice([-1, 1]) * rng.uniform(5.0, 7.0)
        obstacles.append(path_pos[k] + left[k] * side)

    hidden_members = 0
    shown_members = 0
    for k in range(n_t):
        pts, covs, src, mem = [], [], [], []
        who = np.flatnonzero(present_a[:, k])
        rel = people[who, k] - robot[k]
        rng_m = np.linalg.norm(rel, axis=1)
        bearing = np.arctan2(rel[:, 1], rel[:, 0])
        for a, i in enumerate(who):
            if rng_m[a] > 25.0:
                continue
            nearer = rng_m < rng_m[a] - 0.3
            dbear = np.abs((bearing - bearing[a] + math.pi) % (2 * math.pi) - math.pi)
            occluded = bool(np.any(nearer & (dbear < math.radians(occ))))
            if member_a[i, k]:
                hidden_members += occluded
                shown_members += 1
            if occluded or rng.random() < p_miss:
                continue
            z, R = _measure(rel[a], robot[k], rng)
            pts.append(z)
            covs.append(R)
            src.append(i)
            mem.append(bool(member_a[i, k]))
        for ob in obstacles:
            if np.linalg.norm(ob - robot[k]) < 25.0 and rng.random() < 0.5:
                z, R = _measure(ob - robot[k], robot[k], rng)
                pts.append(z)
                covs.append(R)
                src.append(-1)
                mem.append(False)
        for _ in range(rng.poisson(clutter_per_s * DT_S)):
            r, b = rng.uniform(2.0, 20.0), rng.uniform(-math.pi, math.pi)
            z, R = _measure(np.array([r * math.cos(b), r * math.sin(b)]), robot[k], rng)
            pts.append(z)
            covs.append(R)
            src.append(-1)
            mem.append(False)
        order = rng.permutation(len(pts))  # detectors give no order; neither should the input
        sc.frames.append(SimFrame(
            float(t[k]),
            np.array(pts, dtype=float).reshape(-1, 2)[order],
            np.array(covs, dtype=float).reshape(-1, 2, 2)[order],
            np.array(src, dtype=int)[order],
            np.array(mem, dtype=bool)[order]))
    sc.occlusion_rate = hidden_members / max(1, shown_members)
    return sc


def _measure(rel_m: np.ndarray, robot_m: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Polar noise (σ_r = 0.05 m + 2 % of range, σ_b = 0.6°), returned with its Cartesian covariance."""
    r = float(np.linalg.norm(rel_m))
    b = math.atan2(float(rel_m[1]), float(rel_m[0]))
    sr, sb = 0.05 + 0.02 * r, math.radians(0.6)
    rn, bn = r + rng.normal(0, sr), b + rng.normal(0, sb)
    z = robot_m + np.array([rn * math.cos(bn), rn * math.sin(bn)])
    J = np.array([[math.cos(b), -r * math.sin(b)], [math.sin(b), r * math.cos(b)]])
    R = J @ np.diag([sr ** 2, sb ** 2]) @ J.T
    return z, R
