"""Zenoh session factory from graph.yaml's ``zenoh:`` block.

Default: peer mode on loopback with multicast scouting off. Every peer tries to listen on the
well-known endpoint (the first one wins) plus an ephemeral loopback port, and connects to the
well-known endpoint; gossip then tells peers about each other so they form a direct mesh that
survives whichever process held the well-known port going away.

Exposure: with no ``transport/auth`` settings every local process is trusted (anyone on the machine can
publish actuator commands or declare health tokens); that is acceptable only on loopback, so a session
listening on any other address without authentication is logged loudly (:func:`exposure`).
"""

from __future__ import annotations

import ctypes
import dataclasses
import ipaddress
import json
import logging
import math
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh

log = logging.getLogger(__name__)

DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
MODES = ("peer", "client", "router")


@dataclass
class ZenohSettings:
    """What graph.yaml's ``zenoh:`` block may say (all optional)."""

    mode: str = "peer"
    listen: list[str] = field(default_factory=lambda: [DEFAULT_ENDPOINT])
    connect: list[str] = field(default_factory=lambda: [DEFAULT_ENDPOINT])
    multicast_scouting: bool = False
    shm: bool = True
    # Large arrays between followbus processes on this machine in sealed shared memory, a descriptor over Zenoh
    # (bus/shmlane.py). Opt-in: end to end it saves nothing measurable at the shipped resolution (BENCHMARKS.md).
    shm_lane: bool = False
    connect_timeout_ms: int = 10_000  # a client keeps retrying its endpoints this long before failing
    # Raw json5 overrides applied last, e.g. {"access_control": {...}, "transport/link/tls": {...}}.
    config: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> ZenohSettings:
        data = dict(data or {})
        unknown = set(data) - {"mode", "listen", "connect", "multicast_scouting", "shm", "shm_lane",
                               "connect_timeout_ms", "config"}
        if unknown:
            raise ValueError(f"unknown zenoh key(s): {', '.join(sorted(unknown))}")
        settings = cls(**data)
        settings.check()
        return settings

    def check(self) -> None:
        """Raise ValueError (one line) unless a session could be opened with these settings: types, endpoints,
        and the config Zenoh itself builds from them (unknown or mistyped ``config`` keys)."""
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, not {self.mode!r}")
        for key in ("listen", "connect"):
            value = getattr(self, key)
            if not isinstance(value, list) or not all(isinstance(ep, str) for ep in value):
                raise ValueError(f"{key} must be a list of endpoints like {DEFAULT_ENDPOINT}, not {value!r}")
            for endpoint in value:
                check_endpoint(endpoint, listening=key == "listen")
        for key in ("multicast_scouting", "shm", "shm_lane"):
            if not isinstance(getattr(self, key), bool):
                raise ValueError(f"{key} must be true or false, not {getattr(self, key)!r}")
        timeout = self.connect_timeout_ms
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not math.isfinite(timeout) \
                or timeout <= 0:
            raise ValueError(f"connect_timeout_ms must be a finite number > 0, not {timeout!r}")
        if not isinstance(self.config, dict):
            raise ValueError(f"config must be a mapping of zenoh json5 keys, not {self.config!r}")
        try:
            build_config(self, remote_links=False)  # checked on any machine: its interfaces are not the robot's
        except zenoh.ZError as exc:
            raise ValueError(zenoh_error_text(exc)) from None

    def as_client(self, connect: list[str] | None = None) -> ZenohSettings:
        """The same network, joined as a client (tools that only watch: monitor, echo, record)."""
        return ZenohSettings(
            mode="client",
            listen=[],
            connect=list(connect or self.connect or self.listen),
            multicast_scouting=False,
            shm=self.shm,
            shm_lane=self.shm_lane,
            connect_timeout_ms=self.connect_timeout_ms,
            config=dict(self.config),
        )

    def as_launched_node(self) -> ZenohSettings:
        """A node the launcher started, on a router graph with access control (graph.robot.yaml): a client of the
        launcher's session, the hub, which holds every listen endpoint and enforces the access control for every
        link from outside. A client, not a router: a router holds every subscription declared anywhere on the bus
        (a read-only laptop declaring thousands would grow every node and keep its routing busy), a client only
        those matching what it publishes. Its messages go through the hub either way (the nodes listen nowhere).
        The node's own copy of the rules goes (a client leaves it out anyway, build_config): user/password
        authentication is one-way, so on the node's side the hub's link carries no user name."""
        if self.mode != "router" or "access_control" not in self.config:
            return self
        config = {k: v for k, v in self.config.items() if k != "access_control"}
        return dataclasses.replace(self, mode="client", listen=[], connect=list(self.connect or self.listen),
                                   config=config)


