"""Links to other machines never block the robot: Zenoh QoS overwrite on the interfaces a session listens on
beyond loopback.

Most followbus outputs are published with congestion control BLOCK (a node waits rather than lose a message
to the next node on the robot). A router forwards each message on the thread that received it, so a BLOCK
message routed to a laptop on a slow link (its TCP send queue full) stalls that thread, and with it every
node behind it: with a laptop recording every key over 2 Mbit/s, the robot answers almost no frame
(`followbus bench link`, BENCHMARKS.md). Zenoh's ``qos/network`` overwrite turns the messages *sent* (egress) on chosen
interfaces into congestion control DROP: the laptop loses what its link cannot carry (its recorder reports
the ``header.seq`` gaps), the robot's loop on loopback keeps BLOCK.

Large messages (raw frames) on those interfaces are BLOCK_FIRST at priority ``data_low`` instead. Under plain
DROP a link slower than the camera gets none of them: a 921 KB frame is hundreds of batches, and once the link's
queue is full the rest of its fragments are dropped after the drop wait, so no frame arrives whole while the
fragments that did go out fill the link. With BLOCK_FIRST one large message per link and priority is in flight
at a time, pushed on a thread of Zenoh's own (the router's thread does not wait for it); those that come while
it is in flight are dropped, so the receiver gets whole frames as fast as its link carries them, each the newest
there was when the link was free (`followbus bench link`, BENCHMARKS.md). ``background`` keeps them behind
everything else in Zenoh's queues, and keeps that queue theirs alone: with previews beside them at ``data_low``,
the robot answered 1 frame in 30 while a laptop pulled raw frames.

Bulky messages (previews, from 4 KB) are DROP at ``data_low``: the small messages (states, statuses) go first, the
views take what the link has left. At one priority a link too slow for the previews lost the small messages with
them (1.2 of 30 a second at 2 Mbit/s while a laptop pulled raw frames; 30.1 now).

Two settings keep the small messages flowing while a slow link is full. A remote listen endpoint gets a small
kernel send buffer (``#so_sndbuf``): Zenoh writes one batch at a time into the socket, and with the kernel's
default (grown to megabytes) a full link holds that write, and every queue behind it, for seconds; and the
``real_time`` queue (actuator commands, sent express: a batch each) holds more batches, so the commands that come
while one write waits are queued, not dropped. Batches are allocated as they are needed: a link that never
backs up never holds more.

The interfaces are those of the listen endpoints that are not loopback: the one holding the address, or every
interface but loopback for ``0.0.0.0``/``[::]``. IPv4 addresses are looked up with SIOCGIFADDR; an IPv6 address
or a host name cannot be, and is logged (set ``qos/network`` in the graph's zenoh config by hand then).
"""

from __future__ import annotations

import contextlib
import fcntl
import ipaddress
import logging
import socket
import struct
from typing import Any

log = logging.getLogger(__name__)

SIOCGIFADDR = 0x8915
QOS_ID = "followbus-remote-links-drop"
BULK_QOS_ID = "followbus-remote-links-bulk"
LARGE_QOS_ID = "followbus-remote-links-large"
# The kernel send buffer of a remote listen endpoint's links (Linux doubles it): about 0.5 s at 2 Mbit/s, and still
# 1 Gbit/s at 1 ms round trip.
REMOTE_SNDBUF_BYTES = 64 * 1024
# Batches of a link's real_time queue (Zenoh's default: 2): 0.5 s of 30 Hz express commands.
REALTIME_QUEUE_BATCHES = 16
REALTIME_QUEUE_KEY = "transport/link/tx/queue/size/real_time"
# Messages from this size up are "large" on a remote link (BLOCK_FIRST, background): the size from which a
# publisher uses shared memory (bus/pubsub.py SHM_THRESHOLD_BYTES), far above a preview JPEG (a few KB), far
# below a raw 320x240 frame (230 KB).
LARGE_MESSAGE_BYTES = 64 * 1024
# Messages from this size up are "bulk" on a remote link (DROP at data_low): a preview JPEG (8.6 KB) waits behind
# the small messages (states, statuses: under 2 KB).
BULK_MESSAGE_BYTES = 4 * 1024
ANY = {"0.0.0.0", "::", ""}


