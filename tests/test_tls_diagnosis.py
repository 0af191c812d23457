"""A failed join over TLS is named as a TLS failure (issue 25): no --ca, a CA that did not sign the robot's
certificate, tcp/ to a TLS port, tls/ to a plain one; not "wrong or missing password". A real TLS listener on
loopback (Python's ssl with openssl-made certificates, the README's recipe) stands for the robot's port:
the diagnosis probes the port, it does not need Zenoh behind it."""

from __future__ import annotations

import contextlib
import shutil
import socket
import ssl
import threading
from collections.abc import Iterator

import pytest

from followbus.bus.session import ZenohSettings
from followbus.tools.connect import explain_connect_failure

from .test_security import _certificates

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="the openssl CLI makes the certificates")


@contextlib.contextmanager
def _listener(context: ssl.SSLContext | None) -> Iterator[int]:
    """A loopback port that completes TLS handshakes with ``context`` (None: plain TCP), then hangs up."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.1)
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            with conn, contextlib.suppress(OSError):
                conn.settimeout(2)
                if context is not None:
                    context.wrap_socket(conn, server_side=True).close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        stop.set()
        thread.join(5)
        server.close()


def _client(endpoint: str, ca=None, user: str | None = "monitor") -> ZenohSettings:
    config = {}
    if user:
        config["transport/auth/usrpwd"] = {"user": user, "password": "secret"}
    if ca:
        config["transport/link/tls/root_ca_certificate"] = str(ca)
    return ZenohSettings(mode="client", listen=[], connect=[endpoint], config=config)


@pytest.fixture(scope="module")
def robot_tls(tmp_path_factory) -> Iterator[tuple[int, dict]]:
    certs = _certificates(tmp_path_factory.mktemp("robot"))
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(certs["cert"], certs["key"])
    with _listener(context) as port:
        yield port, certs


def test_no_ca_is_named(robot_tls):
    port, _ = robot_tls
    line = explain_connect_failure(_client(f"tls/127.0.0.1:{port}"))
    assert "TLS handshake" in line and "no CA certificate" in line and "--ca" in line, line
    assert "password" not in line


def test_a_wrong_ca_is_named(robot_tls, tmp_path):
    port, _ = robot_tls
    other = _certificates(tmp_path)  # another CA: it did not sign the robot's certificate
    line = explain_connect_failure(_client(f"tls/127.0.0.1:{port}", ca=other["ca"]))
    assert "TLS handshake" in line and "certificate" in line and str(other["ca"]) in line, line
    assert "password" not in line


def test_tcp_to_a_tls_port_is_named(robot_tls):
    port, _ = robot_tls
    line = explain_connect_failure(_client(f"tcp/127.0.0.1:{port}"))
    assert f"tcp/127.0.0.1:{port} is a TLS port" in line and f"tls/127.0.0.1:{port}" in line, line


def test_tls_to_a_plain_port_is_named():
    with _listener(None) as port:
        line = explain_connect_failure(_client(f"tls/127.0.0.1:{port}", ca="/nonexistent/ca.pem"))
    assert "does not speak TLS" in line, line


def test_the_right_ca_leaves_the_password_as_the_reason(robot_tls):
    port, certs = robot_tls
    line = explain_connect_failure(_client(f"tls/127.0.0.1:{port}", ca=certs["ca"]))
    assert "authentication failed for user monitor" in line and "wrong or missing password" in line, line
