"""Diagnostic nodes for checking a deployment's bus end to end: ``ticker`` produces numbered
ticks, ``relay`` forwards them (optionally joining two inputs by frame), ``sink`` counts them.

    nodes:
      ticker: {run: followbus.nodes.diagnostics, outputs: [tick], params: {rate_hz: 30}}
      relay:  {run: followbus.nodes.diagnostics_relay, inputs: {tick: ticker/tick}, outputs: [tick]}
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.node_params import ParamError
from ..bus.schemas import Message, Tick


@dataclass
class TickerParams:
    rate_hz: float = field(default=30.0, metadata={"live": True})  # ticks per second; live (followbus param set)
    payload_bytes: int = 0
    count: int = 0  # 0 = forever
    fail_after_s: float = 0.0  # fault injection: exit with status 3 after this long (checks restart policies)
    wait_for_consumers_s: float = 15.0  # before the first tick, wait this long at most for the consumers
    # Fault injection (checks that a node that stops working is seen and restarted, bus/liveness.py), by tick
    # number, -1 = never: poll raises once at that tick; raises at every poll from it; stops publishing from it.
    raise_once_at: int = -1
    raise_from: int = -1
    silent_from: int = -1

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ParamError("rate_hz", f"rate_hz must be > 0, not {self.rate_hz!r}")
        for name in ("payload_bytes", "count", "fail_after_s", "wait_for_consumers_s"):
            if getattr(self, name) < 0:
                raise ParamError(name, f"{name} must be >= 0, not {getattr(self, name)!r}")


class Ticker(Node):
    OUTPUTS = {"tick": Out(Tick)}
    Params = TickerParams

    def setup(self) -> None:
        self.value = 0
        self.started = time.monotonic()
        self.barrier = self.runtime.wait_for_consumers(self.params.wait_for_consumers_s, 0.2)
        self.payload = np.zeros(self.params.payload_bytes, np.uint8) if self.params.payload_bytes else None

    def poll(self, now_ns: int) -> float | None:
        if self.params.fail_after_s and time.monotonic() - self.started > self.params.fail_after_s:
            self.log.error("fault injection: failing on purpose after %.1f s", self.params.fail_after_s)
            raise SystemExit(3)
        if self.params.count and self.value >= self.params.count:
            return None
        wait = self.barrier.wait_s()
        if wait > 0:
            return wait
        self._inject_faults()
        if 0 <= self.params.silent_from <= self.value:
            return 1.0 / self.params.rate_hz
        msg = Tick(value=self.value, payload=self.payload)
        msg.header.stamp_ns = time.time_ns()
        msg.header.frame_seq = self.value
        self.publish("tick", msg)
        self.value += 1
        return 1.0 / self.params.rate_hz

    def _inject_faults(self) -> None:
        p = self.params
        if self.value == p.raise_once_at and not getattr(self, "_raised", False):
            self._raised = True
            raise OSError(f"fault injection: poll fails once at tick {self.value}")
        if 0 <= p.raise_from <= self.value:
            raise OSError(f"fault injection: poll fails from tick {p.raise_from}")


NODE = Ticker


@dataclass
class RelayParams:
    add: int = 0  # added to the value, so a test can tell relayed ticks from originals


class Relay(Node):
    """Forwards ``tick``; with a second input ``other`` connected, forwards only frame-joined pairs
    (value = tick + other), which exercises the synchroniser."""

    INPUTS = {"tick": In(Tick, required=True), "other": In(Tick)}
    OUTPUTS = {"tick": Out(Tick)}
    Params = RelayParams

    def setup(self) -> None:
        self.forwarded = 0

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        tick = inputs["tick"]
        other = inputs.get("other")
        value = tick.value + self.params.add + (other.value if isinstance(other, Tick) else 0)
        self.publish("tick", Tick(value=value))
        self.forwarded += 1

    def status(self) -> dict[str, Any]:
        return {"forwarded": self.forwarded}


class Sink(Node):
    """Counts the ticks it receives, wired either way: joined by frame (the default), or one by one (sync: none)."""

    INPUTS = {"tick": In(Tick, required=True)}

    def setup(self) -> None:
        self.received = 0
        self.last_value = -1

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        self.on_message("tick", inputs["tick"])  # type: ignore[arg-type]

    def on_message(self, name: str, msg: Message) -> None:
        self.received += 1
        self.last_value = msg.value  # type: ignore[attr-defined]

    def status(self) -> dict[str, Any]:
        return {"received": self.received, "last_value": self.last_value}
