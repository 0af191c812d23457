"""Real processes, real Zenoh on loopback: every schema round-trips between two processes, and a
node counts and drops malformed bytes while it keeps working."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from followbus import msgs
from followbus.bus import schemas
from followbus.bus.pubsub import Publisher, Subscriber, payload_bytes
from followbus.bus.schemas import NodeStatus, Tick, decode
from followbus.bus.session import ZenohSettings, open_session

from .conftest import followbus_argv, wait_until

pytestmark = pytest.mark.slow

ECHO_SERVER = """
import sys, time
from followbus.bus.schemas import decode
import followbus.msgs  # the application's message types: decodable here too
from followbus.bus.session import ZenohSettings, open_session
port = int(sys.argv[1])
s = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
pubs = {}
def on(sample):
    from followbus.bus.pubsub import payload_bytes
    msg = decode(payload_bytes(sample))          # decode in this process...
    key = "rt/out/" + msg.TYPE
    if key not in pubs:
        pubs[key] = s.declare_publisher(key)
    pubs[key].put(msg.encode())                  # ...and re-encode what was understood
sub = s.declare_subscriber("rt/in/*", on)
print("ready", flush=True)
time.sleep(60)
"""


def _sample_messages() -> list[schemas.Message]:
    rng = np.random.default_rng(1)
    box = np.array([10.5, 20.0, 30.0, 60.0])
    return [
        schemas.Frame(width=64, height=48, encoding="bgr8", data=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                      source_width=128, source_height=96),
        msgs.GroundTruth(available=True, box=box, visible_fraction=0.4, others=np.ones((2, 4), np.float32)),
        msgs.Detections(boxes=rng.random((3, 5)).astype(np.float32), backend="yolox", infer_ms=12.5),
        msgs.Prior(initialised=True, state=np.arange(4.0), size=np.array([30.0, 60.0]), covariance=np.eye(4) * 2,
                      innovation_cov=np.eye(2) * 3, gate_chi2=9.488, box=box),
        msgs.Measurement(state="REACQUIRED", accepted=True, secure=True, box=box, m_fuse=0.8, s_color=0.9,
                            s_geo=0.7, omega=0.6, c_t=0.9, candidates=np.ones((2, 5), np.float32),
                            candidate_hist=np.full((16, 8), 1 / 128, np.float32)),
        msgs.Track(state="TRACKING", box=box, velocity=np.array([1.0, -2.0]), measured=True),
        msgs.Template(initialised=True, hist=np.full((16, 8), 1 / 128, np.float32), eta=0.019, p_specular=0.05),
        msgs.MotorCommand(vx_mps=0.4, vy_mps=0.0, wz_radps=-0.2, wheel_radps=np.array([1.0, 2, 3, 4]),
                             range_m=2.1, bearing_rad=None, reason="follow"),
        msgs.Odometry(x_m=1.0, y_m=2.0, theta_rad=0.3, vx_mps=0.4, vy_mps=0.1, wz_radps=0.05),
        schemas.NodeStatus(node="n", pid=42, uptime_s=3.5, topics={"k": {"rate_hz": 30.0}}, extra={"a": 1}),
        schemas.Tick(value=7, payload=np.arange(5000, dtype=np.uint8)),
        schemas.ReplayHint(skip=False, feedback={"template": 8}),
        msgs.GroundPoints(points_robot_m=rng.random((3, 2)), points_m=rng.random((3, 2)),
                             covs_m2=np.stack([np.eye(2) * 0.1] * 3), scores=np.full(3, 0.8), robot_x_m=0.5,
                             robot_theta_rad=0.1, odometry_stamp_ns=120),
        msgs.GroupState(valid=True, centre_m=np.array([4.0, 0.5]), velocity_mps=np.array([0.4, 0.0]),
                           orientation_rad=0.2, centre_robot_m=np.array([3.5, 0.4]),
                           ellipse_centres_m=rng.random((2, 2)), ellipse_extents_m2=np.stack([np.eye(2)] * 2),
                           ellipse_weights=np.array([0.6, 0.4]), members_m=rng.random((4, 2)),
                           others_m=rng.random((1, 2)), step_ms=1.5),
        msgs.CameraMotion(valid=True, matrix=np.array([[1.01, 0.02, -3.5], [-0.02, 1.01, 1.25]]), inliers=40,
                             tracked=55, from_stamp_ns=90, reason=""),
        msgs.RegionDetections(reason="small", region=np.array([10, 20, 138, 148], np.int64),
                              boxes=np.array([[20, 30, 40, 90, 0.9]], np.float32), input_px=128, infer_ms=2.5),
    ]


def _assert_same(a, b) -> None:
    assert type(a) is type(b)
    for field in a.__dataclass_fields__:
        va, vb = getattr(a, field), getattr(b, field)
        if isinstance(va, np.ndarray):
            assert isinstance(vb, np.ndarray) and va.dtype == vb.dtype and np.array_equal(va, vb), field
        else:
            assert va == vb, field


def test_every_schema_round_trips_between_two_processes(port):
    messages = _sample_messages()
    assert {m.TYPE for m in messages} == set(schemas.SCHEMAS), "add new schemas to this test"
    session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    received: dict[str, schemas.Message] = {}
    lock = threading.Lock()

    def on_back(msg):
        with lock:
            received[msg.TYPE] = msg

    back = Subscriber(session, "rt/out/*", on_back)
    server = subprocess.Popen([sys.executable, "-c", ECHO_SERVER, str(port)], stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().strip() == "ready"
        pubs = {m.TYPE: Publisher(session, f"rt/in/{m.TYPE}", "test") for m in messages}
        for _ in range(50):  # resend until the peer's subscription has propagated
            with lock:
                missing = [m for m in messages if m.TYPE not in received]
            if not missing:
                break
            for m in missing:
                m.header.stamp_ns = 123
                m.header.frame_seq = 9
                pubs[m.TYPE].put(m)
            time.sleep(0.2)
        for m in messages:
            assert m.TYPE in received, f"{m.TYPE} never came back"
            _assert_same(m, received[m.TYPE])
    finally:
        back.undeclare()
        server.kill()
        server.wait()
        session.close()


def test_node_counts_and_drops_malformed_messages_and_keeps_running(graph_file, port):
    graph = graph_file(
        "  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n"
        "  sink:\n    run: followbus.nodes.diagnostics_sink\n    inputs: {tick: ticker/tick}\n"
    )
    session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    statuses: list[NodeStatus] = []
    status_sub = session.declare_subscriber(
        "t/@status/sink", lambda s: statuses.append(decode(payload_bytes(s), NodeStatus)))
    node = subprocess.Popen(followbus_argv("node", "sink", "--graph", str(graph)), stdin=subprocess.DEVNULL)
    try:
        assert wait_until(lambda: bool(statuses), 20), "sink never published its status"
        raw = session.declare_publisher("t/ticker/tick")
        good = Publisher(session, "t/ticker/tick", "ticker")
        for junk in (b"\x00\x01garbage", b"FB1\x05\x00\x00\x00\xc1\xc1", msgs.Odometry().encode()):
            raw.put(junk)
        tick = Tick(value=41)
        tick.header.stamp_ns = time.time_ns()
        good.put(tick)

        def counted() -> bool:
            st = statuses[-1]
            topic = st.topics.get("t/ticker/tick", {})
            return topic.get("decode_errors") == 3 and st.extra.get("received") == 1

        assert wait_until(counted, 10), statuses[-1]
        assert statuses[-1].extra["last_value"] == 41
        assert node.poll() is None, "the node died on malformed input"
    finally:
        status_sub.undeclare()
        node.terminate()
        node.wait(10)
        session.close()
    assert node.returncode == 0


def test_a_node_publishing_frames_creates_its_shared_memory_pool_before_its_first_frame(graph_file):
    """Creating the pool takes ~50 ms; done on the first frame, it delayed frame 0 so that frame 1 followed
    right behind it and the detection node's one-frame queue dropped frame 0 (seen in recordings)."""
    from followbus.bus.graph import load_graph
    from followbus.bus.node_runtime import NodeRuntime

    graph = load_graph(graph_file(
        "  capture:\n    run: followbus.nodes.capture\n    outputs: [frame, ground_truth]\n"
        "    params: {source: 'scene:wall-occlusion'}\n"
        "  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n"))
    for name, warmed in (("capture", True), ("ticker", False)):
        runtime = NodeRuntime(graph, name)
        try:
            pools = {p.shm for p in runtime.publishers.values()}
            assert len(pools) == 1 and None not in pools, "shared memory is on in this graph"
            assert (pools.pop()._provider is not None) is warmed, name
        finally:
            runtime.session.close()  # never set up: nothing else to tear down


