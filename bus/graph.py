"""graph.yaml: the dataflow declaration (modelled on dora's dataflow.yml), loaded and validated.

Every problem is reported as ``file:line: message`` through :class:`GraphError`, before anything
starts. The command line turns a GraphError into exit status 2.

    name: followbus-demo
    namespace: fb
    zenoh: {mode: peer, listen: [tcp/127.0.0.1:7447], connect: [tcp/127.0.0.1:7447]}
    nodes:
      detection:
        run: followbus.nodes.detection          # python module with a NODE class
        inputs:
          frame: {from: capture/frame, queue: 1, policy: drop_oldest}
        outputs: [detections]
        params: {backend: auto}
        restart: on-failure                     # or {policy: on-failure, max_restarts: 5, backoff_ms: 500}
        host: robot

A file can extend another (``extends: graph.yaml``, relative to the file): the base is loaded first and the
file applies on top of it. Mappings merge key by key (the zenoh block, a node, its inputs and params), scalars
and lists replace, ``null`` removes (a node, one of its keys, an input; a param's ``null`` is a value), new nodes
are added. Each YAML node remembers its file, so an error in the base names the base file.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import math
import re
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .session import ZenohSettings

NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
NAMESPACE_RE = re.compile(r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")
RUN_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")  # an absolute, dotted module name
TOP_KEYS = {"extends", "name", "namespace", "zenoh", "nodes", "max_lag_ms", "default_host"}
DEFAULT_MAX_LAG_MS = 150.0  # a frame set further behind the newest complete one is skipped (bus.sync)
NODE_KEYS = {"run", "inputs", "outputs", "params", "restart", "host", "sync_timeout_ms", "max_lag_ms", "nice",
             "realtime", "description"}
INPUT_KEYS = {"from", "queue", "policy", "sync", "offset", "optional"}
RESTART_KEYS = {"policy", "max_restarts", "backoff_ms", "max_backoff_ms", "window_s"}
POLICIES = ("drop_oldest", "block")
SYNC_MODES = ("frame", "latest", "none")
RESTART_POLICIES = ("never", "on-failure", "always")


class SourceLine(int):
    """A 1-based line number that remembers its file: a graph that extends another spans several files, so
    the lines kept in specs (NodeSpec.line, InputSpec.line, param_lines) must say which file they are in."""

    path: str

    def __new__(cls, line: int, path: str) -> SourceLine:
        obj = super().__new__(cls, line)
        obj.path = path
        return obj

    def __reduce__(self) -> tuple[Any, ...]:  # copy/pickle keep the file
        return (SourceLine, (int(self), self.path))


class GraphError(Exception):
    """A graph.yaml problem, located to a file and line (a SourceLine's own file wins over ``path``)."""

    def __init__(self, path: str | Path, line: int | None, message: str):
        self.path = str(getattr(line, "path", None) or path)
        self.line = line
        self.message = message
        super().__init__(f"{self.path}:{line}: {message}" if line is not None else f"{self.path}: {message}")


@dataclass
class InputSpec:
    name: str
    source_node: str
    source_output: str
    queue: int = 4
    policy: str = "drop_oldest"
    sync: str = "frame"  # frame: joined by frame_seq; latest: last value kept; none: callback only
    offset: int = 0  # -1: feedback input, joined from the previous frame this node handled (see bus.sync)
    optional: bool = False
    line: int | None = None

    @property
    def topic(self) -> str:
        return f"{self.source_node}/{self.source_output}"


@dataclass
class RestartPolicy:
    """When the launcher restarts a node. The budget is per window, as systemd's StartLimitBurst per
    StartLimitIntervalSec: more than ``max_restarts`` failures within ``window_s`` and the node has failed for
    good; a node that fails once a day is restarted every day. The backoff doubles with the failures in the
    window, from ``backoff_ms`` up to ``max_backoff_ms``."""

    policy: str = "on-failure"
    max_restarts: int = 5
    backoff_ms: int = 500
    max_backoff_ms: int = 10_000
    window_s: int = 60


@dataclass
class NodeSpec:
    name: str
    run: str
    inputs: dict[str, InputSpec] = field(default_factory=dict)
    outputs: list[str] = field(default_factory=list)
    params: dict[str, Any] = field(default_factory=dict)
    restart: RestartPolicy = field(default_factory=RestartPolicy)
    host: str | None = None
    sync_timeout_ms: float = 100.0
    max_lag_ms: float | None = None  # None: the graph's; 0: never skip a lagging frame set
    nice: int | None = None  # CPU priority of the node's process (-20 highest .. 19); None: inherited
    realtime: int | None = None  # SCHED_RR priority (1..99) where permitted, else ``nice``; None: not real-time
    line: int | None = None
    param_lines: dict[str, int] = field(default_factory=dict)


@dataclass
class Graph:
    name: str
    namespace: str
    zenoh: ZenohSettings
    nodes: dict[str, NodeSpec]
    path: str = "<memory>"
    text: str = ""  # self-contained YAML (an extending file's is the resolved document): recordings keep it
    max_lag_ms: float = DEFAULT_MAX_LAG_MS
    # The host of every node that names none (bus/hosts.py): a graph spread over machines runs each node on one.
    default_host: str | None = None

    def host_of(self, node: str) -> str | None:
        """The machine that runs ``node``: its ``host:``, else the graph's ``default_host`` (None: any machine
        that launches the graph; only in a graph that names no host)."""
        return self.nodes[node].host or self.default_host

    def lag_bound_ms(self, node: str) -> float | None:
        """The frame-set lag bound of a node (None: unbounded)."""
        own = self.nodes[node].max_lag_ms
        value = self.max_lag_ms if own is None else own
        return value or None

    def key(self, node: str, output: str) -> str:
        """The bus key of a node's output: ``<namespace>/<node>/<output>``."""
        return f"{self.namespace}/{node}/{output}"

    def health_key(self, node: str) -> str:
        return f"{self.namespace}/@health/{node}"

    def status_key(self, node: str) -> str:
        return f"{self.namespace}/@status/{node}"

    def replay_hint_key(self, node: str) -> str:
        """Where ``followbus replay`` tells a node run with ``--clock stamps`` what the live run did."""
        return f"{self.namespace}/@replay/{node}"

    def error(self, line: int | None, message: str) -> GraphError:
        return GraphError(self.path, line, message)

    # --- variants: each returns a new graph and leaves this one as it is (tools derive graphs only here) ----------
    def override(self, params: Mapping[str, Mapping[str, Any]] | Iterable[str]) -> Graph:
        """This graph with node parameters set: {node: {param: value}}, or ``node.param=value`` assignments."""
        if not isinstance(params, Mapping):
            params = parse_assignments(params, nodes=self.nodes)
        graph = self._variant()
        for node, values in params.items():
            if node not in graph.nodes:
                raise graph.error(None, f"no node named {node!r} (nodes: {', '.join(graph.nodes)})")
            graph.nodes[node].params.update(copy.deepcopy(dict(values)))
        return graph

    def with_namespace(self, namespace: str) -> Graph:
        if not NAMESPACE_RE.match(namespace):
            raise self.error(None, f"namespace {namespace!r} is not a valid key prefix")
        graph = self._variant()
        graph.namespace = namespace
        return graph

    def with_port(self, port: int, host: str = "127.0.0.1") -> Graph:
        """This graph listening and connecting on one TCP port only (a private bus on this machine)."""
        endpoint = f"tcp/{host}:{int(port)}"
        return self.with_zenoh(listen=[endpoint], connect=[endpoint])

    def with_zenoh(self, settings: ZenohSettings | None = None, **changes: Any) -> Graph:
        """This graph on other Zenoh settings: ``settings`` whole, and/or some of its fields changed."""
        graph = self._variant()
        graph.zenoh = dataclasses.replace(settings or graph.zenoh, **changes)
        return graph

    def with_node(self, name: str, **changes: Any) -> Graph:
        """This graph with node options of ``name`` changed (NodeSpec fields: sync_timeout_ms, restart, ...)."""
        graph = self._variant()
        spec = graph.nodes[name]
        for key, value in changes.items():
            if key in ("name", "params") or not hasattr(spec, key):
                raise graph.error(spec.line, f"node {name!r}: no option {key!r} to change here")
            setattr(spec, key, copy.deepcopy(value))
        return graph

    def with_input(self, node: str, name: str, source: str, **options: Any) -> Graph:
        """This graph with an input ``name`` of ``node`` fed from ``source`` (node/output); options as in the file."""
        src_node, _, src_output = source.partition("/")
        graph = self._variant()
        graph.nodes[node].inputs[name] = InputSpec(name=name, source_node=src_node, source_output=src_output,
                                                   **options)
        _check_wiring(graph)
        return graph

    def boundary(self, nodes: Iterable[str]) -> Boundary:
        """Where ``nodes`` meet the rest of this graph (see :class:`Boundary`)."""
        names = list(nodes)
        for name in names:
            if name not in self.nodes:
                raise GraphError(self.path, None, f"no node named {name!r} (nodes: {', '.join(self.nodes)})")
        order = tuple(n for n in self.nodes if n in names)  # graph order, whatever order they were named in
        inputs = tuple((n, i) for n in order for i in self.nodes[n].inputs.values() if i.source_node not in order)
        outputs = tuple(f"{n}/{out}" for n in order for out in self.nodes[n].outputs)
        return Boundary(order, inputs, outputs)

    def subgraph(self, nodes: Iterable[str], name: str | None = None) -> Graph:
        """``nodes`` alone, with a stand-in for each producer of their inputs from outside: the producer's
        ``run`` and the outputs they read, nothing else (a replay or a test publishes in its place)."""
        edge = self.boundary(nodes)
        graph = self._variant()
        graph.name = name or f"{self.name}-{'-'.join(edge.nodes)}"
        stand_ins: dict[str, NodeSpec] = {}
        for _, inp in edge.inputs:
            spec = self.nodes[inp.source_node]
            stand_in = stand_ins.setdefault(spec.name, NodeSpec(name=spec.name, run=spec.run, line=spec.line,
                                                                restart=RestartPolicy(policy="never")))
            if inp.source_output not in stand_in.outputs:
                stand_in.outputs.append(inp.source_output)
        graph.nodes = {n: spec for n, spec in graph.nodes.items() if n in edge.nodes or n in stand_ins}
        graph.nodes.update({n: stand_ins[n] for n in stand_ins})
        graph.nodes = {n: graph.nodes[n] for n in self.nodes if n in graph.nodes}  # graph order
        graph.default_host = None if not any(s.host for s in graph.nodes.values()) else graph.default_host
        return graph

    def to_yaml(self) -> str:
        """The graph as a self-contained graph file (what :func:`load_graph` reads back as this graph)."""
        return yaml.safe_dump(_document(self), sort_keys=False, width=120)

    def _variant(self) -> Graph:
        graph = copy.deepcopy(self)
        graph.text = ""  # a variant's file is what to_yaml() writes
        return graph


@dataclass(frozen=True)
class Boundary:
    """Where some nodes of a graph (run alone: in-process, replayed, isolated) meet the rest of it."""

    nodes: tuple[str, ...]  # in graph order
    inputs: tuple[tuple[str, InputSpec], ...]  # (node, input) whose producer is outside the nodes
    outputs: tuple[str, ...]  # the nodes' topics, node/output

    def input_topics(self, *, required: bool = False, frame: bool = False) -> list[str]:
        """The topics fed from outside (once each): all, only those a frame set needs (same-frame, not optional:
        ``required``), or those that belong to a frame at all (``frame``)."""
        chosen = [i for _, i in self.inputs if (not frame and not required or i.sync == "frame")
                  and (not required or (not i.offset and not i.optional))]
        return list(dict.fromkeys(i.topic for i in chosen))

    def feedback(self) -> dict[tuple[str, str], str]:
        """(node, feedback input) -> its topic, for the feedback inputs (offset -1) produced outside."""
        return {(n, i.name): i.topic for n, i in self.inputs if i.sync == "frame" and i.offset}


def _document(graph: Graph) -> dict[str, Any]:
    doc: dict[str, Any] = {"name": graph.name, "namespace": graph.namespace,
                           "zenoh": dataclasses.asdict(graph.zenoh), "max_lag_ms": graph.max_lag_ms}
    if graph.default_host is not None:
        doc["default_host"] = graph.default_host
    doc["nodes"] = {name: _node_document(spec) for name, spec in graph.nodes.items()}
    return doc


def _node_document(spec: NodeSpec) -> dict[str, Any]:
    out: dict[str, Any] = {"run": spec.run}
    if spec.inputs:
        out["inputs"] = {i.name: {"from": i.topic, "queue": i.queue, "policy": i.policy, "sync": i.sync,
                                  "offset": i.offset, "optional": i.optional} for i in spec.inputs.values()}
    if spec.outputs:
        out["outputs"] = list(spec.outputs)
    if spec.params:
        out["params"] = {k: _plain_value(v) for k, v in spec.params.items()}
    out["restart"] = dataclasses.asdict(spec.restart)
    out["sync_timeout_ms"] = spec.sync_timeout_ms
    options = {"host": spec.host, "max_lag_ms": spec.max_lag_ms, "nice": spec.nice, "realtime": spec.realtime}
    out.update({k: v for k, v in options.items() if v is not None})
    return out


def _plain_value(value: Any) -> Any:
    """A parameter as YAML writes it (a tuple as a list: what the file would have said)."""
    if isinstance(value, (list, tuple)):
        return [_plain_value(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain_value(v) for k, v in value.items()}
    return value


_SCALARS = yaml.SafeLoader("")  # only used to construct scalar values from composed nodes


def parse_assignments(items: Iterable[str], *, flag: str = "--set", nodes: Iterable[str] = (),
                      default_node: str | None = None) -> dict[str, dict[str, Any]]:
    """The one parser of ``node.param=value`` (value in YAML syntax): ``--set`` of every graph command and
    replay's ``--param``. Returns {node: {param: value}}. ``nodes``: the names allowed; ``default_node``: the node
    a bare ``param=value`` is for (replaying one node). A mistake is a GraphError said as the flag the user
    typed, without a file:line."""
    known = list(nodes)
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        target, sep, raw = item.partition("=")
        node, dot, param = target.strip().partition(".")
        if dot and default_node is not None and node not in known:
            node, param = default_node, target.strip()  # a dotted parameter name of the one node
        elif not dot and default_node is not None:
            node, param = default_node, node
        if not sep or not node or not param:
            shape = "param=value or node.param=value" if default_node is not None else "node.param=value"
            raise GraphError("<command line>", None, f"{flag} {item}: must look like {shape}")
        if known and node not in known:
            raise GraphError("<command line>", None, f"{flag} {item}: no node named {node!r} to set {param!r} on "
                                                     f"(nodes: {', '.join(known)})")
        out.setdefault(node, {})[param] = parse_value(raw, f"{flag} {item}")
    return out


def parse_value(raw: str, said: str) -> Any:
    """A parameter value as every command reads one: YAML syntax (0.8, true, [1, 2], text), empty for ""; a
    GraphError that names ``said`` (what the user typed) otherwise."""
    try:
        return yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise GraphError("<command line>", None, f"{said}: the value is not valid YAML ({problem})") from exc


def apply_overrides(graph: Graph, assignments: list[str]) -> None:
    """Apply ``node.param=value`` assignments (``--set``) on top of graph.yaml's params, in place (the graph
    commands keep the assignments to hand them on to the node processes; tools deriving a variant use
    :meth:`Graph.override`)."""
    try:
        parsed = parse_assignments(assignments, nodes=graph.nodes)
    except GraphError as exc:
        raise GraphError(graph.path, None, exc.message) from None
    for node, params in parsed.items():
        graph.nodes[node].params.update(params)


def _line(node: yaml.Node) -> SourceLine:
    return SourceLine(node.start_mark.line + 1, node.start_mark.name)


def _plain(node: yaml.Node, path: str) -> Any:
    """Convert a composed YAML node to Python values, rejecting duplicate keys."""
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            key = _plain(key_node, path)
            if key in out:
                raise GraphError(path, _line(key_node), f"duplicate key {key!r}")
            out[key] = _plain(value_node, path)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_plain(item, path) for item in node.value]
    return _SCALARS.construct_object(node, deep=True)


def _mapping_items(node: yaml.Node, path: str, what: str) -> list[tuple[str, yaml.Node, yaml.Node]]:
    if not isinstance(node, yaml.MappingNode):
        raise GraphError(path, _line(node), f"{what} must be a mapping")
    items = []
    for key_node, value_node in node.value:
        if not isinstance(key_node, yaml.ScalarNode):
            raise GraphError(path, _line(key_node), f"{what}: keys must be plain names")
        items.append((key_node.value, key_node, value_node))
    return items


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


_NULL_TAG = "tag:yaml.org,2002:null"


def _read(path: str, text: str | None, read_from: tuple[str, int | None] | None = None) -> str:
    if text is not None:
        return text
    try:
        # Only a regular file: reading a FIFO waits for a writer for ever, /dev/zero never ends.
        if not stat.S_ISREG(Path(path).stat().st_mode):
            raise GraphError(read_from[0] if read_from else path, read_from[1] if read_from else None,
                             f"{'extends: ' if read_from else ''}{path} is not a regular file")
        return Path(path).read_text()
    except OSError as exc:
        if read_from is not None:  # a base file: the error is the extends line's
            raise GraphError(read_from[0], read_from[1], f"extends: cannot read {path}: {exc.strerror}") from exc
        raise GraphError(path, None, f"cannot read: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        where = (read_from[0], read_from[1]) if read_from else (path, None)
        raise GraphError(*where, f"{'extends: ' if read_from else ''}{path} is not a text file ({exc.reason})") \
            from exc


# libyaml's parser where PyYAML was built with it: a tenth of the pure-Python one's time (evaluation builds the
# graph once per sequence and run).
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _compose(path: str, text: str) -> yaml.Node:
    stream = io.StringIO(text)
    stream.name = path  # type: ignore[misc]  # every mark, so every line, names this file
    loader = _LOADER(stream)
    try:
        root = loader.get_single_node()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        context = getattr(exc, "context", None)
        detail = f"{problem} ({context})" if context else problem
        raise GraphError(path, mark.line + 1 if mark else None, f"invalid YAML: {detail}") from exc
    finally:
        loader.dispose()
    if root is None:
        raise GraphError(path, 1, "empty graph file")
    return root


def _compose_graph(path: str, text: str, chain: tuple[tuple[str, str], ...]) -> tuple[yaml.Node, list[str]]:
    """The file's YAML tree with every file it extends merged under it, and the files (base first).

    ``chain``: the (path, resolved path) of the files that extend this one, to tell a cycle."""
    root = _compose(path, text)
    if not isinstance(root, yaml.MappingNode):
        return root, [path]  # the validator says what is wrong with it
    items = _unique_items(root, ())
    if "extends" not in items:
        return root, [path]
    key_node, value_node = items["extends"]
    line = _line(value_node)
    target = _plain(value_node, path)
    if not isinstance(target, str) or not target.strip():
        raise GraphError(path, line, "extends must be the path of a graph file (relative to this one)")
    base = str(Path(path).parent / target)
    chain = (*chain, (path, str(Path(path).resolve())))
    if str(Path(base).resolve()) in {resolved for _, resolved in chain}:
        raise GraphError(path, line, f"extends: cycle {' -> '.join([*(p for p, _ in chain), base])}")
    base_root, files = _compose_graph(base, _read(base, None, (path, line)), chain)
    if not isinstance(base_root, yaml.MappingNode):
        raise GraphError(base, _line(base_root), "graph must be a mapping")
    own = yaml.MappingNode(root.tag, [(k, v) for k, v in root.value if k is not key_node], start_mark=root.start_mark,
                           end_mark=root.end_mark, flow_style=root.flow_style)
    return _merge(base_root, own, (), base), [*files, path]


def _unique_items(node: yaml.MappingNode, where: tuple[str, ...]) -> dict[str, tuple[yaml.Node, yaml.Node]]:
    items: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    for key_node, value_node in node.value:
        if not isinstance(key_node, yaml.ScalarNode):
            raise GraphError(node.start_mark.name, _line(key_node), f"{_dotted(where)}: keys must be plain names")
        if key_node.value in items:
            raise GraphError(node.start_mark.name, _line(key_node),
                             f"duplicate key {_dotted((*where, key_node.value))!r}")
        items[key_node.value] = (key_node, value_node)
    return items


def _dotted(where: tuple[str, ...]) -> str:
    return ".".join(where) or "graph"


def _is_param_value(where: tuple[str, ...]) -> bool:
    """Whether ``where`` is (inside) one parameter's value: it replaces whole, and null there is a value (an
    Optional parameter's None), where everywhere else null removes the key."""
    return len(where) >= 4 and where[0] == "nodes" and where[2] == "params"


def _shorthand_key(where: tuple[str, ...]) -> str | None:
    """The key a scalar shorthand stands for here: an input 'capture/frame' is {from: capture/frame}, a restart
    'on-failure' is {policy: on-failure}."""
    if len(where) == 4 and where[0] == "nodes" and where[2] == "inputs":
        return "from"
    if len(where) == 3 and where[0] == "nodes" and where[2] == "restart":
        return "policy"
    return None


def _merge(base: yaml.Node, over: yaml.Node, where: tuple[str, ...], base_file: str) -> yaml.Node:
    """``over`` applied on top of ``base``: mappings merge key by key, anything else replaces."""
    shorthand = _shorthand_key(where)
    if shorthand and isinstance(over, yaml.MappingNode) and isinstance(base, yaml.ScalarNode):
        # {queue: 8} over 'capture/frame' keeps the source: the shorthand becomes the mapping it stands for.
        key = yaml.ScalarNode("tag:yaml.org,2002:str", shorthand, start_mark=base.start_mark, end_mark=base.end_mark)
        base = yaml.MappingNode("tag:yaml.org,2002:map", [(key, base)], start_mark=base.start_mark,
                                end_mark=base.end_mark, flow_style=True)
    if not (isinstance(base, yaml.MappingNode) and isinstance(over, yaml.MappingNode)) or _is_param_value(where):
        return over
    merged = _unique_items(base, where)
    for key, (key_node, value_node) in _unique_items(over, where).items():
        if value_node.tag == _NULL_TAG and not _is_param_value((*where, key)):
            if key not in merged:
                raise GraphError(over.start_mark.name, _line(key_node),
                                 f"{_dotted((*where, key))}: null removes nothing ({base_file} has no such key)")
            del merged[key]
        elif key in merged:
            base_key, base_value = merged[key]
            value = _merge(base_value, value_node, (*where, key), base_file)
            # A mapping merged into the base's is still declared where the base declared it (a node's line).
            merged[key] = (key_node if value is value_node else base_key, value)
        else:
            merged[key] = (key_node, value_node)
    return yaml.MappingNode(over.tag, list(merged.values()), start_mark=over.start_mark, end_mark=over.end_mark,
                            flow_style=base.flow_style)


def load_graph(path: str | Path, text: str | None = None) -> Graph:
    """Load and validate graph.yaml (and the files it extends). Raises GraphError (file:line: message)."""
    path = str(path)
    text = _read(path, text)
    root, files = _compose_graph(path, text, ())
    if len(files) > 1:
        # The one text a recording keeps must stand alone (its base files are not in the recording).
        header = f"# {path} with extends resolved ({' -> '.join(files)}); comments dropped\n"
        text = header + yaml.serialize(root, Dumper=yaml.SafeDumper, width=120)
    seen: dict[str, yaml.Node] = {}
    for key, key_node, value_node in _mapping_items(root, path, "graph"):
        if key in seen:
            raise GraphError(path, _line(key_node), f"duplicate key {key!r}")
        if key not in TOP_KEYS:
            raise GraphError(path, _line(key_node), f"unknown key {key!r} (allowed: {', '.join(sorted(TOP_KEYS))})")
        seen[key] = value_node
    for required in ("name", "nodes"):
        if required not in seen:
            raise GraphError(path, 1, f"missing required key {required!r}")

    name = _expect(_plain(seen["name"], path), str, path, _line(seen["name"]), "name")
    namespace = "fb"
    if "namespace" in seen:
        namespace = _expect(_plain(seen["namespace"], path), str, path, _line(seen["namespace"]), "namespace")
        if not NAMESPACE_RE.match(namespace):
            raise GraphError(path, _line(seen["namespace"]), f"namespace {namespace!r} is not a valid key prefix")
    zenoh_settings = ZenohSettings()
    if "zenoh" in seen:
        zdata = _plain(seen["zenoh"], path)
        try:
            zenoh_settings = ZenohSettings.from_dict(_expect(zdata, dict, path, _line(seen["zenoh"]), "zenoh"))
        except (TypeError, ValueError) as exc:
            raise GraphError(path, _line(seen["zenoh"]), f"zenoh: {exc}") from exc

    nodes: dict[str, NodeSpec] = {}
    for node_name, key_node, value_node in _mapping_items(seen["nodes"], path, "nodes"):
        if node_name in nodes:
            raise GraphError(path, _line(key_node), f"duplicate node name {node_name!r}")
        if not NAME_RE.match(node_name) or node_name.startswith("@"):
            raise GraphError(path, _line(key_node), f"node name {node_name!r} is not a valid name")
        nodes[node_name] = _parse_node(node_name, key_node, value_node, path)
    if not nodes:
        raise GraphError(path, _line(seen["nodes"]), "no nodes declared")

    max_lag_ms = DEFAULT_MAX_LAG_MS
    if "max_lag_ms" in seen:
        max_lag_ms = _non_negative_ms(seen["max_lag_ms"], path, "max_lag_ms")
    default_host = None
    if "default_host" in seen:
        default_host = _expect(_plain(seen["default_host"], path), str, path, _line(seen["default_host"]),
                               "default_host")
    graph = Graph(name=name, namespace=namespace, zenoh=zenoh_settings, nodes=nodes, path=path, text=text,
                  max_lag_ms=max_lag_ms, default_host=default_host)
    _check_hosts(graph)
    _check_wiring(graph)
    return graph


def _check_hosts(graph: Graph) -> None:
    """A node that names no host runs on ``default_host``: a graph that names hosts for some nodes needs one,
    or `launch --host` on each machine would not know where those nodes go (and used to start them twice)."""
    if graph.default_host is not None:
        return
    named = [spec for spec in graph.nodes.values() if spec.host]
    unnamed = [name for name, spec in graph.nodes.items() if not spec.host]
    if named and unnamed:
        first = named[0]
        raise GraphError(graph.path, first.line,
                         f"node {first.name!r} runs on host {first.host!r} but {', '.join(unnamed)} name no host: "
                         "add `default_host: NAME` (the machine that runs every node without a host:)")


def _parse_node(name: str, key_node: yaml.Node, node: yaml.Node, path: str) -> NodeSpec:
    fields: dict[str, tuple[yaml.Node, yaml.Node]] = {}
    for key, k_node, v_node in _mapping_items(node, path, f"node {name!r}"):
        if key not in NODE_KEYS:
            raise GraphError(path, _line(k_node),
                             f"node {name!r}: unknown key {key!r} (allowed: {', '.join(sorted(NODE_KEYS))})")
        if key in fields:
            raise GraphError(path, _line(k_node), f"node {name!r}: duplicate key {key!r}")
        fields[key] = (k_node, v_node)
    if "run" not in fields:
        raise GraphError(path, _line(key_node), f"node {name!r}: missing required key 'run'")
    run = _expect(_plain(fields["run"][1], path), str, path, _line(fields["run"][1]), f"node {name!r}: run")
    if not RUN_RE.match(run):
        raise GraphError(path, _line(fields["run"][1]), f"node {name!r}: run must name a Python module "
                                                        f"(e.g. followbus.nodes.detection), not {run!r}")
    spec = NodeSpec(name=name, run=run, line=_line(key_node))

    if "outputs" in fields:
        outputs = _expect(_plain(fields["outputs"][1], path), list, path, _line(fields["outputs"][1]),
                          f"node {name!r}: outputs")
        for item_node, out in zip(fields["outputs"][1].value, outputs, strict=True):
            _expect(out, str, path, _line(item_node), f"node {name!r}: output name")
            if not NAME_RE.match(out):
                raise GraphError(path, _line(item_node), f"node {name!r}: output name {out!r} is not valid")
            if out in spec.outputs:
                raise GraphError(path, _line(item_node), f"node {name!r}: duplicate output {out!r}")
            spec.outputs.append(out)

    if "inputs" in fields:
        for in_name, k_node, v_node in _mapping_items(fields["inputs"][1], path, f"node {name!r}: inputs"):
            if in_name in spec.inputs:
                raise GraphError(path, _line(k_node), f"node {name!r}: duplicate input {in_name!r}")
            spec.inputs[in_name] = _parse_input(name, in_name, k_node, v_node, path)

    if "params" in fields:
        params_node = fields["params"][1]
        if not (isinstance(params_node, yaml.ScalarNode) and params_node.value in ("", "~", "null")):
            for p_name, k_node, v_node in _mapping_items(params_node, path, f"node {name!r}: params"):
                if p_name in spec.params:
                    raise GraphError(path, _line(k_node), f"node {name!r}: duplicate param {p_name!r}")
                spec.params[p_name] = _plain(v_node, path)
                spec.param_lines[p_name] = _line(k_node)

    if "restart" in fields:
        spec.restart = _parse_restart(name, fields["restart"][1], path)
    if "host" in fields:
        spec.host = _expect(_plain(fields["host"][1], path), str, path, _line(fields["host"][1]),
                            f"node {name!r}: host")
    _parse_node_options(spec, fields, path)
    return spec


def _bounded_int(node: yaml.Node, path: str, what: str, low: int, high: int, meaning: str) -> int:
    value = _expect(_plain(node, path), int, path, _line(node), what)
    if not low <= value <= high:
        raise GraphError(path, _line(node), f"{what} must be in {low}..{high}{meaning}")
    return value


def _parse_node_options(spec: NodeSpec, fields: dict[str, tuple[yaml.Node, yaml.Node]], path: str) -> None:
    """The node's scheduling options: sync_timeout_ms, max_lag_ms, nice, realtime."""
    name = spec.name
    if "sync_timeout_ms" in fields:
        node = fields["sync_timeout_ms"][1]
        value = _expect(_plain(node, path), (int, float), path, _line(node), f"node {name!r}: sync_timeout_ms")
        if not (math.isfinite(value) and value > 0):
            raise GraphError(path, _line(node),
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
    value = _expect(_plain(node, path), (int, float), path, _line(node), what)
    if isinstance(value, bool) or not (math.isfinite(value) and value >= 0):
        raise GraphError(path, _line(node), f"{what} must be a finite number >= 0 (0: unbounded), not {value!r}")
    return float(value)


def _parse_input(node: str, name: str, key_node: yaml.Node, value_node: yaml.Node, path: str) -> InputSpec:
    where = f"node {node!r}: input {name!r}"
    line = _line(key_node)
    if not NAME_RE.match(name):
        raise GraphError(path, line, f"{where}: not a valid input name")
    value = _plain(value_node, path)
    options: dict[str, Any] = {}
    lines: dict[str, int] = {}  # each option's own line: in a graph that extends another, maybe another file
    if isinstance(value, str):
        source = value
    elif isinstance(value, dict):
        for opt_name, opt_key, opt_value in _mapping_items(value_node, path, where):
            lines[opt_name] = _line(opt_value)
            if opt_name not in INPUT_KEYS:
                raise GraphError(path, _line(opt_key),
                                 f"{where}: unknown key {opt_name!r} (allowed: {', '.join(sorted(INPUT_KEYS))})")
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
        if spec.policy not in POLICIES:
            raise GraphError(path, lines["policy"], f"{where}: policy must be one of {', '.join(POLICIES)}")
    if "sync" in options:
        spec.sync = _expect(options["sync"], str, path, lines["sync"], f"{where}: sync")
        if spec.sync not in SYNC_MODES:
            raise GraphError(path, lines["sync"], f"{where}: sync must be one of {', '.join(SYNC_MODES)}")
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
    line = _line(value_node)
    value = _plain(value_node, path)
    lines: dict[str, int] = {"policy": line}  # each key's own line (a base's or an override's)
    if isinstance(value, str):
        value = {"policy": value}
    else:
        _expect(value, dict, path, line, where)
        lines.update({key: _line(v_node) for key, _, v_node in _mapping_items(value_node, path, where)})
    for key in value:
        if key not in RESTART_KEYS:
            raise GraphError(path, lines[key],
                             f"{where}: unknown key {key!r} (allowed: {', '.join(sorted(RESTART_KEYS))})")
    policy = RestartPolicy()
    if "policy" in value:
        policy.policy = _expect(value["policy"], str, path, lines["policy"], f"{where}: policy")
        if policy.policy not in RESTART_POLICIES:
            raise GraphError(path, lines["policy"], f"{where}: policy must be one of {', '.join(RESTART_POLICIES)}")
    for key in ("max_restarts", "backoff_ms", "max_backoff_ms", "window_s"):
        if key in value:
            setattr(policy, key, _expect(value[key], int, path, lines[key], f"{where}: {key}"))
            if getattr(policy, key) < 0:
                raise GraphError(path, lines[key], f"{where}: {key} must be >= 0")
    return policy


def _check_wiring(graph: Graph) -> None:
    for spec in graph.nodes.values():
        for inp in spec.inputs.values():
            producer = graph.nodes.get(inp.source_node)
            if producer is None:
                raise graph.error(inp.line, f"node {spec.name!r}: input {inp.name!r} comes from unknown node "
                                            f"{inp.source_node!r}")
            if inp.source_output not in producer.outputs:
                raise graph.error(inp.line, f"node {spec.name!r}: input {inp.name!r}: node {inp.source_node!r} "
                                            f"has no output {inp.source_output!r} (it has: "
                                            f"{', '.join(producer.outputs) or 'none'})")
        if spec.inputs and all(i.sync != "frame" for i in spec.inputs.values()):
            continue
        frame_inputs = [i for i in spec.inputs.values() if i.sync == "frame"]
        if frame_inputs and all(i.optional or i.offset for i in frame_inputs):
            raise graph.error(spec.line, f"node {spec.name!r}: at least one same-frame synchronised input must be "
                                         "required (not optional, offset 0)")
    _check_same_frame_cycles(graph)


def _same_frame_edges(graph: Graph) -> dict[str, list[InputSpec]]:
    """node -> its inputs that wait for the same frame from their producer (sync frame, offset 0)."""
    return {name: [i for i in spec.inputs.values() if i.sync == "frame" and i.offset == 0]
            for name, spec in graph.nodes.items()}


def _check_same_frame_cycles(graph: Graph) -> None:
    """A loop of same-frame inputs waits for itself: frame n of each node needs frame n of the next, which
    needs this one's. A feedback input (offset: -1) takes the previous frame and breaks it."""
    edges = _same_frame_edges(graph)
    done: set[str] = set()

    def visit(node: str, path: list[tuple[str, InputSpec]]) -> None:
        on_path = [n for n, _ in path]
        if node in on_path:
            loop = path[on_path.index(node):]
            names = " -> ".join([*(n for n, _ in loop), node])
            raise graph.error(loop[-1][1].line,
                              f"same-frame cycle {names} (each node waits for the next one's output of the same "
                              "frame: a deadlock); make one of these inputs a feedback input (offset: -1)")
        if node in done:
            return
        for inp in edges[node]:
            visit(inp.source_node, [*path, (node, inp)])
        done.add(node)

    for name in graph.nodes:
        visit(name, [])
