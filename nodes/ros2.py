"""ros2: followbus as a ROS 2 node on rmw_zenoh, no bridge process: the motor command goes out as
``geometry_msgs/msg/Twist`` on ``/cmd_vel`` (configurable) and the followed target as
``geometry_msgs/msg/PointStamped`` in ``base_link`` (x forward, y left, from the command's range and bearing), in
rmw_zenoh's key expressions, CDR payloads, attachments and liveliness tokens (bus/rmw_zenoh.py), so
``ros2 topic echo /cmd_vel`` and ``ros2 node list`` on a machine with rmw_zenoh see them.

    ros2:
      run: followbus.nodes.ros2
      inputs:
        command: {from: motor/command, sync: none}
      params: {cmd_vel_topic: /cmd_vel, domain_id: 0}

The node forwards; it never steers: a command older than ``stale_after_ms`` (the motor node stopped, or its
messages stopped arriving) is followed by a zero Twist, and so is the node's own shutdown, so a ROS 2 base
never keeps driving on followbus's last word. Nothing from ROS 2 comes back into the graph through this node.

The capture node's ROS 2 source (``source: ros2:/camera/image_raw``, or a ``.../compressed`` topic for
``sensor_msgs/msg/CompressedImage``) is :class:`Ros2ImageSource` below.
"""

from __future__ import annotations

import queue
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import zenoh

from ..bus import ros2
from ..bus.node import In, Node
from ..bus.node_params import ParamError
from ..bus.rmw_zenoh import SENSOR_QOS, Qos, Ros2Node
from ..bus.schemas import Message
from ..msgs import ros2 as msgs_ros2
from ..msgs.robot import MotorCommand
from ..vision.sources import SourceError, SourceFrame

ROS2_SOURCE_PREFIX = "ros2:"


@dataclass
class Ros2Params:
    node_name: str = "followbus"
    namespace: str = "/"
    domain_id: int = 0  # ROS_DOMAIN_ID
    cmd_vel_topic: str = "/cmd_vel"
    target_topic: str = "/followbus/target"  # "" : not published
    stale_after_ms: float = 200.0  # no command for this long: a zero Twist (the motor's own stop bound)
    connect: str = ""  # a Zenoh endpoint of the ROS 2 side (its rmw_zenohd router); "": the graph's session

    def check(self) -> None:
        """The topic names and the domain (`followbus check`, `launch`, and the node's setup)."""
        check_topic(self.cmd_vel_topic, "cmd_vel_topic")
        if self.target_topic:
            check_topic(self.target_topic, "target_topic")
        if self.domain_id < 0 or self.domain_id > 232:
            raise ParamError("domain_id", f"domain_id must be 0..232 (ROS_DOMAIN_ID), not {self.domain_id}")


def check_topic(topic: str, what: str, example: str = "/cmd_vel") -> None:
    if not topic.startswith("/") or "//" in topic or topic.endswith("/") or " " in topic:
        raise ParamError(what, f"{what} must be an absolute ROS 2 topic name like {example}, not {topic!r}")


