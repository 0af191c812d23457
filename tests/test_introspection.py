"""followbus topics / echo / hz / nodes against a launched diagnostic graph."""

from __future__ import annotations

import json
import signal
import subprocess

import pytest

from .conftest import followbus_argv, run_followbus, wait_until

pytestmark = pytest.mark.slow

NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 20}
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs: {tick: ticker/tick}
"""


def test_topics_echo_hz_nodes(graph_file):
    graph = graph_file(NODES)
    launcher = subprocess.Popen(followbus_argv("launch", str(graph)), stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    try:
        def nodes_up() -> bool:
            out = run_followbus("nodes", "--graph", str(graph), "--seconds", "1.5").stdout
            return "ticker" in out and "sink" in out and out.count(" up ") == 2

        assert wait_until(nodes_up, 30, interval=0.5)

        topics = run_followbus("topics", "--graph", str(graph), "--seconds", "2")
        assert topics.returncode == 0, topics.stderr
        line = next(ln for ln in topics.stdout.splitlines() if ln.startswith("t/ticker/tick "))
        assert line.split()[1] == "Tick" and 15 < float(line.split()[2]) < 25, line

        echo = run_followbus("echo", "t/ticker/tick", "--graph", str(graph), "-n", "3", "--seconds", "10")
        assert echo.returncode == 0, echo.stderr
        messages = [json.loads(ln.split(": ", 1)[1]) for ln in echo.stdout.splitlines()]
        assert len(messages) == 3 and all(m["type"] == "Tick" for m in messages)
        values = [m["value"] for m in messages]
        assert values == sorted(values) and values[-1] - values[0] == 2

        hz = run_followbus("hz", "t/ticker/tick", "--graph", str(graph), "--seconds", "3")
        assert hz.returncode == 0, hz.stderr
        rate = float(hz.stdout.strip().splitlines()[-1].split(": ")[1].split(" Hz")[0])
        assert 15 < rate < 25, hz.stdout
        assert "latency p50" in hz.stdout
    finally:
        launcher.send_signal(signal.SIGINT)
        launcher.wait(30)


def test_topics_names_an_announced_key_of_which_nothing_arrived(capsys):
    """Over a slow link a key its node announces may deliver nothing in the window: said, not left out silently."""
    from followbus.bus.links import PublishedKey
    from followbus.tools.live.introspect import TopicCounts, _topics_notes

    silent = {"fb/motor/command": PublishedKey("fb/motor/command", "motor", 30.0, 40.0),
              "fb/reid/measurement": PublishedKey("fb/reid/measurement", "reid", 30.0, 900.0)}
    _topics_notes(TopicCounts(), {}, silent, 3.0, {"fb/motor/command": 3.0, "fb/reid/measurement": 0.42})
    assert capsys.readouterr().out.strip().splitlines() == [
        "nothing arrived: fb/motor/command (30.0 Hz by motor's status) in 3 s over this link",
        # announced late in the window (its status came late over a full link): how long it was listened to
        "nothing arrived: fb/reid/measurement (30.0 Hz by reid's status) in the 0.4 s since reid's status "
        "announced it over this link"]


def test_topics_names_the_nodes_up_whose_status_never_came(capsys):
    """A node whose status never crossed the link is missing from the table: named, with what its token says."""
    from followbus.tools.live.introspect import _unannounced_note

    _unannounced_note([], 4.3)
    assert capsys.readouterr().out == ""
    _unannounced_note(["detection", "motor"], 4.31)
    assert capsys.readouterr().out.startswith(
        "no status from detection, motor in 4.3 s over this link, though their liveliness tokens say they are up: "
        "their keys are not listed")
