"""A JSON Schema for graph.yaml, generated from the validator's own definitions (``followbus schema``).

Editors that speak yaml-language-server (VS Code's YAML extension, Neovim's yamlls, Helix, JetBrains) validate
and complete graph.yaml with it as you type, through the ``# yaml-language-server: $schema=...`` first line.
Draft-07, because that is the newest draft yaml-language-server supports.

Nothing here restates what bus.graph decides: the allowed keys come from its key sets (a key with no
description here, or a description for a key the validator does not accept, is an error at generation time),
the defaults from its dataclasses (InputSpec, NodeSpec, RestartPolicy, ZenohSettings), the choices from its
tuples (POLICIES, SYNC_MODES, RESTART_POLICIES, MODES). The ``params`` of each node module come from the
dataclasses its node class names (``Node.Params``), with the field comments as descriptions; a ``run`` module the
schema does not know gets a free-form ``params`` mapping. A file with ``extends`` is checked as an override: no
required keys, and nodes (``node_override``) and inputs (``input_override``) may be partial or
null, since the schema cannot see the base. The validator stays the authority (it also checks the merged graph,
wiring, message types and per-node rules a schema cannot express).
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import inspect
import io
import json
import pkgutil
import re
import textwrap
import tokenize
import types
import typing
from collections.abc import Iterable
from typing import Any

from .graph.spec import (
    DEFAULT_MAX_LAG_MS,
    INPUT_KEYS,
    NAME_RE,
    NAMESPACE_RE,
    NODE_KEYS,
    POLICIES,
    RESTART_KEYS,
    RESTART_POLICIES,
    SYNC_MODES,
    TOP_KEYS,
    InputSpec,
    NodeSpec,
    RestartPolicy,
)
from .session import MODES, ZenohSettings

DRAFT = "http://json-schema.org/draft-07/schema#"
DEFAULT_NAMESPACE = "fb"  # bus.graph.load_graph's default
SOURCE_PATTERN = "^[^/]+/[^/]+$"  # an input's 'node/output'


class SchemaDrift(RuntimeError):
    """The schema's descriptions and the validator's key sets disagree (a programming error)."""


def _default(cls: type, name: str) -> Any:
    for f in dataclasses.fields(cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return _jsonable(f.default)
            if f.default_factory is not dataclasses.MISSING:
                return _jsonable(f.default_factory())
            break
    raise SchemaDrift(f"{cls.__name__} has no default for {name!r}")


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def _type_schema(hint: Any) -> dict[str, Any]:
    """The JSON type of a dataclass field, as bus.node_params.params_from_dict accepts it."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        options = [_type_schema(a) for a in args if a is not type(None)]
        if type(None) in args:
            options.append({"type": "null"})
        if all(set(o) == {"type"} for o in options):
            return {"type": [o["type"] for o in options]}
        return {"anyOf": options}
    if origin is typing.Literal:
        return {"enum": list(args)}
    if hint is bool:
        return {"type": "boolean"}
    if hint is int:
        return {"type": "integer"}
    if hint is float:
        return {"type": "number"}
    if hint is str:
        return {"type": "string"}
    if (origin or hint) in (list, tuple):
        item = [a for a in args if a is not Ellipsis]
        return {"type": "array", **({"items": _type_schema(item[0])} if len(set(item)) == 1 else {})}
    if (origin or hint) is dict:
        return {"type": "object"}
    return {}  # Any, or a type params_from_dict passes through


