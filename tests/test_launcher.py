"""The launcher: starts a 3-node graph, restarts a node killed with SIGKILL, and shuts everything down
on SIGINT leaving no process behind."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from pathlib import Path

import pytest

from followbus.bus.health import HealthWatcher
from followbus.bus.session import ZenohSettings, open_session

from .conftest import followbus_argv, processes_matching, wait_until

pytestmark = pytest.mark.slow

NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 50}
  relay:
    run: followbus.nodes.diagnostics_relay
    inputs: {tick: ticker/tick}
    outputs: [tick]
    params: {add: 1000}
    restart: {policy: on-failure, max_restarts: 3, backoff_ms: 200}
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs: {tick: relay/tick}
"""


def test_launch_restart_and_clean_shutdown(graph_file, port):
    graph = graph_file(NODES)
    launcher = subprocess.Popen(followbus_argv("launch", str(graph)), stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(launcher.stdout.readline, "")), daemon=True)
    reader.start()
    session = open_session(ZenohSettings(mode="client", listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    watcher = HealthWatcher(session, "t")
    try:
        assert wait_until(lambda: any("ready: 3 nodes up" in line for line in lines), 60), "".join(lines)
        assert wait_until(lambda: watcher.alive() == {"ticker", "relay", "sink"}, 10)

        def sink_value() -> int:
            st = watcher.snapshot().get("sink")
            return st.status.extra.get("last_value", -1) if st and st.status else -1

        assert wait_until(lambda: sink_value() >= 1000, 15), "relayed ticks never reached the sink"
        assert wait_until(lambda: watcher.snapshot()["relay"].status is not None, 5)
        relay_pid = watcher.snapshot()["relay"].status.pid
        launch_id = _launch_id(relay_pid)
        assert launch_id, "the launcher gives its children a launch id"
        os.kill(relay_pid, signal.SIGKILL)

        def restarted() -> bool:
            relay = watcher.snapshot()["relay"]
            return relay.alive and relay.ups >= 2 and relay.status is not None and relay.status.pid != relay_pid

        assert wait_until(restarted, 20), "".join(lines[-20:])
        # A restart is the same launch (the template node restores its state then, and only then).
        assert _launch_id(watcher.snapshot()["relay"].status.pid) == launch_id
        before = sink_value()
        assert wait_until(lambda: sink_value() > before + 10, 10), "ticks did not flow again after the restart"
        assert any("restarting relay" in line for line in lines)
    finally:
        launcher.send_signal(signal.SIGINT)
        try:
            code = launcher.wait(30)
        finally:
            if launcher.poll() is None:
                launcher.kill()
            watcher.close()
            session.close()
    assert code == 130, "".join(lines[-30:])  # stopped by Ctrl-C, cleanly: the shell's 130 (README, exit status)
    assert wait_until(lambda: not processes_matching(str(graph)), 5), processes_matching(str(graph))


def _launch_id(pid: int) -> str:
    from followbus.bus.node_runtime import LAUNCH_ID_ENV

    return _child_env(pid, LAUNCH_ID_ENV)


def _child_env(pid: int, name: str) -> str:
    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    prefix = f"{name}=".encode()
    return next((item[len(prefix):].decode() for item in environ if item.startswith(prefix)), "")


def _launch_failing_ticker(graph_file, fail_after_s: float, restart: str, duration_s: int,
                           extra: str = "") -> subprocess.CompletedProcess:
    """`launch --duration` of a diagnostics ticker that fails after ``fail_after_s``, with ``restart`` policy."""
    graph = graph_file(
        "  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n"
        f"    params: {{rate_hz: 10, fail_after_s: {fail_after_s}}}\n"
        f"    restart: {restart}\n" + extra
    )
    return subprocess.run(followbus_argv("launch", str(graph), "--duration", str(duration_s)), capture_output=True,
                          text=True, timeout=60, stdin=subprocess.DEVNULL)


def test_node_that_keeps_failing_makes_launch_exit_nonzero(graph_file):
    sink = "  sink:\n    run: followbus.nodes.diagnostics_sink\n    inputs: {tick: ticker/tick}\n"
    result = _launch_failing_ticker(graph_file, 0.5, "{policy: on-failure, max_restarts: 1, backoff_ms: 100}", 30, sink)
    output = result.stdout + result.stderr
    assert result.returncode == 1, output
    assert "ticker failed for good: 2 failures within 60 s (restart budget 1)" in output
    assert "restarting ticker" in output


def test_failures_older_than_the_restart_window_do_not_spend_the_budget(graph_file):
    # Each run lasts longer than the 1 s window: every failure is the only one in its window, so a budget of one
    # restart never runs out, as a robot's node that fails once an hour must be restarted every hour.
    restart = "{policy: on-failure, max_restarts: 1, window_s: 1, backoff_ms: 100}"
    result = _launch_failing_ticker(graph_file, 1.5, restart, 12)
    output = result.stdout + result.stderr
    assert output.count("restarting ticker in 100 ms (failure 1 of at most 1 within 1 s") >= 3, output
    assert "failed for good" not in output, output
