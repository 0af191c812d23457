"""The laptop section of docs/laptop-and-two-hosts.md, as written: graph.robot.yaml (its own bus: router hub,
user/password, access control, the example user dictionary) runs in one network namespace, listening on its veth
address as the page says to let a laptop in; every command of the section's command block runs in a second namespace
with its own /dev/shm (a laptop), from a directory without any graph file, with the identity the block exports at
that point. Each command must do what the block says: `monitor` sees the nodes, `echo` the commands, `record` a file
that `play` publishes as `operator`; `param` is refused in one line for `monitor` and changes the parameter for
`operator`. Skipped, with the reason, where ip netns is not permitted."""

from __future__ import annotations

import contextlib
import math
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from followbus.tools.bench.netns import NetnsPair, netns_unavailable

from .conftest import REPO, followbus_argv, wait_until

pytestmark = pytest.mark.slow

REASON = netns_unavailable()
PORT = 7447  # the page's: inside its own namespace the robot has the port to itself
USERS = dict(line.split(":", 1) for line in (REPO / "docs" / "zenoh-users.example.txt").read_text().split())
IDENTITY_ENV = ("FOLLOWBUS_DOMAIN", "FOLLOWBUS_NAMESPACE", "FOLLOWBUS_PORT", "FOLLOWBUS_ZENOH_USER",
                "FOLLOWBUS_ZENOH_PASSWORD")
LONG_RUNNING_S = 8.0  # `record` records this long before its Ctrl-C; the other long-running ones until they show


@dataclass
class Step:
    """One command of the page's block with the environment the block gives it."""

    line: str
    argv: list[str]
    env: dict[str, str]
    proc: subprocess.Popen | None = None
    lines: list[str] = field(default_factory=list)

    @property
    def user(self) -> str:
        return self.env.get("FOLLOWBUS_ZENOH_USER", "")

    def output(self) -> str:
        return "".join(self.lines)


def readme_commands(endpoint: str) -> list[Step]:
    """The laptop section's command block: its `export`s and `R=` applied in order, `$R` replaced, `...` (a
    password) given the example dictionary's password of the user exported with it, comments dropped."""
    text = (REPO / "docs" / "laptop-and-two-hosts.md").read_text()
    section = text[text.index("\n## The laptop\n"):]
    block = section[section.index("```\nexport ") + 4:]
    block = block[:block.index("```")]
    env: dict[str, str] = {}
    steps: list[Step] = []
    for raw in block.splitlines():
        line = raw.split("#", 1)[0].strip()
        if line.startswith("export "):
            assignments = dict(word.split("=", 1) for word in shlex.split(line)[1:])
            if assignments.get("FOLLOWBUS_ZENOH_PASSWORD") == "...":
                assignments["FOLLOWBUS_ZENOH_PASSWORD"] = USERS[assignments["FOLLOWBUS_ZENOH_USER"]]
            env.update(assignments)
            continue
        if re.fullmatch(r"R=\S+", line):
            continue
        for command in filter(None, (c.strip() for c in line.split(";"))):
            words = shlex.split(command.replace("$R", endpoint))
            assert words[0] == "followbus", raw
            steps.append(Step(command, words[1:], dict(env)))
    return steps


class Robot:
    """graph.robot.yaml in namespace a: the page's bus, plus the veth address to listen on; a looping synthetic
    scene and the simulated detector, so that it follows a target without a camera or a model."""

    def __init__(self, pair: NetnsPair, tmp: Path, address: str):
        graph = tmp / "graph.laptop-test.yaml"
        graph.write_text(f"extends: {REPO / 'graph.robot.yaml'}\n"
                         f"zenoh:\n  listen: [tcp/127.0.0.1:{PORT}, tcp/{address}:{PORT}]\n"
                         "nodes:\n  capture: {params: {source: 'scene:wall-occlusion', loop: true}}\n"
                         "  detection: {params: {backend: simulated}}\n"
                         f"  template: {{params: {{state_file: '{tmp / 'template.npz'}'}}}}\n")
        env = {k: v for k, v in os.environ.items() if k not in IDENTITY_ENV} | {"FOLLOWBUS_RUNS": str(tmp / "runs")}
        # From the repository: the robot's dictionary_file is docs/zenoh-users.example.txt, relative to it.
        self.proc = subprocess.Popen(pair.argv(0, followbus_argv("launch", str(graph), "--grace", "1")), cwd=REPO,
                                     env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     stdin=subprocess.DEVNULL)
        self.lines: list[str] = []
        threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")), daemon=True).start()

    def wait_ready(self) -> None:
        assert wait_until(lambda: any("ready:" in line for line in self.lines), 90), "".join(self.lines[-30:])

    def stop(self) -> None:
        _interrupt(self.proc, 30)


