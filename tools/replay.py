"""``followbus replay FILE --node NAME``: lockstep replay of a recording into one node.

The node runs as its own process (``followbus node NAME --clock stamps``) in a private graph: a
private namespace on a private loopback port, its spec as recorded (graph.yaml text and effective
params from the file's metadata, or ``--graph``), params overridden by ``--param``. Frame by frame,
in the recording's order (log time, then recording order), the recorded messages that are its
inputs are published with their original bytes; then the replayer waits until the node has produced,
on each output, as many messages for that frame as the recording holds, before sending the next
frame. The node's clock follows the message stamps, so nothing depends on the wall clock.

``--verify`` diffs each produced output against the recorded one field by field: exact for
integers, strings, booleans and integer arrays, ``--rtol``/``--atol`` for floats; header.seq,
header.source and header.pub_ns are ignored. A recording thus becomes a regression test.
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
from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from followbus.bus.codec import DecodeError, Peeked, peek
from followbus.bus.graph import Graph, GraphError, NodeSpec, load_graph
from followbus.bus.schemas import Message, decode
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
LOCKSTEP_QUEUE = 64  # inputs queue deep and block: lockstep never drops, whatever the live policy was
PREFETCH = 64  # recorded messages read ahead
MAX_REPORTED = 1000  # mismatch details kept in the report (the count is always exact)
REPLAY_SHM_BYTES = 256 * 1024 * 1024
QUIET_S = 0.3  # no output and no CPU for this long: the node waits for input (or is done)
IDLE_CPU_TICKS = 3  # clock ticks (10 ms) a waiting node may still spend in that time (zenoh, status thread)


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


# --- the private graph -----------------------------------------------------------------------------

def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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


# --- the replay ------------------------------------------------------------------------------------

@dataclass
class ReplayOptions:
    node: str
    graph_path: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    verify: bool = False
    tolerance: Tolerance = field(default_factory=Tolerance)
    frame_timeout_s: float = 5.0
    startup_timeout_s: float = 60.0
    max_frames: int = 0
    progress: bool = True


@dataclass
class ReplayReport:
    file: str
    node: str
    params: dict[str, Any] = field(default_factory=dict)
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
    timeouts: list[int] = field(default_factory=list)  # frames whose outputs did not all come in time
    deferred_frames: int = 0  # frames not awaited at once: their set waited for a later stamp
    late_inputs: int = 0
    hints: int = 0  # frames told to skip, or to join the feedback the live run joined (a live fallback)
    startup_s: float = 0.0
    wall_s: float = 0.0
    recorded_span_s: float = 0.0
    speed_x: float = 0.0
    node_exit: int | None = None
    error: str = ""

    def ok(self, verify: bool) -> bool:
        if self.error:
            return False
        # Nothing compared proves nothing: a verify that checked no output must not pass.
        return not verify or not (self.mismatch_count or self.missing or self.extra or not self.outputs_compared)


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


def _provenance(data: bytes) -> dict[str, int] | None:
    """header.feedback of a stored bus message (None: recorded before provenance existed)."""
    head = _peek_header(data)
    return head.header.feedback if head is not None and head.provenance else None


def _pub_ns(data: bytes) -> int:
    head = _peek_header(data)
    return head.header.pub_ns if head is not None else 0


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


def causal_order(messages: Iterable[BusMessage]) -> Iterator[BusMessage]:
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
    heap: list[tuple[int, int, int, BusMessage]] = []
    for counter, msg in enumerate(messages):
        while heap and heap[0][0] < msg.log_time:
            yield heapq.heappop(heap)[3]
        pub = msg.log_time if _header(msg.data)[0] < 0 else (_pub_ns(msg.data) or msg.log_time)
        heapq.heappush(heap, (max(pub, msg.log_time), msg.sequence, counter, msg))
    while heap:
        yield heapq.heappop(heap)[3]


def prefetch(items: Iterable[Any], depth: int) -> Iterator[Any]:
    """Iterate in a thread ``depth`` items ahead: reading and decompressing the recording overlaps with
    the node's work on the frame in flight."""
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


