"""Tests of the pure motion-control modules (PID, kinematics, follow controller, drivers)."""

from __future__ import annotations

import math
import os
import select
import termios
import time

import numpy as np
import pytest

from followbus.control.drivers import (
    MAX_HOLD_MS,
    STOP_LINE,
    SerialDriver,
    SimDriver,
    format_command,
    integrate_twist,
    parse_odometry_line,
)
from followbus.control.follow import FollowController, FollowParams
from followbus.control.kinematics import (
    bearing_rad,
    mecanum_body_twist,
    mecanum_wheel_speeds,
    width_based_range_m,
)
from followbus.control.pid import PID

MS = 1_000_000
S = 1_000_000_000
GEOM = {"half_length_m": 0.10, "half_width_m": 0.12, "wheel_radius_m": 0.04}


# --------------------------------------------------------------------------------------- PID
def test_pid_proportional_only() -> None:
    pid = PID(kp=2.0)
    assert pid.update(0.5, 0) == pytest.approx(1.0)
    assert pid.update(-0.25, 100 * MS) == pytest.approx(-0.5)


def test_pid_integral_accumulates_ki_e_dt_and_is_clamped() -> None:
    pid = PID(kp=0.0, ki=1.0, integral_limit=1.5)
    assert pid.update(2.0, 0) == 0.0  # first call: dt unknown, nothing integrated
    assert pid.update(2.0, 500 * MS) == pytest.approx(1.0)  # 1.0 * 2.0 * 0.5 s
    assert pid.update(2.0, 1000 * MS) == pytest.approx(1.5)  # 2.0 clamped to integral_limit
    assert pid.update(2.0, 1000 * MS) == pytest.approx(1.5)  # same stamp: nothing integrated
    pid.reset()
    assert pid.update(2.0, 2000 * MS) == 0.0


def test_pid_output_clamp() -> None:
    pid = PID(kp=10.0, output_limit=3.0)
    assert pid.update(1.0, 0) == 3.0
    assert pid.update(-1.0, 10 * MS) == -3.0


def test_pid_no_derivative_kick_and_filtered_derivative() -> None:
    pid = PID(kp=0.0, kd=1.0, derivative_tau_s=0.0)
    assert pid.update(5.0, 0) == 0.0  # no previous error → no kick
    assert pid.update(6.0, 100 * MS) == pytest.approx(10.0)  # 1.0 / 0.1 s
    filtered = PID(kp=0.0, kd=1.0, derivative_tau_s=0.1)
    filtered.update(5.0, 0)
    # alpha = 0.1 / (0.1 + 0.1) = 0.5 of the raw 10.0
    assert filtered.update(6.0, 100 * MS) == pytest.approx(5.0)


def test_pid_anti_windup_while_saturated() -> None:
    pid = PID(kp=1.0, ki=10.0, output_limit=1.0)
    for k in range(20):
        assert pid.update(5.0, k * 100 * MS) == 1.0
    assert pid.integral == 0.0  # did not wind up while saturated
    assert pid.update(-0.5, 2000 * MS) == pytest.approx(-0.5 + 10.0 * -0.5 * 0.1)


def test_pid_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError, match="kp"):
        PID(kp=-1.0)
    with pytest.raises(ValueError, match="output_limit"):
        PID(kp=1.0, output_limit=0.0)


# -------------------------------------------------------------------------------- kinematics
def test_width_based_range_from_projection() -> None:
    f, cx, width, z = 500.0, 320.0, 0.45, 2.0
    u_tl = f * (-width / 2) / z + cx  # seed 001 Eq. 6a/6b with |x_tl - x_br| = person width
    u_br = f * (width / 2) / z + cx
    assert u_br - u_tl == pytest.approx(112.5)
    assert width_based_range_m(u_br - u_tl, f, width) == pytest.approx(2.0)
    assert width_based_range_m(56.25, f, width) == pytest.approx(4.0)
    with pytest.raises(ValueError):
        width_based_range_m(0.0, f, width)


