"""Person-following controller: target track → body twist → Mecanum wheel speeds.

Control law (seed 001 §III-D: keep the person at a given x and drive its lateral offset to zero;
seed 000 §3.2: PID + Mecanum kinematics at 30 Hz):

* range  = width-based distance of the box (seed 001 Eq. 1, :func:`width_based_range_m`);
* bearing = angle of the box centre from the principal point (CCW positive, left > 0);
* ``vx = PID_range(range − target_distance_m)``   (too far → forward, too close → back off);
* ``wz = PID_yaw(bearing)``                       (target left → turn left, wz > 0);
* ``vy = PID_strafe(range · tan(bearing))`` only if ``strafe_from_bearing``; yaw still keeps the
  camera on the person (the range equation assumes it is straight ahead), the strafe only removes
  the lateral offset faster, using the Mecanum chassis' holonomy.

Track states (see ``followbus.msgs.tracking.TrackState``):

* ``TRACKING`` / ``REACQUIRED``: follow the box.
* ``OCCLUDED``: the box is the tracker's Kalman prediction, not an observation. Keep following it
  so the robot stays pointed where the person is expected to reappear (seed 000 "blind tracking"),
  but every output is scaled by ``occluded_speed_scale`` (default 0.5) and the PID integrators are
  frozen, so an extrapolation error cannot wind them up. Prediction stops giving the box once it is too
  uncertain to locate the person (KalmanParams.occluded_output_max_std_heights): no box, a stop.
* ``LOST`` / ``UNINITIALISED`` / no box: zero twist immediately (reason ``"target-lost"``).

A group's centre (seed 004, graph.group.yaml) is followed with the same law through ``on_position``: the
target is a robot-frame point (forward, left) m, range = its distance, bearing = its angle; the states and
every safety rule below are the same.

Safety: every stop (lost target, invalid box, watchdog) is commanded *at once* — it bypasses the
acceleration limiter, which only shapes motion commands. The chassis's own deceleration limits
what happens physically; a late stop is worse than an abrupt one. After a stop, motion ramps up
from zero again. ``on_tick`` is the watchdog: once no track has arrived for ``watchdog_timeout_ms``
it returns a zero command (reason ``"watchdog"``) on every tick. The watchdog trusts no message stamp:
the caller passes the time each track was *received* (``received_ns``) and the current time
(``now_received_ns``) on its own monotonic clock, so a track stamped an hour ahead cannot keep the
robot driving. With tick period p the stop is issued at most ``watchdog_timeout_ms + p`` after the
last track, so tick fast (≥ 50 Hz) or shorten the timeout.

Time comes only from arguments (message stamps for the control law, receive times for the watchdog;
both default to the stamps, for replays); nothing here reads a clock.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..tracking.params import InvalidParam
from .kinematics import bearing_rad, mecanum_wheel_speeds, width_based_range_m
from .pid import PID

log = logging.getLogger(__name__)

FOLLOW_STATES = frozenset({"TRACKING", "REACQUIRED"})
PREDICTED_STATES = frozenset({"OCCLUDED"})
STOP_STATES = frozenset({"LOST", "UNINITIALISED"})


@dataclass
class FollowParams:
    # --- set-point and camera -------------------------------------------------------------
    target_distance_m: float = 1.5
    # Seed 000 camera is 1280x720; f ≈ 900 px is a ~70° horizontal FOV. Calibrate for real use.
    image_width_px: int = 1280
    focal_px: float = 900.0
    cx_px: float | None = None  # principal point; None → image_width_px / 2
    person_width_m: float = 0.45  # full shoulder width: the "r" of seed 001 Eq. 1 (see kinematics)
    min_box_width_px: float = 4.0  # narrower boxes are degenerate (range → ∞); treated as invalid
    # --- distance → vx PID ----------------------------------------------------------------
    # ki removes the steady lag when following a person walking at constant speed.
    range_kp: float = 0.8
    range_ki: float = 0.1
    range_kd: float = 0.05
    range_integral_limit_mps: float = 0.3
    # --- bearing → wz PID -----------------------------------------------------------------
    yaw_kp: float = 1.5
    yaw_ki: float = 0.0
    yaw_kd: float = 0.05
    yaw_integral_limit_radps: float = 0.3
    # --- lateral offset (m) → vy PID, only with strafe_from_bearing -------------------------
    strafe_from_bearing: bool = False
    strafe_kp: float = 1.0
    strafe_ki: float = 0.0
    strafe_kd: float = 0.0
    strafe_integral_limit_mps: float = 0.2
    derivative_tau_s: float = 0.1  # derivative low-pass; ~3 frames at 30 Hz
    # --- limits ---------------------------------------------------------------------------
    max_speed_mps: float = 0.8
    max_reverse_mps: float = 0.3  # backing off from a too-close person is slower than following
    max_strafe_mps: float = 0.5
    max_yaw_radps: float = 1.5
    max_accel_mps2: float = 1.0  # applies to vx and vy
    max_yaw_accel_radps2: float = 3.0
    # The rate limiter's dt is capped so a command after a long gap cannot jump (one 10 Hz step).
    max_rate_dt_s: float = 0.1
    occluded_speed_scale: float = 0.5
    # Stop after this long without a track: with a 10 ms tick the zero lands ~140 ms after the last track,
    # inside the product's 200 ms promise with margin for a loaded machine.
    watchdog_timeout_ms: float = 130.0
    # --- chassis geometry (small Mecanum platform) ------------------------------------------
    half_length_m: float = 0.10
    half_width_m: float = 0.10
    wheel_radius_m: float = 0.04

    def __post_init__(self) -> None:
        if self.cx_px is None:
            self.cx_px = self.image_width_px / 2.0
        positive = (
            "target_distance_m", "image_width_px", "focal_px", "person_width_m", "min_box_width_px",
            "range_integral_limit_mps", "yaw_integral_limit_radps", "strafe_integral_limit_mps",
            "max_speed_mps", "max_strafe_mps", "max_yaw_radps", "max_accel_mps2",
            "max_yaw_accel_radps2", "max_rate_dt_s", "watchdog_timeout_ms", "half_length_m",
            "half_width_m", "wheel_radius_m",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidParam(name, f"FollowParams.{name} must be finite and > 0, got {value!r}")
        non_negative = (
            "range_kp", "range_ki", "range_kd", "yaw_kp", "yaw_ki", "yaw_kd", "strafe_kp", "strafe_ki",
            "strafe_kd", "derivative_tau_s", "max_reverse_mps",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InvalidParam(name, f"FollowParams.{name} must be finite and >= 0, got {value!r}")
        if not 0.0 <= self.occluded_speed_scale <= 1.0:
            raise InvalidParam("occluded_speed_scale", f"FollowParams.occluded_speed_scale must be in [0, 1], "
                             f"got {self.occluded_speed_scale!r}")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None) -> FollowParams:
        """Build from a config mapping; an unknown key is an error naming that key."""
        values = dict(values or {})
        known = {f.name for f in dataclasses.fields(cls)}
        for key in values:
            if key not in known:
                raise ValueError(f"unknown FollowParams key {key!r} (known: {', '.join(sorted(known))})")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class FollowCommand:
    """One motion command. ``wheel_radps`` is ``(fl, fr, rl, rr)`` rad/s from the twist."""

    t_ns: int
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    wz_radps: float = 0.0
    wheel_radps: np.ndarray = field(default_factory=lambda: np.zeros(4))
    range_m: float | None = None
    bearing_rad: float | None = None
    reason: str = ""

    @property
    def is_zero(self) -> bool:
        return self.vx_mps == 0.0 and self.vy_mps == 0.0 and self.wz_radps == 0.0


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


def _step_toward(prev: float, target: float, max_delta: float) -> float:
    return prev + _clamp(target - prev, -max_delta, max_delta)


class FollowController:
    """Turns track updates into wheel commands; see the module docstring for the behaviour."""

    def __init__(self, params: FollowParams | None = None) -> None:
        self.params = params or FollowParams()
        p = self.params
        self._range_pid = PID(p.range_kp, p.range_ki, p.range_kd, output_limit=p.max_speed_mps,
                              integral_limit=p.range_integral_limit_mps, derivative_tau_s=p.derivative_tau_s)
        self._yaw_pid = PID(p.yaw_kp, p.yaw_ki, p.yaw_kd, output_limit=p.max_yaw_radps,
                            integral_limit=p.yaw_integral_limit_radps, derivative_tau_s=p.derivative_tau_s)
        self._strafe_pid = PID(p.strafe_kp, p.strafe_ki, p.strafe_kd, output_limit=p.max_strafe_mps,
                               integral_limit=p.strafe_integral_limit_mps,
                               derivative_tau_s=p.derivative_tau_s)
        self._last_track_rx_ns: int | None = None  # watchdog: when the last track was received
        self._last_cmd: FollowCommand | None = None

    @property
    def last_command(self) -> FollowCommand | None:
        return self._last_cmd

    def reset(self) -> None:
        """Forget all state (PIDs, last command, watchdog stamp)."""
        for pid in (self._range_pid, self._yaw_pid, self._strafe_pid):
            pid.reset()
        self._last_track_rx_ns = None
        self._last_cmd = None

    # ------------------------------------------------------------------------------------------
    def on_track(self, t_ns: int, state: str, box: Sequence[float] | np.ndarray | None,
                 received_ns: int | None = None) -> FollowCommand:
        """Command for a track ``box`` = ``[x, y, w, h]`` px (top-left origin) in ``state`` at ``t_ns``,
        received at ``received_ns`` on the watchdog's clock (default: ``t_ns``)."""
        t_ns = int(t_ns)
        self._last_track_rx_ns = t_ns if received_ns is None else int(received_ns)
        if box is None or state in STOP_STATES:
            return self._stop(t_ns, "target-lost")
        if state not in FOLLOW_STATES and state not in PREDICTED_STATES:
            log.warning("unknown track state %r; stopping", state)
            return self._stop(t_ns, f"unknown-state:{state}")
        b = np.asarray(box, dtype=float).reshape(-1)
        if b.shape != (4,) or not np.all(np.isfinite(b)) or b[2] < self.params.min_box_width_px:
            log.warning("invalid target box %r; stopping", box)
            return self._stop(t_ns, "invalid-box")

        p = self.params
        x, _, w, _ = (float(v) for v in b)
        range_m = width_based_range_m(w, p.focal_px, p.person_width_m)
        cx_px = p.cx_px if p.cx_px is not None else p.image_width_px / 2.0
        bear = bearing_rad(x + w / 2.0, cx_px, p.focal_px)
        return self._follow(t_ns, state, range_m, bear)

    def on_position(self, t_ns: int, state: str, position_m: Sequence[float] | np.ndarray | None,
                    received_ns: int | None = None) -> FollowCommand:
        """Command for a target at ``position_m`` = (forward, left) m in the robot frame (a group's centre,
        seed 004) in ``state``: the same law and limits as :meth:`on_track`, with range = ‖p‖ and
        bearing = atan2(left, forward). A target not ahead of the robot (forward ≤ 0: the camera cannot see
        it) stops, like an invalid box."""
        t_ns = int(t_ns)
        self._last_track_rx_ns = t_ns if received_ns is None else int(received_ns)
        if position_m is None or state in STOP_STATES:
            return self._stop(t_ns, "target-lost")
        if state not in FOLLOW_STATES and state not in PREDICTED_STATES:
            log.warning("unknown target state %r; stopping", state)
            return self._stop(t_ns, f"unknown-state:{state}")
        pos = np.asarray(position_m, dtype=float).reshape(-1)
        if pos.shape != (2,) or not np.all(np.isfinite(pos)) or pos[0] <= 0:
            log.warning("invalid target position %r; stopping", position_m)
            return self._stop(t_ns, "invalid-target")
        return self._follow(t_ns, state, math.hypot(pos[0], pos[1]), math.atan2(pos[1], pos[0]))

    def _follow(self, t_ns: int, state: str, range_m: float, bear: float) -> FollowCommand:
        p = self.params
        predicted = state in PREDICTED_STATES
        scale = p.occluded_speed_scale if predicted else 1.0
        integrate = not predicted  # a predicted box is a guess: don't integrate its error

        vx = self._range_pid.update(range_m - p.target_distance_m, t_ns, integrate=integrate)
        vx = _clamp(vx, -p.max_reverse_mps, p.max_speed_mps) * scale
        wz = self._yaw_pid.update(bear, t_ns, integrate=integrate) * scale
        vy = 0.0
        if p.strafe_from_bearing:
            lateral_m = range_m * math.tan(bear)  # +y = left, matching the CCW bearing
            vy = self._strafe_pid.update(lateral_m, t_ns, integrate=integrate) * scale

        vx, vy, wz = self._rate_limit(t_ns, vx, vy, wz)
        reason = "occluded" if predicted else state.lower()
        return self._emit(t_ns, vx, vy, wz, range_m, bear, reason)

    def on_tick(self, t_ns: int, now_received_ns: int | None = None) -> FollowCommand | None:
        """Watchdog: a zero command (reason ``"watchdog"``) if no track for ``watchdog_timeout_ms``.

        ``now_received_ns`` is now on the clock of ``on_track``'s ``received_ns`` (default: ``t_ns``);
        a stop is stamped ``t_ns``. Returns ``None`` while tracks are fresh (nothing to publish). Also
        stops when no track has ever arrived. Repeats the zero command on every tick after expiry.
        """
        t_ns = int(t_ns)
        now_rx = t_ns if now_received_ns is None else int(now_received_ns)
        if self._last_track_rx_ns is not None:
            age_ms = (now_rx - self._last_track_rx_ns) * 1e-6
            if age_ms < self.params.watchdog_timeout_ms:
                return None
            if self._last_cmd is None or self._last_cmd.reason != "watchdog":
                log.warning("watchdog: no track for %.0f ms; stopping", age_ms)
            return self._stop(t_ns, "watchdog")
        # Before any track the robot has never moved: the stop is not remembered as the command to ramp from.
        # It is stamped on the timer's clock, later than the capture stamp of the first track, which would
        # hold that track's command at zero (dt 0); and a replay, with no tick before its first stamp, starts
        # from rest: the two must agree.
        cmd = self._stop(t_ns, "watchdog")
        self._last_cmd = None
        return cmd

    # ------------------------------------------------------------------------------------------
    def _rate_limit(self, t_ns: int, vx: float, vy: float, wz: float) -> tuple[float, float, float]:
        p = self.params
        if self._last_cmd is None:
            prev = (0.0, 0.0, 0.0)
            dt = p.max_rate_dt_s  # robot assumed at rest
        else:
            last = self._last_cmd
            prev = (last.vx_mps, last.vy_mps, last.wz_radps)
            dt = _clamp((t_ns - last.t_ns) * 1e-9, 0.0, p.max_rate_dt_s)  # stale/duplicate → no change
        dv = p.max_accel_mps2 * dt
        return (
            _step_toward(prev[0], vx, dv),
            _step_toward(prev[1], vy, dv),
            _step_toward(prev[2], wz, p.max_yaw_accel_radps2 * dt),
        )

    def _stop(self, t_ns: int, reason: str) -> FollowCommand:
        # Integrators must not carry stale effort into the next follow episode.
        for pid in (self._range_pid, self._yaw_pid, self._strafe_pid):
            pid.reset()
        return self._emit(t_ns, 0.0, 0.0, 0.0, None, None, reason)

    def _emit(self, t_ns: int, vx: float, vy: float, wz: float, range_m: float | None,
              bear: float | None, reason: str) -> FollowCommand:
        p = self.params
        wheels = np.array(mecanum_wheel_speeds(vx, vy, wz, p.half_length_m, p.half_width_m, p.wheel_radius_m))
        cmd = FollowCommand(t_ns=t_ns, vx_mps=vx, vy_mps=vy, wz_radps=wz, wheel_radps=wheels,
                            range_m=range_m, bearing_rad=bear, reason=reason)
        self._last_cmd = cmd
        return cmd
