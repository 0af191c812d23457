"""Joining a running graph from a tool (topics, echo, hz, nodes, record, play, monitor, foxglove): one way to
build the client's settings and identity for every command (:func:`client_settings`), and one line when joining
fails.

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
import errno
import logging
import os
import secrets
import socket
import ssl
import sys
import time
from pathlib import Path
from typing import Any

import zenoh

from ..bus.session import ZenohSettings, is_local_endpoint, open_session

log = logging.getLogger(__name__)

PROBE_TIMEOUT_S = 0.5
PASSWORD_ENV = "FOLLOWBUS_ZENOH_PASSWORD"
USER_ENV = "FOLLOWBUS_ZENOH_USER"
VIEWER_CONNECT_TIMEOUT_MS = 3000  # monitor, foxglove: they retry by themselves, so fail fast on a refusal
PUBLISH_PROBE_S = 3.0  # how long `play` waits for its probe message to come back through the router
TCP_BASED = ("tcp", "tls", "ws")  # link protocols whose endpoint a TCP connection can probe
REMOTE_BATCH_BYTES = 8192  # a tool's link over a network: batches of this size (Zenoh's default 65535)


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


def endpoint_held_without_listener(endpoint: str) -> bool:
    """Whether a TCP ``endpoint`` of this machine cannot be listened on although nothing listens there: another
    process's connection holds its port (the kernel hands ports of its ephemeral range to outgoing connections).
    A graph whose peers meet on that port would never form: each node ends up alone."""
    target = _host_port(endpoint)
    if target is None or target[1] == 0:
        return False
    family = socket.AF_INET6 if ":" in target[0] else socket.AF_INET
    with contextlib.closing(socket.socket(family, socket.SOCK_STREAM)) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a listener binds: TIME_WAIT is no obstacle
        try:
            probe.bind(target)
        except OSError as exc:
            return exc.errno == errno.EADDRINUSE and not endpoint_listening(endpoint)
    return False


def ephemeral_port_range() -> tuple[int, int] | None:
    """The ports the kernel gives outgoing connections (Linux: ip_local_port_range); None when unknown."""
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return None


def tls_ca(config: dict[str, Any]) -> str | None:
    """The CA certificate file a session verifies a tls/ endpoint with (``transport/link/tls/root_ca_certificate``)."""
    value = config.get("transport/link/tls/root_ca_certificate")
    if value is None:
        value = (config.get("transport/link/tls") or {}).get("root_ca_certificate")
    return str(value) if value else None


CERT_DATE_ERRORS = (9, 10)  # X509_V_ERR_CERT_NOT_YET_VALID, X509_V_ERR_CERT_HAS_EXPIRED


def graph_tls_problem(settings: ZenohSettings) -> str | None:
    """Why the nodes of a graph would fail the TLS handshake with its endpoints that listen now (the launcher's own,
    or a router the graph joins), with the graph's own CA; None when none does (or none is TLS)."""
    for endpoint in settings.connect:
        if endpoint.startswith("tls/") and endpoint_listening(endpoint):
            problem = tls_problem(endpoint, settings.config)
            if problem:
                return problem
    return None


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
        if exc.verify_code in CERT_DATE_ERRORS:
            return (f"TLS handshake with {endpoint} failed: {exc.verify_message} (the robot's certificate is "
                    "outside its validity dates: renew it, or check this machine's clock)")
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


# --- the client's settings and identity ----------------------------------------------------------------

def _ask_password(user: str) -> str:
    """--user without a password: ask on a terminal; a script gets one line instead of a refused session."""
    from .errors import UsageError

    if not sys.stdin.isatty():
        raise UsageError(f"--user {user} needs a password: pass --password or set ${PASSWORD_ENV} "
                         "(or run in a terminal to be asked)")
    import getpass

    return getpass.getpass(f"zenoh password for {user}: ")


def _client_config(base: dict[str, Any], user: str | None, password: str | None, ca: str | None,
                   keep_identity: bool) -> dict[str, Any]:
    """The graph's zenoh config as a client uses it: never its access control (the router enforces that), its
    identity only when no other one is given (a tool on the robot itself), its link settings (TLS) always."""
    drop = ("access_control",) if keep_identity else ("access_control", "transport/auth")
    config = {k: v for k, v in base.items() if not k.startswith(drop)}
    if user:
        config["transport/auth/usrpwd"] = {"user": user, "password": password or ""}
    if ca:
        config["transport/link/tls/root_ca_certificate"] = ca
    return config


