"""Live monitoring against a router-mode robot graph on loopback (graph.robot.yaml with a private port):
the monitor sees every node and its rates, the monitor identity cannot publish, the web view streams
previews and state, and the monitor reconnects after the robot graph restarts."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from followbus.bus.schemas import NodeStatus
from followbus.bus.session import ZenohSettings, open_session
from followbus.bus.stats import TopicStats
from followbus.msgs.robot import MotorCommand
from followbus.msgs.tracking import Track
from followbus.tools.live.monitor import SEPARATOR, graph_info, show
from followbus.viewing.monitor import BusMonitor, GraphInfo

from .chromium import docs_picture, element_text, page_layout, render_dom, require_chromium, screenshot
from .conftest import REPO, followbus_argv, free_port, wait_until

pytestmark = pytest.mark.slow

USERS = "robot:robot-secret\nmonitor:monitor-secret\noperator:operator-secret\n"
DIAG_NODES = """\
  ticker: {run: followbus.nodes.diagnostics, outputs: [tick], params: {rate_hz: 50}}
  relay: {run: followbus.nodes.diagnostics_relay, inputs: {tick: ticker/tick}, outputs: [tick]}
  sink: {run: followbus.nodes.diagnostics_sink, inputs: {tick: relay/tick}}
"""


def robot_graph(tmp: Path, port: int, nodes: str | None = None) -> Path:
    """graph.robot.yaml on a private port, with its own user dictionary (optionally other nodes), beside a
    private copy of the graph.yaml it extends."""
    users = tmp / "users.txt"
    users.write_text(USERS)
    texts = {name: (REPO / name).read_text() for name in ("graph.yaml", "graph.robot.yaml")}
    for old, new in (("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}"), ("namespace: fb", "namespace: t"),
                     ("docs/zenoh-users.example.txt", str(users)), ("change-me-robot", "robot-secret")):
        assert any(old in text for text in texts.values()), old
        texts = {name: text.replace(old, new) for name, text in texts.items()}
    assert "extends: graph.yaml" in texts["graph.robot.yaml"]
    if nodes is not None:
        base = texts["graph.yaml"]
        texts["graph.yaml"] = base[:base.index("\nnodes:\n")] + "\nnodes:\n" + nodes
    for name, text in texts.items():
        (tmp / name).write_text(text)
    return tmp / "graph.robot.yaml"


class Launch:
    """`followbus launch` as a child process with its output collected."""

    def __init__(self, graph: Path, *extra: str):
        self.proc = subprocess.Popen(followbus_argv("launch", str(graph), *extra), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL, cwd=REPO)
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")), daemon=True).start()

    def wait_ready(self, timeout: float = 60) -> None:
        assert wait_until(lambda: any("ready:" in line for line in self.lines), timeout), "".join(self.lines[-30:])

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def client(port: int, user: str, password: str) -> ZenohSettings:
    return ZenohSettings(mode="client", listen=[], connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_ms=5000,
                         config={"transport/auth/usrpwd": {"user": user, "password": password}})


@pytest.fixture(scope="module")
def tracking_robot(tmp_path_factory):
    """The real tracking graph (simulated detector, synthetic scene) in router mode with access control."""
    tmp = tmp_path_factory.mktemp("robot")
    port = free_port()
    graph = robot_graph(tmp, port)
    launch = Launch(graph, "--set", "capture.source=scene:wall-occlusion", "--set", "capture.loop=true",
                    "--set", "detection.backend=simulated",
                    "--set", f"template.state_file={tmp / 'template.npz'}")
    try:
        launch.wait_ready()
        yield graph, port, launch
    finally:
        launch.stop()


def test_monitor_once_sees_every_node_and_rates(tracking_robot):
    graph, port, launch = tracking_robot
    # `--once` prints each node's first status: right after "ready" (this module's first test) capture's may cover
    # its first frame alone (0.0 Hz: a rate needs two frames in the 5 s window; seen once on a loaded machine).
    # Here the rate is the point, not the start-up: the graph first runs 5 s of frames.
    _wait_for_frames(port, 150)
    result = subprocess.run(followbus_argv("monitor", "--graph", str(graph), "--user", "monitor", "--password",
                                           "monitor-secret", "--once", "--seconds", "15"),
                            capture_output=True, text=True, timeout=40, cwd=REPO)
    out = result.stdout
    assert result.returncode == 0, out + result.stderr[-2000:] + "".join(launch.lines[-20:])
    assert "connected" in out.splitlines()[0]
    # A pipe gets plain text: no escape sequences, no trailing blanks, one row per line.
    assert "\x1b" not in out and all(line == line.rstrip() for line in out.splitlines()), repr(out[:500])
    for node in ("capture", "detection", "prediction", "reid", "template", "motor"):
        row = next((line for line in out.splitlines() if line.startswith(f"{node} ")), "")
        assert row.split()[1:2] == ["up"], out
    # The capture node publishes frames at the scene's rate (~30 Hz): the monitor shows it from NodeStatus.
    frame_row = next(line for line in out.splitlines() if line.startswith("t/capture/frame @capture"))
    assert float(frame_row.split()[3]) > 10.0, frame_row
    assert "t/motor/command @motor" in out


def _wait_for_frames(port: int, count: int) -> None:
    """Until ``count`` frames' ground truth (one small message per frame) went by, as the monitor identity sees."""
    from followbus.bus.pubsub import Subscriber
    from followbus.msgs.perception import GroundTruth

    seen: list[int] = []
    session = open_session(client(port, "monitor", "monitor-secret"))
    sub = Subscriber(session, "t/capture/ground_truth", lambda m: seen.append(m.header.frame_seq), schema=GroundTruth)
    try:
        assert wait_until(lambda: len(seen) >= count, timeout=60), f"{len(seen)} frames in 60 s"
    finally:
        sub.undeclare()
        session.close()


