"""Node runtime: parses params, opens the session, declares inputs/outputs, runs callbacks.

A node is a class deriving from :class:`Node`, exported as ``NODE`` by the module named in
graph.yaml's ``run:``. Its code is single-threaded: Zenoh callbacks only decode and enqueue; the
main loop hands messages to the node in arrival order:

- ``on_message(name, msg)`` for every input message, as it arrives;
- ``on_frame(frame_seq, inputs)`` for each set of frame-synchronised inputs (see bus.sync);
- ``on_timer(now_ns)`` every ``TIMER_PERIOD_MS`` of the node clock;
- ``poll(now_ns) -> seconds`` for sources that produce on their own schedule.

The node clock is wall time, or with ``clock="stamps"`` (lockstep replay) the newest input stamp,
so a replayed node never depends on the wall clock.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import logging
import math
import os
import re
import signal
import socket
import threading
import time
import typing
from dataclasses import dataclass
from typing import Any, ClassVar

import zenoh

from .graph import Graph, GraphError, NodeSpec
from .live_params import LiveParams
from .liveness import (
    HANDLER_FAILURE_LIMIT,
    POLL_FAILURE_LIMIT,
    STOPPED_WORKING_EXIT,
    FailureBudget,
    NodeStoppedWorking,
    ProductionWatch,
    SourceActivity,
)
from .pubsub import InputQueue, Publisher, RateLimitedLog, ShmPool, Subscriber
from .schemas import Frame, Message, NodeStatus, ReplayHint
from .session import open_session
from .stats import TopicStats
from .sync import IMPLAUSIBLE, RESYNCED, STALE, FrameSynchronizer, SequenceGuard, SyncInput
from .typecheck import TypeMismatch, conform

STATUS_PERIOD_S = 1.0
RESET_AFTER_FAILURES = 5  # consecutive on_frame failures after which a node's state is rebuilt
REPLAY_NOTES_KEEP = 512  # frames of live provenance a replayed node keeps
# Set by the launcher for its children: the comma-separated names of the nodes it started.
LAUNCHED_NODES_ENV = "FOLLOWBUS_LAUNCHED_NODES"
# Set by the launcher for its children: the nodes of this host that ``--only`` left out. A source does not wait
# for them: the user said they are not running (a node the graph puts on another host is still waited for).
LEFT_OUT_NODES_ENV = "FOLLOWBUS_LEFT_OUT_NODES"
LEFT_OUT_DISCOVERY_S = 2.0  # how long a source looks for a left-out consumer that may run in another launch
# Set by the launcher for its children: one id per launch, so a node can tell its own restart (same launch)
# from a new launch (state saved by an earlier run may belong to another session: another task).
LAUNCH_ID_ENV = "FOLLOWBUS_LAUNCH_ID"


class ParamError(ValueError):
    """A node parameter problem; ``key`` lets the caller point at the graph.yaml line."""

    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(message)


@dataclass
class NoParams:
    pass


def params_from_dict(cls: type, data: dict[str, Any]) -> Any:
    """Build a params dataclass from a dict, rejecting unknown keys and wrong types."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    for key in data:
        if key not in names:
            raise ParamError(key, f"unknown parameter {key!r} (known: {', '.join(sorted(names)) or 'none'})")
    kwargs = {}
    for key, value in data.items():
        kwargs[key] = _coerce(value, hints[key], key)
    try:
        return cls(**kwargs)
    except ValueError as exc:
        # A params class's own range check that names its parameter (an attribute ``key``) points at its line.
        key = getattr(exc, "key", None)
        if isinstance(exc, ParamError) or not isinstance(key, str):
            raise
        raise ParamError(key, str(exc)) from exc


def split_params(raw: dict[str, Any], *classes: type) -> tuple[Any, ...]:
    """One params dataclass per class from one flat ``params`` mapping: each key goes to the first class with a
    field of that name; a key no class has is a ParamError naming it (so validation points at its line)."""
    parts: list[dict[str, Any]] = [{} for _ in classes]
    owners = [{f.name for f in dataclasses.fields(cls)} for cls in classes]
    for key, value in raw.items():
        owner = next((i for i, names in enumerate(owners) if key in names), None)
        if owner is None:
            known = ", ".join(sorted(set().union(*owners))) or "none"
            raise ParamError(key, f"unknown parameter {key!r} (known: {known})")
        parts[owner][key] = value
    return tuple(params_from_dict(cls, part) for cls, part in zip(classes, parts, strict=True))


def _renamed(raw: dict[str, Any], renamed: dict[str, str]) -> dict[str, Any]:
    """``raw`` with the old names of renamed parameters replaced by the new ones (the new name wins if both)."""
    old = [key for key in raw if key in renamed]
    for key in old:
        logging.getLogger(__name__).warning("parameter %r is now called %r", key, renamed[key])
    return {renamed.get(key, key): value for key, value in raw.items() if key not in old or renamed[key] not in raw}


def _non_finite(value: Any) -> bool:
    """Whether a parameter value holds NaN or ±inf anywhere (in a list or mapping too)."""
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return any(_non_finite(v) for v in value)
    if isinstance(value, dict):
        return any(_non_finite(v) for v in value.values())
    return False


# A number YAML 1.1 reads as text (1e-3, 1e309: its floats need a dot), which YAML 1.2 and Python read as a number.
_EXPONENT_NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$")


def _coerce(value: Any, hint: Any, key: str) -> Any:
    # No parameter means anything with NaN or inf: a NaN gate never follows, an infinite timeout never fires.
    if _non_finite(value):
        raise ParamError(key, f"parameter {key!r} must be finite, not {value!r}")
    try:
        return conform(value, hint)
    except TypeMismatch as exc:
        if isinstance(value, str) and _EXPONENT_NUMBER.match(value.strip()):
            return _coerce_exponent(value, hint, key)
        raise ParamError(key, f"parameter {key!r} must be {exc.expected}, not {type(value).__name__} "
                              f"({value!r})") from None


