"""Built-in synthetic scenes with exact ground truth, deterministic from a seed.

A scene is a small 3-D world seen by a pinhole camera (focal 0.8 x width px, horizon at 40 % of
the height, mounted 1.1 m above a flat floor): a ray-cast textured environment (corridor, hall
or street), box occluders (pillars, walls), and walking people drawn as simple figures (head,
neck, shirt torso and arms, trousers legs, shoes) whose boxes come from the projection.

Ground truth per frame (:class:`SceneFrame`):

* ``target_box``: the figure's full extent ``(x, y, w, h)`` in pixels - *including* parts
  hidden behind occluders or other people - clipped to the image; ``None`` when not a single
  figure pixel is visible (fully occluded or out of view);
* ``target_visible_fraction``: exact visible pixels / figure pixels (occluders, nearer
  people and the image border all count as hiding);
* ``distractor_boxes``: same for every other person with at least one visible pixel;
* ``ego_velocity_mps``: the camera platform's (forward, left) velocity.

Rendering is made to look like a camera image, not a cartoon: perspective textured floors and
walls, mild defocus blur and Gaussian sensor noise (fresh each frame, so frame differencing
sees noise like it would on a real camera). Trajectories do not depend on the seed (occlusion
timing is part of each scene's contract); textures, noise, gait phase and small clothing-shade
jitter do.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import cv2
import numpy as np

from ..msgs.box import Box

CAMERA_HEIGHT_M = 1.1
FIGURE_WIDTH_RATIO = 0.36  # figure width / height (arms included)
# Torso sample region as fractions of the figure box (x0, y0, x1, y1): well inside the shirt.
TORSO_REGION = (0.32, 0.22, 0.68, 0.45)

SCENES: dict[str, str] = {
    "corridor-occlusion": "20 s corridor: target walks away swaying, hides ~1.5 s behind a wall corner, "
    "re-emerges; a green-shirted passer-by approaches (demo default)",
    "lookalike": "10 s hall: a similarly dressed person crosses just behind the target, then walks beside it",
    "wall-occlusion": "8 s hall: target crosses laterally behind a free-standing wall (~1.2 s fully hidden) "
    "and re-emerges on the other side",
    "night-puddles": "10 s night street: dark scene, target walks over bright low-saturation specular "
    "puddles (V>220, S<45) and through a streetlight pool",
    "sun-shadow": "10 s sunny street: target walks into a building's shadow (abrupt ~0.45x brightness) "
    "and back into the sun",
    "ego-motion": "10 s corridor seen from a strafing, yawing, vibrating robot: the whole image shifts, "
    "ego velocity non-zero",
    "lost-target": "8 s hall: target walks out of view to the right at ~3.5 s and never returns",
    "group-walk": "20 s hall: a group of 5 walks away together (no single target; follow the group, seed 004), "
    "one member is hidden behind another for ~4.5 s, a passer-by walks towards the robot beside them",
    "overlay": "10 s street seen by a camera panning to and fro (up to ~23 px/frame) through a burned-in clock, "
    "a logo and a strip of the robot's own body fixed in the image; a look-alike crosses behind the target",
    "bumpy": "10 s hall from a robot on a bumpy floor: seven 54-58 px jerks of the whole image, each smearing its "
    "frame (no detection of anyone there), settling over ~2 s; three people around the target",
    "runners": "10 s street: the target runs away among three runners dressed alike, side by side 0.5-0.9 m apart "
    "at 7-16 m (small to a coarse detector, which boxes neighbours together), two of them overtaking it",
    "shaky": "10 s hall from a hand-held camera: five jerks that re-aim it by 70-100 px over 3 frames, every "
    "frame of a jerk smeared along it (too blurred to fit the camera's motion on, not to detect the target in); "
    "a bystander far off",
}
DEFAULT_SCENE = "corridor-occlusion"


# ----------------------------------------------------------------------------- public data types


@dataclass(frozen=True)
class PersonStyle:
    """Clothing colours (BGR, under unit illumination) and body height of a figure."""

    shirt_bgr: tuple[int, int, int]
    trousers_bgr: tuple[int, int, int]
    hair_bgr: tuple[int, int, int] = (30, 32, 38)
    skin_bgr: tuple[int, int, int] = (125, 155, 205)
    shoes_bgr: tuple[int, int, int] = (28, 28, 30)
    height_m: float = 1.72


@dataclass(frozen=True)
class SceneFrame:
    index: int
    t_ns: int
    bgr: np.ndarray
    target_box: Box | None
    target_visible_fraction: float
    distractor_boxes: list[Box]
    ego_velocity_mps: tuple[float, float]
    distractor_visible_fractions: list[float] = field(default_factory=list)
    camera_offset_px: tuple[float, float] = (0.0, 0.0)  # whole-image shift applied this frame
    motion_blur_px: float = 0.0  # length of this frame's camera-motion smear (scene:bumpy's jerk frames)

    def people(self) -> list[tuple[Box | None, float]]:
        """``(box, visible_fraction)`` for the target (first) and every visible distractor;
        the input :class:`followbus.vision.detectors.SimulatedDetector` expects."""
        out: list[tuple[Box | None, float]] = [(self.target_box, self.target_visible_fraction)]
        out.extend(zip(self.distractor_boxes, self.distractor_visible_fractions, strict=False))
        return out


def torso_region(box: Sequence[float]) -> tuple[int, int, int, int]:
    """Integer ``(x0, y0, x1, y1)`` pixel rectangle of the shirt torso inside a figure box."""
    x, y, w, h = box
    fx0, fy0, fx1, fy1 = TORSO_REGION
    return (round(x + fx0 * w), round(y + fy0 * h), round(x + fx1 * w), round(y + fy1 * h))


# ----------------------------------------------------------------------------- world description


@dataclass
class _Camera:
    width: int
    height: int
    f_px: float
    cx: float
    cy: float
    height_m: float = CAMERA_HEIGHT_M

    @classmethod
    def for_size(cls, width: int, height: int) -> _Camera:
        return cls(width, height, 0.8 * width, width / 2.0, 0.40 * height)

    def figure_box(
        self, x_m: float, z_m: float, height_m: float, bob_m: float = 0.0, offset_px: tuple[float, float] = (0, 0)
    ) -> tuple[int, int, int, int]:
        """Integer (x, y, w, h) of a figure standing at lateral ``x_m``, depth ``z_m``."""
        f = self.f_px
        bottom = self.cy + f * self.height_m / z_m + offset_px[1]
        top = self.cy - f * (height_m + bob_m - self.height_m) / z_m + offset_px[1]
        h = bottom - top
        w = FIGURE_WIDTH_RATIO * h
        u = self.cx + f * x_m / z_m + offset_px[0]
        return round(u - w / 2), round(top), max(3, round(w)), max(6, round(h))


@dataclass
class _Actor:
    role: str  # "target", "distractor" or "member" (of the followed group: boxes like distractors)
    style: PersonStyle
    keyframes: list[tuple[float, float, float]]  # (t_s, x_m, z_m), piecewise linear, absent outside
    sway_m: float = 0.0  # lateral body sway of a walker seen from behind
    sway_period_s: float = 2.2

    def position(self, t: float) -> tuple[float, float] | None:
        kf = self.keyframes
        if t < kf[0][0] or t > kf[-1][0]:
            return None
        for (t0, x0, z0), (t1, x1, z1) in zip(kf, kf[1:], strict=False):
            if t <= t1:
                a = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
                x, z = x0 + a * (x1 - x0), z0 + a * (z1 - z0)
                break
        else:
            x, z = kf[-1][1], kf[-1][2]
        return x + self.sway_m * math.sin(2 * math.pi * t / self.sway_period_s), z


@dataclass
class _Occluder:
    """Axis-aligned box standing on the floor, from lateral x0..x1 and depth z0..z1."""

    x0_m: float
    x1_m: float
    z0_m: float
    z1_m: float
    height_m: float
    bgr: tuple[int, int, int]


@dataclass
class _Env:
    kind: str  # corridor | hall | street
    half_width_m: float
    wall_height_m: float
    far_m: float
    floor_bgr: tuple[int, int, int]
    floor_alt_bgr: tuple[int, int, int]
    wall_bgr: tuple[int, int, int]
    top_bgr: tuple[int, int, int]  # ceiling (indoor) or sky (outdoor)
    tile_m: float = 0.6
    ceiling: bool = True
    ambient: float = 1.0
    lights: list[tuple[float, float, float, float]] = field(default_factory=list)  # x, y, z, gain
    light_radius_m: float = 2.5
    puddles: list[tuple[float, float, float, float]] = field(default_factory=list)  # x, z, rx, rz
    shadow_z_m: tuple[float, float] | None = None  # depth band of the ground in shadow
    shadow_gain: float = 0.45


@dataclass
class _Spec:
    name: str
    duration_s: float
    env: _Env
    actors: list[_Actor]
    occluders: list[_Occluder] = field(default_factory=list)
    noise_sigma: float = 2.0
    ego: bool = False  # strafing/yawing camera (ego-motion scene)
    # still | ego (strafe + yaw) | pan (follows the target) | bumpy (jerks) | shaky (hand-held re-aims)
    camera: str = "still"
    overlay: bool = False  # screen-fixed content: clock, logo, the robot's own body (scene:overlay)

    def __post_init__(self) -> None:
        if self.ego:
            self.camera = "ego"


# ----------------------------------------------------------------------------- rendering helpers


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: int) -> np.ndarray:
    """Low-frequency noise in [-1, 1] (bilinear upsampled random grid) for surface textures."""
    gh, gw = max(2, shape[0] // cell_px + 2), max(2, shape[1] // cell_px + 2)
    g = rng.uniform(-1, 1, size=(gh, gw)).astype(np.float32)
    return cv2.resize(g, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC).clip(-1, 1)


def _render_environment(
    cam: _Camera, env: _Env, occluders: Sequence[_Occluder], rng: np.random.Generator, margin: tuple[int, int]
) -> tuple[np.ndarray, list[tuple[np.ndarray, float]]]:
    """Ray-cast the static world onto a (H + 2 my, W + 2 mx) canvas.

    Returns the background BGR and, per occluder, its (boolean mask, depth) on that canvas.
    """
    mx, my = margin
    H, W = cam.height + 2 * my, cam.width + 2 * mx
    f, cx, cy, ch = cam.f_px, cam.cx + mx, cam.cy + my, cam.height_m
    u, v = np.meshgrid(np.arange(W, dtype=np.float32) + 0.5, np.arange(H, dtype=np.float32) + 0.5)
    du, dv = u - cx, v - cy
    inf = np.float32(1e9)
    hw, wh = env.half_width_m, env.wall_height_m

    with np.errstate(divide="ignore", invalid="ignore"):
        z_floor = np.where(dv > 0, f * ch / dv, inf)
        z_top = np.where(dv < 0, f * (wh - ch) / -dv, inf) if env.ceiling else np.full_like(u, inf)
        z_wall = np.where(du != 0, f * hw / np.abs(du), inf)
        y_wall = ch - dv * z_wall / f
        z_wall = np.where((y_wall >= 0) & (y_wall <= wh), z_wall, inf)
    z = np.minimum(np.minimum(z_floor, z_top), np.minimum(z_wall, np.float32(env.far_m)))
    surf = np.full(u.shape, 3, np.uint8)  # 0 floor, 1 wall, 2 ceiling, 3 far wall / sky
    surf[z == z_wall] = 1
    surf[z == z_top] = 2
    surf[z == z_floor] = 0
    if not env.ceiling:
        # Outdoors: above the facades and the far plane's skyline there is sky.
        y_far = ch - dv * z / f
        surf[(surf == 3) & (y_far > wh * 0.9)] = 4
    x = du * z / f
    y = ch - dv * z / f

    tex = _smooth_noise(rng, (H, W), 24) * 0.06 + _smooth_noise(rng, (H, W), 5) * 0.03
    img = np.zeros((H, W, 3), np.float32)

    # Floor: checker tiles with grout lines that fade with distance (avoids moire far away).
    fl = surf == 0
    tiles = ((np.floor(x / env.tile_m) + np.floor(z / env.tile_m)) % 2).astype(bool)
    floor = np.where(tiles[..., None], np.float32(env.floor_alt_bgr), np.float32(env.floor_bgr))
    gx = np.abs((x / env.tile_m) - np.round(x / env.tile_m)) * env.tile_m
    gz = np.abs((z / env.tile_m) - np.round(z / env.tile_m)) * env.tile_m
    grout = ((gx < 0.012) | (gz < 0.012)) & (z < 12)
    floor = np.where(grout[..., None], floor * 0.7, floor)
    img[fl] = floor[fl]

    # Walls: panel seams every 2 m, doors every 5 m, darker skirting board.
    wl = surf == 1
    wall = np.broadcast_to(np.float32(env.wall_bgr), img.shape).copy()
    seam = np.abs(z / 2.0 - np.round(z / 2.0)) * 2.0 < 0.03
    door = ((z % 5.0) > 3.6) & ((z % 5.0) < 4.6) & (y < 2.05)
    if env.kind == "street":
        # Facade windows instead of doors.
        door = ((z % 3.0) > 1.0) & ((z % 3.0) < 2.2) & ((y % 3.0) > 1.0) & ((y % 3.0) < 2.3)
    wall[seam] *= 0.85
    wall[door] = np.float32((60, 80, 110)) if env.kind != "street" else np.float32((90, 70, 60))
    wall[y < 0.12] *= 0.6
    img[wl] = wall[wl]

    # Ceiling with light panels, or sky gradient.
    tp = surf == 2
    ceil = np.broadcast_to(np.float32(env.top_bgr), img.shape).copy()
    lamp = (np.abs(x) < 0.35) & ((z % 3.0) < 0.6)
    ceil[lamp] = np.float32((245, 248, 250))
    img[tp] = ceil[tp]
    far = surf == 3
    img[far] = np.float32(env.wall_bgr) * 0.8
    sky = surf == 4
    grad = (v / H)[..., None]
    img[sky] = (np.float32(env.top_bgr) * (0.85 + 0.3 * grad))[sky]

    # Illumination: ambient plus soft point lights, ground shadow band.
    shade = np.full(u.shape, env.ambient, np.float32)
    for lx, ly, lz, gain in env.lights:
        d2 = (x - lx) ** 2 + (y - ly) ** 2 + (z - lz) ** 2
        shade += gain / (1.0 + d2 / env.light_radius_m**2)
    shade[sky] = 1.0
    shade[tp & lamp] = 1.0
    if env.shadow_z_m is not None:
        z0, z1 = env.shadow_z_m
        in_shadow = (z >= z0) & (z <= z1) & (fl | wl)
        shade[in_shadow] *= env.shadow_gain
        img[in_shadow] *= np.float32((1.08, 1.0, 0.92))  # skylight-lit shadow is bluish
    atten = 1.0 / (1.0 + 0.025 * np.minimum(z, 40.0))
    img *= (shade * np.where(sky | (tp & lamp), 1.0, atten) * (1.0 + tex))[..., None]

    # Specular puddles: mirror the bright sky/lamps - near white, unsaturated (V > 220, S < 45).
    if env.puddles:
        pm = np.zeros(u.shape, bool)
        for px, pz, rx, rz in env.puddles:
            pm |= fl & (((x - px) / rx) ** 2 + ((z - pz) / rz) ** 2 <= 1.0)
        ripple = 1.0 + 0.03 * _smooth_noise(rng, (H, W), 3)
        img[pm] = (np.float32((236, 240, 242)) * ripple[..., None])[pm]

    occ_layers: list[tuple[np.ndarray, float]] = []
    for oc in occluders:
        col = np.zeros_like(img)
        with np.errstate(divide="ignore", invalid="ignore"):
            # Front face at z0.
            xf = du * oc.z0_m / f
            yf = ch - dv * oc.z0_m / f
            front = (xf >= oc.x0_m) & (xf <= oc.x1_m) & (yf >= 0) & (yf <= oc.height_m)
            # Side face facing the optical axis (x0 when the box is right of centre, x1 when left).
            xs = oc.x0_m if oc.x0_m > 0 else oc.x1_m if oc.x1_m < 0 else None
            side = np.zeros(u.shape, bool)
            if xs is not None:
                zs = np.where(du * xs > 0, f * xs / du, inf)
                ys = ch - dv * zs / f
                side = (zs >= oc.z0_m) & (zs <= oc.z1_m) & (ys >= 0) & (ys <= oc.height_m) & ~front
        base = np.float32(oc.bgr)
        col[front] = base
        col[side] = base * 0.78
        mask = front | side
        col *= (1.0 + tex)[..., None]
        img[mask] = col[mask]
        occ_layers.append((mask, oc.z0_m))
    return np.clip(img, 0, 255).astype(np.uint8), occ_layers


def render_figure(
    h_px: int, w_px: int, style: PersonStyle, phase: float = 0.0, lateral: float = 0.0, illum: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Draw one walking figure filling exactly an ``h_px x w_px`` patch.

    ``phase`` is the gait phase (rad), ``lateral`` in 0..1 how sideways the walk is seen
    (0 = from behind: alternating foot lifts; 1 = side-on: legs swing apart), ``illum`` a
    brightness factor. Returns (BGR uint8 patch, uint8 mask 0/255). The mask touches all four
    patch borders (head top, a planted shoe, both arms) so the figure box is tight.
    """
    H, W = int(h_px), int(w_px)
    img = np.zeros((H, W, 3), np.float32)
    mask = np.zeros((H, W), np.uint8)

    def poly(pts: Sequence[tuple[float, float]], col: Sequence[float]) -> None:
        p = np.array([[round(px * (W - 1)), round(py * (H - 1))] for px, py in pts], np.int32)
        cv2.fillConvexPoly(img, p, tuple(float(c) for c in col))
        cv2.fillConvexPoly(mask, p, 255)

    def ell(cx: float, cy: float, ax: float, ay: float, col: Sequence[float]) -> None:
        c = (round(cx * (W - 1)), round(cy * (H - 1)))
        a = (max(1, round(ax * (W - 1))), max(1, round(ay * (H - 1))))
        cv2.ellipse(img, c, a, 0, 0, 360, tuple(float(v) for v in col), -1)
        cv2.ellipse(mask, c, a, 0, 0, 360, 255, -1)

    shirt, trousers = np.float32(style.shirt_bgr), np.float32(style.trousers_bgr)
    skin, shoes = np.float32(style.skin_bgr), np.float32(style.shoes_bgr)
    s = math.sin(phase)
    lift_l = 0.035 * max(0.0, s) * (1 - lateral)
    lift_r = 0.035 * max(0.0, -s) * (1 - lateral)
    swing = 0.17 * s * lateral
    arm = 0.012 * s

    # Legs (drawn first so the trouser hips overlap their tops).
    for cxl, lift, sw in ((0.36, lift_l, swing), (0.64, lift_r, -swing)):
        ank = 0.955 - lift
        poly([(cxl - 0.13, 0.55), (cxl + 0.13, 0.55), (cxl + sw + 0.09, ank), (cxl + sw - 0.09, ank)], trousers)
        poly([(cxl + sw - 0.11, ank - 0.01), (cxl + sw + 0.11, ank - 0.01),
              (cxl + sw + 0.11, ank + 0.045), (cxl + sw - 0.11, ank + 0.045)], shoes)
    poly([(0.21, 0.49), (0.79, 0.49), (0.79, 0.585), (0.21, 0.585)], trousers)
    # Arms: sleeve then forearm and hand; outer edges reach the box sides.
    for sign, a in ((-1, arm), (1, -arm)):
        ox = 0.0 if sign < 0 else 1.0
        ix = 0.17 if sign < 0 else 0.83
        poly([(ix, 0.165), (ox + 0.02 * -sign, 0.19), (ox, 0.34 + a), (ix, 0.34 + a)], shirt * 0.93)
        poly([(ox, 0.335 + a), (ix - 0.02 * sign, 0.335 + a), (ix - 0.03 * sign, 0.475 + a),
              (ox + 0.03 * -sign, 0.475 + a)], skin)
        ell((ox + ix) / 2 - 0.01 * sign, 0.49 + a, 0.075, 0.022, skin * 0.95)
    # Torso with shoulders.
    poly([(0.15, 0.16), (0.85, 0.16), (0.80, 0.51), (0.20, 0.51)], shirt)
    ell(0.5, 0.165, 0.36, 0.03, shirt)
    # Neck and head (seen from behind it is mostly hair).
    poly([(0.42, 0.11), (0.58, 0.11), (0.58, 0.165), (0.42, 0.165)], skin * 0.9)
    ell(0.5, 0.068, 0.15, 0.068, np.float32(style.hair_bgr))
    ell(0.5, 0.105, 0.115, 0.028, np.float32(style.hair_bgr) * 1.15)

    # Soft top-down shading and cloth folds; the mean stays at the style colour.
    rows = np.linspace(1.06, 0.94, H, dtype=np.float32)[:, None, None]
    folds = 1.0 + 0.03 * np.sin(np.linspace(0, 5 * math.pi, W, dtype=np.float32))[None, :, None]
    img = img * rows * folds * float(illum)
    return np.clip(img, 0, 255).astype(np.uint8), mask


