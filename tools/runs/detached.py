"""``followbus up / ps / logs / down``: graphs that run in the background, as ``dora start --detach``, ``dora list``,
``dora logs`` and ``dora stop`` do.

``up`` starts ``followbus launch GRAPH --log-dir DIR`` in its own session (it survives the terminal) and returns
once every node is up; DIR (``<runs>/<name>-<date>``) gets ``launch.log`` and one ``NODE.log`` per node, and stays
after the graph stops. ``ps`` lists the run records of tools/runs/claims.py (every launch, demo and up has one
while it runs); ``down`` sends the launcher SIGTERM (it stops its nodes) and waits until its claim is released.
"""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from ..errors import UsageError
from .claims import RunRecord, live_runs, runs_root

READY_MARK = "ready:"  # the launcher's "graph 'x' ready: N nodes up" line
DOWN_TIMEOUT_S = 15.0  # the launcher's grace (5 s) for its nodes, and some


def _run_dir(name: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path, n = runs_root() / f"{name}-{stamp}", 1
    while path.exists():
        n += 1
        path = runs_root() / f"{name}-{stamp}-{n}"
    path.mkdir(parents=True)
    return path


def _launch_argv(args, log_dir: Path, domain: int | None) -> list[str]:
    argv = [sys.executable, "-m", "followbus.tools.cli", "launch", str(Path(args.graph).resolve()),
            "--log-dir", str(log_dir), "--startup-timeout", str(args.startup_timeout)]
    for flag, value in (("--domain", domain), ("--namespace", args.namespace), ("--port", args.port),
                        ("--only", args.only)):
        if value is not None:
            argv += [flag, str(value)]
    return argv + [f"--set={item}" for item in args.overrides]


def _wait_ready(proc: subprocess.Popen, log: Path, timeout_s: float) -> int | None:
    """None once the launcher says every node is up; its exit status if it ended first; -1 on timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        code = proc.poll()
        if code is not None:
            return code
        if READY_MARK in log.read_text(errors="replace"):
            return None
        time.sleep(0.1)
    return -1


def cmd_up(args) -> int:
    from ..command import load_graph
    from .claims import free_domain

    graph = load_graph(args.graph)  # a wrong file is one line here, not in a log
    domain = args.domain
    if domain == "auto":
        domain, note = free_domain(args.graph)
        if note:
            print(note)
    log_dir = _run_dir(graph.name)
    log = log_dir / "launch.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(_launch_argv(args, log_dir, domain), stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    code = _wait_ready(proc, log, args.startup_timeout + 5)
    if code is not None:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        said = next((line for line in reversed(lines) if line.startswith("followbus")), lines[-1] if lines else "")
        if code == -1:
            proc.terminate()
            said = f"not up after {args.startup_timeout + 5:.0f} s"
        print(f"followbus up: {graph.name} did not start: {said} (log: {log})", file=sys.stderr)
        return 2 if code == 2 else 1
    record = next((r for r in live_runs() if r.pid == proc.pid), None)
    where = f"{record.endpoint}, namespace {record.namespace}, " if record else ""
    print(f"{graph.name} is up: pid {proc.pid}, {where}{len(graph.nodes)} nodes; logs in {log_dir}\n"
          f"  followbus logs {graph.name} NODE [-f]    followbus down {graph.name}")
    for note in plays_once(graph, args.overrides):
        print(f"  note: {note}")
    return 0


def plays_once(graph, overrides: list[str]) -> list[str]:
    """The nodes that play a finite source once (a scene, a video, a folder, a recording; not a camera or a topic)
    with ``loop`` off: a graph in the background then runs on with nothing to follow, which `up` says."""
    from ...bus.graph import apply_overrides
    from ...bus.node_checks import validate_node

    graph = copy.deepcopy(graph)
    apply_overrides(graph, overrides)
    notes = []
    for name, spec in graph.nodes.items():
        params = validate_node(graph, spec)[1]
        source, loop = getattr(params, "source", None), getattr(params, "loop", None)
        if isinstance(source, str) and loop is False and not source.startswith(("camera:", "ros2:")):
            length = " (a scene lasts 8-20 s)" if source.startswith("scene:") else ""
            notes.append(f"{name} plays {source} once{length}, then publishes nothing: "
                         f"`--set {name}.loop=true` plays it again and again")
    return notes


def _uptime(seconds: float) -> str:
    minutes, sec = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{sec:02d}s"


def health_text(nodes: dict[str, dict] | None) -> str:
    """A graph's node health in a few words: "all up", or how many are up and what the others do."""
    if nodes is None:
        return "?"
    others = {name: n for name, n in sorted(nodes.items()) if n.get("state") != "up"}
    restarts = sum(int(n.get("restarts", 0)) for n in nodes.values())
    again = f", {restarts} restarts" if restarts else ""
    if not others:
        return f"all up{again}"
    return (f"{len(nodes) - len(others)}/{len(nodes)} up: "
            + ", ".join(f"{name} {n.get('state')}" for name, n in others.items()) + again)


def cmd_ps(args) -> int:
    from .claims import read_health

    runs = live_runs()
    if not runs:
        print("no graph is running (start one with `followbus up GRAPH`, `launch` or `demo`)")
        return 0
    rows = [("NAME", "NAMESPACE", "ENDPOINT", "UPTIME", "NODES", "HEALTH", "PID", "USER", "STARTED BY")]
    rows += [(r.name, r.namespace, r.endpoint, _uptime(r.uptime_s()), str(len(r.nodes)), health_text(read_health(r)),
              str(r.pid), r.user, r.command) for r in runs]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip())
    return 0


