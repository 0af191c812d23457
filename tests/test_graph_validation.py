"""A bad graph.yaml exits with status 2 and names the file, the line and the key."""

from __future__ import annotations

import dataclasses

import pytest

from .conftest import REPO, run_followbus

GOOD_NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 10}
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs:
      tick: {from: ticker/tick, queue: 2, policy: drop_oldest}
"""


def test_good_graph_passes(graph_file):
    result = run_followbus("check", str(graph_file(GOOD_NODES)))
    assert result.returncode == 0, result.stderr
    assert "ok (2 nodes)" in result.stdout


# (what, nodes yaml, expected line in the file, text expected in the message)
# The file has 6 header lines (name, namespace, zenoh x3, nodes), so node text starts at line 7.
CASES = [
    ("unknown node key", GOOD_NODES.replace("    outputs: [tick]\n", "    outputs: [tick]\n    colour: red\n"),
     10, "unknown key 'colour'"),
    ("unknown producer node", GOOD_NODES.replace("from: ticker/tick", "from: camera/tick"),
     14, "unknown node 'camera'"),
    ("unknown output", GOOD_NODES.replace("from: ticker/tick", "from: ticker/frames"),
     14, "has no output 'frames'"),
    ("duplicate node name", GOOD_NODES + "  ticker:\n    run: followbus.nodes.diagnostics\n",
     15, "duplicate node name 'ticker'"),
    ("wrong type", GOOD_NODES.replace("queue: 2", "queue: two"), 14, "queue must be an integer"),
    ("unknown param", GOOD_NODES.replace("rate_hz: 10", "rate_hz: 10, speed: 3"), 10, "unknown parameter 'speed'"),
    ("wrong param type", GOOD_NODES.replace("rate_hz: 10", "rate_hz: fast"), 10, "'rate_hz' must be float"),
    ("missing run", GOOD_NODES.replace("    run: followbus.nodes.diagnostics\n", "", 1),
     7, "missing required key 'run'"),
    ("no such module", GOOD_NODES.replace("nodes.diagnostics\n", "nodes.nope\n", 1), 7, "No module named"),
    ("input the node does not take", GOOD_NODES.replace("      tick: {", "      tock: {"), 14, "has no input 'tock'"),
    ("bad policy", GOOD_NODES.replace("drop_oldest", "drop_newest"), 14, "policy must be one of"),
    ("future offset", GOOD_NODES.replace("queue: 2", "offset: 1"), 14, "offset must be 0 or -1"),
    ("bad restart policy", GOOD_NODES.replace("    outputs: [tick]\n", "    outputs: [tick]\n    restart: sometimes\n"),
     10, "restart: policy must be one of"),
    ("invalid yaml", GOOD_NODES.replace("outputs: [tick]", "outputs: [tick"), 10, "invalid YAML"),
]


@pytest.mark.parametrize("what,nodes,line,message", CASES, ids=[c[0] for c in CASES])
def test_bad_graph_exits_2_with_file_line_and_key(graph_file, what, nodes, line, message):
    path = graph_file(nodes)
    result = run_followbus("check", str(path))
    assert result.returncode == 2, (what, result.stdout, result.stderr)
    first = result.stderr.strip().splitlines()[-1]
    assert f"{path}:{line}:" in first, first
    assert message in first, first


def test_unknown_top_level_key_and_launch_also_exit_2(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text("name: x\nnodez: {}\n")
    result = run_followbus("launch", str(path), "--duration", "1")
    assert result.returncode == 2
    assert f"{path}:2: unknown key 'nodez'" in result.stderr


def test_missing_file_exits_2(tmp_path):
    result = run_followbus("check", str(tmp_path / "absent.yaml"))
    assert result.returncode == 2 and "absent.yaml" in result.stderr and "cannot read" in result.stderr


def test_robot_graph_runs_the_same_nodes_as_graph_yaml():
    """graph.robot.yaml differs from graph.yaml only in its bus; its node section drifted once (stale
    odometry sync and no feedback sync timeouts on the robot), so the two are compared here."""
    from followbus.bus.graph import load_graph

    def without_lines(value):  # where a key sits in its file is not what it means
        if isinstance(value, dict):
            return {k: without_lines(v) for k, v in value.items() if k not in ("line", "param_lines")}
        return [without_lines(v) for v in value] if isinstance(value, list) else value

    dev, robot = load_graph(REPO / "graph.yaml"), load_graph(REPO / "graph.robot.yaml")
    nodes = {g: {n: without_lines(dataclasses.asdict(spec)) for n, spec in graph.nodes.items()}
             for g, graph in (("dev", dev), ("robot", robot))}
    assert nodes["robot"] == nodes["dev"]
    assert robot.zenoh.mode == "router" and dev.zenoh.mode == "peer"
