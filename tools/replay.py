"""``followbus replay FILE --node NAME``: a recording fed into one node (or a few), outputs diffed.

The node is the graph's own class, hosted in this process by the in-process runtime (bus/inproc.py, the
same NodeHost as on the bus) on a clock that follows the message stamps; its spec is the recorded one
(graph.yaml text and effective params from the file's metadata, or ``--graph``), params overridden by
``--param``. The recording is read once, in the order its messages were published; each input of the
node is handed over and delivered before the next, so the node sees its inputs in the live order and
handles each as soon as it can. What the live run decided under time pressure is given to the node as
replay hints (bus.schemas.ReplayHint) before the frame they concern: frames it skipped, the feedback each
set joined, choices it noted; the runtime holds back a feedback message the live node received late.
``--node reid,prediction`` runs several nodes together, the edges between them in-process.

``--isolated`` runs the node as the deployed process instead (``followbus node NAME --clock stamps`` in a
private graph: private namespace, private loopback port) and feeds it over Zenoh, with the same order and
hints. When to send the next input is not guessed: the in-process run of the same node, fed alongside,
says how many outputs the process must have published by then (it runs the same code).

``--verify`` diffs each produced output against the recorded one field by field: exact for integers,
strings, booleans and integer arrays, ``--rtol``/``--atol`` for floats; header.seq, header.source and
header.pub_ns are ignored. A recording thus becomes a regression test.
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import json
import logging
import math
import os
import queue
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict, deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import yaml

from followbus.bus.codec import HEADER_KEY, DecodeError, Peeked, _split, peek
from followbus.bus.graph import Graph, GraphError, NodeSpec, load_graph
from followbus.bus.inproc import InProcessError, InProcessGraph
from followbus.bus.schemas import Message, ReplayHint, decode
from followbus.tools.mcap_io import (
    BusMessage,
    RecordingError,
    bus_channels,
    is_bus_channel,
    iter_bus_messages,
    read_metadata,
    read_summary,
)

log = logging.getLogger("followbus.replay")

IGNORED_HEADER_FIELDS = ("seq", "source", "pub_ns")
_IGNORED_HEADER_INDEXES = (0, 3, 4)  # their places in the header array (bus.codec.HEADER_FIELDS)
LOCKSTEP_QUEUE = 64  # --isolated: inputs queue deep and block, whatever the live policy was
PREFETCH = 64  # recorded messages read ahead by the reading thread
LOOKAHEAD_BYTES = 256 * 1024 * 1024  # inputs held back while reading ahead for what live did with a frame
MAX_REPORTED = 1000  # mismatch details kept in the report (the count is always exact)
REPLAY_SHM_BYTES = 256 * 1024 * 1024


# --- field-by-field comparison ---------------------------------------------------------------------

@dataclass
class Tolerance:
    rtol: float = 1e-6
    atol: float = 1e-6


@dataclass
class Difference:
    field: str
    recorded: Any
    replayed: Any


def _show(value: Any) -> Any:
    """A JSON-friendly rendering of a value in a report."""
    if isinstance(value, np.ndarray):
        return value.tolist() if value.size <= 16 else f"<array {value.dtype} {list(value.shape)}>"
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _first_index(mask: np.ndarray) -> str:
    idx = np.argwhere(~mask)[0]
    return "".join(f"[{int(i)}]" for i in idx)


def _diff_array(path: str, a: np.ndarray, b: np.ndarray, tol: Tolerance) -> Difference | None:
    if a.shape != b.shape:
        return Difference(f"{path}.shape", list(a.shape), list(b.shape))
    exact = a.dtype.kind in "biuSUO" and b.dtype.kind in "biuSUO"
    if a.dtype.kind != b.dtype.kind and not (a.dtype.kind in "iu" and b.dtype.kind in "iu"):
        return Difference(f"{path}.dtype", str(a.dtype), str(b.dtype))
    if a.size == 0:
        return None
    if exact:
        mask = np.asarray(a == b)
    else:
        mask = np.isclose(a.astype(np.float64), b.astype(np.float64), rtol=tol.rtol, atol=tol.atol, equal_nan=True)
    if mask.all():
        return None
    idx = np.argwhere(~mask)[0]
    where = tuple(int(i) for i in idx)
    return Difference(path + _first_index(mask), _show(a[where]), _show(b[where]))


def diff_values(path: str, a: Any, b: Any, tol: Tolerance) -> Difference | None:
    """The first difference between two decoded values, or None."""
    if a is None or b is None:
        return None if a is None and b is None else Difference(path, _show(a), _show(b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return Difference(path, _show(a), _show(b))
        return _diff_array(path, a, b, tol)
    if isinstance(a, bool) or isinstance(b, bool):
        return None if (type(a) is type(b) and a == b) else Difference(path, a, b)
    if isinstance(a, int) and isinstance(b, int):
        return None if a == b else Difference(path, a, b)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        if math.isnan(a) and math.isnan(b):
            return None
        return None if math.isclose(a, b, rel_tol=tol.rtol, abs_tol=tol.atol) else Difference(path, a, b)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return Difference(f"{path}.length", len(a), len(b))
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            d = diff_values(f"{path}[{i}]", x, y, tol)
            if d is not None:
                return d
        return None
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                return Difference(f"{path}.{k}", _show(a.get(k)), _show(b.get(k)))
            d = diff_values(f"{path}.{k}", a[k], b[k], tol)
            if d is not None:
                return d
        return None
    return None if (type(a) is type(b) and a == b) else Difference(path, _show(a), _show(b))


def diff_messages(recorded: Message, replayed: Message, tol: Tolerance) -> Difference | None:
    """First differing field of two messages; header.seq/source/pub_ns are not compared."""
    if recorded.TYPE != replayed.TYPE:
        return Difference("type", recorded.TYPE, replayed.TYPE)
    for f in dataclasses.fields(recorded.header):
        if f.name in IGNORED_HEADER_FIELDS:
            continue
        a, b = getattr(recorded.header, f.name), getattr(replayed.header, f.name)
        if a != b:
            return Difference(f"header.{f.name}", a, b)
    for f in dataclasses.fields(recorded):
        if f.name == "header":
            continue
        d = diff_values(f.name, getattr(recorded, f.name), getattr(replayed, f.name), tol)
        if d is not None:
            return d
    return None


def _same_bytes(a: bytes, b: bytes) -> bool:
    """Identical but for the ignored header fields, judged on the frames without decoding any array: most
    outputs of a replay are, and this costs microseconds where a field-by-field diff costs a decode."""
    try:
        (head_a, blobs_a), (head_b, blobs_b) = _split(a), _split(b)
        map_a, map_b = msgpack.unpackb(head_a), msgpack.unpackb(head_b)
        for m in (map_a, map_b):
            header = m[HEADER_KEY]
            for i in _IGNORED_HEADER_INDEXES:
                header[i] = None
    except Exception:  # malformed: the decoding diff reports it
        return False
    return map_a == map_b and blobs_a == blobs_b


def compare_output(recorded: bytes, replayed: bytes, tol: Tolerance) -> Difference | None:
    if _same_bytes(recorded, replayed):
        return None
    try:
        return diff_messages(decode(recorded), decode(replayed), tol)
    except DecodeError as exc:
        return Difference("<decode>", "decodable", str(exc))


# --- reading the recording -------------------------------------------------------------------------

def _peek_header(data: bytes) -> Peeked | None:
    """Type and header of a stored bus message without decoding its fields (None: not a followbus frame)."""
    try:
        return peek(data)
    except DecodeError:
        return None


def _header(data: bytes) -> tuple[int, int]:
    """(frame_seq, stamp_ns) of a stored bus message."""
    head = _peek_header(data)
    return (head.header.frame_seq, head.header.stamp_ns) if head is not None else (-1, 0)


def recording_first_frame(path: Path, look_at: int = 200) -> int | None:
    """The lowest frame_seq among the recording's first messages (log time = capture stamp, so the run's
    first recorded frame is among them); None when none carries a frame."""
    seqs = []
    for k, msg in enumerate(iter_bus_messages(path)):
        if k >= look_at:
            break
        frame_seq = _header(msg.data)[0]
        if frame_seq >= 0:
            seqs.append(frame_seq)
    return min(seqs) if seqs else None


@dataclass
class Input:
    """A recorded input message and its header, peeked once."""

    msg: BusMessage
    frame_seq: int
    stamp_ns: int
    pub_ns: int


def causal_order(messages: Iterable[Input]) -> Iterator[Input]:
    """Messages in the order they were published (header.pub_ns, one host's clock).

    The recording is in log-time order, log time being the capture stamp of the frame a message derives
    from; the order a node saw its inputs is the order they were published (the odometry sample sent
    5 ms after frame k's capture comes before the measurement of frame k sent 22 ms after it). A message
    is published after its capture (pub_ns >= log_time), so once the stream reaches log time L every
    buffered message published before L is final: the reorder buffer holds only the in-flight window.

    Messages of no frame (odometry) keep their stamp order instead: a node picks among them by stamp and
    a replay repeats the live choice (provenance notes), so handing each over at the earliest moment it
    could have existed is safe, whereas its publication time under load could make it late.
    """
    heap: list[tuple[int, int, int, Input]] = []
    for counter, item in enumerate(messages):
        msg = item.msg
        while heap and heap[0][0] < msg.log_time:
            yield heapq.heappop(heap)[3]
        pub = msg.log_time if item.frame_seq < 0 else (item.pub_ns or msg.log_time)
        heapq.heappush(heap, (max(pub, msg.log_time), msg.sequence, counter, item))
    while heap:
        yield heapq.heappop(heap)[3]


def prefetch(items: Iterable[Any], depth: int) -> Iterator[Any]:
    """Iterate in a thread ``depth`` items ahead: reading and decompressing the recording overlaps with
    the node's work (lz4 releases the GIL)."""
    box: queue.Queue[Any] = queue.Queue(maxsize=depth)
    done = object()
    stop = threading.Event()

    def run() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        box.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
        except BaseException as exc:  # handed to the consumer
            box.put(exc)
        box.put(done)

    thread = threading.Thread(target=run, name="replay-read", daemon=True)
    thread.start()
    try:
        while True:
            item = box.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()


# --- options, plan, report -------------------------------------------------------------------------

def parse_param_overrides(items: list[str]) -> dict[str, Any]:
    out = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--param {item!r} must look like key=value (value in YAML syntax)")
        try:
            out[key.strip()] = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise ValueError(f"--param {item!r}: value is not valid YAML ({exc})") from exc
    return out


@dataclass
class ReplayOptions:
    nodes: list[str]
    graph_path: str | None = None
    params: dict[str, Any] = field(default_factory=dict)  # one node: key -> value; several: "node.key" -> value
    verify: bool = False
    isolated: bool = False
    tolerance: Tolerance = field(default_factory=Tolerance)
    frame_timeout_s: float = 5.0
    startup_timeout_s: float = 60.0
    max_frames: int = 0
    progress: bool = True


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
    extra: list[dict[str, Any]] = field(default_factory=list)  # produced, not in the recording
    beyond_end: int = 0  # produced for frames after the recording's last output on that key (not compared)
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


class ReplayPlan:
    """What is replayed: the graph as recorded (params applied), the nodes, and which recorded keys are
    their inputs (produced outside them) and their outputs."""

    def __init__(self, path: Path, options: ReplayOptions):
        self.path = path
        meta = read_metadata(path)
        if options.graph_path:
            self.graph = load_graph(options.graph_path)
            recorded_params: dict[str, str] = {}  # an explicit graph brings its own params
        else:
            text = meta.get("graph", {}).get("yaml")
            if not text:
                raise RecordingError(f"{path}: no graph.yaml in the recording's metadata; pass --graph")
            self.graph = load_graph(f"{path}#graph.yaml", text)
            recorded_params = meta.get("params", {})
        self.nodes = list(dict.fromkeys(options.nodes))
        for name in self.nodes:
            if name not in self.graph.nodes:
                raise RecordingError(f"no node {name!r} in the graph (nodes: {', '.join(self.graph.nodes)})")
        overrides = self._split_overrides(options.params)
        self.params: dict[str, dict[str, Any]] = {}
        for name in self.nodes:
            spec = self.graph.nodes[name]
            params = json.loads(recorded_params[name]) if name in recorded_params else dict(spec.params)
            params.update(overrides.get(name, {}))
            spec.params = params  # what the runtime builds the node with
            self.params[name] = params
        self.recorded_ns = (meta.get("followbus", {}).get("namespace")) or self.graph.namespace
        replayed = set(self.nodes)
        # recorded key -> graph topic (node/output): inputs produced outside the replayed nodes, and their outputs
        self.inputs: dict[str, str] = {}
        for name in self.nodes:
            for inp in self.graph.nodes[name].inputs.values():
                if inp.source_node not in replayed:
                    self.inputs[f"{self.recorded_ns}/{inp.topic}"] = inp.topic
        self.outputs = {f"{self.recorded_ns}/{name}/{out}": f"{name}/{out}"
                        for name in self.nodes for out in self.graph.nodes[name].outputs}
        if not self.inputs:
            raise RecordingError(f"{', '.join(self.nodes)}: no inputs from outside: there is nothing to replay into")
        recorded = bus_channels(path)
        for key in self.inputs:
            if key not in recorded:
                log.warning("the recording has no messages on %s", key)
        if not any(key in recorded for key in self.inputs):
            raise RecordingError(f"{path}: none of the inputs were recorded ({', '.join(self.inputs)})")
        # Nodes whose live decisions are replayed: those with feedback inputs (bus.sync).
        self.feedback_inputs = {name: [i.name for i in self.graph.nodes[name].inputs.values()
                                       if i.sync == "frame" and i.offset] for name in self.nodes}
        self.feedback_inputs = {n: names for n, names in self.feedback_inputs.items() if names}

    def _split_overrides(self, params: dict[str, Any]) -> dict[str, dict[str, Any]]:
        if len(self.nodes) == 1:
            return {self.nodes[0]: dict(params)}
        out: dict[str, dict[str, Any]] = defaultdict(dict)
        for key, value in params.items():
            node, dot, param = key.partition(".")
            if not dot or node not in self.nodes:
                raise ValueError(f"--param {key}=...: with several nodes, name the node (node.param=value, "
                                 f"nodes: {', '.join(self.nodes)})")
            out[node][param] = value
        return out

    def output_node(self, key: str) -> str:
        return self.outputs[key].split("/", 1)[0]


# --- the feed: the recording read once -------------------------------------------------------------

class Feed:
    """The recording read once. Outputs of the replayed nodes become the expected outputs and the replay
    hints as they are read (log-time order: once the reader is past a frame's stamp, every output of that
    frame has been seen); inputs come out in publication order (:func:`causal_order`), grouped by frame,
    each group only once the reader knows what the live run did up to the next frame each node handled
    (a skipped frame is one with no output before a later handled one; whether a feedback message came
    late depends on that next frame's hint)."""

    def __init__(self, plan: ReplayPlan, report: ReplayReport):
        self.plan = plan
        self.report = report
        self.expected: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        self.hints: list[tuple[str, ReplayHint]] = []  # ready to be handed over
        self.eof = False
        self._log_time = -1  # of the newest message read
        self._open: dict[str, tuple[int, int, dict[str, int] | None]] = {}  # node -> (frame, stamp, provenance)
        self._handled: dict[str, int] = {}  # node -> newest frame whose hint is final
        self._previous: dict[str, int] = {}  # node -> newest frame handled live (for counting fallbacks)
        self._warned = False

    # outputs -> expected and hints
    def _read(self, messages: Iterable[BusMessage]) -> Iterator[Input]:
        for msg in messages:
            if msg.log_time > self._log_time:
                self._log_time = msg.log_time
                self._close_frames(msg.log_time)
            head = _peek_header(msg.data)
            frame_seq = head.header.frame_seq if head is not None else -1
            if msg.key not in self.plan.outputs:
                yield (Input(msg, frame_seq, head.header.stamp_ns, head.header.pub_ns) if head is not None
                       else Input(msg, -1, 0, 0))
                continue
            self.expected[(self.plan.outputs[msg.key], frame_seq)].append(msg.data)
            self.report.outputs_expected += 1
            node = self.plan.output_node(msg.key)
            if frame_seq < 0 or node not in self.plan.feedback_inputs or head is None:
                continue
            used = dict(head.header.feedback) if head.provenance else None
            open_ = self._open.get(node)
            if open_ is not None and open_[0] == frame_seq:
                if used:  # a frame's outputs together: the prior's feedback and notes, the track's notes
                    self._open[node] = (frame_seq, open_[1], {**(open_[2] or {}), **used})
            elif frame_seq > self._handled.get(node, -1) and (open_ is None or frame_seq > open_[0]):
                if open_ is not None:
                    self._finish(node, *open_)
                self._open[node] = (frame_seq, head.header.stamp_ns, used or None)
        self.eof = True
        for node, open_ in list(self._open.items()):
            self._finish(node, *open_)
        self._open.clear()

    def _close_frames(self, log_time: int) -> None:
        for node, open_ in list(self._open.items()):
            if open_[1] < log_time:
                self._finish(node, *open_)
                del self._open[node]

    def _finish(self, node: str, frame_seq: int, _stamp: int, used: dict[str, int] | None) -> None:
        """The hints of the frames up to ``frame_seq``: those in between were skipped live."""
        last = self._handled.get(node)
        if last is not None:
            for skipped in range(last + 1, frame_seq):
                self._hint(node, skipped, True, None)
        self._hint(node, frame_seq, False, used)
        self._handled[node] = frame_seq

    def _hint(self, node: str, frame_seq: int, skip: bool, used: dict[str, int] | None) -> None:
        if not (skip or used):
            return
        hint = ReplayHint(skip=skip, feedback=dict(used or {}))
        hint.header.frame_seq = frame_seq
        self.hints.append((node, hint))
        previous = self._previous.get(node)
        fallback = used is not None and previous is not None and any(
            used.get(name, previous) != previous for name in self.plan.feedback_inputs[node])
        self.report.hints += skip or fallback
        if not skip:
            self._previous[node] = frame_seq

    def _known(self, frame_seq: int) -> bool:
        """Does the reader know what each node did up to the next frame after ``frame_seq`` it handled?"""
        return self.eof or all(self._handled.get(node, -1) > frame_seq for node in self.plan.feedback_inputs)

    # inputs -> frame groups
    def groups(self) -> Iterator[tuple[list[tuple[str, ReplayHint]], int, list[Input]]]:
        """(hints to hand over first, frame_seq, the group's input messages: no-frame ones first)."""
        keys = set(self.plan.inputs) | set(self.plan.outputs)
        stream = causal_order(self._read(prefetch(iter_bus_messages(self.plan.path, keys), PREFETCH)))
        ready: deque[tuple[int, list[Input], int]] = deque()  # (frame_seq, messages, bytes)
        held = 0
        group: list[Input] = []
        group_seq: int | None = None
        done: set[int] = set()

        def release(force: bool):
            nonlocal held
            while ready and (force or self._known(ready[0][0]) or held > LOOKAHEAD_BYTES):
                if held > LOOKAHEAD_BYTES and not self._known(ready[0][0]) and not self._warned:
                    self._warned = True
                    log.warning("no output of the replayed node for %d MB of recording after frame %d: going "
                                "on without knowing whether live skipped the frames in between",
                                LOOKAHEAD_BYTES >> 20, ready[0][0])
                frame_seq, messages, size = ready.popleft()
                held -= size
                hints, self.hints = self.hints, []
                # Messages of no frame (odometry) first: a node picks among them by stamp, and what it picked
                # live is replayed from the hint, which needs the sample there before the frame's set.
                yield hints, frame_seq, sorted(messages, key=lambda m: m.frame_seq >= 0)

        for item in stream:
            frame_seq = item.frame_seq
            if frame_seq >= 0:
                if group_seq is not None and frame_seq > group_seq:
                    ready.append((group_seq, group, sum(len(m.msg.data) for m in group)))
                    held += ready[-1][2]
                    done.add(group_seq)
                    group, group_seq = [], None
                if group_seq is not None and frame_seq < group_seq or frame_seq in done:
                    self.report.late_inputs += 1  # out of stamp order: goes with the frame being assembled
                if group_seq is None:
                    group_seq = frame_seq
            group.append(item)  # messages of no frame (-1) go with the frame being assembled
            yield from release(False)
        if group:
            ready.append((group_seq if group_seq is not None else -1, group, 0))
        yield from release(True)


# --- the targets: in-process, or the deployed node as a process -----------------------------------

class InProcessTarget:
    """The nodes hosted here (bus.inproc), on the stamps clock; every input is delivered before the next."""

    def __init__(self, plan: ReplayPlan):
        self.plan = plan
        self.graph = InProcessGraph(plan.graph, nodes=plan.nodes, clock="stamps", record=plan.outputs.values())
        self.handler_s = 0.0
        self.decode_s = 0.0

    def start(self) -> None:
        self.graph.start()

    def hint(self, node: str, hint: ReplayHint) -> None:
        self.graph.hint(node, hint)

    def send(self, topic: str, data: bytes, stamp_ns: int, frame_seq: int) -> None:
        t0 = time.perf_counter()
        self.graph.inject_bytes(topic, data)  # decoded by each subscribed node
        t1 = time.perf_counter()
        self.graph.deliver()
        self.decode_s += t1 - t0
        self.handler_s += time.perf_counter() - t1

    def published(self, topic: str) -> int:
        return self.graph.published[topic]

    def produced(self) -> dict[str, list[bytes]]:
        return {t: self.graph.payloads(*t.split("/", 1)) for t in self.plan.outputs.values()}

    def close(self) -> None:
        self.graph.close()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def private_graph_text(graph: Graph, spec: NodeSpec, params: dict[str, Any], namespace: str, port: int) -> str:
    """graph.yaml of the node under test plus stand-ins for its producers (their outputs only)."""
    endpoint = f"tcp/127.0.0.1:{port}"
    inputs = {}
    producers: dict[str, list[str]] = defaultdict(list)
    for inp in spec.inputs.values():
        inputs[inp.name] = {"from": inp.topic, "queue": max(inp.queue, LOCKSTEP_QUEUE), "policy": "block",
                            "sync": inp.sync, "offset": inp.offset, "optional": inp.optional}
        if inp.source_output not in producers[inp.source_node]:
            producers[inp.source_node].append(inp.source_output)
    nodes: dict[str, Any] = {}
    for name, outputs in producers.items():
        if name != spec.name:
            nodes[name] = {"run": graph.nodes[name].run, "outputs": outputs}
    node_outputs = list(dict.fromkeys(spec.outputs + producers.get(spec.name, [])))
    nodes[spec.name] = {"run": spec.run, "inputs": inputs, "outputs": node_outputs, "params": params,
                        "sync_timeout_ms": spec.sync_timeout_ms, "restart": "never"}
    doc = {"name": f"replay-{spec.name}", "namespace": namespace,
           "zenoh": {"mode": "peer", "listen": [endpoint], "connect": [endpoint], "multicast_scouting": False,
                     "shm": graph.zenoh.shm},
           "nodes": nodes}
    return yaml.safe_dump(doc, sort_keys=False)


def _die_with_parent() -> None:  # runs in the child between fork and exec: the node never outlives us
    import ctypes

    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class IsolatedTarget:
    """The node as the deployed process (``followbus node NAME --clock stamps``) in a private graph over
    Zenoh. The in-process run of the same node, fed alongside, says how many outputs the process must have
    published before the next input goes out: lockstep without guessing when the process is idle."""

    def __init__(self, plan: ReplayPlan, report: ReplayReport, options: ReplayOptions, tmp: Path):
        if len(plan.nodes) != 1:
            raise ValueError("--isolated replays one node (several run in-process only)")
        self.plan = plan
        self.report = report
        self.opts = options
        self.reference = InProcessTarget(plan)
        self.name = plan.nodes[0]
        self.spec = plan.graph.nodes[self.name]
        self.private_ns = f"replay_{secrets.token_hex(4)}"
        self.tmp = tmp
        self.proc: subprocess.Popen | None = None
        self._cond = threading.Condition()
        self._received: dict[str, list[bytes]] = {t: [] for t in plan.outputs.values()}
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._session: Any = None
        self._watcher: Any = None
        self.log_path = tmp / "node.log"

    def start(self) -> None:
        from followbus.bus.health import HealthWatcher
        from followbus.bus.pubsub import Publisher, ShmPool, direct_callback
        from followbus.bus.session import open_session

        self.reference.start()
        graph_path = self.tmp / "graph.yaml"
        graph_path.write_text(private_graph_text(self.plan.graph, self.spec, self.plan.params[self.name],
                                                 self.private_ns, free_port()))
        private = load_graph(graph_path)
        self._session = open_session(private.zenoh)  # takes the private port first; the node connects to it
        for topic in self.plan.outputs.values():
            # Direct callbacks keep the order of samples across keys (bus.pubsub.direct_callback).
            self._subs.append(self._session.declare_subscriber(private.key(*topic.split("/", 1)),
                                                               direct_callback(self._on_output(topic))))
        shm = ShmPool(REPLAY_SHM_BYTES) if private.zenoh.shm else None
        for topic in self.plan.inputs.values():
            self._pubs[topic] = Publisher(self._session, private.key(*topic.split("/", 1)), "replay", shm=shm)
        self._hint_pub = Publisher(self._session, private.replay_hint_key(self.name), "replay")
        self._watcher = HealthWatcher(self._session, self.private_ns, watch_status=False)
        with open(self.log_path, "wb") as node_log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "followbus.tools.cli", "node", self.name, "--graph", str(graph_path),
                 "--clock", "stamps"],
                stdout=node_log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=dict(os.environ, PYTHONUNBUFFERED="1"), preexec_fn=_die_with_parent)
        t0 = time.perf_counter()
        missing = self._watcher.wait_for({self.name}, self.opts.startup_timeout_s)
        self.report.startup_s = time.perf_counter() - t0
        if self.proc.poll() is not None:
            raise RuntimeError(f"node {self.name} exited with status {self.proc.poll()}")
        if missing:
            raise RuntimeError(f"node {self.name} did not come up within {self.opts.startup_timeout_s:.0f} s")

    def _on_output(self, topic: str):
        def callback(sample) -> None:
            from followbus.bus.pubsub import payload_bytes

            data = payload_bytes(sample)
            with self._cond:
                self._received[topic].append(data)
                self._cond.notify_all()

        return callback

    def hint(self, node: str, hint: ReplayHint) -> None:
        self.reference.hint(node, hint)
        self._hint_pub.put(hint)

    def send(self, topic: str, data: bytes, stamp_ns: int, frame_seq: int) -> None:
        self.reference.send(topic, data, stamp_ns, frame_seq)
        self._pubs[topic].put_bytes(data, stamp_ns)
        if not self._wait_caught_up(self.opts.frame_timeout_s):
            self.report.timeouts.append(frame_seq)
            if self.proc is not None and self.proc.poll() is not None:
                raise RuntimeError(f"node {self.name} exited with status {self.proc.returncode}")

    def _wait_caught_up(self, timeout_s: float) -> bool:
        """Wait until the process published what the in-process run published by now."""
        want = {t: self.reference.published(t) for t in self._received}
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not all(len(self._received[t]) >= n for t, n in want.items()):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.proc is not None and self.proc.poll() is not None):
                    return False
                self._cond.wait(min(remaining, 0.2))
        return True

    def produced(self) -> dict[str, list[bytes]]:
        with self._cond:
            return {t: list(v) for t, v in self._received.items()}

    def close(self) -> None:
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
            self.report.node_exit = self.proc.returncode
            if self.report.error or self.report.node_exit not in (0, None):
                tail = self.log_path.read_text(errors="replace").splitlines()[-30:] if self.log_path.exists() else []
                if tail:
                    log.error("node log (last lines):\n%s", "\n".join(tail))
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        if self._watcher is not None:
            self._watcher.close()
        if self._session is not None:
            with contextlib.suppress(Exception):
                self._session.close()
        self.reference.close()


