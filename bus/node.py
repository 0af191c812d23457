"""The node API. A node is a class deriving from :class:`Node`, exported as ``NODE`` by the module graph.yaml's
``run:`` names; it declares its ports and overrides the hooks it needs (docs/writing-a-node.md):

    class Double(Node):
        INPUTS = {"tick": In(Tick, required=True)}
        OUTPUTS = {"tick": Out(Tick)}

        def on_frame(self, frame_seq, inputs):
            self.publish("tick", Tick(value=2 * inputs["tick"].value))

    NODE = Double

Its code is single-threaded: the runtime (bus/node_host.py) hands it one thing at a time, in arrival order, and
each input message goes to one hook:

- ``on_frame(frame_seq, inputs)`` once per frame set: the messages of one camera frame on the inputs graph.yaml
  joins by frame (``sync: frame``, the default; bus/sync.py), by input name;
- ``on_message(name, msg)`` for a message of an input not joined by frame (``sync: none`` or ``latest``), and, as
  it arrives, for one of a joined input declared ``In(..., on_arrival=True)`` (work that need not wait for the
  set, such as applying a feedback message at once);
- an input declared ``In(..., sample_by_stamp=True)`` (wired ``sync: none``) fires nothing: the runtime keeps its
  messages, and ``inputs[name]`` in ``on_frame`` is the newest one stamped at or before the frame
  (``self.runtime.sample(name)`` in ``on_message``: at the message's stamp). Which one it was is noted in the
  outputs, so ``followbus replay`` repeats the choice exactly;
- ``on_timer(now_ns)`` every ``TIMER_PERIOD_MS`` of the node clock; ``poll(now_ns) -> seconds`` for a source that
  produces on its own schedule (None: never again).

``publish`` inside ``on_frame`` and ``on_message`` gives the message the header (stamp, frame number, epoch) of the
frame or message being handled; elsewhere a message without a stamp gets the node clock's time. The node clock is
wall time, or with ``--clock stamps`` (a lockstep replay) the newest input stamp, so a replayed node never
depends on the wall clock.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

from .barrier import DownstreamBarrier
from .clock import Clock
from .graph import Graph, NodeSpec
from .node_params import NoParams, ParamsSpec
from .pubsub import CONGESTION, PRIORITY
from .schemas import Message


@dataclass(frozen=True)
class In:
    """An input port: the message type it takes, and how the node reads it.

    ``required``: graph.yaml must wire it. ``sample_by_stamp``: a stream read by stamp (see the module docstring).
    ``on_arrival``: a frame-joined input whose messages also go to ``on_message`` as they arrive.
    ``read_if(params)``: False when these params never read the input (the node then does not subscribe to it).
    """

    type: type[Message]
    required: bool = False
    sample_by_stamp: bool = False
    on_arrival: bool = False
    read_if: Callable[[Any], bool] | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.type, type) and issubclass(self.type, Message)):
            raise TypeError(f"In: {self.type!r} is not a message type (a bus.schemas.Message class)")
        if self.sample_by_stamp and self.on_arrival:
            raise TypeError("In: an input sampled by stamp fires no hook (on_arrival does not apply)")


@dataclass(frozen=True)
class Out:
    """An output port: the message type, and how Zenoh sends it. ``congestion``: block (default) or drop a
    message a congested link cannot take now; ``express``: sent without batching; ``priority``: data (default),
    interactive_high or real_time (ahead of any backlog on the same link)."""

    type: type[Message]
    congestion: str = "block"
    express: bool = False
    priority: str = "data"

    def __post_init__(self) -> None:
        if not (isinstance(self.type, type) and issubclass(self.type, Message)):
            raise TypeError(f"Out: {self.type!r} is not a message type (a bus.schemas.Message class)")
        if self.congestion not in CONGESTION:
            raise TypeError(f"Out: congestion must be one of {', '.join(CONGESTION)}, not {self.congestion!r}")
        if self.priority not in PRIORITY:
            raise TypeError(f"Out: priority must be one of {', '.join(PRIORITY)}, not {self.priority!r}")


class Runtime(Protocol):
    """What hosts a node (bus/node_host.py NodeHost), as a node sees it: ``self.runtime``."""

    graph: Graph
    spec: NodeSpec  # the node's graph.yaml entry (its name, inputs, outputs)
    clock: Clock  # now_ns (the node clock), wall_ns, monotonic_ns (watchdogs: no stamp steers it), live
    session: Any  # the Zenoh session (None in-process)
    log: logging.Logger

    def publish(self, output: str, msg: Message, like: Message | None = None) -> None: ...

    def sample(self, name: str) -> Message | None:
        """The message of sampled input ``name`` for what is being handled (see the module docstring)."""

    def listened(self, output: str) -> bool:
        """Whether anyone subscribes to ``output`` now: an output only a viewer reads need not be made for nobody."""

    def stop(self) -> None:
        """End the node (its process leaves its loop and tears down)."""

    def wait_for_consumers(self, timeout_s: float, settle_s: float) -> DownstreamBarrier:
        """A source's start-up barrier: ``wait_s()`` is how long to hold the first message back."""


class Node:
    """A node: its ports and params declared, its hooks overridden. ``params`` is the instance of ``Params`` (a
    tuple of instances for a tuple of classes: the node's own settings and its algorithm's), ``log`` its logger,
    ``runtime`` what hosts it (its clock, graph, spec and session, ``sample``, ``listened``, ``stop``,
    ``wait_for_consumers``)."""

    INPUTS: ClassVar[dict[str, In]] = {}
    OUTPUTS: ClassVar[dict[str, Out]] = {}
    # The dataclass of the node's graph.yaml ``params``, or a tuple of them, which split the mapping by field name
    # (bus/node_params.py). Either way a key no class declares is an error at the key's line.
    Params: ClassVar[ParamsSpec] = NoParams
    TIMER_PERIOD_MS: ClassVar[float | None] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for what, ports, kind in (("INPUTS", cls.INPUTS, In), ("OUTPUTS", cls.OUTPUTS, Out)):
            wrong = [name for name, port in ports.items() if not isinstance(port, kind)]
            if wrong:
                raise TypeError(f"{cls.__name__}.{what}: {', '.join(wrong)} must be declared as {kind.__name__}(...)")

    def __init__(self, params: Any, runtime: Runtime):
        self.params = params
        self.runtime = runtime
        self.log: logging.Logger = runtime.log

    # --- hooks ------------------------------------------------------------------------------------
    def setup(self) -> None:
        """Build the node's state. The runtime calls it again to rebuild that state when ``on_frame`` keeps
        failing (whatever the cause, staying dead is the worst outcome)."""

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        """One frame set: its messages by input name (None: an optional input the set went on without)."""

    def on_message(self, name: str, msg: Message) -> None:
        """One message of an input not joined by frame (or declared ``on_arrival``)."""

    def on_timer(self, now_ns: int) -> None:
        """Every ``TIMER_PERIOD_MS`` of the node clock."""

    def poll(self, now_ns: int) -> float | None:
        """A source's work: seconds until the next poll, None for never again."""
        return None

    def teardown(self) -> None:
        """The node stops: save state, close devices."""

    def status(self) -> dict[str, Any]:
        """The node's own counters, in its status (``followbus ps``, ``monitor``) every second."""
        return {}

    # --- the one helper -----------------------------------------------------------------------------
    def publish(self, output: str, msg: Message, like: Message | None = None) -> None:
        """Publish ``msg`` on ``output``. In a handler its header is that of the frame or message being handled
        (``like``: that of another message); outside one, a message without a stamp gets the node clock's time."""
        self.runtime.publish(output, msg, like)