def client_settings(graph_path: str | None, connect: list[str] | None = None, user: str | None = None,
                    password: str | None = None, ca: str | None = None, *, viewer: bool = False,
                    connect_timeout_s: float | None = None) -> ZenohSettings:
    """How a tool joins a graph as a Zenoh client: ``connect`` (--connect) wins, else the graph's endpoints;
    identity from --user/--password ($FOLLOWBUS_ZENOH_USER / $FOLLOWBUS_ZENOH_PASSWORD; a terminal asks),
    else, without --connect, the graph's own; ``ca`` for a tls/ endpoint. ``viewer`` (monitor, foxglove):
    no shared memory and a short connect timeout, since they reconnect by themselves."""
    from .domains import DefaultGraph, apply_domain, load_graph  # with this process's domain
    from .errors import UsageError

    if graph_path and Path(graph_path).exists():
        base = load_graph(graph_path).zenoh
    else:
        base = apply_domain(DefaultGraph()).zenoh
    user = user or os.environ.get(USER_ENV) or None
    if password is not None and not user:
        raise UsageError("--password needs --user (the zenoh user name it belongs to)")
    if user and password is None:
        password = os.environ.get(PASSWORD_ENV)
        if password is None:
            password = _ask_password(user)
    out = base.as_client(list(connect) if connect else None)
    out.config = _client_config(base.config, user, password, ca, keep_identity=not connect and not user)
    if viewer:
        out.shm = False
        out.connect_timeout_ms = VIEWER_CONNECT_TIMEOUT_MS
    if connect_timeout_s is not None:
        out.connect_timeout_ms = max(1, round(connect_timeout_s * 1000))
    if is_remote(out) and "transport/link/tx/batch_size" not in out.config:
        # Zenoh negotiates a link's batch size down to the smaller side's, so this link alone gets small batches.
        # The robot's router writes one batch at a time into a link it cannot preempt: on a full 2 Mbit/s link a
        # 64 KB batch holds the motor commands behind it for a quarter of a second, and those that come meanwhile
        # overflow their queue (bus/netif.py); an 8 KB one for 33 ms, a command's period.
        out.config["transport/link/tx/batch_size"] = REMOTE_BATCH_BYTES
    return out


def settings_from_args(args: Any, viewer: bool = False) -> ZenohSettings:
    """:func:`client_settings` from the options every bus command takes (tools/command.py connect_args)."""
    return client_settings(getattr(args, "graph", None), getattr(args, "connect", None),
                           getattr(args, "user", None), getattr(args, "password", None), getattr(args, "ca", None),
                           viewer=viewer, connect_timeout_s=getattr(args, "connect_timeout", None))


# --- may we publish? ------------------------------------------------------------------------------------

class PublishRefused(Exception):
    """The router drops what this session publishes (access control): the message is the one line to print."""


def check_can_publish(session: zenoh.Session, settings: ZenohSettings, timeout_s: float = PUBLISH_PROBE_S) -> None:
    """Raise :class:`PublishRefused` when the graph does not forward this session's messages.

    Zenoh's access control drops a denied put silently, so a read-only identity's `play` would publish into the
    void. A second session with the same identity subscribes to a probe key outside every namespace
    (``followbus/probe/<random>``, matched by a read-only rule's ``**``) and this one puts on it until the
    router hands it back or ``timeout_s`` passes. Nothing but the probe's subscriber listens to that key."""
    key = f"followbus/probe/{secrets.token_hex(6)}"
    arrived: list[bool] = []
    watcher = open_session(settings)
    try:
        sub = watcher.declare_subscriber(key, lambda _sample: arrived.append(True))
        deadline = time.monotonic() + timeout_s
        while not arrived and time.monotonic() < deadline:
            session.put(key, b"probe")
            time.sleep(0.1)
        sub.undeclare()
    finally:
        watcher.close()
    if not arrived:
        user = auth_user(settings.config)
        who = f"user {user}" if user else "this session"
        raise PublishRefused(f"{', '.join(settings.connect)} does not accept messages from {who} (access control: a "
                             "read-only identity; publishing needs one allowed to, e.g. --user operator)")


# --- what a slow link carries ---------------------------------------------------------------------------

# The uncompressed camera frame every capture node publishes as its ``frame`` output: ~27 MB/s at 640x480 and
# 30 Hz, more than any wireless link carries. A tool joining over a network leaves these keys out unless asked
# (record and topics: --raw-frames); the JPEG ``preview`` (a few KB) stays.
RAW_FRAME_OUTPUT = "frame"


def is_remote(settings: ZenohSettings) -> bool:
    """Whether a tool reaches the graph over a network (any endpoint beyond loopback)."""
    return any(not is_local_endpoint(ep) for ep in settings.connect)


def is_raw_frame(key: str) -> bool:
    """Whether a key is a node's raw frame output (``<ns>/<node>/frame``)."""
    return key.rsplit("/", 1)[-1] == RAW_FRAME_OUTPUT
