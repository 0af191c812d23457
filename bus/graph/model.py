"""The graph: its name, namespace, Zenoh settings and nodes, and the bus keys they use."""

from __future__ import annotations

from dataclasses import dataclass

from ..session import ZenohSettings
from .spec import DEFAULT_MAX_LAG_MS, NodeSpec
from .variants import GraphVariants


@dataclass
class Graph(GraphVariants):
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

