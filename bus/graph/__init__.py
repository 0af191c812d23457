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
The package: ``spec`` (nodes, inputs, errors, the allowed names), ``extends`` (the YAML tree and ``extends:``),
``load`` (load_graph), ``checks`` (hosts, wiring, same-frame cycles), ``model`` (Graph) and ``variants`` (graphs
derived from a graph, and the ``node.param=value`` parser).
"""

from __future__ import annotations

from .load import load_graph
from .model import Graph
from .spec import NAMESPACE_RE, Boundary, GraphError, InputSpec, NodeSpec, RestartPolicy, SourceLine
from .variants import apply_overrides, parse_assignments, parse_value

__all__ = ["NAMESPACE_RE", "Boundary", "Graph", "GraphError", "InputSpec", "NodeSpec", "RestartPolicy", "SourceLine",
           "apply_overrides", "load_graph", "parse_assignments", "parse_value"]