def _listing(runs: list[RunRecord]) -> str:
    return ", ".join(f"{r.name} (pid {r.pid}, {r.namespace}{'' if r.mine else ', user ' + r.user})" for r in runs)


def find_run(which: str | None, runs: list[RunRecord] | None = None) -> RunRecord:
    """The running graph a command names (its name or its launcher's pid). Without a name, the one graph this user
    started: on a shared machine the one graph running may be someone else's, so it is never picked for them."""
    runs = live_runs() if runs is None else runs
    if not runs:
        raise UsageError("no graph is running (`followbus up GRAPH` starts one)")
    if which is None:
        mine = [r for r in runs if r.mine]
        if len(mine) == 1:
            return mine[0]
        if not mine:
            raise UsageError(f"no graph of yours is running (others': {_listing(runs)}); name one to act on it")
        raise UsageError(f"{len(mine)} graphs of yours are running: {_listing(mine)}; name one by its name or pid")
    matches = [r for r in runs if which in (r.name, str(r.pid))]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        raise UsageError(f"no graph named {which!r} is running (running: {_listing(runs)})")
    raise UsageError(f"{len(matches)} graphs match {which!r}: {_listing(matches)}; name one by its pid")


def cmd_down(args) -> int:
    run = find_run(args.name)
    try:
        os.kill(run.pid, signal.SIGTERM)
    except PermissionError:
        raise UsageError(f"{run.name} (pid {run.pid}) was started by user {run.user}: only they can stop it") from None
    started = time.monotonic()
    while any(r.pid == run.pid for r in live_runs()):
        if time.monotonic() - started > DOWN_TIMEOUT_S:
            os.kill(run.pid, signal.SIGKILL)
            print(f"followbus down: {run.name} (pid {run.pid}) did not stop in {DOWN_TIMEOUT_S:.0f} s: killed",
                  file=sys.stderr)
            return 1
        time.sleep(0.1)
    print(f"stopped {run.name} (pid {run.pid}, namespace {run.namespace}) in {time.monotonic() - started:.1f} s")
    return 0


def _log_dir(which: str | None) -> tuple[Path, RunRecord | None]:
    """A running graph's log directory, else the newest finished run of that name; without a name, only this user's
    (a running graph of theirs, else their newest run)."""
    runs = [r for r in live_runs() if r.log_dir]
    named = [r for r in runs if which in (r.name, str(r.pid)) or (which is None and r.mine)]
    if named:
        run = find_run(which, named)  # two of them: which one, by pid
        return Path(run.log_dir), run
    dirs = sorted((d for d in runs_root().glob(f"{which or ''}*-*") if (d / "launch.log").exists()
                   and (which is not None or d.stat().st_uid == os.getuid())), key=lambda d: d.stat().st_mtime)
    if not dirs:
        if which is None and runs:
            raise UsageError(f"no graph of yours was started with `followbus up` (others': {_listing(runs)}); "
                             "name one to read its logs")
        what = f"graph {which!r}" if which else "graph"
        raise UsageError(f"no logs of a {what} started with `followbus up` in {runs_root()}")
    return dirs[-1], None


def cmd_logs(args) -> int:
    which, node = (args.names if len(args.names) == 2 else [None, args.names[0]])
    directory, run = _log_dir(which)
    path = directory / f"{node}.log"
    if not path.exists():
        known = sorted(p.stem for p in directory.glob("*.log"))
        raise UsageError(f"no log of node {node!r} in {directory} (there are: {', '.join(known)})")
    with open(path, "rb") as handle:
        _copy(handle)
        while args.follow and run is not None and any(r.pid == run.pid for r in live_runs()):
            time.sleep(0.2)
            _copy(handle)
    return 0


def _copy(handle) -> None:
    data = handle.read()
    if data:
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
