"""Every command that joins the bus, from a "laptop" (a directory without the graph file) against the robot graph
(graph.robot.yaml: user/password + access control) on loopback: echo, hz, topics, nodes, record and monitor
work as the read-only `monitor` identity with the same options (--connect, --user, $FOLLOWBUS_ZENOH_PASSWORD,
--namespace); `play` is refused for `monitor` (one line, exit 2) and allowed for `operator`; a graph that is not
there, a wrong password and an empty namespace are one line each."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from followbus.bus.recording import iter_bus_messages

from .conftest import followbus_argv, free_port, wait_until
from .test_monitor import DIAG_NODES, Launch, robot_graph

pytestmark = pytest.mark.slow


def _laptop_env(user: str | None = "monitor") -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("FOLLOWBUS_ZENOH_")}
    if user:
        env.update(FOLLOWBUS_ZENOH_USER=user, FOLLOWBUS_ZENOH_PASSWORD=f"{user}-secret")
    return env


def _start(cwd: Path, env: dict[str, str], *args: str) -> subprocess.Popen:
    return subprocess.Popen(followbus_argv(*args), cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 60) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out, err


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("robot")
    port = free_port()
    launch = Launch(robot_graph(tmp, port, DIAG_NODES))
    try:
        launch.wait_ready()
        yield f"tcp/127.0.0.1:{port}"
    finally:
        launch.stop()


def test_laptop_as_monitor_uses_every_bus_command(robot, tmp_path):
    env = _laptop_env()
    join = ("--connect", robot, "--namespace", "t")
    procs = {
        "echo": _start(tmp_path, env, "echo", "t/ticker/tick", "-n", "2", "--timeout", "20", *join),
        "hz": _start(tmp_path, env, "hz", "t/relay/tick", "--seconds", "3", *join),
        "topics": _start(tmp_path, env, "topics", "--seconds", "3", *join),
        "nodes": _start(tmp_path, env, "nodes", *join),
        "record": _start(tmp_path, env, "record", "-o", "laptop.mcap", "--duration", "3", *join),
        "monitor": _start(tmp_path, env, "monitor", "--once", "--seconds", "10", *join),
        # The graph's namespace is t; the laptop's default is fb: it names the one that is alive.
        "empty": _start(tmp_path, env, "nodes", "--connect", robot),
        "monitor-empty": _start(tmp_path, env, "monitor", "--connect", robot, "--once", "--seconds", "6"),
        "topics-empty": _start(tmp_path, env, "topics", "--connect", robot, "--seconds", "2"),
    }
    done = {name: _finish(proc) for name, proc in procs.items()}
    for name in ("echo", "hz", "topics", "nodes", "record", "monitor"):
        assert done[name][0] == 0, (name, done[name])
    assert done["echo"][1].count("t/ticker/tick: ") == 2
    assert "t/relay/tick:" in done["hz"][1]
    assert "t/ticker/tick" in done["topics"][1] and "t/relay/tick" in done["topics"][1]
    assert {"ticker", "relay", "sink"} <= {line.split()[0] for line in done["nodes"][1].splitlines()[1:]}
    assert "connected" in done["monitor"][1].splitlines()[0]
    status, out, _ = done["empty"]
    assert status == 1 and "no node under fb/@health; nodes are alive in: t (" in out, out
    assert "relay" in out and "(pick one with --namespace)" in out
    status, out, _ = done["monitor-empty"]
    assert status == 1 and "monitor  no node under fb/@health; nodes are alive in: t (" in out, out
    status, out, _ = done["topics-empty"]
    assert status == 1 and "nodes are alive in: t (" in out and "(pick one with --namespace)" in out, out
    # A remote link (here loopback: nothing to leave out) records every key and says what it lost.
    assert "recorded " in done["record"][1] and "lost on the way" in done["record"][1]
    keys = {msg.key for msg in iter_bus_messages(tmp_path / "laptop.mcap")}
    assert {"t/ticker/tick", "t/relay/tick"} <= keys


def test_web_view_names_the_namespaces_that_are_alive(robot):
    """The web view, connected to a robot whose graph runs under another namespace, says so on its screen."""
    from .test_monitor import _interrupt
    from .test_webview import _screen, _web_view

    web_port = free_port()
    proc, lines = _web_view(web_port, "--connect", robot, "--user", "monitor", "--password", "monitor-secret")
    try:
        assert wait_until(lambda: "nodes are alive in: t (" in _screen(web_port).get("text", ""), 30), (
            _screen(web_port), lines[-5:])
        assert _screen(web_port)["text"].startswith("waiting for first frame: no node under fb/@health")
    finally:
        _interrupt(proc)


def test_play_is_refused_for_monitor_and_allowed_for_operator(robot, tmp_path):
    recorded = _finish(_start(tmp_path, _laptop_env("operator"), "record", "-o", "run.mcap", "--duration", "2",
                              "--connect", robot, "--namespace", "t"))
    assert recorded[0] == 0, recorded
    play = ("play", "run.mcap", "--fast", "--remap", "t=t_played", "--connect", robot)
    refused = _start(tmp_path, _laptop_env("monitor"), *play)
    allowed = _start(tmp_path, _laptop_env("operator"), *play)
    status, out, err = _finish(refused)
    assert status == 2 and "published" not in out, (out, err)
    assert _one_line(err) == (f"followbus: play refused: {robot} does not accept messages from user monitor "
                              "(access control: a read-only identity; publishing needs one allowed to, e.g. "
                              "--user operator)")
    status, out, err = _finish(allowed)
    assert status == 0, (out, err)
    assert out.splitlines()[0] == f"joined {robot} as operator: the graph accepts our messages"
    assert "published " in out


def test_refusals_are_one_line(robot, tmp_path):
    nobody = f"tcp/127.0.0.1:{free_port()}"
    env = _laptop_env()
    wrong = dict(env, FOLLOWBUS_ZENOH_PASSWORD="wrong")
    procs = {
        "record-nowhere": _start(tmp_path, env, "record", "-o", "x.mcap", "--connect", nobody,
                                 "--connect-timeout", "1"),
        "echo-wrong": _start(tmp_path, wrong, "echo", "t/ticker/tick", "--connect", robot, "--connect-timeout", "1"),
        "hz-no-user": _start(tmp_path, _laptop_env(None), "hz", "t/ticker/tick", "--connect", robot,
                             "--connect-timeout", "1"),
        "password-no-user": _start(tmp_path, _laptop_env(None), "topics", "--connect", robot, "--password", "x"),
    }
    done = {name: _finish(proc) for name, proc in procs.items()}
    assert all(status == 2 for status, _, _ in done.values()), done
    assert _one_line(done["record-nowhere"][2]).startswith(f"followbus: no graph is running on {nobody}")
    assert not (tmp_path / "x.mcap").exists()
    assert _one_line(done["echo-wrong"][2]) == (f"followbus: authentication failed for user monitor on {robot} "
                                                "(wrong or missing password)")
    assert _one_line(done["hz-no-user"][2]) == (f"followbus: {robot} refused the connection: the graph requires "
                                                "authentication (--user and --password, or $FOLLOWBUS_ZENOH_PASSWORD)")
    assert _one_line(done["password-no-user"][2]) == ("followbus: --password needs --user (the zenoh user name it "
                                                      "belongs to)")