# --- the replay ------------------------------------------------------------------------------------

class Replayer:
    def __init__(self, path: Path, options: ReplayOptions):
        self.path = path
        self.opts = options
        self.plan = ReplayPlan(path, options)
        params: dict[str, Any] = (self.plan.params[self.plan.nodes[0]] if len(self.plan.nodes) == 1
                                  else dict(self.plan.params))
        self.report = ReplayReport(file=str(path), node=",".join(self.plan.nodes),
                                   mode="isolated" if options.isolated else "in-process", params=params)
        if options.isolated and len(self.plan.nodes) != 1:
            raise ValueError("--isolated replays one node (several run in-process only)")
        # Built now: a --param the node does not take is the user's mistake, said before anything runs.
        self._inproc = None if options.isolated else InProcessTarget(self.plan)

    def run(self) -> ReplayReport:
        with tempfile.TemporaryDirectory(prefix="followbus-replay-") as tmp:
            target = self._inproc or IsolatedTarget(self.plan, self.report, self.opts, Path(tmp))
            try:
                target.start()
                self.report.recording_first_frame = recording_first_frame(self.path)
                self._feed(target)
            except (RuntimeError, InProcessError) as exc:
                self.report.error = str(exc)
            finally:
                target.close()
        return self.report

    def _feed(self, target: InProcessTarget | IsolatedTarget) -> None:
        feed = Feed(self.plan, self.report)
        bar = self._progress()
        started = time.perf_counter()
        first_stamp = last_stamp = None
        done_frames: set[int] = set()
        try:
            for hints, frame_seq, messages in feed.groups():
                if self.opts.max_frames and frame_seq >= 0 and self.report.frames >= self.opts.max_frames:
                    break
                for node, hint in hints:
                    target.hint(node, hint)
                for item in messages:
                    stamp = item.stamp_ns
                    target.send(self.plan.inputs[item.msg.key], item.msg.data, stamp, frame_seq)
                    self.report.inputs_sent += 1
                    if stamp:
                        first_stamp = stamp if first_stamp is None else min(first_stamp, stamp)
                        last_stamp = stamp if last_stamp is None else max(last_stamp, stamp)
                if frame_seq >= 0:
                    self.report.frames += 1
                    done_frames.add(frame_seq)
                    bar.update(1)
        finally:
            bar.close()
            produced = target.produced()
            self._compare(feed.expected, produced, done_frames)
            self.report.wall_s = time.perf_counter() - started
        if isinstance(target, InProcessTarget):
            self.report.handler_s, self.report.decode_s = target.handler_s, target.decode_s
        if first_stamp is not None and last_stamp is not None:
            self.report.recorded_span_s = (last_stamp - first_stamp) / 1e9
        if self.report.wall_s > 0:
            self.report.speed_x = self.report.recorded_span_s / self.report.wall_s

    def _compare(self, expected: dict[tuple[str, int], list[bytes]], produced: dict[str, list[bytes]],
                 done_frames: set[int]) -> None:
        """Diff what was produced with what was recorded, frame by frame and output by output; then list
        recorded-but-never-produced and produced-but-not-recorded outputs."""
        by_frame: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        for topic, items in produced.items():
            self.report.outputs_received += len(items)
            for data in items:
                by_frame[(topic, _header(data)[0])].append(data)
        last_recorded: dict[str, int] = {}
        for topic, fs in expected:
            last_recorded[topic] = max(last_recorded.get(topic, -1), fs)
        key = {topic: f"{self.plan.recorded_ns}/{topic}" for topic in self.plan.outputs.values()}
        for (topic, fs), recorded in sorted(expected.items()):
            if self.opts.max_frames and fs not in done_frames:
                continue  # beyond --max-frames
            replayed = by_frame.get((topic, fs), [])
            for i in range(min(len(recorded), len(replayed))):
                self.report.outputs_compared += 1
                diff = compare_output(recorded[i], replayed[i], self.opts.tolerance)
                if diff is None:
                    self.report.matched += 1
                    continue
                self.report.mismatch_count += 1
                if len(self.report.mismatches) < MAX_REPORTED:
                    self.report.mismatches.append({"frame_seq": fs, "key": key[topic], "index": i,
                                                   "field": diff.field, "recorded": _show(diff.recorded),
                                                   "replayed": _show(diff.replayed)})
            for i in range(len(replayed), len(recorded)):
                self.report.missing.append({"frame_seq": fs, "key": key[topic], "index": i})
        for (topic, fs), replayed in sorted(by_frame.items()):
            n_exp = len(expected.get((topic, fs), []))
            if fs > last_recorded.get(topic, -1):
                # The recording stopped between this frame's inputs and its outputs: nothing to compare.
                self.report.beyond_end += len(replayed) - n_exp
                continue
            for i in range(n_exp, len(replayed)):
                self.report.extra.append({"frame_seq": fs, "key": key[topic], "index": i})

    def _progress(self):
        from tqdm import tqdm

        summary = read_summary(self.path)
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        primary = next((f"{self.plan.recorded_ns}/{i.topic}" for n in self.plan.nodes
                        for i in self.plan.graph.nodes[n].inputs.values()
                        if i.sync == "frame" and not i.offset and not i.optional
                        and f"{self.plan.recorded_ns}/{i.topic}" in self.plan.inputs), None)
        total = sum(counts.get(ch.id, 0) for ch in summary.channels.values()
                    if ch.topic == primary and is_bus_channel(ch))
        if self.opts.max_frames:
            total = min(total, self.opts.max_frames) if total else self.opts.max_frames
        return tqdm(total=total or None, unit="frame", desc=f"replay {self.report.node}", file=sys.stderr,
                    disable=None if self.opts.progress else True, dynamic_ncols=True)  # None: TTY only


