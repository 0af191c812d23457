"""The web view as an operator's screen: who may open it (token rule, real HTTP on loopback), what it says
(waiting / source ended / robot unreachable, labelled health rows), and the page in headless Chromium against
a real capture node; with the group graph (seed 004) running, the group's ellipses drawn top down and in the
video (docs/webview-group.png). The live two-column page and the README screenshot: tests/test_monitor.py."""

from __future__ import annotations

import html
import http.client
import json
import math
import re
import socket
import subprocess
import threading

import cv2
import numpy as np
import pytest

from followbus.msgs.group import GroundPoints, GroupState
from followbus.tools.live.monitor import _group_line, graph_info
from followbus.tools.live.webview import health_rows, is_loopback_bind, screen_state, web_token
from followbus.tracking.groundplane import floor_to_image, to_odometry_frame
from followbus.viewing.snapshot import group_view

from .chromium import docs_picture, element_text, have_chromium, page_layout, render_dom, require_chromium, screenshot
from .conftest import REPO, followbus_argv, free_port, wait_until
from .test_graph_group import _graph_copies
from .test_monitor import Launch, _interrupt, robot_graph

TOKEN = "s3cret-token-for-tests"
# Capture holds frame 0 back until its consumer (detection, which the graph puts on another host) is up: the test
# decides when frames start.
CAPTURE_AND_CONSUMER = """\
  capture:
    run: followbus.nodes.capture
    outputs: [frame, preview, ground_truth]
    params: {source: "scene:wall-occlusion", max_frames: 12, wait_for_consumers_s: 600}
  detection:
    run: followbus.nodes.detection
    host: gpu
    inputs: {frame: capture/frame, ground_truth: capture/ground_truth}
    outputs: [detections]
    params: {backend: simulated}
"""


@pytest.mark.parametrize(("bind", "loopback"), [
    ("127.0.0.1", True), ("127.3.2.1", True), ("localhost", True), ("LOCALHOST", True), ("::1", True),
    ("[::1]", True), ("0.0.0.0", False), ("::", False), ("", False), ("192.168.1.20", False),
    ("10.0.0.1", False), ("robot.local", False), ("localhost.example.org", False), ("::ffff:10.0.0.1", False),
])
def test_only_loopback_binds_count_as_local(bind, loopback):
    assert is_loopback_bind(bind) is loopback


def test_token_rule_depends_on_the_bind_address():
    assert web_token("127.0.0.1", None) == (None, False)  # loopback: open
    first, generated = web_token("0.0.0.0", None)
    assert generated and first and len(first) >= 16
    assert web_token("192.168.1.20", None)[0] != first  # a fresh one per run
    assert web_token("127.0.0.1", TOKEN) == (TOKEN, False)  # an explicit token applies on loopback too
    assert web_token("0.0.0.0", TOKEN) == (TOKEN, False)
    for bad in ("short", "has space-in-it", "semi;colon-token", "é" * 10):
        with pytest.raises(ValueError):
            web_token("127.0.0.1", bad)


def _snap(**kw) -> dict:
    base = {"connected": True, "unreachable_since_ns": None, "last_error": "", "namespace": "t", "nodes": [
        {"name": "capture", "alive": True, "restarts": 0, "pid": 11, "status_age_s": 0.4, "topics": {},
         "extra": {"done": False, "published": 0}}]}
    base.update(kw)
    return base


def test_screen_states():
    assert screen_state(_snap(), "capture") == {"code": "waiting", "text": "waiting for first frame"}
    elsewhere = {**_snap(), "nodes": [], "namespaces_hint": "no node under fb/@health; nodes are alive in: wf "
                 "(capture, motor) (pick one with --namespace)"}
    assert screen_state(elsewhere, "capture") == {"code": "waiting", "text": "waiting for first frame: no node under "
                                                  "fb/@health; nodes are alive in: wf (capture, motor) (pick one with "
                                                  "--namespace)"}
    preview = {"frame_seq": 41, "width": 320, "age_s": 0.1}
    assert screen_state(_snap(preview=preview), "capture") == {"code": "waiting", "text": "waiting for first frame"}
    live = _snap(preview=preview)
    live["nodes"][0]["extra"]["published"] = 42
    assert screen_state(live, "capture") == {"code": "live", "text": "live: frame 41"}
    assert screen_state({**live, "preview": {**preview, "age_s": 7.2}}, "capture") == {
        "code": "stalled", "text": "no new frame for 7 s (showing frame 41)"}
    ended = _snap(preview=preview)
    ended["nodes"][0]["extra"] = {"done": True, "published": 42}
    assert screen_state(ended, "capture") == {"code": "ended",
                                              "text": "source ended after 42 frames; last frame shown"}
    assert screen_state(ended, "camera")["code"] == "live"  # done only counts on the preview's source node
    never = _snap()
    never["nodes"][0]["extra"] = {"done": True, "published": 0}
    assert screen_state(never, "capture")["text"] == "source ended after 0 frames"
    lost = screen_state({**ended, "connected": False, "unreachable_since_ns": 1, "last_error": "refused"}, "capture")
    assert lost["code"] == "unreachable" and lost["text"].startswith("robot unreachable since ")
    assert lost["text"].endswith("(refused)")
    stale = _snap(preview=preview)
    stale["nodes"][0]["status_age_s"] = 12.0
    assert screen_state(stale, "capture") == {"code": "unreachable",
                                              "text": "robot unreachable: no node status for 12 s"}