def field_comments(cls: type) -> dict[str, str]:
    """The comments next to a dataclass's fields: the block right above a field and its trailing comment.

    Section rulers (``# --- Table 1 ---``) are left out."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[str, str] = {}
    block: list[str] = []
    last_comment_row = -1
    pending: tuple[str, int] | None = None  # a field whose trailing comment may follow on its line
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        row = tok.start[0]
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            if pending and pending[1] == row:
                comments[pending[0]] = " ".join(filter(None, [comments.get(pending[0], ""), text]))
                continue
            if re.match(r"^-{3}", text):
                block, last_comment_row = [], -1
                continue
            if last_comment_row != row - 1:
                block = []
            block.append(text)
            last_comment_row = row
        elif tok.type == tokenize.NAME and tok.start[1] == 4 and tok.line[4:].split(":", 1)[0].strip() == tok.string:
            # a field declaration at class-body indentation: "    name: type = default"
            above = " ".join(block) if last_comment_row == row - 1 else ""
            if above:
                comments[tok.string] = above
            pending = (tok.string, row)
            block, last_comment_row = [], -1
    return comments


def inherited_field_comments(cls: type) -> dict[str, str]:
    """:func:`field_comments` of a dataclass and of the dataclasses it inherits fields from (its own win)."""
    notes: dict[str, str] = {}
    for base in reversed(cls.__mro__):
        if dataclasses.is_dataclass(base):
            notes.update(field_comments(base))
    return notes


def params_schema(classes: Iterable[type]) -> dict[str, Any]:
    """The ``params`` mapping of a node whose parameters are these dataclasses' fields (the first one wins
    a name, as bus.node_params.split_params does)."""
    properties: dict[str, Any] = {}
    for cls in classes:
        hints = typing.get_type_hints(cls)
        notes = inherited_field_comments(cls)
        for f in dataclasses.fields(cls):
            if f.name in properties or not f.init:
                continue
            prop = _type_schema(hints[f.name])
            if notes.get(f.name):
                prop["description"] = notes[f.name]
            prop["default"] = _default(cls, f.name)
            properties[f.name] = prop
    return {"type": ["object", "null"], "additionalProperties": False, "properties": properties}


def _keyed(keys: set[str], described: dict[str, dict[str, Any]], where: str) -> dict[str, Any]:
    """The properties of a mapping whose allowed keys are the validator's ``keys``, in ``described``'s order."""
    missing, extra = keys - set(described), set(described) - keys
    if missing or extra:
        raise SchemaDrift(f"{where}: the validator accepts {sorted(keys)}; the schema describes {sorted(described)}"
                          f" (missing: {sorted(missing)}, not accepted: {sorted(extra)})")
    return dict(described)


def _zenoh_schema() -> dict[str, Any]:
    hints = typing.get_type_hints(ZenohSettings)
    notes = {
        "mode": "peer: a mesh of peers (the default); client: join through a router; router: be the hub",
        "listen": "endpoints to listen on, e.g. tcp/127.0.0.1:7447",
        "connect": "endpoints to connect to",
        "multicast_scouting": "find peers by UDP multicast (off: only the endpoints above)",
        "shm": "shared memory for large payloads between processes on this machine",
        "shm_lane": "opt-in (default false): large arrays (64 KiB and more) between followbus processes on this "
                    "machine through sealed shared memory (memfd), received without a copy; a plain subscriber "
                    "of the key still gets the real message; keep it off where the bus's ACL must protect "
                    "frames (graph.robot.yaml)",
        "connect_timeout_ms": "a client keeps retrying its endpoints this long before failing",
        "config": "raw zenoh json5 settings applied last, e.g. transport/auth/usrpwd, access_control, "
                  "transport/link/tls",
    }
    fields = {f.name for f in dataclasses.fields(ZenohSettings)}
    properties = {}
    for name, note in _keyed(fields, {k: {"description": v} for k, v in notes.items()}, "zenoh").items():
        prop = {**_type_schema(hints[name]), **note, "default": _default(ZenohSettings, name)}
        if name == "mode":
            prop["enum"] = list(MODES)
        if name in ("listen", "connect"):
            prop["items"] = {"type": "string"}
        properties[name] = prop
    return {"type": "object", "additionalProperties": False, "properties": properties,
            "description": "the Zenoh session every node opens (all optional; default: peers on loopback)"}


def _input_schema() -> dict[str, Any]:
    described = {
        "from": {"type": "string", "pattern": SOURCE_PATTERN, "description": "the producer, 'node/output'"},
        "queue": {"type": "integer", "minimum": 1, "default": _default(InputSpec, "queue"),
                  "description": "bounded queue length"},
        "policy": {"enum": list(POLICIES), "default": _default(InputSpec, "policy"),
                   "description": "a full queue: drop_oldest keeps the newest (live video); block makes the "
                                  "producer wait (control paths)"},
        "sync": {"enum": list(SYNC_MODES), "default": _default(InputSpec, "sync"),
                 "description": "frame: joined with the node's other frame inputs by frame number; latest: the "
                                "last value is kept; none: plain callback"},
        "offset": {"enum": [0, -1], "default": _default(InputSpec, "offset"),
                   "description": "-1: a feedback input, joined from the previous frame this node handled"},
        "optional": {"type": "boolean", "default": _default(InputSpec, "optional"),
                     "description": "after sync_timeout_ms the frame set goes on without it"},
    }
    return {"anyOf": [
        {"type": "string", "pattern": SOURCE_PATTERN, "description": "the producer, 'node/output'"},
        {"type": "object", "required": ["from"], "additionalProperties": False,
         "properties": _keyed(INPUT_KEYS, described, "input")},
    ]}


def _restart_schema() -> dict[str, Any]:
    described: dict[str, dict[str, Any]] = {
        "policy": {"enum": list(RESTART_POLICIES), "default": _default(RestartPolicy, "policy")},
        "max_restarts": {"type": "integer", "minimum": 0, "default": _default(RestartPolicy, "max_restarts"),
                         "description": "failures within window_s after which the node has failed for good"},
        "backoff_ms": {"type": "integer", "minimum": 0, "default": _default(RestartPolicy, "backoff_ms"),
                       "description": "wait before the first restart; doubles with each failure in the window"},
        "max_backoff_ms": {"type": "integer", "minimum": 0, "default": _default(RestartPolicy, "max_backoff_ms")},
        "window_s": {"type": "integer", "minimum": 0, "default": _default(RestartPolicy, "window_s"),
                     "description": "only the failures within this many seconds count against max_restarts"},
    }
    return {"description": "what the launcher does when the node's process exits",
            "default": _default(NodeSpec, "restart"),
            "anyOf": [{"enum": list(RESTART_POLICIES)},
                      {"type": "object", "additionalProperties": False,
                       "properties": _keyed(RESTART_KEYS, described, "restart")}]}


def _node_schema(runs: dict[str, tuple[type, ...]]) -> dict[str, Any]:
    described = {
        "run": {"type": "string", "description": "python module exporting NODE (a bus.node.Node class)",
                "examples": sorted(runs)},
        "description": {"type": "string", "description": "free text for readers (not used)"},
        "inputs": {"type": "object", "propertyNames": {"pattern": NAME_RE.pattern},
                   "additionalProperties": {"$ref": "#/definitions/input"},
                   "description": "input name -> 'node/output' or {from: node/output, queue, policy, ...}"},
        "outputs": {"type": "array", "uniqueItems": True, "items": {"type": "string", "pattern": NAME_RE.pattern},
                    "default": _default(NodeSpec, "outputs"),
                    "description": "published on <namespace>/<node>/<output>"},
        "params": {"type": ["object", "null"], "description": "the node's parameters (see its module)"},
        "restart": {"$ref": "#/definitions/restart"},
        "host": {"type": "string", "description": "the machine whose `followbus launch --host NAME` starts it "
                                                  "(default: the graph's default_host)"},
        "sync_timeout_ms": {"type": "number", "exclusiveMinimum": 0, "default": _default(NodeSpec, "sync_timeout_ms"),
                            "description": "how long a frame set waits for its optional inputs"},
        "max_lag_ms": {"type": "number", "minimum": 0,
                       "description": "skip a frame set this far behind the newest complete one (0: never); "
                                      "default: the graph's max_lag_ms"},
        "nice": {"type": "integer", "minimum": -20, "maximum": 19,
                 "description": "CPU priority of the node's process (-20 highest); below 0 needs the right to "
                                "raise priority (root or CAP_SYS_NICE), else it runs at the inherited priority"},
        "realtime": {"type": "integer", "minimum": 1, "maximum": 99,
                     "description": "run the node's process in the real-time class (SCHED_RR at this priority) "
                                    "where permitted (root or CAP_SYS_NICE), else at `nice` with a warning: "
                                    "for light, timing-critical nodes (a watchdog) only"},
    }
    return {
        "type": "object", "required": ["run"], "additionalProperties": False,
        "properties": _keyed(NODE_KEYS, described, "node"),
        # Each known module's params replace the free-form mapping above.
        "allOf": [{"if": {"properties": {"run": {"const": run}}, "required": ["run"]},
                   "then": {"properties": {"params": {"$ref": f"#/definitions/params/{run}"}}}}
                  for run in sorted(runs)],
    }


def _nullable(prop: dict[str, Any]) -> dict[str, Any]:
    allowed = prop.get("type")
    if allowed == "null" or (isinstance(allowed, list) and "null" in allowed):
        return prop
    return {"anyOf": [prop, {"type": "null", "description": "back to the base file's default: removes the key"}]}


def _node_override_schema(node: dict[str, Any]) -> dict[str, Any]:
    """A node in a file that extends another: any subset of a node's keys (merged into the base's node, or a
    new node, which the validator then checks is whole), each also null (removed)."""
    properties = copy.deepcopy(node["properties"])
    properties["inputs"]["additionalProperties"] = {"anyOf": [
        {"$ref": "#/definitions/input_override"},
        {"type": "null", "description": "removes the base's input"}]}
    return {"type": "object", "additionalProperties": False,
            "properties": {name: _nullable(prop) for name, prop in properties.items()},
            "allOf": copy.deepcopy(node["allOf"])}


def _input_override_schema(full: dict[str, Any]) -> dict[str, Any]:
    """An input in a file that extends another: a mapping merges into the base's input, so 'from' may go."""
    short, mapping = copy.deepcopy(full["anyOf"])
    del mapping["required"]
    mapping["properties"] = {name: _nullable(prop) for name, prop in mapping["properties"].items()}
    return {"anyOf": [short, mapping]}