def ros_session(graph_session: zenoh.Session | None, connect: str) -> tuple[zenoh.Session, bool]:
    """The session the ROS 2 side is reached through: the graph's, or one of its own to ``connect`` (owned)."""
    if not connect:
        if graph_session is None:
            raise RuntimeError("the ros2 node needs a Zenoh session (it cannot run in-process)")
        return graph_session, False
    config = zenoh.Config()
    config.insert_json5("connect/endpoints", f'["{connect}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config), True


class Ros2Out(Node):
    INPUTS = {"command": In(MotorCommand, required=True)}  # wired sync: none, each command as it comes
    Params = Ros2Params

    def setup(self) -> None:
        p = self.params
        p.check()
        self.session, self.own_session = ros_session(self.runtime.session, p.connect)
        self.ros = Ros2Node(self.session, p.node_name, p.namespace, p.domain_id)
        self.cmd_vel = self.ros.publisher(p.cmd_vel_topic, ros2.TWIST, Qos(depth=10))
        self.target = self.ros.publisher(p.target_topic, ros2.POINT_STAMPED, Qos(depth=10)) if p.target_topic else None
        self.last_command_ns: int | None = None
        self.moving = False
        self.sent = 0
        self.log.info("ROS 2 node /%s (domain %d): %s on %s", p.node_name, p.domain_id, ros2.TWIST, self.cmd_vel.key)

    def on_message(self, name: str, msg: Message) -> None:
        if not isinstance(msg, MotorCommand):
            return
        self.last_command_ns = self.runtime.clock.monotonic_ns()  # a watchdog: no stamp may steer it
        self._send(msgs_ros2.command_twist(msg), moving=bool(msg.vx_mps or msg.vy_mps or msg.wz_radps))
        point = msgs_ros2.target_point(msg)
        if self.target is not None and point is not None:
            self.target.publish(point)

    def _send(self, twist: Any, moving: bool) -> None:
        self.cmd_vel.publish(twist)
        self.moving = moving
        self.sent += 1

    def poll(self, now_ns: int) -> float | None:
        stale_ns = self.params.stale_after_ms * 1e6
        now_ns = self.runtime.clock.monotonic_ns()
        if self.moving and self.last_command_ns is not None and now_ns - self.last_command_ns > stale_ns:
            self.log.warning("no motor command for %.0f ms: zero Twist on %s", self.params.stale_after_ms,
                             self.params.cmd_vel_topic)
            self._send(ros2.twist(0.0, 0.0, 0.0), moving=False)
        return self.params.stale_after_ms / 4e3

    def status(self) -> dict[str, Any]:
        return {"cmd_vel_sent": self.sent, "moving": self.moving}

    def teardown(self) -> None:
        if self.moving:
            self._send(ros2.twist(0.0, 0.0, 0.0), moving=False)
        self.ros.close()
        if self.own_session:
            self.session.close()


NODE = Ros2Out


# --- the capture source ----------------------------------------------------------------------------

def ros2_image_topic(source: str) -> tuple[str, str]:
    """(topic, message type) of a ``ros2:<topic>`` source; SourceError for a malformed one."""
    topic = source[len(ROS2_SOURCE_PREFIX):].strip()
    try:
        check_topic(topic, "source", "/camera/image_raw")
    except ParamError as exc:
        raise SourceError(f"ROS 2 source {source!r}: {exc}") from None
    return topic, ros2.COMPRESSED_IMAGE if topic.endswith("/compressed") else ros2.IMAGE


class Ros2ImageSource:
    """Frames of a ROS 2 image topic (sensor_msgs/Image bgr8/rgb8/mono8, or CompressedImage), subscribed as a
    ROS 2 node of its own (``<node_name>``) over rmw_zenoh's format. Frames queue up to ``queue_frames`` (the
    oldest dropped beyond: the capture node paces and numbers them); ``t_ns`` is the image's header stamp. While
    none arrives, iteration yields None (the capture node polls again) and never ends: a camera that stops
    publishing is waited for, as a camera device is."""

    def __init__(self, session: zenoh.Session, source: str, node_name: str = "followbus_capture",
                 domain_id: int = 0, queue_frames: int = 64):
        self.topic, self.type_name = ros2_image_topic(source)
        self.name = source
        self.fps = 30.0
        self.dropped = self.bad = 0
        self._frames: queue.Queue[tuple[int, np.ndarray]] = queue.Queue(maxsize=queue_frames)
        self._node = Ros2Node(session, node_name, domain_id=domain_id)
        self._sub = self._node.subscription(self.topic, self.type_name, self._on_image, SENSOR_QOS)

    def _on_image(self, msg: Any, _source_stamp_ns: int) -> None:
        try:
            bgr = self._pixels(msg)
        except ValueError:
            self.bad += 1
            return
        while True:
            try:
                self._frames.put_nowait((ros2.stamp_ns(msg.header), bgr))
                return
            except queue.Full:
                try:
                    self._frames.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def _pixels(self, msg: Any) -> np.ndarray:
        if self.type_name == ros2.IMAGE:
            return ros2.image_pixels(msg)
        bgr = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"undecodable {msg.format!r} image")
        return bgr

    def __iter__(self) -> Iterator[SourceFrame | None]:
        index = 0
        while True:
            try:
                stamp, bgr = self._frames.get(timeout=0.1)
            except queue.Empty:
                yield None
                continue
            yield SourceFrame(index, stamp, bgr, None, {})
            index += 1

    def resume(self, _start: int) -> Iterator[SourceFrame | None]:
        """After a failed iteration: the images that arrive from now on."""
        return iter(self)

    def close(self) -> None:
        self._node.close()