def _coerce_exponent(text: str, hint: Any, key: str) -> Any:
    """``1e-3`` for a number parameter: the number it says, or a ParamError when no float holds it (1e309)."""
    number = float(text)
    if not math.isfinite(number):
        raise ParamError(key, f"parameter {key!r}: {text.strip()} is beyond the range of a float (at most ~1.8e308)")
    try:
        return conform(number, hint)
    except TypeMismatch as exc:
        raise ParamError(key, f"parameter {key!r} must be {exc.expected}, not {text.strip()}") from None


class Clock:
    """A node's clock: wall time; or the newest observed message stamp (lockstep replay); or simulated time
    (``sim``: the in-process runtime, bus.inproc, advances it; it stands for both wall and monotonic time).

    ``now_ns`` is the node clock; ``wall_ns`` and ``monotonic_ns`` are what a live node reads for receive
    times and ages (its watchdog): the real clocks, except in ``sim`` where the simulated time stands in.
    ``live`` is False only for ``stamps``: a simulated run behaves as a live one, on its own time.
    """

    MODES = ("wall", "stamps", "sim")

    def __init__(self, mode: str = "wall", start_ns: int = 0):
        if mode not in self.MODES:
            raise ValueError(f"clock must be one of {', '.join(self.MODES)}, not {mode!r}")
        self.mode = mode
        self._latest = 0
        self._sim_ns = start_ns

    @property
    def live(self) -> bool:
        return self.mode != "stamps"

    def observe(self, stamp_ns: int) -> None:
        self._latest = max(self._latest, stamp_ns)

    def advance_to(self, t_ns: int) -> None:
        """Simulated clock: move to ``t_ns`` (never back)."""
        self._sim_ns = max(self._sim_ns, t_ns)

    def now_ns(self) -> int:
        if self.mode == "sim":
            return self._sim_ns
        return time.time_ns() if self.mode == "wall" else self._latest

    def wall_ns(self) -> int:
        return self._sim_ns if self.mode == "sim" else time.time_ns()

    def monotonic_ns(self) -> int:
        return self._sim_ns if self.mode == "sim" else time.monotonic_ns()


RECORDER_NAME = "recorder"  # liveliness name of `followbus record`, and the launcher's name for it


class DownstreamBarrier:
    """Start-up barrier for source nodes: is everyone who should hear our first message listening?

    Waits for the liveliness of the node's direct consumers (graph.yaml), of every node downstream of it
    that the launcher started (FOLLOWBUS_LAUNCHED_NODES: waiting for the whole chain keeps frame 0's
    results from racing the routes between later nodes), and of a recorder the launcher started. Nodes
    declare their token after their subscribers, so a visible token means they listen. Gives up after
    ``timeout_s`` with a warning naming who is missing, then lets ``settle_s`` pass for routes to settle.
    A node hosted without a session (in-process, bus.inproc) opens at once: every node there is listening
    before any publishes.
    """

    def __init__(self, runtime: NodeHost, timeout_s: float, settle_s: float):
        from .health import HealthWatcher

        graph, name = runtime.graph, runtime.spec.name
        self.log = runtime.log
        self._runtime = runtime
        self.timeout_s = timeout_s
        self.settle_s = settle_s
        self._open_at: float | None = None
        self._health: HealthWatcher | None = None
        self.waiting_for: set[str] = set()
        if runtime.session is None:
            self._open_at = -math.inf
            return
        self.waiting_for = {n for n, spec in graph.nodes.items()
                            if any(i.source_node == name for i in spec.inputs.values())}
        launched = os.environ.get(LAUNCHED_NODES_ENV)
        if launched:
            started = set(launched.split(","))
            frontier = {name}
            while frontier:
                fed = {n for n, spec in graph.nodes.items() if n in started and n not in self.waiting_for | {name}
                       and any(i.source_node in frontier for i in spec.inputs.values())}
                self.waiting_for |= fed
                frontier = fed
            if RECORDER_NAME in started:
                self.waiting_for.add(RECORDER_NAME)
        # Consumers --only left out: waited for only as long as discovery takes (one already running in another
        # launch is seen within it and still hears frame 0), not the whole timeout for one nobody will start.
        self.left_out = self.waiting_for & set(filter(None, os.environ.get(LEFT_OUT_NODES_ENV, "").split(",")))
        self.waiting_for.discard(name)
        self._health = HealthWatcher(runtime.session, graph.namespace, watch_status=False)
        self._deadline = time.monotonic() + timeout_s
        self._left_out_deadline = time.monotonic() + min(timeout_s, LEFT_OUT_DISCOVERY_S)

    def wait_s(self) -> float:
        """Seconds to wait before the first message (0: go)."""
        if self._open_at == -math.inf:
            return 0.0
        if self._open_at is None:
            assert self._health is not None
            missing = self.waiting_for - self._health.alive()
            # In the node's status while it waits: a launcher that sees a consumer this node cannot (two hosts
            # whose sessions do not route to each other) names the split from it (bus/links.py).
            self._runtime.awaiting = missing
            now = time.monotonic()
            if missing - self.left_out and now < self._deadline or missing and now < self._left_out_deadline:
                return 0.05
            if missing & self.left_out:
                self.log.info("not waiting for %s: left out of this launch by --only and not running",
                              ", ".join(sorted(missing & self.left_out)))
                missing -= self.left_out
            if missing:
                self.log.warning("starting without %s (not up after %.0f s)", ", ".join(sorted(missing)),
                                 self.timeout_s)
            self._runtime.awaiting = set()
            self._open_at = time.monotonic() + self.settle_s
        return max(0.0, self._open_at - time.monotonic())

    @property
    def opened(self) -> bool:
        """Whether the wait is over (the first message may go)."""
        return self._open_at is not None and time.monotonic() >= self._open_at

    def close(self) -> None:
        if self._health is not None:
            self._health.close()