class Replayer:
    def __init__(self, path: Path, options: ReplayOptions):
        self.path = path
        self.opts = options
        meta = read_metadata(path)
        fb = meta.get("followbus", {})
        if options.graph_path:
            self.graph = load_graph(options.graph_path)
            recorded_params = None  # an explicit graph brings its own params
        else:
            text = meta.get("graph", {}).get("yaml")
            if not text:
                raise RecordingError(f"{path}: no graph.yaml in the recording's metadata; pass --graph")
            self.graph = load_graph(f"{path}#graph.yaml", text)
            recorded_params = meta.get("params", {}).get(options.node)
        if options.node not in self.graph.nodes:
            raise RecordingError(f"no node {options.node!r} in the graph (nodes: {', '.join(self.graph.nodes)})")
        self.spec = self.graph.nodes[options.node]
        if not self.spec.inputs:
            raise RecordingError(f"node {options.node!r} has no inputs: there is nothing to replay into it")
        params = dict(self.spec.params) if recorded_params is None else json.loads(recorded_params)
        params.update(options.params)
        self.params = params
        self.recorded_ns = fb.get("namespace") or self.graph.namespace
        self.private_ns = f"replay_{secrets.token_hex(4)}"
        self.port = free_port()
        recorded = bus_channels(path)
        # recorded input key -> the node's input names it feeds; recorded output key -> output name
        self.input_keys: dict[str, list[str]] = defaultdict(list)
        for inp in self.spec.inputs.values():
            self.input_keys[f"{self.recorded_ns}/{inp.topic}"].append(inp.name)
        self.output_keys = {f"{self.recorded_ns}/{self.spec.name}/{out}": out for out in self.spec.outputs}
        for key in self.input_keys:
            if key not in recorded:
                log.warning("the recording has no messages on %s (input %s)", key, ", ".join(self.input_keys[key]))
        if not any(key in recorded for key in self.input_keys):
            raise RecordingError(f"{path}: none of {options.node}'s inputs were recorded "
                                 f"({', '.join(self.input_keys)})")
        self.report = ReplayReport(file=str(path), node=options.node, params=params)
        self._cond = threading.Condition()
        self._produced: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        self._expected: dict[tuple[str, int], list[bytes]] = defaultdict(list)
        self._compared: dict[tuple[str, int], int] = defaultdict(int)
        self._newest: dict[str, int] = {}  # newest frame_seq produced on each output
        self._last_output = 0.0
        self.proc: subprocess.Popen | None = None

    # --- bus side ---------------------------------------------------------------------------------
    def _on_output(self, out: str):
        def callback(sample) -> None:
            from followbus.bus.pubsub import payload_bytes

            data = payload_bytes(sample)
            frame_seq, _ = _header(data)
            with self._cond:
                self._produced[(out, frame_seq)].append(data)
                self._newest[out] = max(self._newest.get(out, -1), frame_seq)
                self._last_output = time.monotonic()
                self.report.outputs_received += 1
                self._cond.notify_all()

        return callback

    def _private_key(self, recorded_key: str) -> str:
        return self.private_ns + recorded_key[len(self.recorded_ns):]

    # --- frame bookkeeping ------------------------------------------------------------------------
    def _recorded_hints(self) -> tuple[dict[int, dict[str, int]], set[int]]:
        """(feedback each recorded output joined, frames with any recorded output) of the node: what the
        live run did, told to the replayed node frame by frame (bus.schemas.ReplayHint)."""
        provenance: dict[int, dict[str, int]] = {}
        handled: set[int] = set()
        for msg in iter_bus_messages(self.path, set(self.output_keys)):
            frame_seq, _ = _header(msg.data)
            if frame_seq < 0:
                continue
            handled.add(frame_seq)
            used = _provenance(msg.data)
            if used:  # a frame's outputs together: the prior's feedback and notes, the track's notes
                provenance.setdefault(frame_seq, {}).update(used)
        return provenance, handled

    def _hint_for(self, frame_seq: int) -> tuple[bool, dict[str, int] | None]:
        """What the live run did with this frame: (skipped, feedback joined and choices noted)."""
        if not self._feedback_sent or not self._live_handled:
            return False, None  # nothing to reproduce: no feedback inputs, or no outputs recorded
        skip = frame_seq not in self._live_handled and frame_seq > min(self._live_handled)
        return skip, None if skip else self._live_feedback.get(frame_seq)

    def _send_hints(self) -> None:
        """Tell the node what the live run did with every frame, before any input: whether a feedback message
        must wait for a later set (it reached the live node after that set) depends on the hints of frames
        whose inputs have not been sent yet. Counts the frames where live did not do the ordinary thing."""
        from followbus.bus.schemas import ReplayHint

        if not self._feedback_sent or not self._live_handled:
            return
        previous = None
        for frame_seq in range(min(self._live_handled), max(self._live_handled) + 1):
            skip, used = self._hint_for(frame_seq)
            if not (skip or used):
                continue
            hint = ReplayHint(skip=skip, feedback=dict(used or {}))
            hint.header.frame_seq = frame_seq
            self._hint_pub.put(hint)
            fallback = used is not None and previous is not None and any(
                used.get(name, previous) != previous for name in self._feedback_sent)
            self.report.hints += skip or fallback
            if not skip:
                previous = frame_seq

    def _frame_inputs_complete(self, names: set[str], last_handled: int | None,
                               forced: dict[str, int] | None = None) -> tuple[bool, bool]:
        """(complete, required same-frame inputs present) of a frame set, as the node's synchroniser sees it."""
        complete = required = True
        for inp in self.spec.inputs.values():
            if inp.sync != "frame":
                continue
            if inp.offset:
                wanted = forced[inp.name] if forced and inp.name in forced else last_handled
                if wanted is not None and wanted >= 0 and wanted not in self._feedback_sent[inp.name]:
                    complete = False
            elif inp.name not in names:
                complete = False
                required = required and inp.optional
        return complete, required

    def _compare(self, out: str, frame_seq: int) -> None:
        """Compare what is new for (output, frame) since the last call."""
        with self._cond:
            produced = list(self._produced.get((out, frame_seq), []))
        expected = self._expected.get((out, frame_seq), [])
        done = self._compared[(out, frame_seq)]
        key = f"{self.recorded_ns}/{self.spec.name}/{out}"
        for i in range(done, min(len(produced), len(expected))):
            self.report.outputs_compared += 1
            try:
                diff = diff_messages(decode(expected[i]), decode(produced[i]), self.opts.tolerance)
            except DecodeError as exc:
                diff = Difference("<decode>", "decodable", str(exc))
            if diff is None:
                self.report.matched += 1
                continue
            self.report.mismatch_count += 1
            if len(self.report.mismatches) < MAX_REPORTED:
                self.report.mismatches.append({"frame_seq": frame_seq, "key": key, "index": i, "field": diff.field,
                                               "recorded": _show(diff.recorded), "replayed": _show(diff.replayed)})
        self._compared[(out, frame_seq)] = max(done, min(len(produced), len(expected)))

    def _outputs_ready(self, frame_seq: int) -> bool:
        """All recorded outputs of the frame produced, or passed: a node emits each output in frame order,
        so once it produced a later frame on an output, what it did not produce for this one never comes."""
        return all(len(self._produced.get((out, frame_seq), [])) >= len(self._expected.get((out, frame_seq), []))
                   or self._newest.get(out, -1) > frame_seq
                   for out in self.output_keys.values())

    def _wait_outputs_published_before(self, frame_seq: int, pub_ns: int, timeout_s: float) -> bool:
        """Wait until the node produced this frame's outputs that, live, were published before an input
        published at ``pub_ns``: live, prior k existed before measurement k was computed, so sending both
        at once would let the node see them in an order that never happened."""
        if not pub_ns:
            return True
        need = {out: sum(_pub_ns(data) < pub_ns for data in self._expected.get((out, frame_seq), []))
                for out in self.output_keys.values()}
        if not any(need.values()):
            return True
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not all(len(self._produced.get((out, frame_seq), [])) >= n or self._newest.get(out, -1) > frame_seq
                          for out, n in need.items()):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.proc is not None and self.proc.poll() is not None):
                    return False
                self._cond.wait(min(remaining, 0.05))
        return True

    def _cpu_ticks(self) -> int | None:
        """utime + stime of the node process (Linux), None where /proc is not available."""
        if self.proc is None:
            return None
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return int(fields[11]) + int(fields[12])
        except (OSError, IndexError, ValueError):
            return None

    def _node_idle(self, since: float, ticks: int | None) -> bool:
        """True when, since ``since``, the node produced nothing and spent (almost) no CPU."""
        now_ticks = self._cpu_ticks()
        return (ticks is not None and now_ticks is not None and now_ticks - ticks < IDLE_CPU_TICKS
                and self._last_output < since)

    def _await_frame(self, frame_seq: int, timeout_s: float) -> str:
        """'ready', 'idle' (the node waits for later input: a set held until a later stamp times it out)
        or 'timeout'."""
        deadline = time.monotonic() + timeout_s
        window, ticks = time.monotonic(), self._cpu_ticks()
        with self._cond:
            while not self._outputs_ready(frame_seq):
                now = time.monotonic()
                if now >= deadline or (self.proc is not None and self.proc.poll() is not None):
                    return "timeout"
                if now - window >= QUIET_S:
                    if self._node_idle(window, ticks):
                        return "idle"
                    window, ticks = now, self._cpu_ticks()
                self._cond.wait(min(deadline - now, 0.05))
        return "ready"

    def _wait_quiet(self, quiet_s: float, timeout_s: float) -> None:
        """Wait until the node has been idle for ``quiet_s`` (at most ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        window, ticks = time.monotonic(), self._cpu_ticks()
        while time.monotonic() < deadline:
            time.sleep(quiet_s)
            if ticks is None and self._last_output < window or self._node_idle(window, ticks):
                return
            window, ticks = time.monotonic(), self._cpu_ticks()

    def _wait_outputs(self, frame_seq: int, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._outputs_ready(frame_seq):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.proc is not None and self.proc.poll() is not None):
                    return False
                self._cond.wait(min(remaining, 0.2))
        return True

    def _finish_frame(self, frame_seq: int) -> None:
        for out in self.output_keys.values():
            self._compare(out, frame_seq)

    # --- main -------------------------------------------------------------------------------------
    def run(self) -> ReplayReport:
        from followbus.bus.health import HealthWatcher
        from followbus.bus.pubsub import Publisher, ShmPool, direct_callback
        from followbus.bus.session import open_session

        with tempfile.TemporaryDirectory(prefix="followbus-replay-") as tmp:
            graph_path = Path(tmp) / "graph.yaml"
            graph_path.write_text(private_graph_text(self.graph, self.spec, self.params, self.private_ns, self.port))
            private = load_graph(graph_path)
            session = open_session(private.zenoh)  # takes the private port first; the node connects to it
            subs, pubs, watcher = [], {}, None
            log_path = Path(tmp) / "node.log"
            try:
                for key, out in self.output_keys.items():
                    # Direct callbacks keep the order of samples across keys (bus.pubsub.direct_callback).
                    subs.append(session.declare_subscriber(self._private_key(key),
                                                           direct_callback(self._on_output(out))))
                # Deferred frames keep a few dozen frames in flight: room for them in shared memory.
                shm = ShmPool(REPLAY_SHM_BYTES) if private.zenoh.shm else None
                for key in self.input_keys:
                    pubs[key] = Publisher(session, self._private_key(key), "replay", shm=shm)
                self._hint_pub = Publisher(session, private.replay_hint_key(self.spec.name), "replay")
                watcher = HealthWatcher(session, self.private_ns, watch_status=False)
                with open(log_path, "wb") as node_log:
                    self.proc = subprocess.Popen(
                        [sys.executable, "-m", "followbus.tools.cli", "node", self.spec.name, "--graph",
                         str(graph_path), "--clock", "stamps"],
                        stdout=node_log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                        env=dict(os.environ, PYTHONUNBUFFERED="1"), preexec_fn=_die_with_parent)
                t0 = time.perf_counter()
                missing = watcher.wait_for({self.spec.name}, self.opts.startup_timeout_s)
                self.report.startup_s = time.perf_counter() - t0
                if missing or self.proc.poll() is not None:
                    self.report.error = (f"node {self.spec.name} did not come up within "
                                         f"{self.opts.startup_timeout_s:.0f} s" if self.proc.poll() is None
                                         else f"node {self.spec.name} exited with status {self.proc.poll()}")
                else:
                    self.report.recording_first_frame = recording_first_frame(self.path)
                    self._lockstep(pubs)
            finally:
                self._stop_node()
                if self.report.error or (self.report.node_exit not in (0, None)):
                    tail = log_path.read_text(errors="replace").splitlines()[-30:] if log_path.exists() else []
                    if tail:
                        log.error("node log (last lines):\n%s", "\n".join(tail))
                for sub in subs:
                    with contextlib.suppress(Exception):
                        sub.undeclare()
                if watcher is not None:
                    watcher.close()
                with contextlib.suppress(Exception):
                    session.close()
        return self.report

    def _stop_node(self) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.report.node_exit = self.proc.returncode

    def _progress(self):
        from tqdm import tqdm

        summary = read_summary(self.path)
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        total = 0
        primary = next((f"{self.recorded_ns}/{i.topic}" for i in self.spec.inputs.values()
                        if i.sync == "frame" and not i.offset and not i.optional), None)
        for ch in summary.channels.values():
            if ch.topic == primary and is_bus_channel(ch):
                total += counts.get(ch.id, 0)
        if self.opts.max_frames:
            total = min(total, self.opts.max_frames) if total else self.opts.max_frames
        return tqdm(total=total or None, unit="frame", desc=f"replay {self.spec.name}", file=sys.stderr,
                    disable=None if self.opts.progress else True, dynamic_ncols=True)  # None: TTY only

    def _lockstep(self, pubs: dict[str, Any]) -> None:
        self._feedback_sent: dict[str, set[int]] = {i.name: set() for i in self.spec.inputs.values() if i.offset}
        self._live_feedback, self._live_handled = self._recorded_hints() if self._feedback_sent else ({}, set())
        self._send_hints()
        last_handled: int | None = None
        # Frames whose outputs the node can only emit once later stamps arrive (a set waiting for an
        # optional input, or blocked behind such a set): in stamp order, oldest first.
        pending: list[int] = []
        group: list[tuple[str, bytes, int, int]] = []
        group_seq: int | None = None
        done_frames: set[int] = set()
        first_stamp = last_stamp = None
        bar = self._progress()
        started = time.perf_counter()

        def check_node() -> None:
            if self.proc is not None and self.proc.poll() is not None:
                raise RuntimeError(f"node {self.spec.name} exited with status {self.proc.returncode}")

        def resolve_pending(deadline: float | None = None) -> None:
            """Finish pending frames whose outputs are in; with a deadline, wait for all of them until then."""
            while pending:
                fs = pending[0]
                if not self._outputs_ready_locked(fs):
                    if deadline is None:
                        return  # sets are emitted in frame order: later ones wait behind this one
                    if not self._wait_outputs(fs, max(0.0, deadline - time.monotonic())):
                        self.report.timeouts.append(fs)
                        check_node()
                pending.pop(0)
                self._finish_frame(fs)

        def send_group() -> None:
            nonlocal last_handled, first_stamp, last_stamp
            assert group_seq is not None
            names: set[str] = set()
            skipped, forced = self._hint_for(group_seq)
            # Messages of no frame (odometry) first: a node picks among them by stamp, and what it picked live
            # is replayed from the hint, which needs the sample there before the frame's set is handled.
            for key, data, fs, stamp in sorted(group, key=lambda item: item[2] >= 0):
                if fs == group_seq and not self._wait_outputs_published_before(fs, _pub_ns(data),
                                                                              self.opts.frame_timeout_s):
                    check_node()
                pubs[key].put_bytes(data, stamp)
                self.report.inputs_sent += 1
                for name in self.input_keys[key]:
                    names.add(name)
                    if name in self._feedback_sent:
                        self._feedback_sent[name].add(fs)
                if stamp:
                    first_stamp = stamp if first_stamp is None else min(first_stamp, stamp)
                    last_stamp = stamp if last_stamp is None else max(last_stamp, stamp)
            complete, required = self._frame_inputs_complete(names, last_handled, forced)
            if required and not skipped:
                last_handled = group_seq
            self.report.frames += 1
            done_frames.add(group_seq)
            bar.update(1)
            resolve_pending()
            if (pending or not complete) and not self._outputs_ready_locked(group_seq):
                # The node can only emit this set once later stamps time it out (an optional input is
                # missing), or it is queued behind such a set: go on without waiting. Flow control is
                # not needed here: the node pops its input queues while its synchroniser waits.
                pending.append(group_seq)
                self.report.deferred_frames += 1
                return
            state = self._await_frame(group_seq, self.opts.frame_timeout_s)
            if state == "idle":
                # The node needs a later stamp before it emits this set (it waits for an optional input
                # that the recording does not have): go on, the set comes out with a later frame.
                pending.append(group_seq)
                self.report.deferred_frames += 1
                return
            if state == "timeout":
                self.report.timeouts.append(group_seq)
                check_node()
            self._finish_frame(group_seq)

        try:
            stream = causal_order(iter_bus_messages(self.path, set(self.input_keys) | set(self.output_keys)))
            for msg in prefetch(stream, PREFETCH):
                frame_seq, stamp = _header(msg.data)
                if msg.key in self.output_keys:
                    self._expected[(self.output_keys[msg.key], frame_seq)].append(msg.data)
                    self.report.outputs_expected += 1
                    continue
                if frame_seq >= 0:
                    if group_seq is not None and frame_seq > group_seq:
                        send_group()
                        group, group_seq = [], None
                        if self.opts.max_frames and self.report.frames >= self.opts.max_frames:
                            break
                    if group_seq is not None and frame_seq < group_seq or frame_seq in done_frames:
                        self.report.late_inputs += 1  # out of stamp order: goes with the frame being assembled
                    if group_seq is None:
                        group_seq = frame_seq
                # messages of no frame (frame_seq -1) go with the frame being assembled, in log-time order
                group.append((msg.key, msg.data, frame_seq, stamp))
            if group and group_seq is not None and (not self.opts.max_frames
                                                    or self.report.frames < self.opts.max_frames):
                send_group()
            resolve_pending(deadline=time.monotonic() + self.opts.frame_timeout_s)
            self.report.wall_s = time.perf_counter() - started
            self._wait_quiet(QUIET_S, self.opts.frame_timeout_s)  # stragglers: outputs nobody recorded are extra
        except RuntimeError as exc:
            self.report.error = str(exc)
            self.report.wall_s = time.perf_counter() - started
        finally:
            bar.close()
        self._account_leftovers(done_frames)
        if first_stamp is not None and last_stamp is not None:
            self.report.recorded_span_s = (last_stamp - first_stamp) / 1e9
        if self.report.wall_s > 0:
            self.report.speed_x = self.report.recorded_span_s / self.report.wall_s

    def _outputs_ready_locked(self, frame_seq: int) -> bool:
        with self._cond:
            return self._outputs_ready(frame_seq)

    def _account_leftovers(self, done_frames: set[int]) -> None:
        """Compare what is left, then list recorded-but-never-produced and produced-but-not-recorded outputs."""
        with self._cond:
            produced = {k: list(v) for k, v in self._produced.items()}
        for out, fs in list(self._expected):
            self._compare(out, fs)
        for (out, fs), items in sorted(self._expected.items()):
            if fs not in done_frames and self.opts.max_frames:
                continue  # beyond --max-frames
            n_prod = len(produced.get((out, fs), []))
            key = f"{self.recorded_ns}/{self.spec.name}/{out}"
            for i in range(n_prod, len(items)):
                self.report.missing.append({"frame_seq": fs, "key": key, "index": i})
        last_recorded: dict[str, int] = {}
        for out, fs in self._expected:
            last_recorded[out] = max(last_recorded.get(out, -1), fs)
        for (out, fs), items in sorted(produced.items()):
            n_exp = len(self._expected.get((out, fs), []))
            key = f"{self.recorded_ns}/{self.spec.name}/{out}"
            if fs > last_recorded.get(out, -1):
                # The recording stopped between this frame's inputs and its outputs: nothing to compare.
                self.report.beyond_end += len(items) - n_exp
                continue
            for i in range(n_exp, len(items)):
                self.report.extra.append({"frame_seq": fs, "key": key, "index": i})


# --- command ---------------------------------------------------------------------------------------

def _print_summary(report: ReplayReport, verify: bool) -> None:
    print(f"replayed {report.frames} frames ({report.inputs_sent} input messages) into {report.node} in "
          f"{report.wall_s:.2f} s: {report.speed_x:.1f}x real time over {report.recorded_span_s:.2f} s recorded")
    print(f"outputs: {report.outputs_expected} recorded, {report.outputs_received} produced, "
          f"{report.outputs_compared} compared, {report.matched} identical, {report.mismatch_count} differing, "
          f"{len(report.missing)} missing, {len(report.extra)} extra; {len(report.timeouts)} frame timeouts")
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
            node=args.node, graph_path=args.graph, params=parse_param_overrides(args.param or []),
            verify=args.verify, tolerance=Tolerance(args.rtol, args.atol), frame_timeout_s=args.timeout,
            startup_timeout_s=args.startup_timeout, max_frames=args.max_frames or 0,
            progress=not args.no_progress)
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
