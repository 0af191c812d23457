"""The monitor's state of a running graph, kept from the bus (``followbus monitor``, its web view and the Foxglove
bridge show it).

:class:`BusMonitor` joins the robot's bus as a Zenoh *client* and keeps the latest state: node health from
liveliness tokens and NodeStatus, the target (Track/Prior/Measurement), eta_k (Template), the motor command,
the followed group of a group graph (GroupState, placed with the pose of its frame's GroundPoints),
and one minute of history (eta_k, end-to-end latency, centre error against ground truth). It only ever
subscribes, never to raw frames, and its callbacks only copy small objects under a lock, so the robot never
waits on the laptop. When the robot disappears it says since when, and it reopens the session until the robot
is back. :meth:`BusMonitor.snapshot` is the JSON-friendly picture every viewer renders.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

import zenoh

from ..bus.codec import DecodeError
from ..bus.graph import Graph
from ..bus.health import HealthWatcher, live_namespaces, namespaces_hint
from ..bus.links import links_of_statuses, short_of_sent
from ..bus.pubsub import declare_subscriber, frame_bytes
from ..bus.schemas import Frame, Message, NodeStatus, decode
from ..bus.session import ZenohSettings, open_session
from ..msgs.group import GroundPoints, GroupState
from ..msgs.perception import GroundTruth
from ..msgs.robot import MotorCommand
from ..msgs.tracking import Measurement, Prior, Template, Track
from ..tracking.groundplane import CameraGeometry
from .snapshot import STATUS_FRESH_NS, _centre, latest_views, node_row

log = logging.getLogger("followbus.monitor")

HISTORY_S = 60.0
NAMESPACES_AFTER_S = 2.0  # connected this long without a node of our namespace: look for other namespaces
NAMESPACES_EVERY_S = 5.0
VALUE_STALE_S = 2.0  # a target, eta or command older than this is shown struck through and labelled stale
REOPEN_AFTER_S = 5.0  # unreachable this long: close the session and open a fresh one
# What the monitor watches, by message type: the graph names the outputs that carry them (GraphInfo.from_graph).
WATCHED: dict[str, type[Message]] = {
    "track": Track, "prior": Prior, "measurement": Measurement, "template": Template, "command": MotorCommand,
    "ground_truth": GroundTruth,
    # group following (graph.group.yaml, seed 004): absent in the person graph, then nothing is shown
    "group": GroupState, "points": GroundPoints}
# Without a graph file (a laptop that has none): where the shipped graph.yaml publishes them.
SHIPPED_KEYS = {"track": "prediction/track", "prior": "prediction/prior", "measurement": "reid/measurement",
                "template": "template/template", "command": "motor/command", "ground_truth": "capture/ground_truth",
                "group": "group/group", "points": "groundplane/points"}
SHIPPED_PREVIEW = "capture/preview"
DEFAULT_SOURCE_WIDTH = 640


@dataclass
class GraphInfo:
    """What the monitor takes from the graph (if any): namespace, node names, keys, the source width."""

    namespace: str = "fb"
    nodes: list[str] = field(default_factory=list)
    keys: dict[str, str] = field(default_factory=dict)  # watched name -> bus key
    preview_key: str = ""
    source_width: int = DEFAULT_SOURCE_WIDTH
    camera: CameraGeometry | None = None  # the groundplane node's camera: group shapes drawn into the video
    graph_svg: str = ""  # the graph's drawing (bus/graph_drawing.py), shown by the web view

    @classmethod
    def from_graph(cls, graph: Graph | None, namespace: str | None = None) -> GraphInfo:
        """The keys of the watched messages: each the output of the graph that carries its type (a node class's
        OUTPUTS); the preview is the frame output no node reads. No graph (or a type it does not carry): the
        shipped graph.yaml's keys."""
        info = cls()
        topics, preview = dict(SHIPPED_KEYS), SHIPPED_PREVIEW
        if graph is not None:
            from ..bus.graph_drawing import to_svg

            info.namespace, info.nodes, info.graph_svg = graph.namespace, list(graph.nodes), to_svg(graph)
            found, preview = _watched_topics(graph)
            topics.update(found)  # a type the graph does not carry keeps the shipped key: nothing comes on it
            info._read_params(graph)
        info.namespace = namespace or info.namespace
        info.keys = {name: f"{info.namespace}/{topic}" for name, topic in topics.items()}
        info.preview_key = f"{info.namespace}/{preview}"
        return info

    def _read_params(self, graph: Graph) -> None:
        for spec in graph.nodes.values():
            # The motor controller's image width is the frame width the boxes live in.
            width = (spec.params or {}).get("image_width_px")
            if isinstance(width, (int, float)) and width > 0:
                self.source_width = int(width)
        for name, spec in graph.nodes.items():
            if GroundPoints in _outputs(graph, name).values():
                self.camera = _camera(spec.params or {})


