"""``followbus monitor --web``: the monitor as an operator's screen served from the laptop.

The server holds one :class:`~followbus.tools.live.monitor.BusMonitor` (a Zenoh client that only subscribes: the
latest JPEG preview, never raw frames, plus a bounded history). HTTP handlers only read that state, so however
slow a browser or the Wi-Fi is, nothing flows back to the robot. Each browser fetches one preview at a time
(the next request goes out when the previous image has loaded) and the server serves at most
``MAX_PREVIEWS_PER_S`` per client, always the newest frame: a slow client simply sees fewer frames.

The page: video with overlays on the left, state, plots and the health table (a row per topic, labelled
columns) on the right at laptop width, one column on narrow screens; a banner over the video says what the
operator is looking at: waiting for the first frame, source ended, no new frame (frozen), robot unreachable.
With a group graph on the bus (graph.group.yaml: group/group GroupState, groundplane/points) the page adds
a top-down panel of the group in the robot frame (ellipses, members, disturbers, centre) and draws the
ellipses on the floor in the video; without one the person view is all there is.

Access: a loopback bind is open. Any other bind requires a token (``--web-token`` or a generated one printed
once at start as a ``?token=`` URL), checked on every request; the first visit with ``?token=`` sets a cookie.
``--web-token`` on a loopback bind requires it there too.

Endpoints: ``/`` (the page), ``/state.json`` (snapshot with history, ``screen`` state and ``health`` rows),
``/preview.jpg?after=N&client=ID`` (long-polls up to 1 s for a preview newer than N, or for the first one;
204 if none came), ``/healthz``.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import os
import re
import secrets
import socket
import sys
import threading
import time
from http.cookies import CookieError, SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs, urlencode, urlparse

from ...bus.session import ZenohSettings
from ...viewing.monitor import BusMonitor, GraphInfo
from .introspect import wait_for

log = logging.getLogger("followbus.webview")

MAX_PREVIEWS_PER_S = 10.0
LONG_POLL_S = 1.0
# Nodes publish NodeStatus every second: none for this long while connected means nothing on the robot runs.
STATUS_STALE_S = 5.0
FRAME_STALE_S = 3.0  # no preview for this long: the picture is frozen, say so rather than "live"
TOKEN_COOKIE = "followbus_token"
TOKEN_ENV = "FOLLOWBUS_WEB_TOKEN"
TOKEN_RE = re.compile(r"[A-Za-z0-9._~-]{8,256}")  # URL- and cookie-safe; shorter is guessable
EXIT_BAD_INPUT = 2


def is_loopback_bind(bind: str) -> bool:
    """True when ``bind`` only accepts connections from this machine (127.0.0.0/8, ::1, localhost).

    Anything else, including ``0.0.0.0``/``::`` (every interface), an empty string and host names other than
    ``localhost`` (whose resolution may change), counts as reachable from the network.
    """
    host = bind.strip().strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def web_token(bind: str, given: str | None) -> tuple[str | None, bool]:
    """The token the server requires (None: open) and whether it was generated here.

    Raises ValueError for a token that is too short or has characters unsafe in a URL or cookie."""
    if given is not None:
        if not TOKEN_RE.fullmatch(given):
            raise ValueError("--web-token must be 8-256 characters of A-Z a-z 0-9 . _ ~ -")
        return given, False
    if is_loopback_bind(bind):
        return None, False
    return secrets.token_urlsafe(18), True


def _clock(ns: int | None) -> str:
    return time.strftime("%H:%M:%S", time.localtime(ns / 1e9)) if ns else "?"


def screen_state(snap: dict[str, Any], source_node: str, stale_after_s: float = STATUS_STALE_S,
                 frame_stale_s: float = FRAME_STALE_S) -> dict[str, str]:
    """What the operator is looking at, as ``{"code", "text"}``: unreachable, ended, waiting, stalled or live.

    ``source_node`` publishes the preview; its NodeStatus extra says whether its source is exhausted
    (``done``) and how many frames it published in this run (0: any preview shown is from an earlier run)."""
    if not snap.get("connected"):
        text = f"robot unreachable since {_clock(snap.get('unreachable_since_ns'))}"
        if snap.get("last_error"):
            text += f" ({snap['last_error'][:80]})"
        return {"code": "unreachable", "text": text}
    ages = [n["status_age_s"] for n in snap.get("nodes", []) if n.get("status_age_s") is not None]
    if ages and min(ages) > stale_after_s:
        return {"code": "unreachable", "text": f"robot unreachable: no node status for {min(ages):.0f} s"}
    source = next((n for n in snap.get("nodes", []) if n.get("name") == source_node), None)
    extra = (source or {}).get("extra") or {}
    preview = snap.get("preview")
    if extra.get("done"):
        published = extra.get("published")
        count = f" after {published} frames" if isinstance(published, int) else ""
        shown = "; last frame shown" if preview and published else ""
        return {"code": "ended", "text": f"source ended{count}{shown}"}
    if not preview or extra.get("published") == 0:
        # Connected, but no node of our namespace: say which namespaces do have nodes (a robot's graph that
        # runs under another namespace), as the terminal monitor does.
        hint = snap.get("namespaces_hint")
        return {"code": "waiting", "text": f"waiting for first frame: {hint}" if hint else "waiting for first frame"}
    age = preview.get("age_s")
    if age is not None and age > frame_stale_s:
        return {"code": "stalled", "text": f"no new frame for {age:.0f} s (showing frame {preview.get('frame_seq')})"}
    return {"code": "live", "text": f"live: frame {preview.get('frame_seq', '?')}"}


def health_rows(snap: dict[str, Any]) -> list[dict[str, Any]]:
    """The health table: a row per topic of each node (outputs, then inputs), one row for a node without any.

    Outputs carry only a rate; inputs a rate, p50 latency, drops and messages lost on the way. Topic names drop the
    namespace, and an output its own node's name too (``preview``; an input reads ``capture/frame``)."""
    prefix = f"{snap.get('namespace', '')}/"
    rows: list[dict[str, Any]] = []
    for node in snap.get("nodes", []):
        base = {"node": node["name"], "alive": bool(node.get("alive")),
                "state": node.get("state") or ("up" if node.get("alive") else "down"),
                "restarts": node.get("restarts", 0), "pid": node.get("pid")}
        topics = node.get("topics") or {}
        order = sorted(topics, key=lambda k: (topics[k].get("direction") != "out", k))
        if not order:
            rows.append({**base, "topic": None, "direction": None, "rate_hz": None, "latency_p50_ms": None,
                         "drops": None, "lost": None, "decode_errors": None})
        for key in order:
            t = topics[key]
            name = key[len(prefix):] if key.startswith(prefix) else key
            inbound = t.get("direction") == "in"
            if not inbound and name.startswith(f"{node['name']}/"):
                name = name[len(node["name"]) + 1:]
            rows.append({**base, "topic": name, "direction": "in" if inbound else "out", "rate_hz": t.get("rate_hz"),
                         "latency_p50_ms": t.get("latency_p50_ms") if inbound else None,
                         "drops": t.get("drops", 0) if inbound else None,
                         "lost": t.get("lost", 0) if inbound else None,
                         "decode_errors": t.get("decode_errors", 0)})
    return rows