def test_bearing_sign_and_value() -> None:
    assert bearing_rad(320.0, 320.0, 500.0) == 0.0
    assert bearing_rad(320.0 - 500.0, 320.0, 500.0) == pytest.approx(math.pi / 4)  # left → +
    assert bearing_rad(400.0, 320.0, 500.0) < 0.0


def test_mecanum_pure_forward_all_equal() -> None:
    w = mecanum_wheel_speeds(0.4, 0.0, 0.0, **GEOM)
    assert w == pytest.approx((10.0, 10.0, 10.0, 10.0))


def test_mecanum_pure_strafe_diagonal_pairs_opposite() -> None:
    fl, fr, rl, rr = mecanum_wheel_speeds(0.0, 0.2, 0.0, **GEOM)  # left
    assert fl == pytest.approx(rr) and fr == pytest.approx(rl)
    assert fl == pytest.approx(-fr) and fl < 0 < fr
    assert fr == pytest.approx(5.0)


def test_mecanum_pure_rotation_sides_opposite() -> None:
    fl, fr, rl, rr = mecanum_wheel_speeds(0.0, 0.0, 1.0, **GEOM)  # CCW
    assert fl == pytest.approx(rl) and fr == pytest.approx(rr)
    assert fl == pytest.approx(-fr) and fl < 0 < fr
    assert fr == pytest.approx((0.10 + 0.12) / 0.04)


def test_mecanum_forward_inverse_round_trip() -> None:
    rng = np.random.default_rng(7)
    for vx, vy, wz in rng.uniform(-2.0, 2.0, size=(50, 3)):
        wheels = mecanum_wheel_speeds(vx, vy, wz, **GEOM)
        assert mecanum_body_twist(wheels, **GEOM) == pytest.approx((vx, vy, wz), abs=1e-12)


# -------------------------------------------------------------------------------- follow
def _params(**overrides: object) -> FollowParams:
    values = {"focal_px": 500.0, "image_width_px": 640, "person_width_m": 0.45,
              "target_distance_m": 1.5, **overrides}
    return FollowParams.from_dict(values)


def _box(range_m: float, centre_u: float = 320.0, focal_px: float = 500.0) -> list[float]:
    w = focal_px * 0.45 / range_m
    return [centre_u - w / 2, 100.0, w, 2.5 * w]


def test_follow_params_defaults_and_from_dict() -> None:
    p = FollowParams()
    assert p.cx_px == 640.0 and p.target_distance_m == 1.5 and p.watchdog_timeout_ms == 130.0
    assert _params().cx_px == 320.0
    with pytest.raises(ValueError, match="max_sped_mps"):
        FollowParams.from_dict({"max_sped_mps": 1.0})
    with pytest.raises(ValueError, match="max_speed_mps"):
        FollowParams.from_dict({"max_speed_mps": -1.0})


def test_follow_centred_at_target_distance_is_zero() -> None:
    ctl = FollowController(_params())
    for k in range(10):
        cmd = ctl.on_track(k * 33 * MS, "TRACKING", _box(1.5))
    assert cmd.range_m == pytest.approx(1.5)
    assert cmd.bearing_rad == pytest.approx(0.0)
    assert cmd.vx_mps == pytest.approx(0.0, abs=1e-9)
    assert cmd.wz_radps == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(cmd.wheel_radps, 0.0, atol=1e-7)
    assert cmd.reason == "tracking"


def test_follow_target_left_turns_left() -> None:
    ctl = FollowController(_params())
    cmd = ctl.on_track(0, "TRACKING", _box(1.5, centre_u=200.0))
    assert cmd.bearing_rad > 0 and cmd.wz_radps > 0
    fl, fr, rl, rr = cmd.wheel_radps
    assert fr > fl and rr > rl


