"""Motor drivers: a deterministic simulator and a serial (UART) link to a motor MCU.

Both take wheel speeds ``(fl, fr, rl, rr)`` in rad/s (see :mod:`followbus.control.kinematics` for
the sign convention) and report planar odometry in the odometry frame (x forward at start, y left,
theta CCW, body-frame velocities).

Serial line protocol (ASCII, one message per ``\\n``-terminated line, fields separated by a single
space, decimal point ``.``):

* host → MCU ``M <fl> <fr> <rl> <rr> <hold_ms>\\n`` — wheel speed set-points in rad/s, 3 decimals, and
  how long the MCU may hold them: an integer number of milliseconds after which, with no newer ``M``
  line, it stops all wheels by itself (e.g. ``M 1.250 -1.250 1.250 -1.250 180``).
* host → MCU ``S\\n`` — stop all wheels now (sent on :meth:`SerialDriver.close`).
* MCU → host ``O <x_m> <y_m> <theta_rad> <vx_mps> <vy_mps> <wz_radps>\\n`` — optional odometry.
  Other lines from the MCU (debug text) are ignored. Trailing ``\\r`` is tolerated.

``hold_ms`` is the stop guarantee that does not depend on this host being scheduled: the motor node arms
it on every command with the time left until its 200 ms stop promise for the track the command answers
expires, so a host process that is frozen, starved of CPU or killed leaves the wheels turning at most that
long. An MCU must honour it (0: stop now); it is the guarantee under overload.
"""

from __future__ import annotations

import logging
import math
import os
import select
import termios
import time
from collections.abc import Sequence

import numpy as np

from ..msgs.robot import Odometry
from .kinematics import mecanum_body_twist

log = logging.getLogger(__name__)