def test_monitor_identity_cannot_publish_commands(tracking_robot):
    _graph, port, _launch = tracking_robot
    robot = open_session(client(port, "robot", "robot-secret"))
    received: list[bytes] = []
    sub = robot.declare_subscriber("t/test/**", lambda s: received.append(bytes(s.payload.to_bytes())))
    monitor = open_session(client(port, "monitor", "monitor-secret"))
    operator = open_session(client(port, "operator", "operator-secret"))
    try:
        time.sleep(0.5)  # let the subscription propagate to the router
        for _ in range(10):
            monitor.put("t/test/motor/command", b"from-monitor")
            operator.put("t/test/motor/command", b"from-operator")
            monitor.put("t/test/template/params", b"from-monitor")
            time.sleep(0.05)
        assert wait_until(lambda: received.count(b"from-operator") == 10, 5), received
        time.sleep(0.5)
        assert b"from-monitor" not in received
    finally:
        for s in (monitor, operator, robot):
            s.close()
        del sub
    # Wrong password: the router refuses the session outright.
    bad = client(port, "monitor", "wrong")
    bad.connect_timeout_ms = 1500
    with pytest.raises(Exception):  # noqa: B017 (zenoh raises a generic ZError)
        open_session(bad).close()


def _get(url: str) -> tuple[int, bytes, dict[str, str]]:
    with urllib.request.urlopen(url, timeout=5) as r:
        return r.status, r.read(), dict(r.headers)


