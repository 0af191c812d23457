"""The graph's own tracking nodes as an evaluation follower.

``followbus eval`` scores what the robot runs: the egomotion, prediction, re-ID and template nodes of
graph.yaml, instantiated in this process by the in-process runtime (bus/inproc.py) and fed each frame and its
detections as the capture and detection nodes would publish them. The graph's data order (prior k after
measurement k-1, re-ID against the template of k-1, camera motion k-1 → k) is therefore the graph's own, kept in
one place: the nodes and their synchronisers. The ego velocity of a frame reaches prediction as an odometry sample
stamped at the frame's capture time, as the motor node would publish it.

No node or topic is named here: the nodes run are those that produce none of what is fed in (frames, detections,
odometry), and each topic is found by its message type in the node classes' declarations. This is evaluation/'s
one module that uses the bus (its in-process runtime and graph model); tests/test_layout.py holds it to that.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..bus.graph import Graph, load_graph
from ..bus.inproc import InProcessGraph
from ..bus.node_checks import load_node_class, validate_node
from ..bus.node_params import param_names
from ..bus.schemas import Frame
from ..msgs.perception import CameraMotion, Detections
from ..msgs.robot import Odometry
from ..msgs.tracking import Measurement, Prior, Template, Track
from ..nodes.detection import resolve_input_size
from ..tracking.params import KalmanParams, ReidParams
from ..vision.detector_presets import apply_detector_preset
from .trace import ReidCapture, frame_record

GRAPH_PATH = Path(__file__).resolve().parents[1] / "graph.yaml"
FED_TYPES = (Frame, Detections, Odometry)  # what evaluation publishes in place of capture, detection and motor
# The node clock starts here and frame k is stamped CLOCK_BASE_NS + its source time: stamps near the nodes' own
# clock (nodes reject stamps far from it), differences exactly the source's (the Kalman Δt).
CLOCK_BASE_NS = 1_700_000_000_000_000_000
EPOCH_NS = CLOCK_BASE_NS
MAX_STEPS_PER_FRAME = 1000


class GraphFollowerError(RuntimeError):
    """The graph did not produce a track for a frame it was given."""


@dataclass
class GraphFrame:
    """What the graph published for one frame (measurement and prior only with ``details=True``)."""

    track: Track
    measurement: Measurement | None
    prior: Prior | None
    template: Template | None


def tracking_graph(settings: Mapping[str, Any], graph_path: Path = GRAPH_PATH, detector: str = "graph") -> Graph:
    """graph.yaml with each of ``settings`` (parameter name -> value: an ablation's switches) given to every
    tracking node that reads it, the detection node's params switched to ``detector`` (a preset of
    vision/detector_presets.py: the detector of the fed detections, which the redetection node runs again), and no
    template file read or written. A setting no tracking node reads is a ValueError: it would change nothing."""
    graph = load_graph(graph_path)
    topics = GraphTopics(graph)
    unread = set(settings)
    changes: dict[str, dict[str, Any]] = {}
    for name in topics.nodes:
        reads = param_names(load_node_class(graph.nodes[name].run).Params)
        changes[name] = {key: value for key, value in settings.items() if key in reads}
        unread -= reads
    if unread:
        raise ValueError(f"no tracking node of {graph_path} reads {', '.join(sorted(unread))}")
    changes[topics.node(topics.template)]["state_file"] = ""
    source = detection_node(graph)
    changes[source] = resolve_input_size(apply_detector_preset(dict(graph.nodes[source].params), detector))
    return graph.override(changes)


def detection_node(graph: Graph) -> str:
    """The name of the graph's node that publishes Detections."""
    return next(name for name, spec in graph.nodes.items()
                if Detections in _types(load_node_class(spec.run).OUTPUTS).values())


def detector_params(graph_path: Path = GRAPH_PATH) -> dict[str, Any]:
    """The params of the graph's detection node (the one that publishes Detections), as the file says them."""
    graph = load_graph(graph_path)
    return dict(graph.nodes[detection_node(graph)].params)


class GraphTopics:
    """The graph's tracking nodes and topics, found by message type (see the module docstring)."""

    def __init__(self, graph: Graph) -> None:
        outputs = {name: _types(load_node_class(spec.run).OUTPUTS) for name, spec in graph.nodes.items()}
        fed_by = {name for name, out in outputs.items() if any(t in FED_TYPES for t in out.values())}
        self.nodes = [name for name in graph.nodes if name not in fed_by]
        by_type = {t: f"{name}/{output}" for name in self.nodes for output, t in outputs[name].items()}
        self.track, self.template = by_type[Track], by_type[Template]
        self.prior, self.measurement = by_type[Prior], by_type[Measurement]
        self.camera_motion = by_type.get(CameraMotion)
        boundary = graph.boundary(self.nodes)
        inputs = {name: _types(load_node_class(graph.nodes[name].run).INPUTS) for name in self.nodes}
        fed = {inputs[node][inp.name]: inp.topic for node, inp in boundary.inputs}
        self.frame, self.detections, self.odometry = (fed[t] for t in FED_TYPES)

    @staticmethod
    def node(topic: str) -> str:
        return topic.split("/", 1)[0]