class PreviewGate:
    """Per-client rate limit for previews, and a condition to wait for a newer one."""

    def __init__(self, max_per_s: float = MAX_PREVIEWS_PER_S):
        self.min_interval = 1.0 / max_per_s
        self.cond = threading.Condition()
        self._last: dict[str, float] = {}

    def notify(self) -> None:
        with self.cond:
            self.cond.notify_all()

    def pace(self, client: str) -> None:
        """Sleep so that this client gets at most max_per_s previews (bounded, never blocks the bus)."""
        with self.cond:
            last = self._last.get(client, 0.0)
            wait = last + self.min_interval - time.monotonic()
            if len(self._last) > 1000:  # forget old clients
                self._last.clear()
        if wait > 0:
            time.sleep(wait)
        with self.cond:
            self._last[client] = time.monotonic()


def _source_node(monitor: Any) -> str:
    info = getattr(monitor, "info", None)
    key = getattr(info, "preview_key", "") or "fb/capture/preview"
    return key.split("/")[-2]


def make_handler(monitor: BusMonitor, gate: PreviewGate, token: str | None = None) -> type[BaseHTTPRequestHandler]:
    """The request handler; with ``token`` every request must carry it (query, cookie or Bearer header)."""

    class Handler(BaseHTTPRequestHandler):
        server_version = "followbus-monitor"

        def log_message(self, fmt: str, *args: Any) -> None:  # quiet: one line per request is noise
            log.debug("%s " + fmt, self.address_string(), *args)

        def _send(self, code: int, body: bytes, ctype: str, headers: dict[str, str] | None = None) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            for k, v in (headers or {}).items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(body)

        def _credential(self, query: dict[str, list[str]]) -> tuple[str | None, bool]:
            """The token this request offers, and whether it came in the URL (then it becomes a cookie)."""
            if "token" in query:
                return query["token"][0], True
            auth = self.headers.get("Authorization", "")
            if auth.startswith("Bearer "):
                return auth[len("Bearer "):].strip(), False
            try:
                morsel = SimpleCookie(self.headers.get("Cookie", "")).get(TOKEN_COOKIE)
            except CookieError:
                morsel = None
            return (morsel.value if morsel is not None else None), False

        def _authorise(self, path: str, query: dict[str, list[str]]) -> bool:
            """Answer 401/403 (or the redirect that swaps a URL token for a cookie); True: go on."""
            if token is None:
                return True
            given, in_url = self._credential(query)
            if given is None:
                self._send(401, b"token required: open the URL followbus monitor printed (.../?token=...)\n",
                           "text/plain", {"WWW-Authenticate": 'Bearer realm="followbus monitor"'})
                return False
            if not hmac.compare_digest(given.encode(), token.encode()):
                log.warning("refused %s: wrong token", self.address_string())
                self._send(403, b"wrong token\n", "text/plain")
                return False
            if in_url and path in ("/", "/index.html"):
                # Keep the token out of the address bar and history: a cookie carries it from now on.
                rest = urlencode({k: v for k, v in query.items() if k != "token"}, doseq=True)
                self._send(303, b"", "text/plain", {"Location": "/" + (f"?{rest}" if rest else ""),
                                                   "Set-Cookie": self._cookie()})
                return False
            return True

        def _cookie(self) -> str:
            return f"{TOKEN_COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict"

        def do_GET(self) -> None:  # noqa: N802 (http.server API)
            url = urlparse(self.path)
            query = parse_qs(url.query)
            try:
                if not self._authorise(url.path, query):
                    return
                if url.path in ("/", "/index.html"):
                    self._send(200, PAGE.encode(), "text/html; charset=utf-8")
                elif url.path == "/state.json":
                    self._send(200, json.dumps(self._state(), default=str).encode(), "application/json")
                elif url.path == "/preview.jpg":
                    self._preview(query)
                elif url.path == "/graph.svg":
                    svg = monitor.graph_svg()
                    self._send(200 if svg else 404,
                               (svg or "no graph file given, and no node has said what it publishes yet\n").encode(),
                               "image/svg+xml" if svg else "text/plain")
                elif url.path == "/healthz":
                    self._send(200, b"ok\n", "text/plain")
                else:
                    self._send(404, b"not found\n", "text/plain")
            except (BrokenPipeError, ConnectionResetError):
                pass  # the browser went away

        def _state(self) -> dict[str, Any]:
            snap = monitor.snapshot()
            snap["screen"] = screen_state(snap, _source_node(monitor))
            snap["health"] = health_rows(snap)
            return snap

        def _preview(self, query: dict[str, list[str]]) -> None:
            client = query.get("client", [self.client_address[0]])[0][:64]
            try:
                after = int(query.get("after", ["-1"])[0] or -1)
            except ValueError:
                self._send(400, b"after must be an integer\n", "text/plain")
                return
            gate.pace(client)
            deadline = time.monotonic() + LONG_POLL_S
            with gate.cond:
                # count 0 = nothing received yet: "after -1" still waits for the first preview
                while monitor.preview_count <= max(after, 0) and time.monotonic() < deadline:
                    gate.cond.wait(max(0.0, deadline - time.monotonic()))
            with monitor.lock:
                jpeg, count = monitor.preview_jpeg, monitor.preview_count
                seq = monitor.preview.header.frame_seq if monitor.preview is not None else -1
            if not jpeg or count <= after:  # nothing newer within the long poll: the page keeps its frame
                self._send(204, b"", "image/jpeg", {"X-Preview-Count": str(count)})
                return
            self._send(200, jpeg, "image/jpeg", {"X-Preview-Count": str(count), "X-Frame-Seq": str(seq)})

    return Handler


