"""The chaos bench's judging: what the observer saw (tracks, commands, ground truth), the pure checks on it (the
motor's limits, the watchdog's stop, recovery, tracking coverage, latency), a fault run's result and the summary
of a bench run."""

from __future__ import annotations

import logging
import math
import os
import statistics
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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
    box: tuple[float, float, float, float] | None = None  # the output box the robot follows (x, y, w, h)


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
    box: tuple[float, float, float, float] | None = None  # the target's box (x, y, w, h), None when absent


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
        from ..bus.node_params import parse_params
        from ..control.kinematics import mecanum_wheel_speeds
        from ..nodes.motor import Motor

        _, p = parse_params(Motor.Params, dict(graph.nodes["motor"].params))
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
    cannot be answered by a stop on the bus; the MCU's own stop covers it (each command's hold_ms,
    docs/motor-protocol.md).
    """
    report = WatchdogReport()
    zeros = sorted(c.pub_ns for c in commands if c.is_zero and c.recv_ns > t0_ns)
    issued = sorted((c.pub_ns, c.is_zero) for c in commands)
    for last, nxt in _track_pauses(tracks, t0_ns, t1_ns):
        if not _watched_pause(last, nxt, timeout_ms, bound_ms, motor_down):
            continue
        stop = next((z for z in zeros if last.pub_ns < z <= nxt), None)  # the first zero command in the pause
        if stop is None and not _moving_after(issued, last.pub_ns + int(bound_ms * MS), nxt):
            continue  # stopped before this track and did not move on it (a stale one, say): nothing to stop
        if stop is not None:
            report.stops_ms.append((stop - last.pub_ns) / MS)
        violation = _late_stop(last, nxt, stop, bound_ms)
        if violation is not None:
            report.violations.append(violation)
    return report


def _track_pauses(tracks: Sequence[TrackObs], t0_ns: int, t1_ns: int) -> list[tuple[TrackObs, int]]:
    """Every track received in [t0, t1], in publish order, with the ``pub_ns`` that ends the pause after it: the
    next track's, after the last one t1 (or that track's own, if later)."""
    seq = sorted((t for t in tracks if t0_ns <= t.recv_ns <= t1_ns), key=lambda t: t.pub_ns)
    end = max([t1_ns, *(t.pub_ns for t in seq)])
    return [(last, seq[i + 1].pub_ns if i + 1 < len(seq) else end) for i, last in enumerate(seq)]


def _watched_pause(last: TrackObs, next_ns: int, timeout_ms: float, bound_ms: float,
                   motor_down: tuple[int, int] | None) -> bool:
    """Whether the pause from track ``last`` to ``next_ns`` is the watchdog's to stop: longer than its timeout,
    after a state the motor moves on, and not begun while the motor itself was down (or within the bound before)."""
    gap_ms = (next_ns - last.pub_ns) / MS
    if gap_ms <= timeout_ms or last.state not in MOVING_STATES:
        return False
    return motor_down is None or not (motor_down[0] - bound_ms * MS <= last.pub_ns <= motor_down[1])


def _late_stop(last: TrackObs, next_ns: int, stop_ns: int | None, bound_ms: float) -> str | None:
    """The violation of a pause longer than the bound with no zero command within the bound (None: none)."""
    gap_ms = (next_ns - last.pub_ns) / MS
    if gap_ms > bound_ms and (stop_ns is None or (stop_ns - last.pub_ns) / MS > bound_ms):
        what = "no zero command" if stop_ns is None else f"zero command after {(stop_ns - last.pub_ns) / MS:.0f} ms"
        return f"tracks paused {gap_ms:.0f} ms after a {last.state} track: {what} (bound {bound_ms:.0f} ms)"
    return None


def _moving_after(issued: Sequence[tuple[int, bool]], from_ns: int, to_ns: int) -> bool:
    """Whether the motor was commanded to move at any time in [from_ns, to_ns): its newest command by then was not
    a zero, or one issued in the window was not. ``issued``: (pub_ns, is_zero) of every command, in order."""
    before = [zero for t, zero in issued if t <= from_ns]
    return (bool(before) and not before[-1]) or any(not zero for t, zero in issued if from_ns < t < to_ns)


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


def on_target_fraction(tracks: Sequence[TrackObs], truth: Sequence[TruthObs], t0_ns: int,
                       t1_ns: int) -> float | None:
    """Of the tracks received in [t0, t1] that the robot follows (TRACKING/REACQUIRED with a box) on frames where
    the target is in view, the fraction whose box centre lies in the target's ground-truth box: a robot that
    recovers onto a bystander is tracking, but not following its person. None: nothing to judge."""
    boxes = {g.stamp_ns: g.box for g in truth if g.visible and g.box is not None}
    counted = on = 0
    for t in tracks:
        target = boxes.get(t.stamp_ns)
        if t.source == INJECTOR or not t0_ns <= t.recv_ns <= t1_ns or t.state not in FOLLOW_STATES \
                or t.box is None or target is None:
            continue
        counted += 1
        cx, cy = t.box[0] + t.box[2] / 2.0, t.box[1] + t.box[3] / 2.0
        on += target[0] <= cx <= target[0] + target[2] and target[1] <= cy <= target[1] + target[3]
    return on / counted if counted else None


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


# ----------------------------------------------------------------------------- faults and results


@dataclass
class ChaosOptions:
    detector: str = "yolox416"  # yolox416 | simulated
    scene: str = "corridor-occlusion"
    burners: int = 0  # processes spinning a CPU each for the whole run (background load)
    load_s: float = 10.0  # the load fault and the detector delay: how long the measured stretch lasts
    recovery_bound_s: float = 2.0  # fault over (node back / injection done) -> following again
    hold_s: float = 3.0  # then: tracking most of this long
    hold_fraction: float = 0.5
    on_target_fraction: float = 0.9  # of the followed frames in the hold window, on the target (not a bystander)
    watchdog_bound_ms: float = 200.0  # the product's promise: zero command <= this after the last track
    load_p99_ms: float = 250.0
    load_processed: float = 0.5
    malformed_per_key: int = 10_000
    flood_frames: int = 300
    settle_s: float = 25.0  # before a fault: wait this long at most for the robot to follow (a scene loop)
    # and let a fresh graph run this long first: faults strike a loop in its steady state (a capture restart
    # from frame_seq 17 is not the one that happens on a robot after minutes)
    warmup_s: float = 8.0
    clear_s: float = 7.0  # a fault starts at a point of the scene with the target in view this long after it
    restart_timeout_s: float = 30.0
    record: bool = False
    port: int = 0
    namespace: str = ""  # default chaos<port>
    workdir: Path | None = None
    log_file: Path | None = None


@dataclass
class Injection:
    """What an injector did: when the fault started and ended, plus its own checks and notes."""

    start_ns: int
    end_ns: int
    back_s: float | None = None  # restarted node: kill -> liveliness back
    checks: dict[str, tuple[bool, str]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    load_window: tuple[int, int] | None = None
    injected_stamps: set[int] = field(default_factory=set)
    expect_pause: bool = False  # the fault stops the track stream (noted when no watchdog stop was seen)
    motor_down: tuple[int, int] | None = None  # the motor process itself was dead (kill -> back up)
    check_load_processed: bool = False
    after: Callable[[], None] | None = None  # checks that need the status messages after the fault


@dataclass
class Fault:
    name: str
    description: str
    inject: Callable[[Any], Injection]  # (ChaosRunner) -> what it did
    variant: str = "base"  # which launch of the graph it needs
    needs_record: bool = False
    simulated_only: bool = False


@dataclass
class FaultResult:
    fault: str
    description: str
    survived: bool
    checks: dict[str, bool]
    failures: list[str]
    unsafe_commands: int
    commands: int
    watchdog_ms: float | None
    watchdog_bound_ms: float
    back_s: float | None
    recovery_s: float | None
    recovery_bound_s: float
    hidden_s: float
    held: float | None
    on_target: float | None = None  # of the followed frames in the hold window, the fraction on the target
    latency_p50_ms: float | None = None
    latency_p99_ms: float | None = None
    processed: float | None = None
    load1: float | None = None  # 1-minute load average when the fault's judgement ended
    relaunched: bool = False
    notes: list[str] = field(default_factory=list)

    def explain(self) -> str:
        lines = [f"{self.fault}: {'survived' if self.survived else 'NOT survived'}"]
        lines += [f"  - {f}" for f in self.failures]
        lines += [f"  . {n}" for n in self.notes]
        return "\n".join(lines)


def check(checks: dict[str, tuple[bool, str]], name: str, ok: bool, detail: str) -> None:
    checks[name] = (bool(ok), detail)


def judge_safety(checks: dict[str, tuple[bool, str]], unsafe: list[Any], undecodable: int, commands: int) -> None:
    check(checks, "safe", not unsafe and not undecodable,
           f"{len(unsafe)} unsafe of {commands} commands"
           + (f" (first: {unsafe[0][1]})" if unsafe else "")
           + (f", {undecodable} undecodable" if undecodable else ""))


def judge_watchdog(checks: dict[str, tuple[bool, str]], wd: WatchdogReport, inj: Injection) -> None:
    if wd.violations:
        more = f" (+{len(wd.violations) - 3} more)" if len(wd.violations) > 3 else ""
        detail = "; ".join(wd.violations[:3]) + more
    else:
        detail = f"worst stop {wd.worst_ms:.0f} ms" if wd.stops_ms else "tracks never paused while the robot moved"
    check(checks, "watchdog", not wd.violations, detail)
    if inj.expect_pause and not wd.stops_ms:
        inj.notes.append("the fault did not pause the tracks while the robot moved (nothing for the watchdog)")


def judge_recovery(checks: dict[str, tuple[bool, str]], opts: ChaosOptions, recovery_s: float | None,
                   hidden_s: float, tracks: list[TrackObs], truth: list[TruthObs],
                   t_r: int | None) -> tuple[float | None, float | None]:
    """resumed (within the bound plus the hidden time), held (tracking most of the next seconds) and on target
    (what it tracks then is the person it followed before the fault); returns (held, on target)."""
    ok = recovery_s is not None and recovery_s <= opts.recovery_bound_s + hidden_s
    check(checks, "resumed", ok,
           f"following again {recovery_s:.2f} s after the fault ended" if recovery_s is not None
           else f"not following {opts.recovery_bound_s + hidden_s:.1f} s after the fault ended")
    if t_r is None:
        return None, None
    t_end = t_r + int(opts.hold_s * NS)
    held = tracking_coverage(tracks, truth, t_r, t_end)
    check(checks, "held", held is None or held >= opts.hold_fraction,
           f"tracking {100 * held:.0f} % of the next {opts.hold_s:.0f} s" if held is not None
           else "the scene hid the target all along")
    on_target = on_target_fraction(tracks, truth, t_r, t_end)
    check(checks, "on target", on_target is None or on_target >= opts.on_target_fraction,
           f"{100 * on_target:.0f} % of the followed frames on the target" if on_target is not None
           else "no followed frame with the target in view")
    return held, on_target


def judge_load(checks: dict[str, tuple[bool, str]], opts: ChaosOptions, inj: Injection,
                commands: list[CommandObs], truth: list[TruthObs]) -> dict[str, Any]:
    """Under load: p99 capture->command latency, and the fraction of frames that produced a command."""
    if inj.load_window is None:
        return {}
    figures = latency_figures(commands, truth, *inj.load_window)
    p99 = figures["p99_ms"]
    check(checks, "latency", p99 is not None and p99 <= opts.load_p99_ms,
           f"p99 capture->command {p99:.0f} ms" if p99 is not None else "no command under load")
    if inj.check_load_processed:
        processed = figures["processed"]
        check(checks, "processed", processed is not None and processed >= opts.load_processed,
               f"{100 * (processed or 0):.0f} % of {figures['frames']} frames produced a command")
    return figures


# ----------------------------------------------------------------------------- the summary

def fmt(value: float | None, spec: str, none: str = "—") -> str:
    return none if value is None else format(value, spec)


def _worst(results: Sequence[FaultResult], attr: str, pick: Callable[[list[Any]], Any] = max) -> Any:
    """``pick`` (max, min, median) of a figure over the results that have it; None when none has."""
    values = [getattr(r, attr) for r in results if getattr(r, attr) is not None]
    return pick(values) if values else None


def summarise(results: Sequence[FaultResult]) -> list[dict[str, Any]]:
    """One row per fault over repeats: tried, survived, worst figures."""
    rows: list[dict[str, Any]] = []
    for name in dict.fromkeys(r.fault for r in results):
        rs = [r for r in results if r.fault == name]
        rows.append({
            "fault": name, "tried": len(rs), "survived": sum(r.survived for r in rs),
            "unsafe": sum(r.unsafe_commands for r in rs), "watchdog_worst_ms": _worst(rs, "watchdog_ms"),
            "back_max_s": _worst(rs, "back_s"), "recovery_median_s": _worst(rs, "recovery_s", statistics.median),
            "recovery_max_s": _worst(rs, "recovery_s"), "not_resumed": sum(r.recovery_s is None for r in rs),
            "held_min": _worst(rs, "held", min), "on_target_min": _worst(rs, "on_target", min),
            "p50_ms": _worst(rs, "latency_p50_ms"),
            "p99_ms": _worst(rs, "latency_p99_ms"), "processed_min": _worst(rs, "processed", min),
            "load1_max": _worst(rs, "load1"),
            "failures": sorted({f.split(":", 1)[0] for r in rs for f in r.failures}),
        })
    return rows


def _percent(fraction: float | None) -> str:
    return "—" if fraction is None else f"{100 * fraction:.0f} %"


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    lines = ["| fault | survived / tried | unsafe cmds | watchdog stop ms (worst) | node back s | "
             "recovery s (median / max) | tracking held (min) | on target (min) | p50 / p99 ms | processed | "
             "load (max) | failed checks |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        rec = (f"{fmt(r['recovery_median_s'], '.2f')} / {fmt(r['recovery_max_s'], '.2f')}"
               + (f" ({r['not_resumed']} never)" if r["not_resumed"] else ""))
        lat = "—" if r["p99_ms"] is None else f"{fmt(r['p50_ms'], '.0f')} / {fmt(r['p99_ms'], '.0f')}"
        lines.append(f"| {r['fault']} | {r['survived']} / {r['tried']} | {r['unsafe']} | "
                     f"{fmt(r['watchdog_worst_ms'], '.0f')} | {fmt(r['back_max_s'], '.1f')} | {rec} | "
                     f"{fmt(None if r['held_min'] is None else 100 * r['held_min'], '.0f')}"
                     f"{'' if r['held_min'] is None else ' %'} | {_percent(r['on_target_min'])} | {lat} | "
                     f"{fmt(None if r['processed_min'] is None else 100 * r['processed_min'], '.0f')}"
                     f"{'' if r['processed_min'] is None else ' %'} | {fmt(r['load1_max'], '.1f')} | "
                     f"{', '.join(r['failures']) or '—'} |")
    return "\n".join(lines)


def headline(results: Sequence[FaultResult], load_samples: Sequence[float], options: ChaosOptions) -> dict[str, Any]:
    """The figures a reader compares across runs and machines: load, survival, unsafe commands, the worst stop,
    following latency and frames answered under load (the load fault's)."""
    return {
        "detector": options.detector, "burners": options.burners, "cpu_count": os.cpu_count(),
        "load1_mean": statistics.fmean(load_samples) if load_samples else None,
        "load1_max": max(load_samples) if load_samples else None,
        "loadavg_end": Path("/proc/loadavg").read_text().strip() if Path("/proc/loadavg").exists() else None,
        "runs": len(results), "survived": sum(r.survived for r in results),
        "unsafe_commands": sum(r.unsafe_commands for r in results),
        "commands": sum(r.commands for r in results),
        "stop_max_ms": _worst(results, "watchdog_ms"), "stop_bound_ms": options.watchdog_bound_ms,
        "following_p99_ms": _worst(results, "latency_p99_ms"), "p99_bound_ms": options.load_p99_ms,
        "frames_answered_min": _worst(results, "processed", min),
    }


def format_headline(head: dict[str, Any], launches: int, elapsed_s: float) -> str:
    answered = head["frames_answered_min"]
    return "\n".join([
        f"load: {head['burners']} background burners on {head['cpu_count']} cores; 1-min load average "
        f"{fmt(head['load1_mean'], '.1f')} mean, {fmt(head['load1_max'], '.1f')} max; "
        f"/proc/loadavg at the end: {head['loadavg_end']}",
        f"survived: {head['survived']} of {head['runs']} fault runs ({head['detector']} detector); "
        f"unsafe commands: {head['unsafe_commands']} of {head['commands']}",
        f"stop latency max: {fmt(head['stop_max_ms'], '.0f')} ms (bound {head['stop_bound_ms']:.0f}); "
        f"following p99: {fmt(head['following_p99_ms'], '.0f')} ms (bound {head['p99_bound_ms']:.0f}); "
        f"frames answered: {fmt(None if answered is None else 100 * answered, '.0f')} %",
        f"{launches} launch{'es' if launches != 1 else ''} of the graph; {elapsed_s:.0f} s",
    ])
