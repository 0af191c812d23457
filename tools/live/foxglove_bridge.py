"""``followbus foxglove``: serve the live bus to the Foxglove app through the foxglove-sdk WebSocket server.

A Zenoh client that only subscribes (never raw frames): the JPEG preview becomes ``foxglove.CompressedImage``
on ``/<ns>/preview``; the target box, the Mahalanobis gate ellipse and the re-id candidates become
``foxglove.ImageAnnotations`` on ``/<ns>/annotations`` in preview pixels (boxes live in source-frame pixels, so
they are scaled by preview width / source width); the motor command and node status go out as JSON. With a
group graph (graph.group.yaml, seed 004) the followed group becomes a ``foxglove.SceneUpdate`` on
``/<ns>/group/scene`` in the robot frame ``base_link`` (x forward, y left, metres: the tracker's ellipses at
2 standard deviations, members, disturbers, centre) for a 3D panel, and its floor ellipses are drawn into
the preview annotations through the groundplane node's camera. The SDK
server drops messages for slow clients on its side, so the robot never waits on Foxglove.

In Foxglove: Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8765, then an Image panel on the preview
topic with the annotations topic enabled (and, for a group, a 3D panel with display frame ``base_link``).
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np
import zenoh

from ...bus.codec import DecodeError
from ...bus.pubsub import declare_subscriber, frame_bytes
from ...bus.schemas import Frame, Message, NodeStatus, decode, to_plain
from ...bus.session import ZenohSettings, open_session
from ...msgs.group import GroundPoints, GroupState
from ...msgs.robot import MotorCommand
from ...msgs.tracking import Measurement, Prior, Track
from ...viewing.drawing import ELLIPSE_POINTS, ellipse_outline, gate_polygon
from ...viewing.monitor import GraphInfo
from ...viewing.snapshot import group_view
from .introspect import wait_for

log = logging.getLogger("followbus.foxglove")

ROBOT_FRAME = "base_link"  # x forward, y left (REP 103), the frame group_view places the group in
POSES_KEPT = 64  # GroundPoints poses remembered by frame_seq, to place the GroupState of the same frame
MEMBER_DIAMETER_M = 0.3


GROUP_COLOURS = {"ellipse": (0.9, 0.2, 0.9), "member": (0.2, 0.9, 0.2), "other": (0.9, 0.2, 0.2),
                 "centre": (0.9, 0.2, 0.9)}


def group_shapes(view: dict[str, Any]) -> dict[str, list]:
    """The followed group (:func:`monitor.group_view`, robot frame) as plain floor shapes: ``loops`` (each
    ellipse's outline, (x, y) m) and ``spheres`` ((x, y, diameter m, kind) with kind member, other or centre).
    Unposed (its frame's GroundPoints not received): the centre alone; no valid group: nothing."""
    loops: list[list[tuple[float, float]]] = []
    spheres: list[tuple[float, float, float, str]] = []
    if view.get("valid"):
        for e in view.get("ellipses", []):
            outline = ellipse_outline(np.asarray(e["centre_m"], float), np.asarray(e["extent_m2"], float),
                                      ELLIPSE_POINTS)
            loops.append([(float(x), float(y)) for x, y in outline])
        for kind, key in (("member", "members_robot_m"), ("other", "others_robot_m")):
            spheres += [(float(p[0]), float(p[1]), MEMBER_DIAMETER_M, kind) for p in view.get(key, [])]
        c = view["centre_robot_m"]
        spheres.append((float(c[0]), float(c[1]), MEMBER_DIAMETER_M / 2, "centre"))
    return {"loops": loops, "spheres": spheres}


def group_scene(view: dict[str, Any], stamp_ns: int) -> Any:
    """:func:`group_shapes` as one ``foxglove.SceneUpdate`` entity in ``base_link``: ellipses as magenta line
    loops on the floor, members green, points left out red, the centre magenta. An invalid group gives an
    empty entity, so a stale shape does not linger."""
    from foxglove.messages import (
        Color,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        Timestamp,
        Vector3,
    )

    shapes = group_shapes(view)
    identity = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    origin = Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=identity)

    def colour(kind: str) -> Any:
        r, g, b = GROUP_COLOURS[kind]
        return Color(r=r, g=g, b=b, a=1.0)

    lines = [LinePrimitive(type=LinePrimitiveLineType.LineLoop, pose=origin, thickness=0.03, scale_invariant=False,
                           color=colour("ellipse"), points=[Point3(x=x, y=y, z=0.0) for x, y in loop])
             for loop in shapes["loops"]]
    spheres = [SpherePrimitive(pose=Pose(position=Vector3(x=x, y=y, z=0.0), orientation=identity),
                               size=Vector3(x=d, y=d, z=d), color=colour(kind))
               for x, y, d, kind in shapes["spheres"]]
    ts = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    return SceneUpdate(entities=[SceneEntity(timestamp=ts, frame_id=ROBOT_FRAME, id="group", frame_locked=True,
                                             lines=lines, spheres=spheres)])


class FoxgloveBridge:
    def __init__(self, settings: ZenohSettings, info: GraphInfo, host: str = "127.0.0.1", port: int = 8765):
        import foxglove
        from foxglove.channels import CompressedImageChannel, ImageAnnotationsChannel

        self.info = info
        self.lock = threading.Lock()
        self.preview_width = 0
        self.latest: dict[str, Message] = {}
        ns = info.namespace
        self.server = foxglove.start_server(name="followbus", host=host, port=port)
        self.image = CompressedImageChannel(f"/{ns}/preview")
        self.annotations = ImageAnnotationsChannel(f"/{ns}/annotations")
        self.command = foxglove.Channel(f"/{ns}/motor/command", message_encoding="json")
        self.status = foxglove.Channel(f"/{ns}/status", message_encoding="json")
        self.group_scene: Any = None  # advertised at the first GroupState: a person graph shows no group topic
        self.group: dict[str, Any] | None = None  # the latest group_view, for the preview annotations
        self.poses: dict[int, tuple[float, float, float]] = {}
        self.points: GroundPoints | None = None
        self.session = open_session(settings)
        keys = info.keys
        self.subs = [
            declare_subscriber(self.session, keys["points"], self._on_points),
            declare_subscriber(self.session, keys["group"], self._on_group),
            declare_subscriber(self.session, info.preview_key, self._on_preview),
            declare_subscriber(self.session, keys["track"], self._remember),
            declare_subscriber(self.session, keys["prior"], self._remember),
            declare_subscriber(self.session, keys["measurement"], self._remember),
            declare_subscriber(self.session, keys["command"], self._on_command),
            declare_subscriber(self.session, f"{ns}/@status/*", self._on_status),
        ]

    @property
    def port(self) -> int:
        return int(self.server.port)

    @staticmethod
    def _decode(sample: zenoh.Sample) -> Message | None:
        try:
            return decode(frame_bytes(sample))
        except DecodeError as exc:
            log.debug("decode error on %s: %s", sample.key_expr, exc)
            return None

    def _remember(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample)
        if msg is not None:
            with self.lock:
                self.latest[msg.TYPE] = msg

    def _on_points(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample)
        if isinstance(msg, GroundPoints):
            with self.lock:
                self.points = msg
                self.poses[msg.header.frame_seq] = (msg.robot_x_m, msg.robot_y_m, msg.robot_theta_rad)
                while len(self.poses) > POSES_KEPT:
                    del self.poses[min(self.poses)]

    def _on_group(self, sample: zenoh.Sample) -> None:
        from foxglove.channels import SceneUpdateChannel

        msg = self._decode(sample)
        if not isinstance(msg, GroupState):
            return
        with self.lock:
            view = group_view(msg, self.poses.get(msg.header.frame_seq), self.points, self.info.camera)
            self.group = view
            if self.group_scene is None:
                self.group_scene = SceneUpdateChannel(f"/{self.info.namespace}/group/scene")
        self.group_scene.log(group_scene(view, msg.header.stamp_ns), log_time=msg.header.stamp_ns)

    def _on_command(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample)
        if isinstance(msg, MotorCommand):
            self.command.log(to_plain(msg), log_time=msg.header.pub_ns or None)

    def _on_status(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample)
        if isinstance(msg, NodeStatus):
            self.status.log(to_plain(msg))

    def _on_preview(self, sample: zenoh.Sample) -> None:
        from foxglove.messages import CompressedImage, Timestamp

        msg = self._decode(sample)
        if not isinstance(msg, Frame) or msg.encoding != "jpeg":
            return
        ts = Timestamp(msg.header.stamp_ns // 1_000_000_000, msg.header.stamp_ns % 1_000_000_000)
        frame_id = f"{self.info.namespace}/preview"
        self.image.log(CompressedImage(timestamp=ts, frame_id=frame_id, data=msg.data.tobytes(), format="jpeg"),
                       log_time=msg.header.stamp_ns)
        self.annotations.log(self._annotate(ts, msg.width), log_time=msg.header.stamp_ns)

    def _annotate(self, ts: Any, preview_width: int) -> Any:
        from foxglove.messages import (
            Color,
            ImageAnnotations,
            Point2,
            PointsAnnotation,
            PointsAnnotationType,
            TextAnnotation,
        )

        scale = preview_width / max(self.info.source_width, 1)
        with self.lock:
            track, prior, meas = self.latest.get("Track"), self.latest.get("Prior"), self.latest.get("Measurement")
            group = self.group
        points, texts = [], []

        def poly(pts: list[tuple[float, float]], color: Color, thickness: float) -> None:
            points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.LineLoop,
                                           points=[Point2(x=x, y=y) for x, y in pts], outline_color=color,
                                           fill_color=Color(r=0, g=0, b=0, a=0), thickness=thickness))

        def box(b: Any, color: Color, thickness: float) -> None:
            x, y, w, h = (float(v) * scale for v in np.asarray(b, float).reshape(-1)[:4])
            poly([(x, y), (x + w, y), (x + w, y + h), (x, y + h)], color, thickness)

        yellow, cyan, green = Color(r=0.9, g=0.8, b=0.2, a=1), Color(r=0.2, g=0.8, b=1, a=1), Color(r=0.2, g=0.9,
                                                                                                    b=0.2, a=1)
        if isinstance(meas, Measurement) and np.size(meas.candidates):
            for c in np.asarray(meas.candidates, float).reshape(-1, 5):
                box(c[:4], yellow, 1.0)
        if isinstance(prior, Prior) and prior.initialised and np.all(np.isfinite(prior.innovation_cov)):
            poly(gate_polygon(prior.state[:2], prior.innovation_cov, prior.gate_chi2, scale=scale), cyan, 1.5)
        if group is not None and group.get("valid"):  # the group's floor ellipses through the camera (source px)
            magenta = Color(r=0.9, g=0.2, b=0.9, a=1)
            for e in group.get("ellipses", []):
                pts = [(p[0] * scale, p[1] * scale) for p in e.get("outline_px") or [] if p is not None]
                if len(pts) >= 3:
                    poly(pts, magenta, 1.5)
        if isinstance(track, Track) and track.box is not None:
            box(track.box, green, 2.0)
            x, y = (float(v) * scale for v in np.asarray(track.box, float)[:2])
            texts.append(TextAnnotation(timestamp=ts, position=Point2(x=x, y=max(y - 4, 10)), text=track.state,
                                        font_size=12.0, text_color=green,
                                        background_color=Color(r=0, g=0, b=0, a=0.6)))
        return ImageAnnotations(points=points, texts=texts)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()
        self.server.stop()


def run_foxglove(args: Any) -> int:
    from .monitor import graph_info, monitor_settings

    try:
        import foxglove  # noqa: F401
    except ImportError:
        print("followbus foxglove needs the foxglove-sdk package: pip install foxglove-sdk")
        return 2
    settings = monitor_settings(args.graph, args.connect, args.user, args.password, args.ca)
    info = graph_info(args.graph, args.namespace)
    bridge = FoxgloveBridge(settings, info, args.bind, args.port)
    print(f"followbus foxglove: ws://{args.bind}:{bridge.port} (watching {', '.join(settings.connect)}; "
          "Ctrl-C to stop)", flush=True)
    try:
        wait_for(args.seconds)
    except KeyboardInterrupt:
        pass
    finally:
        bridge.close()
    return 0