# ----------------------------------------------------------------------------- scene catalogue


# scene:overlay: the pan's amplitude (fraction of the image width) and period.
PAN_AMPLITUDE_FRACTION = 0.35
PAN_PERIOD_S = 2.0
# scene:bumpy: bumps (t_s, dx, dy) in px at 640x480 (scaled with the height), the settling time constant, the
# fraction of a bump exposed on its own frame, and how much of a smeared figure a detector can still use.
BUMPS = [(1.2, 30.0, 45.0), (2.5, -10.0, -55.0), (3.7, 45.0, 30.0), (5.0, -25.0, -52.0), (6.3, 50.0, 22.0),
         (7.6, -25.0, -50.0), (8.8, 35.0, 45.0)]
BUMP_SETTLE_S = 2.0
SMEAR_EXPOSURE = 0.8
# scene:shaky: jerks (t_s, dx, dy) in px at 640x480 (scaled with the height), each spread evenly over
# SHAKE_FRAMES frames and kept (the camera is re-aimed, it does not settle back).
SHAKES = [(1.3, 200.0, 90.0), (3.1, -200.0, -90.0), (4.9, 190.0, -90.0), (6.6, -190.0, 90.0), (8.4, 200.0, 60.0)]
SHAKE_FRAMES = 3
SHAKE_EXPOSURE = 1.0  # a hand-held camera indoors exposes the whole frame period
VIBRATION_PX = {"ego": (2.0, 1.2), "bumpy": (0.6, 0.6), "shaky": (1.0, 1.0)}  # per-frame jitter σ (x, y)
SMEAR_DETECTABLE = 0.2  # below SimulatedDetector.MIN_VISIBLE_FRACTION (0.3): the jerk frame has no detection


