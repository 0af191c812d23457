"""``followbus graph``: draw a graph's nodes and keys (bus/graph_drawing.py) as DOT or SVG."""

from __future__ import annotations

from pathlib import Path

from ..errors import UsageError, write_text_output


def graph_file(which: str) -> str:
    """A graph file, or the file of the running graph of that name (`followbus ps`). A folder of that name (the
    checkout's own `followbus/`) is no graph file: the name is looked up."""
    if Path(which).is_file() or which.endswith((".yaml", ".yml")):
        return which
    from .claims import live_runs
    from .detached import find_run

    runs = live_runs()
    if not runs:
        raise UsageError(f"{which}: no such graph file, and no graph is running")
    return find_run(which, runs).graph


def cmd_graph(args) -> int:
    from ...bus.graph_drawing import to_dot, to_svg
    from ..command import load_graph

    graph = load_graph(graph_file(args.graph))
    text = to_svg(graph) if args.svg else to_dot(graph)
    return write_text_output(text, args.output, f"{len(graph.nodes)} nodes")