class Node:
    INPUTS: ClassVar[dict[str, type[Message]]] = {}
    REQUIRED_INPUTS: ClassVar[frozenset[str]] = frozenset()
    OUTPUTS: ClassVar[dict[str, type[Message]]] = {}
    CONGESTION: ClassVar[dict[str, str]] = {}  # output -> "block" | "drop" (default block)
    EXPRESS: ClassVar[frozenset[str]] = frozenset()  # outputs sent without batching (control)
    PRIORITY: ClassVar[dict[str, str]] = {}  # output -> "real_time" | "interactive_high" | "data" (default)
    # The dataclass of the node's graph.yaml ``params``; or a tuple of them (the node's own settings and its
    # algorithm's), which split the mapping by field name: the node then gets a tuple of instances, in that order.
    # Either way a key no class declares is an error at the key's line: every parameter given is one it reads.
    Params: ClassVar[type | tuple[type, ...]] = NoParams
    TIMER_PERIOD_MS: ClassVar[float | None] = None
    # What a command may fill in without knowing the graph's node names (followbus demo): the param naming
    # where a source node's data comes from (``--scene`` sets it), and the param taking the [x, y, w, h] box
    # of what to follow on the first frame (set from the source's first ground-truth box, see first_truth_box).
    SOURCE_PARAM: ClassVar[str | None] = None
    INIT_BOX_PARAM: ClassVar[str | None] = None
    # The param naming a file the node keeps its state in across restarts: a replay clears it, so it neither
    # starts from nor overwrites the live graph's state.
    STATE_FILE_PARAM: ClassVar[str | None] = None
    # Parameters renamed (old name -> new name): a graph, or a recording's graph, written before the rename still
    # loads, with a warning naming the new name.
    RENAMED_PARAMS: ClassVar[dict[str, str]] = {}
    # Params `followbus param set` may change while the node runs (bus/live_params.py): only those the node's code
    # reads afresh on every message from its params objects.
    LIVE_PARAMS: ClassVar[frozenset[str]] = frozenset()
    # Inputs that only feed state the node reads when another input arrives (a stream sampled by stamp): their
    # messages do not wake the node's loop, they are handed over with the next message that does (at most the
    # loop's idle period later, or at once when the queue is half full), still in arrival order, so what the
    # node computes is unchanged; each wake-up of a process costs far more than the few lines of handling.
    LAZY_INPUTS: ClassVar[frozenset[str]] = frozenset()
    # Notes (:meth:`note`) whose value is the stamp of a message of an unsynchronised input: note key -> input
    # name. A replay whose recording lacks that message (the recorder dropped it) cannot repeat the choice,
    # and calls that frame not verifiable instead of a mismatch.
    NOTED_STAMPS: ClassVar[dict[str, str]] = {}

    def __init__(self, params: Any, runtime: NodeHost):
        self.params = params
        self.runtime = runtime
        self.name = runtime.spec.name
        self.log = logging.getLogger(f"followbus.{self.name}")
        self.latest: dict[str, Message] = runtime.latest

    @classmethod
    def parse_params(cls, raw: dict[str, Any]) -> Any:
        """The node's params from its graph.yaml mapping (ParamError naming the key). A node with rules across
        fields overrides this, calls it first and checks them."""
        raw = _renamed(raw, cls.RENAMED_PARAMS)
        if isinstance(cls.Params, tuple):
            return split_params(raw, *cls.Params)
        return params_from_dict(cls.Params, raw)

    @classmethod
    def unread_inputs(cls, params: Any) -> frozenset[str]:
        """Optional inputs these params never read: a node on the bus does not subscribe to them, so nothing is
        sent, received and decoded for nothing (every message costs each end a few hundred microseconds of CPU
        on a busy 2-core machine, most of it outside the node's code)."""
        return frozenset()

    @classmethod
    def first_truth_box(cls, params: Any) -> tuple[float, ...] | None:
        """A source node's ground-truth box of its first frame, when its source has one (else None)."""
        return None

    @classmethod
    def params_classes(cls) -> tuple[type, ...]:
        """The dataclasses whose fields are this node's graph.yaml ``params`` (``followbus schema`` documents
        them, ``followbus param`` reads and sets them)."""
        return cls.Params if isinstance(cls.Params, tuple) else (cls.Params,)

    @classmethod
    def param_names(cls) -> frozenset[str]:
        """Every parameter the node reads (its params classes' fields)."""
        return frozenset(f.name for c in cls.params_classes() for f in dataclasses.fields(c))

    # hooks
    def setup(self) -> None: ...
    def reset(self) -> None:
        """Rebuild the node's state after it became invalid (the runtime calls this when on_frame keeps
        failing). The default runs ``setup()`` again; override to keep what is still good."""
        self.setup()

    def on_message(self, name: str, msg: Message) -> None: ...
    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None: ...
    def on_timer(self, now_ns: int) -> None: ...
    def poll(self, now_ns: int) -> float | None:
        return None

    def teardown(self) -> None: ...
    def holding(self) -> bool:
        """A source that holds its first publication on purpose (capture waiting for its consumers) says so: its
        silence meanwhile is no stall (bus/liveness.py SourceActivity)."""
        return False

    def status_extra(self) -> dict[str, Any]:
        return {}

    # helpers
    def publish(self, output: str, msg: Message, like: Message | None = None) -> None:
        """Publish on an output; ``like`` copies the stamp, frame_seq and epoch of the input it derives from.

        Inside ``on_frame`` the output also carries which feedback messages the set used (header.feedback)."""
        if like is not None:
            msg.header.stamp_ns = like.header.stamp_ns
            msg.header.frame_seq = like.header.frame_seq
            msg.header.epoch_ns = like.header.epoch_ns
        if self.runtime.provenance is not None:
            msg.header.feedback = dict(self.runtime.provenance)
        self.runtime.publishers[output].put(msg)
        self.runtime.production.published(time.monotonic())

    def note(self, key: str, value: int) -> None:
        """Record a choice this handler made that a replay must repeat (e.g. which sample, by stamp,
        an unsynchronised input contributed): it travels in the ``header.feedback`` of what the handler
        publishes next, and ``followbus replay`` hands it back through :meth:`replayed_choice`. ``key`` must not
        name a frame-synchronised input: those keys are the set's own provenance (bus.sync)."""
        if self.runtime.provenance is not None:
            self.runtime.provenance[key] = int(value)

    def replayed_choice(self, frame_seq: int, key: str) -> int | None:
        """In a lockstep replay, the choice the live run noted for this frame (None live, or when not recorded)."""
        return self.runtime.replay_notes.get(frame_seq, {}).get(key)

    def has_output(self, output: str) -> bool:
        return output in self.runtime.publishers

    def has_listeners(self, output: str) -> bool:
        """Whether anyone subscribes to this output now (a publisher without ``listened``, in-process: always).
        An output only a monitor reads (a preview) need not be made while nobody does: publish would send nothing."""
        publisher = self.runtime.publishers.get(output)
        return publisher is not None and getattr(publisher, "listened", True)

    def now_ns(self) -> int:
        return self.runtime.clock.now_ns()

    def wall_ns(self) -> int:
        """Wall time (simulated in-process): for ages against capture stamps, stamps of what the node originates."""
        return self.runtime.clock.wall_ns()

    def monotonic_ns(self) -> int:
        """Monotonic time (simulated in-process): for receive times and watchdogs, which no stamp may steer."""
        return self.runtime.clock.monotonic_ns()

    def stop(self) -> None:
        self.runtime.stop_event.set()


