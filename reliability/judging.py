"""The chaos bench's judging: what the observer saw (tracks, commands, ground truth) and the pure checks on it
(the motor's limits, the watchdog's stop, recovery, tracking coverage, latency)."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..bus.graph import Graph

log = logging.getLogger("followbus.chaos")

NS = 1_000_000_000
MS = 1_000_000
INJECTOR = "chaos"  # header.source of everything the harness publishes
FOLLOW_STATES = frozenset({"TRACKING", "REACQUIRED"})  # "tracking": the robot follows an observed box
MOVING_STATES = FOLLOW_STATES | {"OCCLUDED"}  # states the motor moves on: the watchdog must cover them
FOLLOW_REASONS = frozenset({"tracking", "reacquired"})
FRAME_PERIOD_NS = NS // 30
STALE_TRACK_NS = 300 * MS  # a track older than this at a coverage sample means "no tracking"


class ChaosError(RuntimeError):
    """The harness itself could not do its job (graph did not come up, no pid, ...)."""


# ----------------------------------------------------------------------------- observations


@dataclass
class TrackObs:
    recv_ns: int
    frame_seq: int
    stamp_ns: int
    state: str
    source: str
    pub_ns: int = 0  # the publisher's clock (same machine): the watchdog is timed on it, not on our receipt


@dataclass
class CommandObs:
    recv_ns: int
    frame_seq: int
    stamp_ns: int
    pub_ns: int
    vx_mps: float
    vy_mps: float
    wz_radps: float
    wheel_radps: tuple[float, ...]
    range_m: float | None
    bearing_rad: float | None
    reason: str

    @property
    def is_zero(self) -> bool:
        return self.vx_mps == 0.0 and self.vy_mps == 0.0 and self.wz_radps == 0.0 and not any(self.wheel_radps)

    @property
    def answers_track(self) -> bool:
        """A command computed from a track (carries its frame), not a watchdog tick."""
        return self.frame_seq >= 0 and self.reason != "watchdog"


@dataclass
class TruthObs:
    recv_ns: int
    frame_seq: int
    stamp_ns: int
    visible: bool  # the simulated detector can see the target (box present, visible fraction >= 0.3)


@dataclass
class Limits:
    """What a safe motor command looks like, from the graph's motor params."""

    max_forward_mps: float
    max_reverse_mps: float
    max_strafe_mps: float
    max_yaw_radps: float
    max_wheel_radps: float
    watchdog_timeout_ms: float
    tick_ms: float

    @classmethod
    def from_graph(cls, graph: Graph) -> Limits:
        from ..control.kinematics import mecanum_wheel_speeds
        from ..nodes.motor import Motor

        _, p = Motor.parse_params(dict(graph.nodes["motor"].params))
        corners = [mecanum_wheel_speeds(vx, vy, wz, p.half_length_m, p.half_width_m, p.wheel_radius_m)
                   for vx in (p.max_speed_mps, -p.max_reverse_mps) for vy in (p.max_strafe_mps, -p.max_strafe_mps)
                   for wz in (p.max_yaw_radps, -p.max_yaw_radps)]
        return cls(max_forward_mps=p.max_speed_mps, max_reverse_mps=p.max_reverse_mps,
                   max_strafe_mps=p.max_strafe_mps, max_yaw_radps=p.max_yaw_radps,
                   max_wheel_radps=float(np.max(np.abs(corners))), watchdog_timeout_ms=p.watchdog_timeout_ms,
                   tick_ms=float(Motor.TIMER_PERIOD_MS or 0.0))

    def unsafe(self, cmd: CommandObs) -> list[str]:
        """Why a command is unsafe (empty: it is fine)."""
        eps = 1e-9
        values = [cmd.vx_mps, cmd.vy_mps, cmd.wz_radps, *cmd.wheel_radps]
        values += [v for v in (cmd.range_m, cmd.bearing_rad) if v is not None]
        out = []
        if not all(math.isfinite(v) for v in values):
            out.append("non-finite field")
            return out
        if cmd.vx_mps > self.max_forward_mps + eps or cmd.vx_mps < -self.max_reverse_mps - eps:
            out.append(f"vx {cmd.vx_mps:.3f} m/s")
        if abs(cmd.vy_mps) > self.max_strafe_mps + eps:
            out.append(f"vy {cmd.vy_mps:.3f} m/s")
        if abs(cmd.wz_radps) > self.max_yaw_radps + eps:
            out.append(f"wz {cmd.wz_radps:.3f} rad/s")
        if len(cmd.wheel_radps) != 4 or max(abs(w) for w in cmd.wheel_radps) > self.max_wheel_radps + 1e-6:
            out.append(f"wheels {cmd.wheel_radps}")
        return out


# ----------------------------------------------------------------------------- analysis (pure)


@dataclass
class WatchdogReport:
    stops_ms: list[float] = field(default_factory=list)  # last followable track -> first zero command, per gap
    violations: list[str] = field(default_factory=list)

    @property
    def worst_ms(self) -> float | None:
        return max(self.stops_ms) if self.stops_ms else None