_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def check_endpoint(endpoint: str, listening: bool) -> None:
    """Raise ValueError unless an IP endpoint (``tcp/host:port``) has a valid address and port: Zenoh accepts
    ``tcp/999.1.1.1:99999`` in a config and only fails when it opens (a listener after a long timeout)."""
    proto, sep, address = endpoint.partition("/")
    if not sep or not proto or not address:
        raise ValueError(f"endpoint {endpoint!r} must look like <protocol>/<address>, e.g. {DEFAULT_ENDPOINT}")
    if proto not in _IP_PROTOCOLS:
        return  # unixsock-stream/..., serial/...: Zenoh's own config check below
    host, colon, port = address.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    if not colon or not port.isdigit() or not (0 if listening else 1) <= int(port) <= 65535:
        raise ValueError(f"endpoint {endpoint!r}: the port must be a number in {0 if listening else 1}..65535")
    host = host.strip("[]")
    if re.fullmatch(r"[0-9.]+", host) or ":" in host:  # an IP address, not a host name
        try:
            ipaddress.ip_address(host)
        except ValueError:
            raise ValueError(f"endpoint {endpoint!r}: {host!r} is not an IP address") from None
    elif not re.fullmatch(r"[A-Za-z0-9]([A-Za-z0-9\-.]*[A-Za-z0-9])?", host):
        raise ValueError(f"endpoint {endpoint!r}: {host!r} is not a host name or an IP address")


def zenoh_error_text(exc: Exception) -> str:
    """Zenoh's config error without its Rust debug wrapping: ``Json5Err(Message { msg: "unknown field ..." })``
    → ``unknown field ...``."""
    text = str(exc)
    match = re.search(r'msg: "((?:[^"\\]|\\.)*)"', text) or re.search(r'Str\("((?:[^"\\]|\\.)*)"\)', text)
    detail = match.group(1).replace('\\"', '"') if match else text.split(" at /", 1)[0]
    return f"config: {detail}"


def build_config(settings: ZenohSettings, remote_links: bool = True) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    listen = list(settings.listen)
    if remote_links and settings.mode != "client":
        from .netif import small_send_buffers

        listen = small_send_buffers(listen)  # a full slow link holds a write to it briefly (bus/netif.py)
    if settings.mode == "peer":
        # An ephemeral loopback port so other peers can reach us directly even when the well-known
        # port is held by someone else.
        listen.append("tcp/127.0.0.1:0")
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.mode != "client":
        conf.insert_json5("listen/exit_on_failure", "false")
        conf.insert_json5("connect/exit_on_failure", "false")
    else:
        conf.insert_json5("connect/timeout_ms", json.dumps(settings.connect_timeout_ms))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(settings.shm))
    if remote_links and settings.mode != "client":
        _protect_remote_links(conf, settings)
    for key, value in settings.config.items():
        if settings.mode == "client" and key.startswith("access_control"):
            # The router it joins enforces the graph's rules; a client's own allow-list would judge the router's
            # link, which presents no user name, and refuse everything (a compute host joining the robot graph).
            continue
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:  # name the key: Zenoh's own message may not
            raise zenoh.ZError(f"{key}: {zenoh_error_text(exc).removeprefix('config: ')}") from None
    return conf


def _protect_remote_links(conf: zenoh.Config, settings: ZenohSettings) -> None:
    """What this session sends to other machines is DROP (large messages BLOCK_FIRST), and its real_time queue
    holds more: a laptop on a slow link never blocks the robot, and still gets the commands (bus/netif.py). A
    graph's own ``qos`` or queue settings win."""
    from .netif import drop_on_remote_links, remote_queue_config

    if not any(k.startswith("qos") for k in settings.config):
        overwrite = drop_on_remote_links(list(settings.listen))
        if overwrite:
            conf.insert_json5("qos/network", json.dumps(overwrite))
    for key, value in remote_queue_config(list(settings.listen)).items():
        if key not in settings.config:
            conf.insert_json5(key, json.dumps(value))


