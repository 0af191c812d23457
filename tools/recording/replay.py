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
strings, booleans and integer arrays, ``--rtol``/``--atol`` for floats; header.seq, header.source,
header.pub_ns and the measured times a message type declares (``MEASURED``) are ignored, and so are a
timer's outputs of no frame (live they tick on the wall clock). A recording thus becomes a regression test.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import msgpack
import numpy as np
import yaml

from ...bus.codec import HEADER_KEY, DecodeError, _split
from ...bus.graph import GraphError, load_graph
from ...bus.inproc import InProcessError, InProcessGraph
from ...bus.node import load_node_class
from ...bus.recording import (
    RecordingError,
    bus_channels,
    chunks_to_skip,
    is_bus_channel,
    read_metadata,
    read_summary,
)
from ...bus.schemas import Message, ReplayHint, decode
from ...msgs import catalogue  # noqa: F401  (followbus's message types: decodable)
from .replay_feed import Feed, _header, recording_first_frame

log = logging.getLogger("followbus.replay")

IGNORED_HEADER_FIELDS = ("seq", "source", "pub_ns")
_IGNORED_HEADER_INDEXES = (0, 3, 4)  # their places in the header array (bus.codec.HEADER_FIELDS)
MAX_REPORTED = 1000  # mismatch details kept in the report (the count is always exact)


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
    """First differing field of two messages; header.seq/source/pub_ns and measured times (``MEASURED``, e.g.
    Detections.infer_ms) are not compared."""
    if recorded.TYPE != replayed.TYPE:
        return Difference("type", recorded.TYPE, replayed.TYPE)
    for f in dataclasses.fields(recorded.header):
        if f.name in IGNORED_HEADER_FIELDS:
            continue
        a, b = getattr(recorded.header, f.name), getattr(replayed.header, f.name)
        if a != b:
            return Difference(f"header.{f.name}", a, b)
    for f in dataclasses.fields(recorded):
        if f.name == "header" or f.name in recorded.MEASURED:
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
            problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise ValueError(f"--param {item!r}: value is not valid YAML ({problem})") from exc
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
        key = load_node_class(spec.run).STATE_FILE_PARAM
    except ImportError:
        return
    if key and params.get(key) and key not in given:
        log.info("%s: %s=%s not used by the replay (the live graph's state)", name, key, params[key])
        params[key] = ""


class ReplayPlan:
    """What is replayed: the graph as recorded (params applied), the nodes, and which recorded keys are
    their inputs (produced outside them) and their outputs."""

    def __init__(self, path: Path, options: ReplayOptions):
        self.path = path
        recorded = bus_channels(path)  # first: a file that is not a finalised recording is named as such
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
            _forget_state_file(name, spec, params, overrides.get(name, {}))
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
        # recorded keys a frame's outputs cannot exist without: required same-frame inputs from outside
        self.required_inputs = {f"{self.recorded_ns}/{inp.topic}" for name in self.nodes
                                for inp in self.graph.nodes[name].inputs.values()
                                if inp.source_node not in replayed and inp.sync == "frame" and not inp.offset
                                and not inp.optional}
        # recorded keys of outside inputs that belong to a frame (any offset, optional or not)
        self.frame_inputs = {f"{self.recorded_ns}/{inp.topic}" for name in self.nodes
                             for inp in self.graph.nodes[name].inputs.values()
                             if inp.source_node not in replayed and inp.sync == "frame"}
        if not self.inputs:
            raise RecordingError(f"{', '.join(self.nodes)}: no inputs from outside: there is nothing to replay into")
        for key in self.inputs:
            if key not in recorded:
                log.warning("the recording has no messages on %s", key)
        if not any(key in recorded for key in self.inputs):
            raise RecordingError(f"{path}: none of the inputs were recorded ({', '.join(self.inputs)})")
        # Before the node sees anything: a corrupt chunk would make --verify blame the node for the damage.
        self.skip_chunks = chunks_to_skip(path, set(self.inputs) | set(self.outputs), options.on_corrupt)
        # Nodes whose live decisions are replayed: those with feedback inputs (bus.sync).
        self.feedback_inputs = {name: [i.name for i in self.graph.nodes[name].inputs.values()
                                       if i.sync == "frame" and i.offset] for name in self.nodes}
        self.feedback_inputs = {n: names for n, names in self.feedback_inputs.items() if names}
        # (node, feedback input) -> recorded key, for feedback produced outside the replayed nodes
        self.feedback_keys = {(name, i.name): f"{self.recorded_ns}/{i.topic}" for name in self.nodes
                              for i in self.graph.nodes[name].inputs.values()
                              if i.sync == "frame" and i.offset and i.source_node not in replayed}
        # Outputs of no frame from a node with a timer (motor's odometry and watchdog stops) come from ticks of
        # the wall clock live and of the stamps in a replay: not comparable, counted apart.
        self.timer_topics = {topic for key, topic in self.outputs.items()
                             if self._has_timer(self.output_node(key))}

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

    def _has_timer(self, node: str) -> bool:
        try:
            return bool(load_node_class(self.graph.nodes[node].run).TIMER_PERIOD_MS)
        except ImportError:
            return False  # said as a graph error (file:line) when the node is built

    def output_node(self, key: str) -> str:
        return self.outputs[key].split("/", 1)[0]


