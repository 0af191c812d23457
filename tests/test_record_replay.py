"""Recording and replay, end to end with real processes on a private loopback port: record a launched
diagnostic graph (ticker -> relay -> sink) and count what was published, replay the relay with --verify
(in-process and as its own process: identical, then a changed parameter), recover the file of a SIGKILLed
recorder, and check the Foxglove channels with an independent reader (the official @mcap/core +
@foxglove/schemas, run by node)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from followbus.bus.health import HealthWatcher
from followbus.bus.pubsub import Publisher
from followbus.bus.recording import is_bus_channel, read_metadata, stored_frame
from followbus.bus.schemas import Frame, Tick, decode
from followbus.bus.session import ZenohSettings, open_session
from followbus.msgs.perception import Detections
from followbus.msgs.tracking import Prior, Track
from followbus.tools.recording import foxglove_schemas as fox
from followbus.tools.recording.mcap_io import RecordingWriter

from .conftest import REPO, copy_recording, followbus_argv, free_port, run_followbus, wait_until

pytestmark = pytest.mark.slow

TICKS = 100
NODES = f"""\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {{rate_hz: 50, count: {TICKS}}}
  relay:
    run: followbus.nodes.diagnostics_relay
    inputs: {{tick: {{from: ticker/tick, queue: 128, policy: block}}}}
    outputs: [tick]
    max_lag_ms: 0
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs: {{tick: {{from: relay/tick, queue: 128, policy: block}}}}
    max_lag_ms: 0
"""
# relay and sink count every tick, as the recorder must: a queue that holds them all and no set skipped for lag
# (beside a second graph the relay counted 93 of 100: a stalled live node drops the oldest of a full queue of 4
# and skips a frame set 150 ms behind the newest).
VIEW_FRAMES = 10  # frames, detections, priors and tracks the test itself publishes while recording


def graph_text(port: int, nodes: str) -> str:
    """The same graph layout as conftest's graph_file fixture (a module-scoped fixture cannot use it)."""
    return (f"name: test\nnamespace: t\nzenoh:\n  listen: [tcp/127.0.0.1:{port}]\n"
            f"  connect: [tcp/127.0.0.1:{port}]\nnodes:\n{nodes}")


class Proc:
    """A followbus process whose merged output is collected line by line."""

    def __init__(self, *args: str):
        self.popen = subprocess.Popen(followbus_argv(*args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True, stdin=subprocess.DEVNULL, cwd=REPO)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(iter(self.popen.stdout.readline, "")),
                                        daemon=True)
        self._reader.start()

    def has(self, text: str) -> bool:
        return any(text in line for line in self.lines)

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            return self.popen.wait(timeout)
        finally:
            if self.popen.poll() is None:
                self.popen.kill()
            self._reader.join(timeout=5)

    @property
    def output(self) -> str:
        return "".join(self.lines)


def publish_views(session) -> None:
    """Frames (bgr8), detections, Kalman priors and tracks on the keys the demo graph uses."""
    pubs = {name: Publisher(session, f"t/{name}", "test") for name in
            ("capture/frame", "detection/detections", "prediction/prior", "prediction/track")}
    time.sleep(0.3)
    rng = np.random.default_rng(0)
    for i in range(VIEW_FRAMES):
        stamp = time.time_ns()
        msgs = {
            "capture/frame": Frame(width=64, height=48, data=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)),
            "detection/detections": Detections(boxes=np.array([[5, 6, 20, 30, 0.9], [30, 4, 10, 20, 0.4]],
                                                              np.float32)),
            "prediction/prior": Prior(initialised=i > 0, state=np.array([15.0, 21.0, 1.0, 0.0]),
                                      size=np.array([20.0, 30.0]), innovation_cov=np.array([[40.0, 5.0], [5.0, 20.0]]),
                                      box=np.array([5.0, 6.0, 20.0, 30.0])),
            "prediction/track": Track(state="TRACKING", box=np.array([5.0, 6.0, 20.0, 30.0]),
                                      filtered_box=np.array([5.5, 6.0, 20.0, 30.0])),
        }
        for name, msg in msgs.items():
            msg.header.stamp_ns, msg.header.frame_seq = stamp, i
            pubs[name].put(msg)
        time.sleep(0.03)