# --- command ---------------------------------------------------------------------------------------

def _print_summary(report: ReplayReport, verify: bool) -> None:
    print(f"replayed {report.frames} frames ({report.inputs_sent} input messages) into {report.node} "
          f"({report.mode}) in {report.wall_s:.2f} s: {report.speed_x:.1f}x real time over "
          f"{report.recorded_span_s:.2f} s recorded")
    if report.mode == "in-process" and report.wall_s > 0:
        node_s = report.handler_s + report.decode_s
        print(f"node time: {report.handler_s:.2f} s handlers + {report.decode_s:.2f} s decoding = {node_s:.2f} s; "
              f"replay time {report.wall_s / node_s if node_s else math.inf:.2f}x that "
              f"(the rest: reading the recording, ordering, diffing)")
    elif report.startup_s:
        print(f"node process up in {report.startup_s:.2f} s (not counted above)")
    print(f"outputs: {report.outputs_expected} recorded, {report.outputs_received} produced, "
          f"{report.outputs_compared} compared, {report.matched} identical, {report.mismatch_count} differing, "
          f"{len(report.missing)} missing, {len(report.extra)} extra"
          + (f"; {len(report.timeouts)} frame timeouts" if report.mode == "isolated" else ""))
    if report.hints:
        print(f"live fallbacks reproduced: {report.hints} frames skipped or joined older feedback live "
              "(a late feedback, a skipped backlog), and were replayed the same way")
    if report.recording_first_frame:
        print(f"note: the recording starts at frame {report.recording_first_frame} of the run (recorded mid-run): "
              "the node starts without the state it had built before (template, track state, filter), so its first "
              "outputs can differ until that state converges; `followbus launch --record` records from frame 0")
    if report.mismatches:
        first = min(report.mismatches, key=lambda m: (m["frame_seq"], m["key"], m["index"]))
        print(f"first mismatch: frame {first['frame_seq']}, key {first['key']} (#{first['index']}), field "
              f"{first['field']}: recorded {first['recorded']!r}, replayed {first['replayed']!r}")
    if report.missing:
        m = report.missing[0]
        print(f"first missing output: frame {m['frame_seq']}, key {m['key']}")
    if report.extra:
        m = report.extra[0]
        print(f"first extra output: frame {m['frame_seq']}, key {m['key']}")
    if report.error:
        print(f"error: {report.error}")
    if verify and not report.outputs_compared and not report.error:
        print(f"verify: FAILED: nothing compared (the recording holds no output of {report.node} for the frames "
              "replayed; record the node's outputs too, e.g. `followbus launch --record`)")
    elif verify:
        print("verify: " + ("OK" if report.ok(True) else "FAILED"))
    sys.stdout.flush()


def cmd_replay(args) -> int:
    try:
        options = ReplayOptions(
            nodes=[n.strip() for n in args.node.split(",") if n.strip()], graph_path=args.graph,
            params=parse_param_overrides(args.param or []), verify=args.verify, isolated=args.isolated,
            tolerance=Tolerance(args.rtol, args.atol), frame_timeout_s=args.timeout,
            startup_timeout_s=args.startup_timeout, max_frames=args.max_frames or 0, progress=not args.no_progress)
        if not options.nodes:
            raise ValueError("--node: name a node (or several, comma-separated)")
        replayer = Replayer(Path(args.file), options)
    except (RecordingError, ValueError, GraphError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    report = replayer.run()
    _print_summary(report, args.verify)
    if args.report:
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        Path(args.report).write_text(json.dumps(dataclasses.asdict(report), indent=1, default=str))
    return 0 if report.ok(args.verify) else 1