def load_node_class(run: str) -> type[Node]:
    import importlib

    try:
        module = importlib.import_module(run)
    except (ValueError, TypeError) as exc:  # "" or a relative name ("..capture"): not a module name
        raise ImportError(f"{run!r} is not a module name ({exc})") from exc
    cls = getattr(module, "NODE", None)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise ImportError(f"module {run!r} has no NODE class deriving from followbus.bus.node.Node")
    return cls


def validate_node(graph: Graph, spec: NodeSpec, cls: type[Node] | None = None) -> tuple[type[Node], Any]:
    """Check a node spec against its class: inputs, outputs, types and params. Raises GraphError."""
    if cls is None:
        try:
            cls = load_node_class(spec.run)
        except ImportError as exc:
            raise graph.error(spec.line, f"node {spec.name!r}: run: {exc}") from exc
    _check_ports(graph, spec, cls)
    try:
        params = cls.parse_params(spec.params)
    except ParamError as exc:
        raise _param_error(graph, spec, cls, exc) from exc
    except (TypeError, ValueError) as exc:
        raise graph.error(spec.line, f"node {spec.name!r}: params: {exc}") from exc
    return cls, params


def _check_ports(graph: Graph, spec: NodeSpec, cls: type[Node]) -> None:
    """The node's inputs and outputs against its class: names, required inputs, and each input's message type
    against what its producer publishes."""
    for inp in spec.inputs.values():
        if inp.name not in cls.INPUTS:
            raise graph.error(inp.line, f"node {spec.name!r}: {spec.run} has no input {inp.name!r} "
                                        f"(it takes: {', '.join(cls.INPUTS) or 'none'})")
        producer = graph.nodes[inp.source_node]
        try:
            producer_cls = load_node_class(producer.run)
        except ImportError:
            producer_cls = None
        if producer_cls is not None:
            produced = producer_cls.OUTPUTS.get(inp.source_output)
            if produced is not None and produced is not cls.INPUTS[inp.name]:
                raise graph.error(inp.line, f"node {spec.name!r}: input {inp.name!r} expects "
                                            f"{cls.INPUTS[inp.name].TYPE} but {inp.topic} carries {produced.TYPE}")
    for required in cls.REQUIRED_INPUTS:
        if required not in spec.inputs:
            raise graph.error(spec.line, f"node {spec.name!r}: missing required input {required!r}")
    for out in spec.outputs:
        if out not in cls.OUTPUTS:
            raise graph.error(spec.line, f"node {spec.name!r}: {spec.run} has no output {out!r} "
                                         f"(it produces: {', '.join(cls.OUTPUTS) or 'none'})")


def _param_error(graph: Graph, spec: NodeSpec, cls: type[Node], exc: ParamError) -> GraphError:
    """A parameter problem at the parameter's line (under its old name too, RENAMED_PARAMS); a parameter this node
    does not read but another does is said so: a setting put on the wrong node."""
    readers = _read_elsewhere(graph, spec, cls, exc.key)
    verb = "does" if len(readers) == 1 else "do"
    message = f"{spec.name} does not read {exc.key!r}; {' and '.join(readers)} {verb}" if readers else str(exc)
    old = {new: old for old, new in cls.RENAMED_PARAMS.items()}.get(exc.key, exc.key)
    line = spec.param_lines.get(exc.key) or spec.param_lines.get(old) or spec.line
    return graph.error(line, f"node {spec.name!r}: {message}")


