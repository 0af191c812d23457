"""Graphs apart by default (issue 23): a graph's identity (namespace, port, --domain) is a launch option, a launch
refuses a bus where a graph of its namespace runs, ``--domain auto`` takes the first free domain; and the
commands that operate graphs in the background (up, ps, logs, down, graph)."""

from __future__ import annotations

import contextlib
import os
import re
import socket
import subprocess
from collections.abc import Iterator

import pytest

from followbus.bus.graph import load_graph
from followbus.tools.domains import apply_domain

from .conftest import REPO, followbus_argv, free_port, run_followbus

NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 20}
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs: {tick: ticker/tick}
"""


def test_a_domain_moves_the_port_and_the_namespace(graph_file, port):
    graph = load_graph(graph_file(NODES, namespace="o1iso"))
    apply_domain(graph, {"FOLLOWBUS_DOMAIN": "3"})
    assert graph.namespace == "o1iso-d3"
    assert graph.zenoh.listen == [f"tcp/127.0.0.1:{port + 3}"] and graph.zenoh.connect == graph.zenoh.listen
    # --namespace and --port replace the graph's; the domain moves them in turn.
    graph = apply_domain(load_graph(graph.path), {"FOLLOWBUS_NAMESPACE": "o1x", "FOLLOWBUS_PORT": "21450",
                                                    "FOLLOWBUS_DOMAIN": "1"})
    assert (graph.namespace, graph.zenoh.connect) == ("o1x-d1", ["tcp/127.0.0.1:21451"])
    result = run_followbus("check", str(graph.path), "--domain", "x")  # check takes no identity: argparse says so
    assert result.returncode == 2


def test_a_bad_domain_is_one_line(graph_file):
    result = run_followbus("launch", str(graph_file(NODES)), "--domain", "500")
    assert result.returncode == 2
    assert result.stderr.strip() == "followbus: --domain 500: a domain is a number 0..232"


@pytest.mark.slow
def test_up_ps_logs_down_and_a_launch_into_a_live_graph_is_refused(graph_file, tmp_path, port):
    graph = graph_file(NODES, namespace="o1iso")
    up = run_followbus("up", str(graph), timeout=60)
    assert up.returncode == 0, up.stderr
    pid = int(re.search(r"pid (\d+)", up.stdout)[1])
    try:
        ps = run_followbus("ps")
        assert re.search(rf"test\s+o1iso\s+tcp/127.0.0.1:{port}\s+\S+\s+2\s+all up\s+{pid}\s+\S+\s+up", ps.stdout), \
            ps.stdout
        # Into the same bus and namespace: refused in one line naming who, where and what to do.
        refused = run_followbus("launch", str(graph), "--duration", "1")
        assert refused.returncode == 2
        line = refused.stderr.strip()
        assert "\n" not in line and f"pid {pid}" in line and f"tcp/127.0.0.1:{port}" in line and "--domain" in line
        # A mistake in the file or its overrides comes first: it needs fixing in whichever domain the graph runs.
        mistake = run_followbus("launch", str(graph), "--set", "ticker.no_such_param=1", "--duration", "1")
        assert mistake.returncode == 2 and "no_such_param" in mistake.stderr, mistake.stderr
        assert "--domain" not in mistake.stderr and len(mistake.stderr.strip().splitlines()) == 1, mistake.stderr
        # Seen on the bus too, for a graph this machine has no record of (another runs directory, another host).
        alone = run_followbus_env({"FOLLOWBUS_RUNS": str(tmp_path / "elsewhere")}, "launch", str(graph))
        assert alone.returncode == 2 and "nodes sink, ticker" in alone.stderr, alone.stderr
        # --domain auto moves on, and says so.
        moved = run_followbus("launch", str(graph), "--domain", "auto", "--duration", "1", timeout=60)
        assert moved.returncode == 0, moved.stderr
        assert f"running in domain 1: tcp/127.0.0.1:{port + 1}, namespace o1iso-d1" in moved.stdout
        logs = run_followbus("logs", "test", "sink")
        assert logs.returncode == 0 and "node sink up" in logs.stdout
        unknown = run_followbus("logs", "test", "nosuch")
        assert unknown.returncode == 2 and "there are: " in unknown.stderr and "sink" in unknown.stderr
    finally:
        down = run_followbus("down", str(pid))
    assert down.returncode == 0 and f"stopped test (pid {pid}" in down.stdout
    assert run_followbus("ps").stdout.startswith("no graph is running")
    gone = run_followbus("down", "test")
    assert gone.returncode == 2 and gone.stderr.startswith("followbus: no graph is running")


@contextlib.contextmanager
def held_by_a_connection(port: int) -> Iterator[None]:
    """``port`` as the local port of an open connection, as the kernel gives ports of its ephemeral range to
    outgoing connections (no SO_REUSEADDR: a listener cannot bind it)."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        with socket.socket() as client:
            client.bind(("127.0.0.1", port))
            client.connect(server.getsockname())
            accepted, _ = server.accept()
            with accepted:
                yield


