"""Messages that never arrived are counted (header.seq gaps), and the links between nodes are read from their
statuses: each link's sent, delivered and lost, and the launcher's watch over a graph spread over hosts, which
reports each cross-host link and names one that delivers nothing, ends that cannot see each other, or a host
never heard from (bus/links.py). The two-host tests (tests/test_two_hosts.py) run the same across network
namespaces; these judge the rules on real statuses and a real Zenoh session."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from followbus.bus.barrier import RECORDER_NAME
from followbus.bus.links import (
    PEER_HINT,
    Edge,
    LinkWatch,
    PublishedKeys,
    links_of_statuses,
    short_of_sent,
)
from followbus.bus.pubsub import Publisher, Subscriber
from followbus.bus.schemas import NodeStatus, Tick
from followbus.bus.session import ZenohSettings, open_session
from followbus.bus.stats import SequenceGaps

from .conftest import wait_until


def test_sequence_gaps_count_what_never_arrived_per_publisher():
    gaps = SequenceGaps(max_publishers=2)
    assert [gaps.see("a", s) for s in (0, 1, 4, 5)] == [0, 0, 2, 0]
    assert gaps.see("b", 10) == 0  # first seen: nothing to count yet
    assert gaps.see("a", 0) == -1  # a restarted publisher: followed from there, nothing counted
    assert gaps.see("a", 2) == 1
    gaps.see("c", 0)  # a third publisher: the one seen longest ago (b) is forgotten
    assert gaps.see("b", 20) == 0


def test_a_subscriber_counts_the_messages_that_never_reached_it(port, caplog):
    """A refused message (over the publisher's size limit) keeps its header.seq: the subscriber sees the gap and
    counts it as lost, and says so in its log."""
    sender = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    receiver = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    got: list[int] = []
    pub = Publisher(sender, "gap/tick", "ticker", max_payload_bytes=10_000)
    sub = Subscriber(receiver, "gap/tick", lambda m: got.append(m.value), schema=Tick)
    try:
        assert wait_until(lambda: pub.listened, 5)
        with caplog.at_level(logging.WARNING):
            assert pub.put(Tick(value=1))
            assert not pub.put(Tick(value=2, payload=np.zeros(20_000, np.uint8)))  # refused: seq 1 never sent
            assert not pub.put(Tick(value=3, payload=np.zeros(20_000, np.uint8)))
            assert pub.put(Tick(value=4))
            assert wait_until(lambda: got == [1, 4], 5), got
        snap = sub.stats.snapshot()
        assert (snap["count"], snap["lost"], snap["drops"]) == (2, 2, 0)
        assert any("2 messages on gap/tick from ticker never arrived" in r.getMessage() for r in caplog.records)
    finally:
        sub.undeclare()
        pub.undeclare()
        receiver.close()
        sender.close()


def _status(node: str, host: str = "", topics: dict | None = None, **extra) -> NodeStatus:
    extra = {"host": host, **extra} if host else dict(extra)
    return NodeStatus(node=node, pid=1, topics=topics or {}, extra=extra)


def _out(rate: float, count: int = 100, size: int = 921_600) -> dict:
    return {"direction": "out", "rate_hz": rate, "count": count, "bytes": count * size}


def _in(rate: float, count: int, lost: int = 0) -> dict:
    return {"direction": "in", "rate_hz": rate, "count": count, "lost": lost}


def test_links_are_read_from_the_statuses_of_both_ends():
    statuses = {"capture": _status("capture", "robot", {"t/capture/frame": _out(30.0)}),
                "detection": _status("detection", "gpu", {"t/capture/frame": _in(2.4, 50, lost=400),
                                                          "t/detection/detections": _out(2.4)}),
                "reid": _status("reid", "robot", {"t/capture/frame": _in(30.0, 900),
                                                  "t/detection/detections": _in(2.4, 50)})}
    links = {(link.edge.source, link.edge.target, link.edge.key): link for link in links_of_statuses(statuses)}
    assert set(links) == {("capture", "detection", "t/capture/frame"), ("capture", "reid", "t/capture/frame"),
                          ("detection", "reid", "t/detection/detections")}
    far = links[("capture", "detection", "t/capture/frame")]
    assert far.crosses_hosts and short_of_sent(far)
    assert far.describe() == "t/capture/frame capture (robot) -> detection (gpu): 2.4 of 30.0 Hz delivered, 400 lost"
    near = links[("capture", "reid", "t/capture/frame")]
    assert not near.crosses_hosts and not short_of_sent(near)
    assert not short_of_sent(links[("detection", "reid", "t/detection/detections")])  # all that is sent arrives


@dataclass
class _Health:
    """What LinkWatch reads of bus/health.py's NodeHealth."""

    alive: bool
    status: NodeStatus | None


HOSTS = {"capture": "robot", "detection": "gpu"}
FRAME = Edge("t/capture/frame", "capture", "detection")


def _watch(here: str, peer_mode: bool = False) -> LinkWatch:
    return LinkWatch([FRAME], HOSTS, here, peer_mode=peer_mode, hold_s=3.0, unseen_s=5.0)


def _run(watch: LinkWatch, health_at, seconds: int) -> list[tuple[float, int, str]]:
    """Check once a second for ``seconds``; the lines with the second they came at."""
    out = []
    for t in range(seconds + 1):
        out += [(t, level, line) for level, line in watch.check(health_at(t), float(t))]
    return out


def test_a_delivering_link_is_reported_once_with_its_figures():
    def health(t):
        return {"capture": _Health(True, _status("capture", topics={"t/capture/frame": _out(30.0)})),
                "detection": _Health(True, _status("detection", topics={"t/capture/frame": _in(29.8, 30 * t)}))}

    lines = _run(_watch("robot"), health, 10)
    assert lines == [(3, logging.INFO, "link t/capture/frame capture (robot) -> detection (gpu): 29.8 of 30.0 Hz "
                                       "delivered, 0 lost")]


def test_a_link_that_carries_part_of_it_says_so():
    def health(t):
        return {"capture": _Health(True, _status("capture", topics={"t/capture/frame": _out(30.0)})),
                "detection": _Health(True, _status("detection", topics={"t/capture/frame": _in(2.4, 3 * t, 27 * t)}))}

    [(t, level, line)] = _run(_watch("gpu"), health, 10)
    assert level == logging.WARNING and t == 3
    assert line.startswith("link t/capture/frame capture (robot) -> detection (gpu): 2.4 of 30.0 Hz delivered, ")
    assert line.endswith("lost: the link does not carry all of it")


def test_a_link_that_delivers_nothing_while_its_publisher_sends_is_a_split():
    """Peers on two hosts: both nodes up (their statuses reach this launcher), capture sending 30 Hz, detection's
    input never counting a message. Named within the hold, with the peer-mode hint."""
    def health(_t):
        return {"capture": _Health(True, _status("capture", topics={"t/capture/frame": _out(30.0)})),
                "detection": _Health(True, _status("detection", topics={"t/capture/frame": _in(0.0, 0)}))}

    [(t, level, line)] = _run(_watch("robot", peer_mode=True), health, 10)
    assert (t, level) == (4, logging.WARNING)  # the count stood still from the first check on
    assert line.startswith("links capture (robot) -> detection (gpu) (t/capture/frame): nothing delivered in 3 s "
                           "while capture sends 30.0 Hz: the hosts do not exchange data; ")
    assert line.endswith(PEER_HINT)


def test_a_source_waiting_for_a_consumer_this_launcher_sees_is_a_split():
    """capture's start-up barrier still waits for detection (its status says so) while this launcher sees
    detection up: the two hosts' sessions do not reach each other, named before capture even starts."""
    def health(_t):
        return {"capture": _Health(True, _status("capture", topics={"t/capture/frame": _out(0.0, 0)},
                                                 waiting_for=["detection"])),
                "detection": _Health(True, _status("detection", topics={"t/capture/frame": _in(0.0, 0)}))}

    [(t, _level, line)] = _run(_watch("robot", peer_mode=True), health, 10)
    assert t == 3 and "capture does not see detection, which this launcher sees" in line


def test_a_host_never_heard_from_is_named():
    def health(_t):
        return {"detection": _Health(True, _status("detection", topics={"t/capture/frame": _in(0.0, 0)}))}

    [(t, _level, line)] = _run(_watch("gpu"), health, 12)
    assert t == 8  # unseen for 5 s, then held 3 s
    assert line.startswith("no status from capture (host robot) in 5 s, so this host's nodes are cut off from them: "
                           "is `followbus launch GRAPH --host robot` running")


def test_published_keys_are_read_from_the_nodes_statuses(port):
    sender = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    receiver = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    keys = PublishedKeys(receiver, "t")
    pub = Publisher(sender, "t/@status/capture", "capture", congestion="drop")
    try:
        assert wait_until(lambda: pub.listened, 5)
        pub.put(_status("capture", topics={"t/capture/frame": _out(30.0, 10, 921_600),
                                           "t/capture/preview": _out(30.0, 10, 8_000),
                                           "t/ack/ack": _in(30.0, 10)}))
        assert keys.wait(5)
        assert wait_until(lambda: len(keys.announced()) == 2, 5)
        frame = keys.announced()["t/capture/frame"]
        assert (frame.node, frame.rate_hz, frame.mean_bytes) == ("capture", 30.0, 921_600)
        assert "t/ack/ack" not in keys.announced()  # an input is not what the node publishes
    finally:
        keys.close()
        pub.undeclare()
        time.sleep(0.1)
        receiver.close()
        sender.close()


def test_published_keys_name_the_nodes_up_whose_status_has_not_come(port):
    """A node's liveliness token without its status (a link too full for it): named, so a tool listing the keys it
    knows can say whose keys it is missing; a recorder's token is not a node's."""
    sender = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    receiver = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    tokens = [sender.liveliness().declare_token(f"t/@health/{name}") for name in ("capture", "motor", RECORDER_NAME)]
    keys = PublishedKeys(receiver, "t")
    pub = Publisher(sender, "t/@status/capture", "capture", congestion="drop")
    try:
        assert wait_until(lambda: keys.unannounced() == ["capture", "motor"], 5), keys.unannounced()
        assert wait_until(lambda: pub.listened, 5)
        pub.put(_status("capture", topics={"t/capture/preview": _out(30.0, 10, 8_000)}))
        assert wait_until(lambda: keys.unannounced() == ["motor"], 5), keys.unannounced()
        tokens.pop(1).undeclare()  # the motor went down: no longer missing
        assert wait_until(lambda: keys.unannounced() == [], 5), keys.unannounced()
    finally:
        keys.close()
        pub.undeclare()
        for token in tokens:
            token.undeclare()
        time.sleep(0.1)
        receiver.close()
        sender.close()