# --- the targets: in-process here, or the deployed node as a process (tools/recording/replay_isolated.py) ---------

class Target(Protocol):
    def start(self) -> None: ...
    def hint(self, node: str, hint: ReplayHint) -> None: ...
    def send(self, topic: str, data: bytes, stamp_ns: int, frame_seq: int) -> None: ...
    def produced(self) -> dict[str, list[bytes]]: ...
    def close(self) -> None: ...


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
        self.graph.inject_bytes(topic, data, stamp_ns)  # decoded by each subscribed node
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
        # (--isolated: the in-process run that steps the process.)
        self._inproc = InProcessTarget(self.plan)

    def run(self) -> ReplayReport:
        with tempfile.TemporaryDirectory(prefix="followbus-replay-") as tmp:
            target: Target = self._inproc
            if self.opts.isolated:
                from .replay_isolated import IsolatedTarget

                target = IsolatedTarget(self._inproc, self.report, self.opts, Path(tmp))
            try:
                target.start()
                self.report.recording_first_frame = recording_first_frame(self.path, self.plan.skip_chunks)
                self._feed(target)
            except (RuntimeError, InProcessError) as exc:
                self.report.error = str(exc)
            finally:
                target.close()
        return self.report

    def _feed(self, target: Target) -> None:
        feed = Feed(self.plan)
        bar = self._progress()
        started = time.perf_counter()
        first_stamp = last_stamp = None
        done_frames: set[int] = set()
        sent: dict[int, set[str]] = defaultdict(set)  # frame -> recorded input keys fed for it
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
                    sent[item.frame_seq].add(item.msg.key)
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
            required = self.plan.required_inputs
            # Frames the node cannot reproduce from this recording: a required input of the frame is not in
            # it, the feedback the frame joined live is not, or an input's stream ends before the frame (the
            # recorder stopped first: prediction's track k comes from re-ID's measurement k, say).
            stream_end: dict[str, int] = {}
            for fs, keys in sent.items():
                for key in keys & self.plan.frame_inputs:
                    stream_end[key] = max(stream_end.get(key, -1), fs)
            incomplete = {fs for _topic, fs in feed.expected if fs >= 0 and (
                (required and not required <= sent.get(fs, set()))
                or any(key not in sent.get(joined, set()) for key, joined in feed.joined.get(fs, ()))
                or any(end < fs for end in stream_end.values()))}
            self._compare(feed.expected, produced, done_frames, incomplete)
            self.report.wall_s = time.perf_counter() - started
            self.report.outputs_expected = feed.outputs_expected
            self.report.hints, self.report.late_inputs = feed.hints_reproduced, feed.late_inputs
        if isinstance(target, InProcessTarget):
            self.report.handler_s, self.report.decode_s = target.handler_s, target.decode_s
        if first_stamp is not None and last_stamp is not None:
            self.report.recorded_span_s = (last_stamp - first_stamp) / 1e9
        if self.report.wall_s > 0:
            self.report.speed_x = self.report.recorded_span_s / self.report.wall_s

    def _compare(self, expected: dict[tuple[str, int], list[bytes]], produced: dict[str, list[bytes]],
                 done_frames: set[int], incomplete: set[int] = frozenset()) -> None:
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
            if fs < 0 and topic in self.plan.timer_topics:
                self.report.timer_outputs += len(recorded)
                continue
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
            if fs in incomplete and len(replayed) < len(recorded):
                self.report.unverifiable += len(recorded) - len(replayed)
                continue
            for i in range(len(replayed), len(recorded)):
                self.report.missing.append({"frame_seq": fs, "key": key[topic], "index": i})
        for (topic, fs), replayed in sorted(by_frame.items()):
            if fs < 0 and topic in self.plan.timer_topics:
                continue
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
    if report.timer_outputs:
        print(f"not compared: {report.timer_outputs} recorded outputs of the node's timer (no frame: odometry, "
              "watchdog stops); live it ticks on the wall clock, a replay on the message stamps")
    if report.unverifiable:
        print(f"not verifiable: {report.unverifiable} recorded outputs of frames whose inputs are not all in "
              "the recording (the recorder joined late, dropped them, or stopped before them); "
              "the node cannot produce them")
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
            startup_timeout_s=args.startup_timeout, max_frames=args.max_frames or 0, progress=not args.no_progress,
            on_corrupt=args.on_corrupt)
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
