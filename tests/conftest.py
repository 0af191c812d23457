"""Shared test helpers: loopback ports, graph files, running the followbus CLI as a real process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def followbus_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "followbus.tools.cli", *args]


def run_followbus(*args: str, timeout: float = 120, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(followbus_argv(*args), capture_output=True, text=True, timeout=timeout,
                          cwd=cwd or REPO, stdin=subprocess.DEVNULL)


def wait_until(predicate: Callable[[], bool], timeout: float, interval: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return predicate()


def processes_matching(text: str) -> list[int]:
    """PIDs whose command line contains ``text`` (to prove nothing outlived a launcher)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().split(")")[-1].split()[0]
        except OSError:
            continue
        if text in cmdline and state != "Z":
            pids.append(int(entry.name))
    return pids


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def graph_file(tmp_path: Path, port: int) -> Callable[[str], Path]:
    """Write a graph whose zenoh block uses a private loopback port; returns its path."""

    def write(nodes_yaml: str, name: str = "graph.yaml", namespace: str = "t") -> Path:
        text = (f"name: test\nnamespace: {namespace}\n"
                f"zenoh:\n  listen: [tcp/127.0.0.1:{port}]\n  connect: [tcp/127.0.0.1:{port}]\n"
                f"nodes:\n{nodes_yaml}")
        path = tmp_path / name
        path.write_text(text)
        return path

    return write
