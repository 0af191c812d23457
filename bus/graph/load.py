"""load_graph: graph.yaml (and the files it extends) read into a :class:`Graph`, every value checked where it
stands, so a problem is one ``file:line: message``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from ..session import ZenohSettings
from . import spec as rules
from .checks import check_hosts, check_wiring
from .extends import compose_graph, line_of, mapping_items, plain, read_text
from .model import Graph
from .spec import GraphError, InputSpec, NodeSpec, RestartPolicy


def load_graph(path: str | Path, text: str | None = None) -> Graph:
    """Load and validate graph.yaml (and the files it extends). Raises GraphError (file:line: message)."""
    path = str(path)
    text = read_text(path, text)
    root, files = compose_graph(path, text, ())
    if len(files) > 1:
        # The one text a recording keeps must stand alone (its base files are not in the recording).
        header = f"# {path} with extends resolved ({' -> '.join(files)}); comments dropped\n"
        text = header + yaml.serialize(root, Dumper=yaml.SafeDumper, width=120)
    seen: dict[str, yaml.Node] = {}
    for key, key_node, value_node in mapping_items(root, path, "graph"):
        if key in seen:
            raise GraphError(path, line_of(key_node), f"duplicate key {key!r}")
        if key not in rules.TOP_KEYS:
            raise GraphError(path, line_of(key_node),
                             f"unknown key {key!r} (allowed: {', '.join(sorted(rules.TOP_KEYS))})")
        seen[key] = value_node
    for required in ("name", "nodes"):
        if required not in seen:
            raise GraphError(path, 1, f"missing required key {required!r}")

    name = _expect(plain(seen["name"], path), str, path, line_of(seen["name"]), "name")
    namespace = "fb"
    if "namespace" in seen:
        namespace = _expect(plain(seen["namespace"], path), str, path, line_of(seen["namespace"]), "namespace")
        if not rules.NAMESPACE_RE.match(namespace):
            raise GraphError(path, line_of(seen["namespace"]), f"namespace {namespace!r} is not a valid key prefix")
    zenoh_settings = ZenohSettings()
    if "zenoh" in seen:
        zdata = plain(seen["zenoh"], path)
        try:
            zenoh_settings = ZenohSettings.from_dict(_expect(zdata, dict, path, line_of(seen["zenoh"]), "zenoh"))
        except (TypeError, ValueError) as exc:
            raise GraphError(path, line_of(seen["zenoh"]), f"zenoh: {exc}") from exc

    nodes: dict[str, NodeSpec] = {}
    for node_name, key_node, value_node in mapping_items(seen["nodes"], path, "nodes"):
        if node_name in nodes:
            raise GraphError(path, line_of(key_node), f"duplicate node name {node_name!r}")
        if not rules.NAME_RE.match(node_name) or node_name.startswith("@"):
            raise GraphError(path, line_of(key_node), f"node name {node_name!r} is not a valid name")
        nodes[node_name] = _parse_node(node_name, key_node, value_node, path)
    if not nodes:
        raise GraphError(path, line_of(seen["nodes"]), "no nodes declared")

    max_lag_ms = rules.DEFAULT_MAX_LAG_MS
    if "max_lag_ms" in seen:
        max_lag_ms = _non_negative_ms(seen["max_lag_ms"], path, "max_lag_ms")
    default_host = None
    if "default_host" in seen:
        default_host = _expect(plain(seen["default_host"], path), str, path, line_of(seen["default_host"]),
                               "default_host")
    graph = Graph(name=name, namespace=namespace, zenoh=zenoh_settings, nodes=nodes, path=path, text=text,
                  max_lag_ms=max_lag_ms, default_host=default_host)
    check_hosts(graph)
    check_wiring(graph)
    return graph



def _expect(value: Any, types: type | tuple[type, ...], path: str, line: int, what: str) -> Any:
    if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise GraphError(path, line, f"{what} must be {_type_names(types)}, not a boolean")
    if not isinstance(value, types):
        raise GraphError(path, line, f"{what} must be {_type_names(types)}, not {type(value).__name__}")
    return value


def _type_names(types: type | tuple[type, ...]) -> str:
    names = {"str": "a string", "int": "an integer", "float": "a number", "list": "a list",
             "dict": "a mapping", "bool": "true/false"}
    seq = types if isinstance(types, tuple) else (types,)
    return " or ".join(names.get(t.__name__, t.__name__) for t in seq)



def _parse_node(name: str, key_node: yaml.Node, node: yaml.Node, path: str) -> NodeSpec:
    fields: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    for key, k_node, v_node in mapping_items(node, path, f"node {name!r}"):
        if key not in rules.NODE_KEYS:
            raise GraphError(path, line_of(k_node),
                             f"node {name!r}: unknown key {key!r} (allowed: {', '.join(sorted(rules.NODE_KEYS))})")
        if key in fields:
            raise GraphError(path, line_of(k_node), f"node {name!r}: duplicate key {key!r}")
        fields[key] = (k_node, v_node)
    if "run" not in fields:
        raise GraphError(path, line_of(key_node), f"node {name!r}: missing required key 'run'")
    run = _expect(plain(fields["run"][1], path), str, path, line_of(fields["run"][1]), f"node {name!r}: run")
    if not rules.RUN_RE.match(run):
        raise GraphError(path, line_of(fields["run"][1]), f"node {name!r}: run must name a Python module "
                                                        f"(e.g. followbus.nodes.detection), not {run!r}")
    spec = NodeSpec(name=name, run=run, line=line_of(key_node))

    if "outputs" in fields:
        outputs = _expect(plain(fields["outputs"][1], path), list, path, line_of(fields["outputs"][1]),
                          f"node {name!r}: outputs")
        for item_node, out in zip(fields["outputs"][1].value, outputs, strict=True):
            _expect(out, str, path, line_of(item_node), f"node {name!r}: output name")
            if not rules.NAME_RE.match(out):
                raise GraphError(path, line_of(item_node), f"node {name!r}: output name {out!r} is not valid")
            if out in spec.outputs:
                raise GraphError(path, line_of(item_node), f"node {name!r}: duplicate output {out!r}")
            spec.outputs.append(out)

    if "inputs" in fields:
        for in_name, k_node, v_node in mapping_items(fields["inputs"][1], path, f"node {name!r}: inputs"):
            if in_name in spec.inputs:
                raise GraphError(path, line_of(k_node), f"node {name!r}: duplicate input {in_name!r}")
            spec.inputs[in_name] = _parse_input(name, in_name, k_node, v_node, path)

    if "params" in fields:
        params_node = fields["params"][1]
        if not (isinstance(params_node, yaml.ScalarNode) and params_node.value in ("", "~", "null")):
            for p_name, k_node, v_node in mapping_items(params_node, path, f"node {name!r}: params"):
                if p_name in spec.params:
                    raise GraphError(path, line_of(k_node), f"node {name!r}: duplicate param {p_name!r}")
                spec.params[p_name] = plain(v_node, path)
                spec.param_lines[p_name] = line_of(k_node)

    if "restart" in fields:
        spec.restart = _parse_restart(name, fields["restart"][1], path)
    if "host" in fields:
        spec.host = _expect(plain(fields["host"][1], path), str, path, line_of(fields["host"][1]),
                            f"node {name!r}: host")
    _parse_node_options(spec, fields, path)
    return spec


def _bounded_int(node: yaml.Node, path: str, what: str, low: int, high: int, meaning: str) -> int:
    value = _expect(plain(node, path), int, path, line_of(node), what)
    if not low <= value <= high:
        raise GraphError(path, line_of(node), f"{what} must be in {low}..{high}{meaning}")
    return value


def _parse_node_options(spec: NodeSpec, fields: dict[str, tuple[yaml.Node, yaml.Node]], path: str) -> None:
    """The node's scheduling options: sync_timeout_ms, max_lag_ms, nice, realtime."""
    name = spec.name
    if "sync_timeout_ms" in fields:
        node = fields["sync_timeout_ms"][1]
        value = _expect(plain(node, path), (int, float), path, line_of(node), f"node {name!r}: sync_timeout_ms")
        if not (math.isfinite(value) and value > 0):
            raise GraphError(path, line_of(node),
                             f"node {name!r}: sync_timeout_ms must be a finite number > 0, not {value!r}")
        spec.sync_timeout_ms = float(value)
    if "max_lag_ms" in fields:
        spec.max_lag_ms = _non_negative_ms(fields["max_lag_ms"][1], path, f"node {name!r}: max_lag_ms")
    if "nice" in fields:
        spec.nice = _bounded_int(fields["nice"][1], path, f"node {name!r}: nice", -20, 19, "")
    if "realtime" in fields:
        spec.realtime = _bounded_int(fields["realtime"][1], path, f"node {name!r}: realtime", 1, 99,
                                     " (a SCHED_RR priority)")


