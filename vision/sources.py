"""Frame sources: camera, video file, image folder (SOT/MOT layouts), synthetic scene.

Every source iterates :class:`SourceFrame` objects. Files, folders and scenes get synthetic
stamps ``t_ns = index * 1e9 / fps`` so that runs over recorded data are reproducible; only the
live camera uses ``time.monotonic_ns()``.

Folder layouts understood (see shared/data/README.md):

* ``sot/<name>/``: ``img/*.jpg`` + ``groundtruth.txt`` (one ``x,y,w,h`` per image, ``NaN`` row =
  target absent) + ``meta.json`` (``fps``);
* ``mot/<name>/``: MOTChallenge ``img1/`` + ``gt/gt.txt`` (``frame,id,x,y,w,h,conf,class,vis``) +
  ``seqinfo.ini`` (``frameRate``); every person box of a frame is in ``extras['gt_all']``;
* any folder of images (sorted by name), optionally with an explicit ground-truth file.
"""

from __future__ import annotations

import configparser
import difflib
import itertools
import json
import logging
import math
import os
import re
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..msgs.box import Box
from .scenes import DEFAULT_SCENE, SCENES, make_scene

log = logging.getLogger(__name__)

IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".bmp")
VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg")
DEFAULT_FPS = 30.0
# MOTChallenge classes counted as people: 1 = pedestrian; -1 = unlabelled (e.g. TUD-Campus).
MOT_PERSON_CLASSES = (1, -1)


@dataclass(frozen=True)
class SourceFrame:
    index: int
    t_ns: int
    bgr: np.ndarray
    gt_box: Box | None
    extras: dict[str, Any] = field(default_factory=dict)


def synthetic_stamp_ns(index: int, fps: float) -> int:
    """Reproducible stamp of frame ``index`` at ``fps``."""
    return round(index * 1e9 / fps)


class _Source:
    """Shared plumbing: iteration, length, context manager."""

    name: str = ""
    fps: float = DEFAULT_FPS
    rewindable = False  # True when iterating again restarts the sequence (no need to re-open it)

    def __iter__(self) -> Iterator[SourceFrame]:
        return self.frames()

    def frames(self, start: int = 0) -> Iterator[SourceFrame]:  # pragma: no cover - overridden
        """The frames from index ``start`` on."""
        raise NotImplementedError

    def resume(self, start: int) -> Iterator[SourceFrame]:
        """The frames from ``start`` on, after an iteration that raised at frame ``start`` (a generator that raised
        is finished, so resuming means a new one): the same frame is tried again. A live source reopens its device."""
        return self.frames(start)

    def close(self) -> None:
        """Release device/file handles (no-op for sources that hold none)."""

    def __enter__(self) -> _Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ----------------------------------------------------------------------------- camera / video


class SourceReadError(OSError):
    """A source that did not deliver its next frame: an unreadable image, a camera that stopped delivering. The
    capture node tries the same frame again (a camera: reopened) and fails when that keeps failing."""


class CameraSource(_Source):
    """Live camera via OpenCV (``device``: an index, or a device path such as /dev/v4l/by-id/...); stamps are
    ``time.monotonic_ns()`` at capture. A read that fails raises SourceReadError: a camera that stops delivering
    is a failure to retry (:meth:`resume` reopens the device), never the end of the stream."""

    def __init__(self, device: int | str = 0, width: int | None = None, height: int | None = None,
                 fps: float | None = None) -> None:
        self.device = device
        self.name = f"camera:{device}"
        self._settings = (width, height, fps)
        self.cap = self._open()
        self.fps = float(self.cap.get(cv2.CAP_PROP_FPS) or fps or DEFAULT_FPS)

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.device)
        if not cap.isOpened():
            cap.release()
            raise SourceReadError(f"cannot open {self.name} (no device, or it is busy)")
        width, height, fps = self._settings
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, width), (cv2.CAP_PROP_FRAME_HEIGHT, height),
                            (cv2.CAP_PROP_FPS, fps)):
            if value:
                cap.set(prop, value)
        return cap

    def frames(self, start: int = 0) -> Iterator[SourceFrame]:
        i = start
        while True:
            ok, bgr = self.cap.read()
            t_ns = time.monotonic_ns()
            if not ok:
                raise SourceReadError(f"{self.name} delivered no frame (frame {i})")
            yield SourceFrame(i, t_ns, bgr, None, {})
            i += 1

    def resume(self, start: int) -> Iterator[SourceFrame]:
        """Reopen the device (a camera that stopped delivering is often back once reopened), then read on."""
        self.cap.release()
        self.cap = self._open()
        log.warning("%s reopened at frame %d", self.name, start)
        return self.frames(start)

    def close(self) -> None:
        self.cap.release()