@dataclass
class Recorded:
    path: Path
    graph: Path
    launcher_output: str
    relay_published: int
    sink_received: int


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Recorded:
    """`launch --record` of relay + sink, then a second launch of the ticker (count 100): the recorder is
    subscribed before the first tick, so the file must hold every message that was published."""
    tmp = tmp_path_factory.mktemp("record")
    port = free_port()
    graph = tmp / "graph.yaml"
    graph.write_text(graph_text(port, NODES))
    path = tmp / "run.mcap"
    main = Proc("launch", str(graph), "--only", "relay,sink", "--record", str(path))
    session = open_session(ZenohSettings(mode="client", listen=[], connect=[f"tcp/127.0.0.1:{port}"],
                                         connect_timeout_ms=30_000))
    watcher = HealthWatcher(session, "t")
    try:
        assert wait_until(lambda: main.has("ready: 2 nodes up") and main.has("[recorder] recording t/**"), 60), \
            main.output
        time.sleep(1.0)  # the recorder's subscription reaches every peer
        publish_views(session)
        ticker = subprocess.run(followbus_argv("launch", str(graph), "--only", "ticker", "--duration", "5"),
                                capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL, cwd=REPO)
        assert ticker.returncode == 0, ticker.stdout + ticker.stderr

        def status(node: str):
            health = watcher.snapshot().get(node)
            return health.status if health else None

        def settled() -> bool:
            relay, sink = status("relay"), status("sink")
            return (relay is not None and relay.topics.get("t/relay/tick", {}).get("count") == TICKS
                    and sink is not None and sink.extra.get("received") == TICKS)

        assert wait_until(settled, 10), (status("relay"), status("sink"))
        relay_count = status("relay").topics["t/relay/tick"]["count"]
        sink_count = status("sink").extra["received"]
    finally:
        code = main.stop()
        watcher.close()
        session.close()
    assert code == 130, main.output  # stopped by Ctrl-C (SIGINT): 130, as every command
    return Recorded(path, graph, main.output, relay_count, sink_count)


