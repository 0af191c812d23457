"""Recordings read without followbus: every channel decodes with third-party readers only (the bus channels by
the mcap package's reader and msgpack, the views by the mcap reader with mcap-ros2-support's decoder factory,
JSON validated against the JSON Schema stored in the file, and rosbags reading the ROS 2 companion file by the
message definitions stored in it), and --split-size / --split-duration cut a recording into files that each open
on their own."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jsonschema
import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from followbus.bus.recording import BUS_MESSAGE_ENCODING, stored_frame
from followbus.bus.schemas import SCHEMAS, Frame, decode
from followbus.msgs.perception import Detections
from followbus.msgs.robot import MotorCommand, Odometry
from followbus.msgs.tracking import Track
from followbus.tools.recording.record import Recorder, RecordOptions, ros2_path

from .conftest import free_port, run_followbus

ROS2_TYPES = {"image": "sensor_msgs/msg/CompressedImage", "twist": "geometry_msgs/msg/Twist",
              "odometry": "nav_msgs/msg/Odometry", "detections2d": "vision_msgs/msg/Detection2DArray"}


def ext_values(value: object) -> list[msgpack.ExtType]:
    """The MessagePack ext values anywhere in a decoded value (the arrays of a bus message's head)."""
    if isinstance(value, msgpack.ExtType):
        return [value]
    items = value.values() if isinstance(value, dict) else value if isinstance(value, list) else []
    return [ext for item in items for ext in ext_values(item)]


def decode_bus_message(data: bytes) -> dict:
    """A bus channel's message read by msgpack alone, as its schema document says: the array [head, blob area];
    the head a map with the type name; the out-of-band arrays (ext type 2: [dtype, shape, offset, nbytes]) lie
    one after the other in the blob area and fill it."""
    head, blobs = msgpack.unpackb(data, strict_map_key=False)
    assert isinstance(head, dict) and isinstance(head["_t"], str) and isinstance(blobs, bytes), head
    refs = [msgpack.unpackb(ext.data) for ext in ext_values(head) if ext.code == 2]
    assert [offset for _dtype, _shape, offset, _n in refs] == [sum(r[3] for r in refs[:i]) for i in range(len(refs))]
    assert sum(nbytes for _dtype, _shape, _offset, nbytes in refs) == len(blobs), (head["_t"], refs, len(blobs))
    return head


def decode_every_channel(path: Path) -> tuple[dict[str, list], dict[str, list]]:
    """(bus messages by key, views by topic): every message of every channel decoded by third-party code, bus
    ones by msgpack (their head: type name and schema name agree), cdr by mcap-ros2-support, json by json.loads
    checked against the channel's JSON Schema. Fails on a channel nothing decodes."""
    bus: dict[str, list] = {}
    out: dict[str, list] = {}
    cdr_topics = set()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == BUS_MESSAGE_ENCODING:
                head = decode_bus_message(message.data)
                assert head["_t"] == channel.metadata["type"] and schema.name == f"followbus.{head['_t']}", channel
                bus.setdefault(channel.topic, []).append(head)
                continue
            if channel.message_encoding == "cdr":
                assert schema.encoding == "ros2msg", channel.topic
                cdr_topics.add(channel.topic)
                continue
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema", channel.topic
            value = json.loads(message.data)
            jsonschema.Draft202012Validator(json.loads(schema.data)).validate(value)
            out.setdefault(channel.topic, []).append(value)
        for _schema, channel, _message, decoded in reader.iter_decoded_messages(topics=sorted(cdr_topics)):
            out.setdefault(channel.topic, []).append(decoded)
        assert {c.topic for c in reader.get_summary().channels.values()} == set(bus) | set(out)
    return bus, out


def decode_every_view(path: Path) -> dict[str, list]:
    """Every view channel's messages, decoded by third-party code (and every bus channel's, checked)."""
    return decode_every_channel(path)[1]


def bus_keys(path: Path) -> dict[str, list]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        return {c.topic: [] for c in summary.channels.values() if c.message_encoding == BUS_MESSAGE_ENCODING}


def read_with_rosbags(path: Path) -> dict[str, list]:
    """The ROS 2 companion file, read by rosbags with types built from the definitions stored in the file."""
    store = get_typestore(Stores.EMPTY)
    out: dict[str, list] = {}
    with RosbagsReader(path) as reader:
        for conn in reader.connections:
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
        for conn, _t, raw in reader.messages():
            out.setdefault(conn.topic, []).append(store.deserialize_cdr(raw, conn.msgtype))
    return out


def sample_messages() -> dict[str, object]:
    """One message of every registered type (defaults), the standard ones with values."""
    msgs: dict[str, object] = {f"t/all/{name.lower()}": cls() for name, cls in SCHEMAS.items() if name != "Frame"}
    msgs.update({
        "t/capture/frame": Frame(width=64, height=48, data=np.full((48, 64, 3), 90, np.uint8)),
        "t/motor/command": MotorCommand(vx_mps=0.8, vy_mps=-0.1, wz_radps=0.25, range_m=2.0, bearing_rad=0.1),
        "t/motor/odometry": Odometry(x_m=1.5, y_m=0.5, theta_rad=0.3, vx_mps=0.7),
        "t/detection/detections": Detections(boxes=np.array([[5, 6, 20, 30, 0.9], [1, 2, 3, 4, 0.4]], np.float32)),
        "t/prediction/track": Track(state="TRACKING", box=np.array([5.0, 6.0, 20.0, 30.0]),
                                    velocity=np.array([np.nan, 1.0])),
    })
    return msgs


def test_every_message_type_has_views_third_party_readers_decode(tmp_path):
    """Through the real recorder's conversion and writer: each bus key gets views; each view decodes without
    followbus, and the ROS 2 ones carry the values (REP-103 Twist, Odometry quaternion, box centres)."""
    path = tmp_path / "all.mcap"
    recorder = Recorder(RecordOptions(output=path, patterns=["t/**"]), {"followbus": {"test": "1"}})
    recorder.start_threads()
    stamp = 1_700_000_000_123_456_789
    for key, msg in sample_messages().items():
        msg.header.stamp_ns, msg.header.seq = stamp, 1
        recorder._enqueue(key, msg.encode())
    report = recorder.stop()
    assert report.foxglove_errors == 0 and report.written == len(sample_messages())
    views = decode_every_view(path)
    for key in bus_keys(path):
        assert any(topic.startswith(key + "/") for topic in views), f"{key} has no view"
    twist = views["t/motor/command/twist"][0]
    assert (twist.linear.x, twist.linear.y, twist.angular.z) == (0.8, -0.1, 0.25)
    odom = views["t/motor/odometry/odometry"][0]
    assert odom.header.frame_id == "odom" and odom.child_frame_id == "base_link"
    assert odom.pose.pose.orientation.z == pytest.approx(np.sin(0.15)) and odom.twist.twist.linear.x == 0.7
    dets = views["t/detection/detections/detections2d"][0]
    assert [(d.bbox.center.position.x, d.bbox.size_y, d.results[0].hypothesis.score) for d in dets.detections] \
        == [(15.0, 30.0, pytest.approx(0.9)), (2.5, 4.0, pytest.approx(0.4))]
    assert dets.header.stamp.sec * 10**9 + dets.header.stamp.nanosec == stamp
    image = views["t/capture/frame/image"][0]
    assert image.format == "jpeg" and bytes(image.data[:2]) == b"\xff\xd8"
    track = views["t/prediction/track/json"][0]
    assert track["state"] == "TRACKING" and track["velocity"] == [None, 1.0]  # NaN: null, JSON has none
    assert views["t/motor/command/json"][0]["range_m"] == 2.0
    ros2 = read_with_rosbags(ros2_path(path))
    assert set(ros2) == {t for t in views if t.rsplit("/", 1)[1] in ROS2_TYPES}
    assert ros2["t/motor/command/twist"][0].linear.x == 0.8


def test_a_json_view_that_breaks_its_schema_is_caught(tmp_path):
    """The negative control of the JSON check above: a Track whose state is a number fails its schema."""
    from followbus.tools.recording.views import json_schema

    schema = json.loads(json_schema("Track").data)
    good = {f.name: None for f in dataclasses.fields(Track)}
    good.update(header={"seq": 0, "stamp_ns": 0, "frame_seq": 0, "source": "", "pub_ns": 0, "epoch_ns": 0,
                        "feedback": {}}, state="LOST", velocity=[0.0, 0.0], measured=False)
    jsonschema.validate(good, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**good, "state": 3}, schema)


