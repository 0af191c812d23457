"""Zenoh session factory from graph.yaml's ``zenoh:`` block.

Default: peer mode on loopback with multicast scouting off. Every peer tries to listen on the
well-known endpoint (the first one wins) plus an ephemeral loopback port, and connects to the
well-known endpoint; gossip then tells peers about each other so they form a direct mesh that
survives whichever process held the well-known port going away.
"""

from __future__ import annotations

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
    connect_timeout_ms: int = 10_000  # a client keeps retrying its endpoints this long before failing
    # Raw json5 overrides applied last, e.g. {"access_control": {...}, "transport/link/tls": {...}}.
    config: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> ZenohSettings:
        data = dict(data or {})
        unknown = set(data) - {"mode", "listen", "connect", "multicast_scouting", "shm", "connect_timeout_ms", "config"}
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
    for key, value in settings.config.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def open_session(settings: ZenohSettings | None = None) -> zenoh.Session:
    settings = settings or ZenohSettings()
    log.debug("opening zenoh session: mode=%s listen=%s connect=%s", settings.mode, settings.listen,
              settings.connect)
    return zenoh.open(build_config(settings))
