"""``followbus replay --isolated``: the node as the deployed process (``followbus node NAME --clock stamps``)
in a private graph (private namespace, private loopback port), fed over Zenoh with the same order and hints
as the in-process replay (replay/feed.py)."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from ..bus.children import die_with_parent
from ..bus.graph import Graph, RestartPolicy
from ..bus.schemas import ReplayHint
from ..bus.session import ZenohSettings
from .feed import frame_and_stamp
from .plan import ReplayOptions, ReplayReport
from .targets import InProcessTarget

log = logging.getLogger("followbus.replay")

LOCKSTEP_QUEUE = 64  # inputs queue deep and block, whatever the live policy was
REPLAY_SHM_BYTES = 256 * 1024 * 1024


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def private_graph(graph: Graph, name: str, params: dict[str, Any], namespace: str, port: int) -> Graph:
    """The node under test alone (stand-ins for its producers), on a private peer bus: every input queues deep
    and blocks (lockstep), the node's params as replayed, never restarted, at the replayer's own priority."""
    spec = graph.nodes[name]
    lockstep = {i.name: dataclasses.replace(i, queue=max(i.queue, LOCKSTEP_QUEUE), policy="block")
                for i in spec.inputs.values()}
    private = graph.subgraph([name], name=f"replay-{name}").override({name: params})
    return (private.with_node(name, inputs=lockstep, restart=RestartPolicy(policy="never"), nice=None,
                            realtime=None, host=None)
            .with_zenoh(ZenohSettings(shm=graph.zenoh.shm)).with_port(port).with_namespace(namespace))


class IsolatedTarget:
    """The node as the deployed process (``followbus node NAME --clock stamps``) in a private graph over
    Zenoh. The in-process run of the same node, fed alongside, says how many outputs the process must have
    published before the next input goes out: lockstep without guessing when the process is idle."""

    def __init__(self, reference: InProcessTarget, report: ReplayReport, options: ReplayOptions, tmp: Path):
        plan = reference.plan
        if len(plan.nodes) != 1:
            raise ValueError("--isolated replays one node (several run in-process only)")
        self.plan = plan
        self.report = report
        self.opts = options
        self.reference = reference
        self.name = plan.nodes[0]
        self.spec = plan.graph.nodes[self.name]
        self.private_ns = f"replay_{secrets.token_hex(4)}"
        self.tmp = tmp
        self.proc: subprocess.Popen | None = None
        self._cond = threading.Condition()
        self._received: dict[str, list[bytes]] = {t: [] for t in plan.outputs.values()}
        # Awaited outputs per topic. A timer's outputs of no frame (motor's odometry) tick on each side's own
        # schedule: only frame-bound ones are awaited on those topics.
        self._awaited: dict[str, int] = dict.fromkeys(plan.outputs.values(), 0)
        self._reference_seen: dict[str, tuple[int, int]] = dict.fromkeys(plan.outputs.values(), (0, 0))
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._session: Any = None
        self._watcher: Any = None
        self.log_path = tmp / "node.log"

    def start(self) -> None:
        from ..bus.health import HealthWatcher
        from ..bus.pubsub import Publisher, ShmPool, declare_subscriber
        from ..bus.session import open_session

        self.reference.start()
        graph_path = self.tmp / "graph.yaml"
        private = private_graph(self.plan.graph, self.name, self.plan.params[self.name], self.private_ns,
                                free_port())
        graph_path.write_text(private.to_yaml())
        self._session = open_session(private.zenoh)  # takes the private port first; the node connects to it
        for topic in self.plan.outputs.values():
            # Direct callbacks keep the order of samples across keys (bus.pubsub.direct_callback).
            self._subs.append(declare_subscriber(self._session, private.key(*topic.split("/", 1)),
                                                 self._on_output(topic)))
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
                env=_node_env(), preexec_fn=die_with_parent)
        t0 = time.perf_counter()
        missing = self._watcher.wait_for({self.name}, self.opts.startup_timeout_s)
        self.report.startup_s = time.perf_counter() - t0
        if self.proc.poll() is not None:
            raise RuntimeError(f"node {self.name} exited with status {self.proc.poll()}")
        if missing:
            raise RuntimeError(f"node {self.name} did not come up within {self.opts.startup_timeout_s:.0f} s")

    def _on_output(self, topic: str):
        def callback(sample) -> None:
            from ..bus.codec import DecodeError
            from ..bus.pubsub import frame_bytes, payload_bytes

            try:
                data = frame_bytes(sample)
            except DecodeError:  # a lane message that cannot be read: kept as it came, the comparison shows it
                data = payload_bytes(sample)
            awaited = topic not in self.plan.timer_topics or frame_and_stamp(data)[0] >= 0
            with self._cond:
                self._received[topic].append(data)
                self._awaited[topic] += awaited
                self._cond.notify_all()

        return callback

    def hint(self, node: str, hint: ReplayHint) -> None:
        self.reference.hint(node, hint)
        self._hint_pub.put(hint)

    def stand_in(self, topic: str, data: bytes, stamp_ns: int) -> None:
        raise NotImplementedError("--isolated replays one node: it has no replayed reader to stand in for")

    def send(self, topic: str, data: bytes, stamp_ns: int, frame_seq: int) -> None:
        self.reference.send(topic, data, stamp_ns, frame_seq)
        self._pubs[topic].put_bytes(data, stamp_ns)
        if not self._wait_caught_up(self.opts.frame_timeout_s):
            self.report.timeouts.append(frame_seq)
            if self.proc is not None and self.proc.poll() is not None:
                raise RuntimeError(f"node {self.name} exited with status {self.proc.returncode}")

    def _wait_caught_up(self, timeout_s: float) -> bool:
        """Wait until the process published what the in-process run published by now."""
        want = {t: self._reference_awaited(t) for t in self._received}
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not all(self._awaited[t] >= n for t, n in want.items()):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.proc is not None and self.proc.poll() is not None):
                    return False
                self._cond.wait(min(remaining, 0.2))
        return True

    def _reference_awaited(self, topic: str) -> int:
        if topic not in self.plan.timer_topics:
            return self.reference.published(topic)
        seen, count = self._reference_seen[topic]
        payloads = self.reference.graph.payloads(*topic.split("/", 1))
        count += sum(frame_and_stamp(p)[0] >= 0 for p in payloads[seen:])
        self._reference_seen[topic] = (len(payloads), count)
        return count

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


def _node_env() -> dict[str, str]:
    """The replayer's environment without its domain: the private graph already names the node's port and
    namespace, and a domain exported in the shell would move the node onto the domain's instead."""
    env = {k: v for k, v in os.environ.items() if k != "FOLLOWBUS_DOMAIN"}  # tools/domains.py's variable
    return env | {"PYTHONUNBUFFERED": "1"}
