"""What a replay replays: the graph as recorded (params applied), the nodes, and which recorded keys are their
inputs and outputs (their boundary in the graph, bus.graph.Graph.boundary); the options and the report."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..bus.graph import Graph, load_graph
from ..bus.node_checks import load_node_class
from ..bus.node_host import sampled_input
from ..bus.node_params import marked
from ..bus.recording import (
    RecordingError,
    bus_channels,
    chunks_to_skip,
    read_metadata,
)
from .diff import Tolerance

log = logging.getLogger("followbus.replay")

# --- options, plan, report -------------------------------------------------------------------------

@dataclass
class ReplayOptions:
    nodes: list[str]
    graph_path: str | None = None
    params: dict[str, dict[str, Any]] = field(default_factory=dict)  # node -> its --param values (bus.graph's parser)
    verify: bool = False
    isolated: bool = False
    tolerance: Tolerance = field(default_factory=Tolerance)
    frame_timeout_s: float = 5.0
    startup_timeout_s: float = 60.0
    max_frames: int = 0
    progress: bool = True
    on_corrupt: str = "refuse"  # a chunk failing its CRC: refuse, or skip (bus.recording.ON_CORRUPT)


@dataclass
class ReplayReport:
    file: str
    node: str  # the replayed node(s), comma-separated
    mode: str = "in-process"  # or "isolated"
    params: dict[str, Any] = field(default_factory=dict)  # the node's; several nodes: node -> params
    frames: int = 0
    recording_first_frame: int | None = None  # the run's first recorded frame; > 0: recorded mid-run
    inputs_sent: int = 0
    outputs_expected: int = 0
    outputs_received: int = 0
    outputs_compared: int = 0
    matched: int = 0
    mismatch_count: int = 0
    mismatches: list[dict[str, Any]] = field(default_factory=list)  # the first MAX_REPORTED
    missing: list[dict[str, Any]] = field(default_factory=list)  # recorded, never produced
    # recorded outputs of frames whose required same-frame inputs are not all in the recording (a recorder that
    # joined late): the replayed node cannot have produced them; not verifiable, so neither compared nor missing
    unverifiable: int = 0
    # differing outputs while the nodes re-converged after such a frame (replay/engine.py RESYNC_FRAMES and
    # RESYNC_MAX_FRAMES): a frame's missing input also shapes the next frames (re-ID compares each frame with the one
    # before); not failures
    after_gap: int = 0
    # recorded outputs handed to the next replayed node in place of those a node could not make (such a frame)
    stand_ins: int = 0
    extra: list[dict[str, Any]] = field(default_factory=list)  # produced, not in the recording
    beyond_end: int = 0  # produced for frames after the recording's last output on that key (not compared)
    timer_outputs: int = 0  # recorded outputs of a node's timer (no frame): wall-clock ticks live, not compared
    timeouts: list[int] = field(default_factory=list)  # --isolated: frames whose outputs did not come in time
    late_inputs: int = 0
    hints: int = 0  # frames told to skip, or to join the feedback the live run joined (a live fallback)
    startup_s: float = 0.0
    wall_s: float = 0.0  # reading, feeding, the node's work and the diff (not the process start-up)
    handler_s: float = 0.0  # in-process: the node's handlers (and what they publish)
    decode_s: float = 0.0  # in-process: decoding its inputs
    recorded_span_s: float = 0.0
    speed_x: float = 0.0
    node_exit: int | None = None  # --isolated: the process's exit status
    error: str = ""

    def ok(self, verify: bool) -> bool:
        if self.error:
            return False
        # Nothing compared proves nothing: a verify that checked no output must not pass.
        return not verify or not (self.mismatch_count or self.missing or self.extra or not self.outputs_compared)


def _forget_state_file(name: str, spec: Any, params: dict[str, Any], given: dict[str, Any]) -> None:
    """A replayed node keeps no state file (unless --param names one): the live graph's state/template.npz is
    neither read at its start nor overwritten by a replay."""
    try:
        keys = marked(load_node_class(spec.run).Params, "state_file")
    except ImportError:
        return
    for key in keys:
        if params.get(key) and key not in given:
            log.info("%s: %s=%s not used by the replay (the live graph's state)", name, key, params[key])
            params[key] = ""


class ReplayPlan:
    """What is replayed: the graph as recorded (params applied), the nodes, and which recorded keys are
    their inputs (produced outside them: the nodes' boundary in the graph) and their outputs."""

    def __init__(self, path: Path, options: ReplayOptions):
        self.path = path
        recorded = bus_channels(path)  # first: a file that is not a finalised recording is named as such
        meta = read_metadata(path)
        graph, recorded_params = self._recorded_graph(path, meta, options)
        self.nodes = list(dict.fromkeys(options.nodes))
        for name in self.nodes:
            if name not in graph.nodes:
                raise RecordingError(f"no node {name!r} in the graph (nodes: {', '.join(graph.nodes)})")
        self.params = {name: self._params_of(graph, name, recorded_params, options.params.get(name, {}))
                       for name in self.nodes}
        self.graph = graph.override(self.params)  # what the runtime builds the nodes with
        self.recorded_ns = (meta.get("followbus", {}).get("namespace")) or self.graph.namespace
        edge = self.boundary = self.graph.boundary(self.nodes)
        # recorded key -> graph topic (node/output): inputs produced outside the replayed nodes, and their outputs
        self.inputs = {self.key(t): t for t in edge.input_topics()}
        self.outputs = {self.key(t): t for t in edge.outputs}
        # recorded keys a frame's outputs cannot exist without (required same-frame inputs from outside), and
        # those of outside inputs that belong to a frame (any offset, optional or not)
        self.required_inputs = {self.key(t) for t in edge.input_topics(required=True)}
        self.frame_inputs = {self.key(t) for t in edge.input_topics(frame=True)}
        # node -> its own required same-frame inputs from outside (recorded keys): without one, that node cannot
        # handle the frame; and node -> its outputs another replayed node reads (the recorded message then stands
        # in for the one it cannot make, or the reader waits for it in vain)
        self.required_by_node = {n: self._required_of(n) for n in self.nodes}
        self.internal_outputs = self._read_inside(edge.outputs)
        self._check_inputs(path, recorded)
        # Before the node sees anything: a corrupt chunk would make --verify blame the node for the damage.
        self.skip_chunks = chunks_to_skip(path, set(self.inputs) | set(self.outputs), options.on_corrupt)
        # node -> its feedback inputs (bus.sync), for the nodes that have any; and the nodes whose live decisions
        # are replayed (hints): those that join feedback, or sample an input by stamp
        self.feedback_inputs = self._feedback_inputs()
        self.hinted = [n for n in self.nodes if n in self.feedback_inputs or self._sampled_inputs(n)]
        # (node, feedback input) -> recorded key, for feedback produced outside the replayed nodes
        self.feedback_keys = {where: self.key(t) for where, t in edge.feedback().items()}
        # (node, sampled input) -> recorded key of that input, fed from outside: its notes name a message's stamp
        self.sampled_keys = self._sampled_keys()
        # Outputs of no frame from a node with a timer (motor's odometry and watchdog stops) come from ticks of
        # the wall clock live and of the stamps in a replay: not comparable, counted apart.
        self.timer_topics = {topic for key, topic in self.outputs.items()
                             if self._has_timer(self.output_node(key))}

    @staticmethod
    def _recorded_graph(path: Path, meta: dict[str, Any], options: ReplayOptions) -> tuple[Graph, dict[str, str]]:
        """The graph to replay and the params the run recorded (an explicit --graph brings its own)."""
        if options.graph_path:
            return load_graph(options.graph_path), {}
        text = meta.get("graph", {}).get("yaml")
        if not text:
            raise RecordingError(f"{path}: no graph.yaml in the recording's metadata; pass --graph")
        return load_graph(f"{path}#graph.yaml", text), meta.get("params", {})

    @staticmethod
    def _params_of(graph: Graph, name: str, recorded: dict[str, str], given: dict[str, Any]) -> dict[str, Any]:
        spec = graph.nodes[name]
        params = json.loads(recorded[name]) if name in recorded else dict(spec.params)
        _forget_state_file(name, spec, params, given)
        params.update(given)
        return params

    def _check_inputs(self, path: Path, recorded: Any) -> None:
        if not self.inputs:
            raise RecordingError(f"{', '.join(self.nodes)}: no inputs from outside: there is nothing to replay into")
        for key in self.inputs:
            if key not in recorded:
                log.warning("the recording has no messages on %s", key)
        if not any(key in recorded for key in self.inputs):
            raise RecordingError(f"{path}: none of the inputs were recorded ({', '.join(self.inputs)})")

    def _read_inside(self, outputs: tuple[str, ...]) -> dict[str, list[str]]:
        """node -> its outputs (topics) that another replayed node reads."""
        read = {i.topic for n in self.nodes for i in self.graph.nodes[n].inputs.values()}
        return {n: [t for t in outputs if t.split("/", 1)[0] == n and t in read] for n in self.nodes}

    def _required_of(self, node: str) -> set[str]:
        """Recorded keys of ``node``'s required same-frame inputs from outside."""
        return {self.key(i.topic) for i in self.graph.nodes[node].inputs.values()
                if i.sync == "frame" and not i.offset and not i.optional and self.key(i.topic) in self.inputs}

    def key(self, topic: str) -> str:
        """The recorded key of a graph topic (node/output)."""
        return f"{self.recorded_ns}/{topic}"

    def _feedback_inputs(self) -> dict[str, list[str]]:
        feedback = {name: [i.name for i in self.graph.nodes[name].inputs.values() if i.sync == "frame" and i.offset]
                    for name in self.nodes}
        return {n: names for n, names in feedback.items() if names}

    def _sampled_inputs(self, node: str) -> list[str]:
        """The inputs ``node`` samples by stamp (bus.node In(..., sample_by_stamp=True))."""
        try:
            ports = load_node_class(self.graph.nodes[node].run).INPUTS
        except ImportError:
            return []  # said as a graph error (file:line) when the node is built
        return [name for name, port in ports.items() if port.sample_by_stamp]

    def _sampled_keys(self) -> dict[tuple[str, str], str]:
        found: dict[tuple[str, str], str] = {}
        for node in self.nodes:
            spec = self.graph.nodes[node]
            for input_name in self._sampled_inputs(node):
                inp = spec.inputs.get(input_name)
                if inp is not None and self.key(inp.topic) in self.inputs:
                    found[(node, input_name)] = self.key(inp.topic)
        return found

    def noted_key(self, node: str, note: str) -> str | None:
        """The recorded key of the message a note of ``node`` names by its stamp (None: the note is no sample's)."""
        return self.sampled_keys.get((node, sampled_input(note)))

    def _has_timer(self, node: str) -> bool:
        try:
            return bool(load_node_class(self.graph.nodes[node].run).TIMER_PERIOD_MS)
        except ImportError:
            return False  # said as a graph error (file:line) when the node is built

    def output_node(self, key: str) -> str:
        return self.outputs[key].split("/", 1)[0]