def test_web_view_streams_previews_and_state(tracking_robot, tmp_path):
    graph, port, _launch = tracking_robot
    web_port = free_port()
    proc = subprocess.Popen(followbus_argv("monitor", "--graph", str(graph), "--user", "monitor", "--password",
                                           "monitor-secret", "--web", str(web_port)),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    base = f"http://127.0.0.1:{web_port}"
    try:
        def state() -> dict:
            try:
                return json.loads(_get(base + "/state.json")[1])
            except OSError:
                return {}

        assert wait_until(lambda: state().get("target", {}).get("frame_seq", -1) >= 0, 30), state()
        status, html, _ = _get(base + "/")
        assert status == 200 and b'id="state"' in html and b"/preview.jpg" in html
        s1 = state()
        status, jpeg1, h1 = _get(base + "/preview.jpg?after=-1&client=t")
        assert status == 200 and jpeg1[:2] == b"\xff\xd8", h1
        status, jpeg2, h2 = _get(base + f"/preview.jpg?after={h1['X-Preview-Count']}&client=t")
        assert h2["X-Frame-Seq"] != h1["X-Frame-Seq"]
        assert wait_until(lambda: state().get("target", {}).get("frame_seq", -1) != s1["target"]["frame_seq"], 5)

        def all_alive() -> bool:
            nodes = state().get("nodes") or []
            return bool(nodes) and all(n["alive"] for n in nodes)

        assert wait_until(all_alive, 10), (state().get("nodes"), "".join(_launch.lines[-30:]))
        assert wait_until(lambda: bool(state().get("history", {}).get("latency_ms")), 5), "no latency samples"

        # The page in a real browser at laptop size (in CI always: .ci/run installs Chromium).
        require_chromium()

        def frames_drawn(dom: str) -> int:
            return int(dom.split('id="frames">frames: ')[1].split(" ")[0].split("<")[0])

        def frame_shown(dom: str) -> str | None:
            """The frame the state text names (None: a render caught before the first state poll)."""
            state = dom.split('id="state">target ')
            return state[1].split(" frame ")[1].split(" ")[0] if len(state) > 1 and " frame " in state[1][:200] \
                else None

        # Virtual-time budgets are not wall time: on a loaded 2-core machine a render may catch fewer
        # frames (or none yet), so take up to four renders before judging.
        doms: list[str] = []
        for _ in range(4):
            doms.append(render_dom(base + "/", tmp_path, budget_ms=5000, window="1280,900"))
            shown = {frame_shown(d) for d in doms} - {None}
            if frames_drawn(doms[-1]) >= 3 and frame_shown(doms[-1]) and len(shown) >= 2:
                break
        dom = doms[-1]
        assert frames_drawn(dom) >= 3, dom[:2000]
        assert "target " in dom.split('id="state">')[1][:200]
        assert len(shown) >= 2, f"state text did not update: {shown}"
        code, text = element_text(dom, "screen")
        assert code == "live" and text.startswith("live: frame "), (code, text)
        assert element_text(dom, "banner")[0] == "live"  # hidden while live
        # Two columns at 1280 px: the state text and the health table beside the video, not below it.
        layout = page_layout(dom)
        assert layout["width"] == 1280, layout
        video, health, state_box = layout["video"], layout["health"], layout["state"]
        assert health["left"] >= video["right"] and state_box["left"] >= video["right"], layout
        assert health["top"] < video["bottom"] and health["bottom"] <= 900, layout
        # Labelled columns, and a row per topic (detection's frame input has its own rate, latency and drops).
        head = dom.split('<table id="nodes">')[1].split("</thead>")[0]
        labels = [re.sub(r"<[^>]+>", "", cell) for cell in re.findall(r"<th[^>]*>(.*?)</th>", head)]
        assert labels == ["node", "state", "restarts", "topic", "rate Hz", "p50 latency ms", "drops", "lost",
                          "decode errors"], labels
        row = re.search(r'<tr[^>]*data-node="detection"[^>]*>(?:(?!</tr>).)*<span class="dir">in</span> '
                        r"capture/frame</td><td>([\d.]+)</td><td>([\d.]+)</td><td>(\d+)</td><td>(\d+)</td><td>(\d+)</td>",
                        dom)
        assert row and float(row.group(1)) > 10.0, dom.split('<table id="nodes">')[1][:3000]
        assert element_text(dom, "srcw")[1] == "source width 640 px"
        # The README's picture of the page (docs/webview.png with FOLLOWBUS_UPDATE_PICTURES=1).
        assert screenshot(base + "/", docs_picture("webview.png", tmp_path), tmp_path, budget_ms=5000) == (1280, 900)
        # One column on a narrow screen: the health table below the video.
        narrow = page_layout(render_dom(base + "/", tmp_path, budget_ms=1500, window="800,900"))
        assert narrow["health"]["top"] >= narrow["video"]["bottom"], narrow
    finally:
        _interrupt(proc)


def _interrupt(proc: subprocess.Popen) -> None:
    """Ctrl-C a tool and wait for it; kill it if it does not stop within 10 s."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


def test_monitor_reconnects_after_robot_restart(tmp_path):
    port = free_port()
    graph = robot_graph(tmp_path, port, DIAG_NODES)
    launch = Launch(graph)
    lines: list[str] = []
    monitor = subprocess.Popen(followbus_argv("monitor", "--graph", str(graph), "--user", "monitor", "--password",
                                              "monitor-secret", "--seconds", "60"),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    threading.Thread(target=lambda: lines.extend(iter(monitor.stdout.readline, "")), daemon=True).start()

    def screens() -> list[list[str]]:
        text = "".join(lines)
        return [s.strip().splitlines() for s in text.split(SEPARATOR) if s.strip()]

    def all_up_after(index: int) -> bool:
        for screen in screens()[index:]:
            rows = [r for r in screen if r.split()[:1] and r.split()[0] in ("ticker", "relay", "sink")]
            if len(rows) == 3 and all(r.split()[1] == "up" for r in rows) and "connected" in screen[0]:
                return True
        return False

    try:
        launch.wait_ready()
        assert wait_until(lambda: all_up_after(0), 15), "".join(lines[-40:])
        launch.stop()
        assert wait_until(lambda: any("robot unreachable since" in line for line in lines), 15), "".join(lines[-40:])
        mark = len(screens())
        assert monitor.poll() is None
        launch = Launch(graph)
        launch.wait_ready()
        assert wait_until(lambda: all_up_after(mark), 20), "".join(lines[-40:])
    finally:
        launch.stop()
        monitor.send_signal(signal.SIGINT)
        try:
            monitor.wait(10)
        except subprocess.TimeoutExpired:
            monitor.kill()


def _dashboard(terminal: bool) -> str:
    """The dashboard of a monitor that saw two nodes (one verified, one down and spoofed), a track, a command
    and bad payloads, as printed to a terminal or to a pipe."""
    import io

    from rich.console import Console

    monitor = BusMonitor(ZenohSettings(mode="client", listen=[], connect=["tcp/127.0.0.1:9"]),
                         GraphInfo(namespace="t", nodes=["capture", "detection"]))  # never started: no session
    monitor._set_connected(True)
    for name, alive in (("capture", True), ("detection", True), ("detection", False)):
        monitor._on_health(name, alive)
    frames = TopicStats("t/capture/frame", "out")
    now_ns = time.time_ns()
    for i in range(31):
        frames.record(now_ns - (31 - i) * 33_000_000 - 2_000_000, now_ns=now_ns - (31 - i) * 33_000_000)
    frames.drop(3)
    capture = monitor.nodes["capture"]
    capture.status = NodeStatus(node="capture", pid=4242, uptime_s=12.0, topics={frames.key: frames.snapshot(now_ns)},
                                extra={"handler_errors": 0})
    capture.status_ns, capture.pids, capture.trust = now_ns, [4242], "verified"
    monitor.nodes["detection"].trust = "spoofed?"
    monitor.nodes["detection"].trust_reason = "no such process in the launcher's table"
    track = Track(state="OCCLUDED", box=np.array([10.0, 20.0, 30.0, 90.0]), velocity=np.array([5.0, -2.0]))
    track.header.frame_seq = 77
    monitor._on_message("track", track)
    monitor._on_message("command", MotorCommand(vx_mps=0.25, wz_radps=-0.5, reason="follow"))
    monitor.decode_errors = 2
    out = io.StringIO()
    show(Console(file=out, force_terminal=terminal, width=120 if terminal else 200), monitor.snapshot())
    return out.getvalue()


def test_dashboard_shows_health_rates_target_and_command():
    text = _dashboard(terminal=False)
    assert "\x1b" not in text  # a pipe gets plain text
    lines = text.splitlines()
    assert lines[0].startswith("followbus monitor  tcp/127.0.0.1:9  ns=t") and lines[0].endswith("connected")
    rows = {line.split()[0]: line.split() for line in lines if line.split()[:1] in (["capture"], ["detection"])}
    assert rows["capture"][1:2] == ["up"] and rows["capture"][4] == "4242" and rows["capture"][-1] == "verified"
    assert rows["detection"][1] == "DOWN" and "spoofed? (no such process in the launcher's table)" in text
    topic = next(line for line in lines if line.startswith("t/capture/frame @capture")).split()
    assert topic[2] == "out" and 25 < float(topic[3]) < 35 and float(topic[4]) == pytest.approx(2.0, abs=0.1)
    assert topic[6:] == ["3", "0", "0"]  # drops, lost, decode errors
    assert re.search(r"^target +OCCLUDED  box \[10\.0, 20\.0, 30\.0, 90\.0\]  v \[5\.0, -2\.0\] px/s  frame 77",
                     text, re.M), text
    assert re.search(r"^motor +vx \+0\.25 m/s  vy \+0\.00 m/s  wz -0\.50 rad/s  \[follow\]", text, re.M), text
    assert re.search(r"^monitor +2 decode errors$", text, re.M), text


def test_dashboard_names_a_link_that_delivers_less_than_is_sent():
    """Frames a node never received are shown where the operator looks: the input's lost count in the topic table,
    and a line for the link that carries less than its publisher sends (here over a slow link to another host)."""
    import io

    from rich.console import Console

    monitor = BusMonitor(ZenohSettings(mode="client", listen=[], connect=["tcp/127.0.0.1:9"]),
                         GraphInfo(namespace="t", nodes=["capture", "detection"]))  # never started: no session
    monitor._set_connected(True)
    now_ns = time.time_ns()
    topics = {"capture": {"t/capture/frame": {"direction": "out", "rate_hz": 30.0, "count": 900}},
              "detection": {"t/capture/frame": {"direction": "in", "rate_hz": 2.4, "count": 72, "lost": 828}}}
    for name in ("capture", "detection"):
        monitor._on_health(name, True)
        node = monitor.nodes[name]
        node.status, node.status_ns = NodeStatus(node=name, pid=1, topics=topics[name]), now_ns
    snap = monitor.snapshot()
    assert snap["links"] == ["t/capture/frame capture -> detection: 2.4 of 30.0 Hz delivered, 828 lost"]
    out = io.StringIO()
    show(Console(file=out, force_terminal=False, width=200), snap)
    text = out.getvalue()
    assert re.search(r"^link +t/capture/frame capture -> detection: 2\.4 of 30\.0 Hz delivered, 828 lost$", text, re.M)
    row = next(line for line in text.splitlines() if line.startswith("t/capture/frame @detection")).split()
    assert row[6:] == ["0", "828", "0"]  # drops, lost, decode errors


def test_dashboard_on_a_terminal_is_coloured():
    text = _dashboard(terminal=True)
    plain = re.sub(r"\x1b\[[0-9;]*m", "", text)
    assert "\x1b[" in text and "spoofed? (no such process" in plain
    assert re.search(r"\x1b\[1;31mDOWN", text) and re.search(r"\x1b\[32mverified", text), text


class _WsClient:
    """Just enough RFC 6455 (client side) to talk to the Foxglove WebSocket server: no extra dependency."""

    def __init__(self, port: int, subprotocol: str = "foxglove.sdk.v1, foxglove.websocket.v1"):
        import base64
        import os
        import socket

        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {subprotocol}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head

    def _exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            assert chunk, "connection closed"
            out += chunk
        return out

    def recv(self) -> tuple[int, bytes]:
        b0, b1 = self._exact(2)
        n = b1 & 0x7F
        if n == 126:
            n = int.from_bytes(self._exact(2), "big")
        elif n == 127:
            n = int.from_bytes(self._exact(8), "big")
        return b0 & 0x0F, self._exact(n)

    def send_text(self, text: str) -> None:
        import os

        data, mask = text.encode(), os.urandom(4)
        n = len(data)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + n.to_bytes(2, "big"))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def close(self) -> None:
        self.sock.close()


def test_foxglove_bridge_serves_previews_and_annotations(tracking_robot):
    pytest.importorskip("foxglove", reason="foxglove-sdk not installed (pip install foxglove-sdk)")
    graph, _port, _launch = tracking_robot
    ws_port = free_port()
    proc = subprocess.Popen(followbus_argv("foxglove", "--graph", str(graph), "--user", "monitor", "--password",
                                           "monitor-secret", "--port", str(ws_port), "--seconds", "30"),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    try:
        # 30 s: beside the other test worker's graph the bridge's start (its imports, a Zenoh session) took over 15.
        assert wait_until(lambda: _port_open(ws_port), 30), proc.stdout.read() if proc.poll() is not None else ""
        ws = _WsClient(ws_port)
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not {"/t/preview", "/t/annotations"} <= set(channels):
            opcode, data = ws.recv()
            if opcode == 1:
                msg = json.loads(data)
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
        assert channels["/t/preview"]["schemaName"] == "foxglove.CompressedImage", channels
        assert channels["/t/annotations"]["schemaName"] == "foxglove.ImageAnnotations"
        ws.send_text(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": 1, "channelId": channels["/t/preview"]["id"]}]}))
        got = 0
        while time.monotonic() < deadline + 10 and got < 3:
            opcode, data = ws.recv()
            if opcode == 2 and data[0] == 1:  # binary MessageData: op 1, subscription id, log time, payload
                assert int.from_bytes(data[1:5], "little") == 1
                assert b"jpeg" in data[13:] and b"\xff\xd8" in data[13:]
                got += 1
        assert got == 3, "no preview messages through the Foxglove server"
        ws.close()
    finally:
        _interrupt(proc)


def _group_messages(seq: int, stamp_ns: int):
    """A group of three (two ellipses) seen from a robot at (1, 0) facing +y, and the points of the same frame."""
    from followbus.msgs.group import GroundPoints, GroupState

    points = GroundPoints(points_robot_m=np.array([[2.0, 0.5], [2.5, -0.5], [4.0, 1.0]]),
                          robot_x_m=1.0, robot_y_m=0.0, robot_theta_rad=np.pi / 2)
    group = GroupState(valid=True, centre_m=np.array([0.2, 2.5]), centre_robot_m=np.array([2.5, 0.8]),
                       ellipse_centres_m=np.array([[0.5, 2.0], [1.5, 2.5]]),
                       ellipse_extents_m2=np.array([np.diag([0.2, 0.1]), np.diag([0.1, 0.1])]),
                       ellipse_weights=np.array([0.6, 0.4]), members_m=np.array([[0.5, 2.0], [1.5, 2.5]]),
                       others_m=np.array([[0.0, 4.0]]))
    for msg in (points, group):
        msg.header.frame_seq, msg.header.stamp_ns = seq, stamp_ns
    return points, group


def test_group_scene_places_the_group_in_the_robot_frame():
    """seed 004's group in Foxglove's 3D panel: ellipses as floor loops, members green, disturbers red, all in
    base_link (x forward, y left), i.e. the odometry-frame state taken through the pose of the same frame."""
    pytest.importorskip("foxglove", reason="foxglove-sdk not installed")
    from followbus.tools.live.foxglove_bridge import ROBOT_FRAME, group_scene, group_shapes
    from followbus.viewing.snapshot import group_view

    points, group = _group_messages(7, 1_000_000_000)
    view = group_view(group, (points.robot_x_m, points.robot_y_m, points.robot_theta_rad), points)
    shapes = group_shapes(view)
    assert len(shapes["loops"]) == 2
    # odometry (0.5, 2.0) seen from (1, 0) facing +y: 2.0 m ahead, 0.5 m to the right
    np.testing.assert_allclose(np.mean(shapes["loops"][0], axis=0), (2.0, 0.5), atol=0.05)
    kinds = [s[3] for s in shapes["spheres"]]
    assert kinds.count("member") == 2 and kinds.count("other") == 1 and kinds.count("centre") == 1
    member = next(s for s in shapes["spheres"] if s[3] == "member")
    np.testing.assert_allclose(member[:2], (2.0, 0.5), atol=1e-6)
    unposed = group_shapes(group_view(group, None, points))
    assert not unposed["loops"] and [s[3] for s in unposed["spheres"]] == ["centre"]  # never a misplaced shape
    encoded = group_scene(view, 1_000_000_000).encode()
    assert ROBOT_FRAME.encode() in encoded and len(encoded) > 2 * 48 * 8  # two 48-point loops went in


def test_foxglove_bridge_serves_the_group_scene():
    """A group graph on the bus: the bridge advertises /<ns>/group/scene (foxglove.SceneUpdate) at its first
    GroupState and streams it; real Zenoh on loopback, the bridge's real WebSocket server."""
    pytest.importorskip("foxglove", reason="foxglove-sdk not installed")
    from followbus.bus.schemas import encode
    from followbus.tools.live.foxglove_bridge import FoxgloveBridge

    port, ws_port = free_port(), free_port()
    bridge = FoxgloveBridge(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]), graph_info(None, "t"),
                            port=ws_port)
    robot = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.is_set():
            for msg in _group_messages(seq, time.time_ns()):
                robot.put(f"t/{'groundplane/points' if msg.TYPE == 'GroundPoints' else 'group/group'}", encode(msg))
            seq += 1
            time.sleep(0.05)

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    try:
        ws = _WsClient(bridge.port)
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and "/t/group/scene" not in channels:
            opcode, data = ws.recv()
            if opcode == 1 and (msg := json.loads(data)).get("op") == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
        assert channels["/t/group/scene"]["schemaName"] == "foxglove.SceneUpdate", channels
        subscription = 0
        scene_id = None
        while time.monotonic() < deadline:
            if channels["/t/group/scene"]["id"] != scene_id:  # (re-)advertised: subscribe as a Foxglove client does
                scene_id, subscription = channels["/t/group/scene"]["id"], subscription + 1
                ws.send_text(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": subscription, "channelId": scene_id}]}))
            opcode, data = ws.recv()
            if opcode == 1 and (msg := json.loads(data)).get("op") == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
            elif opcode == 2 and data[0] == 1 and int.from_bytes(data[1:5], "little") == subscription:
                assert b"base_link" in data[13:]
                break
        else:
            raise AssertionError("no group scene through the Foxglove server")
        ws.close()
    finally:
        stop.set()
        publisher.join(5)
        robot.close()
        bridge.close()


def _port_open(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_first_preview_request_waits_for_the_first_preview():
    """A page opened before any preview arrived asks for "anything" (after=-1): it must get the first one
    when it comes, not an immediate empty answer (seen as a 204 when the track arrived before the preview)."""
    from http.server import ThreadingHTTPServer
    from types import SimpleNamespace

    from followbus.tools.live.webview import PreviewGate, make_handler

    monitor = SimpleNamespace(lock=threading.Lock(), preview_jpeg=b"", preview_count=0, preview=None)
    gate = PreviewGate()
    server = ThreadingHTTPServer(("127.0.0.1", 0), make_handler(monitor, gate))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        def arrive() -> None:
            time.sleep(0.3)
            with monitor.lock:
                monitor.preview_jpeg, monitor.preview_count = b"\xff\xd8jpeg", 1
                monitor.preview = SimpleNamespace(header=SimpleNamespace(frame_seq=7))
            gate.notify()

        threading.Thread(target=arrive, daemon=True).start()
        status, body, headers = _get(f"http://127.0.0.1:{server.server_port}/preview.jpg?after=-1&client=t")
        assert status == 200 and body == b"\xff\xd8jpeg" and headers["X-Frame-Seq"] == "7", (status, headers)
    finally:
        server.shutdown()
        server.server_close()


def _dashboard_snapshot(age_s: float) -> dict:
    now = time.time_ns()
    nodes = [{"name": n, "alive": False, "since_ns": now - 5_000_000_000, "restarts": 0, "pid": 12345,
              "uptime_s": 30.0, "handler_errors": 0, "trust": "verified", "trust_reason": "",
              "topics": {f"fb/{n}/out{i}": {"direction": "out", "rate_hz": 30.0} for i in range(3)}}
             for n in ("capture", "detection", "egomotion", "prediction", "reid", "template", "motor")]
    return {"connected": True, "endpoints": ["tcp/127.0.0.1:7447"], "namespace": "fb", "now_ns": now, "nodes": nodes,
            "decode_errors": 0, "centre_error_px": 3.2, "eta": 0.0123,
            "target": {"state": "TRACKING", "box": [123.4, 200.1, 80.2, 190.7], "frame_seq": 1234,
                       "velocity": [5.0, -2.0]},
            "command": {"vx_mps": 0.8, "vy_mps": 0.0, "wz_radps": -0.12, "reason": "tracking", "latency_ms": 45.2},
            "ages": {"track": age_s, "template": age_s, "command": age_s}, "stale_after_s": 2.0}


@pytest.mark.parametrize("age_s", [0.3, 12.0], ids=["fresh", "stale"])
def test_the_dashboard_fits_80x24_with_the_target_and_motor_aged(age_s):
    """Issue 23: on 80x24 the target and motor lines were cut off (and a taller dashboard cannot redraw in place);
    after the graph stopped they still read TRACKING / +0.80 m/s as if live."""
    from rich.console import Console

    from followbus.tools.live.monitor import render

    console = Console(width=80, height=24, record=True, force_terminal=True)
    console.print(render(_dashboard_snapshot(age_s), 24, 80))
    styled = console.export_text(styles=True, clear=False)
    lines = [line.rstrip() for line in console.export_text().splitlines()]
    assert len(lines) <= 24 and max(map(len, lines)) <= 80
    start = next(i for i, line in enumerate(lines) if line.startswith("target"))
    target = " ".join(lines[start:start + 2])  # the last column wraps on a narrow terminal
    motor = " ".join(lines[-2:])
    assert "TRACKING" in target and "vx +0.80" in motor
    assert any(line.endswith("more (followbus topics)") for line in lines)
    if age_s > 2:
        assert "STALE 12 s" in target and motor.rstrip().endswith("STALE 12 s")
        assert "\x1b[2;9" in styled  # dim and struck through on a terminal
    else:
        assert "STALE" not in "\n".join(lines) and "0.3 s" in target and motor.endswith("0.3 s")
