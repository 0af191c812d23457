"""`extends:` in graph files: a file applies on top of the graph it extends (merge semantics, removal, chains,
cycles, a missing base, errors located in the right file and line), and graph.robot.yaml, written that way,
resolves to the graph it was as a hand-synced copy."""

from __future__ import annotations

import copy
import dataclasses
import pickle
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from followbus.bus.graph import GraphError, SourceLine, load_graph
from followbus.bus.node_checks import validate_node
from followbus.bus.session import ZenohSettings
from followbus.tools.cli import main

from .conftest import REPO

BASE = """\
name: base
namespace: b
max_lag_ms: 200
zenoh:
  mode: peer
  listen: [tcp/127.0.0.1:7447]
  connect: [tcp/127.0.0.1:7447]
  config:
    transport/auth/usrpwd: {user: base, password: base-secret}
nodes:
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 50, payload_bytes: 16}
    restart: on-failure
  relay:
    run: followbus.nodes.diagnostics_relay
    inputs:
      tick: ticker/tick
    outputs: [tick]
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs:
      tick: {from: relay/tick, queue: 8, policy: block}
"""


def write(directory: Path, name: str, text: str) -> Path:
    path = directory / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def meaning(value: Any) -> Any:
    """A Graph or spec as plain data without where things sit (lines, the file, its text)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, dict):
        return {k: meaning(v) for k, v in value.items() if k not in ("line", "param_lines", "path", "text")}
    if isinstance(value, list):
        return [meaning(v) for v in value]
    return value


def error_of(path: Path) -> GraphError:
    with pytest.raises(GraphError) as info:
        load_graph(path)
    return info.value


def line_of(path: Path, text: str) -> int:
    """The 1-based line of the first line of ``path`` that contains ``text``."""
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if text in line)


# --- merge semantics ---------------------------------------------------------------------------------------


def test_a_file_without_its_own_changes_is_its_base(tmp_path):
    write(tmp_path, "base.yaml", BASE)
    same = write(tmp_path, "same.yaml", "extends: base.yaml\n")
    assert meaning(load_graph(same)) == meaning(load_graph(tmp_path / "base.yaml"))


def test_mappings_merge_key_by_key_and_scalars_and_lists_replace(tmp_path):
    write(tmp_path, "base.yaml", BASE)
    over = write(tmp_path, "over.yaml", """\
extends: base.yaml
name: over
zenoh:
  mode: router
  listen: [tcp/127.0.0.1:7447, tcp/127.0.0.1:7448]
  config:
    transport/auth/usrpwd: {password: over-secret}
    access_control: {enabled: true}
nodes:
  ticker:
    params: {rate_hz: 10}
    outputs: [tick, extra]
    restart: {max_restarts: 2}
  relay:
    inputs:
      tick: {queue: 1}
    nice: 5
  sink:
    inputs:
      tick: {policy: drop_oldest}
""")
    base, graph = load_graph(tmp_path / "base.yaml"), load_graph(over)
    assert (graph.name, graph.namespace, graph.max_lag_ms) == ("over", "b", 200)  # untouched scalars stay
    assert graph.zenoh == ZenohSettings(
        mode="router", listen=["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"], connect=["tcp/127.0.0.1:7447"],
        config={"transport/auth/usrpwd": {"user": "base", "password": "over-secret"},
                "access_control": {"enabled": True}})
    ticker = graph.nodes["ticker"]
    assert ticker.params == {"rate_hz": 10, "payload_bytes": 16}
    assert ticker.outputs == ["tick", "extra"]  # a list replaces, it does not append
    # 'on-failure' is {policy: on-failure}: a mapping over the shorthand keeps the policy.
    assert (ticker.restart.policy, ticker.restart.max_restarts) == ("on-failure", 2)
    relay_tick = graph.nodes["relay"].inputs["tick"]  # 'ticker/tick' is {from: ticker/tick}
    assert (relay_tick.topic, relay_tick.queue, graph.nodes["relay"].nice) == ("ticker/tick", 1, 5)
    sink_tick = graph.nodes["sink"].inputs["tick"]
    assert (sink_tick.topic, sink_tick.queue, sink_tick.policy) == ("relay/tick", 8, "drop_oldest")
    assert list(graph.nodes) == list(base.nodes)
    # The base is as it was: merging built new trees.
    assert meaning(load_graph(tmp_path / "base.yaml")) == meaning(base)


def test_null_removes_a_node_an_input_or_a_key_but_is_a_params_value(tmp_path):
    write(tmp_path, "base.yaml", BASE)
    over = write(tmp_path, "over.yaml", """\
