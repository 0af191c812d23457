"""A laptop on a 2 Mbit/s link (its own network namespace and /dev/shm; tools/bench/netns.py) against the robot
graph as `monitor`: echo, hz, topics, nodes and record work; topics and record (without the graph file, as on a
laptop) subscribe key by key to what the nodes announce, leaving the raw frames out, and topics names them and
prints the publisher's rate; with raw frames asked for (far more than the link carries) the robot keeps answering
frames, since what it sends over a remote interface is DROP (bus/netif.py; as BLOCK the robot answered none), and
the recording reports what it lost per key; a plain subscriber to the frame key gets whole frames (BLOCK_FIRST:
under DROP not one arrived). The figures are `followbus bench link`'s (BENCHMARKS.md); this checks the behaviour."""

from __future__ import annotations

import json
import re
import socket
import subprocess
from pathlib import Path

import pytest

from followbus.bus.netif import (
    BULK_MESSAGE_BYTES,
    BULK_QOS_ID,
    LARGE_MESSAGE_BYTES,
    LARGE_QOS_ID,
    QOS_ID,
    REALTIME_QUEUE_KEY,
    REMOTE_SNDBUF_BYTES,
    _ipv4_of,
    drop_on_remote_links,
    remote_interfaces,
    remote_queue_config,
    small_send_buffers,
)
from followbus.bus.recording import read_metadata
from followbus.tools.bench.link import LinkBench
from followbus.tools.bench.netns import NetnsPair, netns_unavailable

from .conftest import followbus_argv, free_port

REASON = netns_unavailable()


def test_remote_links_are_the_listen_interfaces_beyond_loopback():
    assert remote_interfaces(["tcp/127.0.0.1:7447", "unixsock-stream//tmp/x"]) == []
    assert drop_on_remote_links(["tcp/127.0.0.1:7447"]) == []
    others = [name for _, name in socket.if_nameindex() if name != "lo"]
    assert remote_interfaces(["tcp/0.0.0.0:7447"]) == others
    with_ip = [(name, ip) for name in others if (ip := _ipv4_of(name))]
    if with_ip:
        name, ip = with_ip[0]
        item, bulk, large = drop_on_remote_links(["tcp/127.0.0.1:1", f"tcp/{ip}:7447"])
        assert item["id"] == QOS_ID and item["interfaces"] == [name] and item["flows"] == ["egress"]
        assert item["overwrite"] == {"congestion_control": "drop"}
        # Applied after it: bulky puts (previews) behind the small ones, and large puts (raw frames) keep one in
        # flight per link, in a queue of their own, instead of losing every one.
        assert bulk["id"] == BULK_QOS_ID and bulk["payload_size"] == f"{BULK_MESSAGE_BYTES}.."
        assert bulk["overwrite"] == {"congestion_control": "drop", "priority": "data_low"}
        assert large["id"] == LARGE_QOS_ID and large["interfaces"] == [name] and large["flows"] == ["egress"]
        assert large["payload_size"] == f"{LARGE_MESSAGE_BYTES}.." and large["messages"] == ["put"]
        assert large["overwrite"] == {"congestion_control": "block_first", "priority": "background"}
        assert remote_queue_config([f"tcp/{ip}:7447"]) == {REALTIME_QUEUE_KEY: 16}


def test_remote_listen_endpoints_get_a_small_send_buffer():
    assert remote_queue_config(["tcp/127.0.0.1:7447"]) == {}
    assert small_send_buffers(["tcp/127.0.0.1:7447", "tcp/192.0.2.1:7447", "tls/0.0.0.0:7447",
                               "tcp/192.0.2.1:7448#iface=eth0", "udp/192.0.2.1:7449"]) == [
        "tcp/127.0.0.1:7447", f"tcp/192.0.2.1:7447#so_sndbuf={REMOTE_SNDBUF_BYTES}",
        f"tls/0.0.0.0:7447#so_sndbuf={REMOTE_SNDBUF_BYTES}", "tcp/192.0.2.1:7448#iface=eth0", "udp/192.0.2.1:7449"]


def _laptop_tools(bench: LinkBench, tmp: Path) -> dict[str, tuple[int, str]]:
    """echo, hz, topics, nodes and record from the laptop's namespace (its own /dev/shm) as `monitor`, side by side,
    from a directory without a graph file (a laptop without the robot's checkout)."""
    join = ["--connect", bench.endpoint, "--user", "monitor", "--namespace", "link"]
    commands = {"echo": ["echo", "link/prediction/track", "-n", "2", "--timeout", "20"],
                "hz": ["hz", "link/capture/preview", "--seconds", "3"], "topics": ["topics", "--seconds", "3"],
                "nodes": ["nodes"], "record": ["record", "-o", str(tmp / "laptop.mcap"), "--duration", "8"]}
    procs = {name: subprocess.Popen(bench.pair.argv(1, followbus_argv(*argv, *join)), env=bench.env,
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                    stdin=subprocess.DEVNULL, cwd=tmp)
             for name, argv in commands.items()}
    return {name: (proc.wait(90), proc.stdout.read()) for name, proc in procs.items()}