def test_health_rows_are_labelled_one_per_topic():
    snap = _snap(nodes=[
        {"name": "detection", "alive": True, "restarts": 2, "pid": 7, "topics": {
            "t/capture/frame": {"direction": "in", "rate_hz": 29.5, "latency_p50_ms": 4.25, "drops": 3,
                                "lost": 5, "decode_errors": 1},
            "t/detection/detections": {"direction": "out", "rate_hz": 29.0, "latency_p50_ms": None, "drops": 0,
                                       "decode_errors": 0}}},
        {"name": "idle", "alive": False, "restarts": 0, "pid": None, "topics": {}}])
    rows = health_rows(snap)
    assert [(r["node"], r["direction"], r["topic"]) for r in rows] == [
        ("detection", "out", "detections"), ("detection", "in", "capture/frame"), ("idle", None, None)]
    out, inp, idle = rows
    assert (out["rate_hz"], out["latency_p50_ms"], out["drops"]) == (29.0, None, None)
    assert (inp["rate_hz"], inp["latency_p50_ms"], inp["drops"], inp["decode_errors"]) == (29.5, 4.25, 3, 1)
    assert (inp["lost"], out["lost"]) == (5, None)  # messages that never arrived: inputs only
    assert (inp["alive"], inp["restarts"], inp["pid"]) == (True, 2, 7)
    assert not idle["alive"] and idle["rate_hz"] is None


def _request(port: int, path: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path, headers=headers or {})
        r = conn.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        conn.close()


def _web_view(web_port: int, *extra: str) -> tuple[subprocess.Popen, list[str]]:
    proc = subprocess.Popen(followbus_argv("monitor", "--web", str(web_port), *extra), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=REPO, stdin=subprocess.DEVNULL)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    assert wait_until(lambda: any("web view on" in line for line in lines) or proc.poll() is not None, 20), lines
    assert proc.poll() is None, "".join(lines)
    return proc, lines


@pytest.mark.slow
def test_web_token_is_checked_on_every_request(monkeypatch, tmp_path):
    monkeypatch.delenv("FOLLOWBUS_WEB_TOKEN", raising=False)
    web_port = free_port()
    # Nothing listens on the robot's port: the page still serves, and says the robot is unreachable.
    proc, lines = _web_view(web_port, "--web-token", TOKEN, "--connect", f"tcp/127.0.0.1:{free_port()}")
    try:
        assert "token required (--web-token)" in lines[0] and TOKEN not in lines[0], lines[0]
        for path in ("/", "/state.json", "/preview.jpg?after=-1&client=t", "/healthz", "/nope"):
            status, headers, _ = _request(web_port, path)
            assert status == 401 and headers["www-authenticate"].startswith("Bearer"), (path, status)
        for headers in ({"Cookie": "followbus_token=wrong-token"}, {"Authorization": "Bearer wrong-token"}, {}):
            path = "/state.json" if headers else "/state.json?token=wrong-token"
            assert _request(web_port, path, headers)[0] == 403, headers
        # The first visit swaps the URL token for a cookie and keeps the other parameters.
        status, headers, _ = _request(web_port, f"/?source_width=320&token={TOKEN}")
        assert status == 303 and headers["location"] == "/?source_width=320", headers
        cookie = headers["set-cookie"]
        assert cookie.startswith(f"followbus_token={TOKEN};") and "HttpOnly" in cookie, cookie
        jar = {"Cookie": cookie.split(";")[0]}
        status, _, page = _request(web_port, "/", jar)
        assert status == 200 and b'id="nodes"' in page
        for headers in (jar, {"Authorization": f"Bearer {TOKEN}"}):
            status, _, body = _request(web_port, "/state.json", headers)
            assert status == 200
        assert _request(web_port, f"/state.json?token={TOKEN}")[0] == 200  # scripts: the token in the URL
        assert wait_until(lambda: json.loads(_request(web_port, "/state.json", jar)[2])["screen"]["code"]
                          == "unreachable", 10)
        # A browser opening the printed URL: redirect, cookie, and the page's own requests pass with it.
        require_chromium()
        dom = render_dom(f"http://127.0.0.1:{web_port}/?token={TOKEN}", tmp_path, budget_ms=1500)
        code, text = element_text(dom, "banner")
        assert code == "unreachable" and text.startswith("robot unreachable since "), (code, text)
        assert element_text(dom, "screen") == (code, text)
        assert element_text(dom, "srcw")[1] == "source width 640 px"  # the default: no graph given
        assert element_text(dom, "frames")[1] == "frames: 0"
        assert element_text(dom, "state")[1].startswith("target (no track yet)")
        assert "no node seen yet" in dom
        assert page_layout(dom)["width"] == 1280
    finally:
        _interrupt(proc)