def graph_schema(runs: dict[str, tuple[type, ...]]) -> dict[str, Any]:
    """The schema of graph.yaml; ``runs`` maps a ``run`` module to its node's params dataclasses."""
    described = {
        "extends": {"type": "string", "minLength": 1,
                    "description": "a graph file (relative to this one) that this file applies on top of: "
                                   "mappings merge key by key, scalars and lists replace, null removes a key "
                                   "(a node, an input); name and nodes then come from the base"},
        "name": {"type": "string", "description": "the graph's name"},
        "namespace": {"type": "string", "pattern": NAMESPACE_RE.pattern, "default": DEFAULT_NAMESPACE,
                      "description": "prefix of every bus key: <namespace>/<node>/<output>"},
        "zenoh": {"$ref": "#/definitions/zenoh"},
        "max_lag_ms": {"type": "number", "minimum": 0, "default": DEFAULT_MAX_LAG_MS,
                       "description": "a frame set whose capture is this far behind the newest complete set is "
                                      "skipped (0: unbounded); per node too"},
        "nodes": {"type": "object", "propertyNames": {"pattern": NAME_RE.pattern},
                  "description": "node name -> node (one OS process each)"},
        "default_host": {"type": "string", "minLength": 1,
                         "description": "the machine that runs every node without host: (required when some "
                                        "nodes name a host and others do not)"},
    }
    node = _node_schema(runs)
    inp = _input_schema()
    return {
        "$schema": DRAFT,
        "title": "followbus graph.yaml",
        "description": "The dataflow of a followbus graph. Generated by `followbus schema` from bus/graph/; "
                       "`followbus check` is the authority.",
        "type": "object",
        "additionalProperties": False,
        "properties": _keyed(TOP_KEYS, described, "graph"),
        # A whole graph needs a name and whole nodes; a file that extends another says only what differs.
        "if": {"required": ["extends"]},
        "then": {"properties": {"nodes": {"additionalProperties": {"anyOf": [
            {"$ref": "#/definitions/node_override"},
            {"type": "null", "description": "removes the base's node"}]}}}},
        "else": {"required": ["name", "nodes"],
                 "properties": {"nodes": {"minProperties": 1, "additionalProperties": {"$ref": "#/definitions/node"}}}},
        "definitions": {
            "zenoh": _zenoh_schema(),
            "node": node,
            "node_override": _node_override_schema(node),
            "input": inp,
            "input_override": _input_override_schema(inp),
            "restart": _restart_schema(),
            "params": {run: params_schema(classes) for run, classes in sorted(runs.items())},
        },
    }


def node_runs(package: str) -> dict[str, tuple[type, ...]]:
    """Every module of ``package`` that exports a NODE class, with that class's params dataclasses."""
    from .node import Node
    from .node_params import params_classes

    pkg = importlib.import_module(package)
    runs: dict[str, tuple[type, ...]] = {}
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        name = f"{package}.{info.name}"
        module = importlib.import_module(name)
        cls = getattr(module, "NODE", None)
        if isinstance(cls, type) and issubclass(cls, Node):
            runs[name] = params_classes(cls.Params)
    return runs


def schema_text(package: str) -> str:
    """docs/graph.schema.json as ``followbus schema`` writes it, for the node modules of ``package``
    (stable output: a test compares it with the committed file)."""
    return json.dumps(graph_schema(node_runs(package)), indent=2, ensure_ascii=False) + "\n"
