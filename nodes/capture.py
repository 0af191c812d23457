"""capture: publishes camera frames (raw, via shared memory locally), a small JPEG preview for
remote viewers, and ground truth when the source has it.

Sources (``source`` param): ``camera:<index>`` or ``camera:<device path>``, a video file, an image folder
(optionally in the ../shared/data layouts, with ground truth), ``scene:<name>`` (built-in synthetic scenes with exact
ground truth), or an MCAP recording (``*.mcap``: its raw frames, and its ground truth when recorded,
re-published with their original spacing), or a ROS 2 image topic (``ros2:/camera/image_raw``:
sensor_msgs/Image; a ``.../compressed`` topic: CompressedImage; over rmw_zenoh's format, nodes/ros2.py).
``pace: realtime`` paces to the source rate;
``pace: fast`` publishes as fast as the consumers allow: at most ``max_in_flight`` frames ahead of
the ``ack`` input (wire it to the last node of the chain, e.g. prediction/track).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..bus.codec import DecodeError
from ..bus.node import In, Node, Out
from ..bus.node_params import ParamError
from ..bus.schemas import Frame, Message, decode
from ..msgs.perception import GroundTruth
from ..msgs.tracking import Track
from ..vision.sources import SourceError, SourceReadError, check_source, open_source

MAX_SIDE_PX = 8192  # frames larger than 8K are refused at check time, not allocated by a crash-looping node
_END = object()  # the source has no more frames (None is a live source's "no new frame yet")


@dataclass
class CaptureParams:
    # camera:<index or device> | video file | image folder | *.mcap | scene:<name> | ros2:<topic> (demo --scene)
    source: str = field(default="scene:corridor-occlusion", metadata={"demo": "source"})
    seed: int = 0  # synthetic scenes
    fps: float = 0.0  # 0: the source's own rate (30 for folders without one)
    width_px: int = 640  # synthetic scenes
    height_px: int = 480
    groundtruth: str = ""  # image folders: explicit ground-truth file
    mcap_frame_key: str = ""  # MCAP sources: the recorded frame key (default: the one ending in /frame)
    ros2_domain_id: int = 0  # ROS 2 sources: ROS_DOMAIN_ID
    pace: str = "realtime"  # realtime | fast
    max_in_flight: int = 2  # pace: fast
    loop: bool = False
    max_frames: int = 0  # 0: the whole source
    wait_for_consumers_s: float = 15.0  # before frame 0, wait this long at most for the consuming nodes
    start_delay_s: float = 0.5  # then this much more, for the routes between them to settle
    preview_width_px: int = 320
    jpeg_quality: int = 70

    def __post_init__(self) -> None:
        if self.pace not in ("realtime", "fast"):
            raise ParamError("pace", f"pace must be 'realtime' or 'fast', not {self.pace!r}")
        for key, low in (("width_px", 16), ("height_px", 16), ("preview_width_px", 16), ("max_in_flight", 1),
                         ("jpeg_quality", 1), ("fps", 0), ("max_frames", 0), ("wait_for_consumers_s", 0),
                         ("start_delay_s", 0), ("ros2_domain_id", 0)):
            if getattr(self, key) < low:
                raise ParamError(key, f"{key} must be >= {low}, not {getattr(self, key)!r}")
        for key in ("width_px", "height_px", "preview_width_px"):
            if getattr(self, key) > MAX_SIDE_PX:
                raise ParamError(key, f"{key} must be at most {MAX_SIDE_PX} (an 8K frame's side), "
                                      f"not {getattr(self, key)!r}")
        if self.ros2_domain_id > 232:  # ROS 2's own bound on ROS_DOMAIN_ID
            raise ParamError("ros2_domain_id", f"ros2_domain_id must be in 0..232, not {self.ros2_domain_id!r}")
        if self.jpeg_quality > 100:
            raise ParamError("jpeg_quality", f"jpeg_quality must be in 1..100, not {self.jpeg_quality!r}")

    def check(self) -> None:
        """Can the source be opened? Run by `followbus check`, `launch` and `demo` before anything starts, so a
        missing file or an unknown scene is one line instead of a node crash-looping (SourceError)."""
        try:
            if _is_mcap(self.source):
                mcap_frame_channel(self.source, self.mcap_frame_key)
            elif _is_ros2(self.source):
                from .ros2 import ros2_image_topic  # here: other sources never load the ROS 2 types

                ros2_image_topic(self.source)
            else:
                check_source(self.source, groundtruth=self.groundtruth)
        except SourceError as exc:
            raise ParamError("source", str(exc)) from exc

    def first_truth_box(self) -> tuple[float, ...] | None:
        """The ground-truth box of frame 0 when the source is an annotated image folder (followbus demo gives it to
        the node that takes the box to follow)."""
        source = self.source
        if not source or source.startswith(("scene:", "camera:")) or not Path(source).is_dir():
            return None
        from ..vision.sources import ImageFolderSource

        folder = ImageFolderSource(Path(source), self.groundtruth or None)
        if not folder.has_ground_truth:
            return None
        box, _ = folder.ground_truth(0)
        return None if box is None else tuple(float(v) for v in box)


class Capture(Node):
    INPUTS = {"ack": In(Track)}  # pace: fast
    OUTPUTS = {"frame": Out(Frame, congestion="drop"), "preview": Out(Frame, congestion="drop"),
               "ground_truth": Out(GroundTruth)}
    Params = CaptureParams

    def setup(self) -> None:
        p = self.params
        self.source = self._open()
        self.frames: Any = iter(self.source)  # None after a failed read: the next poll resumes at `position`
        self.position = 0  # the source's index of the next frame in this pass
        self.fps = p.fps or getattr(self.source, "fps", 30.0) or 30.0
        self.published = 0
        # Names this session's frame numbering: a restarted capture counts from 0 again under a new epoch,
        # which every node follows instead of taking the new frames for stale ones (bus.sync).
        self.epoch_ns = self.runtime.clock.wall_ns()
        self.acked = -1
        self.t0_wall_ns: int | None = None
        self.first_source_ns = 0
        self.done = False
        # Frame 0 must not be published before the nodes that consume it are listening (a lost first
        # frame means no target initialisation, and a lockstep run that never starts).
        self.barrier = self.runtime.wait_for_consumers(p.wait_for_consumers_s, p.start_delay_s)
        # Published every frame either way (available=False without), so joins never wait for it.
        self.has_truth = p.source.startswith("scene:") or bool(getattr(self.source, "has_ground_truth", False))
        if p.pace == "fast" and "ack" not in self.runtime.spec.inputs:
            self.log.warning("pace: fast without an 'ack' input: publishing at full speed, frames may be dropped")
        self.log.info("source %s at %.1f fps, pace %s", p.source, self.fps, p.pace)

    def _open(self):
        p = self.params
        if _is_mcap(p.source):
            return McapFrameSource(p.source, p.mcap_frame_key)
        if _is_ros2(p.source):
            from .ros2 import Ros2ImageSource

            if self.runtime.session is None:
                raise SourceError("a ROS 2 source needs the bus (it cannot run in-process)")
            return Ros2ImageSource(self.runtime.session, p.source, domain_id=p.ros2_domain_id)
        kw: dict[str, Any] = {}
        if p.source.startswith("scene:"):
            kw = {"seed": p.seed, "width": p.width_px, "height": p.height_px}
            if p.fps:
                kw["fps"] = p.fps
        elif not p.source.startswith("camera:"):
            if p.fps:
                kw["fps"] = p.fps
            if p.groundtruth:
                kw["groundtruth"] = p.groundtruth
        return open_source(p.source, **kw)

    def on_message(self, name: str, msg: Message) -> None:
        if name == "ack":
            self.acked = max(self.acked, msg.header.frame_seq)

    def poll(self, now_ns: int) -> float | None:
        p = self.params
        if self.done:
            return None
        wait = self.barrier.wait_s()
        if wait > 0:
            return wait
        in_flight = self.published - 1 - self.acked
        if p.pace == "fast" and "ack" in self.runtime.spec.inputs and in_flight >= p.max_in_flight:
            return 0.002  # consumers are behind: wait for the ack of an earlier frame
        item = self._next_item()
        if item is None:  # a live source (ROS 2) with no new image yet
            return 0.0
        if item is _END:
            return self._source_ended()
        if self.t0_wall_ns is None:
            self.t0_wall_ns = self.runtime.clock.wall_ns()
            self.first_source_ns = item.t_ns
        self.last_source_ns = item.t_ns
        # Stamps keep the source's exact frame spacing (Kalman Δt is deterministic) anchored to
        # wall time (latency = receive time - stamp is meaningful when paced to real time).
        stamp = self.t0_wall_ns + (item.t_ns - self.first_source_ns)
        self._publish(item, stamp)
        if p.max_frames and self.published >= p.max_frames:
            self.done = True
            return None
        if p.pace == "fast":
            return 0.0
        return max(0.0, (stamp + int(1e9 / self.fps) - self.runtime.clock.wall_ns()) / 1e9)

    def _next_item(self) -> Any:
        """The source's next frame, None (none yet) or _END. A source that raises is never taken for exhausted: its
        generator is finished, so the next poll resumes the source at the same frame (a camera reopens) and the
        runtime's poll budget (bus/liveness.py) retries it with backoff, then fails the node, whose launcher
        restarts it and names the error."""
        try:
            if self.frames is None:
                self.frames = self.source.resume(self.position)
                self.log.info("source %s resumed at frame %d", self.params.source, self.position)
            item = next(self.frames)
        except StopIteration:
            return _END
        except Exception as exc:
            self.frames = None
            if isinstance(exc, SourceReadError):
                raise  # its message names the source (the image, the camera)
            raise SourceReadError(f"source {self.params.source!r}: {type(exc).__name__}: {exc}") from exc
        if item is not None:
            self.position = item.index + 1
        return item

    def _source_ended(self) -> float | None:
        """Every frame of the source was published: again from its first with ``loop``, else done for good."""
        if self.params.loop:
            # A source that can run again does so (a scene keeps its rendered assets: re-opening one
            # cost a ~180 ms stall at every pass, 300+ ms on a busy CPU); others are re-opened.
            if not getattr(self.source, "rewindable", False):
                self.source.close()
                self.source = self._open()
            self.frames = iter(self.source)
            self.position = 0
            self.first_source_ns -= self.last_source_ns + int(1e9 / self.fps)
            return 0.0
        self.log.info("source exhausted after %d frames", self.published)
        self.done = True
        return None

    def _publish(self, item, stamp_ns: int) -> None:
        bgr = np.ascontiguousarray(item.bgr)
        h, w = bgr.shape[:2]
        seq = self.published
        frame = Frame(width=w, height=h, encoding="bgr8", data=bgr)
        frame.header.stamp_ns, frame.header.frame_seq = stamp_ns, seq
        gt = GroundTruth(available=self.has_truth)
        if item.gt_box is not None:
            gt.box = np.asarray(item.gt_box, dtype=np.float64)
        gt.visible_fraction = float(item.extras.get("visible_fraction", 1.0 if item.gt_box is not None else 0.0))
        others = item.extras.get("distractor_boxes")
        if others is None:  # MOT layout: everyone annotated except the followed person
            target = tuple(item.gt_box) if item.gt_box is not None else None
            others = [row[1:5] for row in item.extras.get("gt_all", []) if tuple(row[1:5]) != target]
        gt.others = np.asarray(others, dtype=np.float64).reshape(-1, 4)
        vis = item.extras.get("distractor_visible_fractions")
        if vis is not None:
            gt.others_visible = np.asarray(vis, dtype=np.float64).reshape(-1)
        gt.header.stamp_ns, gt.header.frame_seq = stamp_ns, seq
        frame.header.epoch_ns = gt.header.epoch_ns = self.epoch_ns
        # Ground truth first: a detector joining it with the frame never waits.
        self.publish("ground_truth", gt)
        self.publish("frame", frame)
        if self.runtime.listened("preview"):  # a resize and a JPEG encode each frame: not for nobody
            self.publish("preview", self._preview(bgr, stamp_ns, seq))
        self.published += 1

    def _preview(self, bgr: np.ndarray, stamp_ns: int, seq: int) -> Frame:
        p = self.params
        h, w = bgr.shape[:2]
        scale = min(1.0, p.preview_width_px / w)
        small = cv2.resize(bgr, (int(w * scale), int(h * scale)), interpolation=cv2.INTER_AREA) if scale < 1 else bgr
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, p.jpeg_quality])
        msg = Frame(width=small.shape[1], height=small.shape[0], encoding="jpeg",
                    data=np.frombuffer(jpeg.tobytes() if ok else b"", np.uint8), source_width=w, source_height=h)
        msg.header.stamp_ns, msg.header.frame_seq, msg.header.epoch_ns = stamp_ns, seq, self.epoch_ns
        return msg

    def status(self) -> dict[str, Any]:
        return {"published": self.published, "acked": self.acked, "done": self.done}

    def teardown(self) -> None:
        self.source.close()


def _is_mcap(source: str) -> bool:
    return source.strip().lower().endswith(".mcap")


def _is_ros2(source: str) -> bool:
    return source.strip().startswith("ros2:")


def mcap_frame_channel(path: str, frame_key: str = "") -> tuple[Any, str]:
    """(summary, frame key) of a recording to read frames from (bus/recording.py, the one reader of
    recordings); SourceError when the file is missing, unreadable or has no frames."""
    from ..bus.recording import (  # here: a camera-fed capture never loads mcap
        RecordingError,
        chunks_to_skip,
        frame_channel,
    )

    try:
        summary, key = frame_channel(path, frame_key)
        chunks_to_skip(path, None, "refuse")  # a corrupt chunk: `followbus recover` makes a file without it
        return summary, key
    except RecordingError as exc:
        reason = str(exc).removeprefix(f"{path}: ")
        raise SourceError(f"MCAP source {path!r}: {reason}") from exc


class McapFrameSource:
    """Raw frames (and ground truth, when recorded) of a followbus MCAP recording, in log-time order."""

    def __init__(self, path: str, frame_key: str = ""):
        self.path = Path(path)
        # The same checks `followbus check` and `launch` run before starting anything (SourceError).
        summary, self.frame_key = mcap_frame_channel(self.path, frame_key)
        topics = {ch.topic for ch in summary.channels.values()}
        self.truth_key = self.frame_key.rsplit("/", 1)[0] + "/ground_truth"
        self.has_ground_truth = self.truth_key in topics
        self.name = self.path.name
        stats = summary.statistics
        duration_s = ((stats.message_end_time - stats.message_start_time) / 1e9) if stats else 0.0
        count = next((stats.channel_message_counts.get(cid, 0) for cid, ch in summary.channels.items()
                      if ch.topic == self.frame_key), 0) if stats else 0
        self.fps = (count - 1) / duration_s if count > 1 and duration_s > 0 else 30.0

    def __iter__(self):
        return self.frames()

    def resume(self, start: int):
        return self.frames(start)

    def frames(self, start: int = 0):
        from ..bus.recording import iter_bus_messages  # here: a camera-fed capture never loads mcap
        from ..vision.sources import SourceFrame

        truth: dict[int, GroundTruth] = {}
        first_stamp: int | None = None
        index = 0
        keys = [self.frame_key] + ([self.truth_key] if self.has_ground_truth else [])
        # The shared reader (bus/recording.py): bus channels only, whichever label the recording gives them.
        for record in iter_bus_messages(self.path, keys):
            try:
                msg = decode(record.data)
            except DecodeError:
                continue  # a corrupt recorded message: skipped, the next frame follows
            if isinstance(msg, GroundTruth):
                truth[msg.header.frame_seq] = msg
                continue
            if not isinstance(msg, Frame) or msg.encoding != "bgr8":
                continue
            first_stamp = msg.header.stamp_ns if first_stamp is None else first_stamp
            gt = truth.pop(msg.header.frame_seq, None)
            extras: dict[str, Any] = {"recorded_frame_seq": msg.header.frame_seq}
            if gt is not None and gt.available:
                extras.update(visible_fraction=gt.visible_fraction, distractor_boxes=gt.others.tolist(),
                              distractor_visible_fractions=gt.others_visible.tolist())
            box = None if gt is None or gt.box is None else tuple(float(v) for v in gt.box)
            if index < start:
                index += 1
                continue
            yield SourceFrame(index, msg.header.stamp_ns - first_stamp, np.array(msg.data), box, extras)
            index += 1

    def close(self) -> None:
        pass


NODE = Capture