@pytest.mark.slow
def test_generated_token_is_printed_once_and_required(monkeypatch, capsys):
    """The non-loopback path (a generated token) on 127.0.0.1: the rule is made to see a non-loopback bind."""
    from followbus.tools.live import webview
    from followbus.tools.live.monitor import monitor_settings

    monkeypatch.delenv("FOLLOWBUS_WEB_TOKEN", raising=False)
    monkeypatch.setattr(webview, "is_loopback_bind", lambda bind: False)
    web_port = free_port()
    settings = monitor_settings(None, [f"tcp/127.0.0.1:{free_port()}"])
    done: list[int] = []
    server = threading.Thread(target=lambda: done.append(webview.serve(settings, graph_info(None), "127.0.0.1",
                                                                       web_port, seconds=4.0)), daemon=True)
    server.start()
    out = ""

    def printed() -> bool:
        nonlocal out
        out += capsys.readouterr().out
        return "web view on" in out

    assert wait_until(printed, 10), out
    line = next(line for line in out.splitlines() if "web view on" in line)
    assert "token required (--bind is not loopback; generated for this run)" in line, line
    token = line.split("?token=")[1].split()[0]
    assert len(token) >= 16
    assert _request(web_port, "/state.json")[0] == 401
    assert _request(web_port, "/state.json?token=" + token[::-1])[0] == 403
    assert _request(web_port, "/state.json", {"Authorization": f"Bearer {token}"})[0] == 200
    server.join(15)
    assert done == [0] and out.count(token) == 1, out


@pytest.mark.slow
def test_user_mistakes_exit_2_with_one_line():
    result = subprocess.run(followbus_argv("monitor", "--web", str(free_port()), "--web-token", "short"),
                            capture_output=True, text=True, timeout=30, cwd=REPO, stdin=subprocess.DEVNULL)
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "--web-token" in result.stderr, result
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        result = subprocess.run(followbus_argv("monitor", "--web", str(taken.getsockname()[1]), "--seconds", "5"),
                                capture_output=True, text=True, timeout=30, cwd=REPO, stdin=subprocess.DEVNULL)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result
    assert "cannot serve the web view" in result.stderr and "Traceback" not in result.stderr


def _screen(web_port: int) -> dict:
    try:
        return json.loads(_request(web_port, "/state.json")[2])["screen"]
    except (OSError, ValueError):
        return {}