def motion_smear(bgr: np.ndarray, direction: tuple[float, float], length_px: float) -> np.ndarray:
    """Linear motion blur of the whole image along ``direction`` (unit), ``length_px`` long."""
    n = max(3, int(round(length_px)) | 1)
    kernel = np.zeros((n, n), np.float32)
    c = n // 2
    for i in range(n):
        a = i - c
        kernel[int(round(c + a * direction[1])), int(round(c + a * direction[0]))] = 1.0
    return cv2.filter2D(bgr, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)


def _detectable(target_vis: float, others_vis: list[float], blur_px: float) -> tuple[float, list[float]]:
    """Visible fractions as a detector sees them: smeared over 40-60 px, no figure keeps enough sharp pixels."""
    if blur_px <= 0.0:
        return target_vis, others_vis
    return target_vis * SMEAR_DETECTABLE, [v * SMEAR_DETECTABLE for v in others_vis]


def draw_overlay(bgr: np.ndarray, t_s: float) -> None:
    """Screen-fixed content, in place: a burned-in clock (top left), a logo (top right) and a strip of the
    robot's own body with hazard stripes and bolts (bottom). None of it moves with the scene."""
    h, w = bgr.shape[:2]
    s = h / 480.0
    cs = int(t_s * 100)
    clock = f"12:{(34 + cs // 6000) % 60:02d}:{(cs // 100) % 60:02d}.{cs % 100:02d}"
    cv2.rectangle(bgr, (0, 0), (int(210 * s), int(44 * s)), (0, 0, 0), -1)
    cv2.putText(bgr, clock, (int(8 * s), int(32 * s)), cv2.FONT_HERSHEY_SIMPLEX, 0.9 * s, (255, 255, 255),
                max(1, int(2 * s)), cv2.LINE_AA)
    x0, y0, cell = w - int(110 * s), int(8 * s), max(2, int(10 * s))
    for i in range(8):
        for j in range(3):
            col = (40, 40, 220) if (i + j) % 2 else (250, 250, 250)
            cv2.rectangle(bgr, (x0 + i * cell, y0 + j * cell), (x0 + (i + 1) * cell, y0 + (j + 1) * cell), col, -1)
    cv2.putText(bgr, "FB", (x0 + int(20 * s), y0 + int(60 * s)), cv2.FONT_HERSHEY_DUPLEX, 1.0 * s,
                (250, 250, 250), max(1, int(2 * s)), cv2.LINE_AA)
    top = h - int(40 * s)
    bgr[top:] = (52, 50, 48)
    band = bgr[top + int(6 * s): top + int(20 * s)]
    xs = (np.arange(band.shape[1])[None, :] + np.arange(band.shape[0])[:, None]) // max(1, int(14 * s))
    band[xs % 2 == 0] = (20, 190, 230)
    band[xs % 2 == 1] = (20, 20, 20)
    for x in range(int(30 * s), w, int(60 * s)):
        cv2.circle(bgr, (x, top + int(30 * s)), max(2, int(4 * s)), (170, 170, 175), -1)