def _non_negative_ms(node: yaml.Node, path: str, what: str) -> float:
    value = _expect(plain(node, path), (int, float), path, line_of(node), what)
    if isinstance(value, bool) or not (math.isfinite(value) and value >= 0):
        raise GraphError(path, line_of(node), f"{what} must be a finite number >= 0 (0: unbounded), not {value!r}")
    return float(value)


def _parse_input(node: str, name: str, key_node: yaml.Node, value_node: yaml.Node, path: str) -> InputSpec:
    where = f"node {node!r}: input {name!r}"
    line = line_of(key_node)
    if not rules.NAME_RE.match(name):
        raise GraphError(path, line, f"{where}: not a valid input name")
    value = plain(value_node, path)
    options: dict[str, Any] = {}
    lines: dict[str, int] = {}  # each option's own line: in a graph that extends another, maybe another file
    if isinstance(value, str):
        source = value
    elif isinstance(value, dict):
        for opt_name, opt_key, opt_value in mapping_items(value_node, path, where):
            lines[opt_name] = line_of(opt_value)
            if opt_name not in rules.INPUT_KEYS:
                raise GraphError(path, line_of(opt_key),
                                 f"{where}: unknown key {opt_name!r} (allowed: {', '.join(sorted(rules.INPUT_KEYS))})")
        if "from" not in value:
            raise GraphError(path, line, f"{where}: missing required key 'from'")
        source = value["from"]
        options = {k: v for k, v in value.items() if k != "from"}
    else:
        raise GraphError(path, line, f"{where}: must be 'node/output' or a mapping with 'from'")
    if not isinstance(source, str) or source.count("/") != 1:
        raise GraphError(path, lines.get("from", line), f"{where}: source {source!r} must look like 'node/output'")
    src_node, src_output = source.split("/")
    spec = InputSpec(name=name, source_node=src_node, source_output=src_output, line=line)
    if "queue" in options:
        spec.queue = _expect(options["queue"], int, path, lines["queue"], f"{where}: queue")
        if spec.queue < 1:
            raise GraphError(path, lines["queue"], f"{where}: queue must be >= 1")
    if "policy" in options:
        spec.policy = _expect(options["policy"], str, path, lines["policy"], f"{where}: policy")
        if spec.policy not in rules.POLICIES:
            raise GraphError(path, lines["policy"], f"{where}: policy must be one of {', '.join(rules.POLICIES)}")
    if "sync" in options:
        spec.sync = _expect(options["sync"], str, path, lines["sync"], f"{where}: sync")
        if spec.sync not in rules.SYNC_MODES:
            raise GraphError(path, lines["sync"], f"{where}: sync must be one of {', '.join(rules.SYNC_MODES)}")
    if "offset" in options:
        spec.offset = _expect(options["offset"], int, path, lines["offset"], f"{where}: offset")
        if spec.offset not in (0, -1):
            raise GraphError(path, lines["offset"], f"{where}: offset must be 0 or -1 (-1: feedback from the previous "
                                                    "frame this node handled; a frame cannot wait for its future)")
    if "optional" in options:
        spec.optional = _expect(options["optional"], bool, path, lines["optional"], f"{where}: optional")
    return spec


