"""``followbus launch``: one OS process per node, readiness from liveliness, restart policies,
prefixed logs, clean shutdown, children that never outlive the launcher."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..bus.barrier import LAUNCHED_NODES_ENV, LEFT_OUT_NODES_ENV
from ..bus.children import die_with_parent
from ..bus.graph import Graph, NodeSpec
from ..bus.health import (
    LAUNCHER_PERIOD_S,
    HealthWatcher,
    LaunchedProcess,
    launcher_id,
    launcher_key,
    node_state,
    process_table,
)
from ..bus.hosts import host_plan, nodes_on
from ..bus.links import LinkWatch, edges_of_graph
from ..bus.liveness import STOPPED_WORKING_EXIT
from ..bus.node_runtime import LAUNCH_ID_ENV
from ..bus.pubsub import Publisher, direct_callback
from ..bus.session import MemoryTrim, open_session
from .runs.claims import health_path, write_health

log = logging.getLogger("followbus.launch")
LINK_CHECK_PERIOD_S = 1.0  # a graph spread over hosts: its links are judged this often (statuses come once a second)
INTERRUPTED_EXIT = 130  # every command's status after Ctrl-C (tools/cli.py)
TOOL_GRACE_S = 30.0  # a tool beside the graph (the recorder) gets this long to stop after SIGTERM

# A node that fails again after being restarted this recently is crash-looping: its restarts are not helping.
CRASH_LOOP_EXITS = 2
CRASH_LOOP_WINDOW_S = 60.0
# A line a node printed that says why it stopped: a logged ERROR, or the last line of a Python traceback.
ERROR_LINE_RE = re.compile(r"\bERROR\b|^[A-Za-z_][\w.]*(Error|Exception|Exit)\b")


@dataclass
class Child:
    spec: NodeSpec
    argv: list[str]
    proc: subprocess.Popen | None = None
    restarts: int = 0
    next_start: float = 0.0
    failed: bool = False  # failed for good (restart budget exhausted or policy never)
    finished: bool = False  # exited cleanly and will not be restarted
    pid: int = 0  # the current process, or the last one once it exited
    exit_code: int | None = None
    changed_at: float = 0.0  # monotonic time of its last start or exit
    threads: list[threading.Thread] = field(default_factory=list)
    failures: list[tuple[float, int]] = field(default_factory=list)  # (monotonic time, status) of failed exits
    last_error: str = ""  # the last line it printed that says why it stopped (see ERROR_LINE_RE)
    last_line: str = ""  # the last line it printed at all (a one-line "followbus: ..." refusal, say)
    published: bool = False  # some output of it was seen on the bus (watch_outputs)
    output_subs: list = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.spec.name


class Launcher:
    def __init__(self, graph: Graph, *, only: list[str] | None = None, host: str | None = None,
                 startup_timeout_s: float = 30.0, grace_s: float = 5.0, extra_env: dict[str, str] | None = None,
                 extra_children: list[tuple[str, list[str]]] | None = None, quiet: bool = False,
                 overrides: list[str] | None = None, log_file: Path | None = None, watch_outputs: bool = False,
                 log_dir: Path | None = None):
        self.graph = graph
        self.log_dir = log_dir  # a log file per node (<log_dir>/<node>.log) besides the prefixed lines
        # Subscribe to every node's outputs until its first message: problems() names the silent ones.
        self.watch_outputs = watch_outputs
        self.interrupted = False  # stopped by Ctrl-C/SIGTERM rather than by its duration
        self.refusal = ""  # why the graph could not start at all (TLS), one line
        self.ran_s = 0.0
        self.grace_s = grace_s
        self.startup_timeout_s = startup_timeout_s
        self.quiet = quiet
        self.overrides = list(overrides or [])
        self.log_file = open(log_file, "a") if log_file is not None else None  # noqa: SIM115 (closed at shutdown)
        self.stop_event = threading.Event()
        self.ready_event = threading.Event()
        self._out_lock = threading.Lock()
        self.env = dict(os.environ, **(extra_env or {}), PYTHONUNBUFFERED="1")
        on_host = set(nodes_on(graph, host))  # each node on exactly one host (bus/hosts.py)
        selected = [spec for name, spec in graph.nodes.items() if name in on_host and (not only or name in only)]
        if only:
            unknown = set(only) - set(graph.nodes)
            if unknown:
                raise ValueError(f"--only names unknown node(s): {', '.join(sorted(unknown))}")
        self.children = [Child(spec, self._node_argv(spec.name)) for spec in selected]
        # Nodes may wait for each other at start-up (capture holds frame 0 until its chain listens).
        self.env[LAUNCHED_NODES_ENV] = ",".join([spec.name for spec in selected]
                                                + [name for name, _ in extra_children or []])
        self.left_out = on_host - {spec.name for spec in selected}  # this host's nodes --only left out
        self.env[LEFT_OUT_NODES_ENV] = ",".join(sorted(self.left_out))
        for name, argv in extra_children or []:
            self.children.append(Child(NodeSpec(name=name, run="<tool>"), argv))
        self.health: HealthWatcher | None = None
        self.session = None
        # A graph spread over hosts: this launcher watches the links between its nodes and the other hosts'.
        self.links = _link_watch(graph, host)
        self._links_due = 0.0
        self.memory_trim: MemoryTrim | None = None
        # The process table (which node runs as which pid, which exited) lets monitors tell a live node
        # from a token someone else declared under its name (bus/health.py).
        self.launcher_id = launcher_id(socket.gethostname(), os.getpid())
        self._table_pub: Publisher | None = None
        self._table_due = 0.0  # monotonic time of the next publication; 0 = at once
        self._started_ns = time.time_ns()
        self.env[LAUNCH_ID_ENV] = f"{self.launcher_id}@{self._started_ns}"  # restarted children keep it

    def _node_argv(self, name: str) -> list[str]:
        argv = [sys.executable, "-m", "followbus.tools.cli", "node", name, "--graph", str(Path(self.graph.path))]
        for item in self.overrides:
            if item.split(".", 1)[0] == name:
                argv += ["--set", item]
        return argv

    def _print(self, text: str) -> None:
        if self.quiet:
            return
        with self._out_lock:
            out = self.log_file or sys.stdout
            out.write(text + "\n")
            out.flush()

    def _pump(self, child: Child, stream) -> None:
        width = max(len(c.name) for c in self.children)
        prefix = f"[{child.name:<{width}}] "
        own = open(self.log_dir / f"{child.name}.log", "ab") if self.log_dir else None  # noqa: SIM115
        for raw in iter(stream.readline, b""):
            if own is not None:
                own.write(raw)
                own.flush()
            line = raw.decode(errors="replace").rstrip()
            if ERROR_LINE_RE.search(line.strip()):
                child.last_error = line.strip()
            if line.strip():
                child.last_line = line.strip()
            self._print(prefix + line)
        stream.close()
        if own is not None:
            own.close()

    def _start(self, child: Child) -> None:
        child.proc = subprocess.Popen(
            child.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=self.env,
            preexec_fn=die_with_parent, stdin=subprocess.DEVNULL,
        )
        thread = threading.Thread(target=self._pump, args=(child, child.proc.stdout), daemon=True)
        thread.start()
        child.threads.append(thread)
        child.pid, child.exit_code, child.changed_at = child.proc.pid, None, time.monotonic()
        self._table_due = 0.0
        log.info("started %s (pid %d)", child.name, child.proc.pid)

    def _on_exit(self, child: Child, code: int) -> None:
        child.exit_code, child.changed_at = code, time.monotonic()
        if code != 0 and not self.stop_event.is_set():
            child.failures.append((child.changed_at, code))
        self._table_due = 0.0
        policy = child.spec.restart
        log_fn = log.info if code == 0 else log.warning
        log_fn("%s exited with status %d", child.name, code)
        wants_restart = policy.policy == "always" or (policy.policy == "on-failure" and code != 0)
        if child.spec.run == "<tool>" or self.stop_event.is_set() or not wants_restart:
            child.failed = code != 0 and not _interrupted(code)
            child.finished = True
            if child.failed:
                log.error("%s failed for good (status %d, restart policy %s)", child.name, code, policy.policy)
            return
        # The budget is per window (RestartPolicy): only the failures of the last window_s count.
        in_window = sum(1 for t, _ in child.failures if child.changed_at - t <= policy.window_s) or 1
        if in_window > policy.max_restarts:
            child.failed = True
            child.finished = True
            log.error("%s failed for good: %d failures within %d s (restart budget %d)", child.name, in_window,
                      policy.window_s, policy.max_restarts)
            return
        backoff_ms = min(policy.backoff_ms * (2 ** (in_window - 1)), policy.max_backoff_ms)
        child.restarts += 1
        child.next_start = time.monotonic() + backoff_ms / 1000
        log.warning("restarting %s in %d ms (failure %d of at most %d within %d s; %d restarts so far)", child.name,
                    backoff_ms, in_window, policy.max_restarts, policy.window_s, child.restarts)

    def _publish_table(self, stopped: bool = False) -> None:
        """Publish the process table now; ``stopped`` retracts it (the launcher is going away)."""
        if self._table_pub is None:
            return
        now = time.monotonic()
        processes = {c.name: LaunchedProcess(c.pid, c.proc is not None and not stopped, c.restarts, c.exit_code,
                                             since_s=now - c.changed_at)
                     for c in self.children if c.pid}
        msg = process_table(self.launcher_id, processes, os.getpid(), (time.time_ns() - self._started_ns) / 1e9,
                            stopped=stopped)
        try:
            self._table_pub.put(msg)
        except Exception as exc:  # monitoring must never take the graph down
            log.warning("could not publish the process table: %r", exc)
        self._table_due = time.monotonic() + LAUNCHER_PERIOD_S

    def node_states(self) -> dict[str, dict[str, Any]]:
        """Each node's state as `followbus ps` shows it: up, stalled, done (bus/health.py node_state), starting (no
        token yet), restarting, failed; and its restarts."""
        snapshot = self.health.snapshot() if self.health is not None else {}
        out = {}
        for child in self.children:
            if child.spec.run == "<tool>":
                continue
            health = snapshot.get(child.name)
            if child.failed:
                state = "failed"
            elif child.proc is None:
                state = "exited" if child.finished else "restarting"
            elif health is None or not health.alive:
                state = "starting"
            else:
                state = node_state(True, health.status.extra if health.status else None)
            out[child.name] = {"state": state, "restarts": child.restarts}
        return out

    def _write_health(self) -> None:
        try:
            write_health(health_path(self.graph), self.node_states())
        except OSError as exc:  # `ps` shows less; the graph runs on
            log.debug("could not write the health file: %r", exc)

    def request_stop(self, *_args) -> None:
        self.stop_event.set()

    def _watch_outputs(self) -> None:
        for child in self.children:
            if child.spec.run == "<tool>":
                continue
            for out in child.spec.outputs:
                def seen(_sample, child: Child = child) -> None:
                    child.published = True
                child.output_subs.append(self.session.declare_subscriber(self.graph.key(child.name, out),
                                                                         direct_callback(seen)))

    def _unwatch(self, every: bool = False) -> None:
        """Undeclare the output subscriptions of nodes already heard from (all of them with ``every``): one
        message is all problems() needs, and a subscriber on raw frames would keep receiving them."""
        for child in self.children:
            if child.output_subs and (every or child.published):
                for sub in child.output_subs:
                    with contextlib.suppress(Exception):
                        sub.undeclare()
                child.output_subs = []

    def problems(self) -> list[str]:
        """What went wrong in the run that just ended, one phrase per node: a node that failed for good or
        crash-looped (with the last error it printed), one that stopped working and was restarted, and, for a
        run that lasted its duration with ``watch_outputs``, a node that never published any of its outputs."""
        return self.failures() + self.silences()

    def failures(self) -> list[str]:
        """The nodes that failed for good, crash-looped or stopped working, one phrase each."""
        return [phrase for phrase in map(_failure, self.children) if phrase]

    def silences(self) -> list[str]:
        """With ``watch_outputs``, after a run that lasted its duration: the nodes that never published (one phrase)."""
        if not self.watch_outputs or self.interrupted:
            return []
        silent = [c.name for c in self.children if c.spec.run != "<tool>" and c.spec.outputs and not c.published]
        return [f"no output in {self.ran_s:.0f} s from {', '.join(silent)}"] if silent else []

    def run(self, duration_s: float | None = None, on_ready=None) -> int:
        """Run until duration elapses (counted from the moment every node is up, so start-up on a busy
        machine does not eat the run), Ctrl-C/SIGTERM, or every node has finished. Returns the exit status."""
        self._open_bus()
        self.refusal = self._tls_refusal()
        if self.refusal:
            return self._shutdown(2)
        for child in self.children:
            self._start(child)
        node_names = {c.name for c in self.children if c.spec.run != "<tool>"}
        started = time.monotonic()
        deadline = None  # set when the graph is ready
        ready_at: float | None = None
        try:
            while not self.stop_event.is_set():
                now = time.monotonic()
                if deadline is not None and now >= deadline:
                    break
                self._tend(now)
                if ready_at is None:
                    missing = node_names - self.health.alive()
                    if not missing:
                        ready_at = now
                        deadline = None if duration_s is None else now + duration_s
                        self._announce_ready(len(node_names), now - started, on_ready)
                    elif now - started > self.startup_timeout_s:
                        self._report_startup_timeout(missing)
                        self.ran_s = now - started
                        return self._shutdown(1)
                if self._should_stop():
                    break
                time.sleep(0.05)
        except KeyboardInterrupt:
            log.info("interrupted")
            self.interrupted = True
        self.interrupted = self.interrupted or self.stop_event.is_set()
        # How long the graph ran: from the moment every node was up (else from the start, for a report of
        # a start-up that never finished).
        self.ran_s = time.monotonic() - (ready_at if ready_at is not None else started)
        status = 1 if any(c.failed for c in self.children) else 0
        return self._shutdown(status)

    def _open_bus(self) -> None:
        """Open the session, the liveliness watch, the process table and (with watch_outputs) the output watch."""
        self.session = open_session(self.graph.zenoh)
        self.memory_trim = MemoryTrim(self.session)  # the hub: what a departed laptop's declarations held
        # Statuses too: `followbus ps` shows a stalled source from the health file (_write_health), and a graph
        # spread over hosts judges its links from them.
        self.health = HealthWatcher(self.session, self.graph.namespace, watch_status=True, cross_check=False)
        self._table_pub = Publisher(self.session, launcher_key(self.graph.namespace, self.launcher_id),
                                    self.launcher_id, congestion="drop")
        if self.watch_outputs:
            self._watch_outputs()

    def _tend(self, now: float) -> None:
        """One turn of the loop's upkeep: reap exited children, start the ones due, publish the process
        table when due, and drop the output watch of nodes already heard from."""
        for child in self.children:
            if child.proc is not None:
                self._reap(child)
            elif not child.finished and now >= child.next_start:
                self._start(child)
        if now >= self._table_due:
            self._publish_table()
            self._write_health()
        if self.links is not None and self.health is not None and now >= self._links_due:
            self._links_due = now + LINK_CHECK_PERIOD_S
            for level, line in self.links.check(self.health.snapshot(), now):
                log.log(level, "%s", line)
        if self.watch_outputs:
            self._unwatch()

    def _reap(self, child: Child) -> None:
        code = child.proc.poll()
        if code is not None:
            child.proc = None
            self._on_exit(child, code)

    def _announce_ready(self, n_nodes: int, startup_s: float, on_ready) -> None:
        self._write_health()  # before the line `followbus up` waits for: a `ps` after it sees every node up
        self.ready_event.set()
        # `followbus up` waits for this line in a detached run's launch.log (READY_MARK).
        log.info("graph %r ready: %d nodes up in %.1f s", self.graph.name, n_nodes, startup_s)
        if on_ready is not None:
            on_ready()

    def _tls_refusal(self) -> str:
        """A graph whose nodes cannot pass the TLS handshake with its endpoints (an expired certificate, a CA that did
        not sign it) would end in a start-up timeout that names no cause: said at once instead, naming TLS."""
        from .connect import graph_tls_problem

        problem = graph_tls_problem(self.graph.zenoh)
        if problem:
            log.error("%s", problem)
        return problem or ""

    def _report_startup_timeout(self, missing: set[str]) -> None:
        from .connect import graph_tls_problem

        tls = graph_tls_problem(self.graph.zenoh)
        log.error("startup timeout after %.0f s: no liveliness from %s%s", self.startup_timeout_s,
                  ", ".join(sorted(missing)), f" ({tls})" if tls else "")
        self.refusal = self.refusal or (tls or "")

    def _should_stop(self) -> bool:
        """Every child has finished, or a node (not a tool) failed for good."""
        if all(c.finished for c in self.children):
            return True
        if any(c.failed for c in self.children if c.spec.run != "<tool>"):
            # A graph missing a node for good (its motor, say) must not limp on. A tool beside it (the
            # recorder on a full disk) failing is reported, but the robot keeps following.
            log.error("stopping the graph: a node failed for good")
            return True
        return False

    def _shutdown(self, status: int) -> int:
        self.stop_event.set()
        running = [c for c in self.children if c.proc is not None and c.proc.poll() is None]
        for child in running:
            with contextlib.suppress(ProcessLookupError):
                child.proc.send_signal(signal.SIGTERM)
        stopped_at = time.monotonic()
        for child in running:
            # The recorder drains its queue to disk and finalises the file: killed, it leaves one to `recover`.
            grace_s = self.grace_s if child.spec.run != "<tool>" else max(self.grace_s, TOOL_GRACE_S)
            try:
                child.proc.wait(timeout=max(0.0, stopped_at + grace_s - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.1f s; killing it", child.name, grace_s)
                child.proc.kill()
                child.proc.wait()
        for child in self.children:
            for thread in child.threads:
                thread.join(timeout=1.0)
        failed = sorted(c.name for c in self.children if c.failed)
        if failed:
            log.error("node(s) failed for good: %s", ", ".join(failed))
        self._publish_table(stopped=True)
        with contextlib.suppress(OSError):
            health_path(self.graph).unlink()
        self._unwatch(every=True)
        if self.health is not None:
            self.health.close()
        if self.memory_trim is not None:
            self.memory_trim.close()
        if self.session is not None:
            self.session.close()
        if self.log_file is not None:
            self.log_file.close()
        return status


def _link_watch(graph: Graph, host: str | None) -> LinkWatch | None:
    """The watch over the links between ``host`` and the graph's other hosts (None: a one-host graph)."""
    if host is None or len(host_plan(graph)) < 2:
        return None
    hosts = {name: graph.host_of(name) or "" for name in graph.nodes}
    return LinkWatch(edges_of_graph(graph), hosts, host, peer_mode=graph.zenoh.mode == "peer")