extends: base.yaml
max_lag_ms: null
zenoh: {config: null}
nodes:
  sink: null
  relay:
    inputs: {tick: null, other: {from: ticker/tick, sync: latest}}
    outputs: null
  ticker:
    restart: null
    params: {payload_bytes: null}
  added:
    run: followbus.nodes.diagnostics_sink
    inputs: {tick: ticker/tick}
""")
    graph = load_graph(over)
    assert list(graph.nodes) == ["ticker", "relay", "added"]  # removed in place, new ones at the end
    assert list(graph.nodes["relay"].inputs) == ["other"] and graph.nodes["relay"].outputs == []
    assert graph.max_lag_ms == 150.0 and graph.zenoh.config == {}  # back to the defaults
    ticker = graph.nodes["ticker"]
    assert ticker.restart == type(ticker.restart)() and ticker.params == {"rate_hz": 50, "payload_bytes": None}


def test_null_for_something_the_base_does_not_have_is_an_error(tmp_path):
    write(tmp_path, "base.yaml", BASE)
    over = write(tmp_path, "over.yaml", "extends: base.yaml\nnodes:\n  tempalte: null\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(over), 3)
    assert "nodes.tempalte: null removes nothing" in err.message and "base.yaml" in err.message


def test_a_removed_producer_is_a_wiring_error_at_the_consumers_input_in_the_base(tmp_path):
    base = write(tmp_path, "base.yaml", BASE)
    over = write(tmp_path, "over.yaml", "extends: base.yaml\nnodes: {relay: null}\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(base), line_of(base, "tick: {from: relay/tick"))
    assert "comes from unknown node 'relay'" in err.message


def test_a_new_node_must_be_whole(tmp_path):
    write(tmp_path, "base.yaml", BASE)
    over = write(tmp_path, "over.yaml", "extends: base.yaml\nnodes:\n  extra:\n    outputs: [x]\n")
    err = error_of(over)
    assert (err.path, err.line, err.message) == (str(over), 3, "node 'extra': missing required key 'run'")


# --- chains, cycles, missing files ---------------------------------------------------------------------------


def test_a_chain_resolves_each_path_relative_to_its_own_file(tmp_path):
    write(tmp_path, "c.yaml", BASE)
    write(tmp_path, "mid/b.yaml", "extends: ../c.yaml\nname: b\nnodes: {ticker: {params: {rate_hz: 20}}}\n")
    a = write(tmp_path, "top/a.yaml", "extends: ../mid/b.yaml\nnamespace: a\nnodes: {relay: {nice: 3}}\n")
    graph = load_graph(a)
    assert (graph.name, graph.namespace) == ("b", "a")
    assert graph.nodes["ticker"].params == {"rate_hz": 20, "payload_bytes": 16}
    assert graph.nodes["relay"].nice == 3 and graph.path == str(a)
    # The recorded text stands alone: loaded from anywhere, it is the same graph.
    assert "extends" not in yaml.safe_load(graph.text)
    assert meaning(load_graph("recording.mcap#graph.yaml", graph.text)) == meaning(graph)


def test_a_cycle_is_one_clear_error(tmp_path):
    write(tmp_path, "a.yaml", "extends: b.yaml\nname: a\n")
    b = write(tmp_path, "b.yaml", "name: b\nextends: a.yaml\n")
    err = error_of(tmp_path / "a.yaml")
    assert (err.path, err.line) == (str(b), 2)
    assert err.message == f"extends: cycle {tmp_path / 'a.yaml'} -> {b} -> {tmp_path / 'a.yaml'}"
    me = write(tmp_path, "me.yaml", "extends: ./me.yaml\n")
    assert "extends: cycle" in error_of(me).message


def test_a_missing_base_names_the_extends_line(tmp_path):
    over = write(tmp_path, "over.yaml", "name: x\nextends: nowhere.yaml\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(over), 2)
    assert err.message == f"extends: cannot read {tmp_path / 'nowhere.yaml'}: No such file or directory"
    for bad in ("extends: ''", "extends: [a.yaml, b.yaml]", "extends: null"):
        err = error_of(write(tmp_path, "bad.yaml", bad + "\n"))
        assert err.line == 1 and err.message.startswith("extends must be the path of a graph file"), bad


def test_cli_check_gives_one_line_and_status_2(tmp_path, capsys):
    write(tmp_path, "a.yaml", "extends: b.yaml\n")
    write(tmp_path, "b.yaml", "extends: a.yaml\n")
    assert main(["check", str(tmp_path / "a.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("followbus: ") and "extends: cycle" in err and err.count("\n") == 1, err
    write(tmp_path, "base.yaml", BASE)
    ok = write(tmp_path, "ok.yaml", "extends: base.yaml\nnodes: {sink: null}\n")
    assert main(["check", str(ok)]) == 0
    assert "ok (2 nodes)" in capsys.readouterr().out


# --- errors point at the right file and line -----------------------------------------------------------------


def test_an_error_in_the_base_names_the_base(tmp_path):
    base = write(tmp_path, "base.yaml", BASE.replace("queue: 8", "queue: 0"))
    over = write(tmp_path, "over.yaml", "# a comment\nextends: base.yaml\nname: over\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(base), line_of(base, "queue: 0")) and "queue must be >= 1" in err.message
    broken = write(tmp_path, "base.yaml", BASE.replace("outputs: [tick]\n", "outputs: [tick\n", 1))
    err = error_of(over)
    assert err.path == str(broken) and err.message.startswith("invalid YAML")


def test_an_error_in_the_override_names_the_override(tmp_path):
    base = write(tmp_path, "base.yaml", BASE)
    over = write(tmp_path, "over.yaml", """\
