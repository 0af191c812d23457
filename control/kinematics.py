"""Monocular range/bearing of the target and Mecanum-wheel kinematics.

Conventions (robot body frame, REP-103 style): x forward, y left, z up; angles and yaw rates are
counter-clockwise positive seen from above. The camera looks along +x and its image u axis points
to the robot's right, so a target left of the principal point has a positive bearing.

Wheel order is always ``(fl, fr, rl, rr)`` = front-left, front-right, rear-left, rear-right, in
rad/s, positive when that wheel alone would push the robot forward (i.e. motor directions are
already flipped for the mirrored sides).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def width_based_range_m(box_width_px: float, focal_px: float, person_width_m: float) -> float:
    """Distance (m, camera optical axis) to a person from the width of the bounding box.

    Seed 001 Eq. 1: ``z = f_x · r / (u_br − u_tl)``. The text calls r the "radius" of the cylinder
    the person is modelled as, but the derivation in its Appendix VI-A sets ``|x_tl − x_br| = r``,
    i.e. r is the full metric horizontal extent between the two box edges — the person's *width*
    (2 × the cylinder radius), not the radius. ``person_width_m`` is that full width (shoulder
    breadth, ~0.45 m for an adult), and ``box_width_px = u_br − u_tl``. Like the paper, this
    assumes the person is roughly straight ahead (small bearing); the controller keeps it so.

    Example: a 0.45 m wide person 2 m away seen with f = 500 px spans 112.5 px → 2.0 m.
    """
    if not (box_width_px > 0 and math.isfinite(box_width_px)):
        raise ValueError(f"box_width_px must be finite and > 0, got {box_width_px!r}")
    if not (focal_px > 0 and math.isfinite(focal_px)):
        raise ValueError(f"focal_px must be finite and > 0, got {focal_px!r}")
    if not (person_width_m > 0 and math.isfinite(person_width_m)):
        raise ValueError(f"person_width_m must be finite and > 0, got {person_width_m!r}")
    return float(focal_px) * float(person_width_m) / float(box_width_px)


def bearing_rad(box_centre_x_px: float, cx_px: float, focal_px: float) -> float:
    """Horizontal angle to the box centre (rad), CCW positive: > 0 when the target is left of cx."""
    if not (focal_px > 0 and math.isfinite(focal_px)):
        raise ValueError(f"focal_px must be finite and > 0, got {focal_px!r}")
    # Image u grows to the right (−y), hence cx − u.
    return math.atan2(float(cx_px) - float(box_centre_x_px), float(focal_px))


def _check_geometry(half_length_m: float, half_width_m: float, wheel_radius_m: float) -> None:
    for name, value in (("half_length_m", half_length_m), ("half_width_m", half_width_m),
                        ("wheel_radius_m", wheel_radius_m)):
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"{name} must be finite and > 0, got {value!r}")


def mecanum_wheel_speeds(
    vx_mps: float,
    vy_mps: float,
    wz_radps: float,
    half_length_m: float,
    half_width_m: float,
    wheel_radius_m: float,
) -> tuple[float, float, float, float]:
    """Inverse kinematics: body twist → wheel speeds ``(fl, fr, rl, rr)`` in rad/s.

    Standard X configuration with 45° rollers (roller axes form an "X" when the chassis is seen
    from above, so driving FL alone pushes the body forward-and-right)::

        fl = (vx − vy − (lx+ly)·wz) / r        fr = (vx + vy + (lx+ly)·wz) / r
        rl = (vx + vy − (lx+ly)·wz) / r        rr = (vx − vy + (lx+ly)·wz) / r

    with lx = ``half_length_m`` (centre to axle, along x), ly = ``half_width_m`` (centre to wheel
    contact, along y), r = ``wheel_radius_m``. Consequences: pure forward → all equal; strafe left
    (vy > 0) → FR/RL forward, FL/RR backward; CCW yaw → right side forward, left side backward.
    """
    _check_geometry(half_length_m, half_width_m, wheel_radius_m)
    k = half_length_m + half_width_m
    r = wheel_radius_m
    fl = (vx_mps - vy_mps - k * wz_radps) / r
    fr = (vx_mps + vy_mps + k * wz_radps) / r
    rl = (vx_mps + vy_mps - k * wz_radps) / r
    rr = (vx_mps - vy_mps + k * wz_radps) / r
    return (float(fl), float(fr), float(rl), float(rr))


def mecanum_body_twist(
    wheel_radps: Sequence[float] | np.ndarray,
    half_length_m: float,
    half_width_m: float,
    wheel_radius_m: float,
) -> tuple[float, float, float]:
    """Forward kinematics: wheel speeds ``(fl, fr, rl, rr)`` rad/s → body twist ``(vx, vy, wz)``.

    Least-squares inverse of :func:`mecanum_wheel_speeds` (exact for consistent wheel speeds; with
    four wheels and three DoF, any inconsistent component — wheel slip — is averaged away)::

        vx = r/4 · ( fl + fr + rl + rr)
        vy = r/4 · (−fl + fr + rl − rr)
        wz = r/(4(lx+ly)) · (−fl + fr − rl + rr)
    """
    _check_geometry(half_length_m, half_width_m, wheel_radius_m)
    w = np.asarray(wheel_radps, dtype=float).reshape(-1)
    if w.shape != (4,):
        raise ValueError(f"expected 4 wheel speeds (fl, fr, rl, rr), got shape {w.shape}")
    fl, fr, rl, rr = (float(v) for v in w)
    r = wheel_radius_m
    vx = r / 4.0 * (fl + fr + rl + rr)
    vy = r / 4.0 * (-fl + fr + rl - rr)
    wz = r / (4.0 * (half_length_m + half_width_m)) * (-fl + fr - rl + rr)
    return (vx, vy, wz)