def _parse_restart(node: str, value_node: yaml.Node, path: str) -> RestartPolicy:
    where = f"node {node!r}: restart"
    line = line_of(value_node)
    value = plain(value_node, path)
    lines: dict[str, int] = {"policy": line}  # each key's own line (a base's or an override's)
    if isinstance(value, str):
        value = {"policy": value}
    else:
        _expect(value, dict, path, line, where)
        lines.update({key: line_of(v_node) for key, _, v_node in mapping_items(value_node, path, where)})
    for key in value:
        if key not in rules.RESTART_KEYS:
            raise GraphError(path, lines[key],
                             f"{where}: unknown key {key!r} (allowed: {', '.join(sorted(rules.RESTART_KEYS))})")
    policy = RestartPolicy()
    if "policy" in value:
        policy.policy = _expect(value["policy"], str, path, lines["policy"], f"{where}: policy")
        if policy.policy not in rules.RESTART_POLICIES:
            raise GraphError(path, lines["policy"],
                             f"{where}: policy must be one of {', '.join(rules.RESTART_POLICIES)}")
    for key in ("max_restarts", "backoff_ms", "max_backoff_ms", "window_s"):
        if key in value:
            setattr(policy, key, _expect(value[key], int, path, lines[key], f"{where}: {key}"))
            if getattr(policy, key) < 0:
                raise GraphError(path, lines[key], f"{where}: {key} must be >= 0")
    return policy

