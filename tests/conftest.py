"""Shared test helpers: loopback ports, graph files, running the followbus CLI as a real process."""

from __future__ import annotations

import atexit
import contextlib
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"

# The run records of the graphs tests launch (tools/runs/claims.py) stay out of the user's ~/.local/state. Each
# pytest-xdist worker keeps its own (it would inherit the controller's): a test's `ps`, or `down NAME`, must
# neither see nor stop the other worker's graphs, as on two machines.
if "FOLLOWBUS_RUNS" not in os.environ or os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["FOLLOWBUS_RUNS"] = tempfile.mkdtemp(prefix="followbus-test-runs-")
    atexit.register(shutil.rmtree, os.environ["FOLLOWBUS_RUNS"], True)

# The tests play a user at a terminal, whose Ctrl-C reaches the command. A suite started as a background job (`&`,
# nohup) starts with SIGINT ignored, which every process it spawns would inherit (a command keeps an ignored SIGINT
# ignored, as a background job's should: tools/cli.py): a handler here resets it to the default in the children.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def free_port(span: int = 4) -> int:
    """A loopback port P with P..P+span-1 free (a graph's domains 1.. move its port up by one each), below the
    kernel's ephemeral range: there no outgoing connection (another test's graph forming its mesh) can take the port
    of a graph about to start, which then never forms (RELIABILITY.md, "A split graph")."""
    from followbus.tools.connect import ephemeral_port_range

    low = (ephemeral_port_range() or (32768, 60999))[0]
    rng = random.SystemRandom()
    for _ in range(1000):
        port = rng.randrange(max(low // 2, 1024), low - span)
        if all(_bindable(port + i) for i in range(span)):
            return port
    raise RuntimeError(f"no {span} free loopback ports in a row below {low}")


def _bindable(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@contextlib.contextmanager
def refusing_endpoint() -> Iterator[str]:
    """A loopback endpoint where no graph runs while the block lasts. Its port stays bound and not listening, so
    it refuses: a free port released at once can become another test's graph (the other pytest worker's)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as bound:
        bound.bind(("127.0.0.1", 0))
        yield f"tcp/127.0.0.1:{bound.getsockname()[1]}"


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


def copy_recording(src: Path, dst: Path, *, keep: Callable[[object, object], bool] | None = None,
                   relabel: Callable[[object, object], tuple[str, bytes, str]] | None = None,
                   rewrite: Callable[[object, bytes], bytes] | None = None, library: str = "test") -> None:
    """Rewrite an MCAP recording as a test needs it: ``keep(channel, message)`` drops messages (a recorder that
    missed some), ``relabel(schema, channel)`` gives (schema encoding, schema data, message encoding) for a
    channel with a schema (older labels), ``rewrite(channel, data)`` a message's data (the bytes older
    recordings stored); metadata is copied as it is."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from followbus.bus.recording import read_metadata

    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out)
        writer.start(profile="", library=library)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if keep is not None and not keep(channel, message):
                continue
            if channel.id not in channel_ids:
                sid, encoding = 0, channel.message_encoding
                if schema is not None:
                    schema_encoding, data = schema.encoding, schema.data
                    if relabel is not None:
                        schema_encoding, data, encoding = relabel(schema, channel)
                    if schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(schema.name, schema_encoding, data)
                    sid = schema_ids[schema.id]
                channel_ids[channel.id] = writer.register_channel(channel.topic, encoding, sid, dict(channel.metadata))
            data = message.data if rewrite is None else rewrite(channel, message.data)
            writer.add_message(channel_ids[channel.id], message.log_time, data, message.publish_time,
                               message.sequence)
        for name, data in read_metadata(src).items():
            writer.add_metadata(name, data)
        writer.finish()


# Under `pytest -n 2 --dist loadgroup` (make test) every module runs whole on one worker (its module-scoped
# graphs and recordings are made once), and the modules whose live graphs judge timing (the watchdog's stop,
# recovery bounds, a bench's message counts) share one group: they run one after another, never two at once on
# a two-core machine, while the other worker runs the rest.
TIMING_SENSITIVE_MODULES = frozenset({
    "test_chaos", "test_graph_tracking", "test_graph_group", "test_bench_bus", "test_security", "test_ros2",
    "test_record_replay", "test_link", "test_two_hosts", "test_laptop_section",
})


# tryfirst: xdist's own hook reads the xdist_group marks to name each test's group (pytest < 9.2: pyproject.toml).
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = item.module.__name__.rsplit(".", 1)[-1] if item.module is not None else item.nodeid
        group = "timing-sensitive" if module in TIMING_SENSITIVE_MODULES else module
        item.add_marker(pytest.mark.xdist_group(group))
