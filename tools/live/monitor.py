"""``followbus monitor``: a read-only view of a running graph from another machine.

:class:`BusMonitor` joins the robot's bus as a Zenoh *client* and keeps the latest state: node health from
liveliness tokens and NodeStatus, the target (Track/Prior/Measurement), eta_k (Template), the motor command,
the followed group of a group graph (GroupState, placed with the pose of its frame's GroundPoints),
and one minute of history (eta_k, end-to-end latency, centre error against ground truth). It only ever
subscribes, never to raw frames, and its callbacks only copy small objects under a lock, so the robot never
waits on the laptop. When the robot disappears it says since when, and it reopens the session until the robot
is back. The terminal dashboard (this module) and the web view (``webview.py``) render its snapshots.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from ...bus.codec import DecodeError
from ...bus.health import HealthWatcher, live_namespaces, namespaces_hint
from ...bus.pubsub import declare_subscriber, frame_bytes
from ...bus.schemas import Frame, Message, NodeStatus, decode
from ...bus.session import ZenohSettings, open_session
from ...msgs.group import GroundPoints, GroupState
from ...msgs.perception import GroundTruth
from ...msgs.robot import MotorCommand
from ...msgs.tracking import Measurement, Prior, Template, Track
from ...tracking.groundplane import CameraGeometry, floor_to_image, rotation, to_robot_frame

log = logging.getLogger("followbus.monitor")

HISTORY_S = 60.0
NAMESPACES_AFTER_S = 2.0  # connected this long without a node of our namespace: look for other namespaces
NAMESPACES_EVERY_S = 5.0
VALUE_STALE_S = 2.0  # a target, eta or command older than this is shown struck through and labelled stale
REOPEN_AFTER_S = 5.0  # unreachable this long: close the session and open a fresh one
# Which output carries what, and the node that publishes it in graph.yaml (overridden from --graph).
WATCHED = {"track": ("prediction", Track), "prior": ("prediction", Prior), "measurement": ("reid", Measurement),
           "template": ("template", Template), "command": ("motor", MotorCommand),
           "ground_truth": ("capture", GroundTruth),
           # group following (graph.group.yaml, seed 004): absent in the person graph, then nothing is shown
           "group": ("group", GroupState), "points": ("groundplane", GroundPoints)}
PREVIEW = ("capture", "preview")
DEFAULT_SOURCE_WIDTH = 640
RATE_SETTLE_S = 2.0
GROUP_SIGMA = 2.0  # the web view draws each group ellipse at 2 standard deviations of its extent (~86 % of members)
SEPARATOR = "=" * 72  # between snapshots when stdout is not a terminal


def monitor_settings(graph_path: str | None, connect: list[str] | None, user: str | None = None,
                     password: str | None = None, ca: str | None = None) -> ZenohSettings:
    """Client settings for a viewer on the laptop (tools/connect.py client_settings, the one builder)."""
    from ..connect import client_settings

    return client_settings(graph_path, connect, user, password, ca, viewer=True)


@dataclass
class GraphInfo:
    """What the monitor takes from the graph file (if any): namespace, node names, keys, the source width."""

    namespace: str = "fb"
    nodes: list[str] = field(default_factory=list)
    keys: dict[str, str] = field(default_factory=dict)  # watched output name -> bus key
    preview_key: str = ""
    source_width: int = DEFAULT_SOURCE_WIDTH
    camera: CameraGeometry | None = None  # the groundplane node's camera: group shapes drawn into the video
    graph_svg: str = ""  # the graph's drawing (bus/graph_drawing.py), shown by the web view

    @classmethod
    def load(cls, graph_path: str | None, namespace: str | None = None) -> GraphInfo:
        info = cls()
        owners = {out: node for out, (node, _) in WATCHED.items()}
        preview_owner = PREVIEW[0]
        if graph_path and Path(graph_path).exists():
            from ...bus.graph_drawing import to_svg
            from ..command import load_graph

            graph = load_graph(graph_path)
            info.namespace = graph.namespace
            info.nodes = list(graph.nodes)
            info.graph_svg = to_svg(graph)
            for name, spec in graph.nodes.items():
                outputs = list(spec.outputs)
                for out in owners:
                    if out in outputs:
                        owners[out] = name
                if "preview" in outputs:
                    preview_owner = name
                # The motor controller's image width is the frame width the boxes live in.
                width = (spec.params or {}).get("image_width_px")
                if isinstance(width, (int, float)) and width > 0:
                    info.source_width = int(width)
                if "points" in outputs:
                    info.camera = _camera(spec.params or {})
        if namespace:
            info.namespace = namespace
        info.keys = {out: f"{info.namespace}/{node}/{out}" for out, node in owners.items()}
        info.preview_key = f"{info.namespace}/{preview_owner}/preview"
        return info


def _camera(params: dict[str, Any]) -> CameraGeometry | None:
    known = {f.name for f in fields(CameraGeometry)}
    try:
        return CameraGeometry(**{k: v for k, v in params.items() if k in known})
    except (TypeError, ValueError) as exc:  # the node itself will refuse it; the view just draws no projection
        log.warning("groundplane camera not usable for the video overlay: %s", exc)
        return None


@dataclass
class NodeView:
    name: str
    alive: bool = False
    since_ns: int = 0
    ups: int = 0
    pids: list[int] = field(default_factory=list)
    status: NodeStatus | None = None
    status_ns: int = 0
    trust: str = "unverified"  # bus.health: verified / unverified / spoofed? (token vs launcher's process table)
    trust_reason: str = ""

    @property
    def restarts(self) -> int:
        # Distinct pids are the honest count across our own reconnects (a re-subscription replays tokens).
        return max(len(self.pids) - 1, 0) if self.pids else max(self.ups - 1, 0)


def _box(value: Any) -> list[float] | None:
    return None if value is None else [round(float(v), 1) for v in np.asarray(value).reshape(-1)[:4]]


def _centre(box: Any) -> tuple[float, float]:
    b = np.asarray(box, dtype=float).reshape(-1)
    return float(b[0] + b[2] / 2), float(b[1] + b[3] / 2)


def _rounded(a: Any, nd: int = 3) -> list:
    return np.round(np.asarray(a, dtype=float), nd).tolist()



def ellipse_outline(centre: np.ndarray, extent: np.ndarray, n: int = 32) -> np.ndarray:
    """GROUP_SIGMA times the extent's standard ellipse {c + L u : |u| = 1}, L Lᵀ = extent, as n floor points."""
    w, v = np.linalg.eigh(0.5 * (extent + extent.T))
    axes = v * (GROUP_SIGMA * np.sqrt(np.clip(w, 0.0, None)))
    t = np.linspace(0.0, 2 * math.pi, n)
    return centre + np.stack([np.cos(t), np.sin(t)], axis=1) @ axes.T