extends: base.yaml
nodes:
  sink:
    inputs:
      tick:
        queue: 0
""")
    err = error_of(over)
    assert (err.path, err.line) == (str(over), 6) and "queue must be >= 1" in err.message
    over.write_text("extends: base.yaml\nnodes:\n  sink:\n    priority: 1\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(over), 4) and "unknown key 'priority'" in err.message
    over.write_text("extends: base.yaml\nnodes:\n  ticker:\n    restart: {backoff_ms: -1}\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(over), 4) and "backoff_ms must be >= 0" in err.message
    over.write_text("extends: base.yaml\nnodes:\n  ticker:\n    restart: {backoff_ms: -1}\n  ticker:\n    nice: 1\n")
    err = error_of(over)
    assert (err.path, err.line) == (str(over), 5) and "duplicate key 'nodes.ticker'" in err.message
    # The validator's node checks (after loading) locate params and nodes the same way.
    over.write_text("extends: base.yaml\nname: o\nnodes:\n  ticker:\n    params:\n      rate_hz: fast\n")
    graph = load_graph(over)
    with pytest.raises(GraphError) as info:
        validate_node(graph, graph.nodes["ticker"])
    assert (info.value.path, info.value.line) == (str(over), 6) and "rate_hz" in info.value.message
    write(tmp_path, "base.yaml", BASE.replace("payload_bytes: 16", "payload_bytez: 16"))
    over.write_text("extends: base.yaml\nname: o\n")
    graph = load_graph(over)
    with pytest.raises(GraphError) as info:
        validate_node(graph, graph.nodes["ticker"])
    assert (info.value.path, info.value.line) == (str(base), line_of(base, "payload_bytez"))


def test_source_lines_keep_their_file_through_copies():
    line = SourceLine(7, "base.yaml")
    for clone in (copy.deepcopy(line), pickle.loads(pickle.dumps(line))):
        assert (clone, clone.path, type(clone)) == (7, "base.yaml", SourceLine)
    assert GraphError("over.yaml", line, "m").path == "base.yaml"
    assert str(GraphError("over.yaml", 3, "m")) == "over.yaml:3: m"


# --- graph.robot.yaml --------------------------------------------------------------------------------------

# What graph.robot.yaml adds to graph.yaml, frozen (an intended change to the robot's bus updates this too).
_ROBOT_KEYS = ["**", "**/@health/**", "**/@status/**", "**/@launcher/**", "**/@param/**", "**/@replay/**",
               "**/@lane/**", "@followbus/**", "@/**"]
# An allow-list (issue 25): robot and operator may do everything, monitor only subscribe, ask liveliness and receive.
ROBOT_CONFIG = {
    "transport/auth/usrpwd": {"user": "robot", "password": "change-me-robot",
                              "dictionary_file": "docs/zenoh-users.example.txt"},
    # A full link drops after 1 ms, fragments too (zenoh waits 50 ms for those: a laptop's raw frames held the hub).
    "transport/link/tx/queue/congestion_control/drop": {"wait_before_drop": 1000,
                                                        "max_wait_before_drop_fragments": 1000},
    "access_control": {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {"id": "full", "permission": "allow", "flows": ["ingress", "egress"],
             "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                          "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
             "key_exprs": _ROBOT_KEYS},
            {"id": "read-only-receive", "permission": "allow", "flows": ["egress"],
             "messages": ["put", "delete", "reply", "liveliness_token"], "key_exprs": _ROBOT_KEYS},
            {"id": "read-only-ask", "permission": "allow", "flows": ["ingress"], "messages": ["declare_subscriber"],
             "key_exprs": ["**", "**/@health/**", "**/@status/**", "**/@launcher/**"]},
            {"id": "read-only-health", "permission": "allow", "flows": ["ingress"],
             "messages": ["declare_liveliness_subscriber", "liveliness_query"], "key_exprs": ["**/@health/**"]},
        ],
        "subjects": [{"id": "robot", "usernames": ["robot", "operator"]}, {"id": "monitor", "usernames": ["monitor"]}],
        "policies": [{"rules": ["full"], "subjects": ["robot"]},
                     {"rules": ["read-only-receive", "read-only-ask", "read-only-health"], "subjects": ["monitor"]}],
    },
}
# The last commit with graph.robot.yaml as a hand-synced copy of graph.yaml.
COPY_COMMIT = "e1e901e"


def test_robot_graph_is_graph_yaml_with_a_router_bus():
    dev, robot = load_graph(REPO / "graph.yaml"), load_graph(REPO / "graph.robot.yaml")
    assert "extends: graph.yaml" in robot_text() and "\nnodes:" not in robot_text()
    expected = meaning(dev)
    expected["name"] = "followbus-robot"
    expected["zenoh"] = dataclasses.asdict(dataclasses.replace(dev.zenoh, mode="router", config=ROBOT_CONFIG))
    assert meaning(robot) == expected
    assert robot.nodes["motor"].line.path == str(REPO / "graph.yaml")


def robot_text() -> str:
    return (REPO / "graph.robot.yaml").read_text()


def test_robot_graph_resolves_to_the_copy_it_replaced(tmp_path):
    """Over the graph.yaml of the last commit that had the copy, graph.robot.yaml is that copy, field by field."""
    files = {}
    for name in ("graph.yaml", "graph.robot.yaml"):
        shown = subprocess.run(["git", "-C", str(REPO), "show", f"{COPY_COMMIT}:{name}"], capture_output=True,
                               text=True)
        if shown.returncode != 0:
            pytest.skip(f"no git history here ({shown.stderr.strip()})")
        files[name] = shown.stdout
    old = write(tmp_path, "old/graph.robot.yaml", files["graph.robot.yaml"])
    write(tmp_path, "new/graph.yaml", files["graph.yaml"])
    new = write(tmp_path, "new/graph.robot.yaml", robot_text())
    assert "extends" not in files["graph.robot.yaml"]
    new_meaning, old_meaning = meaning(load_graph(new)), meaning(load_graph(old))
    # Since the copy, the access control became an allow-list (issue 25) and a full link drops after 1 ms (issue
    # 26): the rest is the copy, field by field.
    assert new_meaning["zenoh"]["config"].pop("transport/link/tx/queue/congestion_control/drop") == {
        "wait_before_drop": 1000, "max_wait_before_drop_fragments": 1000}
    assert new_meaning["zenoh"]["config"].pop("access_control")["default_permission"] == "deny"
    assert old_meaning["zenoh"]["config"].pop("access_control")["default_permission"] == "allow"
    assert new_meaning == old_meaning


@pytest.mark.parametrize("data, valid", [
    ({"extends": "graph.yaml", "nodes": {"reid": {"params": {"tau_occ": 0.5}}, "template": None}}, True),
    ({"extends": "graph.yaml", "nodes": {"reid": {"inputs": {"template": None, "prior": {"queue": 4}}}}}, True),
    ({"extends": "graph.yaml", "nodes": {"reid": {"run": "followbus.nodes.reid", "params": {"tau_occc": 1}}}},
     False),
    ({"extends": "graph.yaml", "nodes": {"reid": {"priority": 1}}}, False),
    ({"name": "g", "nodes": {"reid": {"params": {"tau_occ": 0.5}}}}, False),  # no base: nodes must be whole
    ({"name": "g", "nodes": {"reid": None}}, False),
])
def test_schema_allows_partial_nodes_only_in_an_extending_file(data, valid):
    jsonschema = pytest.importorskip("jsonschema")
    import json

    schema = json.loads((REPO / "docs" / "graph.schema.json").read_text())
    errors = list(jsonschema.Draft7Validator(schema).iter_errors(data))
    assert (not errors) == valid, [e.message for e in errors]
