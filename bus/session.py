"""Zenoh session factory from graph.yaml's ``zenoh:`` block.

Default: peer mode on loopback with multicast scouting off. Every peer tries to listen on the
well-known endpoint (the first one wins) plus an ephemeral loopback port, and connects to the
well-known endpoint; gossip then tells peers about each other so they form a direct mesh that
survives whichever process held the well-known port going away.

Exposure: with no ``transport/auth`` settings every local process is trusted (anyone on the machine can
publish motor commands or declare health tokens); that is acceptable only on loopback, so a session
listening on any other address without authentication is logged loudly (:func:`exposure`).
"""

from __future__ import annotations

import ipaddress
import json
import logging
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
    # Large arrays between processes on this machine in followbus's own shared memory, a descriptor over
    # Zenoh (bus/shmlane.py): used only while every subscriber of the key is a followbus one on this host.
    shm_lane: bool = True
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
        if settings.mode not in MODES:
            raise ValueError(f"zenoh mode must be one of {MODES}, not {settings.mode!r}")
        return settings

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


def build_config(settings: ZenohSettings) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    listen = list(settings.listen)
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
    if settings.mode != "client" and not any(k.startswith("qos") for k in settings.config):
        # What this session sends to other machines is DROP: a laptop on a slow link never blocks the robot.
        from .netif import drop_on_remote_links

        overwrite = drop_on_remote_links(list(settings.listen))
        if overwrite:
            conf.insert_json5("qos/network", json.dumps(overwrite))
    for key, value in settings.config.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


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
            "on the bus (motor commands included) and fake node health; add transport/auth/usrpwd to the zenoh "
            "config (README, Security)")


def open_session(settings: ZenohSettings | None = None) -> zenoh.Session:
    settings = settings or ZenohSettings()
    warning = exposure(settings)
    if warning:
        log.warning("zenoh: %s", warning)
    log.debug("opening zenoh session: mode=%s listen=%s connect=%s", settings.mode, settings.listen,
              settings.connect)
    return zenoh.open(build_config(settings))