_TARGET = PersonStyle(shirt_bgr=(42, 48, 190), trousers_bgr=(78, 50, 32), height_m=1.72)
_PASSER = PersonStyle(shirt_bgr=(70, 160, 60), trousers_bgr=(120, 170, 195), hair_bgr=(40, 60, 90), height_m=1.80)
_LOOKALIKE = PersonStyle(shirt_bgr=(52, 52, 178), trousers_bgr=(84, 56, 38), height_m=1.75)
_BYSTANDER = PersonStyle(shirt_bgr=(170, 120, 60), trousers_bgr=(50, 50, 55), height_m=1.66)

_CORRIDOR = _Env("corridor", half_width_m=1.6, wall_height_m=2.6, far_m=22.0, floor_bgr=(150, 160, 165),
                 floor_alt_bgr=(125, 135, 140), wall_bgr=(175, 200, 215), top_bgr=(205, 210, 212),
                 ambient=0.85, lights=[(0, 2.5, z, 0.25) for z in (3.0, 6.0, 9.0, 12.0)])
_HALL = replace(_CORRIDOR, kind="hall", half_width_m=6.0, wall_height_m=3.5, far_m=18.0,
                floor_bgr=(110, 120, 135), floor_alt_bgr=(95, 105, 118), wall_bgr=(190, 195, 180),
                lights=[(0, 3.4, z, 0.2) for z in (3.0, 7.0, 11.0)])


