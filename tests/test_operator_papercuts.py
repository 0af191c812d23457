"""Operator papercuts (issue 36, tried as a ROS 2 / dora user would): every command honours the same identity
($FOLLOWBUS_NAMESPACE, $FOLLOWBUS_PORT, $FOLLOWBUS_DOMAIN) with or without a graph file (monitor watched `fb`
outside a checkout, its web view's /graph.svg was 404); `down` and `logs` without a name act only on this user's
graphs; `ps` shows node health; `record` exits 130 on Ctrl-C; hints that named the wrong cure (param set, echo of
parameter_events); the drawing's backward keys; README drift; a scene that plays once. Real launches, real
processes of another user (setpriv), real signals."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from followbus.bus.graph import load_graph
from followbus.bus.graph_drawing import _edges, back_edges, layout
from followbus.bus.recording import bus_channels, read_summary
from followbus.vision.detectors import resolve_detector_model

from .conftest import REPO, followbus_argv, free_port, wait_until

NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 50}
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs: {tick: ticker/tick}
"""


def _run(env: dict[str, str], *args: str, cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(followbus_argv(*args), capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          stdin=subprocess.DEVNULL, env=env)


def _two_free_ports(offset: int) -> int:
    """A port p with p and p + offset free (a domain moves the port up by its number)."""
    for _ in range(50):
        port = free_port()
        if port + offset < 65536:
            with socket.socket() as probe:
                try:
                    probe.bind(("127.0.0.1", port + offset))
                    return port
                except OSError:
                    continue
    raise RuntimeError("no free pair of ports")


@pytest.fixture(scope="module")
def identity_graph(tmp_path_factory) -> Iterator[tuple[dict[str, str], Path]]:
    """A graph launched from its "checkout" with an identity from the environment (namespace, port, domain 2);
    yields that environment and a directory without any graph file (a laptop, a ROS 2 user's home)."""
    tmp = tmp_path_factory.mktemp("identity")
    checkout, elsewhere = tmp / "checkout", tmp / "elsewhere"
    checkout.mkdir()
    elsewhere.mkdir()
    port = _two_free_ports(2)
    (checkout / "graph.yaml").write_text(f"name: test\nnamespace: t\nzenoh:\n  listen: [tcp/127.0.0.1:{port}]\n"
                                         f"  connect: [tcp/127.0.0.1:{port}]\nnodes:\n{NODES}")
    env = {**os.environ, "FOLLOWBUS_NAMESPACE": "opsenv", "FOLLOWBUS_PORT": str(port), "FOLLOWBUS_DOMAIN": "2",
           "FOLLOWBUS_RUNS": str(tmp / "runs")}
    launch = subprocess.Popen(followbus_argv("launch", "graph.yaml"), cwd=checkout, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    try:
        assert wait_until(lambda: _ready(env, elsewhere), 60, interval=1.0), "the graph did not come up"
        yield env, elsewhere
    finally:
        launch.send_signal(signal.SIGINT)
        launch.communicate(timeout=60)


def _ready(env: dict[str, str], cwd: Path) -> bool:
    nodes = _run(env, "nodes", "--seconds", "1", cwd=cwd)
    return nodes.returncode == 0 and len(re.findall(r"^(sink|ticker)\s+up\b", nodes.stdout, re.M)) == 2


@pytest.mark.slow
def test_every_command_finds_the_graph_outside_a_checkout(identity_graph, tmp_path):
    """On d899b0d `monitor` and `record` without a graph file watched and recorded fb (nothing), although `nodes`,
    `param` and `echo` found opsenv-d2."""
    env, elsewhere = identity_graph
    recording = tmp_path / "run.mcap"
    commands = [
        (("monitor", "--once", "--seconds", "15"), "ns=opsenv-d2"),
        (("nodes", "--seconds", "1.5"), "ticker         up"),
        (("topics", "--seconds", "1.5"), "opsenv-d2/ticker/tick"),
        (("echo", "opsenv-d2/ticker/tick", "-n", "1", "--timeout", "10"), "opsenv-d2/ticker/tick: {"),
        (("hz", "opsenv-d2/ticker/tick", "--seconds", "2.5", "--timeout", "10"), "opsenv-d2/ticker/tick: "),
        (("param", "get", "ticker.rate_hz"), "ticker.rate_hz = "),
        (("record", "-o", str(recording), "--duration", "2"), "recording opsenv-d2/**"),
    ]
    failed = []
    for command, shows in commands:
        result = _run(env, *command, cwd=elsewhere)
        if result.returncode != 0 or shows not in result.stdout:
            failed.append(f"{' '.join(command)}: status {result.returncode}: {result.stdout[-600:]}{result.stderr}")
    assert not failed, "\n".join(failed)
    assert "opsenv-d2/ticker/tick" in bus_channels(recording)


@pytest.mark.slow
def test_the_web_view_outside_a_checkout_draws_the_graph_from_the_bus(identity_graph):
    """On d899b0d /graph.svg was 404 without a graph file."""
    env, elsewhere = identity_graph
    web = free_port()
    proc = subprocess.Popen(followbus_argv("monitor", "--web", str(web), "--seconds", "30"), cwd=elsewhere, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)

    def svg() -> str:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{web}/graph.svg", timeout=2) as reply:
                return reply.read().decode()
        except OSError:
            return ""

    try:
        assert wait_until(lambda: svg().count('class="node"') == 2, 25), svg()
        drawing = svg()
        assert drawing.count('class="node"') == 2 and "<title>opsenv-d2/ticker/tick</title>" in drawing, drawing
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


@pytest.mark.slow
def test_param_hints_name_the_cure(identity_graph):
    env, elsewhere = identity_graph
    typo = _run(env, "param", "set", "ticker.rate_hx", "10", cwd=elsewhere)
    # On d899b0d: "ticker.rate_hx is not live-tunable ...; set it at launch with --set ticker.rate_hx=VALUE".
    assert typo.returncode == 2 and "--set" not in typo.stderr, typo.stderr
    assert "node 'ticker' has no parameter 'rate_hx' (did you mean ticker.rate_hz?" in typo.stderr, typo.stderr
    huge = _run(env, "param", "set", "ticker.rate_hz", "1e309", cwd=elsewhere)
    # On d899b0d: "parameter 'rate_hz' must be float, not str ('1e309')".
    assert huge.returncode == 2 and "1e309 is beyond the range of a float" in huge.stderr, huge.stderr
    exponent = _run(env, "param", "set", "ticker.rate_hz", "4e1", cwd=elsewhere)
    assert exponent.returncode == 0 and exponent.stdout.strip().endswith("-> 40.0"), exponent.stdout + exponent.stderr


@pytest.mark.slow
def test_echo_of_parameter_events_says_no_parameter_changed(identity_graph):
    """On d899b0d: "no node publishes .../parameter_events; did you mean <another key>?"."""
    env, elsewhere = identity_graph
    for cwd in (elsewhere, None):  # without the graph file, and with it
        args = ("echo", "opsenv-d2/sink/parameter_events", "--timeout", "3")
        if cwd is None:
            cwd = next(p for p in elsewhere.parent.iterdir() if p.name == "checkout")
        result = _run(env, *args, cwd=cwd)
        assert result.returncode == 1, result.stdout + result.stderr
        assert "no parameter of sink changed since it started" in result.stderr, result.stderr
        assert "did you mean" not in result.stderr


SYSTEM_PYTHON = "/usr/bin/python3"  # one another user can run (the test's own may live in root's home)


def _other_users_run(runs: Path, name: str, pid_file: Path) -> subprocess.Popen:
    """A graph's run record held by a process of user nobody, as another user's launch holds its claim (``runs``:
    a directory every user may write, as a shared $FOLLOWBUS_RUNS is)."""
    claims = runs / "claims"
    claims.mkdir(parents=True, exist_ok=True)
    for directory in (runs, claims):
        directory.chmod(0o1777)
    holder = (
        "import fcntl, json, os, sys, time\n"
        f"path = '{claims}/9999-theirs-' + str(os.getpid()) + '.lock'\n"
        "handle = open(path, 'a+')\n"
        "fcntl.flock(handle, fcntl.LOCK_EX)\n"
        f"handle.write(json.dumps(dict(name='{name}', graph='/home/them/graph.yaml', namespace='theirs', "
        "endpoint='tcp/127.0.0.1:9999', pid=os.getpid(), started=time.time(), nodes=['ticker'], command='up', "
        f"log_dir='{runs}/{name}-x')))\n"
        "handle.flush()\n"
        f"open('{pid_file}', 'w').write(str(os.getpid()))\n"
        "time.sleep(120)\n")
    proc = subprocess.Popen(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", SYSTEM_PYTHON, "-c",
                             holder], stdin=subprocess.DEVNULL)
    assert wait_until(pid_file.exists, 15), "the other user's run did not start"
    return proc


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("setpriv") is None or os.getuid() != 0 or not Path(SYSTEM_PYTHON).exists(),
                    reason="needs setpriv, root and a system python to run a process as another user")
