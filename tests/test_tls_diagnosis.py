"""A failed join over TLS is named as a TLS failure (issue 25): no --ca, a CA that did not sign the robot's
certificate, tcp/ to a TLS port, tls/ to a plain one; not "wrong or missing password". A real TLS listener on
loopback (Python's ssl with openssl-made certificates, the README's recipe) stands for the robot's port:
the diagnosis probes the port, it does not need Zenoh behind it."""

from __future__ import annotations

import contextlib
import shutil
import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from followbus.bus.session import ZenohSettings
from followbus.tools.connect import explain_connect_failure

from .conftest import run_followbus
from .test_security import _certificates, tls_graph

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


def _expired(tmp: Path) -> dict[str, Path]:
    """A CA and a certificate for 127.0.0.1 signed by it that expired in 2020 (`openssl ca` sets past dates)."""
    certs = _certificates(tmp)
    conf, key, csr, cert = (tmp / n for n in ("ca.cnf", "expired.key", "expired.csr", "expired.pem"))
    (tmp / "index.txt").write_text("")
    (tmp / "serial").write_text("1000\n")
    conf.write_text(f"[ca]\ndefault_ca = test\n[test]\ndir = {tmp}\ndatabase = {tmp}/index.txt\nnew_certs_dir = {tmp}\n"
                    f"serial = {tmp}/serial\ndefault_md = sha256\npolicy = any\ncopy_extensions = copy\n"
                    "[any]\ncommonName = supplied\n")
    for argv in (
        ["req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-keyout", key, "-out", csr,
         "-subj", "/CN=robot", "-addext", "subjectAltName=IP:127.0.0.1", "-addext", "extendedKeyUsage=serverAuth"],
        ["ca", "-batch", "-config", conf, "-cert", certs["ca"], "-keyfile", tmp / "ca.key", "-in", csr, "-out", cert,
         "-startdate", "20200101000000Z", "-enddate", "20200201000000Z"],
    ):
        subprocess.run(["openssl", *map(str, argv)], check=True, capture_output=True, timeout=30)
    return {"ca": certs["ca"], "key": key, "cert": cert}


def test_an_expired_certificate_is_named_as_such(tmp_path):
    certs = _expired(tmp_path)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(certs["cert"], certs["key"])
    with _listener(context) as port:
        line = explain_connect_failure(_client(f"tls/127.0.0.1:{port}", ca=certs["ca"]))
    assert "TLS handshake" in line and "certificate has expired" in line and "validity dates" in line, line


def test_launch_with_an_expired_certificate_names_tls_at_once(tmp_path, port):
    """On d899b0d: "startup timeout after 30 s: no liveliness from ticker", no word of TLS."""
    certs = _expired(tmp_path)
    endpoint = f"tls/127.0.0.1:{port}"
    graph = tmp_path / "graph.yaml"
    graph.write_text(tls_graph(endpoint, certs, "  ticker: {run: followbus.nodes.diagnostics, outputs: [tick]}\n"))
    started = time.monotonic()
    result = run_followbus("launch", str(graph), "--duration", "3", "--startup-timeout", "60", timeout=120)
    assert result.returncode == 2, result.stdout + result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith(f"followbus launch: TLS handshake with {endpoint} failed: certificate has expired"), line
    assert time.monotonic() - started < 30, "named only at the start-up timeout"
