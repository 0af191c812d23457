"""Links to other machines never block the robot: Zenoh QoS overwrite on the interfaces a session listens on
beyond loopback.

Most followbus outputs are published with congestion control BLOCK (a node waits rather than lose a message
to the next node on the robot). A router forwards each message on the thread that received it, so a BLOCK
message routed to a laptop on a slow link (its TCP send queue full) stalls that thread, and with it every
node behind it: measured with a laptop recording every key over 2 Mbit/s, the robot answered 0 of 89 frames
(BENCHMARKS.md, bench link). Zenoh's ``qos/network`` overwrite turns the messages *sent* (egress) on chosen
interfaces into congestion control DROP: the laptop loses what its link cannot carry (its recorder reports
the ``header.seq`` gaps), the robot's loop on loopback keeps BLOCK.

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
    """The ``qos/network`` items that make every put and delete sent over a remote interface DROP ([] when the
    session listens on loopback only)."""
    interfaces = remote_interfaces(listen)
    if not interfaces:
        return []
    return [{"id": QOS_ID, "interfaces": interfaces, "messages": ["put", "delete"], "flows": ["egress"],
             "overwrite": {"congestion_control": "drop"}}]