def _pixels(points_m: np.ndarray, camera: CameraGeometry | None) -> list | None:
    if camera is None:
        return None
    uv = floor_to_image(points_m, camera)
    return [None if not np.isfinite(p).all() else [round(float(p[0]), 1), round(float(p[1]), 1)] for p in uv]


def group_view(group: GroupState, pose: tuple[float, float, float] | None, points: GroundPoints | None,
               camera: CameraGeometry | None = None) -> dict[str, Any]:
    """The followed group in the robot frame (x forward, y left; the robot at the origin), for the web view,
    and with ``camera`` (the groundplane node's geometry) its floor shapes in image pixels too.

    GroupState is in the odometry frame; the pose of the same frame's GroundPoints (by frame_seq) takes it into
    the robot frame (inverse of seed 004 Eq. 4: p_r = Rᵀ(p − t), extents Rᵀ X R). Without that pose (its points
    not received) the shape is not placed: only the centre, which the group node gives in the robot frame."""
    out: dict[str, Any] = {"frame_seq": group.header.frame_seq, "valid": bool(group.valid), "lost": bool(group.lost),
                           "step_ms": round(float(group.step_ms), 2), "posed": pose is not None,
                           "sigma": GROUP_SIGMA}
    if points is not None:  # the latest detections on the floor, whatever the tracker made of them
        out["points"] = {"frame_seq": points.header.frame_seq, "robot_m": _rounded(points.points_robot_m)}
    if not group.valid:
        return out
    centre = np.asarray(group.centre_robot_m, dtype=float).reshape(2)
    out.update(centre_robot_m=_rounded(centre), speed_mps=round(float(np.hypot(*group.velocity_mps)), 3),
               members=int(len(group.members_m)), others=int(len(group.others_m)))
    out["centre_px"] = (_pixels(centre, camera) or [None])[0]
    if pose is None:
        return out
    x, y, theta = pose
    rot = rotation(theta)
    ellipses = []
    for m, ext, w in zip(group.ellipse_centres_m, group.ellipse_extents_m2, group.ellipse_weights, strict=True):
        c_r, ext_r = to_robot_frame(m, x, y, theta)[0], rot.T @ ext @ rot
        ellipses.append({"centre_m": _rounded(c_r), "extent_m2": _rounded(ext_r, 4), "weight": round(float(w), 4),
                         "outline_px": _pixels(ellipse_outline(c_r, ext_r), camera)})
    out["ellipses"] = ellipses
    out["members_robot_m"] = _rounded(to_robot_frame(group.members_m, x, y, theta))
    out["others_robot_m"] = _rounded(to_robot_frame(group.others_m, x, y, theta))
    out["members_px"] = _pixels(to_robot_frame(group.members_m, x, y, theta), camera)
    out["orientation_robot_rad"] = round(float(group.orientation_rad - theta), 4)
    return out