def test_split_size_and_duration_cut_the_recording_into_files_that_open_alone(tmp_path):
    """--split-size: every file a complete MCAP with the metadata, bus channels and their views; together they
    hold every message once, in order; the ROS 2 companions split alike."""
    from followbus.bus.pubsub import Publisher
    from followbus.bus.session import ZenohSettings, open_session

    port = free_port()
    session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    path = tmp_path / "split.mcap"
    recorder = Recorder(RecordOptions(output=path, patterns=["n1s/**"], split_bytes=60_000),
                        {"followbus": {"namespace": "n1s"}})
    try:
        recorder.start(session)
        pub = Publisher(session, "n1s/capture/frame", "test")
        time.sleep(0.3)
        rng = np.random.default_rng(1)
        for i in range(30):  # ~9 kB raw + a JPEG view each: several files
            frame = Frame(width=64, height=48, data=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
            frame.header.stamp_ns, frame.header.frame_seq = time.time_ns(), i
            pub.put(frame)
            time.sleep(0.01)
        time.sleep(0.5)
    finally:
        report = recorder.stop()
        session.close()
    files = sorted((p for p in tmp_path.glob("split_*.mcap") if ".ros2" not in p.name),
                   key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    assert report.files == files and len(files) >= 3, report.files
    seqs = []
    for file in files:
        with open(file, "rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None  # finalised: summary and index
            assert {m.name for m in reader.iter_metadata()} >= {"followbus", "split", "recording_stats"}
            seqs += [decode(stored_frame(m.data)).header.frame_seq for _s, c, m in reader.iter_messages()
                     if c.message_encoding == BUS_MESSAGE_ENCODING]
        assert decode_every_view(file)["n1s/capture/frame/image"]
        assert read_with_rosbags(ros2_path(file))["n1s/capture/frame/image"]
    assert seqs == list(range(30))
    info = run_followbus("info", str(files[-1]))
    assert info.returncode == 0, info.stderr


def test_record_refuses_a_negative_split(tmp_path):
    result = run_followbus("record", "-o", str(tmp_path / "x.mcap"), "--split-duration", "-1",
                           "--connect", f"tcp/127.0.0.1:{free_port()}")
    assert result.returncode == 2 and "split" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.slow
def test_a_recorded_demo_run_decodes_without_followbus(tmp_path):
    """The tracking graph (demo scene, simulated detector) launched with --record for ~40 frames: every channel
    decodes by third-party readers, every bus key has views, and the Twist view carries the command's own
    velocities, as the bus message (read by msgpack) does."""
    from .test_replay_tracking import _record

    path = _record(tmp_path, "n1demo", 100)  # (_record counts 60 fewer: ~40 frames of re-ID)
    bus, views = decode_every_channel(path)
    keys = bus_keys(path)
    assert set(bus) == set(keys) and all(bus[key] for key in keys)
    frames = bus["n1demo/capture/frame"]
    assert frames and all(f["data"].code == 2 for f in frames)  # the image: out of band, in the blob area
    launch_log = (tmp_path / "launch.log").read_text()[-4000:]
    assert {"n1demo/motor/command", "n1demo/motor/odometry", "n1demo/reid/measurement",
            "n1demo/prediction/track", "n1demo/capture/frame"} <= set(keys), (sorted(keys), launch_log)
    for key in keys:
        assert any(topic.startswith(key + "/") for topic in views), f"{key} has no view"
    commands = [views["n1demo/motor/command/json"], views["n1demo/motor/command/twist"]]
    assert len(commands[0]) == len(commands[1]) > 0
    assert [(c["vx_mps"], c["wz_radps"]) for c in commands[0]] == [(t.linear.x, t.angular.z) for t in commands[1]]
    assert [(c["vx_mps"], c["wz_radps"]) for c in bus["n1demo/motor/command"]] == [(t.linear.x, t.angular.z)
                                                                                 for t in commands[1]]
    states = {t["state"] for t in views["n1demo/prediction/track/json"]}
    assert states and states <= {"TRACKING", "OCCLUDED", "REACQUIRED", "LOST", "UNINITIALISED"}, states
    ros2 = read_with_rosbags(ros2_path(path))
    assert len(ros2["n1demo/motor/command/twist"]) == len(commands[1])
    assert len(ros2["n1demo/capture/frame/image"]) == len(views["n1demo/capture/frame/image"]) > 0
    assert len(ros2["n1demo/detection/detections/detections2d"]) > 0 and ros2["n1demo/motor/odometry/odometry"]


def test_bench_record_views_measures_before_and_now(tmp_path, capsys):
    """`followbus bench record-views`: both rows per round, per frame of the recording; no frames: exit 2."""
    import argparse

    from followbus.tools.bench.record_views import run_bench_record_views
    from followbus.tools.recording.mcap_io import RecordingWriter

    path = tmp_path / "small.mcap"
    writer = RecordingWriter(path)
    for i, (key, msg) in enumerate(list(sample_messages().items()) * 2):
        msg.header.stamp_ns = 1_000_000_000 + i
        writer.write(writer.bus_channel(key, msg.TYPE), msg.header.stamp_ns, msg.encode())
    writer.finish()
    args = argparse.Namespace(file=str(path), rounds=1, frame_output="frame")
    assert run_bench_record_views(args) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.startswith("1 ")]
    assert [r[1] for r in rows] == ["before", "now"] and all(float(r[2]) > 0 for r in rows)
    assert run_bench_record_views(argparse.Namespace(file=str(path), rounds=1, frame_output="nothing")) == 2


def test_split_duration_starts_a_new_file_on_time(tmp_path):
    path = tmp_path / "timed.mcap"
    recorder = Recorder(RecordOptions(output=path, patterns=["t/**"], split_seconds=0.3, ros2_file=False), {})
    recorder.start_threads()
    for i in range(10):
        msg = MotorCommand(vx_mps=0.1 * i)
        msg.header.stamp_ns, msg.header.seq = 1_000_000_000 + i, i
        recorder._enqueue("t/motor/command", msg.encode())
        time.sleep(0.1)
    report = recorder.stop()
    assert 2 <= len(report.files) <= 5 and report.files[0].name == "timed_0.mcap", report.files
    assert report.ros2_files == [] and not list(tmp_path.glob("*.ros2.mcap"))
    twists = [t for f in report.files for t in decode_every_view(f).get("t/motor/command/twist", [])]
    assert [round(t.linear.x, 9) for t in twists] == [round(0.1 * i, 9) for i in range(10)]