def is_local_endpoint(endpoint: str) -> bool:
    """Whether only processes on this machine can reach an endpoint (loopback IP, or a Unix socket)."""
    proto, _, address = endpoint.partition("/")
    if proto.startswith("unixsock"):
        return True
    host = address.split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def _has_auth(config: dict[str, Any]) -> bool:
    """Whether the raw overrides authenticate peers (user/password, public keys, or mutual TLS)."""
    for key, value in config.items():
        if key.startswith("transport/auth") or (key == "transport/link/tls/enable_mtls" and value is True):
            return True
        if isinstance(value, dict) and ((key == "transport" and "auth" in value)
                                        or (key == "transport/link/tls" and value.get("enable_mtls") is True)):
            return True
    return False


def exposure(settings: ZenohSettings) -> str | None:
    """Why other machines could write on this bus unauthenticated, or None (client, loopback only, or auth)."""
    if settings.mode == "client" or _has_auth(settings.config):
        return None
    reachable = [ep for ep in settings.listen if not is_local_endpoint(ep)]
    if not reachable:
        return None
    return (f"listening on {', '.join(reachable)} without authentication: anyone who can reach it can publish "
            "on the bus (actuator commands included) and fake node health; add transport/auth/usrpwd to the zenoh "
            "config (docs/security.md)")


def open_session(settings: ZenohSettings | None = None) -> zenoh.Session:
    """Open a Zenoh session. With shared memory on, a session Zenoh cannot give shared memory (/dev/shm full:
    "Unable to create POSIX shm segment") opens without it, with a warning: a node that crash-loops at start
    because something else filled /dev/shm would stop the robot for nothing."""
    settings = settings or ZenohSettings()
    warning = exposure(settings)
    if warning:
        log.warning("zenoh: %s", warning)
    log.debug("opening zenoh session: mode=%s listen=%s connect=%s", settings.mode, settings.listen,
              settings.connect)
    try:
        return zenoh.open(build_config(settings))
    except zenoh.ZError as exc:
        if not settings.shm or "shm" not in str(exc).lower():
            raise
        log.warning("zenoh: shared memory unavailable (%s); opening the session without it", exc)
        return zenoh.open(build_config(dataclasses.replace(settings, shm=False)))


# --- memory a departed session leaves behind -----------------------------------------------------------------

TRIM_DELAY_S = 1.0  # after the last session left: one trim for a burst of departures


class MemoryTrim:
    """Hands the heap freed by departed sessions back to the system (glibc ``malloc_trim``).

    A session that declared thousands of subscribers costs a router about 1.5 KB of routing state each; Zenoh frees
    it when the session leaves, but glibc keeps freed memory in its per-thread arenas, so the router's RSS would
    stay up for good. A trim on a timer thread, TRIM_DELAY_S after the last departure, returns it (docs/security.md,
    "Subscribers"; `followbus bench flood`). Nothing happens where the C library has no ``malloc_trim`` (musl)."""

    def __init__(self, session: zenoh.Session):
        self._trim = getattr(ctypes.CDLL(None), "malloc_trim", None)
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self.trims = 0
        self._listener = (session.info.declare_transport_events_listener(self._on_event, history=False)
                          if self._trim is not None else None)

    def _on_event(self, event: Any) -> None:
        if event.kind != zenoh.SampleKind.DELETE:
            return
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
            self._timer = threading.Timer(TRIM_DELAY_S, self.trim)
            self._timer.daemon = True
            self._timer.start()

    def trim(self) -> None:
        if self._trim is None:
            return
        start = time.perf_counter()
        self._trim(0)
        self.trims += 1
        log.debug("malloc_trim after a session left: %.1f ms", (time.perf_counter() - start) * 1e3)

    def close(self) -> None:
        with self._lock:
            if self._timer is not None:
                self._timer.cancel()
        if self._listener is not None:
            try:
                self._listener.undeclare()
            except Exception as exc:  # a session already closed
                log.debug("transport events listener: %r", exc)
