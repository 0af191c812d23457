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
class _GroupPath:
    """The nominal group path, per frame: time, position, velocity and its forward / left unit axes."""

    t: np.ndarray                         # (T,)
    pos: np.ndarray                       # (T, 2)
    vel: np.ndarray                       # (T, 2)
    fwd: np.ndarray                       # (T, 2)
    left: np.ndarray                      # (T, 2)


def _path_axes(path_vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward and left unit vectors along a path, from its velocity."""
    head = np.arctan2(path_vel[:, 1], path_vel[:, 0])
    return np.stack([np.cos(head), np.sin(head)], axis=1), np.stack([-np.sin(head), np.cos(head)], axis=1)


@dataclass
class _Cast:
    """Everyone in a scenario as it is built: per person, its positions (T, 2) and when it is a member / present."""

    positions: list[np.ndarray] = field(default_factory=list)
    member: list[np.ndarray] = field(default_factory=list)
    present: list[np.ndarray] = field(default_factory=list)

    def add(self, pos: np.ndarray, member: np.ndarray, present: np.ndarray) -> None:
        self.positions.append(pos)
        self.member.append(member)
        self.present.append(present)

    def add_non_member(self, pos: np.ndarray) -> None:
        """Someone in the scene all along who never joins the group."""
        self.add(pos, np.zeros(len(pos), bool), np.ones(len(pos), bool))


def _slot_walker(path_pos: np.ndarray, path_vel: np.ndarray, slot: np.ndarray, scale: np.ndarray,
                 rng: np.random.Generator) -> np.ndarray:
    """World positions of a member holding ``slot`` (forward, left) with its own lateral weave."""
    t = np.arange(len(path_pos)) * DT_S
    fwd, left = _path_axes(path_vel)
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
    # One generator for every draw, in a fixed order (formation, walkers, obstacles, then frame by frame):
    # reordering the phases below changes every number.
    rng = np.random.default_rng([seed, SCENARIOS.index(name)])
    path = _nominal_path(name, np.arange(int(round(duration_s / DT_S))) * DT_S)
    slots, scale, follow_m = _formation(name, path.t, rng)
    sc = _scenario_truth(name, path, _build_cast(name, path, slots, scale, rng), follow_m)
    obstacles = _place_obstacles(path, rng)
    _simulate_frames(sc, obstacles, _occlusion_deg(name, occlusion_deg), p_miss, clutter_per_s, rng)
    return sc


def _nominal_path(name: str, t: np.ndarray) -> _GroupPath:
    pos, vel = _turning(t) if name == "turning" else _straight(t)
    fwd, left = _path_axes(vel)
    return _GroupPath(t, pos, vel, fwd, left)


def _formation(name: str, t: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """The 8 members' slots (forward, left) m, the formation's scale over time, and how far behind the group's
    centre the robot follows (0: among the group, between the columns)."""
    n_members = 8
    if name == "double-column":
        return _double_column(n_members), np.ones(len(t)), 0.0
    slots = _blob(n_members, rng)
    if name == "formation":
        return slots, np.interp(t, [0, 8, 12, 16, 22, 60], [1.0, 1.0, 0.5, 0.5, 1.5, 1.5]), 4.0
    return slots, np.ones(len(t)), 4.0


def _occlusion_deg(name: str, occlusion_deg: float | None) -> float:
    """The occlusion angle: the caller's, else 10° for the occlusion scenario (Table 3), 3° elsewhere."""
    if occlusion_deg is not None:
        return occlusion_deg
    return 10.0 if name == "occlusion" else 3.0


def _build_cast(name: str, path: _GroupPath, slots: np.ndarray, scale: np.ndarray,
                rng: np.random.Generator) -> _Cast:
    cast = _Cast()
    for s in slots:
        cast.add(_slot_walker(path.pos, path.vel, s, scale, rng), np.ones(len(path.t), bool),
                 np.ones(len(path.t), bool))
    # Seed 004 runs its disturbance and occlusion experiments on the Fig. 2a scenario (Table 3's n = 2 / 5° rows
    # are Table 2's numbers): the same squad, joiner and leaver, with disturbers added or the angle widened.
    if name in ("straight", "disturbance", "occlusion"):
        _add_joiner_and_leaver(cast, path, scale, rng)
    if name == "disturbance":
        _add_disturbers(cast, path.t)
    return cast


def _add_joiner_and_leaver(cast: _Cast, path: _GroupPath, scale: np.ndarray, rng: np.random.Generator) -> None:
    t = path.t
    # Joiner: walks in from 9 m to the left, reaches its slot (rear-left) at 12 s, member from then.
    own = _slot_walker(path.pos, path.vel, np.array([-3.6, 1.4]), scale, rng)
    lateral = np.interp(t, [0, 8, 12, 60], [9.0, 9.0, 0.0, 0.0])
    cast.add(own + path.left * lateral[:, None], t >= 12.0, t >= 4.0)
    # Leaver: member 2 peels off to the right from 18 s, at 1 m/s sideways and slowing down.
    k = 2
    off = np.clip(t - 18.0, 0, None)
    cast.positions[k] = cast.positions[k] - path.left * (1.0 * off)[:, None] - path.fwd * (0.6 * off)[:, None]
    cast.member[k] = t < 18.0


def _add_disturbers(cast: _Cast, t: np.ndarray) -> None:
    n_t = len(t)
    # Two crossing the path through the group's front and rear at 1.3 m/s.
    for t_cross, dx in ((9.0, 2.5), (19.0, -2.0)):
        x0 = SPEED_MPS * t_cross + dx
        cast.add_non_member(np.stack([np.full(n_t, x0), 1.3 * (t - t_cross) * (1 if dx > 0 else -1)], axis=1))
    # Oncoming at 3.5 m to the right.
    cast.add_non_member(np.stack([40.0 - 1.1 * t, np.full(n_t, -3.5)], axis=1))
    # A bystander standing 4 m left of the path.
    cast.add_non_member(np.tile([16.0, 4.0], (n_t, 1)))
    # Walking the same way at 0.6 m/s, 4.5 m to the right: overtaken.
    cast.add_non_member(np.stack([6.0 + 0.6 * t, np.full(n_t, -4.5)], axis=1))


def _scenario_truth(name: str, path: _GroupPath, cast: _Cast, follow_m: float) -> Scenario:
    """The scenario without its frames: everyone's true positions, the robot's and the group centre's."""
    people = np.stack(cast.positions)                # (P, T, 2)
    member = np.stack(cast.member)
    present = np.stack(cast.present)
    robot = path.pos - path.fwd * follow_m
    gt_centre = np.array([people[member[:, k], k].mean(axis=0) for k in range(len(path.t))])
    return Scenario(name, _DESCRIPTIONS[name], path.t, gt_centre, path.vel.copy(), robot, people, member, present)


def _place_obstacles(path: _GroupPath, rng: np.random.Generator) -> list[np.ndarray]:
    # Static false positives: obstacles beside the path detected as people half of the time (§5.2).
    steps_m = np.linalg.norm(np.diff(path.pos, axis=0), axis=1)
    path_len = float(np.sum(steps_m))
    arc_m = np.cumsum(np.r_[0, steps_m])
    obstacles = []
    for s_m in np.linspace(10, max(12.0, path_len - 5), 3):
        k = int(np.argmin(np.abs(arc_m - s_m)))
        side = rng.choice([-1, 1]) * rng.uniform(5.0, 7.0)
        obstacles.append(path.pos[k] + path.left[k] * side)
    return obstacles


@dataclass
class _FrameDetections:
    """One frame's detections as they are gathered, each measured with its covariance on the way in."""

    points: list[np.ndarray] = field(default_factory=list)
    covs: list[np.ndarray] = field(default_factory=list)
    source: list[int] = field(default_factory=list)
    is_member: list[bool] = field(default_factory=list)

    def add(self, rel_m: np.ndarray, robot_m: np.ndarray, rng: np.random.Generator, source: int,
            is_member: bool) -> None:
        z, R = _measure(rel_m, robot_m, rng)
        self.points.append(z)
        self.covs.append(R)
        self.source.append(source)
        self.is_member.append(is_member)

    def shuffled(self, t_s: float, rng: np.random.Generator) -> SimFrame:
        order = rng.permutation(len(self.points))  # detectors give no order; neither should the input
        return SimFrame(
            t_s,
            np.array(self.points, dtype=float).reshape(-1, 2)[order],
            np.array(self.covs, dtype=float).reshape(-1, 2, 2)[order],
            np.array(self.source, dtype=int)[order],
            np.array(self.is_member, dtype=bool)[order])


def _simulate_frames(sc: Scenario, obstacles: list[np.ndarray], occlusion_deg: float, p_miss: float,
                     clutter_per_s: float, rng: np.random.Generator) -> None:
    """Fill ``sc.frames`` (people, then obstacles, then clutter, shuffled) and ``sc.occlusion_rate``."""
    hidden_members = 0
    shown_members = 0
    for k in range(len(sc.t_s)):
        dets = _FrameDetections()
        hidden, shown = _sense_people(sc, k, occlusion_deg, p_miss, rng, dets)
        hidden_members += hidden
        shown_members += shown
        robot = sc.robot_m[k]
        for ob in obstacles:
            if np.linalg.norm(ob - robot) < 25.0 and rng.random() < 0.5:
                dets.add(ob - robot, robot, rng, -1, False)
        for _ in range(rng.poisson(clutter_per_s * DT_S)):
            r, b = rng.uniform(2.0, 20.0), rng.uniform(-math.pi, math.pi)
            dets.add(np.array([r * math.cos(b), r * math.sin(b)]), robot, rng, -1, False)
        sc.frames.append(dets.shuffled(float(sc.t_s[k]), rng))
    sc.occlusion_rate = hidden_members / max(1, shown_members)


def _sense_people(sc: Scenario, k: int, occlusion_deg: float, p_miss: float, rng: np.random.Generator,
                  dets: _FrameDetections) -> tuple[int, int]:
    """Measure the people in range at frame k who are neither occluded nor missed. Returns (members occluded,
    members in range): the occlusion rate counts occluded members whether or not a miss would have hidden them."""
    hidden = shown = 0
    robot = sc.robot_m[k]
    who = np.flatnonzero(sc.present[:, k])
    rel = sc.people_m[who, k] - robot
    range_m = np.linalg.norm(rel, axis=1)
    bearing = np.arctan2(rel[:, 1], rel[:, 0])
    for a, i in enumerate(who):
        if range_m[a] > 25.0:
            continue
        occluded = _is_occluded(a, range_m, bearing, occlusion_deg)
        if sc.member[i, k]:
            hidden += occluded
            shown += 1
        if occluded or rng.random() < p_miss:
            continue
        dets.add(rel[a], robot, rng, i, bool(sc.member[i, k]))
    return hidden, shown


def _is_occluded(a: int, range_m: np.ndarray, bearing: np.ndarray, occlusion_deg: float) -> bool:
    """Someone nearer the sensor (by more than 0.3 m) lies within ``occlusion_deg`` of person a's bearing."""
    nearer = range_m < range_m[a] - 0.3
    dbear = np.abs((bearing - bearing[a] + math.pi) % (2 * math.pi) - math.pi)
    return bool(np.any(nearer & (dbear < math.radians(occlusion_deg))))


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