def _read_elsewhere(graph: Graph, spec: NodeSpec, cls: type[Node], key: str) -> list[str]:
    """For a parameter this node does not read: the other nodes of the graph that do (a setting put on the wrong
    node)."""
    if key in cls.param_names():
        return []  # the node reads it: the value, not the name, was wrong
    readers = []
    for name, other in graph.nodes.items():
        try:
            if name != spec.name and key in load_node_class(other.run).param_names():
                readers.append(name)
        except ImportError:
            continue  # reported at that node
    return readers


def _set_priority(nice: int | None, realtime: int | None, log: logging.Logger) -> None:
    """Run this process in the real-time class at ``realtime`` (SCHED_RR), or else at CPU priority ``nice``: the
    a watchdog must keep its timing on a busy machine. Called before the session opens, so the threads
    Zenoh starts (which deliver the node's messages) inherit it."""
    if realtime is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(realtime))
            log.info("running real-time (SCHED_RR priority %d)", realtime)
            return
        except (OSError, AttributeError) as exc:  # needs root or CAP_SYS_NICE (and RT bandwidth in a container)
            log.warning("could not run real-time (SCHED_RR %d: %s); falling back to %s", realtime, exc,
                        f"nice {nice}" if nice is not None else "the inherited priority")
    if nice is None:
        return
    try:
        os.nice(nice - os.nice(0))
    except OSError as exc:  # raising priority needs root or CAP_SYS_NICE
        log.warning("could not set nice %d (%s); running at nice %d", nice, exc, os.nice(0))