def _spec(name: str) -> _Spec:
    """Scene definitions; trajectories are in metres and seconds (camera at x = 0, looking +z)."""
    if name == "corridor-occlusion":
        # Walks away from z 2.4 m; 7.8-10.8 s steps right behind a wall corner (x >= 0.25 m at
        # z 1.6 m) and back out.
        kf = [(0.0, 0.0, 2.4), (7.8, 0.05, 3.96), (9.2, 1.12, 4.24), (10.0, 1.12, 4.4),
              (11.4, 0.05, 4.68), (20.0, -0.1, 6.4)]
        return _Spec(name, 20.0, _CORRIDOR, [
            _Actor("target", _TARGET, kf, sway_m=0.06),
            _Actor("distractor", _PASSER, [(2.0, -0.95, 13.0), (13.5, -0.95, 1.2)], sway_m=0.03),
        ], [_Occluder(0.25, 1.6, 1.6, 2.0, 2.6, (150, 175, 190))])
    if name == "lookalike":
        return _Spec(name, 10.0, _HALL, [
            _Actor("target", _TARGET, [(0.0, 0.0, 3.0), (10.0, 0.15, 5.5)], sway_m=0.06),
            _Actor("distractor", _LOOKALIKE, [(0.0, 2.6, 4.3), (3.6, 0.0, 4.25), (5.0, -0.9, 4.3),
                                              (10.0, -0.9, 6.2)], sway_m=0.05),
        ])
    if name == "wall-occlusion":
        return _Spec(name, 8.0, _HALL, [
            _Actor("target", _TARGET, [(0.0, 2.1, 4.0), (1.0, 2.1, 4.0), (7.2, -2.3, 4.0), (8.0, -2.3, 4.0)]),
        ], [_Occluder(-0.5, 0.35, 2.2, 2.4, 2.3, (120, 135, 150))])
    if name == "night-puddles":
        night = replace(
            _HALL, kind="street", ceiling=False, half_width_m=5.0, wall_height_m=9.0, far_m=40.0,
            floor_bgr=(62, 60, 58), floor_alt_bgr=(56, 55, 54), wall_bgr=(80, 78, 85), top_bgr=(28, 16, 12),
            ambient=0.32, lights=[(-2.0, 4.5, 5.0, 1.6), (2.5, 4.5, 13.0, 1.4)], light_radius_m=2.0,
            puddles=[(0.1, 3.6, 0.9, 0.55), (-0.4, 5.2, 0.7, 0.6), (0.5, 6.6, 1.1, 0.7), (-1.6, 4.2, 0.5, 0.4)],
            tile_m=1.5)
        return _Spec(name, 10.0, night, [
            _Actor("target", _TARGET, [(0.0, 0.0, 2.6), (10.0, 0.2, 7.6)], sway_m=0.07),
        ], noise_sigma=4.0)
    if name == "sun-shadow":
        street = replace(
            _HALL, kind="street", ceiling=False, half_width_m=5.0, wall_height_m=10.0, far_m=45.0,
            floor_bgr=(175, 180, 185), floor_alt_bgr=(160, 166, 172), wall_bgr=(150, 175, 200),
            top_bgr=(235, 200, 150), ambient=1.05, lights=[], shadow_z_m=(4.4, 6.2), tile_m=0.8)
        return _Spec(name, 10.0, street, [
            _Actor("target", _TARGET, [(0.0, 0.0, 2.5), (10.0, 0.1, 7.5)], sway_m=0.06),
        ])
    if name == "ego-motion":
        return _Spec(name, 10.0, _CORRIDOR, [
            _Actor("target", _TARGET, [(0.0, 0.0, 2.6), (10.0, 0.1, 3.8)], sway_m=0.06),
        ], ego=True)
    if name == "lost-target":
        return _Spec(name, 8.0, _HALL, [
            _Actor("target", _TARGET, [(0.0, 0.0, 3.0), (1.5, 0.1, 3.5), (6.0, 5.5, 4.5)], sway_m=0.05),
            _Actor("distractor", _BYSTANDER, [(0.0, -2.2, 7.0), (8.0, -1.2, 9.5)], sway_m=0.04),
        ])
    if name == "group-walk":
        return _Spec(name, 20.0, _HALL, _group_walk_actors())
    if name == "overlay":
        # The camera pans to and fro (Scene._pan_px): the whole scene sweeps across the image, the overlay
        # never moves; the look-alike walks across behind the target.
        street = replace(_HALL, kind="street", ceiling=False, half_width_m=5.0, wall_height_m=10.0, far_m=45.0,
                         floor_bgr=(150, 158, 165), floor_alt_bgr=(120, 128, 136), wall_bgr=(150, 175, 200),
                         top_bgr=(235, 200, 150), ambient=1.0, lights=[], tile_m=0.45)
        return _Spec(name, 10.0, street, [
            _Actor("target", _TARGET, [(0.0, 0.0, 4.0), (10.0, 0.0, 4.8)], sway_m=0.05),
            _Actor("distractor", _LOOKALIKE, [(0.0, 1.6, 5.6), (10.0, -1.2, 6.0)], sway_m=0.05),
            _Actor("distractor", _BYSTANDER, [(0.0, -2.6, 7.0), (10.0, -1.8, 7.5)], sway_m=0.04),
        ], camera="pan", overlay=True)
    if name == "runners":
        street = replace(_HALL, kind="street", ceiling=False, half_width_m=5.0, wall_height_m=9.0, far_m=45.0,
                         lights=[], tile_m=0.8)
        return _Spec(name, 10.0, street, [
            _Actor("target", _TARGET, [(0.0, 0.0, 7.0), (10.0, 0.1, 16.0)], sway_m=0.06),
            _Actor("distractor", _LOOKALIKE, [(0.0, -0.6, 7.4), (10.0, -0.5, 16.6)], sway_m=0.06),
            _Actor("distractor", _LOOKALIKE, [(0.0, 0.7, 6.0), (10.0, 0.55, 17.5)], sway_m=0.06),
            _Actor("distractor", _LOOKALIKE, [(0.0, -1.3, 5.5), (10.0, 0.9, 16.3)], sway_m=0.06),
        ])
    if name == "shaky":
        return _Spec(name, 10.0, _HALL, [
            _Actor("target", _TARGET, [(0.0, 0.0, 3.0), (5.0, 0.6, 4.2), (10.0, -0.2, 5.0)], sway_m=0.06),
            _Actor("distractor", _BYSTANDER, [(0.0, 3.0, 11.0), (10.0, 2.2, 10.0)], sway_m=0.04),
        ], camera="shaky")
    if name == "bumpy":
        return _Spec(name, 10.0, _HALL, [
            _Actor("target", _TARGET, [(0.0, 0.0, 2.8), (10.0, 0.2, 4.4)], sway_m=0.06),
            _Actor("distractor", _LOOKALIKE, [(0.0, -0.6, 3.0), (10.0, -0.55, 4.6)], sway_m=0.05),
            _Actor("distractor", _BYSTANDER, [(0.0, 1.8, 6.5), (10.0, 1.3, 3.0)], sway_m=0.04),
            _Actor("distractor", _PASSER, [(1.0, -3.5, 8.0), (9.0, 3.5, 8.0)], sway_m=0.03),
        ], camera="bumpy")
    raise ValueError(f"unknown scene {name!r}; available: {', '.join(SCENES)}")


_GROUP_STYLES = [
    PersonStyle(shirt_bgr=(42, 48, 190), trousers_bgr=(78, 50, 32), height_m=1.85),
    PersonStyle(shirt_bgr=(170, 120, 60), trousers_bgr=(50, 50, 55), height_m=1.70),
    PersonStyle(shirt_bgr=(60, 150, 190), trousers_bgr=(40, 40, 45), height_m=1.76),
    PersonStyle(shirt_bgr=(140, 60, 120), trousers_bgr=(90, 80, 70), height_m=1.66),
    PersonStyle(shirt_bgr=(200, 200, 205), trousers_bgr=(60, 45, 35), height_m=1.58),
]