def test_follow_too_far_drives_forward_too_close_backs_off() -> None:
    ctl = FollowController(_params())
    cmd = ctl.on_track(0, "TRACKING", _box(3.0))
    assert cmd.range_m == pytest.approx(3.0)
    assert cmd.vx_mps > 0 and np.all(cmd.wheel_radps > 0)
    back = FollowController(_params())
    assert back.on_track(0, "TRACKING", _box(0.8)).vx_mps < 0


def test_follow_acceleration_limit_between_commands() -> None:
    p = _params(max_accel_mps2=1.0, max_yaw_accel_radps2=3.0)
    ctl = FollowController(p)
    first = ctl.on_track(0, "TRACKING", _box(5.0, centre_u=100.0))  # far and left: saturating demand
    second = ctl.on_track(33 * MS, "TRACKING", _box(5.0, centre_u=100.0))
    assert second.vx_mps - first.vx_mps == pytest.approx(1.0 * 0.033)
    assert second.wz_radps - first.wz_radps == pytest.approx(3.0 * 0.033)
    assert second.vx_mps < p.max_speed_mps  # the limiter, not the speed clamp, was binding
    for k in range(2, 60):
        cmd = ctl.on_track(k * 33 * MS, "TRACKING", _box(5.0, centre_u=100.0))
    assert cmd.vx_mps == pytest.approx(p.max_speed_mps)
    assert cmd.wz_radps == pytest.approx(p.yaw_kp * cmd.bearing_rad)  # settled on the PID demand


def test_follow_lost_stops_immediately() -> None:
    ctl = FollowController(_params())
    for k in range(60):
        moving = ctl.on_track(k * 33 * MS, "TRACKING", _box(4.0, centre_u=250.0))
    assert moving.vx_mps > 0.5
    cmd = ctl.on_track(60 * 33 * MS, "LOST", _box(4.0))
    assert (cmd.vx_mps, cmd.vy_mps, cmd.wz_radps) == (0.0, 0.0, 0.0)
    assert np.all(cmd.wheel_radps == 0.0) and cmd.reason == "target-lost"
    assert cmd.range_m is None and cmd.bearing_rad is None
    assert ctl.on_track(61 * 33 * MS, "TRACKING", None).reason == "target-lost"
    assert ctl.on_track(62 * 33 * MS, "TRACKING", [0, 0, 0, 0]).is_zero  # degenerate box


def test_follow_occluded_reduced_speed() -> None:
    p = _params(max_accel_mps2=100.0, max_yaw_accel_radps2=100.0)
    tracking = FollowController(p).on_track(0, "TRACKING", _box(2.5, centre_u=280.0))
    occluded = FollowController(p).on_track(0, "OCCLUDED", _box(2.5, centre_u=280.0))
    assert occluded.reason == "occluded"
    assert occluded.vx_mps == pytest.approx(p.occluded_speed_scale * tracking.vx_mps)
    assert occluded.wz_radps == pytest.approx(p.occluded_speed_scale * tracking.wz_radps)
    assert 0 < occluded.vx_mps < tracking.vx_mps
    # A coast too uncertain to locate the person comes without a box (tracking/kalman.py output_box): a stop.
    ctl = FollowController(p)
    assert not ctl.on_track(0, "OCCLUDED", _box(2.5, centre_u=280.0)).is_zero
    stop = ctl.on_track(33 * MS, "OCCLUDED", None)
    assert stop.is_zero and stop.reason == "target-lost"


def test_follow_strafe_from_bearing_flag() -> None:
    box = _box(1.5, centre_u=200.0)
    assert FollowController(_params()).on_track(0, "TRACKING", box).vy_mps == 0.0
    cmd = FollowController(_params(strafe_from_bearing=True)).on_track(0, "TRACKING", box)
    assert cmd.vy_mps > 0


