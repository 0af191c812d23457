"""docs/graph.schema.json: generated from the validator's definitions, fresh, and agreeing with the validator on
the shipped graphs and on graphs it rejects."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from followbus.bus import graph_schema
from followbus.bus.graph import GraphError, InputSpec, RestartPolicy, load_graph
from followbus.bus.graph.spec import (
    INPUT_KEYS,
    NODE_KEYS,
    POLICIES,
    RESTART_KEYS,
    RESTART_POLICIES,
    SYNC_MODES,
    TOP_KEYS,
)
from followbus.bus.node_checks import load_node_class, validate_node
from followbus.bus.node_params import params_classes, parse_params
from followbus.bus.session import MODES, ZenohSettings
from followbus.tools.cli import main

from .conftest import REPO

jsonschema = pytest.importorskip("jsonschema", reason="jsonschema not installed (pip install -e '.[dev]')")

SCHEMA_FILE = REPO / "docs" / "graph.schema.json"
SHIPPED = [REPO / "graph.yaml", REPO / "graph.robot.yaml", REPO / "graph.group.yaml"]
MODELINE = "# yaml-language-server: $schema=docs/graph.schema.json"
NODES_PACKAGE = "followbus.nodes"


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    return json.loads(graph_schema.schema_text(NODES_PACKAGE))


@pytest.fixture(scope="module")
def validator(schema):
    jsonschema.Draft7Validator.check_schema(schema)
    return jsonschema.Draft7Validator(schema)


def _object_branch(definition: dict[str, Any]) -> dict[str, Any]:
    return next(b for b in definition["anyOf"] if b.get("type") == "object")


def test_schema_keys_are_the_validators(schema):
    defs = schema["definitions"]
    assert set(schema["properties"]) == TOP_KEYS
    assert set(defs["node"]["properties"]) == NODE_KEYS
    assert set(_object_branch(defs["input"])["properties"]) == INPUT_KEYS
    assert set(_object_branch(defs["restart"])["properties"]) == RESTART_KEYS
    assert set(defs["zenoh"]["properties"]) == {f.name for f in dataclasses.fields(ZenohSettings)}
    # Choices and defaults are the validator's.
    inp = _object_branch(defs["input"])["properties"]
    assert inp["policy"]["enum"] == list(POLICIES) and inp["sync"]["enum"] == list(SYNC_MODES)
    assert {k: inp[k]["default"] for k in ("queue", "policy", "sync", "offset", "optional")} == {
        k: getattr(InputSpec("i", "a", "b"), k) for k in ("queue", "policy", "sync", "offset", "optional")}
    assert _object_branch(defs["restart"])["properties"]["policy"]["enum"] == list(RESTART_POLICIES)
    assert defs["restart"]["default"] == dataclasses.asdict(RestartPolicy())
    assert defs["zenoh"]["properties"]["mode"]["enum"] == list(MODES)
    defaults = ZenohSettings()
    for name, prop in defs["zenoh"]["properties"].items():
        assert prop["default"] == getattr(defaults, name), name
        ZenohSettings.from_dict({name: prop["default"]})  # every key the schema offers is accepted
    with pytest.raises(ValueError):
        ZenohSettings.from_dict({"not_a_key": 1})
    minimal = load_graph("g.yaml", "name: g\nnodes: {a: {run: followbus.nodes.diagnostics}}\n")
    assert schema["properties"]["namespace"]["default"] == minimal.namespace
    assert schema["properties"]["max_lag_ms"]["default"] == minimal.max_lag_ms
    assert defs["node"]["properties"]["sync_timeout_ms"]["default"] == minimal.nodes["a"].sync_timeout_ms


def test_a_validator_key_the_schema_does_not_describe_fails_generation(monkeypatch):
    monkeypatch.setattr(graph_schema, "NODE_KEYS", NODE_KEYS | {"priority"})
    with pytest.raises(graph_schema.SchemaDrift, match="priority"):
        graph_schema.graph_schema({})
    monkeypatch.setattr(graph_schema, "NODE_KEYS", NODE_KEYS - {"host"})
    with pytest.raises(graph_schema.SchemaDrift, match="host"):
        graph_schema.graph_schema({})


def test_params_of_every_shipped_node_module(schema):
    runs = {spec.run for path in SHIPPED for spec in load_graph(path).nodes.values()}
    params = schema["definitions"]["params"]
    assert runs <= set(params), runs - set(params)
    for run, definition in params.items():
        cls = load_node_class(run)
        names = [f.name for c in params_classes(cls.Params) for f in dataclasses.fields(c)]
        assert set(definition["properties"]) == set(names), run
        # Every parameter the schema offers, at its default, is one the node accepts; anything else is not.
        parse_params(cls.Params, {k: p["default"] for k, p in definition["properties"].items()})
        with pytest.raises(ValueError, match="not_a_param"):
            parse_params(cls.Params, {"not_a_param": 1})
    gate = params["followbus.nodes.prediction"]["properties"]["gate_chi2"]
    assert gate["type"] == "number" and "Mahalanobis" in gate["description"]  # tracking/params.py's comment
    assert "gate_chi2" not in params["followbus.nodes.reid"]["properties"]  # re-ID gates with the prior's
    # A field inherited from a shared base keeps its comment.
    assert "Δt" in params["followbus.nodes.reid"]["properties"]["dt_ms"]["description"]


def test_committed_schema_is_fresh():
    assert SCHEMA_FILE.read_text() == graph_schema.schema_text(NODES_PACKAGE), (
        "docs/graph.schema.json is stale: run `followbus schema -o docs/graph.schema.json` and commit it")


def test_cli_prints_and_writes_the_schema(tmp_path, capsys):
    assert main(["schema"]) == 0
    assert capsys.readouterr().out == SCHEMA_FILE.read_text()
    out = tmp_path / "graph.schema.json"
    assert main(["schema", "-o", str(out)]) == 0
    assert out.read_text() == SCHEMA_FILE.read_text()
    capsys.readouterr()
    assert main(["schema", "-o", str(tmp_path / "missing" / "x.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("followbus: cannot write") and err.count("\n") == 1, err


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_graphs_point_at_the_schema_and_pass_it(path: Path, validator):
    text = path.read_text()
    assert text.splitlines()[0] == MODELINE
    assert (path.parent / MODELINE.split("$schema=")[1]).resolve() == SCHEMA_FILE.resolve()
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(yaml.safe_load(text))]
    assert not errors, errors


def _base() -> dict[str, Any]:
    return yaml.safe_load((REPO / "graph.yaml").read_text())


def _validator_rejects(data: dict[str, Any]) -> str | None:
    """The validator's message for a graph (load_graph, then every node's params), or None if it accepts it."""
    try:
        graph = load_graph("g.yaml", yaml.safe_dump(data, sort_keys=False))
        for spec in graph.nodes.values():
            validate_node(graph, spec)
    except GraphError as exc:
        return exc.message
    return None


def _set(path: str, value: Any):
    def mutate(data: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        target = data
        for key in parents:
            target = target[key]
        if value is KeyError:
            del target[last]
        else:
            target[last] = value
    return mutate


WRONG = {
    "unknown top key": _set("nodez", {}),
    "unknown node key": _set("nodes.motor.priority", 1),
    "unknown input key": _set("nodes.detection.inputs.frame.qeue", 1),
    "bad policy": _set("nodes.detection.inputs.frame.policy", "drop_newest"),
    "negative queue": _set("nodes.detection.inputs.frame.queue", -1),
    "zero queue": _set("nodes.detection.inputs.frame.queue", 0),
    "bad sync": _set("nodes.prediction.inputs.odometry.sync", "nearest"),
    "future offset": _set("nodes.reid.inputs.template.offset", 1),
    "optional not a boolean": _set("nodes.reid.inputs.template.optional", "yes"),
    "source without output": _set("nodes.template.inputs.frame", "capture"),
    "bad restart policy": _set("nodes.capture.restart", "sometimes"),
    "negative backoff": _set("nodes.motor.restart.backoff_ms", -5),
    "unknown restart key": _set("nodes.motor.restart.retries", 3),
    "missing run": _set("nodes.motor.run", KeyError),
    "missing nodes": _set("nodes", KeyError),
    "no nodes": _set("nodes", {}),
    "bad node name": _set("nodes.2fast", {"run": "followbus.nodes.diagnostics"}),
    "bad output name": _set("nodes.capture.outputs", ["frame", "pre view", "ground_truth"]),
    "zero sync timeout": _set("nodes.prediction.sync_timeout_ms", 0),
    "negative max_lag_ms": _set("max_lag_ms", -1),
    "bad namespace": _set("namespace", "fb/"),
    "bad zenoh mode": _set("zenoh.mode", "mesh"),
    "unknown zenoh key": _set("zenoh.listen_on", []),
    "unknown param": _set("nodes.detection.params.treshold", 0.5),
    "param of the wrong type": _set("nodes.detection.params.input_size_px", "big"),
    "boolean param as a string": _set("nodes.prediction.params.use_odometry", "no"),
}

RIGHT = {
    "input as a string": _set("nodes.template.inputs.frame", "capture/frame"),
    "restart as a mapping": _set("nodes.capture.restart", {"policy": "always", "max_backoff_ms": 2000}),
    "empty params": _set("nodes.motor.params", None),
    "description and host": _set("nodes.motor.description", "drives the base"),
    "max_lag_ms off": _set("nodes.reid.max_lag_ms", 0),
    "tracker param on reid": _set("nodes.reid.params.lost_after_ms", 1500.0),
    "unknown module, any params": _set("nodes.extra", {"run": "mypkg.mynode", "params": {"anything": [1, 2]}}),
}


@pytest.mark.parametrize("case", WRONG, ids=str)
def test_schema_rejects_what_the_validator_rejects(case: str, validator):
    data = copy.deepcopy(_base())
    WRONG[case](data)
    assert _validator_rejects(data) is not None, f"{case}: the validator accepts it"
    assert list(validator.iter_errors(data)), f"{case}: the schema accepts it"


@pytest.mark.parametrize("case", RIGHT, ids=str)
def test_schema_accepts_what_the_validator_accepts(case: str, validator):
    data = copy.deepcopy(_base())
    RIGHT[case](data)
    if case.startswith("unknown module"):
        # The validator checks a module's params by importing it; the schema lets an unknown one through.
        assert load_graph("g.yaml", yaml.safe_dump(data, sort_keys=False)).nodes["extra"].run == "mypkg.mynode"
    else:
        assert _validator_rejects(data) is None, case
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(data)]
    assert not errors, (case, errors)
