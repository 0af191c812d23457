"""NodeRuntime: one node in this process, its messages carried over Zenoh (``followbus node``, what the launcher
starts for each node), and ``run_node``, its loop until it is stopped."""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import signal
import socket
import threading
import time
from typing import Any

import zenoh

from .clock import Clock
from .graph import Graph, NodeSpec
from .live_params import LiveParams
from .liveness import STOPPED_WORKING_EXIT, NodeStoppedWorking
from .node_checks import unread_inputs, validate_node
from .node_host import NodeHost
from .pubsub import InputQueue, Publisher, ShmPool, Subscriber
from .schemas import Frame, Message, NodeStatus, ReplayHint
from .session import open_session
from .stats import TopicStats

STATUS_PERIOD_S = 1.0
# Set by the launcher for its children: one id per launch, so a node can tell its own restart (same launch)
# from a new launch (state saved by an earlier run may belong to another session: another task).
LAUNCH_ID_ENV = "FOLLOWBUS_LAUNCH_ID"


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


def _spec(graph: Graph, name: str) -> NodeSpec:
    if name not in graph.nodes:
        raise graph.error(None, f"no node named {name!r} (nodes: {', '.join(graph.nodes)})")
    return graph.nodes[name]


class NodeRuntime(NodeHost):
    """Hosts one node in this process, its messages carried over Zenoh."""

    def __init__(self, graph: Graph, name: str, *, clock: str = "wall", session: zenoh.Session | None = None):
        if clock == "sim":
            raise ValueError("a node on the bus runs on wall time or stamps; simulated time is bus.inproc's")
        super().__init__(graph, name, Clock(clock), validate_node(graph, _spec(graph, name)))
        _set_priority(self.spec.nice, self.spec.realtime, logging.getLogger(f"followbus.{name}"))
        self._own_session = session is None
        self.session = session or open_session(_node_settings(graph))
        self.started_ns = time.time_ns()
        self.subscribers: list[Subscriber] = []
        self.queues: dict[str, InputQueue] = {}
        self._cond = threading.Condition()
        self._arrival = itertools.count()
        shm = ShmPool() if graph.zenoh.shm else None
        if shm is not None and any(self.cls.OUTPUTS[out].type is Frame for out in self.spec.outputs):
            shm.warm_up()  # frames go through shared memory: not on the first frame's time
        for out in self.spec.outputs:
            port = self.cls.OUTPUTS[out]
            self.publishers[out] = Publisher(
                self.session, graph.key(self.spec.name, out), self.spec.name, congestion=port.congestion,
                express=port.express, priority=port.priority, shm=shm, lane=graph.zenoh.shm_lane,
            )
        self.create_node()
        unread = unread_inputs(self.cls, self.params)
        for inp in self.spec.inputs.values():
            if inp.name in unread:
                self.log.info("not subscribing to input %s: these params never read it", inp.name)
                continue
            key = graph.key(inp.source_node, inp.source_output)
            stats = TopicStats(key, "in")
            # An input read by stamp only feeds what the node reads when another input comes: its messages do not
            # wake the loop, they are handed over with the next message that does (at most the loop's idle period
            # later, or at once when the queue is half full), still in arrival order, so what the node computes is
            # unchanged; each wake-up of a process costs far more than the few lines of handling.
            port = self.cls.INPUTS[inp.name]
            queue = InputQueue(inp.name, inp.queue, inp.policy, stats, self._cond, wakes=not port.sample_by_stamp)
            self.queues[inp.name] = queue
            self.subscribers.append(Subscriber(
                self.session, key, self._enqueuer(queue), schema=port.type, stats=stats,
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
        # slow subscriber (a busy monitor): zenoh's put holds the caller until the link drains. Above the data it
        # describes: on a link too slow for the data (a laptop's tools over Wi-Fi) a monitor still learns every
        # node's health and keys, once a second, a few hundred bytes each.
        self._status_pub = Publisher(self.session, graph.status_key(self.spec.name), self.spec.name,
                                     congestion="drop", priority="interactive_high")
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
            extra.update(self.node.status())
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
                    self.activity.poll_ended(delay, time.monotonic(), holding=self.holding())
                    next_poll_wall = None if delay is None else time.monotonic() + max(0.0, delay)
                self.check_working(polling=next_poll_wall is not None)
        finally:
            self.close()

    def _idle_wait_s(self, next_poll_wall: float | None) -> float:
        """How long the loop may wait for a message: until the next poll, timer tick or set deadline, and at most
        50 ms (inputs read by stamp wait for a wake-up: this bounds how long)."""
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
        self.close_node()
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
