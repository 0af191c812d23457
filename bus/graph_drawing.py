"""A drawing of a graph's dataflow, as rqt_graph and ``dora graph`` give: nodes (boxes) and the keys they publish
(ellipses), an arrow from a node to each key it publishes and from a key to each node that takes it.

Two forms: Graphviz DOT (written here: for ``dot -Tpng``, or any DOT viewer) and a self-made SVG. The SVG is laid
out here rather than by Graphviz's ``dot`` because Graphviz is a system package (no wheel on PyPI), which the
two set-up commands would have to install with apt as root, and the web view must draw the graph on any machine.
The layout is layered, as dot's is: every item sits one column right of what feeds it (longest path); an edge
that closes a cycle (a feedback input, ``offset: -1``, or an input read without joining by frame from a node
further down the flow) is drawn dashed, against the flow, and does not count for the columns.
"""

from __future__ import annotations

from html import escape
from typing import Any

COLUMN_PX, ROW_PX, MARGIN_PX = 170, 56, 24
NODE_W, NODE_H, KEY_W, KEY_H = 120, 32, 138, 26


def _edges(graph: Any) -> tuple[list[tuple[str, str, bool]], list[str]]:
    """(from, to, feedback) between items ``n:<node>`` and ``k:<node>/<output>``, and the items in file order."""
    items, edges = [], []
    for name, spec in graph.nodes.items():
        items.append(f"n:{name}")
        for out in spec.outputs:
            items.append(f"k:{name}/{out}")
            edges.append((f"n:{name}", f"k:{name}/{out}", False))
    for name, spec in graph.nodes.items():
        for inp in spec.inputs.values():
            edges.append((f"k:{inp.topic}", f"n:{name}", inp.offset < 0))
    return edges, items


def back_edges(graph: Any) -> set[tuple[str, str]]:
    """The edges that close a cycle, found depth first in file order, as dot breaks cycles: a feedback input
    (``offset: -1``), or an input taken without joining by frame from a node further down the flow. An edge from a
    node to the key it publishes never closes one (a key is reached only through its publisher), so every key
    stays right of its publisher."""
    edges, items = _edges(graph)
    out: dict[str, list[str]] = {item: [] for item in items}
    for src, dst, _feedback in edges:
        if src in out and dst in out:
            out[src].append(dst)
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    found: set[tuple[str, str]] = set()
    for root in items:
        if root in state:
            continue
        state[root] = 1
        stack = [(root, iter(out[root]))]
        while stack:
            item, children = stack[-1]
            child = next(children, None)
            if child is None:
                state[item] = 2
                stack.pop()
            elif state.get(child) == 1:
                found.add((item, child))
            elif child not in state:
                state[child] = 1
                stack.append((child, iter(out[child])))
    return found


def layout(graph: Any) -> dict[str, tuple[int, int]]:
    """Column and row of every item: a column one right of the furthest item feeding it, over the edges that close
    no cycle (:func:`back_edges`; feedback inputs among them)."""
    edges, items = _edges(graph)
    backward = back_edges(graph)
    forward = [(src, dst) for src, dst, feedback in edges
               if src in items and not feedback and (src, dst) not in backward]
    column = dict.fromkeys(items, 0)
    for _ in items:  # longest path by relaxation over an acyclic set of edges: at most one pass per item
        changed = False
        for src, dst in forward:
            if column[dst] < column[src] + 1:
                column[dst] = column[src] + 1
                changed = True
        if not changed:
            break
    rows: dict[int, int] = {}
    out = {}
    for item in items:
        col = column[item]
        out[item] = (col, rows.get(col, 0))
        rows[col] = rows.get(col, 0) + 1
    return out


