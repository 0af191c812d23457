"""The node API (bus/node.py) as a node's author meets it, through the in-process runtime: fifteen public names,
each input message reaching one hook, what ``publish`` puts in the header, and the wiring ``check`` refuses
because its messages would reach no hook."""

from __future__ import annotations

import textwrap

import pytest

from followbus.bus.graph import GraphError, load_graph
from followbus.bus.inproc import InProcessGraph
from followbus.bus.node import In, Node, Out
from followbus.bus.node_checks import validate_node
from followbus.bus.schemas import Tick

EPOCH_NS = 1_600_000_000_000_000_000
T0 = 1_700_000_000_000_000_000
DT = 33_333_333

PROBE = '''
from followbus.bus.node import In, Node, Out
from followbus.bus.schemas import Tick


class Probe(Node):
    INPUTS = {"tick": In(Tick, required=True), "early": In(Tick, on_arrival=True), "loose": In(Tick)}
    OUTPUTS = {"tick": Out(Tick), "beat": Out(Tick)}
    TIMER_PERIOD_MS = 10.0

    def setup(self):
        self.frames, self.messages = [], []

    def on_frame(self, frame_seq, inputs):
        self.frames.append(frame_seq)
        self.publish("tick", Tick(value=inputs["tick"].value))

    def on_message(self, name, msg):
        self.messages.append((name, msg.header.frame_seq))

    def on_timer(self, now_ns):
        self.publish("beat", Tick(value=1))


NODE = Probe
'''


@pytest.fixture
def probe(tmp_path, monkeypatch):
    (tmp_path / "probe_node.py").write_text(PROBE)
    monkeypatch.syspath_prepend(str(tmp_path))

    def graph(inputs: str = "{tick: ticker/tick}"):
        return load_graph("<test>", text=textwrap.dedent(f"""\
            name: t
            nodes:
              ticker: {{run: followbus.nodes.diagnostics, outputs: [tick]}}
              probe: {{run: probe_node, inputs: {inputs}, outputs: [tick, beat]}}
            """))

    return graph


def _tick(k: int, value: int = 0) -> Tick:
    msg = Tick(value=value)
    msg.header.frame_seq, msg.header.stamp_ns, msg.header.epoch_ns = k, T0 + k * DT, EPOCH_NS
    return msg


def test_a_node_class_has_at_most_fifteen_public_names():
    class Bare(Node):
        pass

    class Host:  # what a node instance adds: the names Node.__init__ sets
        log = None

    public = {name for name in dir(Bare) if not name.startswith("_")}
    public |= {name for name in vars(Bare(None, Host())) if not name.startswith("_")}  # type: ignore[arg-type]
    assert len(public) <= 15, sorted(public)
    assert {"INPUTS", "OUTPUTS", "Params", "on_frame", "on_message", "publish", "runtime"} <= public


def test_ports_are_declared_with_in_and_out():
    with pytest.raises(TypeError, match="must be declared as In"):
        type("Bad", (Node,), {"INPUTS": {"tick": Tick}})
    with pytest.raises(TypeError, match="congestion"):
        Out(Tick, congestion="sometimes")
    with pytest.raises(TypeError, match="not a message type"):
        In(int)


def test_a_port_declared_the_old_way_is_one_line_at_the_run_line(tmp_path, monkeypatch):
    (tmp_path / "old_style.py").write_text(PROBE.replace('In(Tick, required=True)', 'Tick'))
    monkeypatch.syspath_prepend(str(tmp_path))
    graph = load_graph("<test>", text="name: t\nnodes:\n  old: {run: old_style}\n")
    with pytest.raises(GraphError, match=r"<test>:3: node 'old': run: module 'old_style' failed to import: "
                                         r"TypeError: Probe.INPUTS: tick must be declared as In\(...\)"):
        validate_node(graph, graph.nodes["old"])


def test_each_input_message_reaches_one_hook(probe):
    """A frame-joined input goes to on_frame only (not to on_message first); one read on arrival goes to on_message
    as it comes as well, and one wired sync: none to on_message only."""
    graph = probe("{tick: ticker/tick, early: {from: ticker/tick}, loose: {from: ticker/tick, sync: none}}")
    with InProcessGraph(graph, nodes=["probe"]) as g:
        for k in range(3):
            g.inject("ticker/tick", _tick(k, value=10 + k))
            g.deliver()
        node = g.node("probe")
        assert node.frames == [0, 1, 2]
        assert sorted(node.messages) == [("early", k) for k in range(3)] + [("loose", k) for k in range(3)]


def test_publish_in_a_handler_carries_the_header_of_what_it_handles(probe):
    """No ``like=``: the output of frame k has frame k's stamp, number and epoch (the frame_seq -1 and stamp 0 of an
    unset header reached no join downstream); a timer's output is stamped with the node clock."""
    with InProcessGraph(probe(), nodes=["probe"]) as g:
        for k in range(3):
            g.inject("ticker/tick", _tick(k, value=k))
            g.deliver()
        heads = [(m.header.frame_seq, m.header.stamp_ns, m.header.epoch_ns) for m in g.outputs("probe", "tick")]
        assert heads == [(k, T0 + k * DT, EPOCH_NS) for k in range(3)]
        g.run_for(50_000_000)
        beats = g.outputs("probe", "beat")
        assert beats and all(b.header.stamp_ns > 0 and b.header.frame_seq == -1 for b in beats)


@pytest.mark.parametrize("inputs", [
    "{loose: {from: ticker/tick}, tick: ticker/tick}",  # frame-joined, and the node has on_frame
    "{tick: {from: ticker/tick, sync: none}}",  # one by one, and the node has on_message
])
def test_wiring_that_reaches_a_hook_is_accepted(probe, inputs):
    graph = probe(inputs)
    validate_node(graph, graph.nodes["probe"])


def test_wiring_whose_messages_would_reach_no_hook_is_refused():
    """An input sampled by stamp wired to be joined by frame, and a frame-joined input of a node that only handles
    messages one by one: each is an error at the input's line, before anything runs."""
    sampled = load_graph("<test>", text=textwrap.dedent("""\
        name: t
        nodes:
          detection: {run: followbus.nodes.detection, outputs: [detections]}
          motor: {run: followbus.nodes.motor, outputs: [odometry]}
          groundplane:
            run: followbus.nodes.groundplane
            inputs: {detections: detection/detections, odometry: motor/odometry}
            outputs: [points]
        """))
    with pytest.raises(GraphError, match="<test>:7: .*'odometry' is sampled by stamp: wire it with sync: none"):
        validate_node(sampled, sampled.nodes["groundplane"])
    joined = load_graph("<test>", text="name: t\nnodes:\n"
                                       "  prediction: {run: followbus.nodes.prediction, outputs: [track]}\n"
                                       "  motor: {run: followbus.nodes.motor, inputs: {track: prediction/track}}\n")
    with pytest.raises(GraphError, match="<test>:4: .*reads 'track' in on_message.*sync: none"):
        validate_node(joined, joined.nodes["motor"])