def _types(ports: dict[str, Any]) -> dict[str, type]:
    """A node class's ports (bus.node In/Out) as their message types."""
    return {name: port.type for name, port in ports.items()}


def node_params(graph: Graph, node: str, cls: type) -> Any:
    """The ``cls`` part of ``node``'s params in ``graph``, defaults included."""
    params = validate_node(graph, graph.nodes[node])[1]
    return next(p for p in (params if isinstance(params, tuple) else (params,)) if isinstance(p, cls))


def best_detection(measurement: Measurement | None) -> tuple[float, ...] | None:
    """Re-ID's best-scoring candidate of the frame when it is a detector box (None: no candidate, or the best was a
    motion blob): what the missed-re-acquisition count compares with the target (evaluation/metrics.py)."""
    if measurement is None or not len(measurement.candidates):
        return None
    best = int(np.argmax(measurement.candidates[:, 4]))
    if measurement.candidate_sources[best] == "motion":
        return None
    return tuple(float(v) for v in measurement.candidates[best, :4])


class GraphFollower:
    """A follower (evaluation/runner.py's protocol) that is the graph: its first :meth:`step` (which carries the
    initial box, if any) builds the in-process graph, every step publishes one frame with its detections and
    returns the box of the Track that prediction publishes for it; :attr:`last` holds all the graph published
    for that frame, :meth:`node` a node instance (as a test would inspect it)."""

    def __init__(self, settings: Mapping[str, Any] | None = None, graph_path: Path = GRAPH_PATH, *,
                 details: bool = False, trace: bool = False, detector: str = "graph") -> None:
        self.planned = tracking_graph(settings or {}, graph_path, detector)  # built at the first step
        t = self.topics = GraphTopics(self.planned)
        # The fed detections' input side, as the detection node says it in each message (the region's scale)
        size = self.planned.nodes[t.node(t.detections)].params.get("input_size_px", 416)
        backend = self.planned.nodes[t.node(t.detections)].params.get("backend", "auto")
        self.input_px = int(size) if backend in ("auto", "yolox", "yolov8") else 0
        # What the graph's settings decide before it is built: whether re-ID takes low-score boxes, and whether
        # prediction warps its prior by the camera's motion (without it the camera-motion node is not run).
        self.uses_low_scores = node_params(self.planned, t.node(t.measurement), ReidParams).low_score_stage
        kalman = node_params(self.planned, t.node(t.prior), KalmanParams)
        self.compensates_camera_motion = kalman.camera_motion_compensation
        # Eval reads the track and the template's η; tests (details=True) also the measurement and prior;
        # ``trace`` (followbus eval --trace) also the camera motion and re-ID's scores: info["trace"] each frame.
        self.details = details or trace
        self.recorded: list[str] = []  # the topics read each frame (known once the graph is built)
        self.trace = trace
        self.capture = ReidCapture()
        self.transforms: dict[int, CameraMotion] = {}
        self.loose: list[str] = []  # recorded topics a frame may lack or get late
        self.graph: InProcessGraph | None = None
        self.k = 0
        self.last: GraphFrame | None = None

    def _start(self, init_box: Sequence[float] | None) -> InProcessGraph:
        graph, t = self.planned, self.topics
        if init_box is not None:
            graph = graph.override({t.node(t.measurement): {"init_box": [float(v) for v in init_box]}})
        nodes = list(t.nodes)
        self.recorded = [t.track, t.template, t.measurement, *([t.prior] if self.details else [])]
        if t.camera_motion and not self.compensates_camera_motion:
            nodes.remove(t.node(t.camera_motion))  # as in the graph without the node: priors are not warped
        self.loose = [t.camera_motion] if self.trace and t.camera_motion and t.node(t.camera_motion) in nodes else []
        g = InProcessGraph(graph, nodes=nodes, clock="sim", clock_start_ns=CLOCK_BASE_NS,
                           record=[*self.recorded, *self.loose], record_bytes=False)  # read with drain: no bytes needed
        g.start()
        if self.trace:
            self._instrument(g.node(t.node(t.measurement)).reid)
        return g

    def _instrument(self, reid: Any) -> None:
        """Keep what the in-process re-ID computes beyond its message (every candidate's scores, the classifier's
        score of each contender) in :attr:`capture`, by wrapping its methods on this instance only."""
        capture, step, embed = self.capture, reid.step, reid._embed
        score = reid.identity.score
        asked: list[tuple[float, ...]] = []

        def traced_step(*args: Any, **kwargs: Any) -> Any:
            capture.clear()
            measurement = step(*args, **kwargs)
            capture.candidates = reid.candidates
            return measurement

        def traced_embed(frame_bgr: np.ndarray, boxes: list[Any]) -> Any:
            asked[:] = [tuple(float(v) for v in b) for b in boxes]
            return embed(frame_bgr, boxes)

        def traced_score(embs: np.ndarray) -> Any:
            scores = score(embs)
            capture.identity.update(zip(asked, (float(v) for v in np.ravel(scores)), strict=False))
            return scores

        reid.step, reid._embed, reid.identity.score = traced_step, traced_embed, traced_score

    def prepare(self, init_box: Sequence[float] | None) -> None:
        """Build the graph (node set-up: the re-ID model loaded) now, told whom to follow, rather than in the first
        step: evaluation times steps, and a set-up is not a frame."""
        if self.graph is None:
            self.graph = self._start(init_box)

    def step(self, frame_bgr: np.ndarray, detections: np.ndarray, t_ns: int, v_ego_mps: Sequence[float] = (0.0, 0.0),
             init_box: Sequence[float] | None = None,
             low_detections: np.ndarray | None = None) -> tuple[tuple[float, ...] | None, dict[str, Any]]:
        self.prepare(init_box)  # the first step builds the graph, unless the caller prepared it
        g, k = self.graph, self.k
        spent = dict(g.handler_s)
        stamp = CLOCK_BASE_NS + int(t_ns)
        g.run_until(stamp)

        def stamped(msg):
            msg.header.frame_seq, msg.header.stamp_ns, msg.header.epoch_ns = k, stamp, EPOCH_NS
            return msg

        # Odometry first: prediction takes the newest sample not after the frame's stamp.
        t = self.topics
        g.inject(t.odometry, stamped(Odometry(vx_mps=float(v_ego_mps[0]), vy_mps=float(v_ego_mps[1]))))
        bgr = np.ascontiguousarray(frame_bgr)
        # A read-only image (the runner's, decoded from disk for this run alone) is shared with the nodes rather
        # than copied for them: nobody can write to it any more.
        g.inject(t.frame, stamped(Frame(width=bgr.shape[1], height=bgr.shape[0], encoding="bgr8",
                                                data=bgr)), handover=not bgr.flags.writeable)
        low = low_detections if low_detections is not None and self.uses_low_scores else None
        g.inject(t.detections, stamped(Detections(
            boxes=np.asarray(detections, np.float32).reshape(-1, 5), backend="eval", input_px=self.input_px,
            low_boxes=np.zeros((0, 5), np.float32) if low is None else np.asarray(low, np.float32).reshape(-1, 5))))
        self.last = out = self._outputs_of(g, k)
        self.k += 1
        box = None if out.track.box is None else tuple(float(v) for v in out.track.box)
        info: dict[str, Any] = {"state": out.track.state, "best_candidate": best_detection(out.measurement),
                                "eta": 0.0 if out.template is None else float(out.template.eta),
                                # each node's share of this step (the report's tracker time per part)
                                "part_ms": {n: (s - spent[n]) * 1e3 for n, s in g.handler_s.items()}}
        if self.trace:
            info["trace"] = frame_record(out, self.capture, self.transforms.pop(k, None))
        return box, info

    def node(self, name: str) -> Any:
        if self.graph is None:
            raise GraphFollowerError("the graph is built at the first step")
        return self.graph.node(name)

    def _outputs_of(self, g: InProcessGraph, k: int) -> GraphFrame:
        """Run the graph until prediction has published frame k's track (at once, unless a frame set waits
        for an optional input until its deadline, as frame 0's does for a camera motion that cannot exist)."""
        got: dict[str, Any] = {}
        for _ in range(MAX_STEPS_PER_FRAME):
            g.deliver()
            for msg in (m for topic in self.loose for m in g.drain(topic)):
                self.transforms[msg.header.frame_seq] = msg  # optional for prediction: may come after the track
            for topic in self.recorded:
                for msg in g.drain(topic):
                    if msg.header.frame_seq != k:
                        raise GraphFollowerError(f"frame {k}: the graph published {topic} of frame "
                                                 f"{msg.header.frame_seq}")
                    got[topic] = msg
            t = self.topics
            if t.track in got:
                return GraphFrame(got[t.track], got.get(t.measurement), got.get(t.prior), got.get(t.template))
            if not g.step():
                break
        raise GraphFollowerError(f"frame {k}: the graph published no track (node status: "
                                 f"{ {n: g.status(n)['extra'] for n in g.hosts} })")

    def close(self) -> None:
        if self.graph is not None:
            self.graph.close()