def to_dot(graph: Any) -> str:
    """The graph in Graphviz DOT: boxes for nodes, ellipses for keys (labelled with their full bus key)."""
    edges, items = _edges(graph)
    lines = [f'digraph "{graph.name}" {{', "  rankdir=LR;", '  node [fontname="Helvetica", fontsize=11];']
    for item in items:
        kind, _, name = item.partition(":")
        if kind == "n":
            lines.append(f'  "{item}" [label="{name}", shape=box, style="rounded,filled", fillcolor="#dbe8f7"];')
        else:
            lines.append(f'  "{item}" [label="{graph.namespace}/{name}", shape=ellipse, fontsize=9];')
    for src, dst, feedback in edges:
        if src in items:
            style = ' [style=dashed, constraint=false, label="k-1"]' if feedback else ""
            lines.append(f'  "{src}" -> "{dst}"{style};')
    lines.append("}")
    return "\n".join(lines) + "\n"


def _centre(cell: tuple[int, int]) -> tuple[float, float]:
    return MARGIN_PX + cell[0] * COLUMN_PX + NODE_W / 2 + 10, MARGIN_PX + cell[1] * ROW_PX + NODE_H / 2


def _svg_item(item: str, cell: tuple[int, int], namespace: str) -> str:
    kind, _, name = item.partition(":")
    x, y = _centre(cell)
    if kind == "n":
        return (f'<g class="node"><rect x="{x - NODE_W / 2:.0f}" y="{y - NODE_H / 2:.0f}" width="{NODE_W}" '
                f'height="{NODE_H}" rx="6" fill="#dbe8f7" stroke="#35618f"/><text x="{x:.0f}" y="{y + 4:.0f}" '
                f'text-anchor="middle" font-size="12">{escape(name)}</text></g>')
    return (f'<g class="key"><title>{escape(namespace)}/{escape(name)}</title><ellipse cx="{x:.0f}" cy="{y:.0f}" '
            f'rx="{KEY_W / 2}" ry="{KEY_H / 2}" fill="#fff" stroke="#888"/><text x="{x:.0f}" y="{y + 3:.0f}" '
            f'text-anchor="middle" font-size="9">{escape(name)}</text></g>')


def _svg_edge(a: tuple[int, int], b: tuple[int, int], feedback: bool) -> str:
    (x1, y1), (x2, y2) = _centre(a), _centre(b)
    x1, x2 = (x1 + KEY_W / 2, x2 - KEY_W / 2) if x2 > x1 else (x1 - KEY_W / 2, x2 + KEY_W / 2)
    bend = 0 if not feedback else -40 - 8 * abs(a[0] - b[0])
    path = f"M{x1:.0f},{y1:.0f} C{(x1 + x2) / 2:.0f},{y1 + bend:.0f} {(x1 + x2) / 2:.0f},{y2 + bend:.0f} " \
           f"{x2:.0f},{y2:.0f}"
    dash = ' stroke-dasharray="5,4"' if feedback else ""
    return f'<path d="{path}" fill="none" stroke="#555"{dash} marker-end="url(#arrow)"/>'


def to_svg(graph: Any) -> str:
    """The graph as a standalone SVG document (laid out by :func:`layout`)."""
    cells = layout(graph)
    edges, items = _edges(graph)
    width = MARGIN_PX * 2 + (max(c for c, _ in cells.values()) + 1) * COLUMN_PX
    height = MARGIN_PX * 2 + (max(r for _, r in cells.values()) + 1) * ROW_PX
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" font-family="Helvetica, Arial, sans-serif">',
             f"<title>{escape(graph.name)} ({escape(graph.namespace)})</title>",
             '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="7" markerHeight="7" '
             'orient="auto"><path d="M0,0 L10,5 L0,10 z" fill="#555"/></marker></defs>']
    backward = back_edges(graph)
    parts += [_svg_edge(cells[src], cells[dst], feedback or (src, dst) in backward)
              for src, dst, feedback in edges if src in cells]
    parts += [_svg_item(item, cells[item], graph.namespace) for item in items]
    parts.append("</svg>")
    return "\n".join(parts) + "\n"