def _topics_rows(text: str) -> dict[str, list[str]]:
    return {line.split()[0]: line.split() for line in text.splitlines() if line.startswith("link/")}


@pytest.mark.slow
@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_laptop_recording_over_2mbit_never_stops_the_robot(tmp_path):
    laptop_dir = tmp_path / "laptop"
    laptop_dir.mkdir()
    with NetnsPair(rate_mbit=2.0) as pair:
        # The laptop at nice 10, not the bench's 19: beside two burners and another test worker a nice-19 recorder
        # got so little CPU that it never wrote its file, and the test had nothing to count.
        bench = LinkBench(pair, tmp_path, free_port(), "simulated", laptop_nice=10)
        try:
            bench.start()
            tools = _laptop_tools(bench, laptop_dir)
            everything = bench.run_case("record-all", 20.0, until_answered=True)
            default = bench.run_case("record", 2.0)
            frames = bench.run_case("frames", 10.0)
        finally:
            bench.close()
    assert all(status == 0 for status, _ in tools.values()), tools
    tracks = [line for line in tools["echo"][1].splitlines() if line.startswith("link/prediction/track: ")]
    assert len(tracks) == 2 and "link/capture/preview:" in tools["hz"][1]
    assert "motor" in tools["nodes"][1]
    # topics over the link: key by key what the nodes announce, the raw frames left out and named (subscribing to
    # them as well, it printed 1.4 Hz for the 30 Hz command); the rate is the publisher's (header.seq, pub_ns).
    topics = tools["topics"][1]
    rows = _topics_rows(topics)
    assert "link/capture/frame" not in rows and "not subscribed: link/capture/frame (raw frames, " in topics, topics
    # Five tools side by side ask for about three times what 2 Mbit/s carries, so not every node's messages (nor,
    # on a loaded machine, its status) cross in topics' window: a node missing from the table is named, never left
    # out in silence.
    for node in ("capture", "detection", "egomotion", "prediction", "reid", "template", "motor"):
        assert (any(key.startswith(f"link/{node}/") for key in rows) or f"nothing arrived: link/{node}/" in topics
                or re.search(rf"no status from [^\n]*\b{node}\b", topics)), (node, topics)
    # The publisher's rate (header.seq over pub_ns), not the link's: five tools ask for about three times what the
    # link carries, and the rate printed is above what arrived (30 against 16-19 Hz, or against 0.8 when a key's
    # messages came in one burst). A bound against capture's rate failed beside a second graph: on two overloaded
    # cores the tracks came late, and the motor rightly repeated stops at 10 Hz.
    rates = {key: (float(row[2]), float(row[3])) for key, row in rows.items() if row[2] != "-"}
    assert len(rates) >= 3 and any(rate > 1.3 * recv for rate, recv in rates.values()), topics
    # record without the graph file: the keys the nodes announce, one by one: the raw frames never crossed the link
    # and the rest arrived (pulling raw frames too, it held 1 preview in 22 s).
    assert "subscribing key by key to what the nodes announce" in tools["record"][1], tools["record"][1]
    stats = read_metadata(laptop_dir / "laptop.mcap")["recording_stats"]
    keys = json.loads(stats["keys"])
    assert "link/capture/frame" not in keys, keys
    assert keys["link/capture/preview"]["received"] > 8 * 5 and keys["link/motor/command"]["received"] > 8 * 5, keys
    # The robot (answering frames before: LinkBench.start) goes on answering while the laptop asks for ~27 MB/s
    # over 0.25 MB/s; with BLOCK on the laptop's link it answered none for 20 s windows, and stayed stalled after the
    # laptop left (BENCHMARKS.md). On a machine this loaded the robot alone has silent seconds: hence "within 20 s".
    assert everything.robot["answered"] > 0, everything.robot
    # What the link could not carry is counted per key (the previews between the raw frames by header.seq gaps).
    assert "keys" in everything.laptop, everything.laptop  # the laptop wrote its recording (exit, first lines)
    keys = everything.laptop["keys"]
    assert everything.laptop["seq_gaps"] == sum(k["seq_gaps"] for k in keys.values()) > 0, keys
    assert keys["link/capture/preview"]["seq_gaps"] > 0, keys
    assert default.laptop["first_lines"][0].startswith("remote link (tcp/") and \
        "leaving out raw frames (link/capture/frame" in default.laptop["first_lines"][0], default.laptop
    assert "link/capture/frame" not in default.laptop["keys"] and "link/capture/preview" in default.laptop["keys"]
    # A plain subscriber to the frame key gets whole frames, as many as the link carries (~0.27 a second at
    # 2 Mbit/s), and the commands still arrive beside them: under DROP not one frame arrived at 2, 20 or 50 Mbit/s.
    got = frames.laptop["keys"]
    assert got.get("link/capture/frame", {}).get("received", 0) >= 1, got
    assert got["link/motor/command"]["received"] > 0, got
