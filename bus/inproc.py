"""In-process runtime: a whole graph (or some of its nodes) in one process, on a simulated clock.

The nodes are the graph's own classes (graph.yaml ``run:``), hosted by the same :class:`NodeHost` as a node
on the bus: the same frame synchroniser, sequence guards, feedback inputs (``offset: -1``), optional and
``sync: none`` inputs, replay hints and error guards. Only the transport differs: ``Node.publish`` hands the
message to this runtime, which gives every subscribed node its own copy, validated: exactly what it would
decode from the bus (bus.schemas ``wire_copy``, held to ``decode(encode(msg))`` by the codec tests, without
making the bytes; ``wire=True`` makes and decodes them), and a malformed message is counted and dropped as
there. Recorded topics also keep the encoded bytes. No Zenoh, no threads, no wall clock.

**Scheduling.** Handlers take no simulated time. Messages are delivered breadth-first: each round takes
everything queued for every node, then hands each node (in graph order) its messages in publication
order; what they publish is queued for the next round, until nothing is left. Input queues keep their
size and policy: ``drop_oldest`` loses the oldest of a burst bigger than the queue, as a busy live node
would; ``block`` loses nothing (the producer would wait for room, and the consumer takes no time). Only
then does the clock move, to the next due event: a source's ``poll`` (every node is polled once at the
start, then again after the delay it returns), a timer tick (``on_timer`` every ``TIMER_PERIOD_MS``), or
a frame-set deadline (``sync_timeout_ms``). Same inputs, same outputs, bit for bit, run after run.

**Clocks.** ``clock="sim"`` (default): one simulated clock stands for wall and monotonic time
(the node's ``runtime.clock``, the synchroniser's deadlines, ``header.pub_ns``); nodes
behave as live ones (``Clock.live``), on that time. ``clock="stamps"``: each node's clock follows the stamps
of its inputs, as ``followbus node --clock stamps`` in a lockstep replay (timers tick after deliveries,
frame sets time out on stamps, the lag bound is off); :meth:`InProcessGraph.hint` gives it the replay
hints.

    graph = load_graph("graph.yaml")
    apply_overrides(graph, ["detection.backend=simulated"])
    with InProcessGraph(graph, record=["sink/out"]) as g:
        g.run_frames(60)
        outs = g.outputs("sink", "out")
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import time
from collections import deque
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from .clock import Clock
from .codec import DecodeError, Header, peek
from .graph import Graph
from .node import Node
from .node_checks import validate_node
from .node_host import NodeHost
from .pubsub import MAX_PAYLOAD_BYTES, RateLimitedLog
from .schemas import Frame, Message, ReplayHint, decode, encode, validate, wire_copy
from .stats import TopicStats

log = logging.getLogger(__name__)

DEFAULT_CLOCK_START_NS = 1_700_000_000_000_000_000  # a plausible wall time (2023-11-14), ns
MAX_ROUNDS = 10_000  # delivery rounds at one instant before a message loop is called runaway
MAX_IDLE_STEPS = 10_000  # steps with neither the clock moving nor a message (a source polling with delay 0)
# A copied message's size for the publication limit and the statistics: its arrays plus this for the rest (the
# head of a small message is 100-300 bytes; the bytes are made only for recorded topics and with wire=True).
HEAD_ALLOWANCE_BYTES = 256


class InProcessError(RuntimeError):
    """The in-process run cannot go on: a node's setup failed, or messages or polls never settle."""


@contextlib.contextmanager
def _exit_is_an_error(host: NodeHost) -> Iterator[None]:
    """A handler that exits (SystemExit: live, its process would end and be restarted) must not end this
    process: the run stops with an InProcessError naming the node."""
    try:
        yield
    except SystemExit as exc:
        raise InProcessError(f"node {host.spec.name!r} exited (status {exc.code})") from exc


