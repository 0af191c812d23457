"""Every silence of issue 23 says its line, with its exit status: echo/hz on a key nothing publishes, launch --only
with inputs nothing launched produces, a monitor that never reached a graph, Ctrl-C (130)."""

from __future__ import annotations

import signal
import subprocess
import threading
import time

import pytest

from followbus.tools.live.silence import explain_silence

from .conftest import REPO, followbus_argv, refusing_endpoint, run_followbus, wait_until
from .test_cli_errors import one_error_line, router  # noqa: F401 (a fixture)

KEYS = {"fb/prediction/track": "prediction", "fb/capture/frame": "capture"}


def test_a_misspelt_key_names_its_close_matches():
    line = explain_silence("fb/prediction/trak", "fb", KEYS, {"prediction", "capture"})
    assert line == "no node publishes fb/prediction/trak; did you mean fb/prediction/track?"


def test_a_key_without_the_namespace_names_the_full_key():
    line = explain_silence("prediction/track", "fb", KEYS, {"prediction"})
    assert line.startswith("no node publishes prediction/track; did you mean fb/prediction/track")


def test_a_key_whose_node_is_down_or_silent_says_which():
    assert explain_silence("fb/prediction/track", "fb", KEYS, {"capture"}) == (
        "nothing on fb/prediction/track yet: node prediction, which publishes it, is not running")
    assert "node prediction is up but has not published it" in explain_silence("fb/prediction/track", "fb", KEYS,
                                                                                 {"prediction"})


@pytest.mark.slow
def test_echo_and_hz_on_a_bus_without_a_graph_say_so_after_a_second(router):  # noqa: F811
    for cmd in ("echo", "hz"):
        result = run_followbus(cmd, "t/ticker/tick", "--connect", router, "--seconds", "2.5", timeout=30)
        assert result.returncode == 1, result.stderr
        assert result.stderr.strip().splitlines()[0] == (
            "followbus: nothing on t/ticker/tick: no graph is running in namespace fb (no node is alive)")


@pytest.mark.slow
def test_launch_only_names_the_inputs_nothing_launched_produces(graph_file):
    graph = graph_file("  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n"
                       "  sink:\n    run: followbus.nodes.diagnostics_sink\n    inputs: {tick: ticker/tick}\n",
                       namespace="o1only")
    result = run_followbus("launch", str(graph), "--only", "sink", "--duration", "1", timeout=60)
    assert result.stderr.splitlines()[0] == ("followbus launch: no producer launched for sink.tick (ticker/tick): "
                                             "they wait for a node started elsewhere (or a replay)")


@pytest.mark.slow
def test_launch_only_starts_a_source_without_waiting_for_the_consumers_it_left_out(graph_file):
    """`launch --only capture` used to hold frame 0 for wait_for_consumers_s (15 s) waiting for a detection node
    nobody was going to start, then blame capture for publishing nothing."""
    graph = graph_file("  capture:\n    run: followbus.nodes.capture\n    outputs: [frame, preview, ground_truth]\n"
                       "    params: {source: 'scene:wall-occlusion', loop: true}\n"
                       "  detection:\n    run: followbus.nodes.detection\n    inputs: {frame: capture/frame}\n"
                       "    outputs: [detections]\n    params: {backend: simulated}\n", namespace="o1left")
    result = run_followbus("launch", str(graph), "--only", "capture", "--duration", "4", timeout=60)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "waits for" not in result.stderr
    said = result.stdout + result.stderr
    assert "not waiting for detection: left out of this launch by --only and not running" in said


def test_monitor_that_never_reached_a_graph_fails_in_one_line():
    with refusing_endpoint() as endpoint:
        result = run_followbus("monitor", "--connect", endpoint, "--seconds", "1", timeout=30)
    assert one_error_line(result).startswith(f"followbus: no graph is running on {endpoint}")


@pytest.mark.slow
@pytest.mark.parametrize("argv", [["echo", "t/x"], ["launch"]], ids=["echo", "launch"])
def test_ctrl_c_exits_130(argv, graph_file, router):  # noqa: F811
    graph = graph_file("  ticker:\n    run: followbus.nodes.diagnostics\n    outputs: [tick]\n", namespace="o1int")
    # echo joins a bus with nothing on its key (a router): it waits for messages until Ctrl-C.
    full = [*argv, "--connect", router] if argv[0] == "echo" else [*argv, str(graph)]
    # Ctrl-C at a terminal: SIGINT at its default, also when the suite runs as a background job (tests/conftest.py).
    proc = subprocess.Popen(followbus_argv(*full), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, stdin=subprocess.DEVNULL)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    try:
        if argv[0] == "launch":
            assert wait_until(lambda: run_followbus("ps").stdout.count("o1int") == 1, 30)
        else:  # connected and waiting: it has said why nothing came yet
            assert wait_until(lambda: any("nothing on t/x" in line for line in lines), 30), lines
        proc.send_signal(signal.SIGINT)
        # A bound, not a timing: with two burners beside two test workers this took more than 20 s twice.
        try:
            code = proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGUSR1)  # the command's own stack dump (faulthandler): where it is stuck
            time.sleep(2)
            code = None
        assert code == 130, "".join(lines)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