def test_down_and_logs_without_a_name_never_pick_another_users_graph(tmp_path, port):
    """On d899b0d `down` without a name stopped the one graph running, whoever started it."""
    runs = Path(tempfile.mkdtemp(prefix="followbus-shared-runs-"))  # under /tmp: reachable by user nobody
    env = {**os.environ, "FOLLOWBUS_RUNS": str(runs)}
    env.pop("FOLLOWBUS_DOMAIN", None)
    theirs = _other_users_run(runs, "theirs", runs / "theirs.pid")
    try:
        down = _run(env, "down", cwd=tmp_path)
        assert down.returncode == 2 and theirs.poll() is None, down.stdout + down.stderr
        line = down.stderr.strip()
        assert "\n" not in line and "no graph of yours is running" in line and "user nobody" in line, line
        logs = _run(env, "logs", "ticker", cwd=tmp_path)
        assert logs.returncode == 2 and "no graph of yours" in logs.stderr and "user nobody" in logs.stderr, logs.stderr
        ps = _run(env, "ps", cwd=tmp_path)
        assert re.search(r"^theirs\s.*\s\?\s+\d+\s+nobody\s+up$", ps.stdout, re.M), ps.stdout
        # A graph of mine beside theirs: `down` without a name stops mine, and only mine.
        graph = tmp_path / "graph.yaml"
        folder = tmp_path / "seq"
        folder.mkdir()
        for i in range(3):
            cv2.imwrite(str(folder / f"{i}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
        graph.write_text(f"name: mine\nnamespace: mine\nzenoh:\n  listen: [tcp/127.0.0.1:{port}]\n"
                         f"  connect: [tcp/127.0.0.1:{port}]\nnodes:\n{NODES}"
                         "  capture:\n    run: followbus.nodes.capture\n    outputs: [frame, preview, ground_truth]\n"
                         f"    params: {{source: {folder}}}\n")
        up = _run(env, "up", str(graph), cwd=tmp_path)
        assert up.returncode == 0, up.stdout + up.stderr
        # The folder plays once: said when the graph is up (on d899b0d nothing said so).
        assert f"note: capture plays {folder} once" in up.stdout and "--set capture.loop=true" in up.stdout, up.stdout

        def health() -> str:
            row = next((r for r in _run(env, "ps", cwd=tmp_path).stdout.splitlines() if r.startswith("mine ")), "")
            return row

        assert wait_until(lambda: "2/3 up: capture done" in health(), 20), health()
        down = _run(env, "down", cwd=tmp_path)
        assert down.returncode == 0 and down.stdout.startswith("stopped mine"), down.stdout + down.stderr
        assert theirs.poll() is None
    finally:
        theirs.kill()
        theirs.wait()
        shutil.rmtree(runs, ignore_errors=True)


@pytest.mark.slow
def test_record_exits_130_on_ctrl_c(tmp_path):
    """As the README says of every command; on d899b0d `record` exited 0."""
    bus = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen(followbus_argv("router", "--listen", bus), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    out = tmp_path / "run.mcap"
    try:
        record = subprocess.Popen(followbus_argv("record", "--connect", bus, "-o", str(out), "--namespace", "t"),
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                  stdin=subprocess.DEVNULL, cwd=tmp_path)
        lines: list[str] = []
        assert wait_until(lambda: bool(lines.append(record.stdout.readline()) or "recording" in lines[-1]), 30), lines
        record.send_signal(signal.SIGINT)
        rest, _ = record.communicate(timeout=60)
    finally:
        router.terminate()
        router.communicate(timeout=30)
    assert record.returncode == 130, "".join(lines) + rest
    assert read_summary(out) is not None  # finalised all the same


@pytest.mark.parametrize("name", ["graph.yaml", "graph.robot.yaml", "graph.group.yaml"])
def test_every_key_is_drawn_right_of_its_publisher(name):
    """On d899b0d a cycle through an input not joined by frame (odometry) pushed nodes right of their own keys."""
    graph = load_graph(REPO / name)
    cells = layout(graph)
    for node, spec in graph.nodes.items():
        for out in spec.outputs:
            assert cells[f"k:{node}/{out}"][0] == cells[f"n:{node}"][0] + 1, (node, out)
    edges, _ = _edges(graph)
    backward = {(src, dst) for src, dst, _ in edges if src in cells and cells[dst][0] <= cells[src][0]}
    feedback = {(src, dst) for src, dst, fb in edges if fb}
    assert backward <= back_edges(graph) | feedback, backward  # only an edge closing a cycle runs back
    assert all(src.startswith("k:") for src, _ in backward)  # from a key to a node reading it, never the reverse


def test_a_running_graph_is_drawn_by_name_from_the_checkout(monkeypatch, tmp_path):
    """`followbus graph followbus` run in the checkout took its `followbus/` folder for the graph file."""
    from followbus.tools.errors import UsageError
    from followbus.tools.runs.drawing_cmd import graph_file

    monkeypatch.chdir(REPO)
    monkeypatch.setenv("FOLLOWBUS_RUNS", str(tmp_path))
    assert (REPO / "followbus").is_dir()
    with pytest.raises(UsageError, match="no graph is running"):
        graph_file("followbus")
    assert graph_file("graph.yaml") == "graph.yaml"


def test_the_readme_shows_what_runs():
    """On d899b0d the README's demo said 6 nodes and yolox_nano_416, its graph followbus-demo."""
    readme = (REPO / "README.md").read_text()
    graph = load_graph(REPO / "graph.yaml")
    assert "followbus-demo" not in readme
    assert f"```yaml\nname: {graph.name}\n" in readme
    demo = re.search(r"launching (\d+) nodes for", readme)
    assert demo and int(demo[1]) == len(graph.nodes), demo
    params = graph.nodes["detection"].params
    model = resolve_detector_model("auto", input_size=params["input_size_px"], input_shape=params["input_shape"])
    assert f"model /work/main/models/{Path(str(model)).name}" in readme, model
    for text in (REPO / "tools").rglob("*.py"):
        assert "followbus-demo" not in text.read_text(), text