class VideoFileSource(_Source):
    """Video file via OpenCV; stamps synthesised from the container fps (or ``fps``)."""

    def __init__(self, path: str | os.PathLike[str], fps: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"video file not found: {self.path}")
        self.name = self.path.stem
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise RuntimeError(f"OpenCV cannot decode video {self.path}")
        container_fps = cap.get(cv2.CAP_PROP_FPS)
        self._n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        cap.release()
        self.fps = float(fps or (container_fps if container_fps and container_fps > 0 else DEFAULT_FPS))

    def __len__(self) -> int:
        return self._n

    def frames(self, start: int = 0) -> Iterator[SourceFrame]:
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise SourceReadError(f"OpenCV cannot decode video {self.path}")
            for _ in range(start):  # grab, not seek: exact whatever the codec's key frames
                if not cap.grab():
                    return
            i = start
            while True:
                ok, bgr = cap.read()
                if not ok:
                    return
                yield SourceFrame(i, synthetic_stamp_ns(i, self.fps), bgr, None, {"path": str(self.path)})
                i += 1
        finally:
            cap.release()


# ----------------------------------------------------------------------------- image folders


def read_sot_groundtruth(path: str | os.PathLike[str]) -> list[Box | None]:
    """One box per line (``,``, tab or space separated); NaN or unparsable rows -> None."""
    boxes: list[Box | None] = []
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        parts = [p for p in re.split(r"[,\s]+", line.strip()) if p]
        try:
            vals = [float(p) for p in parts[:4]]
        except ValueError:
            boxes.append(None)
            continue
        if len(vals) < 4 or any(math.isnan(v) for v in vals) or vals[2] <= 0 or vals[3] <= 0:
            boxes.append(None)
        else:
            boxes.append((vals[0], vals[1], vals[2], vals[3]))
    return boxes


def read_mot_groundtruth(
    path: str | os.PathLike[str], all_classes: bool = False
) -> dict[int, list[tuple[int, float, float, float, float]]]:
    """MOTChallenge gt.txt -> {frame (1-based): [(id, x, y, w, h), ...]}.

    Unless ``all_classes``, rows flagged "ignore" (conf column 0) and non-pedestrian classes
    (MOT17: vehicles, static people, reflections, ...) are dropped, as the MOT evaluation does.
    """
    out: dict[int, list[tuple[int, float, float, float, float]]] = {}
    for line in Path(path).read_text().splitlines():
        parts = line.strip().split(",")
        if len(parts) < 6:
            continue
        frame, tid = int(float(parts[0])), int(float(parts[1]))
        x, y, w, h = (float(p) for p in parts[2:6])
        if not all_classes:
            if len(parts) >= 7 and float(parts[6]) == 0:
                continue
            if len(parts) >= 8 and int(float(parts[7])) not in MOT_PERSON_CLASSES:
                continue
        out.setdefault(frame, []).append((tid, x, y, w, h))
    return out


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file())