def _group_walk_actors() -> list[_Actor]:
    """group-walk: five members around a centre walking away at 0.32 m/s with a slight drift to the right.
    Member 5 (the shortest) steps onto the ray of member 1 (the tallest), 1.2 m behind it, from 5-7 s and
    back out from 10.5-12.5 s, so it is hidden from ~6.5 to ~11 s; a passer-by walks towards the robot 1.5-2 m to the
    right of the group."""

    def centre(t: float) -> tuple[float, float]:
        return 0.5 * t / 20.0, 3.4 + 0.32 * t

    offsets = [(-0.6, -0.5), (0.6, -0.4), (-0.1, 0.5), (1.5, 0.6)]

    def member(k: int, t: float) -> tuple[float, float]:
        cx, cz = centre(t)
        return cx + offsets[k][0], cz + offsets[k][1]

    def hidden_member(t: float) -> tuple[float, float]:
        x1, z1 = member(0, t)
        z_on, cx, cz = z1 + 1.2, *centre(t)
        x_on = x1 * z_on / z1  # on member 1's camera ray: behind it in the image
        a = min(1.0, max(0.0, (t - 5.0) / 2.0)) - min(1.0, max(0.0, (t - 10.5) / 2.0))
        return (1 - a) * (cx - 1.35) + a * x_on, (1 - a) * (cz + 0.3) + a * z_on

    times = [0.25 * i for i in range(81)]
    paths = [[member(k, t) for t in times] for k in range(4)] + [[hidden_member(t) for t in times]]
    actors = [_Actor("member", style, [(t, x, z) for t, (x, z) in zip(times, path, strict=True)])
              for style, path in zip(_GROUP_STYLES, paths, strict=True)]
    actors.append(_Actor("distractor", _PASSER, [(2.0, 3.6, 15.0), (16.0, 3.0, 1.2)], sway_m=0.03))
    return actors


# ----------------------------------------------------------------------------- scene

WALKING_SPEED_MPS = 0.15  # slower than this a figure stands: no gait, no bob, seen as from behind


class _View(NamedTuple):
    """Where one frame's camera looks: the crop of the wide background canvas and what follows from it."""

    ox: int  # crop origin on the canvas (px)
    oy: int
    shift: tuple[float, float]  # whole-image shift applied this frame (px)
    person_offset: tuple[float, float]  # rotation part of the shift only; the strafe moves people via x_m - x_cam
    x_cam: float  # camera lateral offset (m)
    vy: float  # camera lateral velocity (m/s)


class _Placed(NamedTuple):
    """A person drawn this frame: depth, actor index, integer figure box (x, y, w, h), BGR patch and mask."""

    z_m: float
    k: int
    box: tuple[int, int, int, int]
    patch: np.ndarray
    mask: np.ndarray


class _Gait:
    """Every actor's walk across frames: gait phase (rad) and floor position on the previous frame."""

    def __init__(self, phases: list[float]) -> None:
        self.phases = phases
        self.prev_pos: list[tuple[float, float] | None] = [None] * len(phases)

    def lose(self, k: int) -> None:
        """Actor ``k`` is not in the world this frame: its speed restarts from zero when it is back."""
        self.prev_pos[k] = None

    def step(self, k: int, pos: tuple[float, float], dt: float) -> tuple[float, float]:
        """Advance actor ``k`` to ``pos``: its (head bob m, lateral 0..1) for :func:`render_figure`."""
        x_m, z_m = pos
        speed = lateral = 0.0
        prev = self.prev_pos[k]
        if prev is not None:
            vx_m, vz_m = (x_m - prev[0]) / dt, (z_m - prev[1]) / dt
            speed = math.hypot(vx_m, vz_m)
            lateral = abs(vx_m) / (abs(vx_m) + abs(vz_m) + 1e-6) if speed > WALKING_SPEED_MPS else 0.0
        self.prev_pos[k] = pos
        if speed > WALKING_SPEED_MPS:
            self.phases[k] += 2 * math.pi * 0.9 * dt * min(1.5, 0.5 + speed)
        bob = 0.015 * abs(math.sin(self.phases[k])) if speed > WALKING_SPEED_MPS else 0.0
        return bob, lateral


