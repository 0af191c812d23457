"""Where a replay sends the recording: the nodes hosted in this process (bus/inproc.py), or the deployed node as a
process (replay/isolated.py); both take inputs and hints and say what the nodes produced."""

from __future__ import annotations

import time
from typing import Protocol

from ..bus.inproc import InProcessGraph
from ..bus.schemas import ReplayHint
from .plan import ReplayPlan

# --- the targets: in-process here, or the deployed node as a process (replay/isolated.py) ---------

class Target(Protocol):
    def start(self) -> None: ...
    def hint(self, node: str, hint: ReplayHint) -> None: ...
    def send(self, topic: str, data: bytes, stamp_ns: int, frame_seq: int) -> None: ...
    def stand_in(self, topic: str, data: bytes, stamp_ns: int) -> None: ...
    def produced(self) -> dict[str, list[bytes]]: ...
    def close(self) -> None: ...


class InProcessTarget:
    """The nodes hosted here (bus.inproc), on the stamps clock; every input is delivered before the next."""

    def __init__(self, plan: ReplayPlan):
        self.plan = plan
        self.graph = InProcessGraph(plan.graph, nodes=plan.nodes, clock="stamps", record=plan.outputs.values())
        self.handler_s = 0.0
        self.decode_s = 0.0

    def start(self) -> None:
        self.graph.start()

    def hint(self, node: str, hint: ReplayHint) -> None:
        self.graph.hint(node, hint)

    def send(self, topic: str, data: bytes, stamp_ns: int, frame_seq: int) -> None:
        t0 = time.perf_counter()
        self.graph.inject_bytes(topic, data, stamp_ns)  # decoded by each subscribed node
        t1 = time.perf_counter()
        self.graph.deliver()
        self.decode_s += t1 - t0
        self.handler_s += time.perf_counter() - t1

    def stand_in(self, topic: str, data: bytes, stamp_ns: int) -> None:
        """A replayed node's recorded output to the other replayed nodes, in place of one it cannot make; not
        counted as produced."""
        self.graph.inject_bytes(topic, data, stamp_ns, record=False)
        self.graph.deliver()

    def published(self, topic: str) -> int:
        return self.graph.published[topic]

    def produced(self) -> dict[str, list[bytes]]:
        return {t: self.graph.payloads(*t.split("/", 1)) for t in self.plan.outputs.values()}

    def close(self) -> None:
        self.graph.close()