def _interrupt(proc: subprocess.Popen, timeout: float = 20) -> None:
    """Ctrl-C, as a user would; a command still running ``timeout`` later first prints every thread's stack into
    its output (`kill -USR1`, tools/cli.py), so the failure that follows says where it waited."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout)
    if proc.poll() is None:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        proc.kill()
        proc.wait()


def _start(pair: NetnsPair, step: Step, cwd: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in IDENTITY_ENV} | step.env
    step.proc = subprocess.Popen(pair.argv(1, followbus_argv(*step.argv)), cwd=cwd, env=env, text=True,
                                 stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    threading.Thread(target=lambda: step.lines.extend(iter(step.proc.stdout.readline, "")), daemon=True).start()


def _in_laptop(pair: NetnsPair, code: str) -> str:
    """Python run in the laptop's namespace (what a browser there would fetch)."""
    return subprocess.run(pair.argv(1, [sys.executable, "-c", code], private_shm=False), capture_output=True, text=True,
                          timeout=20).stdout


def _web_state(pair: NetnsPair, port: str) -> str:
    fetch = f"u.urlopen('http://127.0.0.1:{port}/state.json', timeout=3).read().decode()"
    return _in_laptop(pair, f"import urllib.request as u\ntry: print({fetch})\nexcept Exception: pass")


def _shown(pair: NetnsPair, step: Step) -> bool:
    """Whether a command that runs until Ctrl-C has shown what the page says it does."""
    out, words = step.output(), step.argv
    if words[0] == "monitor" and "--web" in words:
        return '"capture"' in _web_state(pair, words[words.index("--web") + 1])
    if words[0] == "monitor" and "--once" not in words:  # --once ends by itself, however slowly on a loaded machine
        return "connected" in out and any(line.split()[:2] == ["motor", "up"] for line in out.splitlines())
    if words[0] == "foxglove":
        return "ws://" in out
    if words[0] == "hz":
        return any(line.startswith(f"{words[1]}:") and "Hz" in line for line in out.splitlines())
    return False


def _run_all(pair: NetnsPair, steps: list[Step], cwd: Path) -> None:
    """Start every step; each that has not ended by itself is interrupted once it has shown its part (or after
    LONG_RUNNING_S), as a user's Ctrl-C."""
    for step in steps:
        _start(pair, step, cwd)
    deadline = time.monotonic() + 60
    recording_since: dict[int, float] = {}  # from its "recording ..." line: joining takes long on a loaded machine
    while time.monotonic() < deadline and any(s.proc.poll() is None for s in steps):
        for i, step in enumerate(steps):
            if step.argv[0] == "record" and i not in recording_since and "\nrecording " in "\n" + step.output():
                recording_since[i] = time.monotonic()
            recorded = time.monotonic() - recording_since.get(i, math.inf) > LONG_RUNNING_S
            if step.proc.poll() is None and (recorded or _shown(pair, step)):
                _interrupt(step.proc)
        time.sleep(0.5)
    for step in steps:
        _interrupt(step.proc)  # anything left: stopped, and its check says what it lacked


def _check(step: Step, cwd: Path) -> None:
    out, status, words = step.output(), step.proc.returncode, step.argv
    where = f"{step.line} (as {step.user}): exit {status}\n{out[-3000:]}"
    assert "Traceback" not in out, where
    if words[0] == "param" and step.user == "monitor":
        lines = [line for line in out.splitlines() if line.strip()]
        assert status == 2 and len(lines) == 1, where
        assert lines[0].startswith("followbus: param refused: ") and "user monitor" in lines[0], where
        return
    interrupted = words[0] in ("hz", "foxglove", "record") or (words[0] == "monitor" and "--once" not in words)
    assert status in ((0, 130, -signal.SIGINT) if interrupted else (0,)), where
    if words[0] == "param" and words[1] == "set":
        assert f"{words[2]}: " in out and f"-> {words[3]}" in out, where
    elif words[0] == "echo":
        assert out.count(f"{words[1]}: ") == int(words[words.index("-n") + 1]), where
    elif words[0] == "nodes":
        assert {"capture", "detection", "prediction", "motor"} <= {line.split()[0] for line in out.splitlines()
                                                                    if line.split()}, where
    elif words[0] == "topics":
        assert "fb/motor/command" in out, where
    elif words[0] == "record":
        from followbus.bus.recording import iter_bus_messages

        keys = {msg.key for msg in iter_bus_messages(cwd / words[words.index("-o") + 1])}
        assert {"fb/motor/command", "fb/prediction/track"} <= keys, (where, keys)
    elif words[0] == "play":
        assert "published " in out, where


@pytest.mark.skipif(REASON is not None, reason=f"two network namespaces: {REASON}")
def test_every_command_of_the_laptop_section_from_another_namespace(tmp_path):
    laptop = tmp_path / "laptop"  # no graph.yaml here: every command joins with what the block gives it
    laptop.mkdir()
    with NetnsPair() as pair:
        steps = readme_commands(f"tcp/{pair.addresses[0]}:{PORT}")
        assert {s.argv[0] for s in steps} >= {"monitor", "echo", "record", "param", "play"}, steps
        # What a later command needs: the recording play publishes, param set after the refused get.
        later = [s for s in steps if s.argv[0] == "play" or s.argv[:2] == ["param", "set"]]
        robot = Robot(pair, tmp_path, pair.addresses[0])
        try:
            robot.wait_ready()
            _run_all(pair, [s for s in steps if s not in later], laptop)
            for step in later:
                _run_all(pair, [step], laptop)
            for step in steps:
                _check(step, laptop)
        finally:
            robot.stop()