def _interrupted(code: int) -> bool:
    """A child that exited as every command does after Ctrl-C (the terminal sent it SIGINT with the launcher)."""
    from .errors import INTERRUPTED

    return code == INTERRUPTED_EXIT and INTERRUPTED.is_set()


def _failure(child: Child) -> str | None:
    """One phrase for a child that failed for good, crash-looped or stopped working (bus/liveness.py); else None."""
    said = child.last_error or child.last_line
    why = f": {said[:320]}" if said else ""  # room for a source and its error
    last_t, last_code = child.failures[-1] if child.failures else (0.0, child.exit_code)
    recent = [t for t, _ in child.failures if t >= last_t - CRASH_LOOP_WINDOW_S]
    if child.failed or len(recent) >= CRASH_LOOP_EXITS:
        what = "failed for good" if child.failed else "crash-looped"
        return f"{child.name} {what} (exited {len(child.failures)} times, last status {last_code}){why}"
    if any(code == STOPPED_WORKING_EXIT for _, code in child.failures):
        # Restarted, and maybe working again, but a scripted run must not pass as if nothing happened.
        return f"{child.name} stopped working and was restarted ({child.restarts} restarts){why}"
    return None


def install_stop_signals(launcher: Launcher) -> None:
    from .errors import INTERRUPTED

    def handler(signum, _frame):
        if signum == signal.SIGINT:
            INTERRUPTED.set()
        log.info("received %s: stopping the graph", signal.Signals(signum).name)
        launcher.request_stop()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
