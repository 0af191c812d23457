"""motor: follows the target with PID on bearing and width-based range (seed 001 Eq. 1), Mecanum
inverse kinematics to four wheel speeds, speed and acceleration limits.

Safety: a watchdog ticking at 100 Hz commands zero when no valid track has been *received* for
``watchdog_timeout_ms`` (130 ms: the stop lands ~140 ms after the last track, inside the 200 ms promise
with margin for a loaded machine). It runs on this process's monotonic clock, never on message stamps,
so no message can disable it. A LOST (or uninitialised) target is an immediate zero. Live, a track whose
capture is older than ``max_track_age_ms`` does not count as valid: the robot never acts on a stale view
of the world. Drivers: ``sim`` integrates the robot pose and publishes odometry (which feeds
prediction's ego-motion-aware noise, Eq. 7 of seed 000); ``serial`` writes the documented line protocol
of control/drivers.py to ``port``, and arms the MCU's own stop on every command (``hold_ms``): the MCU stops
by itself ``mcu_stop_ms`` after the track a command answers was received, so the 200 ms promise holds even
when this process is not scheduled (a machine overloaded, the process frozen or killed).

Each command carries the stamp and frame_seq of the track it answers, so end-to-end latency from
frame capture to motor command is ``command.pub_ns - command.stamp_ns``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.node_params import ParamError
from ..bus.pubsub import RateLimitedLog
from ..bus.schemas import Message
from ..control.drivers import SerialDriver, SimDriver
from ..control.follow import FollowCommand, FollowController, FollowParams
from ..msgs.group import GroupState
from ..msgs.robot import MotorCommand, Odometry
from ..msgs.tracking import Track


@dataclass
class MotorParams:
    driver: str = "sim"  # sim | serial
    port: str = ""  # serial device, e.g. /dev/ttyUSB0
    baud: int = 115200
    # live: older tracks (capture -> here) are not acted on; 0: no limit. Read on every track: followbus param set
    # changes it at once.
    max_track_age_ms: float = field(default=500.0, metadata={"live": True})
    # serial: the MCU stops by itself this long after the track a command answers was received (each command's
    # hold_ms, control/drivers.py): the stop that holds when this process is not scheduled. At most 200 ms
    # minus the serial line's time (a 40-byte line at 115200 baud: 3.5 ms).
    mcu_stop_ms: float = 190.0

    def __post_init__(self) -> None:
        if self.driver not in ("sim", "serial"):
            raise ParamError("driver", f"driver must be 'sim' or 'serial', not {self.driver!r}")
        if self.driver == "serial" and not self.port:
            raise ParamError("driver", "driver 'serial' needs a port")
        if not self.baud > 0:
            raise ParamError("baud", f"baud must be > 0, not {self.baud!r}")
        if not self.max_track_age_ms >= 0:  # a negative age would refuse every track: a robot that never follows
            raise ParamError("max_track_age_ms", f"max_track_age_ms must be >= 0 (0: no limit), "
                                                 f"not {self.max_track_age_ms!r}")
        if not 0 < self.mcu_stop_ms <= 200:
            raise ParamError("mcu_stop_ms", f"mcu_stop_ms must be in (0, 200] (the stop promise), "
                                            f"not {self.mcu_stop_ms!r}")


class Motor(Node):
    INPUTS = {"track": In(Track, required=True)}
    # A command or odometry sample that cannot go out now is worthless later: never let a congested link
    # block the control loop (the driver has already been told; the bus only reports it). Commands travel
    # in Zenoh's real-time lane, without batching, ahead of any backlog of frames or bad payloads on the same link.
    OUTPUTS = {"command": Out(MotorCommand, congestion="drop", express=True, priority="real_time"),
               "odometry": Out(Odometry, congestion="drop")}
    TIMER_PERIOD_MS = 10.0  # watchdog and odometry tick (100 Hz)
    # A standing stop is re-published at this period (not every tick): a stop dropped on a congested link
    # reaches the bus, a monitor that joins late sees it, and the bus carries 10 stops/s, not 100.
    STOP_REPEAT_MS = 100.0

    Params = (MotorParams, FollowParams)

    def setup(self) -> None:
        self.motor_params, follow = self.params
        self.controller = FollowController(follow)
        self.sim = None
        self.serial = None
        if self.motor_params.driver == "sim":
            self.sim = SimDriver(follow.half_length_m, follow.half_width_m, follow.wheel_radius_m)
        else:
            self.serial = SerialDriver(self.motor_params.port, self.motor_params.baud)
        self.wheels = np.zeros(4)
        self.last_cmd: FollowCommand | None = None
        self.commands = 0
        self.last_odom_ns = 0
        self.last_command_ns = 0  # when the last command went out (node clock)
        self.too_old = 0  # tracks not acted on: captured longer than max_track_age_ms ago
        self._too_old_warn = RateLimitedLog(self.log, 10.0)
        self.clock = self.runtime.clock
        self.live = self.clock.live  # wall time, or the in-process runtime's simulated time

    def on_message(self, name: str, msg: Message) -> None:
        if not isinstance(msg, Track):
            return
        fresh, received_ns = self._receive(msg)
        if not fresh:
            return
        cmd = self.controller.on_track(msg.header.stamp_ns, msg.state, msg.box, received_ns=received_ns)
        self._command(cmd, received_ns=received_ns)

    def _receive(self, msg: Message) -> tuple[bool, int | None]:
        """(act on it?, receive time). Controller time is the message stamp (replay-deterministic); the watchdog
        uses the receive time on this process's monotonic clock (live) so that no stamp can hold it off."""
        if not self.live:
            return True, None
        max_age_ms = self.motor_params.max_track_age_ms
        age_ms = (self.clock.wall_ns() - msg.header.stamp_ns) / 1e6
        if max_age_ms and age_ms > max_age_ms:
            self.too_old += 1
            # Said, not only counted: a robot that holds still because its tracks come late (an overloaded
            # machine) or seem to (a camera host whose clock is behind this one's) is not left to be guessed at.
            self._too_old_warn.warning(
                "not acting on a track captured %.0f ms ago (max_track_age_ms %.0f; %d so far): the graph is "
                "behind, or the capturing host's clock is behind this one's (check NTP)", age_ms, max_age_ms,
                self.too_old)
            return False, None
        return True, self.clock.monotonic_ns()

    def on_timer(self, now_ns: int) -> None:
        cmd = self.controller.on_tick(now_ns, self.clock.monotonic_ns() if self.live else None)
        repeated_stop = self.last_cmd is not None and self.last_cmd.is_zero and cmd is not None \
            and cmd.reason == self.last_cmd.reason and now_ns - self.last_command_ns < self.STOP_REPEAT_MS * 1e6
        if cmd is not None and not repeated_stop:
            self._command(cmd)
        if self.sim is not None:
            self._odometry(self.sim.apply(self.wheels, now_ns))
        elif self.serial is not None:
            sample = self.serial.read_odometry(0.0)
            if sample is not None:
                self._odometry(sample)

    def _command(self, cmd: FollowCommand, received_ns: int | None = None) -> None:
        """Drive the wheels and publish the command: inside on_message with the header of the track it answers,
        from the timer stamped with the node clock (wall time live)."""
        self.wheels = np.asarray(cmd.wheel_radps, dtype=np.float64)  # the sim integrates them on its tick
        if self.serial is not None:
            self.serial.write_command(self.wheels, self._hold_ms(received_ns))
        out = MotorCommand(vx_mps=cmd.vx_mps, vy_mps=cmd.vy_mps, wz_radps=cmd.wz_radps, wheel_radps=self.wheels,
                           range_m=cmd.range_m, bearing_rad=cmd.bearing_rad, reason=cmd.reason)
        self.publish("command", out)
        self.last_cmd = cmd
        self.last_command_ns = self.clock.now_ns()
        self.commands += 1

    def _hold_ms(self, received_ns: int | None) -> float:
        """How long the MCU may hold a command answering a track received at ``received_ns`` (None: a stop, or
        a replay): what is left of ``mcu_stop_ms`` since then."""
        bound = self.motor_params.mcu_stop_ms
        if received_ns is None:
            return bound
        return bound - (self.clock.monotonic_ns() - received_ns) / 1e6

    def _odometry(self, sample: Odometry) -> None:
        if sample.header.stamp_ns <= self.last_odom_ns:
            return
        self.last_odom_ns = sample.header.stamp_ns
        self.publish("odometry", sample)

    def teardown(self) -> None:
        if self.serial is not None:
            self.serial.close()  # sends the stop line

    def status(self) -> dict[str, Any]:
        last = self.last_cmd
        return {"commands": self.commands, "too_old": self.too_old, "reason": last.reason if last else "",
                "vx_mps": round(last.vx_mps, 3) if last else 0.0, "wz_radps": round(last.wz_radps, 3) if last else 0.0}


class GroupMotor(Motor):
    """motor following a group's centre (seed 004; graph.group.yaml runs it as followbus.nodes.group_motor).

    Input ``group``: the group node's state. Valid → follow ``centre_robot_m`` (state TRACKING), coasting on
    the prediction (no member seen this frame) → OCCLUDED (half speed, integrators frozen), no group → an
    immediate zero. The watchdog, the age limit and every stop are Motor's, unchanged."""

    INPUTS = {"group": In(GroupState, required=True)}

    def on_message(self, name: str, msg: Message) -> None:
        if not isinstance(msg, GroupState):
            return
        fresh, received_ns = self._receive(msg)
        if not fresh:
            return
        state = "LOST" if not msg.valid else "OCCLUDED" if msg.lost else "TRACKING"
        cmd = self.controller.on_position(msg.header.stamp_ns, state, msg.centre_robot_m if msg.valid else None,
                                          received_ns=received_ns)
        self._command(cmd, received_ns=received_ns)


NODE = Motor