def read_all(path: Path) -> dict[str, list]:
    """Every message by topic, read with the mcap package's own reader; a bus channel's message data is its frame
    (bus/recording.stored_frame: the one conversion of what a bus channel holds)."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
            if is_bus_channel(channel):
                message = dataclasses.replace(message, data=stored_frame(message.data))
            out.setdefault(channel.topic, []).append((channel, message))
    return out


def test_record_holds_every_published_message(recorded: Recorded):
    topics = read_all(recorded.path)
    ticks = [decode(m.data, Tick) for _c, m in topics["t/ticker/tick"]]
    relayed = [decode(m.data, Tick) for _c, m in topics["t/relay/tick"]]
    # The ticker published exactly TICKS (its count param), the relay's own status says how many it sent.
    assert sorted(t.value for t in ticks) == list(range(TICKS))
    assert sorted(t.header.seq for t in ticks) == list(range(TICKS))
    assert len(relayed) == recorded.relay_published == recorded.sink_received == TICKS
    for channel, message in topics["t/ticker/tick"] + topics["t/relay/tick"]:
        msg = decode(message.data)
        assert channel.message_encoding == "msgpack" and channel.metadata["type"] == "Tick"
        assert message.log_time == message.publish_time == msg.header.stamp_ns > 0
        assert message.sequence == msg.header.seq
    for key in ("t/capture/frame", "t/detection/detections", "t/prediction/prior", "t/prediction/track"):
        assert len(topics[key]) == VIEW_FRAMES, key
    assert not any("@status" in topic for topic in topics)  # not asked for

    meta = read_metadata(recorded.path)
    assert meta["graph"]["yaml"] == recorded.graph.read_text()
    assert json.loads(meta["params"]["ticker"]) == {"rate_hz": 50, "count": TICKS}
    assert meta["followbus"]["namespace"] == "t" and meta["followbus"]["git_commit"]
    stats = meta["recording_stats"]
    assert stats["dropped"] == "0" and stats["seq_gaps"] == "0" and stats["received"] == stats["written"]
    assert "dropped by the recorder: 0; lost on the way (header.seq gaps): 0" in recorded.launcher_output

    info = run_followbus("info", str(recorded.path))
    assert info.returncode == 0, info.stderr
    row = next(line.split() for line in info.stdout.splitlines() if line.startswith("t/ticker/tick "))
    assert row[1:4] == ["followbus.Tick", "msgpack", str(TICKS)]
    assert "compression none" in info.stdout  # the default: raw frames do not compress


def test_replay_verify_reproduces_the_relay(recorded: Recorded, tmp_path):
    report_path = tmp_path / "replay.json"
    result = run_followbus("replay", str(recorded.path), "--node", "relay", "--verify", "--report",
                           str(report_path), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(report_path.read_text())
    assert report["frames"] == TICKS and report["outputs_compared"] == TICKS == report["matched"]
    assert report["mismatch_count"] == 0 and not report["missing"] and not report["extra"]
    assert report["mode"] == "in-process" and report["node_exit"] is None  # no process was started
    assert report["handler_s"] > 0 and "node time:" in result.stdout
    assert "verify: OK" in result.stdout


def test_replay_isolated_runs_the_deployed_node(recorded: Recorded, tmp_path, monkeypatch):
    """--isolated: the relay as its own process over Zenoh on a private loopback port, same verdict; also from a
    shell that exports a domain (the node keeps the private graph's port and namespace, not the domain's)."""
    monkeypatch.setenv("FOLLOWBUS_DOMAIN", "7")
    report_path = tmp_path / "replay.json"
    result = run_followbus("replay", str(recorded.path), "--node", "relay", "--isolated", "--verify", "--report",
                           str(report_path), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(report_path.read_text())
    assert report["mode"] == "isolated" and report["node_exit"] == 0 and not report["timeouts"]
    assert report["frames"] == TICKS and report["outputs_compared"] == TICKS == report["matched"]
    changed = run_followbus("replay", str(recorded.path), "--node", "relay", "--isolated", "--param", "add=5",
                            "--verify", timeout=120)
    assert changed.returncode == 1, changed.stdout + changed.stderr
    assert "first mismatch: frame 0, key t/relay/tick (#0), field value: recorded 0, replayed 5" in changed.stdout


def test_replay_with_changed_param_reports_the_field(recorded: Recorded, tmp_path):
    report_path = tmp_path / "replay.json"
    result = run_followbus("replay", str(recorded.path), "--node", "relay", "--param", "add=5", "--verify",
                           "--report", str(report_path), timeout=120)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "first mismatch: frame 0, key t/relay/tick (#0), field value: recorded 0, replayed 5" in result.stdout
    report = json.loads(report_path.read_text())
    assert report["params"] == {"add": 5}
    assert report["mismatch_count"] == TICKS
    assert {m["field"] for m in report["mismatches"]} == {"value"}
    assert all(m["replayed"] == m["recorded"] + 5 for m in report["mismatches"])


def test_sigkilled_recorder_file_is_recovered(graph_file, port, tmp_path):
    graph = graph_file(NODES.replace(f"count: {TICKS}", "count: 0"))  # ticks until stopped
    launcher = Proc("launch", str(graph))
    path = tmp_path / "killed.mcap"
    recorder = None
    try:
        assert wait_until(lambda: launcher.has("ready: 3 nodes up"), 60), launcher.output
        recorder = Proc("record", "--graph", str(graph), "-o", str(path), "--chunk-seconds", "0.5")
        assert wait_until(lambda: recorder.has("recording t/**"), 30), recorder.output
        time.sleep(2.5)
        recorder.stop(signal.SIGKILL)
    finally:
        if recorder is not None and recorder.popen.poll() is None:
            recorder.stop(signal.SIGKILL)
        launcher.stop()
    with open(path, "rb") as f, pytest.raises(Exception):  # noqa: B017 (any failure: there is no footer)
        make_reader(f).get_summary()
    fixed = tmp_path / "fixed.mcap"
    result = run_followbus("recover", str(path), "-o", str(fixed))
    assert result.returncode == 0, result.stdout + result.stderr
    topics = read_all(fixed)
    ticks = sorted(decode(m.data, Tick).value for _c, m in topics.get("t/ticker/tick", []))
    assert len(ticks) > 0, result.stdout
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks)))  # complete chunks: no hole in the middle
    assert all(decode(m.data).header.stamp_ns == m.log_time for msgs in topics.values() for c, m in msgs
               if is_bus_channel(c))  # the bus channels (views: tests/test_record_views.py)
    assert read_metadata(fixed)["followbus"]["namespace"] == "t"
    assert f"recovered {sum(len(v) for v in topics.values())} messages" in result.stdout


# --- the independent reader ------------------------------------------------------------------------

JS_DIR = Path(__file__).parent / "js"


@pytest.fixture(scope="module")
def mcap_checker() -> list[str]:
    """node + the official npm packages, installed (npm ci, lockfile-pinned) into a cache directory."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if not node or not npm:
        pytest.skip("node/npm not installed: the independent MCAP/Foxglove reader (tests/js) cannot run")
    lock = (JS_DIR / "package-lock.json").read_bytes() + (JS_DIR / "package.json").read_bytes()
    cache_root = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "followbus"
    cache = cache_root / f"js-{hashlib.sha256(lock).hexdigest()[:16]}"
    if not (cache / "node_modules" / ".installed").exists():
        cache.mkdir(parents=True, exist_ok=True)
        for name in ("package.json", "package-lock.json"):
            shutil.copy(JS_DIR / name, cache / name)
        result = subprocess.run([npm, "ci", "--ignore-scripts", "--no-audit", "--no-fund"], cwd=cache,
                                capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL)
        if result.returncode != 0:
            pytest.skip(f"npm ci of tests/js failed (registry unreachable?): {result.stderr.strip()[-300:]}")
        (cache / "node_modules" / ".installed").touch()
    shutil.copy(JS_DIR / "check_mcap.mjs", cache / "check_mcap.mjs")  # resolves the packages next to it
    return [node, str(cache / "check_mcap.mjs")]