def test_watchdog() -> None:
    ctl = FollowController(_params())
    assert ctl.on_tick(0).reason == "watchdog"  # never received a track: stay stopped
    for k in range(30):
        ctl.on_track(k * 33 * MS, "TRACKING", _box(3.0))
    last = 29 * 33 * MS
    assert not ctl.last_command.is_zero
    assert ctl.on_tick(last + 120 * MS) is None
    cmd = ctl.on_tick(last + 250 * MS)
    assert cmd is not None and cmd.reason == "watchdog" and cmd.is_zero
    assert np.all(cmd.wheel_radps == 0.0)
    assert ctl.on_tick(last + 270 * MS).is_zero  # keeps stopping

    resumed = ctl.on_track(last + 300 * MS, "TRACKING", _box(3.0))
    assert 0 < resumed.vx_mps <= ctl.params.max_accel_mps2 * 0.030 + 1e-12  # ramps up from zero


def test_watchdog_trusts_receive_times_not_stamps() -> None:
    """A track stamped an hour ahead must not hold the watchdog off: it runs on the receive clock."""
    ctl = FollowController(FollowParams(image_width_px=640, focal_px=450.0))
    hour = 3600 * 10**9
    ctl.on_track(hour, "TRACKING", [300, 100, 60, 150], received_ns=1_000 * MS)
    assert ctl.on_tick(5 * MS, now_received_ns=1_100 * MS) is None
    cmd = ctl.on_tick(6 * MS, now_received_ns=1_140 * MS)
    assert cmd is not None and cmd.reason == "watchdog" and cmd.is_zero


def test_follow_a_position_uses_the_same_law_as_a_box() -> None:
    """on_position (a group's centre, seed 004): range = distance, bearing = angle; a person straight ahead
    at 3 m gives the same command as its box; left turns left; lost, invalid and behind stop at once."""
    by_box, by_pos = FollowController(_params()), FollowController(_params())
    for k in range(20):
        a = by_box.on_track(k * 33 * MS, "TRACKING", _box(3.0))
        b = by_pos.on_position(k * 33 * MS, "TRACKING", [3.0, 0.0])
    assert (b.vx_mps, b.wz_radps, b.range_m, b.reason) == pytest.approx((a.vx_mps, a.wz_radps, 3.0, "tracking"))
    left = FollowController(_params()).on_position(0, "TRACKING", [2.0, 1.0])
    assert left.bearing_rad == pytest.approx(math.atan2(1.0, 2.0)) and left.wz_radps > 0
    assert left.range_m == pytest.approx(math.hypot(2.0, 1.0))
    fast = _params(max_accel_mps2=100.0, max_yaw_accel_radps2=100.0)
    occluded = FollowController(fast).on_position(0, "OCCLUDED", [2.5, 0.0])
    tracking = FollowController(fast).on_position(0, "TRACKING", [2.5, 0.0])
    assert occluded.reason == "occluded" and tracking.vx_mps > 0
    assert occluded.vx_mps == pytest.approx(0.5 * tracking.vx_mps)
    assert by_pos.on_position(21 * 33 * MS, "LOST", [3.0, 0.0]).reason == "target-lost"
    for bad in ([-2.0, 0.5], [math.nan, 0.0], [1.0]):
        for k in range(5):
            by_pos.on_position(k * 33 * MS, "TRACKING", [3.0, 0.0])
        cmd = by_pos.on_position(6 * 33 * MS, "TRACKING", bad)
        assert cmd.is_zero and cmd.reason == "invalid-target", bad
    # The watchdog is the same: no position for watchdog_timeout_ms -> zero.
    by_pos.on_position(0, "TRACKING", [3.0, 0.0])
    assert by_pos.on_tick(100 * MS) is None and by_pos.on_tick(140 * MS).reason == "watchdog"


# -------------------------------------------------------------------------------- drivers
def _forward(v_mps: float) -> tuple[float, float, float, float]:
    return mecanum_wheel_speeds(v_mps, 0.0, 0.0, **GEOM)