class ImageFolderSource(_Source):
    """Images of a folder in name order, with ground truth from the SOT or MOT layout.

    ``path`` may be a ``sot/<name>`` dir, a ``mot/<name>`` dir, or a plain image folder.
    ``groundtruth`` overrides the ground-truth file (SOT format). ``fps`` overrides
    meta.json / seqinfo.ini (default 30). For MOT, ``gt_box`` is the box of ``target_id`` when
    given (None in frames where that id is absent), else None; ``extras['gt_all']`` always
    lists ``(id, x, y, w, h)`` of every annotated person in the frame.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        groundtruth: str | os.PathLike[str] | None = None,
        fps: float | None = None,
        *,
        target_id: int | None = None,
        mot_all_classes: bool = False,
    ) -> None:
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(f"image folder not found: {root}")
        self.root = root
        self.name = root.name
        self.layout = "folder"
        self.target_id = target_id
        meta_fps: float | None = None
        self._sot_gt: list[Box | None] | None = None
        self._mot_gt: dict[int, list[tuple[int, float, float, float, float]]] | None = None

        if (root / "img1").is_dir() and ((root / "gt" / "gt.txt").is_file() or (root / "seqinfo.ini").is_file()):
            self.layout = "mot"
            img_dir = root / "img1"
            ini = root / "seqinfo.ini"
            if ini.is_file():
                cp = configparser.ConfigParser()
                cp.read(ini)
                if cp.has_option("Sequence", "frameRate"):
                    meta_fps = cp.getfloat("Sequence", "frameRate")
                if cp.has_option("Sequence", "imDir"):
                    img_dir = root / cp.get("Sequence", "imDir")
            gt_file = root / "gt" / "gt.txt"
            if gt_file.is_file():
                self._mot_gt = read_mot_groundtruth(gt_file, mot_all_classes)
        elif (root / "img").is_dir():
            self.layout = "sot"
            img_dir = root / "img"
            meta = root / "meta.json"
            if meta.is_file():
                meta_fps = json.loads(meta.read_text()).get("fps")
            if (root / "groundtruth.txt").is_file():
                self._sot_gt = read_sot_groundtruth(root / "groundtruth.txt")
        else:
            img_dir = root
        if groundtruth is not None:
            self._sot_gt = read_sot_groundtruth(groundtruth)

        self.images = _list_images(img_dir)
        if not self.images:
            raise FileNotFoundError(f"no images ({', '.join(IMAGE_EXTS)}) in {img_dir}")
        self.fps = float(fps or meta_fps or DEFAULT_FPS)
        if self._sot_gt is not None and len(self._sot_gt) != len(self.images):
            log.warning("%s: %d ground-truth rows for %d images (missing rows = absent)",
                        root, len(self._sot_gt), len(self.images))

    def __len__(self) -> int:
        return len(self.images)

    @property
    def has_ground_truth(self) -> bool:
        return self._sot_gt is not None or self._mot_gt is not None

    def ground_truth(self, index: int) -> tuple[Box | None, dict[str, Any]]:
        """(gt_box, extras) of frame ``index`` (0-based) without reading the image."""
        extras: dict[str, Any] = {"path": str(self.images[index]), "layout": self.layout}
        gt: Box | None = None
        if self._sot_gt is not None and index < len(self._sot_gt):
            gt = self._sot_gt[index]
        if self._mot_gt is not None:
            rows = self._mot_gt.get(index + 1, [])  # MOT frames are 1-based
            extras["gt_all"] = list(rows)
            if self.target_id is not None:
                gt = next(((x, y, w, h) for tid, x, y, w, h in rows if tid == self.target_id), None)
        return gt, extras

    def frames(self, start: int = 0) -> Iterator[SourceFrame]:
        for i in range(start, len(self.images)):
            p = self.images[i]
            bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if bgr is None:
                raise SourceReadError(f"cannot read image {p}")
            gt, extras = self.ground_truth(i)
            yield SourceFrame(i, synthetic_stamp_ns(i, self.fps), bgr, gt, extras)


# ----------------------------------------------------------------------------- synthetic scenes


class SceneSource(_Source):
    """A :mod:`followbus.vision.scenes` scene as a source.

    ``extras``: ``visible_fraction``, ``distractor_boxes``, ``distractor_visible_fractions``,
    ``ego_velocity_mps``, ``camera_offset_px``, ``people`` (input of the simulated detector)
    and ``scene``.
    """

    rewindable = True  # iterating again replays the same frames, without re-rendering the scene's assets

    def __init__(self, name: str = DEFAULT_SCENE, seed: int = 0, width: int = 640, height: int = 480,
                 fps: float = 30.0) -> None:
        self.scene = make_scene(name, seed=seed, width=width, height=height, fps=fps)
        self.name = name
        self.seed = seed
        self.fps = self.scene.fps

    def __len__(self) -> int:
        return self.scene.n_frames

    def frames(self, start: int = 0) -> Iterator[SourceFrame]:
        for f in itertools.islice(self.scene.frames(), start, None):
            extras = {
                "scene": self.name,
                "visible_fraction": f.target_visible_fraction,
                "distractor_boxes": f.distractor_boxes,
                "distractor_visible_fractions": f.distractor_visible_fractions,
                "ego_velocity_mps": f.ego_velocity_mps,
                "camera_offset_px": f.camera_offset_px,
                "people": f.people(),
            }
            yield SourceFrame(f.index, f.t_ns, f.bgr, f.target_box, extras)


# ----------------------------------------------------------------------------- spec parsing


class SourceError(ValueError):
    """A capture source that cannot be used; the message is one line: the spec, what is wrong, the choices."""


def _did_you_mean(name: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(name, choices, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _scene_name(spec: str) -> str:
    name = spec.split(":", 1)[1] or DEFAULT_SCENE
    if name not in SCENES:
        raise SourceError(f"unknown scene {name!r} in {spec!r}{_did_you_mean(name, list(SCENES))}; "
                          f"available: {', '.join(SCENES)}")
    return name


def _camera_device(spec: str) -> int | str:
    """``camera:<index>`` -> the index; ``camera:<path>`` (a device such as /dev/v4l/by-id/..., whose name stays
    the same whichever USB port the camera is in) -> the path."""
    device = spec.split(":", 1)[1] or "0"
    if device.isdigit():
        return int(device)
    if device.startswith("/"):
        return device
    raise SourceError(f"camera spec needs a numeric index or a device path (camera:/dev/video0), got {spec!r}")


def _missing_path(spec: str, p: Path) -> SourceError:
    where = "" if str(p.resolve()) == spec.strip() else f" ({p.resolve()})"
    return SourceError(f"source {spec!r}: no such file or directory{where}")


def _path_like(spec: str) -> bool:
    """Whether a spec names a file or folder (``scen:x`` or ``rtsp://...`` do not)."""
    return re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", spec) is None


def _unknown_spec(spec: str) -> SourceError:
    return SourceError(f"unknown source spec {spec!r}: expected camera:<index>, scene:<{'|'.join(SCENES)}>, "
                       f"a video file ({', '.join(VIDEO_EXTS)}), an image folder or an MCAP recording")


def _check_camera(spec: str, device: int | str) -> None:
    """The device path, or on Linux /dev/video<N>, exists; elsewhere OpenCV opens the index."""
    if isinstance(device, str) or sys.platform.startswith("linux"):
        path = Path(device if isinstance(device, str) else f"/dev/video{device}")
        if not path.exists():
            present = sorted(str(d) for d in Path("/dev").glob("video*"))
            raise SourceError(f"source {spec!r}: {path} does not exist (video devices here: "
                              f"{', '.join(present) or 'none'})")
        return
    cap = cv2.VideoCapture(device)
    try:
        if not cap.isOpened():
            raise SourceError(f"source {spec!r}: OpenCV cannot open camera {device} (no device, or it is busy)")
    finally:
        cap.release()


def check_source(spec: str, *, groundtruth: str = "") -> None:
    """Check, cheaply and before anything starts, that a capture source can be opened. Raises SourceError.

    Scenes: the name is known. Files and folders: they exist and open (a video opens in OpenCV, a folder
    holds images and its first one decodes; MCAP recordings are the capture node's). Cameras: the device path,
    or on Linux ``/dev/video<N>``, exists (opening it here could take it from a graph already running); elsewhere
    OpenCV opens the index.
    """
    s = spec.strip()
    if not s:
        raise SourceError("the capture source is empty")
    if s.startswith("scene:"):
        _scene_name(s)
        return
    if s.startswith("camera:"):
        _check_camera(spec, _camera_device(s))
        return
    p = Path(s).expanduser()
    if p.suffix.lower() == ".mcap":  # the capture node checks those with the bus's reader of recordings
        raise SourceError(f"{spec!r} is an MCAP recording: the capture node reads it, not a vision source")
    if not p.exists():
        raise _missing_path(spec, p) if _path_like(s) else _unknown_spec(spec)
    if groundtruth and not Path(groundtruth).expanduser().is_file():
        raise SourceError(f"source {spec!r}: ground-truth file {groundtruth!r} not found")
    if p.is_file() and p.suffix.lower() not in VIDEO_EXTS:
        raise SourceError(f"source {spec!r} is a file but not a video ({', '.join(VIDEO_EXTS)}) "
                          "or an MCAP recording (.mcap)")
    try:
        if p.is_dir():
            first = ImageFolderSource(p, groundtruth or None).images[0]
            if cv2.imread(str(first), cv2.IMREAD_COLOR) is None:
                raise OSError(f"cannot read image {first}")
        else:
            VideoFileSource(p)
    except (OSError, RuntimeError, ValueError) as exc:
        raise SourceError(f"source {spec!r}: {exc}") from exc


def open_source(spec: str, **kw: Any) -> _Source:
    """Open a source from a spec string.

    ``camera:<index>`` or ``camera:<device path>``, ``scene:<name>`` (keywords: seed, width, height, fps), a video file
    path, or an image folder path (keywords: groundtruth, fps, target_id). MCAP recordings are
    replayed by the bus tools, not here. Raises ValueError (SourceError) for anything else.
    """
    s = spec.strip()
    if s.startswith("camera:"):
        return CameraSource(_camera_device(s), **kw)
    if s.startswith("scene:"):
        return SceneSource(_scene_name(s), **kw)
    p = Path(s).expanduser()
    if p.suffix.lower() == ".mcap":
        raise SourceError(f"{spec!r} is an MCAP recording: replay it with the bus tools, not a vision source")
    if p.is_dir():
        return ImageFolderSource(p, **kw)
    if p.is_file() and p.suffix.lower() in VIDEO_EXTS:
        return VideoFileSource(p, **kw)
    if not p.exists() and _path_like(s):
        raise _missing_path(spec, p)  # a path, not a malformed spec: say that it is missing
    raise _unknown_spec(spec)


def list_sequences(data_root: str | os.PathLike[str]) -> list[Path]:
    """Sequence dirs under ``data_root``: ``sot/*`` (with img/) then ``mot/*`` (with img1/), sorted."""
    root = Path(data_root)
    out: list[Path] = []
    for kind, img in (("sot", "img"), ("mot", "img1")):
        d = root / kind
        if d.is_dir():
            out.extend(sorted(p for p in d.iterdir() if (p / img).is_dir()))
    return out
