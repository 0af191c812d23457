"""``followbus bench record-views FILE``: what the recorder's views cost per frame, against the former views.

Replays the bus messages of a recording through the recorder's two threads' work, in one process, rounds
alternated: *convert* (decode + the views) and *write* (bus bytes + views into an MCAP file on /dev/shm when it
exists, else the temporary directory), per frame of the recording's frame key. ``before`` is the former recorder's
views (frames as foxglove.CompressedImage, JPEG in base64 JSON; annotations of Detections, Prior, Track);
``now`` is tools/recording/views.py (ROS 2 CDR for frames, command, odometry, detections; JSON of every message;
the same annotations) plus the ROS 2 companion file. The recorder keeps up while convert and write each stay
under a frame period (33 ms at 30 Hz): they run on threads of their own. Times are the thread's CPU time
(``time.thread_time``), so a loaded machine lengthens them less than it does wall time.
"""

from __future__ import annotations

import base64
import json
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ...bus.recording import iter_bus_messages
from ...bus.schemas import Frame, decode
from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)
from ..recording import foxglove_schemas as fox
from ..recording.mcap_io import ROS2_PROFILE, RecordingWriter
from ..recording.views import ROS2_SCHEMA_ENCODING, View, foxglove_schema, message_views


def _before_views(key: str, msg, stamp_ns: int) -> list[View]:
    """The recorder's views before ROS 2 CDR and JSON: the base64 JPEG image and the three annotations."""
    if isinstance(msg, Frame):
        data = (np.asarray(msg.data, np.uint8).tobytes() if msg.encoding == "jpeg"
                else cv2.imencode(".jpg", msg.data, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes())
        payload = json.dumps({"timestamp": fox.stamp(stamp_ns), "frame_id": key,
                              "data": base64.b64encode(data).decode("ascii"), "format": "jpeg"}).encode()
        return [View(f"{key}/image", foxglove_schema(fox.COMPRESSED_IMAGE), payload)]
    annotate = fox.ANNOTATORS.get(msg.TYPE)
    return [View(f"{key}/annotations", foxglove_schema(fox.IMAGE_ANNOTATIONS), annotate(msg))] if annotate else []


def _round(messages: list, now: bool, folder: Path) -> tuple[float, float, int]:
    """(convert s, write s, view bytes) of one pass over the recording's messages."""
    convert = write = 0.0
    view_bytes = 0
    writer = RecordingWriter(folder / "bench.mcap")
    ros2_writer = RecordingWriter(folder / "bench.ros2.mcap", profile=ROS2_PROFILE) if now else None
    for record in messages:
        t0 = time.thread_time()
        msg = decode(record.data)
        views = message_views(record.key, msg, record.log_time) if now else _before_views(record.key, msg,
                                                                                          record.log_time)
        t1 = time.thread_time()
        writer.write(writer.bus_channel(record.key, msg.TYPE), record.log_time, record.data)
        for view in views:
            writer.write(writer.view_channel(view.topic, view.schema, record.key), record.log_time, view.payload)
            if ros2_writer is not None and view.schema.encoding == ROS2_SCHEMA_ENCODING:
                ros2_writer.write(ros2_writer.view_channel(view.topic, view.schema, record.key), record.log_time,
                                  view.payload)
            view_bytes += len(view.payload)
        convert, write = convert + t1 - t0, write + time.thread_time() - t1
    t2 = time.thread_time()
    writer.finish()
    if ros2_writer is not None:
        ros2_writer.finish()
    return convert, write + time.thread_time() - t2, view_bytes


def run_bench_record_views(args) -> int:
    messages = [m for m in iter_bus_messages(args.file) if m.type_name]
    frames = sum(1 for m in messages if m.key.endswith("/" + args.frame_output))
    if not frames:
        print(f"followbus: {args.file} has no <node>/{args.frame_output} messages to count frames by", flush=True)
        return 2
    base = "/dev/shm" if os.path.isdir("/dev/shm") else None
    print(f"{len(messages)} bus messages, {frames} frames; load {_load()}")
    print(f"{'round':<6} {'views':<7} {'convert CPU ms/frame':>21} {'write CPU ms/frame':>19} {'view kB/frame':>14}")
    for i in range(args.rounds):
        for now in (False, True):
            with tempfile.TemporaryDirectory(dir=base) as folder:
                convert, write, view_bytes = _round(messages, now, Path(folder))
            print(f"{i + 1:<6} {'now' if now else 'before':<7} {1e3 * convert / frames:>21.2f} "
                  f"{1e3 * write / frames:>19.2f} {view_bytes / frames / 1e3:>14.1f}", flush=True)
    print(f"load {_load()}")
    return 0


def _load() -> str:
    return Path("/proc/loadavg").read_text().strip() if Path("/proc/loadavg").exists() else "?"

