"""The web view as an operator's screen: who may open it (token rule, real HTTP on loopback), what it says
(waiting / source ended / robot unreachable, labelled health rows), and the page in headless Chromium against
a real capture node. The live two-column page and the README screenshot: tests/test_monitor.py."""

from __future__ import annotations

import http.client
import json
import socket
import subprocess
import threading

import pytest

from followbus.tools.webview import health_rows, is_loopback_bind, screen_state, web_token

from .chromium import element_text, have_chromium, page_layout, render_dom, require_chromium
from .conftest import REPO, followbus_argv, free_port, wait_until
from .test_monitor import Launch, _interrupt, robot_graph

TOKEN = "s3cret-token-for-tests"
# Capture holds frame 0 back until its consumer (detection) is up: the test decides when frames start.
CAPTURE_AND_CONSUMER = """\
  capture:
    run: followbus.nodes.capture
    outputs: [frame, preview, ground_truth]
    params: {source: "scene:wall-occlusion", max_frames: 12, wait_for_consumers_s: 600}
  detection:
    run: followbus.nodes.detection
    inputs: {frame: capture/frame}
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
                                "decode_errors": 1},
            "t/detection/detections": {"direction": "out", "rate_hz": 29.0, "latency_p50_ms": None, "drops": 0,
                                       "decode_errors": 0}}},
        {"name": "idle", "alive": False, "restarts": 0, "pid": None, "topics": {}}])
    rows = health_rows(snap)
    assert [(r["node"], r["direction"], r["topic"]) for r in rows] == [
        ("detection", "out", "detections"), ("detection", "in", "capture/frame"), ("idle", None, None)]
    out, inp, idle = rows
    assert (out["rate_hz"], out["latency_p50_ms"], out["drops"]) == (29.0, None, None)
    assert (inp["rate_hz"], inp["latency_p50_ms"], inp["drops"], inp["decode_errors"]) == (29.5, 4.25, 3, 1)
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
    from followbus.tools import webview
    from followbus.tools.monitor import GraphInfo, monitor_settings

    monkeypatch.delenv("FOLLOWBUS_WEB_TOKEN", raising=False)
    monkeypatch.setattr(webview, "is_loopback_bind", lambda bind: False)
    web_port = free_port()
    settings = monitor_settings(None, [f"tcp/127.0.0.1:{free_port()}"])
    done: list[int] = []
    server = threading.Thread(target=lambda: done.append(webview.serve(settings, GraphInfo.load(None), "127.0.0.1",
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
    url = f"http://127.0.0.1:{web_port}/"
    proc, lines = _web_view(web_port, "--graph", str(graph), "--user", "monitor", "--password", "monitor-secret")
    launch = consumer = None
    try:
        assert "open to this machine only" in lines[0], lines[0]
        assert wait_until(lambda: _screen(web_port).get("code") == "unreachable", 10), _screen(web_port)
        # Before the first state the page holds placeholders, not half-filled sentences; then the graph's width.
        page = _request(web_port, "/")[2].decode()
        assert element_text(page, "srcw")[1] == "source width not known yet"
        assert element_text(page, "state")[1].startswith("no state yet")

        # Capture is up and waits for detection: the page waits for the first frame, visibly.
        launch = Launch(graph, "--only", "capture")
        launch.wait_ready()
        assert wait_until(lambda: _screen(web_port).get("code") == "waiting", 20), (_screen(web_port), lines[-5:])
        if browser:
            dom = render_dom(url, tmp_path, budget_ms=1500)
            assert element_text(dom, "banner") == ("waiting", "waiting for first frame")
            assert element_text(dom, "screen") == ("waiting", "waiting for first frame")
            assert 'data-node="capture"' in dom and "frames: 0" in dom

        # Its consumer comes up, capture plays its 12 frames and stops: the last frame stays, with the reason.
        consumer = subprocess.Popen(followbus_argv("node", "detection", "--graph", str(graph)), cwd=REPO,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
        assert wait_until(lambda: _screen(web_port).get("code") == "ended", 30), (_screen(web_port), lines[-5:])
        assert _screen(web_port)["text"] == "source ended after 12 frames; last frame shown"
        if browser:
            dom = render_dom(url, tmp_path, budget_ms=2000)
            assert element_text(dom, "banner") == ("ended", "source ended after 12 frames; last frame shown")
            assert element_text(dom, "frames")[1] == "frames: 1 (seq 11)"  # drawn once, not redrawn per poll
    finally:
        if consumer is not None:
            _interrupt(consumer)
        if launch is not None:
            launch.stop()
        _interrupt(proc)
    if not browser:
        require_chromium()  # the states held over HTTP; say that the page itself was not rendered