def _endpoint_host(endpoint: str) -> str | None:
    proto, _, address = endpoint.partition("/")
    if proto not in ("tcp", "tls", "udp", "quic", "ws"):
        return None
    return address.split("#", 1)[0].split("?", 1)[0].rpartition(":")[0].strip("[]")


def _ipv4_of(name: str) -> str | None:
    with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        packed = fcntl.ioctl(s.fileno(), SIOCGIFADDR, struct.pack("256s", name.encode()[:15]))
        return socket.inet_ntoa(packed[20:24])
    return None


def remote_interfaces(listen: list[str]) -> list[str]:
    """The network interfaces (not loopback) that the listen endpoints are reachable on."""
    names = [name for _, name in socket.if_nameindex() if name != "lo"]
    found: list[str] = []
    for endpoint in listen:
        host = _endpoint_host(endpoint)
        if host is None:
            continue
        if host in ANY:
            found += names
            continue
        try:
            ip = ipaddress.ip_address(host)
        except ValueError:
            log.warning("zenoh: cannot tell the interface of %s (a host name): its links may block", endpoint)
            continue
        if ip.is_loopback:
            continue
        owner = [name for name in names if _ipv4_of(name) == host]
        if not owner:
            log.warning("zenoh: no interface holds %s (or it is IPv6): links through it may block", host)
        found += owner
    return list(dict.fromkeys(found))


def drop_on_remote_links(listen: list[str]) -> list[dict[str, Any]]:
    """The ``qos/network`` items that make every put and delete sent over a remote interface DROP, puts of
    :data:`BULK_MESSAGE_BYTES` and more DROP at ``data_low``, and puts of :data:`LARGE_MESSAGE_BYTES` and more
    BLOCK_FIRST at ``background`` ([] when the session listens on loopback only). Zenoh applies the items in order:
    each overwrites the ones before it for the larger puts."""
    interfaces = remote_interfaces(listen)
    if not interfaces:
        return []
    return [{"id": QOS_ID, "interfaces": interfaces, "messages": ["put", "delete"], "flows": ["egress"],
             "overwrite": {"congestion_control": "drop"}},
            {"id": BULK_QOS_ID, "interfaces": interfaces, "messages": ["put"], "flows": ["egress"],
             "payload_size": f"{BULK_MESSAGE_BYTES}..", "overwrite": {"congestion_control": "drop",
                                                                      "priority": "data_low"}},
            {"id": LARGE_QOS_ID, "interfaces": interfaces, "messages": ["put"], "flows": ["egress"],
             "payload_size": f"{LARGE_MESSAGE_BYTES}..",
             "overwrite": {"congestion_control": "block_first", "priority": "background"}}]


def small_send_buffers(listen: list[str]) -> list[str]:
    """The listen endpoints, each TCP or TLS one beyond loopback with ``#so_sndbuf`` (unless it sets its own link
    options after ``#``)."""
    out = []
    for endpoint in listen:
        host = _endpoint_host(endpoint)
        remote = host is not None and (host in ANY or not _is_loopback(host))
        if remote and endpoint.split("/", 1)[0] in ("tcp", "tls") and "#" not in endpoint:
            endpoint = f"{endpoint}#so_sndbuf={REMOTE_SNDBUF_BYTES}"
        out.append(endpoint)
    return out


def remote_queue_config(listen: list[str]) -> dict[str, Any]:
    """The queue settings of a session that listens beyond loopback ({} when it listens on loopback only)."""
    return {REALTIME_QUEUE_KEY: REALTIME_QUEUE_BATCHES} if remote_interfaces(listen) else {}


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"