class _Queue:
    """An input queue with the bus's size and policy (see the module docstring for ``block``)."""

    def __init__(self, maxlen: int, policy: str, stats: TopicStats):
        self.maxlen = maxlen
        self.policy = policy
        self.stats = stats
        self.items: deque[Message] = deque()

    def push(self, msg: Message) -> None:
        if len(self.items) >= self.maxlen and self.policy == "drop_oldest":
            self.items.popleft()
            self.stats.drop()
        self.items.append(msg)


class _Publisher:
    """``Node.publish`` in-process: fills the header as bus.pubsub.Publisher does, on the simulated clock."""

    def __init__(self, owner: InProcessGraph, host: _Host, output: str):
        self.owner = owner
        self.host = host
        self.topic = f"{host.spec.name}/{output}"
        self.source = host.spec.name
        self.stats = TopicStats(owner.graph.key(host.spec.name, output), "out")
        self._seq = 0

    def put(self, msg: Message) -> bool:
        msg.header.seq = self._seq
        msg.header.source = self.source
        msg.header.pub_ns = self.owner.now_ns
        self._seq += 1
        return self.owner._publish(self.topic, msg, self.stats)


def _own_copy(msg: Message) -> Message:
    """A subscriber's own message and header over shared (read-only) values: copy.copy's result, at a fraction
    of its cost (it is made for every message every subscriber receives)."""
    new = object.__new__(type(msg))
    new.__dict__.update(msg.__dict__)
    header = object.__new__(Header)
    header.__dict__.update(msg.header.__dict__)
    new.header = header
    return new


def _as_received(payload: bytes | None, copied: Message | DecodeError | None) -> Message:
    """A recorded publication as a subscriber got it; DecodeError if it could not (as decoding it would)."""
    if copied is None:
        return decode(payload)  # type: ignore[arg-type]  # only the bytes were published (inject_bytes, wire)
    if isinstance(copied, DecodeError):
        raise copied
    return _own_copy(copied)


class _Host(NodeHost):
    """One node of an in-process graph."""

    def __init__(self, owner: InProcessGraph, name: str, clock: Clock, validated: tuple[type[Node], Any]):
        super().__init__(owner.graph, name, clock, validated)
        self.owner = owner
        self.queues: dict[str, _Queue] = {}
        for inp in self.spec.inputs.values():
            stats = TopicStats(owner.graph.key(inp.source_node, inp.source_output), "in")
            self.queues[inp.name] = _Queue(inp.queue, inp.policy, stats)
        for out in self.spec.outputs:
            self.publishers[out] = _Publisher(owner, self, out)
        self.create_node()
        self.next_poll_ns: int | None = None  # set at start: every node is polled once, as live
        self.stopped = False

    def receive(self, input_name: str, sent: bytes | memoryview | Message | DecodeError, size: int, stamp_ns: int,
                now_ns: int, checked: dict[Any, Message | DecodeError]) -> None:
        """Queue what was published for this input: ``sent`` is the encoded message (decoded here), or the
        runtime's copy of it (or why it would not decode). ``checked``: what earlier subscribers of the same
        publication made of it, by expected type; each subscriber gets its own copy of the message and header
        (the arrays, read-only, are shared), as if it had decoded the bytes itself."""
        queue = self.queues[input_name]
        schema = self.cls.INPUTS[input_name].type
        shared = checked.get(schema)
        if shared is None:
            try:
                if isinstance(sent, DecodeError):
                    raise sent
                if not isinstance(sent, Message):
                    shared = validate(decode(sent, schema))
                elif schema is not None and type(sent) is not schema:
                    raise DecodeError(f"expected {schema.TYPE}, got {sent.TYPE}")
                else:
                    shared = validate(sent)
            except DecodeError as exc:
                shared = exc
            checked[schema] = shared
        if isinstance(shared, DecodeError):
            queue.stats.decode_error()
            self._warn.warning("dropped malformed message on %s: %s", queue.stats.key, shared)
            return
        msg = _own_copy(shared)
        queue.stats.record(stamp_ns, size, now_ns=now_ns)
        msg._arrival = next(self.owner._arrival)  # type: ignore[attr-defined]
        queue.push(msg)

    def take(self) -> list[tuple[str, Message]]:
        items = [(name, m) for name, q in self.queues.items() for m in q.items]
        for q in self.queues.values():
            q.items.clear()
        items.sort(key=lambda item: item[1]._arrival)  # type: ignore[attr-defined]
        return items

    def pending(self) -> bool:
        for q in self.queues.values():  # noqa: SIM110  # a loop, not any(): asked for every node every round
            if q.items:
                return True
        return False

    def status(self) -> dict[str, Any]:
        """The node's counters (what its NodeStatus would carry in ``extra`` and ``topics``)."""
        extra = self.sync_counters()
        try:
            extra.update(self.node.status())
        except Exception as exc:  # as live: status never takes the node down
            extra["status_error"] = repr(exc)
        topics = {p.stats.key: p.stats.snapshot(self.owner.now_ns) for p in self.publishers.values()}
        topics.update({q.stats.key: q.stats.snapshot(self.owner.now_ns) for q in self.queues.values()})
        return {"extra": extra, "topics": topics, "stopped": self.stopped}


