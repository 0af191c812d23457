"""bus/graph/variants.py: variants of a loaded graph (each a new graph), written back as a graph file, and the one
parser of ``node.param=value``."""

from __future__ import annotations

import pytest

from followbus.bus.graph import GraphError, load_graph, parse_assignments

from .conftest import REPO


@pytest.fixture(scope="module")
def graph():
    return load_graph(REPO / "graph.yaml")


def test_a_variant_leaves_the_loaded_graph_as_it_is(graph):
    before = graph.to_yaml()
    variant = graph.override({"reid": {"gamma": 3.0}}).with_namespace("ht").with_port(7631)
    assert variant.nodes["reid"].params["gamma"] == 3.0 and variant.namespace == "ht"
    assert variant.zenoh.listen == variant.zenoh.connect == ["tcp/127.0.0.1:7631"]
    assert graph.to_yaml() == before and graph.namespace == "fb"
    assert variant.override(["reid.gamma=4"]).nodes["reid"].params["gamma"] == 4


def test_to_yaml_reads_back_as_the_same_graph(graph):
    variant = graph.with_node("reid", sync_timeout_ms=250.0).with_input("capture", "ack", "prediction/track",
                                                                         sync="none")
    again = load_graph("variant.yaml", variant.to_yaml())
    assert again.to_yaml() == variant.to_yaml()
    assert again.nodes["reid"].sync_timeout_ms == 250.0 and again.nodes["capture"].inputs["ack"].sync == "none"
    assert {n: s.params for n, s in again.nodes.items()} == {n: s.params for n, s in graph.nodes.items()}


def test_boundary_and_subgraph(graph):
    edge = graph.boundary(["template", "reid"])
    assert edge.nodes == ("reid", "template")  # graph order
    assert "capture/frame" in edge.input_topics() and "prediction/prior" in edge.input_topics(required=True)
    assert set(edge.outputs) == {"reid/measurement", "template/template"}
    alone = graph.subgraph(["reid"])
    producers = {i.source_node for i in graph.nodes["reid"].inputs.values()}
    assert set(alone.nodes) == producers | {"reid"}
    for name in producers - {"reid"}:  # stand-ins: the outputs reid reads, nothing else
        assert not alone.nodes[name].inputs and not alone.nodes[name].params
        assert set(alone.nodes[name].outputs) <= set(graph.nodes[name].outputs)
    load_graph("alone.yaml", alone.to_yaml())  # a valid graph file
    with pytest.raises(GraphError, match="no node named 'nobody'"):
        graph.boundary(["nobody"])


def test_one_parser_of_assignments():
    assert parse_assignments(["reid.gamma=3", "reid.init_box=[1, 2, 3, 4]"], nodes=["reid"]) == \
        {"reid": {"gamma": 3, "init_box": [1, 2, 3, 4]}}
    assert parse_assignments(["gamma=3"], flag="--param", nodes=["reid"], default_node="reid") == \
        {"reid": {"gamma": 3}}
    with pytest.raises(GraphError, match=r"--set gamma=3: must look like node.param=value"):
        parse_assignments(["gamma=3"], nodes=["reid"])
    with pytest.raises(GraphError, match=r"no node named 'reed'"):
        parse_assignments(["reed.gamma=3"], nodes=["reid"])
    with pytest.raises(GraphError, match=r"--param reid.gamma=\[1: the value is not valid YAML"):
        parse_assignments(["reid.gamma=[1"], flag="--param", nodes=["reid"])


def _renamed_graph():
    """graph.yaml with its prediction node called ``predictor``: no tool may know the node by name."""
    text = (REPO / "graph.yaml").read_text().replace("  prediction:\n", "  predictor:\n")
    return load_graph("renamed.yaml", text.replace("from: prediction/", "from: predictor/"))


def test_the_evaluation_follower_and_the_monitor_find_topics_by_type():
    from followbus.evaluation.graph_follower import GraphTopics
    from followbus.viewing.monitor import GraphInfo

    topics = GraphTopics(_renamed_graph())
    assert (topics.track, topics.prior) == ("predictor/track", "predictor/prior")
    assert topics.nodes == ["egomotion", "predictor", "redetection", "reid", "template"]
    assert (topics.frame, topics.detections, topics.odometry) == ("capture/frame", "detection/detections",
                                                                  "motor/odometry")
    info = GraphInfo.from_graph(_renamed_graph(), "ht")
    assert info.keys["track"] == "ht/predictor/track" and info.keys["command"] == "ht/motor/command"
    assert info.preview_key == "ht/capture/preview"  # the frame output no node reads