@pytest.mark.slow
def test_a_port_held_by_a_connection_is_named_and_auto_moves_past_it(graph_file, port):
    """Another process's connection holds the graph's port and nothing listens there: the graph's peers could not
    meet on it, and each node would run alone until the launch timed out saying only that no node came up. A launch
    says why in one line (exit 2); --domain auto moves on to the next domain."""
    graph = graph_file(NODES, namespace="o1held")
    with held_by_a_connection(port):
        refused = run_followbus("launch", str(graph), "--duration", "1")
        assert refused.returncode == 2
        line = refused.stderr.strip()
        assert "\n" not in line and f"port {port}" in line and "held by another process's connection" in line, line
        moved = run_followbus("launch", str(graph), "--domain", "auto", "--duration", "1", timeout=60)
        assert moved.returncode == 0, moved.stderr
        assert f"running in domain 1: tcp/127.0.0.1:{port + 1}, namespace o1held-d1" in moved.stdout


def run_followbus_env(env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(followbus_argv(*args), capture_output=True, text=True, timeout=60, cwd=REPO,
                          stdin=subprocess.DEVNULL, env={**os.environ, **env})


def test_graph_draws_nodes_and_keys(graph_file):
    graph = graph_file(NODES.replace("inputs: {tick: ticker/tick}", "inputs: {tick: ticker/tick}\n    outputs: [n]"))
    dot = run_followbus("graph", str(graph), "--dot")
    assert dot.returncode == 0
    assert '"n:ticker" -> "k:ticker/tick";' in dot.stdout and '"k:ticker/tick" -> "n:sink";' in dot.stdout
    assert 'label="t/ticker/tick"' in dot.stdout
    svg = run_followbus("graph", str(graph), "--svg")
    assert svg.stdout.startswith("<svg") and svg.stdout.count('class="node"') == 2
    assert svg.stdout.count('class="key"') == 2


def test_graph_layers_follow_the_data_and_feedback_does_not_count():
    from followbus.bus.graph_drawing import back_edges, layout

    graph = load_graph(REPO / "graph.yaml")
    cells = layout(graph)
    closing = back_edges(graph)  # the inputs that close a cycle (the odometry prediction reads from the motor)
    for name, spec in graph.nodes.items():
        for inp in spec.inputs.values():
            if inp.offset == 0 and (f"k:{inp.topic}", f"n:{name}") not in closing:
                assert cells[f"k:{inp.topic}"][0] < cells[f"n:{name}"][0], (name, inp.topic)
    assert len(set(cells.values())) == len(cells)  # nothing drawn over anything


@pytest.mark.slow
def test_two_demos_at_once_each_run_their_own_graph(tmp_path):
    """Two demos started together with --domain auto (as `make demo` does) run on two buses: each reports its own
    summary, the second in domain 1. (Their TSR under the machine's load: BENCHMARKS.md.)"""
    env = {**os.environ, "FOLLOWBUS_PORT": str(free_port()), "FOLLOWBUS_NAMESPACE": "o1demo"}
    argv = followbus_argv("demo", "--domain", "auto", "--duration", "8")
    procs = [subprocess.Popen([*argv, "--log", str(tmp_path / f"demo{i}.log")], cwd=REPO, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
             for i in range(2)]
    outs = [p.communicate(timeout=120)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert sum("running in domain 1:" in out for out in outs) == 1, outs
    for out in outs:
        assert re.search(r"TSR@20px \d", out), out
        assert re.search(r"detector: \d+\.\d ms a frame \(p90 \d+\.\d\) for a 33\.3 ms frame period", out), out


def test_demo_from_another_directory_runs_the_checkouts_graph(tmp_path, monkeypatch, capsys):
    from followbus.tools.demo import default_graph_path

    monkeypatch.chdir(tmp_path)
    assert default_graph_path("graph.yaml") == str(REPO / "graph.yaml")
    said = capsys.readouterr().out.strip()
    assert said == f"no graph.yaml in {tmp_path}: running the checkout's {REPO / 'graph.yaml'}"
    (tmp_path / "graph.yaml").write_text("")
    assert default_graph_path("graph.yaml") == "graph.yaml"  # one here is the user's
    assert default_graph_path("mine.yaml") == "mine.yaml"  # a missing --graph: the loader's own line
