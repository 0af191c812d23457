"""The checks a whole graph passes once its nodes are read: hosts named consistently, every input wired to an
output that exists, and no loop of same-frame inputs (a deadlock)."""

from __future__ import annotations

from .spec import GraphError, GraphLike, InputSpec


def check_hosts(graph: GraphLike) -> None:
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



def check_wiring(graph: GraphLike) -> None:
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


def _same_frame_edges(graph: GraphLike) -> dict[str, list[InputSpec]]:
    """node -> its inputs that wait for the same frame from their producer (sync frame, offset 0)."""
    return {name: [i for i in spec.inputs.values() if i.sync == "frame" and i.offset == 0]
            for name, spec in graph.nodes.items()}


def _check_same_frame_cycles(graph: GraphLike) -> None:
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
