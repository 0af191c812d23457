"""host: and default_host: (bus/hosts.py): every node runs on exactly one host. The old rule (a node without
host: runs on every `launch --host`) started capture and motor on the compute host too; a graph that names a
host for some nodes only is now refused unless it says default_host, and `check --host` lists each host's
nodes."""

from __future__ import annotations

import pytest

from followbus.bus.graph import GraphError, load_graph
from followbus.bus.hosts import HOST_ENV, HostError, host_plan, nodes_on, this_host
from followbus.tools.cli import main

NODES = """\
nodes:
  capture: {run: followbus.nodes.diagnostics, outputs: [tick]}
  detection: {run: followbus.nodes.diagnostics_relay, inputs: {tick: capture/tick}, outputs: [tick], host: gpu}
  motor: {run: followbus.nodes.diagnostics_sink, inputs: {tick: detection/tick}}
"""


def _graph(tmp_path, head: str = "", name: str = "split.yaml"):
    path = tmp_path / name
    path.write_text(f"name: split\nnamespace: t\n{head}{NODES}")
    return path


def _old_rule(graph, host: str) -> list[str]:
    """What `launch --host` started until this change: the host's nodes and every node without host:."""
    return [name for name, spec in graph.nodes.items() if spec.host in (None, host)]


def test_old_rule_duplicated_nodes_new_rule_refuses_or_partitions(tmp_path):
    graph = load_graph(str(_graph(tmp_path, "default_host: robot\n")))
    # The old duplicate: launched on both machines, capture and motor ran twice (both motors commanded).
    old = {host: _old_rule(graph, host) for host in ("robot", "gpu")}
    assert set(old["robot"]) & set(old["gpu"]) == {"capture", "motor"}
    # The new rule: each node on exactly one host.
    assert nodes_on(graph, "robot") == ["capture", "motor"] and nodes_on(graph, "gpu") == ["detection"]
    assert host_plan(graph) == {"robot": ["capture", "motor"], "gpu": ["detection"]}
    # The same graph without default_host is refused where it is loaded (launch, check, node, demo).
    with pytest.raises(GraphError) as err:
        load_graph(str(_graph(tmp_path)))
    assert str(err.value).endswith("node 'detection' runs on host 'gpu' but capture, motor name no host: add "
                                   "`default_host: NAME` (the machine that runs every node without a host:)")


def test_which_host_a_launch_stands_for(tmp_path, monkeypatch):
    graph = load_graph(str(_graph(tmp_path, "default_host: robot\n")))
    monkeypatch.delenv(HOST_ENV, raising=False)
    monkeypatch.setattr("socket.gethostname", lambda: "laptop")
    with pytest.raises(HostError, match="runs on hosts robot, gpu: say which this machine is with --host"):
        this_host(graph, None)
    with pytest.raises(HostError, match=r"no node of .* runs on host 'gpu2' \(hosts: robot, gpu\)"):
        nodes_on(graph, "gpu2")
    monkeypatch.setenv(HOST_ENV, "gpu")
    assert this_host(graph, None) == "gpu"
    monkeypatch.setattr("socket.gethostname", lambda: "robot")
    monkeypatch.delenv(HOST_ENV)
    assert this_host(graph, None) == "robot"
    # A one-machine graph (no host anywhere) needs no --host: every node.
    single = tmp_path / "one.yaml"
    single.write_text("name: one\n" + NODES.replace(", host: gpu", ""))
    one = load_graph(str(single))
    assert this_host(one, None) is None and nodes_on(one, None) == list(one.nodes)


def test_check_lists_what_each_host_runs_and_launch_refuses_an_unknown_host(tmp_path, capsys, monkeypatch):
    path = str(_graph(tmp_path, "default_host: robot\n"))
    assert main(["check", path]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1:] == ["hosts (`followbus launch --host HOST` starts these nodes):",
                       "  robot (default_host): capture, motor", "  gpu: detection"]
    assert main(["check", path, "--host", "gpu"]) == 0
    assert capsys.readouterr().out.splitlines()[1:] == [
        "hosts (`followbus launch --host HOST` starts these nodes):", "  gpu: detection"]
    assert main(["launch", path, "--host", "gpu2", "--duration", "1"]) == 2
    assert capsys.readouterr().err.strip() == (f"followbus: no node of {path} runs on host 'gpu2' "
                                               "(hosts: robot, gpu)")
    monkeypatch.delenv(HOST_ENV, raising=False)
    monkeypatch.setattr("socket.gethostname", lambda: "laptop")
    assert main(["launch", path, "--duration", "1"]) == 2
    assert "say which this machine is with --host" in capsys.readouterr().err