@pytest.mark.slow
def test_page_says_unreachable_then_waiting_then_source_ended(tmp_path):
    """One web view (loopback: no token) through a robot's life: not up yet, up without a frame, source done.
    Without Chromium (outside CI only) the states are checked over HTTP and the test then skips. The page's
    "robot unreachable": test_web_token_is_checked_on_every_request."""
    browser = have_chromium()
    robot_port, web_port = free_port(), free_port()
    graph = robot_graph(tmp_path, robot_port, CAPTURE_AND_CONSUMER)
    with open(tmp_path / "graph.yaml", "a") as base:
        base.write("default_host: robot\n")  # the nodes without host: run on "robot"
    url = f"http://127.0.0.1:{web_port}/"
    proc, lines = _web_view(web_port, "--graph", str(graph), "--user", "monitor", "--password", "monitor-secret")
    launch = consumer = None
    try:
        assert "open to this machine only" in lines[0], lines[0]
        assert wait_until(lambda: _screen(web_port).get("code") == "unreachable", 10), _screen(web_port)
        # Before the first state the page holds placeholders, not half-filled sentences; then the graph's width.
        page = _request(web_port, "/")[2].decode()
        assert element_text(page, "srcw")[1] == "source width not known yet"
        # The graph's drawing (bus/graph_drawing.py), under the health table.
        status, headers, svg = _request(web_port, "/graph.svg")
        assert status == 200 and headers["content-type"] == "image/svg+xml" and svg.count(b'class="node"') == 2
        assert 'src="graph.svg"' in page
        assert element_text(page, "state")[1].startswith("no state yet")

        # Capture is up and waits for detection: the page waits for the first frame, visibly.
        launch = Launch(graph, "--host", "robot")
        launch.wait_ready()
        assert wait_until(lambda: _screen(web_port).get("code") == "waiting", 20), (_screen(web_port), lines[-5:])
        if browser:
            dom = render_dom(url, tmp_path, budget_ms=1500)
            assert element_text(dom, "banner") == ("waiting", "waiting for first frame")
            assert element_text(dom, "screen") == ("waiting", "waiting for first frame")
            assert 'data-node="capture"' in dom and "frames: 0" in dom

        # Its consumer comes up, capture plays its 12 frames and stops: the last frame stays, with the reason.
        consumer_log = open(tmp_path / "detection.log", "w")  # noqa: SIM115 - closed in finally
        consumer = subprocess.Popen(followbus_argv("node", "detection", "--graph", str(graph)), cwd=REPO,
                                    stdout=consumer_log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        # A bound, not a timing: a loaded 2-core machine can take tens of seconds to start the detection process.
        assert wait_until(lambda: _screen(web_port).get("code") == "ended", 90), (
            _screen(web_port), lines[-5:], launch.lines[-10:], (tmp_path / "detection.log").read_text()[-2000:])
        assert _screen(web_port)["text"] == "source ended after 12 frames; last frame shown"
        if browser:
            dom = render_dom(url, tmp_path, budget_ms=2000)
            assert element_text(dom, "banner") == ("ended", "source ended after 12 frames; last frame shown")
            assert element_text(dom, "frames")[1] == "frames: 1 (seq 11)"  # drawn once, not redrawn per poll
            # No group on the bus: the person view only, the group panel stays hidden.
            assert re.search(r'<div id="groundbox" hidden', dom) and page_layout(dom)["ground"]["bottom"] == 0
    finally:
        if consumer is not None:
            _interrupt(consumer)
            consumer_log.close()
        if launch is not None:
            launch.stop()
        _interrupt(proc)
    if not browser:
        require_chromium()  # the states held over HTTP; say that the page itself was not rendered


def test_group_view_puts_the_odometry_frame_state_in_the_robot_frame():
    """GroupState is in the odometry frame; the view places it around the robot with the pose of the same
    frame's ground points (inverse of seed 004 Eq. 4), and projects the floor shapes into the image."""
    info = graph_info(str(REPO / "graph.group.yaml"))
    assert info.keys["group"] == "fb/group/group" and info.keys["points"] == "fb/groundplane/points"
    assert info.camera is not None and info.camera.focal_px == 512.0 and info.camera.camera_height_m == 1.1
    assert graph_info(str(REPO / "graph.yaml")).camera is None  # the person graph: nothing to project

    pose = (1.5, -0.4, math.radians(30))
    robot_pts = np.array([[3.0, 0.5], [3.4, -0.6], [4.1, 0.1], [2.5, -2.5]])
    odom_pts, _ = to_odometry_frame(robot_pts, np.zeros((4, 2, 2)), *pose)
    extent_robot = np.array([[0.5, 0.2], [0.2, 0.3]])
    rot = np.array([[math.cos(pose[2]), -math.sin(pose[2])], [math.sin(pose[2]), math.cos(pose[2])]])
    group = GroupState(valid=True, centre_m=odom_pts[:3].mean(axis=0), velocity_mps=np.array([0.3, 0.4]),
                       centre_robot_m=robot_pts[:3].mean(axis=0), ellipse_centres_m=odom_pts[:2],
                       ellipse_extents_m2=np.stack([rot @ extent_robot @ rot.T] * 2),
                       ellipse_weights=np.array([.6, .4]),
                       members_m=odom_pts[:3], others_m=odom_pts[3:], orientation_rad=pose[2] + 0.2)
    group.header.frame_seq = 7
    points = GroundPoints(points_robot_m=robot_pts, points_m=odom_pts)
    view = group_view(group, pose, points, info.camera)
    assert view["posed"] and view["members"] == 3 and view["others"] == 1 and view["speed_mps"] == 0.5
    np.testing.assert_allclose([e["centre_m"] for e in view["ellipses"]], robot_pts[:2], atol=1e-3)
    np.testing.assert_allclose(view["ellipses"][0]["extent_m2"], extent_robot, atol=1e-4)
    np.testing.assert_allclose(view["members_robot_m"], robot_pts[:3], atol=1e-3)
    np.testing.assert_allclose(view["others_robot_m"], robot_pts[3:], atol=1e-3)
    assert view["orientation_robot_rad"] == pytest.approx(0.2)
    np.testing.assert_allclose(view["centre_px"], floor_to_image(robot_pts[:3].mean(axis=0), info.camera)[0],
                               atol=0.1)
    # The outline in the image: the 2-sigma floor ellipse projected, around the centre's own pixel.
    outline = np.array(view["ellipses"][0]["outline_px"], dtype=float)
    centre_px = floor_to_image(robot_pts[:1], info.camera)[0]
    assert outline.shape == (32, 2) and np.all(outline.min(axis=0) < centre_px) and np.all(outline.max(axis=0) >
                                                                                            centre_px)
    assert "3 members, 1 left out, 2 ellipses" in _group_line(view)  # the terminal dashboard's row
    # Without the frame's pose the shape is not placed: the centre only (the group node's robot frame).
    bare = group_view(group, None, None, info.camera)
    assert "ellipses" not in bare and "members_robot_m" not in bare and bare["centre_robot_m"] == pytest.approx(
        robot_pts[:3].mean(axis=0).tolist())
    assert group_view(GroupState(), pose, None)["valid"] is False


def _magenta(png: np.ndarray, box: dict) -> int:
    """Pixels of the ellipses' colour (#f0f) inside a layout box of a screenshot."""
    part = png[box["top"]:box["bottom"], box["left"]:box["right"]].astype(int)
    b, g, r = part[..., 0], part[..., 1], part[..., 2]
    return int(np.count_nonzero((r > 180) & (b > 180) & (g < 90)))


@pytest.mark.slow
def test_group_graph_page_draws_the_ellipses(tmp_path, port):
    """graph.group.yaml for real (simulated detector, scene group-walk) and the web view in headless Chromium:
    the top-down panel appears and draws the tracker's ellipses, members and centre, and the ellipses are on
    the floor in the video (a pixel count of their colour in a screenshot, which is the README's picture)."""
    graph = _graph_copies(tmp_path, port)
    web_port = free_port()
    launch = Launch(graph, "--set", "detection.backend=simulated", "--set", "capture.loop=true")
    proc = None
    try:
        launch.wait_ready()
        proc, lines = _web_view(web_port, "--graph", str(graph))

        def group() -> dict:
            try:
                return json.loads(_request(web_port, "/state.json")[2]).get("group") or {}
            except (OSError, ValueError):
                return {}

        # Past the first seconds, when the shape has settled: several people, ellipses placed with the pose.
        assert wait_until(lambda: group().get("frame_seq", 0) > 90 and len(group().get("ellipses", [])) >= 1
                          and group().get("members", 0) >= 3, 40), (group(), "".join(launch.lines[-20:]))
        require_chromium()
        window = "1280,1000"
        dom = render_dom(f"http://127.0.0.1:{web_port}/", tmp_path, budget_ms=3000, window=window)
        assert '<div id="groundbox">' in dom, dom[:3000]  # shown (not hidden) with a group on the bus
        drawn = json.loads(html.unescape(re.search(r'id="ground"[^>]*data-drawn="([^"]*)"', dom).group(1)))
        assert drawn["ellipses"] >= 1 and drawn["members"] >= 3, drawn
        assert element_text(dom, "state")[1].startswith("group frame "), element_text(dom, "state")
        layout = page_layout(dom)
        ground, video = layout["ground"], layout["video"]
        assert ground["top"] >= video["bottom"] and ground["bottom"] <= 1000, layout
        shot = docs_picture("webview-group.png", tmp_path)
        assert screenshot(f"http://127.0.0.1:{web_port}/", shot, tmp_path, budget_ms=3000, window=window) == (
            1280, 1000)
        png = cv2.imread(str(shot))
        # The ellipses' colour appears in the panel and in the video, and nowhere else on the page.
        in_panel, in_video = _magenta(png, ground), _magenta(png, video)
        everywhere = _magenta(png, {"top": 0, "bottom": 1000, "left": 0, "right": 1280})
        assert in_panel > 100 and in_video > 50, (in_panel, in_video)
        assert everywhere - in_panel - in_video < 20, (everywhere, in_panel, in_video)
    finally:
        if proc is not None:
            _interrupt(proc)
        launch.stop()
