"""The parts of a graph: its nodes, their inputs and restart policies, where an error is (file and line), and
the names and choices graph.yaml allows."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

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



class GraphLike(Protocol):
    """What the checks read of a graph (bus.graph.model.Graph)."""

    path: str
    nodes: dict[str, NodeSpec]
    default_host: str | None

    def error(self, line: int | None, message: str) -> GraphError: ...