class NodeHost:
    """What hosting one node takes, whatever carries its messages: its class and params, its clock, the frame
    synchroniser and sequence guards of its inputs, and handing it messages, frame sets, timer ticks and
    replay hints. :class:`NodeRuntime` carries the messages over Zenoh (one process per node);
    ``bus.inproc.InProcessGraph`` between nodes in one process on a simulated clock. Both run this code, so a
    node behaves the same in either. A subclass fills ``publishers`` (output -> object with ``put(msg)``)
    and then calls :meth:`create_node`.
    """

    session: zenoh.Session | None = None  # NodeRuntime's; None in-process

    def __init__(self, graph: Graph, name: str, clock: Clock,
                 validated: tuple[type[Node], Any] | None = None):
        if name not in graph.nodes:
            raise GraphError(graph.path, None, f"no node named {name!r} (nodes: {', '.join(graph.nodes)})")
        self.graph = graph
        self.spec = graph.nodes[name]
        self.cls, self.params = validated if validated is not None else validate_node(graph, self.spec)
        self.clock = clock
        self.stop_event = threading.Event()
        self.log = logging.getLogger(f"followbus.{name}")
        self.publishers: dict[str, Any] = {}
        self.latest: dict[str, Message] = {}
        self.handler_errors = 0
        self.resets = 0
        self.awaiting: set[str] = set()  # the consumers a source's start-up barrier still waits for
        # Working, not just alive (bus/liveness.py): consecutive failures of poll and of the handlers, and
        # when this node last published.
        self.poll_failures = FailureBudget(POLL_FAILURE_LIMIT)
        self.handler_failures = FailureBudget(HANDLER_FAILURE_LIMIT)
        self.production = ProductionWatch()
        self.activity = SourceActivity()
        self._frame_failures = 0  # consecutive
        self.provenance: dict[str, int] | None = None  # feedback used by the set being handled
        self._warn = RateLimitedLog(self.log)
        frame_inputs = [SyncInput(i.name, i.offset, i.optional) for i in self.spec.inputs.values()
                        if i.sync == "frame"]
        # The lag bound is a live policy: a lockstep replay never builds a backlog, and skipping there
        # would depend on how fast the replayer feeds the node.
        lag_ms = graph.lag_bound_ms(name) if clock.live else None
        self.sync = (FrameSynchronizer(frame_inputs, int(self.spec.sync_timeout_ms * 1e6),
                                       max_lag_ns=None if lag_ms is None else int(lag_ms * 1e6))
                     if frame_inputs else None)
        self._feedback_inputs = [i.name for i in frame_inputs if i.offset]
        # Inputs not joined by frame are still frame-numbered streams (a consumer's inputs, capture's acks): the
        # same sequence checks keep a forged or stale message from reaching the node.
        self._guards = {i.name: SequenceGuard() for i in self.spec.inputs.values() if i.sync != "frame"}
        self._held: list[tuple[str, Message]] = []  # replay: feedback the live node received later
        self.replay_notes: dict[int, dict[str, int]] = {}  # replay: frame -> provenance of the live outputs
        self.timer_ns = int(self.cls.TIMER_PERIOD_MS * 1e6) if self.cls.TIMER_PERIOD_MS else None
        self.next_timer_ns: int | None = None

    def create_node(self) -> None:
        self.node = self.cls(self.params, self)

    def start(self) -> None:
        """Set the node up and start its timer."""
        self.node.setup()
        self.next_timer_ns = self.clock.now_ns() + self.timer_ns if self.timer_ns else None

    def sync_counters(self) -> dict[str, Any]:
        extra: dict[str, Any] = {"handler_errors": self.handler_errors, "resets": self.resets,
                                 "poll_failures": self.poll_failures.streak}
        if self.sync is not None:
            extra.update(self.sync.counters())
        if self._guards:
            extra.update(seq_stale=sum(g.stale for g in self._guards.values()),
                         seq_implausible=sum(g.implausible for g in self._guards.values()),
                         seq_resyncs=sum(g.resyncs for g in self._guards.values()))
        return extra

    def _guarded(self, what: str, fn, *args) -> Any:
        try:
            result = fn(*args)
        except Exception:
            # A bug or an unexpected message must not take the robot down: count, log, go on. Past
            # HANDLER_FAILURE_LIMIT failures in a row the node stops working (check_working).
            self.handler_errors += 1
            self.handler_failures.failed()
            if self.handler_errors <= 3 or self.handler_errors % 100 == 0:
                self.log.exception("%s failed (%d errors so far)", what, self.handler_errors)
            return None
        self.handler_failures.succeeded()
        return result

    def poll_once(self, now_ns: int) -> float | None:
        """Poll the node: seconds until the next poll, None for "never again" (the source is done).

        A poll that raises is retried after a backoff (0.05 s doubling to 1 s), never dropped for good: one
        failed camera read must not silence a source while its process looks up. POLL_FAILURE_LIMIT failures
        in a row raise NodeStoppedWorking (the process exits, the launcher restarts it)."""
        try:
            delay = self.node.poll(now_ns)
        except Exception as exc:
            self.handler_errors += 1
            backoff_s = self.poll_failures.failed()
            if self.poll_failures.exhausted:
                raise NodeStoppedWorking(f"poll failed {self.poll_failures.streak} times in a row "
                                         f"(last: {type(exc).__name__}: {exc})") from exc
            self.log.exception("poll failed (%d in a row); retrying in %.2f s", self.poll_failures.streak,
                               backoff_s)
            return backoff_s
        self.poll_failures.succeeded()
        return delay

    def check_working(self, polling: bool) -> None:
        """Raise NodeStoppedWorking when the handlers keep failing, or a source (``polling``: its poll is still
        scheduled) that has published before has been silent for many of its own periods."""
        if self.handler_failures.exhausted:
            raise NodeStoppedWorking(f"{self.handler_failures.streak} handler calls failed in a row")
        silent_s = self.production.silent_s(time.monotonic()) if polling else None
        if silent_s is not None:
            raise NodeStoppedWorking(f"published nothing for {silent_s:.1f} s (bound "
                                     f"{self.production.bound_s():.1f} s: its period x {self.production.periods})")

    def apply_hints(self, hints: list[Message]) -> None:
        """Replay: what the live run did with some frames (ReplayHint), handed over before those frames' inputs."""
        for hint in hints:
            assert isinstance(hint, ReplayHint)
            self.replay_notes[hint.header.frame_seq] = dict(hint.feedback)
            while len(self.replay_notes) > REPLAY_NOTES_KEEP:
                del self.replay_notes[min(self.replay_notes)]
            if self.sync is not None and hint.skip:
                self.sync.skip(hint.header.frame_seq)
            elif self.sync is not None:
                self.sync.force_feedback(hint.header.frame_seq, hint.feedback)

    def run_timer(self, now_ns: int) -> bool:
        """Tick the node's timer if it is due at ``now_ns``; True if it ticked."""
        if self.next_timer_ns is None or self.timer_ns is None or now_ns < self.next_timer_ns:
            return False
        self._guarded("on_timer", self.node.on_timer, now_ns)
        self.next_timer_ns = max(self.next_timer_ns + self.timer_ns, now_ns - self.timer_ns)
        return True

    def _dispatch(self, name: str, msg: Message) -> None:
        spec = self.spec.inputs[name]
        h = msg.header
        guard = self._guards.get(name)
        if guard is not None and h.frame_seq >= 0:
            verdict = guard.check(h.frame_seq, h.stamp_ns, h.epoch_ns, floor=guard.newest_seq)
            if verdict in (STALE, IMPLAUSIBLE):
                self._warn.warning("dropped %s %s frame %d (stamp %d): out of sequence with the stream",
                                   verdict, name, h.frame_seq, h.stamp_ns)
                return
            if verdict == RESYNCED:
                self.log.warning("input %s: the source restarted or was replaced (frame %d); following it",
                                 name, h.frame_seq)
        if (spec.offset and self.sync is not None and self.clock.mode == "stamps"
                and self.sync.holds_back(name, h.frame_seq)):
            # Live, this feedback arrived after a set that joined an older one: hand it to the node after that
            # set, as live, or on_message (a feedback update) runs in an order that never was.
            self._held.append((name, msg))
            return
        self.clock.observe(h.stamp_ns)
        if spec.sync == "frame" and self.sync is not None:
            # Judged before the node sees it: a forged or stale message must not reach on_message either.
            verdict = self.sync.add(name, h.frame_seq, msg, self._sync_now(), stamp_ns=h.stamp_ns, epoch_ns=h.epoch_ns)
            if verdict == IMPLAUSIBLE:
                self._warn.warning("rejected %s frame %d (stamp %d): out of sequence with the stream",
                                   name, h.frame_seq, h.stamp_ns)
                return
            if verdict == STALE:
                self.log.debug("stale %s frame %d dropped", name, h.frame_seq)
                return
            if verdict == RESYNCED:
                self.log.warning("input %s: the source restarted or was replaced (frame %d, epoch %d); "
                                 "re-synchronising on it", name, h.frame_seq, h.epoch_ns)
        self.provenance = {}  # what on_message publishes carries its own notes (Node.note)
        try:
            self._guarded(f"on_message({name})", self.node.on_message, name, msg)
        finally:
            self.provenance = None
        if spec.sync == "latest":
            self.latest[name] = msg
        elif spec.sync == "frame":
            self._emit_ready()

    def _sync_now(self) -> int:
        return self.clock.wall_ns() if self.clock.live else self.clock.now_ns()

    def _emit_ready(self) -> None:
        if self.sync is None:
            return
        for frame_seq, inputs in self.sync.poll(self._sync_now()):
            self._handle_frame(frame_seq, inputs)
        if self._held:
            held, self._held = self._held, []
            for name, msg in held:
                self._dispatch(name, msg)  # held again if it still must wait

    def _handle_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        used = {name: inputs.get(name) for name in self._feedback_inputs}
        self.provenance = {name: (m.header.frame_seq if m is not None else -1) for name, m in used.items()}
        # An optional same-frame input the set went on without (not on time, or late): a replay lacks it too.
        assert self.sync is not None  # frame sets come from it
        self.provenance.update({name: -1 for name in self.sync.optional if inputs.get(name) is None})
        errors = self.handler_errors
        try:
            self._guarded("on_frame", self.node.on_frame, frame_seq, inputs)
        finally:
            self.provenance = None
        self._frame_failures = self._frame_failures + 1 if self.handler_errors > errors else 0
        if self._frame_failures >= RESET_AFTER_FAILURES:
            # Whatever the cause (a poisoned filter, a state no input can repair), staying dead is the worst
            # outcome: rebuild the node's state and let it re-initialise from the next frames.
            self.log.error("on_frame failed %d times in a row; resetting the node's state", self._frame_failures)
            self._frame_failures = 0
            self.resets += 1
            self._guarded("reset", self.node.reset)