class BusMonitor:
    """Subscribes to the robot's bus (reopening the session as needed) and keeps a bounded state."""

    def __init__(self, settings: ZenohSettings, info: GraphInfo, *, preview: bool = False,
                 history_s: float = HISTORY_S, reopen_after_s: float = REOPEN_AFTER_S,
                 on_preview: Callable[[], None] | None = None):
        self.settings = settings
        self.info = info
        self.want_preview = preview
        self.history_s = history_s
        self.reopen_after_s = reopen_after_s
        self.on_preview = on_preview
        self.lock = threading.Lock()
        self.stop_event = threading.Event()
        self.nodes: dict[str, NodeView] = {n: NodeView(n) for n in info.nodes}
        self.latest: dict[str, Message] = {}
        self.received_ns: dict[str, int] = {}  # when each latest message arrived: its age on screen
        self.received: dict[str, int] = {}
        self.decode_errors = 0
        self.preview: Frame | None = None
        self.preview_jpeg = b""
        self.preview_count = 0
        self.preview_received_ns = 0  # receive time: the web view tells a frozen preview from a live one
        self.connected = False
        self.ever_connected = False
        self.unreachable_since_ns = time.time_ns()
        self.sessions_opened = 0
        self.last_error = ""
        self.namespaces_hint = ""  # no node of ours: the namespaces that have some (_look_elsewhere)
        self._next_namespace_look = time.monotonic() + NAMESPACES_AFTER_S
        self._tracks: dict[int, Track] = {}
        self._truth: dict[int, GroundTruth] = {}
        self._poses: dict[int, tuple[float, float, float]] = {}  # frame_seq -> robot pose of that frame's points
        self.history: dict[str, deque[tuple[float, float]]] = {
            "eta": deque(maxlen=4000), "latency_ms": deque(maxlen=4000), "centre_error_px": deque(maxlen=4000)}
        self._session: zenoh.Session | None = None
        self._watcher: HealthWatcher | None = None
        self._subs: list[Any] = []
        self._thread = threading.Thread(target=self._run, name="monitor-session", daemon=True)

    # -- session lifecycle -------------------------------------------------------------------------
    def start(self) -> BusMonitor:
        self._thread.start()
        return self

    def close(self) -> None:
        self.stop_event.set()
        self._thread.join(timeout=10)
        self._close_session()

    def _open(self) -> None:
        session = open_session(self.settings)
        self.sessions_opened += 1
        self._session = session
        self._watcher = HealthWatcher(session, self.info.namespace, on_change=self._on_health)
        for name, key in self.info.keys.items():
            self._subs.append(declare_subscriber(session, key, self._make_handler(name)))
        if self.want_preview:
            self._subs.append(declare_subscriber(session, self.info.preview_key, self._on_preview))

    def _close_session(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subs = []
        if self._watcher is not None:
            self._watcher.close()
            self._watcher = None
        if self._session is not None:
            with contextlib.suppress(Exception):
                self._session.close()
            self._session = None

    def _reachable(self) -> bool:
        if self._session is None:
            return False
        try:
            info = self._session.info
            return bool(list(info.routers_zid()) or list(info.peers_zid()))
        except Exception:  # a closed or broken session
            return False

    def _set_connected(self, connected: bool) -> None:
        with self.lock:
            if connected == self.connected:
                return
            self.connected = connected
            if connected:
                self.ever_connected = True
                log.info("connected to %s", ", ".join(self.settings.connect))
            else:
                self.unreachable_since_ns = time.time_ns()
                # Liveliness cannot be trusted through a broken link: show every node as down since now.
                for node in self.nodes.values():
                    if node.alive:
                        node.alive = False
                        node.since_ns = self.unreachable_since_ns
                log.warning("robot unreachable (%s)", ", ".join(self.settings.connect))

    def _run(self) -> None:
        lost_at: float | None = None
        while not self.stop_event.is_set():
            if self._session is None:
                try:
                    self._open()
                    lost_at = None
                except Exception as exc:  # router not up yet, refused credentials, ...
                    self.last_error = str(exc).split(" at ")[0]
                    log.debug("open failed: %s", exc)
                    self._close_session()
                    self._set_connected(False)
                    self.stop_event.wait(0.5)
                    continue
            reachable = self._reachable()
            self._set_connected(reachable)
            if reachable:
                lost_at = None
                self._look_elsewhere()
            else:
                lost_at = lost_at or time.monotonic()
                # Zenoh clients reconnect by themselves; reopening is the fallback if that never happens.
                if time.monotonic() - lost_at > self.reopen_after_s:
                    log.info("reopening the session")
                    self._close_session()
                    continue
            self.stop_event.wait(0.25)

    def _look_elsewhere(self) -> None:
        """No node alive in our namespace a while after connecting: find the namespaces that have some (every
        NAMESPACES_EVERY_S, on this session thread; the hint goes away once a node of ours shows up)."""
        with self.lock:
            ours = any(n.alive for n in self.nodes.values())
        now = time.monotonic()
        if ours:
            self.namespaces_hint = ""
            return
        if now < self._next_namespace_look or self._session is None:
            return
        self._next_namespace_look = now + NAMESPACES_EVERY_S
        found = live_namespaces(self._session)
        with self.lock:
            ours = any(n.alive for n in self.nodes.values())
            self.namespaces_hint = "" if ours else namespaces_hint(self.info.namespace, found)

    # -- callbacks (zenoh threads: copy and return) ------------------------------------------------
    def _on_health(self, name: str, alive: bool) -> None:
        with self.lock:
            node = self.nodes.setdefault(name, NodeView(name))
            if node.alive != alive or not node.since_ns:
                node.alive = alive
                node.since_ns = time.time_ns()
                if alive:
                    node.ups += 1

    def _make_handler(self, name: str) -> Callable[[zenoh.Sample], None]:
        def handler(sample: zenoh.Sample) -> None:
            try:
                msg = decode(frame_bytes(sample), WATCHED[name][1])
            except DecodeError as exc:
                with self.lock:
                    self.decode_errors += 1
                log.debug("decode error on %s: %s", sample.key_expr, exc)
                return
            self._on_message(name, msg)

        return handler

    def _on_message(self, name: str, msg: Message) -> None:
        now = time.time()
        with self.lock:
            self.latest[name] = msg
            self.received_ns[name] = time.time_ns()
            self.received[name] = self.received.get(name, 0) + 1
            if isinstance(msg, Template) and msg.initialised:
                self.history["eta"].append((now, float(msg.eta)))
            elif isinstance(msg, MotorCommand) and msg.header.stamp_ns > 0 and msg.header.pub_ns > 0:
                self.history["latency_ms"].append((now, (msg.header.pub_ns - msg.header.stamp_ns) / 1e6))
            elif isinstance(msg, Track):
                self._tracks[msg.header.frame_seq] = msg
                self._centre_error(msg.header.frame_seq, now)
            elif isinstance(msg, GroundTruth) and msg.available:
                self._truth[msg.header.frame_seq] = msg
                self._centre_error(msg.header.frame_seq, now)
            elif isinstance(msg, GroundPoints):
                self._poses[msg.header.frame_seq] = (msg.robot_x_m, msg.robot_y_m, msg.robot_theta_rad)
            for cache in (self._tracks, self._truth, self._poses):
                while len(cache) > 256:
                    cache.pop(next(iter(cache)))
            self._trim(now)

    def _centre_error(self, seq: int, now: float) -> None:
        track, truth = self._tracks.get(seq), self._truth.get(seq)
        if track is None or truth is None or track.box is None or truth.box is None:
            return
        (tx, ty), (gx, gy) = _centre(track.box), _centre(truth.box)
        self.history["centre_error_px"].append((now, math.hypot(tx - gx, ty - gy)))

    def _trim(self, now: float) -> None:
        horizon = now - self.history_s
        for series in self.history.values():
            while series and series[0][0] < horizon:
                series.popleft()

    def _on_preview(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(frame_bytes(sample), Frame)
        except DecodeError:
            with self.lock:
                self.decode_errors += 1
            return
        if msg.encoding != "jpeg":  # never accept raw frames on this path
            return
        with self.lock:
            self.preview = msg
            self.preview_jpeg = msg.data.tobytes()
            self.preview_count += 1
            self.preview_received_ns = time.time_ns()
        if self.on_preview is not None:
            self.on_preview()

    # -- snapshot ---------------------------------------------------------------------------------
    def _merge_status(self) -> None:
        watcher = self._watcher
        if watcher is None:
            return
        for name, health in watcher.snapshot().items():
            with self.lock:
                node = self.nodes.setdefault(name, NodeView(name))
                node.trust, node.trust_reason = health.trust, health.trust_reason
                if health.status is not None and health.status_ns > node.status_ns:
                    node.status, node.status_ns = health.status, health.status_ns
                    if health.status.pid and health.status.pid not in node.pids:
                        node.pids.append(health.status.pid)

    def snapshot(self) -> dict[str, Any]:
        """A JSON-friendly picture of everything the monitor knows."""
        self._merge_status()
        now_ns = time.time_ns()
        with self.lock:
            self._trim(time.time())
            nodes = []
            for name in sorted(self.nodes):
                n = self.nodes[name]
                st = n.status
                fresh = st is not None and now_ns - n.status_ns < 3_000_000_000
                nodes.append({
                    "name": name, "alive": n.alive, "since_ns": n.since_ns, "restarts": n.restarts, "ups": n.ups,
                    "pid": st.pid if st else None, "uptime_s": st.uptime_s if st else None,
                    "status_age_s": (now_ns - n.status_ns) / 1e9 if st else None,
                    "topics": (st.topics if st and fresh else {}),
                    "handler_errors": st.extra.get("handler_errors", 0) if st else 0,
                    "trust": n.trust, "trust_reason": n.trust_reason,
                    "extra": dict(st.extra) if st else {},  # e.g. capture's done: the web view's "source ended"
                })
            track, prior = self.latest.get("track"), self.latest.get("prior")
            meas, template = self.latest.get("measurement"), self.latest.get("template")
            command = self.latest.get("command")
            out: dict[str, Any] = {
                "now_ns": now_ns, "connected": self.connected, "ever_connected": self.ever_connected,
                "unreachable_since_ns": None if self.connected else self.unreachable_since_ns,
                "endpoints": list(self.settings.connect), "namespace": self.info.namespace,
                "last_error": self.last_error, "namespaces_hint": self.namespaces_hint,
                "sessions_opened": self.sessions_opened,
                "decode_errors": self.decode_errors, "received": dict(self.received), "nodes": nodes,
                "source_width": (self.preview.source_width if self.preview is not None and self.preview.source_width
                                 else self.info.source_width),
                "history": {k: [[round(t, 3), round(v, 4)] for t, v in series] for k, series in self.history.items()},
                "ages": {k: round((now_ns - t) / 1e9, 2) for k, t in self.received_ns.items()},
                "stale_after_s": VALUE_STALE_S,
            }
            if isinstance(track, Track):
                out["target"] = {"state": track.state, "box": _box(track.box), "filtered_box": _box(track.filtered_box),
                                 "velocity": [round(float(v), 1) for v in track.velocity], "measured": track.measured,
                                 "frame_seq": track.header.frame_seq, "stamp_ns": track.header.stamp_ns}
            if isinstance(prior, Prior):
                out["prior"] = {"initialised": prior.initialised, "centre": [float(v) for v in prior.state[:2]],
                                "innovation_cov": np.asarray(prior.innovation_cov, float).tolist(),
                                "gate_chi2": prior.gate_chi2, "box": _box(prior.box),
                                "frame_seq": prior.header.frame_seq}
            if isinstance(meas, Measurement):
                cands = np.asarray(meas.candidates, float).reshape(-1, 5) if np.size(meas.candidates) else []
                out["measurement"] = {"state": meas.state, "accepted": meas.accepted, "box": _box(meas.box),
                                      "m_fuse": meas.m_fuse, "candidates": [[round(float(v), 2) for v in c]
                                                                            for c in cands],
                                      "frame_seq": meas.header.frame_seq}
            if isinstance(template, Template):
                out["eta"] = template.eta if template.initialised else None
                out["p_specular"] = template.p_specular
            if isinstance(command, MotorCommand):
                out["command"] = {"vx_mps": command.vx_mps, "vy_mps": command.vy_mps, "wz_radps": command.wz_radps,
                                  "range_m": command.range_m, "bearing_rad": command.bearing_rad,
                                  "reason": command.reason, "frame_seq": command.header.frame_seq,
                                  "latency_ms": ((command.header.pub_ns - command.header.stamp_ns) / 1e6
                                                 if command.header.stamp_ns > 0 else None)}
            group = self.latest.get("group")
            if isinstance(group, GroupState):
                points = self.latest.get("points")
                out["group"] = group_view(group, self._poses.get(group.header.frame_seq),
                                          points if isinstance(points, GroundPoints) else None, self.info.camera)
            err = self.history["centre_error_px"]
            out["centre_error_px"] = err[-1][1] if err else None
            if self.preview is not None:
                out["preview"] = {"count": self.preview_count, "width": self.preview.width,
                                  "age_s": (now_ns - self.preview_received_ns) / 1e9,
                                  "height": self.preview.height, "frame_seq": self.preview.header.frame_seq,
                                  "stamp_ns": self.preview.header.stamp_ns}
            return out


# -- terminal rendering (rich: colours and in-place redraw on a terminal, plain text in a pipe) ------------
TRUST_STYLE = {"verified": "green", "unverified": "yellow", "spoofed?": "bold red"}
TARGET_STYLE = {"TRACKING": "green", "REACQUIRED": "cyan", "OCCLUDED": "yellow", "LOST": "red"}
PIPE_WIDTH = 200  # not a terminal: wide enough that no row wraps (scripts split lines into fields)


def _clock(ns: int) -> str:
    return time.strftime("%H:%M:%S", time.localtime(ns / 1e9))


def _num(value: Any, fmt: str = ".1f", missing: str = "-") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return missing
    return format(value, fmt)


def _count(value: int, style: str) -> Text:
    return Text(str(value), style=style if value else "")


def _table(columns: list[str], rows: list[list[str | Text]]) -> Table:
    # No rules (two spaces between columns: the topic table fits 80 columns) and no padding at the sides: a row
    # starts with its first field, as grep and split expect. Cells are Text, never markup ("[follow]").
    table = Table(box=None, pad_edge=False, header_style="bold", show_header=any(columns))
    for name in columns:
        # On a narrow terminal only the last column (the trust reason, the target) wraps.
        table.add_column(name, no_wrap=name != columns[-1], min_width=len("spoofed?" if name == "check" else name),
                         justify="left" if name in (columns[0], "state", "dir", "check", "") else "right")
    for row in rows:
        table.add_row(*(cell if isinstance(cell, Text) else Text(cell) for cell in row))
    return table


def _group_line(group: dict[str, Any]) -> str:
    if not group.get("valid"):
        return f"(no group yet)  frame {group['frame_seq']}"
    fwd, left = group["centre_robot_m"]
    return (f"{'LOST ' if group['lost'] else ''}{group['members']} members, {group['others']} left out, "
            f"{len(group.get('ellipses', []))} ellipses  centre {fwd:.2f} m ahead {left:+.2f} m left  "
            f"{group['speed_mps']:.2f} m/s  step {group['step_ms']:.1f} ms  frame {group['frame_seq']}")


def render(snap: dict[str, Any], height: int | None = None, width: int | None = None) -> Group:
    """The dashboard: a status line, the target and the motor command (each with its age), node health, per-topic
    statistics (cut to ``height`` lines, when given)."""
    if snap["connected"]:
        link = Text("connected", "green")
    else:
        error = f" ({snap['last_error'][:80]})" if snap.get("last_error") else ""
        link = Text(f"robot unreachable since {_clock(snap['unreachable_since_ns'])}{error}", "bold red")
    head = Text.assemble(("followbus monitor", "bold"), f"  {', '.join(snap['endpoints'])}  ns={snap['namespace']}"
                         f"  {_clock(snap['now_ns'])}  ", link)
    nodes, topics = [], []
    for n in snap["nodes"]:
        for_s = (snap["now_ns"] - n["since_ns"]) / 1e9 if n["since_ns"] else None
        trust = n["trust"] + (f" ({n['trust_reason']})" if n["trust_reason"] else "")
        nodes.append([n["name"], Text("up", "green") if n["alive"] else Text("DOWN", "bold red"), _num(for_s, ".0f"),
                      str(n["restarts"]), _num(n["pid"], "d"), _num(n["uptime_s"], ".0f"),
                      _count(n["handler_errors"], "red"), Text(trust, TRUST_STYLE.get(n["trust"], ""))])
        topics += [[f"{key} @{n['name']}", t.get("direction", "?"), _num(t.get("rate_hz")),
                    _num(t.get("latency_p50_ms")), _num(t.get("latency_p99_ms")), _count(t.get("drops", 0), "yellow"),
                    _count(t.get("decode_errors", 0), "red")] for key, t in sorted(n["topics"].items())]
    state = _state_rows(snap)
    group = snap.get("group")
    if group:  # group following (graph.group.yaml)
        state.insert(0, ["group", _group_line(group)])
    if snap["decode_errors"]:
        state.append(["monitor", Text(f"{snap['decode_errors']} decode errors", "red")])
    if snap.get("namespaces_hint"):
        state.append(["monitor", Text(snap["namespaces_hint"], "yellow")])
    # As many topics as the terminal has lines for, so that the target and motor lines stay on screen (80x24).
    if height is not None:
        room = height - (len(head.wrap(Console(width=width or 80), width or 80)) + 2 * len(state) + len(nodes) + 6)
        if len(topics) > max(room, 1):
            more = len(topics) - max(room - 1, 0)
            topics = topics[:max(room - 1, 0)] + [[f"... {more} more (followbus topics)", "", "", "", "", "", ""]]
    return Group(head, "", _table(["node", "state", "for s", "restarts", "pid", "uptime s", "errs", "check"], nodes),
                 "", _table(["topic (as seen by node)", "dir", "rate Hz", "p50 ms", "p99 ms", "drops", "dec err"],
                            topics), "", _table(["", ""], state))


def _aged(label: str, value: Any, age: float | None, stale_s: float) -> list[Any]:
    """A state row whose value carries its age; past ``stale_s`` struck through, dimmed and labelled stale."""
    if age is None:
        return [label, value]
    text = value.copy() if isinstance(value, Text) else Text(str(value))
    if age > stale_s:
        text.stylize("dim strike")
        return [label, Text.assemble(text, (f"  STALE {age:.0f} s", "bold yellow"))]
    return [label, Text.assemble(text, (f"  {age:.1f} s", "dim"))]


def _state_rows(snap: dict[str, Any]) -> list[list[Any]]:
    target, cmd = snap.get("target"), snap.get("command")
    ages, stale_s = snap.get("ages", {}), snap.get("stale_after_s", VALUE_STALE_S)
    target_text = "(no track yet)" if not target else Text.assemble(
        (target["state"], TARGET_STYLE.get(target["state"], "")),
        f"  box {target['box']}  v {target['velocity']} px/s  frame {target['frame_seq']}"
        f"  centre err {_num(snap.get('centre_error_px'))} px")
    motor_text = (f"vx {cmd['vx_mps']:+.2f} m/s  vy {cmd['vy_mps']:+.2f} m/s  wz {cmd['wz_radps']:+.2f} rad/s  "
                  f"[{cmd['reason']}]  capture->command {_num(cmd['latency_ms'])} ms" if cmd else "(no command yet)")
    return [_aged("target", target_text, ages.get("track") if target else None, stale_s),
            _aged("eta_k", _num(snap.get("eta"), ".4f"), ages.get("template") if snap.get("eta") is not None
                  else None, stale_s),
            _aged("motor", motor_text, ages.get("command") if cmd else None, stale_s)]


def show(console: Console, snap: dict[str, Any]) -> None:
    """Print one dashboard: coloured on a terminal; otherwise plain lines without the cells' trailing blanks."""
    with console.capture() as captured:
        console.print(render(snap))
    text = captured.get()
    console.file.write(text if console.is_terminal else "".join(line.rstrip() + "\n" for line in text.splitlines()))
    console.file.flush()


def _all_up(snap: dict[str, Any], expected: list[str]) -> bool:
    by_name = {n["name"]: n for n in snap["nodes"]}
    names = expected or list(by_name)
    # Rates are over a window: a node up for less than RATE_SETTLE_S would show misleadingly low ones.
    return bool(names) and all(by_name.get(n, {}).get("alive") and by_name[n]["topics"]
                               and (by_name[n]["uptime_s"] or 0.0) >= RATE_SETTLE_S for n in names)


def run_monitor(args: Any) -> int:
    """``followbus monitor``: terminal dashboard, one snapshot (--once), or the web view (--web)."""
    from ..connect import check_credentials

    settings = monitor_settings(args.graph, args.connect, args.user, args.password, args.ca)
    if getattr(args, "connect_timeout", None) is not None:
        settings.connect_timeout_ms = max(1, round(args.connect_timeout * 1000))
    info = GraphInfo.load(args.graph, args.namespace)
    check_credentials(settings)  # a refused password is one line (exit 2), not a robot shown unreachable
    if args.web is not None:
        from .webview import serve

        return serve(settings, info, args.bind, args.web, args.seconds, token=args.web_token)
    monitor = BusMonitor(settings, info).start()
    console = Console()  # colours on a terminal; in a pipe plain text (no ANSI), wide enough that no row wraps
    console = console if console.is_terminal else Console(width=PIPE_WIDTH)
    try:
        if args.once:
            # Wait for every node's token and a status message (topic rates), or the time limit.
            deadline = time.monotonic() + (args.seconds or 5.0)
            while time.monotonic() < deadline and not _all_up(monitor.snapshot(), info.nodes):
                time.sleep(0.1)
            snap = monitor.snapshot()
            show(console, snap)
            return 0 if snap["connected"] and _all_up(snap, info.nodes) else 1
        deadline = None if args.seconds is None else time.monotonic() + args.seconds
        if console.is_terminal:
            # Cut to the terminal's height: taller than the screen, Live cannot redraw in place (lines pile up).
            with Live(console=console, auto_refresh=False, vertical_overflow="crop") as live:
                while deadline is None or time.monotonic() < deadline:
                    live.update(render(monitor.snapshot(), console.size.height, console.size.width), refresh=True)
                    time.sleep(0.5)
        else:
            while deadline is None or time.monotonic() < deadline:
                console.file.write(SEPARATOR + "\n")
                show(console, monitor.snapshot())
                time.sleep(0.5)
    finally:
        monitor.close()
    if not monitor.ever_connected:  # a timed run that never saw the graph: not a success
        from ..connect import explain_connect_failure

        print(f"followbus: {explain_connect_failure(settings)}", file=sys.stderr)
        return 2
    return 0
