"""Person detections → ground-plane points with covariance (input of the group tracker, seed 004).

Frames (right-handed, metres): the *robot frame* has x forward, y left (the bearing convention of
control/: CCW positive); the *odometry frame* is the fixed frame of the robot's odometry, in which seed
004 tracks the group.

Range, two ways (``range_from``):

* ``foot`` (default): the foot row v (box bottom) is where the person touches the floor. A camera
  ``camera_height_m`` above a flat floor, pitched down by ``camera_tilt_rad``, sees pixel (u, v) along the
  ray r = (a, b·cos θ + sin θ, cos θ − b·sin θ) in a level (right, down, forward) frame, a = (u − cx)/f,
  b = (v − cy)/f. The ray meets the floor at scale s = h / (b·cos θ + sin θ), so
  forward = s·(cos θ − b·sin θ), left = −s·a. Rows at or above the horizon never meet the floor and are
  dropped, as are boxes whose bottom touches the image border (the feet are cut off: the row is not the
  floor contact).
* ``width``: seed 001 Eq. 1, z = f·r / w (``person_width_m`` = r), left = −z·a (bearing from u, as control/
  does). Needs no camera height, but a partly hidden person looks narrower, i.e. farther.

Covariance: pixel noise ``pixel_std_px`` on (u, v) (or on (u, w)) through the Jacobian of the projection,
plus ``body_std_m``² on both axes (a box's foot point is not the body's centre; people sway). Range error
grows with the square of the range, as it should for a monocular camera.

Seed 004 Eq. 4 moves a robot-frame point into the odometry frame with the robot pose (x, y, θ):
p_odom = R(θ) p_robot + (x, y), covariance R Σ Rᵀ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..msgs.group import GroundPoints
from .params import InvalidParam, check_ranges


@dataclass
class CameraGeometry:
    """Pinhole camera on the robot. Defaults: the synthetic scenes' camera at 640x480 (vision/scenes.py:
    f = 0.8·width, horizon at 40 % of the height, 1.1 m above the floor, level). Calibrate for a real one."""

    image_width_px: int = 640
    image_height_px: int = 480
    focal_px: float = 512.0
    cx_px: float | None = None  # None: image centre
    cy_px: float | None = None  # None: 40 % of the height (the scenes' horizon)
    camera_height_m: float = 1.1
    camera_tilt_rad: float = 0.0  # pitched down > 0
    camera_forward_m: float = 0.0  # camera position on the robot (robot frame), so points are robot-centred
    camera_left_m: float = 0.0

    def __post_init__(self) -> None:
        if self.cx_px is None:
            self.cx_px = self.image_width_px / 2.0
        if self.cy_px is None:
            self.cy_px = 0.4 * self.image_height_px
        for name in ("image_width_px", "image_height_px", "focal_px", "camera_height_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidParam(name, f"{name} must be finite and > 0, got {value!r}")
        if not abs(self.camera_tilt_rad) < math.pi / 2:
            raise InvalidParam("camera_tilt_rad", f"camera_tilt_rad must be within ±90°, got {self.camera_tilt_rad!r}")


@dataclass
class GroundPlaneParams:
    range_from: str = "foot"  # foot | width (seed 001 Eq. 1)
    person_width_m: float = 0.62  # r of seed 001 Eq. 1 for range_from: width (the scenes' figures, arms included)
    pixel_std_px: float = 3.0  # box-edge noise
    body_std_m: float = 0.15  # foot point vs body centre, sway
    min_score: float = 0.3  # weaker detections are not people enough to shape a group
    max_range_m: float = 20.0  # farther points are too uncertain to help (range error ∝ range²)
    border_margin_px: float = 2.0  # a box bottom this close to the image bottom has its feet cut off

    def __post_init__(self) -> None:
        if self.range_from not in ("foot", "width"):
            raise InvalidParam("range_from", f"range_from must be 'foot' or 'width', not {self.range_from!r}")
        for name in ("person_width_m", "pixel_std_px", "max_range_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InvalidParam(name, f"{name} must be finite and > 0, got {value!r}")
        if not (math.isfinite(self.body_std_m) and self.body_std_m >= 0):
            raise InvalidParam("body_std_m", f"body_std_m must be finite and >= 0, got {self.body_std_m!r}")
        check_ranges(self, non_negative=("border_margin_px",), unit_interval=("min_score",))


def boxes_to_ground(boxes: np.ndarray, cam: CameraGeometry, params: GroundPlaneParams,
                    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> GroundPoints:
    """Project detection boxes ``[x, y, w, h, score]`` (px) onto the floor: the robot-frame points, and the same
    points in the odometry frame at robot pose ``pose`` (x_m, y_m, theta_rad; seed 004 Eq. 4). A box that
    gives no point (see the module docstring) has no row."""
    b = np.asarray(boxes, dtype=float).reshape(-1, 5)
    pts, covs, keep = _project(b, cam, params)
    x, y, th = pose
    odom_pts, odom_covs = to_odometry_frame(pts[keep], covs[keep], x, y, th)
    return GroundPoints(points_robot_m=pts[keep], points_m=odom_pts, covs_m2=odom_covs,
                        scores=b[keep, 4].astype(np.float64), robot_x_m=float(x), robot_y_m=float(y),
                        robot_theta_rad=float(th))


def _project(b: np.ndarray, cam: CameraGeometry, params: GroundPlaneParams
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robot-frame points (N×2, m) and covariances (N×2×2, m²) of box rows ``b``, and which rows give one."""
    n = len(b)
    pts = np.zeros((n, 2))
    covs = np.zeros((n, 2, 2))
    keep = np.isfinite(b).all(axis=1) & (b[:, 2] > 0) & (b[:, 3] > 0) & (b[:, 4] >= params.min_score)
    f, sp = cam.focal_px, params.pixel_std_px
    a = (b[:, 0] + b[:, 2] / 2 - cam.cx_px) / f  # horizontal position of the box centre, normalised
    if params.range_from == "foot":
        v = b[:, 1] + b[:, 3]
        keep &= v < cam.image_height_px - params.border_margin_px
        bb = (v - cam.cy_px) / f
        c, s_t = math.cos(cam.camera_tilt_rad), math.sin(cam.camera_tilt_rad)
        denom = bb * c + s_t
        keep &= denom > 1e-6  # at or above the horizon: the ray never meets the floor
        scale = np.where(keep, cam.camera_height_m / np.where(denom > 1e-6, denom, 1.0), 0.0)
        fwd = scale * (c - bb * s_t)
        left = -scale * a
        # Jacobian of (forward, left) wrt (u, v) (derived in the module docstring): d fwd/dv = −s/(f·denom),
        # d left/du = −s/f, d left/dv = a·s·cos θ/(f·denom).
        dd = np.where(keep, denom, 1.0)
        J = np.zeros((n, 2, 2))
        J[:, 0, 1] = -scale / (f * dd)
        J[:, 1, 0] = -scale / f
        J[:, 1, 1] = a * scale * c / (f * dd)
    else:
        w = np.where(b[:, 2] > 0, b[:, 2], 1.0)
        fwd = f * params.person_width_m / w  # seed 001 Eq. 1
        left = -fwd * a
        # (u, w) noise: d fwd/dw = −z/w, d left/du = −z/f, d left/dw = a·z/w.
        J = np.zeros((n, 2, 2))
        J[:, 0, 1] = -fwd / w
        J[:, 1, 0] = -fwd / f
        J[:, 1, 1] = a * fwd / w
    keep &= np.isfinite(fwd) & (fwd > 0) & (np.hypot(fwd, left) <= params.max_range_m)
    pts[:, 0] = fwd + cam.camera_forward_m
    pts[:, 1] = left + cam.camera_left_m
    covs = sp * sp * J @ J.transpose(0, 2, 1) + np.eye(2) * params.body_std_m ** 2
    return pts, covs, keep