def _hub_listening(endpoints: list[str]) -> bool:
    """Whether a TCP endpoint of the graph already accepts connections (a launcher's hub on this machine)."""
    for endpoint in endpoints:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.split("#", 1)[0].rpartition(":")
        if proto not in ("tcp", "tls") or not port.isdigit():
            continue
        try:
            with contextlib.closing(socket.create_connection((host.strip("[]"), int(port)), timeout=0.3)):
                return True
        except OSError:
            continue
    return False


def _node_settings(graph: Graph) -> Any:
    """A launched node joins the launcher's session, the hub (session.py as_launched_node); so does a node started
    by hand beside a running launch of a router graph with access control, whose own allow-list would refuse the
    hub's link (it carries no user name on the node's side)."""
    launched = os.environ.get(LAUNCH_ID_ENV) is not None
    if launched or _hub_listening(list(graph.zenoh.listen)):
        return graph.zenoh.as_launched_node()
    return graph.zenoh


class NodeRuntime(NodeHost):
    """Hosts one node in this process, its messages carried over Zenoh."""

    def __init__(self, graph: Graph, name: str, *, clock: str = "wall", session: zenoh.Session | None = None):
        if clock == "sim":
            raise ValueError("a node on the bus runs on wall time or stamps; simulated time is bus.inproc's")
        super().__init__(graph, name, Clock(clock))
        _set_priority(self.spec.nice, self.spec.realtime, logging.getLogger(f"followbus.{name}"))
        self._own_session = session is None
        self.session = session or open_session(_node_settings(graph))
        self.started_ns = time.time_ns()
        self.subscribers: list[Subscriber] = []
        self.queues: dict[str, InputQueue] = {}
        self._cond = threading.Condition()
        self._arrival = itertools.count()
        shm = ShmPool() if graph.zenoh.shm else None
        if shm is not None and any(self.cls.OUTPUTS.get(out) is Frame for out in self.spec.outputs):
            shm.warm_up()  # frames go through shared memory: not on the first frame's time
        for out in self.spec.outputs:
            key = graph.key(self.spec.name, out)
            self.publishers[out] = Publisher(
                self.session, key, self.spec.name, congestion=self.cls.CONGESTION.get(out, "block"),
                express=out in self.cls.EXPRESS, priority=self.cls.PRIORITY.get(out, "data"), shm=shm,
                lane=graph.zenoh.shm_lane,
            )
        self.create_node()
        unread = self.cls.unread_inputs(self.params)
        for inp in self.spec.inputs.values():
            if inp.name in unread:
                self.log.info("not subscribing to input %s: these params never read it", inp.name)
                continue
            key = graph.key(inp.source_node, inp.source_output)
            stats = TopicStats(key, "in")
            queue = InputQueue(inp.name, inp.queue, inp.policy, stats, self._cond,
                               wakes=inp.name not in self.cls.LAZY_INPUTS)
            self.queues[inp.name] = queue
            self.subscribers.append(Subscriber(
                self.session, key, self._enqueuer(queue), schema=self.cls.INPUTS[inp.name], stats=stats,
                logger=self.log, lane=graph.zenoh.shm_lane,
            ))
        self._hints: list[ReplayHint] = []
        if clock == "stamps" and self.sync is not None:
            # Lockstep replay: the replayer says which frames the live node skipped and which feedback it
            # joined, so a live fallback (a late feedback, a skipped backlog) is reproduced exactly.
            self.subscribers.append(Subscriber(self.session, graph.replay_hint_key(name), self._on_hint,
                                               schema=ReplayHint, logger=self.log))
        self._token: Any = None  # declared once the node is set up (start)
        # Status is periodic: under congestion the next one will do. Blocking here could stall the node on a
        # slow subscriber (a busy monitor): zenoh's put holds the caller until the link drains.
        self._status_pub = Publisher(self.session, graph.status_key(self.spec.name), self.spec.name,
                                     congestion="drop")
        self._status_thread = threading.Thread(target=self._status_loop, name="status", daemon=True)
        self._event_pubs: dict[str, Publisher] = {}
        self.live_params = LiveParams(self, self._publish_event)

    def start(self) -> None:
        super().start()
        # Alive only once set up, and after the subscribers: a node whose setup fails (a missing model, a
        # detector wired without its input) must never be seen up, or a source's start-up barrier would open
        # for a node about to exit and publish frame 0 to nobody.
        self._token = self.session.liveliness().declare_token(self.graph.health_key(self.spec.name))

    def _enqueuer(self, queue: InputQueue):
        def push(msg: Message) -> None:
            # Arrival order across inputs matters (a result for frame k-1 before the detections
            # of frame k), so every message carries a process-wide arrival number.
            msg._arrival = next(self._arrival)  # type: ignore[attr-defined]
            queue.push(msg)

        return push

    def _on_hint(self, hint: Message) -> None:
        with self._cond:
            self._hints.append(hint)  # type: ignore[arg-type]
            self._cond.notify_all()

    def _publish_event(self, key: str, msg: NodeStatus) -> None:
        if key not in self._event_pubs:
            self._event_pubs[key] = Publisher(self.session, key, self.spec.name)
        self._event_pubs[key].put(msg)
        self._status_pub.put(self.status())  # the new value in the status at once, not a second later

    def status(self) -> NodeStatus:
        topics = {p.key: p.stats.snapshot() for p in self.publishers.values()}
        topics.update({q.stats.key: q.stats.snapshot() for q in self.queues.values()})
        extra = self.sync_counters()
        host = self.graph.host_of(self.spec.name)
        if host:
            extra["host"] = host
        if self.awaiting:
            extra["waiting_for"] = sorted(self.awaiting)
        source = self.activity.state(self.production, time.monotonic())
        if source is not None:
            extra["source"] = source
        if self.live_params.changed:
            extra["params_set"] = dict(self.live_params.changed)
        try:
            extra.update(self.node.status_extra())
        except Exception as exc:  # status must never take the node down
            extra["status_error"] = repr(exc)
        msg = NodeStatus(node=self.spec.name, pid=os.getpid(), uptime_s=(time.time_ns() - self.started_ns) / 1e9,
                         topics=topics, extra=extra)
        msg.header.stamp_ns = time.time_ns()
        return msg

    def _status_loop(self) -> None:
        while not self.stop_event.wait(STATUS_PERIOD_S):
            try:
                self._status_pub.put(self.status())
            except Exception as exc:
                self._warn.warning("status publish failed: %r", exc)

    def install_signal_handlers(self) -> None:
        def handler(signum, _frame):
            self.log.info("received %s, shutting down", signal.Signals(signum).name)
            self.stop_event.set()
            with self._cond:
                self._cond.notify_all()

        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)

    def run(self) -> None:
        try:
            self.start()
        except BaseException:
            self.close()  # a setup that failed leaves no queryable or session behind to keep the process alive
            raise
        self._status_thread.start()
        self.log.info("node %s up (%s)", self.spec.name, self.spec.run)
        next_poll_wall: float | None = time.monotonic()
        try:
            while not self.stop_event.is_set():
                with self._cond:
                    wait_s = self._idle_wait_s(next_poll_wall)
                    if not any(len(q) for q in self.queues.values() if q.wakes) and wait_s > 0:
                        self._cond.wait(wait_s)
                    items = [(name, m) for name, q in self.queues.items() for m in q.pop_all()]
                    hints, self._hints = self._hints, []
                    self._cond.notify_all()  # wake producers blocked on a full queue
                self.apply_hints(hints)  # published before the frame's inputs, so they arrive first
                items.sort(key=lambda item: item[1]._arrival)
                for name, msg in items:
                    self._dispatch(name, msg)
                self._emit_ready()
                now = self.clock.now_ns()
                self.run_timer(now)
                if next_poll_wall is not None and time.monotonic() >= next_poll_wall:
                    self.activity.poll_started(time.monotonic())
                    delay = self.poll_once(now)
                    self.activity.poll_ended(delay, time.monotonic(), holding=self.node.holding())
                    next_poll_wall = None if delay is None else time.monotonic() + max(0.0, delay)
                self.check_working(polling=next_poll_wall is not None)
        finally:
            self.close()

    def _idle_wait_s(self, next_poll_wall: float | None) -> float:
        """How long the loop may wait for a message: until the next poll, timer tick or set deadline, and at most
        50 ms (LAZY_INPUTS wait for a wake-up: this bounds how long)."""
        wait_s = 0.05
        if next_poll_wall is not None:
            wait_s = min(wait_s, max(0.0, next_poll_wall - time.monotonic()))
        if self.next_timer_ns is not None and self.clock.mode == "wall":
            wait_s = min(wait_s, max(0.0, (self.next_timer_ns - time.time_ns()) / 1e9))
        if self.sync is not None and self.clock.mode == "wall":
            deadline = self.sync.next_deadline_ns()
            if deadline is not None:
                wait_s = min(wait_s, max(0.0, (deadline - time.time_ns()) / 1e9))
        return wait_s

    def close(self) -> None:
        self.stop_event.set()
        self._guarded("teardown", self.node.teardown)
        if self._token is not None:
            with contextlib.suppress(Exception):
                self._token.undeclare()
        with contextlib.suppress(Exception):
            self.live_params.close()
        for sub in self.subscribers:
            with contextlib.suppress(Exception):
                sub.undeclare()
        if self._own_session:
            with contextlib.suppress(Exception):
                self.session.close()
        self.log.info("node %s stopped", self.spec.name)


def run_node(graph: Graph, name: str, *, clock: str = "wall") -> int:
    """Run a node until it is stopped: 0, or STOPPED_WORKING_EXIT when it stopped working (bus/liveness.py),
    so the launcher restarts it; its liveliness token is gone by then (close)."""
    runtime = NodeRuntime(graph, name, clock=clock)
    runtime.install_signal_handlers()
    try:
        runtime.run()
    except NodeStoppedWorking as exc:
        runtime.log.error("node %s stopped working: %s; exiting with status %d to be restarted", name, exc,
                          STOPPED_WORKING_EXIT)
        return STOPPED_WORKING_EXIT
    return 0