class InProcessGraph:
    """Runs ``graph``'s nodes (or only ``nodes``) in this process; see the module docstring.

    ``record``: the topics (``node/output``) whose publications are kept for :meth:`outputs` and
    :meth:`payloads` (default: all; frames are large); ``record_bytes=False`` keeps only the messages (for
    :meth:`drain` and :meth:`outputs`), not their encoded bytes. Inputs of nodes not run here can be fed with
    :meth:`inject` (a topic of the graph: ``"detection/detections"``). Node setup runs on the first
    ``inject``/``step``/``run_*`` (or :meth:`start`), so :meth:`node` can be inspected before.
    """

    def __init__(self, graph: Graph, nodes: Iterable[str] | None = None, *, clock: str = "sim",
                 clock_start_ns: int = DEFAULT_CLOCK_START_NS, record: Iterable[str] | None = None,
                 max_payload_bytes: int = MAX_PAYLOAD_BYTES, wire: bool = False, record_bytes: bool = True):
        if clock not in ("sim", "stamps"):
            raise ValueError(f"clock must be 'sim' or 'stamps', not {clock!r}")
        self.graph = graph
        # The hosted nodes (graph order) and where they meet the rest of the graph: the inputs to inject.
        self.boundary = graph.boundary(graph.nodes if nodes is None else nodes)
        order = list(self.boundary.nodes)
        validated = {name: validate_node(graph, graph.nodes[name]) for name in order}  # all before any is built
        self.clock_mode = clock
        self.now_ns = clock_start_ns
        self._sim_clock = Clock("sim", clock_start_ns)
        self.max_payload_bytes = max_payload_bytes
        self.wire = wire
        self.record_bytes = record_bytes or wire
        self._arrival = itertools.count()
        self._warn = RateLimitedLog(log)
        self.hosts: dict[str, _Host] = {}
        for name in order:
            node_clock = self._sim_clock if clock == "sim" else Clock("stamps")
            self.hosts[name] = _Host(self, name, node_clock, validated[name])
        self._routes: dict[str, list[tuple[_Host, str]]] = {}
        for host in self.hosts.values():
            for inp in host.spec.inputs.values():
                self._routes.setdefault(inp.topic, []).append((host, inp.name))
        self.topics = {f"{n}/{out}" for n, spec in graph.nodes.items() for out in spec.outputs}
        record_set = set(self.topics) if record is None else set(record)
        unknown = sorted(record_set - self.topics)
        if unknown:
            raise ValueError(f"record: no such topic {', '.join(unknown)} (topics: {', '.join(sorted(self.topics))})")
        # topic -> (encoded message, the subscribers' copy of it or None when only the bytes exist)
        self._recorded: dict[str, list[tuple[bytes | None, Message | DecodeError | None]]] = {
            t: [] for t in record_set}
        self.published: dict[str, int] = dict.fromkeys(self.topics, 0)
        # seconds each node spent on the messages delivered to it (its handlers and routing what they publish)
        self.handler_s: dict[str, float] = dict.fromkeys(self.hosts, 0.0)
        self.started = False
        self.closed = False

    # --- set-up and tear-down -------------------------------------------------------------------
    def start(self) -> None:
        """Set every node up (graph order). Raises InProcessError if one cannot start."""
        if self.started:
            return
        self.started = True
        for name, host in self.hosts.items():
            try:
                host.start()
            except (Exception, SystemExit) as exc:
                # Live, the node's process would exit (and be restarted by its policy); here the run cannot
                # stand for the graph without it.
                raise InProcessError(f"node {name!r} failed to start: {exc!r}") from exc
            host.next_poll_ns = self.now_ns

    def close(self) -> None:
        """Tear every node down (its ``teardown``: state saved, a serial port closed)."""
        if self.closed:
            return
        self.closed = True
        if not self.started:
            return
        for host in self.hosts.values():
            if not host.stopped:
                host.close_node()

    def __enter__(self) -> InProcessGraph:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- access ---------------------------------------------------------------------------------
    def node(self, name: str) -> Node:
        """The node instance (its state can be inspected, as a test would)."""
        return self.host(name).node

    def host(self, name: str) -> NodeHost:
        if name not in self.hosts:
            raise KeyError(f"node {name!r} is not run here (running: {', '.join(self.hosts)})")
        return self.hosts[name]

    def status(self, name: str) -> dict[str, Any]:
        """The counters a node's status would report: ``extra`` (sync, guards, handler errors, its own) and
        ``topics`` (per-topic counts, drops, decode errors)."""
        return self.hosts[name].status()

    def _published_on(self, topic: str) -> list[tuple[bytes | None, Message | DecodeError | None]]:
        """What was recorded of ``topic``; KeyError naming the recorded ones if it is not recorded."""
        if topic not in self._recorded:
            raise KeyError(f"topic {topic!r} is not recorded (recorded: {', '.join(sorted(self._recorded))})")
        return self._recorded[topic]

    def payloads(self, node: str, output: str) -> list[bytes]:
        """The encoded messages ``node`` published on ``output``, in order (recorded topics only)."""
        topic = f"{node}/{output}"
        published = self._published_on(topic)
        if any(payload is None for payload, _ in published):
            raise ValueError(f"{topic}: recorded without its bytes (record_bytes=False): use outputs or drain")
        return [payload for payload, _ in published]  # type: ignore[misc]

    def outputs(self, node: str, output: str) -> list[Message]:
        """The messages ``node`` published on ``output``, as its subscribers got them (recorded topics only)."""
        return [_as_received(payload, copied) for payload, copied in self._published_on(f"{node}/{output}")]

    def drain(self, topic: str) -> list[Message]:
        """The messages published on a recorded ``topic`` (``node/output``) since the last drain, as their
        subscribers got them, and forgotten: a long run keeps nothing it has read."""
        published = self._published_on(topic)
        self._recorded[topic] = []
        return [_as_received(payload, copied) for payload, copied in published]

    # --- feeding --------------------------------------------------------------------------------
    def inject(self, topic: str, msg: Message, *, handover: bool = False) -> bool:
        """Publish ``msg`` on ``topic`` (``node/output``) as if its producer had, header as given; it reaches
        the subscribed nodes at the next step. False if refused (size). ``handover``: the caller gives the
        message up and never writes to its arrays again, so the subscribers share them (read-only) instead
        of each publication copying them (evaluation's frames, read from disk for this one use)."""
        if topic not in self.topics:
            raise ValueError(f"no topic {topic!r} in the graph (topics: {', '.join(sorted(self.topics))})")
        self.start()
        return self._publish(topic, msg, None, handover=handover)

    def inject_bytes(self, topic: str, payload: bytes, stamp_ns: int | None = None, *, record: bool = True) -> bool:
        """Publish an encoded message (a recording's) on ``topic``; a malformed one is counted by each
        subscriber as a decode error and dropped, as on the bus. ``stamp_ns``: its header's, if known.
        ``record=False``: not kept among the topic's publications (a stand-in for a node's own output)."""
        if topic not in self.topics:
            raise ValueError(f"no topic {topic!r} in the graph (topics: {', '.join(sorted(self.topics))})")
        self.start()
        if stamp_ns is None:
            try:
                stamp_ns = peek(payload).header.stamp_ns  # the header only: each subscriber decodes the rest
            except DecodeError:
                stamp_ns = 0
        return self._route(topic, payload, stamp_ns, None, keep=record)

    def hint(self, node: str, hint: ReplayHint) -> None:
        """Replay: what the live run did with frame ``hint.header.frame_seq`` (skip it, or join exactly these
        feedback frames); give it before that frame's inputs."""
        self.start()
        self.hosts[node].apply_hints([hint])

    def _publish(self, topic: str, msg: Message, stats: TopicStats | None, *, handover: bool = False) -> bool:
        """A message published in this process: encoded (``wire=True``), or copied for the subscribers as they
        would decode it (what cannot be encoded raises here, at the publisher, as ``encode`` would)."""
        if self.wire:
            return self._route(topic, encode(msg), msg.header.stamp_ns, stats)
        try:
            copied: Message | DecodeError = wire_copy(msg, share_arrays=handover)
        except DecodeError as exc:  # written, but no subscriber could read it back: each counts it
            copied = exc
        size = HEAD_ALLOWANCE_BYTES + sum(v.nbytes for v in vars(msg).values() if isinstance(v, np.ndarray))
        payload = encode(msg) if self.record_bytes and topic in self._recorded else None
        return self._route(topic, copied, msg.header.stamp_ns, stats, size=size, payload=payload)

    def _route(self, topic: str, sent: bytes | memoryview | Message | DecodeError, stamp_ns: int,
               stats: TopicStats | None, *, size: int | None = None, payload: bytes | None = None,
               keep: bool = True) -> bool:
        """Deliver ``sent`` (an encoded message, or the runtime's copy of one) to the subscribed nodes.
        ``size``: the encoded size (an estimate when only the copy exists); ``payload``: the bytes to record;
        ``keep=False``: not recorded."""
        copied = isinstance(sent, (Message, DecodeError))
        if not copied:
            size, payload = len(sent), sent  # type: ignore[arg-type]
        assert size is not None
        if size > self.max_payload_bytes:
            if stats is not None:
                stats.refuse()
            self._warn.warning("refused a %.1f MB message on %s: over the %.1f MB publication limit",
                               size / 1e6, topic, self.max_payload_bytes / 1e6)
            return False
        if stats is not None:
            stats.record(stamp_ns, size, now_ns=self.now_ns)
        self.published[topic] += 1
        recorded = self._recorded.get(topic) if keep else None
        if recorded is not None:
            recorded.append((payload, sent if copied else None))  # type: ignore[arg-type]
        checked: dict[Any, Message | DecodeError] = {}  # one check per expected type, not per subscriber
        for host, input_name in self._routes.get(topic, ()):
            if not host.stopped:
                host.receive(input_name, sent, size, stamp_ns, self.now_ns, checked)
        return True

    # --- running --------------------------------------------------------------------------------
    def deliver(self) -> int:
        """Hand every queued message to its node, breadth-first, until none is left; returns how many."""
        self.start()
        handled = 0
        for _ in range(MAX_ROUNDS):
            batch = [(host, host.take()) for host in self.hosts.values() if host.pending() and not host.stopped]
            if not batch:
                return handled
            for host, items in batch:
                started = time.perf_counter()
                with _exit_is_an_error(host):
                    for name, msg in items:
                        if host.stopped:
                            break
                        host._dispatch(name, msg)
                        self._check_stopped(host)
                    if not host.stopped:
                        host._emit_ready()
                        if self.clock_mode == "stamps":  # as NodeRuntime: the timer follows the newest stamp
                            host.run_timer(host.clock.now_ns())
                        self._check_stopped(host)
                self.handler_s[host.spec.name] += time.perf_counter() - started
                handled += len(items)
        raise InProcessError(f"messages still flowing after {MAX_ROUNDS} delivery rounds at one instant "
                             "(a cycle of nodes that answer every message with another?)")

    def next_event_ns(self) -> int | None:
        """When the next poll, timer tick or frame-set deadline is due (None: nothing will happen by itself)."""
        self.start()
        due: list[int] = []
        for host in self.hosts.values():
            if host.stopped:
                continue
            if host.next_poll_ns is not None:
                due.append(host.next_poll_ns)
            if self.clock_mode == "sim":
                if host.next_timer_ns is not None:
                    due.append(host.next_timer_ns)
                deadline = host.sync.next_deadline_ns() if host.sync is not None else None
                if deadline is not None:
                    due.append(deadline)
        return min(due) if due else None

    def step(self) -> bool:
        """Deliver what is queued; then move the clock to the next due event, run what is due then (graph
        order: expired frame sets, timer, poll) and deliver what that published. False: nothing left to do."""
        self.deliver()
        t = self.next_event_ns()
        if t is None:
            return False
        self._advance(t)
        for host in self.hosts.values():
            if host.stopped:
                continue
            with _exit_is_an_error(host):
                if self.clock_mode == "sim":
                    host._emit_ready()  # frame sets whose deadline passed go on without what they waited for
                    host.run_timer(t)
                if host.next_poll_ns is not None and host.next_poll_ns <= t:
                    delay = host.poll_once(host.clock.now_ns())
                    host.next_poll_ns = None if delay is None else t + max(0, round(delay * 1e9))
                self._check_stopped(host)
        self.deliver()
        return True

    def run_until(self, t_ns: int) -> None:
        """Run every event due up to simulated time ``t_ns``, then set the clock to ``t_ns``."""
        self._loop(lambda: (self.next_event_ns() or t_ns + 1) <= t_ns)
        self._advance(t_ns)
        self.deliver()

    def run_for(self, duration_ns: int) -> None:
        self.run_until(self.now_ns + duration_ns)

    def run_frames(self, n: int, topic: str | None = None) -> int:
        """Run until ``n`` more messages were published on ``topic`` (default: the first frame output of the
        graph's first node run here that has one) and handled downstream, or its source is exhausted.
        Returns how many were published."""
        topic = topic or self._frame_topic()
        producer = self.hosts.get(topic.split("/", 1)[0])
        if producer is None:
            raise ValueError(f"{topic}: its node is not run here (run_until, or inject its messages)")
        target = self.published[topic] + n
        start = self.published[topic]
        self._loop(lambda: self.published[topic] < target and not producer.stopped
                   and (producer.next_poll_ns is not None or self._anything_queued()))
        return self.published[topic] - start

    def _loop(self, go_on) -> None:
        self.start()
        last, idle = None, 0
        while go_on():
            if not self.step():
                return
            progress = (self.now_ns, sum(self.published.values()))
            idle = idle + 1 if progress == last else 0
            last = progress
            if idle > MAX_IDLE_STEPS:
                raise InProcessError(f"{MAX_IDLE_STEPS} steps without the clock moving or a message published "
                                     "(a source that polls again at once and publishes nothing?)")

    def _frame_topic(self) -> str:
        for host in self.hosts.values():
            for out in host.spec.outputs:
                if host.cls.OUTPUTS[out].type is Frame:
                    return f"{host.spec.name}/{out}"
        raise ValueError("no node run here publishes frames: name the topic to count")

    def _anything_queued(self) -> bool:
        return any(h.pending() for h in self.hosts.values())

    def _advance(self, t_ns: int) -> None:
        if t_ns > self.now_ns:
            self.now_ns = t_ns
            self._sim_clock.advance_to(t_ns)

    def _check_stopped(self, host: _Host) -> None:
        if host.stop_event.is_set() and not host.stopped:
            # Node.stop(): live, its process leaves its loop and tears down.
            host.stopped = True
            host.next_poll_ns = host.next_timer_ns = None
            for q in host.queues.values():
                q.items.clear()
            host.close_node()
