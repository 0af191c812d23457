"""``followbus foxglove``: serve the live bus to the Foxglove app through the foxglove-sdk WebSocket server.

A Zenoh client that only subscribes (never raw frames): the JPEG preview becomes ``foxglove.CompressedImage``
on ``/<ns>/preview``; the target box, the Mahalanobis gate ellipse and the re-id candidates become
``foxglove.ImageAnnotations`` on ``/<ns>/annotations`` in preview pixels (boxes live in source-frame pixels, so
they are scaled by preview width / source width); the motor command and node status go out as JSON. The SDK
server drops messages for slow clients on its side, so the robot never waits on Foxglove.

In Foxglove: Open connection -> Foxglove WebSocket -> ws://127.0.0.1:8765, then an Image panel on the preview
topic with the annotations topic enabled.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any

import numpy as np
import zenoh

from ..bus.codec import DecodeError
from ..bus.pubsub import direct_callback, payload_bytes
from ..bus.schemas import Frame, Measurement, Message, MotorCommand, NodeStatus, Prior, Track, decode, to_plain
from ..bus.session import ZenohSettings, open_session
from .introspect import wait_for
from .monitor import GraphInfo

log = logging.getLogger("followbus.foxglove")

ELLIPSE_POINTS = 48


def gate_points(centre: Any, cov: Any, chi2: float, scale: float, n: int = ELLIPSE_POINTS) -> list[tuple[float, float]]:
    """The gate {z : (z-c)^T S^-1 (z-c) = chi2} as a polygon: c + V sqrt(chi2 L) u, scaled to the preview."""
    c = np.asarray(centre, float).reshape(2)
    s = np.asarray(cov, float).reshape(2, 2)
    vals, vecs = np.linalg.eigh(0.5 * (s + s.T))
    axes = vecs * np.sqrt(np.clip(vals, 0.0, None) * max(chi2, 0.0))
    t = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    pts = (c[:, None] + axes @ np.stack([np.cos(t), np.sin(t)])) * scale
    return [(float(x), float(y)) for x, y in pts.T]


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
        self.session = open_session(settings)
        keys = info.keys
        self.subs = [
            self.session.declare_subscriber(info.preview_key, direct_callback(self._on_preview)),
            self.session.declare_subscriber(keys["track"], direct_callback(self._remember)),
            self.session.declare_subscriber(keys["prior"], direct_callback(self._remember)),
            self.session.declare_subscriber(keys["measurement"], direct_callback(self._remember)),
            self.session.declare_subscriber(keys["command"], direct_callback(self._on_command)),
            self.session.declare_subscriber(f"{ns}/@status/*", direct_callback(self._on_status)),
        ]

    @property
    def port(self) -> int:
        return int(self.server.port)

    @staticmethod
    def _decode(sample: zenoh.Sample) -> Message | None:
        try:
            return decode(payload_bytes(sample))
        except DecodeError as exc:
            log.debug("decode error on %s: %s", sample.key_expr, exc)
            return None

    def _remember(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample)
        if msg is not None:
            with self.lock:
                self.latest[msg.TYPE] = msg

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
            poly(gate_points(prior.state[:2], prior.innovation_cov, prior.gate_chi2, scale), cyan, 1.5)
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
    from .monitor import monitor_settings

    try:
        import foxglove  # noqa: F401
    except ImportError:
        print("followbus foxglove needs the foxglove-sdk package: pip install foxglove-sdk")
        return 2
    settings = monitor_settings(args.graph, args.connect, args.user, args.password, args.ca)
    info = GraphInfo.load(args.graph, args.namespace)
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
