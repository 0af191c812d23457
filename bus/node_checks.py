"""A graph's node against its class, before anything starts: the module exports a Node class, the wiring matches
its ports (names, required inputs, message types, how each input is joined) and its params parse. Every problem is
a GraphError at the graph.yaml line it comes from."""

from __future__ import annotations

import importlib
from typing import Any

from .graph import Graph, GraphError, InputSpec, NodeSpec
from .node import Node
from .node_params import ParamError, marked, param_names, parse_params


def load_node_class(run: str) -> type[Node]:
    """The ``NODE`` class of the module graph.yaml's ``run:`` names (ImportError saying what is wrong: a user's
    module that fails to import, a port declared the old way, is one line, not a traceback)."""
    if not run or run.startswith("."):
        raise ImportError(f"{run!r} is not a module name (an absolute, dotted name: followbus.nodes.capture)")
    try:
        module = importlib.import_module(run)
    except ImportError:
        raise
    except Exception as exc:
        raise ImportError(f"module {run!r} failed to import: {type(exc).__name__}: {exc}") from exc
    cls = getattr(module, "NODE", None)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise ImportError(f"module {run!r} has no NODE class deriving from followbus.bus.node.Node")
    return cls


def validate_node(graph: Graph, spec: NodeSpec, cls: type[Node] | None = None) -> tuple[type[Node], Any]:
    """Check a node spec against its class: inputs, outputs, types and params. Raises GraphError."""
    if cls is None:
        try:
            cls = load_node_class(spec.run)
        except ImportError as exc:
            raise graph.error(spec.line, f"node {spec.name!r}: run: {exc}") from exc
    _check_ports(graph, spec, cls)
    try:
        params = parse_params(cls.Params, spec.params)
    except ParamError as exc:
        raise _param_error(graph, spec, cls, exc) from exc
    except (TypeError, ValueError) as exc:
        raise graph.error(spec.line, f"node {spec.name!r}: params: {exc}") from exc
    return cls, params


def unread_inputs(cls: type[Node], params: Any) -> frozenset[str]:
    """Inputs these params never read (``In.read_if``): a node on the bus does not subscribe to them, so nothing is
    sent, received and decoded for nothing (every message costs each end a few hundred microseconds of CPU on a
    busy 2-core machine, most of it outside the node's code)."""
    return frozenset(name for name, port in cls.INPUTS.items() if port.read_if is not None and not port.read_if(params))


def _check_ports(graph: Graph, spec: NodeSpec, cls: type[Node]) -> None:
    """The node's inputs and outputs against its class: names, required inputs, each input's message type against
    what its producer publishes, and how it is joined against how the class reads it."""
    for inp in spec.inputs.values():
        if inp.name not in cls.INPUTS:
            raise graph.error(inp.line, f"node {spec.name!r}: {spec.run} has no input {inp.name!r} "
                                        f"(it takes: {', '.join(cls.INPUTS) or 'none'})")
        _check_input_type(graph, spec, cls, inp)
        _check_input_sync(graph, spec, cls, inp)
    for name, port in cls.INPUTS.items():
        if port.required and name not in spec.inputs:
            raise graph.error(spec.line, f"node {spec.name!r}: missing required input {name!r}")
    for out in spec.outputs:
        if out not in cls.OUTPUTS:
            raise graph.error(spec.line, f"node {spec.name!r}: {spec.run} has no output {out!r} "
                                         f"(it produces: {', '.join(cls.OUTPUTS) or 'none'})")


def _check_input_type(graph: Graph, spec: NodeSpec, cls: type[Node], inp: InputSpec) -> None:
    try:
        producer_cls = load_node_class(graph.nodes[inp.source_node].run)
    except ImportError:
        return  # said at the producer
    produced = producer_cls.OUTPUTS.get(inp.source_output)
    expected = cls.INPUTS[inp.name].type
    if produced is not None and produced.type is not expected:
        raise graph.error(inp.line, f"node {spec.name!r}: input {inp.name!r} expects {expected.TYPE} but "
                                    f"{inp.topic} carries {produced.type.TYPE}")


def _check_input_sync(graph: Graph, spec: NodeSpec, cls: type[Node], inp: InputSpec) -> None:
    """An input the class samples by stamp is wired ``sync: none``; any other reaches a hook the class has (frame
    sets: on_frame; one message at a time: on_message). Otherwise its messages would reach no hook at all."""
    port = cls.INPUTS[inp.name]
    if port.sample_by_stamp:
        if inp.sync != "none":
            raise graph.error(inp.line, f"node {spec.name!r}: input {inp.name!r} is sampled by stamp: wire it with "
                                        f"sync: none (not {inp.sync})")
        return
    if inp.sync == "frame" and not port.on_arrival and cls.on_frame is Node.on_frame:
        raise graph.error(inp.line, f"node {spec.name!r}: {spec.run} reads {inp.name!r} in on_message, one message "
                                    "at a time: wire it with sync: none (sync: frame joins it into frame sets)")
    if inp.sync != "frame" and cls.on_message is Node.on_message:
        raise graph.error(inp.line, f"node {spec.name!r}: {spec.run} reads {inp.name!r} in frame sets (on_frame): "
                                    f"wire it with sync: frame, the default (not {inp.sync})")


def _param_error(graph: Graph, spec: NodeSpec, cls: type[Node], exc: ParamError) -> GraphError:
    """A parameter problem at the parameter's line (under its old name too: field metadata ``was``); a parameter
    this node does not read but another does is said so: a setting put on the wrong node."""
    readers = _read_elsewhere(graph, spec, cls, exc.key)
    verb = "does" if len(readers) == 1 else "do"
    message = f"{spec.name} does not read {exc.key!r}; {' and '.join(readers)} {verb}" if readers else str(exc)
    old = marked(cls.Params, "was").get(exc.key, exc.key)
    line = spec.param_lines.get(exc.key) or spec.param_lines.get(old) or spec.line
    return graph.error(line, f"node {spec.name!r}: {message}")


def _read_elsewhere(graph: Graph, spec: NodeSpec, cls: type[Node], key: str) -> list[str]:
    """For a parameter this node does not read: the other nodes of the graph that do (a setting put on the wrong
    node)."""
    if key in param_names(cls.Params):
        return []  # the node reads it: the value, not the name, was wrong
    readers = []
    for name, other in graph.nodes.items():
        try:
            if name != spec.name and key in param_names(load_node_class(other.run).Params):
                readers.append(name)
        except ImportError:
            continue  # reported at that node
    return readers
