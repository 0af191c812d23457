"""``followbus monitor --web``: the monitor as a web page served from the laptop.

The server holds one :class:`~followbus.tools.monitor.BusMonitor` (a Zenoh client that only subscribes: the
latest JPEG preview, never raw frames, plus a bounded history). HTTP handlers only read that state, so however
slow a browser or the Wi-Fi is, nothing flows back to the robot. Each browser fetches one preview at a time
(the next request goes out when the previous image has loaded) and the server serves at most
``MAX_PREVIEWS_PER_S`` per client, always the newest frame: a slow client simply sees fewer frames.

Endpoints: ``/`` (the page), ``/state.json`` (snapshot with history), ``/preview.jpg?after=N&client=ID``
(long-polls up to 1 s for a preview newer than N, or for the first one; 204 if none came), ``/healthz``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs, urlparse

from followbus.bus.session import ZenohSettings
from followbus.tools.introspect import wait_for
from followbus.tools.monitor import BusMonitor, GraphInfo

log = logging.getLogger("followbus.webview")

MAX_PREVIEWS_PER_S = 10.0
LONG_POLL_S = 1.0


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


def make_handler(monitor: BusMonitor, gate: PreviewGate) -> type[BaseHTTPRequestHandler]:
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

        def do_GET(self) -> None:  # noqa: N802 (http.server API)
            url = urlparse(self.path)
            query = parse_qs(url.query)
            try:
                if url.path in ("/", "/index.html"):
                    self._send(200, PAGE.encode(), "text/html; charset=utf-8")
                elif url.path == "/state.json":
                    self._send(200, json.dumps(monitor.snapshot()).encode(), "application/json")
                elif url.path == "/preview.jpg":
                    self._preview(query)
                elif url.path == "/healthz":
                    self._send(200, b"ok\n", "text/plain")
                else:
                    self._send(404, b"not found\n", "text/plain")
            except (BrokenPipeError, ConnectionResetError):
                pass  # the browser went away

        def _preview(self, query: dict[str, list[str]]) -> None:
            client = query.get("client", [self.client_address[0]])[0][:64]
            after = int(query.get("after", ["-1"])[0] or -1)
            gate.pace(client)
            deadline = time.monotonic() + LONG_POLL_S
            with gate.cond:
                # count 0 = nothing received yet: "after -1" still waits for the first preview
                while monitor.preview_count <= max(after, 0) and time.monotonic() < deadline:
                    gate.cond.wait(max(0.0, deadline - time.monotonic()))
            with monitor.lock:
                jpeg, count = monitor.preview_jpeg, monitor.preview_count
                seq = monitor.preview.header.frame_seq if monitor.preview is not None else -1
            if not jpeg:
                self._send(204, b"", "image/jpeg", {"X-Preview-Count": str(count)})
                return
            self._send(200, jpeg, "image/jpeg", {"X-Preview-Count": str(count), "X-Frame-Seq": str(seq)})

    return Handler


def start_server(settings: ZenohSettings, info: GraphInfo, bind: str, port: int
                 ) -> tuple[ThreadingHTTPServer, BusMonitor, threading.Thread]:
    """Start the bus monitor and the HTTP server (in a thread); the caller shuts both down."""
    gate = PreviewGate()
    monitor = BusMonitor(settings, info, preview=True, on_preview=gate.notify).start()
    server = ThreadingHTTPServer((bind, port), make_handler(monitor, gate))
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, name="webview-http", daemon=True)
    thread.start()
    return server, monitor, thread


def serve(settings: ZenohSettings, info: GraphInfo, bind: str, port: int, seconds: float | None = None) -> int:
    server, monitor, thread = start_server(settings, info, bind, port)
    host, real_port = server.server_address[:2]
    print(f"followbus monitor: web view on http://{host}:{real_port}/ (watching {', '.join(settings.connect)}; "
          "Ctrl-C to stop)", flush=True)
    try:
        wait_for(seconds)
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=2)
        monitor.close()
    return 0


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>followbus monitor</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font:14px system-ui,sans-serif;margin:12px;background:#111;color:#ddd}
h1{font-size:16px;margin:0 0 8px} .row{display:flex;flex-wrap:wrap;gap:12px}
canvas{background:#000;border:1px solid #333} table{border-collapse:collapse;font-size:12px}
td,th{border-bottom:1px solid #333;padding:2px 6px;text-align:right} td:first-child,th:first-child{text-align:left}
.up{color:#6c6} .down{color:#e55} #link.bad{color:#e55} .plot{display:block;margin-bottom:6px}
#state{font:13px monospace;white-space:pre}
</style></head><body>
<h1>followbus monitor <span id="link">connecting...</span></h1>
<div class="row">
 <div><canvas id="view" width="640" height="480"></canvas>
  <div id="frames">frames: 0</div>
  <div style="font-size:12px;color:#888">green: target box, cyan: gate ellipse (prior, chi2), yellow: candidates.
   Boxes are scaled
   by preview width / source width (<span id="srcw"></span> px; override with ?source_width=N).</div></div>
 <div><div id="state">no state yet</div>
  <canvas class="plot" id="p_err" width="420" height="110"></canvas>
  <canvas class="plot" id="p_eta" width="420" height="110"></canvas>
  <canvas class="plot" id="p_lat" width="420" height="110"></canvas>
  <table id="nodes"><thead><tr><th>node</th><th>state</th><th>restarts</th><th>pid</th><th>out Hz</th>
   <th>in p50 ms</th><th>drops</th><th>dec err</th></tr></thead><tbody></tbody></table></div>
</div>
<script>
"use strict";
const params = new URLSearchParams(location.search);
const client = Math.random().toString(36).slice(2);
const view = document.getElementById("view"), ctx = view.getContext("2d");
let state = null, frames = 0, lastCount = -1, img = null;

function fmt(v, d) { return (v === null || v === undefined) ? "-" : Number(v).toFixed(d); }

function drawOverlay() {
  if (!state || !img) return;
  const pv = state.preview || {width: img.width};
  const srcw = Number(params.get("source_width")) || state.source_width || pv.width;
  document.getElementById("srcw").textContent = srcw;
  const s = pv.width / srcw;
  const m = state.measurement;
  if (m) {
    ctx.strokeStyle = "#ec3"; ctx.setLineDash([4, 3]); ctx.fillStyle = "#ec3"; ctx.font = "11px monospace";
    for (const c of m.candidates) { ctx.strokeRect(c[0]*s, c[1]*s, c[2]*s, c[3]*s);
      ctx.fillText(c[4].toFixed(2), c[0]*s, c[1]*s - 2); }
    ctx.setLineDash([]);
  }
  const p = state.prior;
  if (p && p.initialised) {
    // Gate: {z : (z-c)^T S^-1 (z-c) <= chi2}; axes sqrt(chi2*lambda_i) along S's eigenvectors.
    const [a, b, , d] = [p.innovation_cov[0][0], p.innovation_cov[0][1], p.innovation_cov[1][0],
                         p.innovation_cov[1][1]];
    const tr = (a + d) / 2, det = Math.sqrt(Math.max(((a - d) / 2) ** 2 + b * b, 0));
    const l1 = tr + det, l2 = Math.max(tr - det, 0), ang = 0.5 * Math.atan2(2 * b, a - d);
    ctx.strokeStyle = "#3cf"; ctx.beginPath();
    ctx.ellipse(p.centre[0]*s, p.centre[1]*s, Math.sqrt(p.gate_chi2*l1)*s, Math.sqrt(p.gate_chi2*l2)*s, ang,
                0, 2 * Math.PI);
    ctx.stroke();
  }
  const t = state.target;
  if (t && t.box) { ctx.strokeStyle = "#3e3"; ctx.lineWidth = 2;
    ctx.strokeRect(t.box[0]*s, t.box[1]*s, t.box[2]*s, t.box[3]*s); ctx.lineWidth = 1; }
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

function plot(id, series, label, unit) {
  const c = document.getElementById(id), g = c.getContext("2d"), now = Date.now() / 1000;
  g.clearRect(0, 0, c.width, c.height); g.fillStyle = "#1a1a1a"; g.fillRect(0, 0, c.width, c.height);
  const pts = series.filter(p => p[0] > now - 60);
  const last = pts.length ? pts[pts.length - 1][1] : null;
  g.fillStyle = "#aaa"; g.font = "11px monospace";
  g.fillText(`${label}: ${last === null ? "-" : last.toPrecision(3)} ${unit} (last 60 s)`, 4, 12);
  if (pts.length < 2) return;
  let lo = Math.min(...pts.map(p => p[1])), hi = Math.max(...pts.map(p => p[1]));
  if (hi - lo < 1e-9) { hi += 1e-3; lo -= 1e-3; }
  g.fillText(hi.toPrecision(3), c.width - 60, 12); g.fillText(lo.toPrecision(3), c.width - 60, c.height - 3);
  g.strokeStyle = "#6cf"; g.beginPath();
  pts.forEach((p, i) => { const x = (p[0] - (now - 60)) / 60 * c.width;
    const y = c.height - 4 - (p[1] - lo) / (hi - lo) * (c.height - 20);
    if (i) g.lineTo(x, y); else g.moveTo(x, y); });
  g.stroke();
}

function render() {
  const s = state, link = document.getElementById("link");
  link.textContent = s.connected ? `connected to ${s.endpoints.join(", ")}` :
    `robot unreachable since ${new Date(s.unreachable_since_ns / 1e6).toLocaleTimeString()}`;
  link.className = s.connected ? "" : "bad";
  const t = s.target, c = s.command;
  const lines = [
    t ? `target ${t.state} frame ${t.frame_seq} box [${t.box ? t.box.map(v => v.toFixed(0)).join(", ") : "-"}]`
      : "target (no track yet)",
    `velocity ${t ? t.velocity.join(", ") : "-"} px/s  centre error ${fmt(s.centre_error_px, 1)} px`,
    `eta_k ${fmt(s.eta, 4)}  m_fuse ${s.measurement ? fmt(s.measurement.m_fuse, 3) : "-"}`,
    c ? `motor vx ${fmt(c.vx_mps, 2)} m/s wz ${fmt(c.wz_radps, 2)} rad/s [${c.reason}]` +
        ` latency ${fmt(c.latency_ms, 1)} ms`
      : "motor (no command yet)",
  ];
  document.getElementById("state").textContent = lines.join("\\n");
  const body = document.querySelector("#nodes tbody"); body.innerHTML = "";
  for (const n of s.nodes) {
    const topics = Object.values(n.topics || {});
    const out = topics.filter(x => x.direction === "out").map(x => fmt(x.rate_hz, 1)).join(" ");
    const inn = topics.filter(x => x.direction === "in").map(x => fmt(x.latency_p50_ms, 1)).join(" ");
    const drops = topics.reduce((a, x) => a + (x.drops || 0), 0);
    const dec = topics.reduce((a, x) => a + (x.decode_errors || 0), 0);
    const tr = document.createElement("tr");
    tr.innerHTML = `<td>${n.name}</td><td class="${n.alive ? "up" : "down"}">${n.alive ? "up" : "DOWN"}</td>` +
      `<td>${n.restarts}</td><td>${n.pid ?? "-"}</td><td>${out || "-"}</td><td>${inn || "-"}</td>` +
      `<td>${drops}</td><td>${dec}</td>`;
    body.appendChild(tr);
  }
  plot("p_err", s.history.centre_error_px, "centre error", "px");
  plot("p_eta", s.history.eta, "eta_k", "");
  plot("p_lat", s.history.latency_ms, "capture->command latency", "ms");
}

async function pollState() {
  for (;;) {
    try { state = await (await fetch("/state.json", {cache: "no-store"})).json(); render(); }
    catch (e) { document.getElementById("link").textContent = "monitor server unreachable"; }
    await new Promise(res => setTimeout(res, 500));
  }
}
pollState(); pollPreview();
</script></body></html>
"""