def test_frames_written_into_shared_memory_in_place_arrive_as_encode_writes_them(port):
    """Publisher.put writes a large message's head and arrays straight into its shared-memory buffer: the
    receiver gets exactly the bytes of encode() (the one wire format), whatever backs the arrays."""
    from followbus.bus.pubsub import ShmPool, _byte_source
    from followbus.bus.schemas import encode

    camera = bytearray(np.random.default_rng(3).integers(0, 255, 720 * 1280 * 3, dtype=np.uint8).tobytes())
    image = np.frombuffer(camera, np.uint8).reshape(720, 1280, 3)
    assert _byte_source(image) is camera  # a buffer the camera filled: copied once, from the bytearray itself
    assert isinstance(_byte_source(image[:360]), bytes)  # part of a buffer: its own bytes
    assert isinstance(_byte_source(np.ascontiguousarray(image[:, :, ::-1])), bytes)
    frames = [
        schemas.Frame(width=1280, height=720, encoding="bgr8", data=image),
        schemas.Frame(width=640, height=480, encoding="bgr8", data=image[::2, ::2]),  # a strided view
        schemas.Frame(width=1280, height=720, encoding="bgr8", data=image[:, :, ::-1].copy()),
        schemas.Tick(value=1, payload=np.arange(200_000, dtype=np.uint8)),  # several blobs' worth of head
    ]
    sender = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    receiver = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    got: dict[int, bytes] = {}
    shm_seen: list[bool] = []

    def on(sample) -> None:
        shm_seen.append(sample.payload.as_shm() is not None)
        data = payload_bytes(sample)
        got[decode(data).header.seq] = data

    from followbus.bus.pubsub import direct_callback

    sub = receiver.declare_subscriber("shm/in", direct_callback(on))
    pub = Publisher(sender, "shm/in", "test", shm=ShmPool())
    try:
        sent: dict[int, bytes] = {}
        for _ in range(50):  # resend until the subscription has propagated
            for i, msg in enumerate(frames):
                msg.header.frame_seq = i
                pub.put(msg)
                sent[msg.header.seq] = encode(msg)  # the same header: put has just filled seq, source, pub_ns
            if wait_until(lambda: {decode(d).header.frame_seq for d in list(got.values())} == set(range(len(frames))),
                          0.5):
                break
        assert {decode(d).header.frame_seq for d in list(got.values())} == set(range(len(frames)))
        for seq, data in list(got.items()):  # a snapshot: resent copies may still be arriving on zenoh's thread
            assert data == sent[seq], f"message {seq} differs from encode()"
        assert all(shm_seen), "large payloads should have travelled through shared memory"
    finally:
        sub.undeclare()
        pub.undeclare()
        receiver.close()
        sender.close()


