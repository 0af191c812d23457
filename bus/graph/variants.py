"""Variants of a graph: each method returns a new graph and leaves the one it is called on as it is (tools derive
graphs only here), the graph written back as YAML, and the one parser of ``node.param=value`` assignments."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

import yaml

from ..session import ZenohSettings
from .checks import check_wiring
from .spec import NAMESPACE_RE, Boundary, GraphError, InputSpec, NodeSpec, RestartPolicy

G = TypeVar("G", bound="GraphVariants")


class GraphVariants:
    """The variant API of :class:`bus.graph.model.Graph` (its data is declared there)."""

    name: str
    namespace: str
    zenoh: ZenohSettings
    nodes: dict[str, NodeSpec]
    path: str
    text: str
    max_lag_ms: float
    default_host: str | None

    def error(self, line: int | None, message: str) -> GraphError:
        return GraphError(self.path, line, message)

    def override(self: G, params: Mapping[str, Mapping[str, Any]] | Iterable[str]) -> G:
        """This graph with node parameters set: {node: {param: value}}, or ``node.param=value`` assignments."""
        if not isinstance(params, Mapping):
            params = parse_assignments(params, nodes=self.nodes)
        graph = self._variant()
        for node, values in params.items():
            if node not in graph.nodes:
                raise graph.error(None, f"no node named {node!r} (nodes: {', '.join(graph.nodes)})")
            graph.nodes[node].params.update(copy.deepcopy(dict(values)))
        return graph

    def with_namespace(self: G, namespace: str) -> G:
        if not NAMESPACE_RE.match(namespace):
            raise self.error(None, f"namespace {namespace!r} is not a valid key prefix")
        graph = self._variant()
        graph.namespace = namespace
        return graph

    def with_port(self: G, port: int, host: str = "127.0.0.1") -> G:
        """This graph listening and connecting on one TCP port only (a private bus on this machine)."""
        endpoint = f"tcp/{host}:{int(port)}"
        return self.with_zenoh(listen=[endpoint], connect=[endpoint])

    def with_zenoh(self: G, settings: ZenohSettings | None = None, **changes: Any) -> G:
        """This graph on other Zenoh settings: ``settings`` whole, and/or some of its fields changed."""
        graph = self._variant()
        graph.zenoh = dataclasses.replace(settings or graph.zenoh, **changes)
        return graph

    def with_node(self: G, name: str, **changes: Any) -> G:
        """This graph with node options of ``name`` changed (NodeSpec fields: sync_timeout_ms, restart, ...)."""
        graph = self._variant()
        spec = graph.nodes[name]
        for key, value in changes.items():
            if key in ("name", "params") or not hasattr(spec, key):
                raise graph.error(spec.line, f"node {name!r}: no option {key!r} to change here")
            setattr(spec, key, copy.deepcopy(value))
        return graph

    def with_input(self: G, node: str, name: str, source: str, **options: Any) -> G:
        """This graph with an input ``name`` of ``node`` fed from ``source`` (node/output); options as in the file."""
        src_node, _, src_output = source.partition("/")
        graph = self._variant()
        graph.nodes[node].inputs[name] = InputSpec(name=name, source_node=src_node, source_output=src_output,
                                                   **options)
        check_wiring(graph)
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

    def subgraph(self: G, nodes: Iterable[str], name: str | None = None) -> G:
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

    def _variant(self: G) -> G:
        graph = copy.deepcopy(self)
        graph.text = ""  # a variant's file is what to_yaml() writes
        return graph



def _document(graph: GraphVariants) -> dict[str, Any]:
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


def apply_overrides(graph: GraphVariants, assignments: list[str]) -> None:
    """Apply ``node.param=value`` assignments (``--set``) on top of graph.yaml's params, in place (the graph
    commands keep the assignments to hand them on to the node processes; tools deriving a variant use
    :meth:`Graph.override`)."""
    try:
        parsed = parse_assignments(assignments, nodes=graph.nodes)
    except GraphError as exc:
        raise GraphError(graph.path, None, exc.message) from None
    for node, params in parsed.items():
        graph.nodes[node].params.update(params)