def floor_to_image(points_m: np.ndarray, cam: CameraGeometry) -> np.ndarray:
    """Robot-frame floor points (N×2, m) → pixels (N×2, u right, v down); NaN where a point is not in front of
    the camera. The inverse of the foot projection above: the point is (right, down, forward) =
    (−left, h, fwd) in the level frame, R_θᵀ takes it into the pitched camera, then the pinhole. The web
    view draws the group's floor shapes into the video with it."""
    p = np.asarray(points_m, dtype=float).reshape(-1, 2)
    fwd, left = p[:, 0] - cam.camera_forward_m, p[:, 1] - cam.camera_left_m
    c, s = math.cos(cam.camera_tilt_rad), math.sin(cam.camera_tilt_rad)
    h = cam.camera_height_m
    y_c, z_c = c * h - s * fwd, s * h + c * fwd
    front = z_c > 1e-6
    z = np.where(front, z_c, 1.0)
    uv = np.stack([cam.cx_px - cam.focal_px * left / z, cam.cy_px + cam.focal_px * y_c / z], axis=1)
    uv[~front] = np.nan
    return uv


def to_odometry_frame(points_m: np.ndarray, covs_m2: np.ndarray, x_m: float, y_m: float, theta_rad: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Seed 004 Eq. 4: robot-frame points and covariances into the odometry frame, robot pose (x, y, θ)."""
    R = rotation(theta_rad)
    pts = np.asarray(points_m, dtype=float).reshape(-1, 2) @ R.T + np.array([x_m, y_m])
    covs = R @ np.asarray(covs_m2, dtype=float).reshape(-1, 2, 2) @ R.T
    return pts, covs


def to_robot_frame(points_m: np.ndarray, x_m: float, y_m: float, theta_rad: float) -> np.ndarray:
    """Inverse of Eq. 4 for points: odometry frame → robot frame at pose (x, y, θ)."""
    R = rotation(theta_rad)
    return (np.asarray(points_m, dtype=float).reshape(-1, 2) - np.array([x_m, y_m])) @ R


def rotation(theta_rad: float) -> np.ndarray:
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s], [s, c]])
