"""Joining a running graph from a tool (topics, echo, hz, nodes, monitor, ...), with one line when it fails.

zenoh-python 1.10 raises the same ``zenoh.ZError: Unable to connect to any of [...]. Timeout!`` whether
nothing listens on the endpoint or the router refused our credentials (it closes the link in answer to
the handshake, and retries go on until ``connect/timeout_ms``). A plain TCP connection to the endpoint
tells the two apart: accepted means something listens there, so the zenoh handshake itself was refused.
A TLS handshake of our own (Python's ssl, with the CA the session would use) then tells a TLS failure (no CA,
a CA that did not sign the robot's certificate, ``tcp/`` to a TLS port, ``tls/`` to a plain one) from a refused
password.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import ssl
from typing import Any

import zenoh

from ..bus.session import ZenohSettings, open_session

log = logging.getLogger(__name__)

PROBE_TIMEOUT_S = 0.5
TCP_BASED = ("tcp", "tls", "ws")  # link protocols whose endpoint a TCP connection can probe


class BusUnreachable(Exception):
    """No session could be opened on the given endpoints; the message says why and what to do."""


def auth_user(config: dict[str, Any]) -> str | None:
    """The user name the session authenticates with (``transport/auth/usrpwd``), if any."""
    value = config.get("transport/auth/usrpwd")
    if value is None:
        value = ((config.get("transport") or {}).get("auth") or {}).get("usrpwd")
    if isinstance(value, dict) and value.get("user"):
        return str(value["user"])
    return None


def _host_port(endpoint: str) -> tuple[str, int] | None:
    proto, _, address = endpoint.partition("/")
    if proto not in TCP_BASED:
        return None
    address = address.split("#", 1)[0].split("?", 1)[0]
    host, _, port = address.rpartition(":")
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        return None


def endpoint_listening(endpoint: str, timeout_s: float = PROBE_TIMEOUT_S) -> bool | None:
    """Whether something accepts TCP connections on ``endpoint`` (None: not a TCP-based endpoint)."""
    target = _host_port(endpoint)
    if target is None:
        return None
    try:
        with contextlib.closing(socket.create_connection(target, timeout=timeout_s)):
            return True
    except OSError:
        return False


def tls_ca(config: dict[str, Any]) -> str | None:
    """The CA certificate file a session verifies a tls/ endpoint with (``transport/link/tls/root_ca_certificate``)."""
    value = config.get("transport/link/tls/root_ca_certificate")
    if value is None:
        value = (config.get("transport/link/tls") or {}).get("root_ca_certificate")
    return str(value) if value else None


def _tls_handshake(host: str, port: int, context: ssl.SSLContext) -> None:
    with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S * 4) as raw, \
            context.wrap_socket(raw, server_hostname=host):
        pass


def _speaks_tls(host: str, port: int) -> bool:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE  # only: is it TLS at all?
    try:
        _tls_handshake(host, port, context)
        return True
    except ssl.SSLError as exc:
        return "CERTIFICATE_REQUIRED" in str(exc).upper()  # TLS, wanting a client certificate
    except OSError:
        return False


def tls_problem(endpoint: str, config: dict[str, Any]) -> str | None:
    """Why a session would fail the TLS handshake with a listening ``endpoint`` (None: no TLS problem found)."""
    target = _host_port(endpoint)
    if target is None:
        return None
    host, port = target
    if endpoint.startswith("tcp/"):
        if _speaks_tls(host, port):
            return (f"{endpoint} is a TLS port: connect with tls/{endpoint.partition('/')[2]} and the robot's CA "
                    "certificate (--ca FILE)")
        return None
    if not endpoint.startswith("tls/"):
        return None
    if not _speaks_tls(host, port):
        return f"TLS handshake with {endpoint} failed: it does not speak TLS (a tcp/ endpoint?)"
    ca = tls_ca(config)
    if ca is None:
        return f"TLS handshake with {endpoint} failed: no CA certificate to verify the robot's (pass --ca FILE)"
    try:
        context = ssl.create_default_context(cafile=ca)
    except (OSError, ssl.SSLError) as exc:
        return f"TLS: cannot use the CA certificate {ca}: {getattr(exc, 'strerror', None) or exc}"
    try:
        _tls_handshake(host, port, context)
    except ssl.SSLCertVerificationError as exc:
        return (f"TLS handshake with {endpoint} failed: {exc.verify_message} (is the robot's certificate signed "
                f"by {ca}, and for {host}?)")
    except ssl.SSLError as exc:
        if "CERTIFICATE_REQUIRED" in str(exc).upper():
            return f"TLS handshake with {endpoint} failed: the robot requires a client certificate (mutual TLS)"
        return f"TLS handshake with {endpoint} failed: {exc.reason or exc}"
    except OSError:
        return None
    return None


def explain_connect_failure(settings: ZenohSettings) -> str:
    """One line: nobody listens (no graph running), or the graph refused us (authentication, TLS)."""
    endpoints = list(settings.connect) or list(settings.listen)
    where = ", ".join(endpoints) or "(no endpoint)"
    probes = {ep: endpoint_listening(ep) for ep in endpoints}
    listening = [ep for ep, up in probes.items() if up]
    if not listening:
        if any(up is None for up in probes.values()):
            return f"could not connect to {where} within {settings.connect_timeout_ms / 1000:g} s"
        return (f"no graph is running on {where}: start one with `followbus launch` or `followbus router` "
                "(or join another with --connect tcp/HOST:PORT)")
    tls = tls_problem(listening[0], settings.config)
    if tls:
        return tls
    user = auth_user(settings.config)
    if user:
        return f"authentication failed for user {user} on {listening[0]} (wrong or missing password)"
    if listening[0].startswith("tls/"):
        return (f"{listening[0]} refused the connection after the TLS handshake: the graph requires a user "
                "(--user, --password)")
    return (f"{listening[0]} refused the connection: the graph requires authentication "
            "(--user and --password, or $FOLLOWBUS_ZENOH_PASSWORD)")


def is_connect_failure(exc: BaseException) -> bool:
    return isinstance(exc, zenoh.ZError) and "Unable to connect" in str(exc)


def check_credentials(settings: ZenohSettings) -> None:
    """When something listens on the endpoints, join once and leave: raises :class:`BusUnreachable` when the
    graph refuses us (a wrong or missing password), instead of a monitor that only ever says "unreachable".
    A graph that is not up (yet) is left to the caller, who may wait for it."""
    if not any(endpoint_listening(ep) for ep in settings.connect):
        return
    open_client_session(settings).close()


def open_client_session(settings: ZenohSettings) -> zenoh.Session:
    """open_session, with a failure to join turned into :class:`BusUnreachable` (its message one line)."""
    try:
        return open_session(settings)
    except zenoh.ZError as exc:
        if not is_connect_failure(exc):
            raise
        log.debug("zenoh: %s", exc)
        raise BusUnreachable(explain_connect_failure(settings)) from exc