def test_a_node_whose_setup_fails_is_never_seen_alive(graph_file, port):
    """A node announces itself (its liveliness token) only once set up. Before, the token came first: a simulated
    detector wired without its ground_truth input exited in setup, yet capture's start-up barrier saw it alive for
    a moment in 1 run of 4 and published frame 0 to nobody (test_webview waited 90 s for a source that had not
    started). The healthy ticker beside it shows the tokens are seen."""
    from followbus.bus.pubsub import direct_callback

    graph = graph_file(
        "  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n"
        "  capture:\n    run: followbus.nodes.capture\n    outputs: [frame, ground_truth]\n"
        "    params: {source: 'scene:wall-occlusion', max_frames: 1}\n"
        "  detection:\n    run: followbus.nodes.detection\n    inputs: {frame: capture/frame}\n"
        "    outputs: [detections]\n    params: {backend: simulated}\n"
    )
    session = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    seen: list[tuple[str, str]] = []
    sub = session.liveliness().declare_subscriber(
        "t/@health/*", direct_callback(lambda s: seen.append((str(s.key_expr), str(s.kind)))), history=True)
    procs = [subprocess.Popen(followbus_argv("node", name, "--graph", str(graph)), stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for name in ("detection", "ticker")]
    detection, ticker = procs
    try:
        assert detection.wait(60) == 1, detection.stderr.read()
        assert "needs the ground_truth input wired" in detection.stderr.read()
        assert wait_until(lambda: any(key == "t/@health/ticker" for key, _ in seen), 30), seen
        assert not any(key == "t/@health/detection" for key, _ in seen), seen
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(10)
        sub.undeclare()
        session.close()
    assert ticker.returncode == 0


def test_a_publisher_sends_to_subscribers_that_come_and_go_without_asking_zenoh_on_each_put(port):
    """Publisher.put reads the matching status its listener keeps (asking Zenoh on every put cost motor a third
    of its CPU): a subscriber that appears after the publisher gets the messages, one that left gets none, and a
    publisher declared after its subscriber knows of it at once."""
    sender = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    receiver = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    got: list[int] = []
    pub = Publisher(sender, "match/odo", "test")
    try:
        assert not pub.listened  # nobody listens yet: nothing is sent (capture makes no preview)
        sub = Subscriber(receiver, "match/odo", lambda m: got.append(m.value), schema=Tick)
        assert wait_until(lambda: pub.listened, 5)
        pub.put(Tick(value=1))
        assert wait_until(lambda: got == [1], 5)
        late = Publisher(sender, "match/odo", "test")  # declared after the subscriber: matched from the start
        assert late.listened
        late.undeclare()
        sub.undeclare()
        assert wait_until(lambda: not pub.listened, 5)
        pub.put(Tick(value=2))
        time.sleep(0.2)
        assert got == [1]
    finally:
        pub.undeclare()
        receiver.close()
        sender.close()


def test_a_lazy_input_queue_does_not_wake_its_consumer_until_half_full():
    """A node's inputs read by stamp (prediction's 100 Hz odometry) do not wake its loop on every message; the queue
    still wakes it before it can overflow, and an ordinary queue wakes it on each message."""
    from followbus.bus.pubsub import InputQueue
    from followbus.bus.stats import TopicStats

    class CountingCondition(threading.Condition):
        notified = 0

        def notify_all(self) -> None:
            self.notified += 1
            super().notify_all()

    cond = CountingCondition()
    lazy = InputQueue("odometry", 8, "drop_oldest", TopicStats("k", "in"), cond, wakes=False)
    for value in range(3):
        lazy.push(Tick(value=value))
    assert cond.notified == 0
    lazy.push(Tick(value=3))  # half full: wake the consumer now
    assert cond.notified == 1
    with cond:
        assert [m.value for m in lazy.pop_all()] == [0, 1, 2, 3]
    eager = InputQueue("frame", 8, "drop_oldest", TopicStats("k", "in"), cond)
    eager.push(Tick(value=0))
    assert cond.notified == 2


def test_a_node_does_not_subscribe_to_an_input_its_params_never_read(graph_file):
    """Detection reads capture's ground truth only with the simulated backend: with a real detector its runtime
    does not subscribe to it, so capture sends nothing there (its publisher is not listened to)."""
    from followbus.bus.graph import load_graph
    from followbus.bus.node_runtime import NodeRuntime

    nodes = ("  capture:\n    run: followbus.nodes.capture\n    outputs: [frame, ground_truth]\n"
             "    params: {source: 'scene:wall-occlusion'}\n"
             "  detection:\n    run: followbus.nodes.detection\n    outputs: [detections]\n"
             "    inputs: {frame: capture/frame, ground_truth: {from: capture/ground_truth, optional: true}}\n"
             "    params: {backend: %s}\n")
    for backend, subscribed in (("hog", {"frame"}), ("simulated", {"frame", "ground_truth"})):
        runtime = NodeRuntime(load_graph(graph_file(nodes % backend, name=f"{backend}.yaml")), "detection")
        try:
            assert set(runtime.queues) == subscribed, backend
            assert len(runtime.subscribers) == len(subscribed)
        finally:
            runtime.session.close()  # never set up: nothing else to tear down