def run_checker(checker: list[str], path: Path) -> tuple[int, dict]:
    result = subprocess.run([*checker, str(path)], capture_output=True, text=True, timeout=120)
    try:
        return result.returncode, json.loads(result.stdout)
    except json.JSONDecodeError:
        pytest.fail(f"checker output is not JSON: {result.stdout[-500:]} {result.stderr[-2000:]}")


def test_foxglove_channels_match_the_official_schemas(recorded: Recorded, mcap_checker):
    code, summary = run_checker(mcap_checker, recorded.path)
    assert code == 0 and not summary["errors"], summary["errors"]
    channels = summary["channels"]
    # frames are ROS 2 sensor_msgs/CompressedImage (decoded in tests/test_record_views.py)
    assert channels["t/capture/frame/image"]["schema"] == "sensor_msgs/msg/CompressedImage"
    assert channels["t/capture/frame/image"]["count"] == VIEW_FRAMES
    for key in ("t/detection/detections", "t/prediction/prior", "t/prediction/track"):
        assert channels[f"{key}/annotations"]["schema"] == "foxglove.ImageAnnotations", key
        assert channels[f"{key}/annotations"]["count"] == VIEW_FRAMES, key
    assert channels["t/detection/detections/annotations"]["boxes"] == 2 * VIEW_FRAMES
    # prior: the gate ellipse + the predicted box, from the second frame on (the first is not initialised)
    assert channels["t/prediction/prior/annotations"]["boxes"] == 2 * (VIEW_FRAMES - 1)
    assert channels["t/ticker/tick"]["count"] == TICKS  # the reader sees the bus channels too


def test_checker_rejects_a_channel_that_breaks_its_schema(mcap_checker, tmp_path):
    """The negative control: the same reader must fail on Foxglove messages that do not fit their schema."""
    path = tmp_path / "bad.mcap"
    writer = RecordingWriter(path)
    image = writer.foxglove_channel("t/capture/frame/image", fox.COMPRESSED_IMAGE, "t/capture/frame")
    good = json.loads(fox.compressed_image(1_000_000_000, "t/capture/frame", b"\xff\xd8jpeg\xff\xd9"))
    del good["frame_id"]
    writer.write(image, 1_000_000_000, json.dumps(good).encode())
    boxes = writer.foxglove_channel("t/detection/detections/annotations", fox.IMAGE_ANNOTATIONS, "t/d")
    ann = json.loads(fox.detections_annotations(Detections(boxes=np.array([[1.0, 2.0, 3.0, 4.0, 0.5]]))))
    ann["points"][0]["type"] = "LINE_LOOP"  # the schema wants the enum's integer
    writer.write(boxes, 1_000_000_000, json.dumps(ann).encode())
    writer.finish()
    code, summary = run_checker(mcap_checker, path)
    assert code == 1
    assert any("t/capture/frame/image" in e and "frame_id" in e for e in summary["errors"]), summary["errors"]
    assert any("annotations" in e and "type" in e for e in summary["errors"]), summary["errors"]


def test_frames_whose_inputs_the_recorder_missed_are_not_verifiable_not_missing(recorded: Recorded, tmp_path):
    """A recorder that joined late (or dropped some inputs) leaves frames the node cannot be replayed on: their
    recorded outputs are counted as not verifiable, apart from outputs the node failed to produce."""
    lacking = tmp_path / "lacking.mcap"
    dropped: list[int] = []

    def keep(channel, message) -> bool:
        if channel.topic.endswith("/ticker/tick") and len(dropped) < 3:
            dropped.append(message.sequence)
            return False
        return True

    copy_recording(recorded.path, lacking, keep=keep, library="test: the recorder missed the first ticks")
    report_path = tmp_path / "replay.json"
    result = run_followbus("replay", str(lacking), "--node", "relay", "--verify", "--report", str(report_path),
                           timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(report_path.read_text())
    assert report["unverifiable"] == 3 and not report["missing"] and report["mismatch_count"] == 0
    assert report["outputs_compared"] == TICKS - 3 == report["matched"]
    assert "not verifiable: 3 recorded outputs" in result.stdout