def _clip_box(box: tuple[int, int, int, int], width: int, height: int) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` of an ``(x, y, w, h)`` box clipped to the image (empty when x1 <= x0 or y1 <= y0)."""
    bx, by, bw, bh = box
    return max(bx, 0), max(by, 0), min(bx + bw, width), min(by + bh, height)


def _visible_fractions(placed: list[_Placed], occ_views: list[tuple[float, np.ndarray]], width: int,
                       height: int) -> dict[int, float]:
    """Visible pixels / figure pixels per actor index, nearest first: occluders and nearer people hide farther
    people, and so does the image border."""
    layers = [(z, "occ", m) for z, m in occ_views] + [(p.z_m, "person", p) for p in placed]
    layers.sort(key=lambda it: it[0])
    cover = np.zeros((height, width), bool)
    vis: dict[int, float] = {}
    for _, kind, obj in layers:
        if kind == "occ":
            np.logical_or(cover, obj, out=cover)
            continue
        bx, by = obj.box[:2]
        x0, y0, x1, y1 = _clip_box(obj.box, width, height)
        total = int(np.count_nonzero(obj.mask))
        if x1 <= x0 or y1 <= y0 or total == 0:
            vis[obj.k] = 0.0
            continue
        m = obj.mask[y0 - by : y1 - by, x0 - bx : x1 - bx] > 0
        vis[obj.k] = float(np.count_nonzero(m & ~cover[y0:y1, x0:x1])) / total
        cover[y0:y1, x0:x1] |= m
    return vis


def _composite(frame: np.ndarray, bg_view: np.ndarray, placed: list[_Placed],
               occ_views: list[tuple[float, np.ndarray]]) -> None:
    """Draw the people into ``frame`` in place, farthest first, then occluders over everything behind them."""
    height, width = frame.shape[:2]
    draw = [(p.z_m, "person", p) for p in placed] + [(z, "occ", m) for z, m in occ_views]
    draw.sort(key=lambda it: -it[0])
    for _, kind, obj in draw:
        if kind == "occ":
            cv2.copyTo(bg_view, obj.view(np.uint8), frame)  # in place (same-size dst)
            continue
        bx, by = obj.box[:2]
        x0, y0, x1, y1 = _clip_box(obj.box, width, height)
        if x1 <= x0 or y1 <= y0:
            continue
        cv2.copyTo(obj.patch[y0 - by : y1 - by, x0 - bx : x1 - bx], obj.mask[y0 - by : y1 - by, x0 - bx : x1 - bx],
                   frame[y0:y1, x0:x1])


def _optics_and_sensor(frame: np.ndarray, bank: list[tuple[np.ndarray, np.ndarray]], noise_idx: int,
                       rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Slight defocus, then fresh sensor noise (never the same bank entry twice): the frame and the entry used."""
    frame = cv2.GaussianBlur(frame, (3, 3), 0.7)
    noise_idx = (noise_idx + 1 + int(rng.integers(0, len(bank) - 1))) % len(bank)
    pos_n, neg_n = bank[noise_idx]
    return cv2.subtract(cv2.add(frame, pos_n), neg_n), noise_idx


class Scene:
    """A named synthetic sequence; :meth:`frames` re-renders it identically on every call."""

    def __init__(self, spec: _Spec, seed: int, width: int, height: int, fps: float) -> None:
        self._spec = spec
        self.name = spec.name
        self.description = SCENES[spec.name]
        self.seed = int(seed)
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.n_frames = round(spec.duration_s * self.fps)
        self.camera = _Camera.for_size(self.width, self.height)
        rng = np.random.default_rng([self.seed, 1])
        # Seed-dependent clothing shade jitter (+-6 per channel) and gait phases.
        self._actors = []
        for a in spec.actors:
            j = rng.integers(-6, 7, size=6)
            st = replace(a.style,
                         shirt_bgr=tuple(int(np.clip(c + d, 0, 255)) for c, d in zip(a.style.shirt_bgr, j[:3],
                                                                                      strict=True)),
                         trousers_bgr=tuple(int(np.clip(c + d, 0, 255)) for c, d in zip(a.style.trousers_bgr,
                                                                                         j[3:], strict=True)))
            self._actors.append((replace(a, style=st), float(rng.uniform(0, 2 * math.pi))))
        margins = {"still": (0.0, 0.0), "ego": (0.12, 0.06), "pan": (PAN_AMPLITUDE_FRACTION + 0.02, 0.0),
                   "bumpy": (0.12, 0.16), "shaky": (0.34, 0.2)}
        mfx, mfy = margins[spec.camera]
        self._margin = (round(mfx * self.width), round(mfy * self.height))
        self._background: np.ndarray | None = None
        self._occluders: list[tuple[np.ndarray, float]] = []
        self._bank: tuple[list[tuple[np.ndarray, np.ndarray]], dict] | None = None

    @property
    def target_style(self) -> PersonStyle:
        """The target's clothes; in a group scene (no single target) the first member's."""
        return next(st.style for st, _ in self._actors if st.role in ("target", "member"))

    def group_truth_m(self, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Ground truth of a group scene at ``t_s``: (centre (2,), members (N, 2)) on the floor in the robot
        frame (x forward, y left, metres from the camera); None when the scene has no group member in view."""
        x_cam = self._ego(t_s)[0]
        members = [a.position(t_s) for a, _ in self._actors if a.role == "member"]
        pts = np.array([(z, -(x - x_cam)) for x, z in (m for m in members if m is not None)]).reshape(-1, 2)
        if not len(pts):
            return None
        return pts.mean(axis=0), pts

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        return f"Scene({self.name!r}, seed={self.seed}, {self.width}x{self.height}, {self.n_frames} @ {self.fps} fps)"

    def _ensure_background(self) -> None:
        if self._background is None:
            rng = np.random.default_rng([self.seed, 2])
            self._background, self._occluders = _render_environment(
                self.camera, self._spec.env, self._spec.occluders, rng, self._margin)

    def _noise_bank(self) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.random.Generator]:
        """Eight sensor-noise frames split into +/- parts for saturating uint8 add/subtract, and the
        frame loop's generator in the state that follows them. Drawn once (~90 ms at 640x480) and kept,
        so a looping capture re-iterates the scene without a stall at each pass; every pass is identical."""
        if self._bank is None:
            rng = np.random.default_rng([self.seed, 3])
            bank = []
            for _ in range(8):
                n = rng.normal(0.0, self._spec.noise_sigma, size=(self.height, self.width, 3))
                bank.append((np.clip(n, 0, 255).astype(np.uint8), np.clip(-n, 0, 255).astype(np.uint8)))
            self._bank = (bank, rng.bit_generator.state)
        bank, state = self._bank
        rng = np.random.default_rng()
        rng.bit_generator.state = state
        return bank, rng

    def _illumination(self, x_m: float, z_m: float) -> float:
        env = self._spec.env
        if env.shadow_z_m is not None:
            z0, z1 = env.shadow_z_m
            return env.shadow_gain if z0 <= z_m <= z1 else 1.0
        if env.kind == "street":  # night: ambient plus streetlights at torso height
            g = env.ambient + sum(gain / (1.0 + ((x_m - lx) ** 2 + (1.2 - ly) ** 2 + (z_m - lz) ** 2)
                                          / env.light_radius_m**2) for lx, ly, lz, gain in env.lights)
            return float(min(1.1, g))
        return 1.0

    EGO_BACKGROUND_DEPTH_M = 4.0

    def _pan_px(self, t: float) -> float:
        """scene:overlay's pan: the whole image shifts by A sin(2πt/T) px (at most 2πA/T px/s: ~16 px a frame)."""
        return PAN_AMPLITUDE_FRACTION * self.width * math.sin(2 * math.pi * t / PAN_PERIOD_S)

    def _jerk_px(self, t: float) -> tuple[float, float]:
        """scene:bumpy's image offset: each bump jolts the image by (dx, dy) at once, settling exponentially."""
        dx = dy = 0.0
        for tj, jx, jy in BUMPS:
            if t >= tj:
                decay = math.exp(-(t - tj) / BUMP_SETTLE_S)
                dx, dy = dx + jx * decay * self.height / 480.0, dy + jy * decay * self.height / 480.0
        return dx, dy

    def _shake_px(self, t: float) -> tuple[float, float]:
        """scene:shaky's image offset: each jerk moves the image by (dx, dy), evenly over SHAKE_FRAMES frames."""
        span = SHAKE_FRAMES / self.fps
        scale = self.height / 480.0
        dx = sum(jx * min(max((t - tj) / span, 0.0), 1.0) for tj, jx, _ in SHAKES) * scale
        dy = sum(jy * min(max((t - tj) / span, 0.0), 1.0) for tj, _, jy in SHAKES) * scale
        return dx, dy

    def _ego(self, t: float) -> tuple[float, float, float, float]:
        """(camera lateral offset m, rotation image shift x px, y px, lateral velocity m/s).

        The robot strafes sinusoidally (Mecanum base) and yaws slightly; rotation shifts the whole
        image, the strafe moves people by their true parallax and the background as if it were
        a plane :attr:`EGO_BACKGROUND_DEPTH_M` away. scene:overlay pans (yaw only); scene:bumpy jerks.
        """
        if self._spec.camera == "pan":
            return 0.0, self._pan_px(t), 0.0, 0.0
        if self._spec.camera == "bumpy":
            return (0.0, *self._jerk_px(t), 0.0)
        if self._spec.camera == "shaky":
            return (0.0, *self._shake_px(t), 0.0)
        if self._spec.camera != "ego":
            return 0.0, 0.0, 0.0, 0.0
        w = 2 * math.pi / 4.0
        vy = 0.35 * math.sin(w * t)
        x_cam = -0.35 / w * math.cos(w * t)  # integral of vy (zero mean)
        yaw_px = 0.035 * self.camera.f_px * math.sin(2 * math.pi * t / 3.1)
        pitch_px = 2.0 * math.sin(2 * math.pi * t / 0.9)
        return x_cam, yaw_px, pitch_px, vy

    def _screen_effects(self, frame: np.ndarray, t: float, dt: float) -> tuple[np.ndarray, float]:
        """The screen-fixed overlay (scene:overlay) and a jerk's smear (scene:bumpy): the frame and the smear's
        length (0: none)."""
        if self._spec.overlay:
            draw_overlay(frame, t)
        blur_px, direction = self._jerk_blur_px(t, dt), self._jerk_direction
        if self._spec.camera == "shaky":
            blur_px, direction = self._shake_blur(t, dt)
        if blur_px > 0.0:
            frame = motion_smear(frame, direction(t, dt) if callable(direction) else direction, blur_px)
        return frame, blur_px

    def _shake_blur(self, t: float, dt: float) -> tuple[float, tuple[float, float]]:
        """scene:shaky's smear: the image's own motion during the frame's exposure, along it."""
        (x0, y0), (x1, y1) = self._shake_px(t - dt), self._shake_px(t)
        length = math.hypot(x1 - x0, y1 - y0)
        if length < 1.0:
            return 0.0, (1.0, 0.0)
        return SHAKE_EXPOSURE * length, ((x1 - x0) / length, (y1 - y0) / length)

    def _jerk_blur_px(self, t: float, dt: float) -> float:
        """Smear length of the frame at ``t``: a bump's own frame is exposed while the image jolts."""
        if self._spec.camera != "bumpy":
            return 0.0
        hit = [(jx, jy) for tj, jx, jy in BUMPS if t - dt < tj <= t]
        return SMEAR_EXPOSURE * max((math.hypot(jx, jy) * self.height / 480.0 for jx, jy in hit), default=0.0)

    def _jerk_direction(self, t: float, dt: float) -> tuple[float, float]:
        jx, jy = next((jx, jy) for tj, jx, jy in BUMPS if t - dt < tj <= t)
        n = math.hypot(jx, jy)
        return jx / n, jy / n

    def frames(self) -> Iterator[SceneFrame]:
        """Render every frame (about 2-4 ms each at 640x480)."""
        self._ensure_background()
        assert self._background is not None
        bank, rng = self._noise_bank()
        noise_idx = 0
        jit = np.zeros(2)
        gait = _Gait([p0 for _, p0 in self._actors])
        dt = 1.0 / self.fps

        for i in range(self.n_frames):
            t = i * dt
            jit = self._vibrate(jit, rng)
            view = self._view(t, jit)
            bg_view = self._crop(self._background, view)
            frame = bg_view.copy()
            placed = self._place_people(t, dt, view, gait)
            occ_views = [(z, self._crop(m, view)) for m, z in self._occluders]
            vis = _visible_fractions(placed, occ_views, self.width, self.height)
            _composite(frame, bg_view, placed, occ_views)
            frame, blur_px = self._screen_effects(frame, t, dt)
            frame, noise_idx = _optics_and_sensor(frame, bank, noise_idx, rng)
            target_box, target_vis, d_boxes, d_vis = self._ground_truth(placed, vis)
            # bumpy's smear (40-60 px in one frame) hides everyone from a detector; shaky's (~25 px) does not
            target_vis, d_vis = _detectable(target_vis, d_vis, blur_px if self._spec.camera == "bumpy" else 0.0)
            # Ego velocity: forward speed of a robot keeping pace with the walker, plus the strafe.
            ego_v = {"ego": (0.9, view.vy), "bumpy": (0.5, 0.0)}.get(self._spec.camera, (0.0, 0.0))
            yield SceneFrame(
                index=i,
                t_ns=round(i * 1e9 / self.fps),
                bgr=frame,
                target_box=target_box,
                target_visible_fraction=round(target_vis, 4),
                distractor_boxes=d_boxes,
                ego_velocity_mps=ego_v,
                distractor_visible_fractions=[round(v, 4) for v in d_vis],
                camera_offset_px=view.shift,
                motion_blur_px=blur_px,
            )

    def _vibrate(self, jit: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The next image jitter (px) of a vibrating camera (correlated from frame to frame); others keep zero
        and draw nothing from ``rng`` (the sensor noise draws from it too)."""
        if self._spec.camera in VIBRATION_PX:
            jit = 0.6 * jit + rng.normal(0.0, VIBRATION_PX[self._spec.camera])
        return jit

    def _view(self, t: float, jit: np.ndarray) -> _View:
        x_cam, rot_dx, rot_dy, vy = self._ego(t)
        strafe_px = -self.camera.f_px * x_cam / self.EGO_BACKGROUND_DEPTH_M
        mx, my = self._margin
        # Crop the wide background so its content moves by the whole-image shift.
        ox = int(np.clip(round(mx - (strafe_px + rot_dx + jit[0])), 0, 2 * mx))
        oy = int(np.clip(round(my - (rot_dy + jit[1])), 0, 2 * my))
        shift = (float(mx - ox), float(my - oy))
        return _View(ox, oy, shift, (shift[0] - strafe_px, shift[1]), x_cam, vy)

    def _crop(self, canvas: np.ndarray, view: _View) -> np.ndarray:
        """The frame-sized window of a background-sized canvas (the background, an occluder mask) this frame."""
        return canvas[view.oy : view.oy + self.height, view.ox : view.ox + self.width]

    def _place_people(self, t: float, dt: float, view: _View, gait: _Gait) -> list[_Placed]:
        """Every actor in the world at ``t``, projected and rendered (not yet drawn into the frame)."""
        placed = []
        for k, (actor, _) in enumerate(self._actors):
            pos = actor.position(t)
            if pos is None:
                gait.lose(k)
                continue
            bob, lateral = gait.step(k, pos, dt)
            x_m, z_m = pos
            bx, by, bw, bh = self.camera.figure_box(x_m - view.x_cam, z_m, actor.style.height_m, bob,
                                                    view.person_offset)
            patch, mask = render_figure(bh, bw, actor.style, gait.phases[k], lateral, self._illumination(x_m, z_m))
            placed.append(_Placed(z_m, k, (bx, by, bw, bh), patch, mask))
        return placed

    def _ground_truth(self, placed: list[_Placed],
                      vis: dict[int, float]) -> tuple[Box | None, float, list[Box], list[float]]:
        """(target box, its visible fraction, distractor boxes, theirs) of everyone with a visible pixel, boxes
        clipped to the image, distractors in actor order."""
        target_box: Box | None = None
        target_vis = 0.0
        d_boxes: list[Box] = []
        d_vis: list[float] = []
        for person in sorted(placed, key=lambda p: p.k):
            v = vis.get(person.k, 0.0)
            if v <= 0.0:
                continue
            x0, y0, x1, y1 = _clip_box(person.box, self.width, self.height)
            box = (float(x0), float(y0), float(x1 - x0), float(y1 - y0))
            if self._actors[person.k][0].role == "target":
                target_box, target_vis = box, v
            else:
                d_boxes.append(box)
                d_vis.append(v)
        return target_box, target_vis, d_boxes, d_vis

    def __iter__(self) -> Iterator[SceneFrame]:
        return self.frames()


def make_scene(name: str, seed: int = 0, width: int = 640, height: int = 480, fps: float = 30.0) -> Scene:
    """Build a scene by name (see :data:`SCENES`); raises ValueError for unknown names."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; available: {', '.join(SCENES)}")
    if width < 64 or height < 48 or fps <= 0:
        raise ValueError("scene size must be at least 64x48 and fps positive")
    return Scene(_spec(name), seed, width, height, fps)


def hidden_ranges(frames: Sequence[SceneFrame] | Iterator[SceneFrame]) -> list[tuple[int, int]]:
    """Inclusive frame-index ranges where the target box is None (fully hidden or out of view)."""
    out: list[tuple[int, int]] = []
    start = None
    last = -1
    for fr in frames:
        last = fr.index
        if fr.target_box is None and start is None:
            start = fr.index
        elif fr.target_box is not None and start is not None:
            out.append((start, fr.index - 1))
            start = None
    if start is not None:
        out.append((start, last))
    return out