def test_sim_forward_one_second() -> None:
    sim = SimDriver(**GEOM)
    sim.apply(_forward(0.4), 0)
    odo = sim.apply(_forward(0.4), S)
    assert (odo.x_m, odo.y_m, odo.theta_rad) == pytest.approx((0.4, 0.0, 0.0), abs=1e-12)
    assert odo.vx_mps == pytest.approx(0.4) and odo.header.stamp_ns == S
    stepped = SimDriver(**GEOM)
    for k in range(31):
        odo = stepped.apply(_forward(0.4), k * S // 30)
    assert odo.x_m == pytest.approx(0.4)


def test_sim_rotation_strafe_and_circle() -> None:
    sim = SimDriver(**GEOM)
    sim.apply(mecanum_wheel_speeds(0.0, 0.0, 1.0, **GEOM), 0)
    odo = sim.apply(np.zeros(4), int(math.pi / 2 * S))
    assert odo.theta_rad == pytest.approx(math.pi / 2, abs=1e-9)
    assert (odo.x_m, odo.y_m) == pytest.approx((0.0, 0.0), abs=1e-12)
    odo = sim.apply(mecanum_wheel_speeds(0.0, 0.2, 0.0, **GEOM), odo.header.stamp_ns)
    odo = sim.apply(np.zeros(4), odo.header.stamp_ns + S)  # strafe left while facing +y → moves to −x
    assert (odo.x_m, odo.y_m) == pytest.approx((-0.2, 0.0), abs=1e-9)
    circle = SimDriver(**GEOM)
    circle.apply(mecanum_wheel_speeds(0.5, 0.0, 0.5, **GEOM), 0)
    odo = circle.apply(np.zeros(4), int(2 * math.pi / 0.5 * S))
    assert (odo.x_m, odo.y_m, odo.theta_rad) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
    assert integrate_twist(0, 0, 0, 0.5, 0, 0.5, math.pi / 0.5)[:2] == pytest.approx((0.0, 2.0))  # diameter
    # Strafing left (radius 1 m) while turning CCW curves backwards: a quarter turn ends at (−1, 1).
    assert integrate_twist(0, 0, 0, 0, 0.5, 0.5, math.pi / 2 / 0.5) == pytest.approx((-1.0, 1.0, math.pi / 2))


def test_sim_first_order_lag() -> None:
    sim = SimDriver(**GEOM, time_constant_s=0.1)
    sim.apply(_forward(0.4), 0)
    odo = sim.apply(_forward(0.4), S)
    # x = v (T − τ(1 − e^{−T/τ}))
    assert odo.x_m == pytest.approx(0.4 * (1.0 - 0.1 * (1 - math.exp(-10.0))), rel=1e-9)
    assert odo.vx_mps == pytest.approx(0.4 * (1 - math.exp(-10.0)))


def test_serial_format_parse_round_trip() -> None:
    assert format_command([1, -1, 0.12345, -0.0004], 190) == b"M 1.000 -1.000 0.123 0.000 190\n"
    # The MCU's own stop: rounded down, never negative, never beyond MAX_HOLD_MS, never NaN.
    assert format_command([0, 0, 0, 0], 12.9).endswith(b" 12\n")
    assert format_command([0, 0, 0, 0], -5).endswith(b" 0\n")
    assert format_command([0, 0, 0, 0], 1e9).endswith(f" {MAX_HOLD_MS}\n".encode())
    assert STOP_LINE == b"S\n"  # the serial driver's stop, the line protocol's
    with pytest.raises(ValueError):
        format_command([float("nan"), 0, 0, 0], 100)
    with pytest.raises(ValueError):
        format_command([0, 0, 0], 100)
    with pytest.raises(ValueError):
        format_command([0, 0, 0, 0], float("nan"))
    line = b"O 1.500 -0.250 0.785 0.400 0.000 -0.100\r\n"
    odo = parse_odometry_line(line, 42)
    assert (odo.header.stamp_ns, odo.x_m, odo.y_m, odo.theta_rad, odo.vx_mps, odo.vy_mps, odo.wz_radps) == (
        42, 1.5, -0.25, 0.785, 0.4, 0.0, -0.1)
    wheels = (3.25, -1.5, 0.001, 12.0)
    parsed = [float(v) for v in format_command(wheels, 100).decode().split()[1:5]]
    assert parsed == list(wheels)
    for bad in ("M 1 2 3 4", "O 1 2 3", "O 1 2 3 4 5 x", "O 1 2 3 4 5 nan"):
        with pytest.raises(ValueError):
            parse_odometry_line(bad, 0)


def _read_line(fd: int, timeout_s: float = 2.0) -> bytes:
    buf = b""
    deadline = time.monotonic() + timeout_s
    while not buf.endswith(b"\n"):
        remaining = deadline - time.monotonic()
        assert remaining > 0, f"timed out, got {buf!r}"
        if select.select([fd], [], [], remaining)[0]:
            buf += os.read(fd, 1)
    return buf


def test_serial_driver_over_pty() -> None:
    master, slave = os.openpty()
    try:
        driver = SerialDriver(os.ttyname(slave), baud=115200)
        attrs = termios.tcgetattr(slave)
        assert attrs[4] == termios.B115200 and attrs[5] == termios.B115200
        assert not attrs[3] & termios.ICANON and not attrs[1] & termios.OPOST

        driver.write_command([1.0, -2.0, 0.5, 0.0], 150)
        assert _read_line(master) == b"M 1.000 -2.000 0.500 0.000 150\n"

        assert driver.read_odometry(0.05) is None
        os.write(master, b"hello from mcu\nO 1 2 ")  # debug line and a partial odometry line
        assert driver.read_odometry(0.05) is None
        os.write(master, b"0.5 0.1 0 0.2\nO 1.1 2 0.5 0.1 0 0.2\n")
        odo = driver.read_odometry(1.0)
        assert odo is not None and odo.x_m == pytest.approx(1.1)  # newest of the two lines
        assert (odo.y_m, odo.theta_rad, odo.vx_mps, odo.wz_radps) == pytest.approx((2.0, 0.5, 0.1, 0.2))

        driver.close()
        assert driver.closed
        assert _read_line(master) == b"S\n"
        driver.close()  # idempotent
        with pytest.raises(OSError):
            driver.write_command([0, 0, 0, 0], 0)
    finally:
        os.close(master)
        os.close(slave)


def test_serial_driver_rejects_unknown_baud() -> None:
    with pytest.raises(ValueError, match="baud"):
        SerialDriver("/dev/null", baud=12345)


def test_motor_arms_the_mcu_stop_on_every_serial_command() -> None:
    """Issue 25: the 200 ms stop must not depend on the motor process being scheduled. Every M line carries
    how long the MCU may hold it (what is left of mcu_stop_ms since the track it answers was received)."""
    from followbus.bus.graph import apply_overrides, load_graph
    from followbus.bus.inproc import InProcessGraph
    from followbus.msgs.tracking import Track

    from .conftest import REPO

    master, slave = os.openpty()
    try:
        graph = load_graph(REPO / "graph.yaml")
        apply_overrides(graph, ["motor.driver=serial", f"motor.port={os.ttyname(slave)}", "motor.mcu_stop_ms=180"])
        with InProcessGraph(graph, nodes=["motor"]) as g:
            t0 = g.now_ns
            for k in range(3):
                g.run_until(t0 + k * 33_000_000)
                box = np.array([280.0, 120.0, 80.0, 240.0])
                track = Track(state="TRACKING", box=box, filtered_box=box)
                track.header.frame_seq, track.header.stamp_ns = k, g.now_ns
                g.inject("prediction/track", track)
                g.deliver()
            g.run_until(t0 + 500_000_000)  # the watchdog's stop
            lines = [_read_line(master) for _ in range(4)]
    finally:
        os.close(master)
        os.close(slave)
    fields = [line.split() for line in lines]
    assert all(f[0] == b"M" and len(f) == 6 for f in fields), lines
    holds = [int(f[5]) for f in fields]
    assert all(0 <= h <= 180 for h in holds), holds
    assert holds[0] >= 150  # delivered at once in-process: nearly the whole bound is left