def _wrap_angle(a: float) -> float:
    """Wrap to (−π, π]."""
    a = math.fmod(a + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def _as_wheels(wheel_radps: Sequence[float] | np.ndarray) -> np.ndarray:
    w = np.asarray(wheel_radps, dtype=float).reshape(-1)
    if w.shape != (4,):
        raise ValueError(f"expected 4 wheel speeds (fl, fr, rl, rr), got shape {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError(f"wheel speeds must be finite, got {w.tolist()}")
    return w


def integrate_twist(x_m: float, y_m: float, theta_rad: float, vx_mps: float, vy_mps: float,
                    wz_radps: float, dt_s: float) -> tuple[float, float, float]:
    """Exact pose after holding a constant body twist for ``dt_s`` (SE(2) exponential)."""
    phi = wz_radps * dt_s
    if abs(phi) < 1e-9:
        dxb, dyb = vx_mps * dt_s, vy_mps * dt_s
    else:
        s, c = math.sin(phi), math.cos(phi)
        dxb = (vx_mps * s + vy_mps * (c - 1.0)) / wz_radps
        dyb = (vx_mps * (1.0 - c) + vy_mps * s) / wz_radps
    ct, st = math.cos(theta_rad), math.sin(theta_rad)
    return (x_m + ct * dxb - st * dyb, y_m + st * dxb + ct * dyb, _wrap_angle(theta_rad + phi))


class SimDriver:
    """Ideal Mecanum chassis: wheel commands → forward kinematics → integrated pose.

    ``apply(cmd, t_ns)`` first advances the simulation from the previous call's stamp to ``t_ns``
    under the *previous* command (zero-order hold, like a real motor controller holding its last
    set-point), then latches ``cmd``. So applying ``w`` at t=0 and again at t=1 s moves the robot
    by ``v(w)·1 s``. The first call only sets the clock.

    ``time_constant_s`` > 0 adds a first-order lag per wheel (motor/inertia): actual speed tends to
    the command as ``1 − exp(−t/τ)``; integration then uses ``substep_s`` steps with each step's
    exact mean wheel speed. ``time_constant_s = 0`` (default) is an ideal, instantaneous drive.
    Time only comes from ``t_ns``, so runs are deterministic.
    """

    def __init__(self, half_length_m: float = 0.10, half_width_m: float = 0.10, wheel_radius_m: float = 0.04,
                 time_constant_s: float = 0.0, substep_s: float = 0.005) -> None:
        if time_constant_s < 0 or substep_s <= 0:
            raise ValueError("time_constant_s must be >= 0 and substep_s > 0")
        mecanum_body_twist(np.zeros(4), half_length_m, half_width_m, wheel_radius_m)  # validates geometry
        self.half_length_m = half_length_m
        self.half_width_m = half_width_m
        self.wheel_radius_m = wheel_radius_m
        self.time_constant_s = time_constant_s
        self.substep_s = substep_s
        self.reset()

    def reset(self, x_m: float = 0.0, y_m: float = 0.0, theta_rad: float = 0.0) -> None:
        self._pose = (float(x_m), float(y_m), _wrap_angle(float(theta_rad)))
        self._wheels = np.zeros(4)  # actual wheel speeds
        self._cmd = np.zeros(4)  # latched command
        self._t_ns: int | None = None

    def _twist(self, wheels: np.ndarray) -> tuple[float, float, float]:
        return mecanum_body_twist(wheels, self.half_length_m, self.half_width_m, self.wheel_radius_m)

    def _advance(self, dt_s: float) -> None:
        x, y, th = self._pose
        if self.time_constant_s == 0.0:
            self._wheels = self._cmd.copy()
            x, y, th = integrate_twist(x, y, th, *self._twist(self._wheels), dt_s)
        else:
            tau = self.time_constant_s
            n = max(1, math.ceil(dt_s / self.substep_s))
            h = dt_s / n
            decay = math.exp(-h / tau)
            mean_gain = tau / h * (1.0 - decay)  # mean of exp(-t/tau) over a step, normalised
            for _ in range(n):
                gap = self._wheels - self._cmd
                mean = self._cmd + gap * mean_gain
                x, y, th = integrate_twist(x, y, th, *self._twist(mean), h)
                self._wheels = self._cmd + gap * decay
        self._pose = (x, y, th)

    def apply(self, cmd_wheel_speeds: Sequence[float] | np.ndarray, t_ns: int) -> Odometry:
        """Advance to ``t_ns`` under the previous command, latch the new one, return odometry."""
        cmd = _as_wheels(cmd_wheel_speeds)
        t_ns = int(t_ns)
        if self._t_ns is None:
            self._t_ns = t_ns
        elif t_ns > self._t_ns:
            self._advance((t_ns - self._t_ns) * 1e-9)
            self._t_ns = t_ns
        else:
            log.debug("SimDriver: stamp %d does not advance past %d", t_ns, self._t_ns)
        self._cmd = cmd
        if self.time_constant_s == 0.0:
            self._wheels = cmd.copy()  # ideal drive: the reported velocity is the new command's
        return self.odometry()

    def odometry(self) -> Odometry:
        vx, vy, wz = self._twist(self._wheels)
        x, y, th = self._pose
        return Odometry.at(self._t_ns or 0, x_m=x, y_m=y, theta_rad=th, vx_mps=vx, vy_mps=vy,
                              wz_radps=wz)


# ---------------------------------------------------------------------------------------------
# Serial protocol (pure)

STOP_LINE = b"S\n"


MAX_HOLD_MS = 1000  # the longest an MCU may be told to hold a set-point


def format_command(wheel_radps: Sequence[float] | np.ndarray, hold_ms: float) -> bytes:
    """``M <fl> <fr> <rl> <rr> <hold_ms>\\n`` with 3 decimals; rejects non-finite speeds (never send NaN).

    ``hold_ms`` is rounded down and clamped to 0..MAX_HOLD_MS: the MCU stops by itself that long after this
    line unless a newer one arrives."""
    w = _as_wheels(wheel_radps)
    if not math.isfinite(hold_ms):
        raise ValueError(f"hold_ms must be finite, got {hold_ms!r}")
    hold = min(MAX_HOLD_MS, max(0, math.floor(hold_ms)))
    # round() + 0.0 turns -0.0004 into 0.000 rather than "-0.000".
    fields = " ".join(f"{round(float(v), 3) + 0.0:.3f}" for v in w)
    return f"M {fields} {hold}\n".encode("ascii")


def parse_odometry_line(line: bytes | str, t_ns: int) -> Odometry:
    """Parse ``O <x> <y> <theta> <vx> <vy> <wz>``; raise ``ValueError`` if it is not one."""
    text = line.decode("ascii", errors="replace") if isinstance(line, (bytes, bytearray)) else line
    parts = text.strip().split()
    if len(parts) != 7 or parts[0] != "O":
        raise ValueError(f"not an odometry line: {text.strip()!r}")
    try:
        values = [float(v) for v in parts[1:]]
    except ValueError as exc:
        raise ValueError(f"bad number in odometry line {text.strip()!r}") from exc
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite value in odometry line {text.strip()!r}")
    x, y, th, vx, vy, wz = values
    return Odometry.at(t_ns, x_m=x, y_m=y, theta_rad=th, vx_mps=vx, vy_mps=vy, wz_radps=wz)


# ---------------------------------------------------------------------------------------------
# Serial driver (hardware: reads the wall clock for timeouts and odometry stamps)


def _baud_constant(baud: int) -> int:
    const = getattr(termios, f"B{int(baud)}", None)
    if const is None:
        raise ValueError(f"unsupported baud rate {baud}")
    return const


class SerialDriver:
    """Motor MCU over a serial device, opened with ``os.open`` + termios raw 8N1 at ``baud``.

    Odometry samples are stamped with ``time.time_ns()`` at reception (the camera stamps' clock).
    Usable as a context manager; :meth:`close` sends ``S`` before closing.
    """

    def __init__(self, port: str, baud: int = 115200, write_timeout_s: float = 0.1) -> None:
        speed = _baud_constant(baud)
        self.port = port
        self.baud = baud
        self.write_timeout_s = write_timeout_s
        self._rx = bytearray()
        # Non-blocking so a stalled device cannot hang the control loop; no controlling tty.
        self._fd: int | None = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            self._configure(speed)
        except Exception:
            os.close(self._fd)
            self._fd = None
            raise
        log.info("serial motor driver on %s at %d baud", port, baud)

    def _configure(self, speed: int) -> None:
        assert self._fd is not None
        iflag, oflag, cflag, lflag, _, _, cc = termios.tcgetattr(self._fd)
        # Raw mode (as cfmakeraw): no echo, no line editing, no CR/LF translation, no flow control.
        iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP | termios.INLCR
                   | termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF | termios.IXANY)
        oflag &= ~termios.OPOST
        lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
        cflag &= ~(termios.CSIZE | termios.PARENB | termios.CSTOPB)
        cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
        cc[termios.VMIN] = 0
        cc[termios.VTIME] = 0
        termios.tcsetattr(self._fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])
        termios.tcflush(self._fd, termios.TCIOFLUSH)  # drop stale bytes from before we opened

    @property
    def closed(self) -> bool:
        return self._fd is None

    def _write(self, data: bytes) -> None:
        if self._fd is None:
            raise OSError(f"serial port {self.port} is closed")
        deadline = time.monotonic() + self.write_timeout_s
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._fd, view)
                view = view[n:]
                continue
            except BlockingIOError:
                pass
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"serial write to {self.port} timed out")
            select.select([], [self._fd], [], remaining)

    def write_command(self, wheel_radps: Sequence[float] | np.ndarray, hold_ms: float) -> None:
        """Send wheel speed set-points ``(fl, fr, rl, rr)`` rad/s, which the MCU holds at most ``hold_ms``."""
        self._write(format_command(wheel_radps, hold_ms))

    def stop(self) -> None:
        self._write(STOP_LINE)

    def read_odometry(self, timeout_s: float = 0.0) -> Odometry | None:
        """Newest odometry line received within ``timeout_s`` (None if none arrived).

        Drains everything already buffered and returns the latest complete ``O`` line; waits up to
        ``timeout_s`` only if none is available yet. Malformed lines are logged and skipped.
        """
        if self._fd is None:
            raise OSError(f"serial port {self.port} is closed")
        deadline = time.monotonic() + max(0.0, timeout_s)
        latest: Odometry | None = None
        while True:
            try:
                chunk = os.read(self._fd, 4096)
            except BlockingIOError:
                chunk = b""
            if chunk:
                self._rx += chunk
                parsed = self._parse_buffered()
                if parsed is not None:
                    latest = parsed
                continue  # keep draining
            if latest is not None:
                return latest
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            select.select([self._fd], [], [], remaining)

    def _parse_buffered(self) -> Odometry | None:
        latest = None
        while True:
            end = self._rx.find(b"\n")
            if end < 0:
                if len(self._rx) > 4096:  # garbage without newlines: do not grow forever
                    self._rx.clear()
                return latest
            line = bytes(self._rx[:end])
            del self._rx[: end + 1]
            if line.split()[:1] != [b"O"]:
                log.debug("serial: ignoring line %r", line)
                continue
            try:
                latest = parse_odometry_line(line, time.time_ns())
            except ValueError as exc:
                log.warning("serial: %s", exc)

    def close(self) -> None:
        """Send ``S`` (best effort), then close the device. Idempotent."""
        if self._fd is None:
            return
        try:
            self.stop()
        except OSError as exc:
            log.warning("serial: could not send stop on close: %s", exc)
        finally:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> SerialDriver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