class _Server(ThreadingHTTPServer):
    daemon_threads = True


class _Server6(_Server):
    address_family = socket.AF_INET6


def start_server(settings: ZenohSettings, info: GraphInfo, bind: str, port: int, token: str | None = None
                 ) -> tuple[ThreadingHTTPServer, BusMonitor, threading.Thread]:
    """Start the bus monitor and the HTTP server (in a thread); the caller shuts both down.

    Raises OSError when the address cannot be bound (nothing is left running then)."""
    gate = PreviewGate()
    host = bind.strip("[]")
    server_cls = _Server6 if ":" in host else _Server
    # Bind first: a taken port or a bad address fails before the bus is joined.
    server = server_cls((host, port), BaseHTTPRequestHandler)
    monitor = BusMonitor(settings, info, preview=True, on_preview=gate.notify).start()
    server.RequestHandlerClass = make_handler(monitor, gate, token)
    thread = threading.Thread(target=server.serve_forever, name="webview-http", daemon=True)
    thread.start()
    return server, monitor, thread


def serve(settings: ZenohSettings, info: GraphInfo, bind: str, port: int, seconds: float | None = None,
          token: str | None = None) -> int:
    """Serve the web view until Ctrl-C (or ``seconds``); 2 with one line on stderr for a bad token or bind."""
    given = token if token is not None else (os.environ.get(TOKEN_ENV) or None)
    try:
        required, generated = web_token(bind, given)
        server, monitor, thread = start_server(settings, info, bind, port, required)
    except ValueError as exc:
        print(f"followbus monitor: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:  # port taken, address not on this machine, ...
        print(f"followbus monitor: cannot serve the web view on {bind}:{port}: {exc.strerror or exc}",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    host, real_port = server.server_address[:2]
    url = f"http://{f'[{host}]' if ':' in host else host}:{real_port}/"
    if generated:  # printed once: the operator opens this URL, the browser keeps a cookie
        url += f"?token={required}"
        access = "token required (--bind is not loopback; generated for this run)"
    elif required:
        access = "token required (--web-token)"
    else:
        access = "open to this machine only"
    if not is_loopback_bind(bind) and ipaddress.ip_address(host).is_unspecified:
        access += "; listening on every interface, use this machine's address"
    print(f"followbus monitor: web view on {url} ({access}; watching {', '.join(settings.connect)}; "
          "Ctrl-C to stop)", flush=True)
    try:
        wait_for(seconds)
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=2)
    # Not on Ctrl-C (KeyboardInterrupt passes by): the process then ends at once (tools/cli.py) with the session
    # left open, as the terminal monitor does; closing it first can wait on a slow link past anyone's patience.
    monitor.close()
    return 0


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>followbus monitor</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font:14px system-ui,sans-serif;margin:12px;background:#111;color:#ddd}
header{display:flex;gap:16px;align-items:baseline;margin-bottom:8px}
h1{font-size:16px;margin:0} #link.bad{color:#e55}
#layout{display:grid;grid-template-columns:minmax(0,1fr);gap:16px}
@media (min-width:1100px){#layout{grid-template-columns:minmax(0,1fr) minmax(0,1fr)}}
#video{position:relative;background:#000;border:1px solid #333}
#view{display:block;width:100%;height:auto}
#banner{position:absolute;left:0;right:0;top:40%;text-align:center;font-size:20px;padding:10px;
 background:rgba(20,20,20,.8)}
#banner[data-state=live]{display:none} #banner[data-state=unreachable],#banner[data-state=server]{color:#f77}
#banner[data-state=ended],#banner[data-state=stalled]{color:#fc6;top:auto;bottom:0;font-size:16px}
.legend{font-size:12px;color:#888;margin:4px 0}
#screen{font-weight:bold} #screen[data-state=live]{color:#6c6} #screen[data-state=unreachable],
#screen[data-state=server]{color:#e55} #screen[data-state=ended],#screen[data-state=waiting],
#screen[data-state=stalled]{color:#fc6}
#state{font:13px monospace;white-space:pre;margin:0 0 8px}
#state .stale{color:#777;text-decoration:line-through} #state .stalelabel{color:#fc6;font-weight:bold}
#state .age{color:#777} #graphbox img{max-width:100%;background:#eee}
.plot{display:block;width:100%;height:64px;margin-bottom:4px}
table{border-collapse:collapse;font-size:11px;line-height:1.2;width:100%}
td,th{border-bottom:1px solid #333;padding:1px 5px;text-align:right;vertical-align:top}
th{color:#aaa;font-weight:normal} td.l,th.l{text-align:left} tr.first td{border-top:1px solid #555}
td.topic{white-space:nowrap}
#ground{display:block;width:100%;height:320px;background:#1a1a1a;border:1px solid #333}
.up{color:#6c6} .down{color:#e55} .stalled{color:#fc6;font-weight:bold} .done{color:#6cc}
.dir{color:#888} .na{color:#555}
</style></head><body>
<header><h1>followbus monitor</h1><span id="screen" data-state="waiting">waiting for the monitor's first state</span>
 <span id="link">connecting...</span></header>
<main id="layout">
 <section id="left">
  <div id="video"><canvas id="view" width="640" height="480"></canvas>
   <div id="banner" data-state="waiting">waiting for first frame</div></div>
  <div id="frames">frames: 0</div>
  <p class="legend">green: target box, cyan: gate ellipse (prior, chi2), yellow: candidates (score).
   Boxes are scaled by preview width / source width (<span id="srcw">source width not known yet</span>;
   override with ?source_width=N).</p>
  <div id="groundbox" hidden><canvas id="ground" width="640" height="320"></canvas>
   <p class="legend">The followed group (seed 004), top down in the robot frame: the robot at the bottom
    facing up, rings every metre. Magenta: the tracker's ellipses at <span id="gsigma">2</span> standard
    deviations of each sub-target's extent (weight %), also drawn on the floor in the video; green: members;
    red: points left out (disturbers); grey: this frame's detections on the floor; white cross: the group
    centre the motor follows.</p></div>
 </section>
 <section id="right">
  <div id="state">no state yet: target, eta_k and motor command appear here</div>
  <canvas class="plot" id="p_err"></canvas>
  <canvas class="plot" id="p_eta"></canvas>
  <canvas class="plot" id="p_lat"></canvas>
  <table id="nodes"><thead><tr><th class="l">node</th><th class="l">state</th><th>restarts</th>
   <th class="l">topic</th><th>rate Hz</th><th title="inputs: median capture-to-receive latency">p50 latency ms</th>
   <th title="inputs: messages dropped by the queue policy">drops</th>
   <th title="inputs: messages that never arrived (gaps in the publisher's header.seq)">lost</th>
   <th>decode errors</th></tr></thead>
   <tbody><tr><td class="l na" colspan="9">no node status yet</td></tr></tbody></table>
  <div id="monitor_errors" class="legend"></div>
  <details id="graphbox"><summary>graph: nodes and keys</summary><img id="graph" alt="the graph's drawing"
   src="graph.svg"></details>
 </section>
</main>
<script>
"use strict";
const params = new URLSearchParams(location.search);
const client = Math.random().toString(36).slice(2);
const view = document.getElementById("view"), ctx = view.getContext("2d");
let state = null, frames = 0, lastCount = -1, img = null;

function fmt(v, d) { return (v === null || v === undefined) ? "-" : Number(v).toFixed(d); }
function esc(v) { return String(v).replace(/[&<>"]/g, c => ({"&": "&amp;", "<": "&lt;", ">": "&gt;",
                                                           '"': "&quot;"}[c])); }
function box(el) { const r = el.getBoundingClientRect();
  return {left: Math.round(r.left), top: Math.round(r.top), right: Math.round(r.right),
          bottom: Math.round(r.bottom)}; }

function probe() {
  // Where things ended up, for tests and for anyone debugging the layout from the DOM alone.
  document.body.dataset.layout = JSON.stringify({width: innerWidth, video: box(document.getElementById("video")),
    health: box(document.getElementById("nodes")), state: box(document.getElementById("state")),
    ground: box(document.getElementById("ground"))});
}

function setScreen(code, text) {
  for (const id of ["screen", "banner"]) {
    const el = document.getElementById(id); el.dataset.state = code; el.textContent = text; }
}

function sourceWidth(pv) {
  return Number(params.get("source_width")) || (state && state.source_width) || (pv && pv.width) || null;
}

function drawOverlay() {
  if (!state || !img) return;
  const pv = state.preview || {width: img.width};
  const s = pv.width / (sourceWidth(pv) || pv.width);
  const m = state.measurement;
  if (m) {
    ctx.strokeStyle = "#ec3"; ctx.setLineDash([4, 3]); ctx.fillStyle = "#ec3"; ctx.font = "11px monospace";
    for (const c of m.candidates) { ctx.strokeRect(c[0]*s, c[1]*s, c[2]*s, c[3]*s);
      ctx.fillText(c[4].toFixed(2), c[0]*s, c[1]*s - 2); }
    ctx.setLineDash([]);
  }
  const p = state.prior;
  if (p && p.initialised && p.gate) {
    // The gate ellipse as the server computed it (viewing/drawing.py, from tracking/kalman.py's gate).
    const e = p.gate;
    ctx.strokeStyle = "#3cf"; ctx.beginPath();
    ctx.ellipse(e.centre[0]*s, e.centre[1]*s, e.axes[0]*s, e.axes[1]*s, e.angle_deg * Math.PI / 180, 0, 2 * Math.PI);
    ctx.stroke();
  }
  const g = state.group;
  if (g && g.valid) {
    // The group's floor shapes projected through the groundplane camera (source pixels, scaled like boxes).
    ctx.strokeStyle = GROUP_COLOUR; ctx.lineWidth = 2;
    for (const e of g.ellipses || []) {
      if (!e.outline_px) continue;
      ctx.beginPath(); let pen = false;
      for (const q of e.outline_px) {
        if (!q) { pen = false; continue; }
        if (pen) ctx.lineTo(q[0]*s, q[1]*s); else ctx.moveTo(q[0]*s, q[1]*s);
        pen = true;
      }
      ctx.stroke();
    }
    ctx.fillStyle = "#3e3";
    for (const q of g.members_px || []) if (q) { ctx.beginPath(); ctx.arc(q[0]*s, q[1]*s, 3, 0, 2*Math.PI);
      ctx.fill(); }
    if (g.centre_px) cross(ctx, g.centre_px[0]*s, g.centre_px[1]*s, 7);
    ctx.lineWidth = 1;
  }
  const t = state.target;
  if (t && t.box) { ctx.strokeStyle = "#3e3"; ctx.lineWidth = 2;
    ctx.strokeRect(t.box[0]*s, t.box[1]*s, t.box[2]*s, t.box[3]*s); ctx.lineWidth = 1; }
}

const GROUP_COLOUR = "#f0f";

function cross(g, x, y, r) {
  g.strokeStyle = "#fff"; g.lineWidth = 2; g.beginPath();
  g.moveTo(x - r, y); g.lineTo(x + r, y); g.moveTo(x, y - r); g.lineTo(x, y + r); g.stroke();
  g.beginPath(); g.arc(x, y, r * 0.7, 0, 2 * Math.PI); g.stroke(); g.lineWidth = 1;
}

function outline(e, sigma) {
  // sigma * the extent's standard ellipse: c + sigma (sqrt(l1) cos t e1 + sqrt(l2) sin t e2), robot frame.
  const [[a, b], [, d]] = e.extent_m2, m = (a + d) / 2, r = Math.sqrt(Math.max(((a - d) / 2) ** 2 + b * b, 0));
  const l1 = m + r, l2 = Math.max(m - r, 0), ang = 0.5 * Math.atan2(2 * b, a - d);
  const e1 = [Math.cos(ang), Math.sin(ang)], e2 = [-Math.sin(ang), Math.cos(ang)], pts = [];
  for (let i = 0; i <= 48; i++) { const t = i / 48 * 2 * Math.PI;
    const u = sigma * Math.sqrt(l1) * Math.cos(t), v = sigma * Math.sqrt(l2) * Math.sin(t);
    pts.push([e.centre_m[0] + u * e1[0] + v * e2[0], e.centre_m[1] + u * e1[1] + v * e2[1]]); }
  return pts;
}

function drawGround(g) {
  // Top-down robot frame (x forward = up, y left = left), the robot at the bottom centre.
  const c = document.getElementById("ground");
  if (c.width !== c.clientWidth || c.height !== c.clientHeight) { c.width = c.clientWidth; c.height = c.clientHeight; }
  const k = c.getContext("2d"), W = c.width, H = c.height;
  k.clearRect(0, 0, W, H); k.fillStyle = "#1a1a1a"; k.fillRect(0, 0, W, H);
  const ells = (g.valid && g.ellipses) || [], shapes = ells.map(e => outline(e, g.sigma));
  const pts = [].concat(...shapes, (g.points && g.points.robot_m) || [], g.members_robot_m || [],
                        g.others_robot_m || [], g.valid ? [g.centre_robot_m] : []);
  const far = Math.min(25, Math.max(6, ...pts.map(p => p[0] + 1)));
  const side = Math.max(3, ...pts.map(p => Math.abs(p[1]) + 1));
  const ppm = Math.min((H - 28) / far, (W / 2 - 8) / side), ox = W / 2, oy = H - 14;
  const X = p => ox - p[1] * ppm, Y = p => oy - p[0] * ppm;
  k.strokeStyle = "#333"; k.fillStyle = "#777"; k.font = "11px monospace";
  for (let r = 1; r <= far; r++) { k.beginPath(); k.arc(ox, oy, r * ppm, Math.PI, 2 * Math.PI); k.stroke();
    if (r % 2 === 0) k.fillText(`${r} m`, ox + 3, oy - r * ppm + 11); }
  k.fillStyle = "#fff"; k.beginPath(); k.moveTo(ox, oy - 10); k.lineTo(ox - 6, oy + 6); k.lineTo(ox + 6, oy + 6);
  k.closePath(); k.fill();
  k.fillStyle = "#888";
  for (const p of (g.points && g.points.robot_m) || []) { k.beginPath(); k.arc(X(p), Y(p), 5, 0, 2 * Math.PI);
    k.fill(); }
  k.strokeStyle = GROUP_COLOUR; k.lineWidth = 2; k.fillStyle = GROUP_COLOUR;
  shapes.forEach((sh, i) => { k.beginPath(); sh.forEach((p, j) => j ? k.lineTo(X(p), Y(p)) : k.moveTo(X(p), Y(p)));
    k.stroke(); const cm = ells[i].centre_m;
    k.fillText(`${Math.round(ells[i].weight * 100)}%`, X(cm) + 4, Y(cm) - 4); });
  k.lineWidth = 1; k.fillStyle = "#3e3";
  for (const p of g.members_robot_m || []) { k.beginPath(); k.arc(X(p), Y(p), 3, 0, 2 * Math.PI); k.fill(); }
  k.strokeStyle = "#e55"; k.lineWidth = 2;
  for (const p of g.others_robot_m || []) { k.beginPath(); k.moveTo(X(p) - 4, Y(p) - 4); k.lineTo(X(p) + 4, Y(p) + 4);
    k.moveTo(X(p) + 4, Y(p) - 4); k.lineTo(X(p) - 4, Y(p) + 4); k.stroke(); }
  if (g.valid) {
    const cp = g.centre_robot_m;
    k.strokeStyle = "#aaa"; k.lineWidth = 1; k.setLineDash([4, 4]); k.beginPath(); k.moveTo(ox, oy);
    k.lineTo(X(cp), Y(cp)); k.stroke(); k.setLineDash([]);
    cross(k, X(cp), Y(cp), 8);
  }
  k.fillStyle = "#aaa";
  k.fillText(g.valid ? `frame ${g.frame_seq}${g.lost ? " LOST (predicted)" : ""}` : "no group yet", 6, 14);
  // What was drawn, for tests and for debugging from the DOM alone.
  c.dataset.drawn = JSON.stringify({frame_seq: g.frame_seq, ellipses: shapes.length,
    members: (g.members_robot_m || []).length, others: (g.others_robot_m || []).length, metres_per_px: 1 / ppm});
}

async function pollPreview() {
  // One request at a time: a slow link gets fewer, always fresh, frames.
  for (;;) {
    try {
      const r = await fetch(`/preview.jpg?after=${lastCount}&client=${client}`, {cache: "no-store"});
      if (r.status === 200) {
        lastCount = Number(r.headers.get("X-Preview-Count"));
        const bmp = await createImageBitmap(await r.blob());
        if (view.width !== bmp.width || view.height !== bmp.height) { view.width = bmp.width;
          view.height = bmp.height; }
        img = bmp; ctx.drawImage(bmp, 0, 0); drawOverlay();
        frames += 1;
        document.getElementById("frames").textContent = `frames: ${frames} (seq ${r.headers.get("X-Frame-Seq")})`;
      } else { await new Promise(res => setTimeout(res, 300)); }
    } catch (e) { await new Promise(res => setTimeout(res, 1000)); }
  }
}

function timeAxis(g, w, h) {
  // Seconds before now along the bottom: a tick every 15 s, "now" at the right end of the curve.
  g.strokeStyle = "#444"; g.fillStyle = "#888"; g.font = "10px monospace";
  g.beginPath(); g.moveTo(0, h - 12); g.lineTo(w, h - 12); g.stroke();
  for (const ago of [60, 45, 30, 15, 0]) {
    const x = (60 - ago) / 60 * w;
    g.beginPath(); g.moveTo(x, h - 12); g.lineTo(x, h - 9); g.stroke();
    const text = ago ? `-${ago} s` : "now";
    g.fillText(text, Math.min(Math.max(x - text.length * 3, 0), w - text.length * 6), h - 1);
  }
  g.fillStyle = "#aaa"; g.font = "11px monospace";
}

function plot(id, series, label, unit) {
  const c = document.getElementById(id), now = Date.now() / 1000;
  if (c.width !== c.clientWidth || c.height !== c.clientHeight) { c.width = c.clientWidth; c.height = c.clientHeight; }
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height); g.fillStyle = "#1a1a1a"; g.fillRect(0, 0, c.width, c.height);
  const pts = series.filter(p => p[0] > now - 60);
  const last = pts.length ? pts[pts.length - 1][1] : null;
  g.fillStyle = "#aaa"; g.font = "11px monospace";
  g.fillText(`${label}: ${last === null ? "-" : last.toPrecision(3)} ${unit} (last 60 s)`, 4, 12);
  timeAxis(g, c.width - 64, c.height);
  if (pts.length < 2) return;
  let lo = Math.min(...pts.map(p => p[1])), hi = Math.max(...pts.map(p => p[1]));
  if (hi - lo < 1e-9) { hi += 1e-3; lo -= 1e-3; }
  // The curve keeps clear of the right margin, where the scale is written.
  const w = c.width - 64;
  g.fillText(hi.toPrecision(3), w + 6, 12); g.fillText(lo.toPrecision(3), w + 6, c.height - 14);
  g.strokeStyle = "#6cf"; g.beginPath();
  pts.forEach((p, i) => { const x = (p[0] - (now - 60)) / 60 * w;
    const y = c.height - 16 - (p[1] - lo) / (hi - lo) * (c.height - 32);
    if (i) g.lineTo(x, y); else g.moveTo(x, y); });
  g.stroke();
}

function healthTable(rows) {
  const body = document.querySelector("#nodes tbody");
  if (!rows.length) {
    body.innerHTML = '<tr><td class="l na" colspan="9">no node seen yet</td></tr>'; return; }
  const span = {};
  for (const r of rows) span[r.node] = (span[r.node] || 0) + 1;
  const html = [];
  let prev = null;
  for (const r of rows) {
    const first = r.node !== prev; prev = r.node;
    let tr = `<tr${first ? ' class="first"' : ""} data-node="${esc(r.node)}">`;
    if (first) {
      const n = span[r.node];
      tr += `<td class="l" rowspan="${n}" title="pid ${r.pid ?? "-"}">${esc(r.node)}</td>` +
        `<td class="l ${esc(r.state)}" rowspan="${n}">${r.state === "down" ? "DOWN" : esc(r.state)}</td>` +
        `<td rowspan="${n}">${r.restarts}</td>`;
    }
    const na = '<td class="na">-</td>';
    if (r.topic === null) { tr += '<td class="l na" colspan="6">no status</td></tr>'; html.push(tr); continue; }
    tr += `<td class="l topic"><span class="dir">${r.direction}</span> ${esc(r.topic)}</td>` +
      `<td>${fmt(r.rate_hz, 1)}</td>` +
      (r.direction === "in" ? `<td>${fmt(r.latency_p50_ms, 1)}</td><td>${r.drops}</td><td>${r.lost}</td>`
        : na + na + na) +
      `<td>${r.decode_errors}</td></tr>`;
    html.push(tr);
  }
  body.innerHTML = html.join("");
}

function render() {
  const s = state, link = document.getElementById("link");
  link.textContent = s.connected ? `connected to ${s.endpoints.join(", ")}` : `watching ${s.endpoints.join(", ")}`;
  link.className = s.connected ? "" : "bad";
  setScreen(s.screen.code, s.screen.text);
  const srcw = sourceWidth(s.preview);
  document.getElementById("srcw").textContent = srcw ? `source width ${srcw} px` : "source width not known yet";
  const t = s.target, c = s.command, g = s.group, ages = s.ages || {}, staleS = s.stale_after_s || 2;
  // Every value carries its age; past stale_after_s it is struck through and labelled stale (never shown as live).
  const aged = (text, age) => typeof age !== "number" ? esc(text)
    : age > staleS ? `<span class="stale">${esc(text)}</span> <span class="stalelabel">STALE ${age.toFixed(0)} s</span>`
    : `${esc(text)} <span class="age">${age.toFixed(1)} s</span>`;
  document.getElementById("groundbox").hidden = !g;  // the person graph has no group: no panel
  if (g) { document.getElementById("gsigma").textContent = g.sigma; drawGround(g); }
  const lines = [
    ...(!g ? [] : (!g.valid ? [`group (none yet) frame ${g.frame_seq}`] : [
      `group ${g.lost ? "LOST " : ""}frame ${g.frame_seq}: ${g.members} members, ${g.others} left out, ` +
        `${(g.ellipses || []).length} ellipses`,
      `  centre ${fmt(g.centre_robot_m[0], 2)} m ahead ${fmt(g.centre_robot_m[1], 2)} m left, ` +
        `${fmt(g.speed_mps, 2)} m/s, tracker ${fmt(g.step_ms, 1)} ms/frame`]).map(line => esc(line))),
    aged(t ? `target ${t.state} frame ${t.frame_seq} box [${t.box ? t.box.map(v => v.toFixed(0)).join(", ") : "-"}]`
      : "target (no track yet)", t && ages.track),
    aged(`velocity ${t ? t.velocity.join(", ") : "-"} px/s  centre error ${fmt(s.centre_error_px, 1)} px`,
      t && ages.track),
    aged(`eta_k ${fmt(s.eta, 4)}  m_fuse ${s.measurement ? fmt(s.measurement.m_fuse, 3) : "-"}`,
      s.eta !== null && s.eta !== undefined && ages.template),
    aged(c ? `motor vx ${fmt(c.vx_mps, 2)} m/s wz ${fmt(c.wz_radps, 2)} rad/s [${c.reason}]` +
        ` latency ${fmt(c.latency_ms, 1)} ms`
      : "motor (no command yet)", c && ages.command),
  ];
  document.getElementById("state").innerHTML = lines.join("\\n");
  healthTable(s.health);
  document.getElementById("monitor_errors").textContent =
    s.decode_errors ? `monitor decode errors: ${s.decode_errors}` : "";
  plot("p_err", s.history.centre_error_px, "centre error", "px");
  plot("p_eta", s.history.eta, "eta_k", "");
  plot("p_lat", s.history.latency_ms, "capture->command latency", "ms");
  probe();
}

async function pollState() {
  for (;;) {
    try {
      const r = await fetch("/state.json", {cache: "no-store"});
      if (r.status !== 200) throw new Error(`HTTP ${r.status}`);
      state = await r.json(); render();
    } catch (e) {
      setScreen("server", `monitor server unreachable (${e.message})`); }
    await new Promise(res => setTimeout(res, 500));
  }
}
addEventListener("resize", probe);
probe(); pollState(); pollPreview();
</script></body></html>
"""