def watchdog_report(tracks: Sequence[TrackObs], commands: Sequence[CommandObs], t0_ns: int, t1_ns: int,
                    timeout_ms: float, bound_ms: float, motor_down: tuple[int, int] | None = None) -> WatchdogReport:
    """Stop latency for every pause in the track stream inside [t0, t1] that follows a moving state.

    A pause longer than ``timeout_ms`` gets its stop latency measured when a zero command came in it;
    a pause longer than ``bound_ms`` without a zero command within ``bound_ms`` is a violation. Times are
    the publishers' ``pub_ns`` (prediction's, the motor's; same machine clock), so the harness's own
    scheduling does not enter the figure; the window [t0, t1] is on receive times. ``motor_down``: the motor
    process's own death (kill to back up, pub_ns clock): a pause that starts then, or within the bound before,
    cannot be answered by a stop on the bus; the MCU's own stop covers it (each command's hold_ms, README).
    """
    report = WatchdogReport()
    seq = sorted((t for t in tracks if t0_ns <= t.recv_ns <= t1_ns), key=lambda t: t.pub_ns)
    zeros = sorted(c.pub_ns for c in commands if c.is_zero and c.recv_ns > t0_ns)
    end = max([t1_ns, *(t.pub_ns for t in seq)])
    for i, last in enumerate(seq):
        nxt = seq[i + 1].pub_ns if i + 1 < len(seq) else end
        gap_ms = (nxt - last.pub_ns) / MS
        if gap_ms <= timeout_ms or last.state not in MOVING_STATES:
            continue
        if motor_down is not None and motor_down[0] - bound_ms * MS <= last.pub_ns <= motor_down[1]:
            continue
        stop = next((z for z in zeros if last.pub_ns < z <= nxt), None)
        if stop is not None:
            report.stops_ms.append((stop - last.pub_ns) / MS)
        if gap_ms > bound_ms and (stop is None or (stop - last.pub_ns) / MS > bound_ms):
            what = "no zero command" if stop is None else f"zero command after {(stop - last.pub_ns) / MS:.0f} ms"
            report.violations.append(f"tracks paused {gap_ms:.0f} ms after a {last.state} track: {what} "
                                     f"(bound {bound_ms:.0f} ms)")
    return report


def hidden_ns(truth: Sequence[TruthObs], t0_ns: int, t1_ns: int) -> int:
    """Time in [t0, t1] during which the scene hid the target (from the ground truth stream)."""
    return sum(FRAME_PERIOD_NS for g in truth if t0_ns <= g.recv_ns <= t1_ns and not g.visible)


def first_follow_ns(commands: Sequence[CommandObs], after_ns: int, exclude_stamps: Iterable[int] = ()) -> int | None:
    """Receive time of the first command after ``after_ns`` that follows the target (not an injected track)."""
    excluded = set(exclude_stamps)
    times = [c.recv_ns for c in commands
             if c.recv_ns > after_ns and c.reason in FOLLOW_REASONS and c.answers_track and c.stamp_ns not in excluded]
    return min(times) if times else None


def tracking_coverage(tracks: Sequence[TrackObs], truth: Sequence[TruthObs], t0_ns: int, t1_ns: int,
                      step_ns: int = 100 * MS) -> float | None:
    """Fraction of time samples in [t0, t1] at which the newest track (at most 300 ms old) was
    TRACKING/REACQUIRED; samples at which the scene hid the target are not counted. None: nothing to judge."""
    own = sorted((t for t in tracks if t.source != INJECTOR), key=lambda t: t.recv_ns)
    gts = sorted(truth, key=lambda g: g.recv_ns)
    recv = [t.recv_ns for t in own]
    gt_recv = [g.recv_ns for g in gts]
    counted = covered = 0
    for t in range(t0_ns, t1_ns + 1, step_ns):
        gi = int(np.searchsorted(gt_recv, t, side="right")) - 1
        if gi >= 0 and t - gts[gi].recv_ns < STALE_TRACK_NS and not gts[gi].visible:
            continue  # the scene hides the target: nobody could track it now
        counted += 1
        ti = int(np.searchsorted(recv, t, side="right")) - 1
        if ti >= 0 and t - own[ti].recv_ns < STALE_TRACK_NS and own[ti].state in FOLLOW_STATES:
            covered += 1
    return covered / counted if counted else None


def latency_figures(commands: Sequence[CommandObs], truth: Sequence[TruthObs], t0_ns: int,
                    t1_ns: int) -> dict[str, float | int | None]:
    """capture→command latency (command pub_ns - capture stamp) of the frames captured in [t0, t1], and
    the fraction of those frames that produced a command."""
    stamps = {g.stamp_ns for g in truth if t0_ns <= g.recv_ns <= t1_ns}
    answered: dict[int, float] = {}
    for c in commands:
        if c.answers_track and c.stamp_ns in stamps and c.stamp_ns not in answered:
            answered[c.stamp_ns] = (c.pub_ns - c.stamp_ns) / MS
    lat = np.asarray(list(answered.values()), dtype=float)
    return {"frames": len(stamps), "commands": int(lat.size),
            "processed": (lat.size / len(stamps)) if stamps else None,
            "p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
            "p99_ms": float(np.percentile(lat, 99)) if lat.size else None}