def _outputs(graph: Graph, node: str) -> dict[str, type[Message]]:
    from ..bus.node_checks import load_node_class

    try:
        declared = load_node_class(graph.nodes[node].run).OUTPUTS
    except ImportError:  # a node this machine cannot import: its outputs carry nothing the monitor knows
        return {}
    return {out: port.type for out, port in declared.items() if out in graph.nodes[node].outputs}


def _watched_topics(graph: Graph) -> tuple[dict[str, str], str]:
    read = {inp.topic for spec in graph.nodes.values() for inp in spec.inputs.values()}
    topics: dict[str, str] = {}
    preview = SHIPPED_PREVIEW
    for node in graph.nodes:
        for out, kind in _outputs(graph, node).items():
            names = [name for name, watched in WATCHED.items() if watched is kind]
            topics.update({name: f"{node}/{out}" for name in names})
            if kind is Frame and f"{node}/{out}" not in read:
                preview = f"{node}/{out}"
    return topics, preview


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
                msg = decode(frame_bytes(sample), WATCHED[name])
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

    def graph_svg(self) -> str:
        """The graph's drawing: of the graph file when the monitor has one, else of what the nodes' statuses say
        they publish and read (a laptop without the robot's graph.yaml still sees the dataflow)."""
        if self.info.graph_svg:
            return self.info.graph_svg
        from ..bus.graph_drawing import to_svg

        self._merge_status()
        with self.lock:
            statuses = {name: node.status for name, node in self.nodes.items() if node.status is not None}
        graph = graph_from_statuses(self.info.namespace, statuses)
        return to_svg(graph) if graph.nodes else ""

    def snapshot(self) -> dict[str, Any]:
        """A JSON-friendly picture of everything the monitor knows (its parts: viewing/snapshot.py)."""
        self._merge_status()
        now_ns = time.time_ns()
        with self.lock:
            self._trim(time.time())
            preview = self.preview
            out: dict[str, Any] = {
                "now_ns": now_ns, "connected": self.connected, "ever_connected": self.ever_connected,
                "unreachable_since_ns": None if self.connected else self.unreachable_since_ns,
                "endpoints": list(self.settings.connect), "namespace": self.info.namespace,
                "last_error": self.last_error, "namespaces_hint": self.namespaces_hint,
                "sessions_opened": self.sessions_opened,
                "decode_errors": self.decode_errors, "received": dict(self.received),
                "nodes": [node_row(name, self.nodes[name], now_ns) for name in sorted(self.nodes)],
                "source_width": (preview.source_width if preview is not None and preview.source_width
                                 else self.info.source_width),
                "history": {k: [[round(t, 3), round(v, 4)] for t, v in series] for k, series in self.history.items()},
                "ages": {k: round((now_ns - t) / 1e9, 2) for k, t in self.received_ns.items()},
                "stale_after_s": VALUE_STALE_S,
            }
            # Links that deliver nothing, or less than their publisher sends (bus/links.py), from fresh statuses.
            statuses = {name: node.status for name, node in self.nodes.items()
                        if node.status is not None and now_ns - node.status_ns < STATUS_FRESH_NS}
            out["links"] = [link.describe() for link in links_of_statuses(statuses) if short_of_sent(link)]
            out.update(latest_views(self.latest, self._poses, self.info.camera))
            err = self.history["centre_error_px"]
            out["centre_error_px"] = err[-1][1] if err else None
            if preview is not None:
                out["preview"] = {"count": self.preview_count, "width": preview.width,
                                  "age_s": (now_ns - self.preview_received_ns) / 1e9,
                                  "height": preview.height, "frame_seq": preview.header.frame_seq,
                                  "stamp_ns": preview.header.stamp_ns}
            return out


def graph_from_statuses(namespace: str, statuses: dict[str, NodeStatus]) -> Any:
    """A graph as bus/graph_drawing.py draws it, from the topics each node's status lists (key, direction): its
    outputs under its own name, its inputs by the key they read. Which input is feedback is not in a status."""
    from types import SimpleNamespace

    prefix = f"{namespace}/"
    nodes: dict[str, Any] = {}
    for name, status in sorted(statuses.items()):
        outputs, inputs = [], {}
        for key, topic in sorted(status.topics.items()):
            if not key.startswith(prefix):
                continue
            source = key[len(prefix):]
            if topic.get("direction") == "out" and source.startswith(f"{name}/"):
                outputs.append(source[len(name) + 1:])
            elif topic.get("direction") == "in" and "/" in source:
                inputs[source] = SimpleNamespace(topic=source, offset=0)
        nodes[name] = SimpleNamespace(outputs=outputs, inputs=inputs)
    return SimpleNamespace(name="drawn from the bus", namespace=namespace, nodes=nodes)
