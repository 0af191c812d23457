"""Issue 15 (parts 2, 3, 6): a user's mistake is one line on stderr and exit status 2, never a traceback,
and it is found before anything starts; a run that went wrong (a node crash-looped, stayed silent, a
replay compared nothing) exits 1 with one line that says which. Every case is the real `followbus`
command as a subprocess, against real Zenoh sessions on loopback where a bus is involved."""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import re
import select
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh

from followbus.bus.node_params import ParamError
from followbus.bus.schemas import Tick
from followbus.nodes.capture import CaptureParams
from followbus.tools.recording.mcap_io import RecordingWriter
from followbus.vision.models import MODELS_ENV
from followbus.vision.sources import SourceError, check_source, open_source

from .conftest import REPO, followbus_argv, free_port, refusing_endpoint, run_followbus, wait_until

pytestmark = pytest.mark.slow

CAPTURE = """\
  capture:
    run: followbus.nodes.capture
    outputs: [frame]
    params: {{source: "{source}"}}
"""
DIAG = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 20}
  relay:
    run: followbus.nodes.diagnostics_relay
    inputs: {tick: ticker/tick}
    outputs: [tick]
"""
USERS = "robot:robot-secret\nmonitor:monitor-secret\n"


def one_error_line(result: subprocess.CompletedProcess, status: int = 2) -> str:
    """The run's only stderr line (asserting the status and that there is no traceback)."""
    assert result.returncode == status, result.stdout[-3000:] + result.stderr[-3000:]
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def private_graph_copy(tmp_path: Path) -> Path:
    """graph.yaml on a private loopback port and namespace."""
    port = free_port()
    text = (REPO / "graph.yaml").read_text().replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}")
    path = tmp_path / "graph.yaml"
    path.write_text(text.replace("namespace: fb", "namespace: t"))
    return path


def garbage_images(folder: Path) -> Path:
    folder.mkdir(parents=True)
    for name in ("0001.jpg", "0002.jpg"):
        (folder / name).write_bytes(np.random.default_rng(0).bytes(400))
    return folder


# ----------------------------------------------------------------------------- the capture source


def source_cases(tmp_path: Path) -> list[tuple[str, str]]:
    return [
        (str(tmp_path / "missing.mcap"), "MCAP source '{src}': No such file or directory"),
        (str(tmp_path / "missing.mp4"), "source '{src}': no such file or directory"),
        ("scene:corridor", "unknown scene 'corridor' in 'scene:corridor' (did you mean 'corridor-occlusion'?); "
                           "available: corridor-occlusion, lookalike,"),
        ("camera:99", "source 'camera:99': /dev/video99 does not exist (video devices here:"),
        (str(garbage_images(tmp_path / "imgs")), "source '{src}': cannot read image"),
    ]


def test_check_and_launch_refuse_a_source_that_cannot_open(tmp_path, graph_file):
    if not sys.platform.startswith("linux"):
        pytest.skip("the camera check looks for /dev/videoN")
    for source, message in source_cases(tmp_path):
        message = message.format(src=source)
        graph = graph_file(CAPTURE.format(source=source))
        params_line = next(i for i, ln in enumerate(graph.read_text().splitlines(), 1) if "params:" in ln)
        line = one_error_line(run_followbus("check", str(graph)))
        # From the file: its line (the capture params); from --set: the --set as typed.
        assert line.startswith(f"followbus: {graph}:{params_line}: node 'capture': {message}"), line
        other = graph_file(CAPTURE.format(source="scene:lookalike"), name="ok.yaml")
        line = one_error_line(run_followbus("check", str(other), "--set", f"capture.source={source}"))
        assert line.startswith(f"followbus: --set capture.source={source}: {message}"), line
    # launch checks before it starts anything: no node process, no crash loop, status 2 at once.
    result = run_followbus("launch", str(graph_file(CAPTURE.format(source="scene:corridor"), name="l.yaml")),
                           "--duration", "10", timeout=60)
    assert "unknown scene 'corridor'" in one_error_line(result)
    assert "started capture" not in result.stdout + result.stderr
    ok = run_followbus("check", str(graph_file(CAPTURE.format(source="scene:lookalike"), name="ok2.yaml")))
    assert ok.returncode == 0 and ok.stdout.strip().endswith("ok (1 nodes)"), ok.stdout + ok.stderr


def test_source_errors_in_process(tmp_path):
    with pytest.raises(SourceError, match="no such file or directory"):
        open_source(str(tmp_path / "missing.mp4"))  # was "unknown source spec"
    with pytest.raises(SourceError, match="unknown source spec 'scen:lookalike'"):
        check_source("scen:lookalike")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(SourceError, match="is a file but not a video"):
        check_source(str(tmp_path / "notes.txt"))
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file")
    with pytest.raises(SourceError, match="is an MCAP recording: the capture node reads it"):
        check_source(str(tmp_path / "junk.mcap"))  # vision/ knows no recordings: bus/recording.py reads them
    with pytest.raises(ParamError, match=r"MCAP source '.*junk.mcap': not an MCAP file$"):
        CaptureParams(source=str(tmp_path / "junk.mcap")).check()
    check_source("scene:lost-target")


# ----------------------------------------------------------------------------- --set


def test_set_errors_name_the_option_not_a_line(graph_file):
    graph = graph_file(CAPTURE.format(source="scene:lookalike"))
    line = one_error_line(run_followbus("check", str(graph), "--set", "captur.source=scene:lookalike"))
    assert line == (f"followbus: {graph}: --set captur.source=scene:lookalike: no node named 'captur' to set "
                    "'source' on (nodes: capture)")
    assert ":?:" not in line
    line = one_error_line(run_followbus("launch", str(graph), "--set", "capture.sourc=x", "--duration", "5"))
    assert line.startswith("followbus: --set capture.sourc=x: unknown parameter 'sourc' (known: "), line
    line = one_error_line(run_followbus("check", str(graph), "--set", "capture.source"))
    assert line == f"followbus: {graph}: --set capture.source: must look like node.param=value"
    # The robot's graph: a track age limit below 0 would refuse every track (a robot that never follows).
    line = one_error_line(run_followbus("check", str(REPO / "graph.yaml"), "--set", "motor.max_track_age_ms=-5"))
    assert "max_track_age_ms must be >= 0 (0: no limit), not -5.0" in line, line
    # A state file the node could not write is said by check and launch, not by the node on every save.
    line = one_error_line(run_followbus("check", str(REPO / "graph.yaml"), "--set", "template.state_file=/proc/t.npz"))
    assert line == ("followbus: --set template.state_file=/proc/t.npz: state_file /proc/t.npz: cannot write in /proc: "
                    "No such file or directory (the node could not keep its state there)"), line


# ----------------------------------------------------------------------------- launch --duration


def test_launch_duration_fails_when_a_node_crash_loops(graph_file):
    graph = graph_file(DIAG.replace("rate_hz: 20}", "rate_hz: 20, fail_after_s: 0.2}\n"
                                    "    restart: {policy: on-failure, max_restarts: 50, backoff_ms: 50}"))
    result = run_followbus("launch", str(graph), "--duration", "5", timeout=90)
    assert result.returncode == 1, result.stdout[-3000:] + result.stderr[-3000:]
    line = result.stderr.strip().splitlines()[-1]
    assert re.match(r"followbus launch: ticker crash-looped \(exited \d+ times, last status 3\): .*ERROR .*"
                    r"fault injection: failing on purpose", line), line
    assert "Traceback" not in result.stderr


def test_launch_duration_fails_when_a_node_never_publishes(graph_file):
    graph = graph_file(DIAG)
    result = run_followbus("launch", str(graph), "--only", "relay", "--duration", "3", timeout=60)
    assert result.returncode == 1, result.stdout[-3000:] + result.stderr[-3000:]
    assert result.stderr.strip().splitlines()[-1] == "followbus launch: no output in 3 s from relay"


# ----------------------------------------------------------------------------- demo


def test_demo_unknown_scene_is_one_line_before_launching(tmp_path):
    graph = private_graph_copy(tmp_path)
    result = run_followbus("demo", "--graph", str(graph), "--scene", "lookalik", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith("followbus: --scene lookalik: unknown scene 'lookalik' in 'scene:lookalik' (did you "
                           "mean 'lookalike'?)"), line
    assert "launching" not in result.stdout and not (tmp_path / "state").exists()


def test_demo_that_captured_nothing_fails_with_its_own_log(tmp_path):
    graph = private_graph_copy(tmp_path)
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "demo.log").write_text("an older run\n")
    result = run_followbus("demo", "--graph", str(graph), "--set", "detection.backend=simulated", "--duration",
                           "0.5", cwd=tmp_path, timeout=60)
    assert result.returncode == 1, result.stdout + result.stderr
    logs = sorted((tmp_path / "state").glob("demo-*.log"))
    assert len(logs) == 1 and re.fullmatch(r"demo-\d{8}-\d{6}\.log", logs[0].name), logs
    assert f"node logs: state/{logs[0].name}" in result.stdout
    first = result.stderr.strip().splitlines()[0]
    # Half a second after start-up nothing has come through the loop (capture holds frame 0 for 0.5 s).
    assert first.startswith(("followbus demo: 0 frames captured", "followbus demo: no output in 1 s from")), first
    assert (tmp_path / "state" / "demo.log").read_text() == "an older run\n"


def test_demo_verdict_puts_a_failed_node_before_what_it_caused():
    """Beside a second graph the crashing motor's restarts outlasted the start-up wait: no frame came through and the
    graph was not up, and the verdict began with those instead of with the motor that caused them."""
    import threading
    from types import SimpleNamespace

    from followbus.tools.demo import _cause_first

    failed = "motor failed for good (exited 3 times, last status 1): FileNotFoundError: ttyNOPE"
    silent = "no output in 6 s from reid, motor"
    launcher = SimpleNamespace(failures=lambda: [failed], silences=lambda: [silent], interrupted=False,
                               problems=lambda: [failed, silent], ready_event=threading.Event(), ran_s=6.0)
    assert _cause_first(launcher, frames=0) == [
        failed, "0 frames captured", "the graph was not up after 6 s (start-up takes a few seconds)", silent]
    launcher.ready_event.set()
    assert _cause_first(launcher, frames=120) == [failed, silent]
    launcher.failures = lambda: []  # nothing failed: the missing frames lead
    assert _cause_first(launcher, frames=0) == ["0 frames captured", silent]


def test_demo_names_the_node_that_crashed_and_why(tmp_path):
    graph = private_graph_copy(tmp_path)
    # Two restarts rather than graph.yaml's ten with a doubling backoff (~25 s): the verdict is the same.
    text = graph.read_text()
    motor_restart = "restart: {policy: on-failure, max_restarts: 10, backoff_ms: 200}"
    assert motor_restart in text
    graph.write_text(text.replace(motor_restart, "restart: {policy: on-failure, max_restarts: 2, backoff_ms: 200}"))
    result = run_followbus("demo", "--graph", str(graph), "--set", "detection.backend=simulated", "--set",
                           "motor.driver=serial", "--set", f"motor.port={tmp_path / 'ttyNOPE'}", "--set",
                           f"template.state_file={tmp_path / 'template.npz'}", "--duration", "6", cwd=tmp_path,
                           timeout=90)
    assert result.returncode == 1, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()  # the launcher's warnings (restarts), then the verdict
    verdict = next(i for i, ln in enumerate(lines) if ln.startswith("followbus demo: "))
    assert lines[verdict].startswith("followbus demo: motor "), result.stderr
    assert "(node logs: state/demo-" in lines[verdict]
    # The reason, from this run's log: its last error lines.
    assert any("[motor" in ln and "No such file or directory" in ln and "ttyNOPE" in ln
               for ln in lines[verdict + 1:]), lines
    assert "Traceback" not in result.stderr


# ----------------------------------------------------------------------------- no graph running


def test_introspection_without_a_graph_says_so(tmp_path):
    commands = [("topics",), ("echo", "t/x"), ("hz", "t/x"), ("nodes",)]
    with refusing_endpoint() as endpoint:
        procs = [subprocess.Popen(followbus_argv(*cmd, "--connect", endpoint, "--connect-timeout", "1"),
                                  cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  stdin=subprocess.DEVNULL)
                 for cmd in commands]
        ended = [(cmd, proc, *proc.communicate(timeout=60)) for cmd, proc in zip(commands, procs, strict=True)]
    for cmd, proc, out, err in ended:
        line = one_error_line(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
        assert line == (f"followbus: no graph is running on {endpoint}: start one with `followbus launch` or "
                        "`followbus router` (or join another with --connect tcp/HOST:PORT)"), (cmd, line)


def test_play_without_a_graph_is_one_line(tmp_path):
    path = tmp_path / "ticks.mcap"
    writer = RecordingWriter(path)
    channel = writer.bus_channel("t/ticker/tick", "Tick")
    for i in range(3):
        tick = Tick(value=i)
        tick.header.stamp_ns, tick.header.seq = 1_700_000_000_000_000_000 + i * 10**8, i
        writer.write(channel, tick.header.stamp_ns, tick.encode())
    writer.finish()
    with refusing_endpoint() as endpoint:
        line = one_error_line(run_followbus("play", str(path), "--connect", endpoint, "--connect-timeout", "1"))
    # The one "no graph is running" form, not zenoh's raw error with a Rust source path (issue 23).
    assert line.startswith(f"followbus: no graph is running on {endpoint}: start one with") and ".rs" not in line


@pytest.fixture
def router():
    """`followbus router` on a private loopback port; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(followbus_argv("router", "--listen", endpoint, "--duration", "60"),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, stdin=subprocess.DEVNULL)
    try:
        assert "listening" in proc.stdout.readline()
        yield endpoint
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_echo_and_hz_give_up_after_timeout(router):
    for cmd in ("echo", "hz"):
        started = time.monotonic()
        result = run_followbus(cmd, "t/nothing", "--connect", router, "--timeout", "1", timeout=30)
        assert one_error_line(result, status=1) == ("followbus: no message on t/nothing in 1 s (`followbus topics` "
                                                    "lists the keys with traffic)")
        assert time.monotonic() - started < 20  # it gave up instead of waiting forever


# ----------------------------------------------------------------------------- authentication


@pytest.fixture
def auth_router(tmp_path):
    """A Zenoh router that requires user/password (transport/auth/usrpwd), in this process."""
    users = tmp_path / "users.txt"
    users.write_text(USERS)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    for key, value in (("mode", "router"), ("scouting/multicast/enabled", False), ("listen/endpoints", [endpoint]),
                       ("transport/auth/usrpwd", {"user": "robot", "password": "robot-secret",
                                                  "dictionary_file": str(users)})):
        conf.insert_json5(key, json.dumps(value))
    session = zenoh.open(conf)
    try:
        yield endpoint
    finally:
        session.close()


def test_monitor_names_a_missing_or_wrong_password(auth_router, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "FOLLOWBUS_ZENOH_PASSWORD"}

    def monitor(*extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(followbus_argv("monitor", "--connect", auth_router, "--user", "monitor", "--once",
                                             "--seconds", "1", *extra), capture_output=True, text=True, timeout=60,
                              cwd=tmp_path, env=env, stdin=subprocess.DEVNULL)

    assert one_error_line(monitor()) == ("followbus: --user monitor needs a password: pass --password or set "
                                         "$FOLLOWBUS_ZENOH_PASSWORD (or run in a terminal to be asked)")
    assert one_error_line(monitor("--password", "wrong", "--connect-timeout", "1")) == (
        f"followbus: authentication failed for user monitor on {auth_router} (wrong or missing password)")
    good = monitor("--password", "monitor-secret")
    assert "Traceback" not in good.stderr and "connected" in good.stdout.splitlines()[0], good.stdout + good.stderr
    # Without any user: the graph refuses us, and says it wants authentication.
    line = one_error_line(run_followbus("topics", "--connect", auth_router, "--connect-timeout", "1", cwd=tmp_path))
    assert line == (f"followbus: {auth_router} refused the connection: the graph requires authentication "
                    "(--user and --password, or $FOLLOWBUS_ZENOH_PASSWORD)")


def test_monitor_asks_for_the_password_on_a_terminal(auth_router, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "FOLLOWBUS_ZENOH_PASSWORD"}
    master, slave = os.openpty()

    def controlling_tty() -> None:  # getpass reads /dev/tty: the pty must be the child's terminal
        os.setsid()
        fcntl.ioctl(slave, termios.TIOCSCTTY, 0)

    proc = subprocess.Popen(followbus_argv("monitor", "--connect", auth_router, "--user", "monitor", "--once",
                                           "--seconds", "1"), stdin=slave, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env, preexec_fn=controlling_tty)
    os.close(slave)
    seen = b""
    try:
        def prompted() -> bool:
            nonlocal seen
            if select.select([master], [], [], 0.1)[0]:
                with contextlib.suppress(OSError):
                    seen += os.read(master, 1024)
            return b"zenoh password for monitor:" in seen

        assert wait_until(prompted, 30), seen
        os.write(master, b"monitor-secret\n")
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
    assert "Traceback" not in err and "authentication failed" not in err, err
    assert "connected" in out.splitlines()[0], out + err


# ----------------------------------------------------------------------------- eval


def test_eval_without_a_model_points_at_the_simulated_detector(tmp_path):
    code = ("import sys; import followbus.vision.models as m; from pathlib import Path; "
            f"m.REPO_ROOT = Path({str(tmp_path / 'repo')!r}); "
            "from followbus.tools.cli import main; sys.exit(main(sys.argv[1:]))")
    env = {k: v for k, v in os.environ.items() if k != MODELS_ENV}
    result = subprocess.run([sys.executable, "-c", code, "eval", "scene:wall-occlusion", "--out",
                             str(tmp_path / "out"), "--max-frames", "3"], capture_output=True, text=True,
                            timeout=120, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL)
    line = one_error_line(result)
    params = yaml.safe_load((REPO / "graph.yaml").read_text())["nodes"]["detection"]["params"]
    model = ("yolox_nano_dynamic.onnx" if params.get("input_shape") == "fit"
             else f"yolox_nano_{params['input_size_px']}.onnx")
    # eval's default detector is graph.yaml's (backend auto)
    assert line.startswith(f"followbus: detector backend 'auto' needs the YOLOX model {model}, "
                           "which is missing"), line
    assert line.endswith("; or score without a model: --detector simulated (ground truth + noise)"), line


def test_eval_folder_that_is_not_a_sequence_and_data_root(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "a.txt").write_text("x")
    line = one_error_line(run_followbus("eval", str(folder), "--out", str(tmp_path / "out")))
    assert line == (f"followbus: {folder}: not a sequence folder (followbus/LaSOT: img/ + groundtruth.txt; OTB: "
                    "img/ + groundtruth_rect.txt; GOT-10k: frames + groundtruth.txt; MOTChallenge: img1/ + gt/gt.txt)")
    (folder / "img").mkdir()
    line = one_error_line(run_followbus("eval", str(folder), "--out", str(tmp_path / "out")))
    assert line == (f"followbus: {folder}: img/ has no ground truth beside it: groundtruth.txt (followbus, LaSOT) "
                    "or groundtruth_rect.txt (OTB) is missing")
    env = dict(os.environ, FOLLOWBUS_DATA=str(folder))
    result = subprocess.run(followbus_argv("eval", "all", "--out", str(tmp_path / "out")), capture_output=True,
                            text=True, timeout=60, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL)
    assert one_error_line(result) == f"followbus: FOLLOWBUS_DATA={str(folder)!r} has no sot/ or mot/ directory"


# ----------------------------------------------------------------------------- replay --verify


def test_replay_verify_with_nothing_compared_fails(tmp_path):
    graph = ("name: test\nnamespace: t\nnodes:\n  ticker: {run: followbus.nodes.diagnostics, outputs: [tick]}\n"
             "  relay: {run: followbus.nodes.diagnostics_relay, inputs: {tick: ticker/tick}, outputs: [tick]}\n")
    path = tmp_path / "inputs-only.mcap"  # the relay's inputs were recorded, its outputs were not
    writer = RecordingWriter(path)
    writer.metadata("graph", {"yaml": graph})
    writer.metadata("followbus", {"namespace": "t"})
    channel = writer.bus_channel("t/ticker/tick", "Tick")
    for i in range(5):
        tick = Tick(value=i)
        tick.header.stamp_ns, tick.header.frame_seq, tick.header.seq = 1_700_000_000_000_000_000 + i * 10**8, i, i
        writer.write(channel, tick.header.stamp_ns, tick.encode())
    writer.finish()
    result = run_followbus("replay", str(path), "--node", "relay", "--verify", "--no-progress", timeout=120)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "0 compared" in result.stdout
    assert result.stdout.strip().splitlines()[-1].startswith("verify: FAILED: nothing compared"), result.stdout
    assert "verify: OK" not in result.stdout


def test_replay_mistakes_are_one_line(tmp_path):
    graph = ("name: test\nnamespace: t\nnodes:\n  ticker: {run: followbus.nodes.diagnostics, outputs: [tick]}\n"
             "  relay: {run: followbus.nodes.diagnostics_relay, inputs: {tick: ticker/tick}, outputs: [tick]}\n"
             "  sink: {run: followbus.nodes.diagnostics_sink, inputs: {tick: relay/tick}}\n")
    path = tmp_path / "r.mcap"
    writer = RecordingWriter(path)
    writer.metadata("graph", {"yaml": graph})
    writer.metadata("followbus", {"namespace": "t"})
    tick = Tick(value=0)
    tick.header.stamp_ns, tick.header.frame_seq = 1_700_000_000_000_000_000, 0
    writer.write(writer.bus_channel("t/ticker/tick", "Tick"), tick.header.stamp_ns, tick.encode())
    writer.finish()
    cases = {
        ("--node", "relay,sink", "--isolated"): "followbus: --isolated replays one node (several run in-process only)",
        ("--node", "relay,sink", "--param", "add=1"): "followbus: --param add=1: must look like node.param=value",
        ("--node", "ticker"): "followbus: ticker: no inputs from outside: there is nothing to replay into",
        ("--node", "relay", "--param", "add=[1"): "followbus: --param add=[1: the value is not valid YAML (expected "
                                                  "',' or ']', but got '<stream end>')",
    }
    for args, expected in cases.items():
        assert one_error_line(run_followbus("replay", str(path), *args, "--no-progress")) == expected, args
    line = one_error_line(run_followbus("replay", str(tmp_path / "missing.mcap"), "--node", "relay"))
    assert line == f"followbus: {tmp_path / 'missing.mcap'}: No such file or directory"


# ----------------------------------------------------------------------------- the table of commands


def test_help_builds_the_table_without_importing_the_work():
    """`followbus --help` names every command from the table; no handler module (numpy, zenoh, mcap...) is loaded,
    and only the chosen command gets its arguments."""
    code = ("import sys; from followbus.tools.cli import COMMANDS, build_parser; "
            "text = build_parser(['--help']).format_help(); "
            "assert all(c.name in text and c.help in text for c in COMMANDS), text; "
            "print(sorted(m for m in ('numpy', 'zenoh', 'mcap', 'cv2', 'rich', 'yaml') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                            env={**os.environ, "COLUMNS": "200"})  # one line a command
    assert result.returncode == 0 and result.stdout.strip() == "[]", result.stdout + result.stderr


def _leaves(commands, prefix=()):
    """(words, command) of every runnable command: `bench chaos` is ("bench", "chaos")."""
    for c in commands:
        yield from _leaves(c.subcommands, (*prefix, c.name)) if c.subcommands else [((*prefix, c.name), c)]


def test_every_command_has_a_help_and_a_handler():
    from followbus.tools.cli import COMMANDS, build_parser
    from followbus.tools.command import Lazy

    for words, command in _leaves(COMMANDS):
        parser = build_parser(list(words))
        with pytest.raises(SystemExit) as done:
            parser.parse_args([*words, "--help"])
        assert done.value.code == 0
        required = {"node": ["n"], "echo": ["k"], "hz": ["k"], "play": ["f"], "replay": ["f", "--node", "n"],
                    "info": ["f"], "recover": ["f"], "logs": ["n"], "get": ["n.p"],
                    "set": ["n.p", "1"], "record-views": ["f"]}.get(words[-1], [])
        assert parser.parse_args([*words, *required]).run is command.run, words
        if isinstance(command.run, Lazy):  # a handler imported when it runs: it must be there
            assert callable(command.run.resolve()), words


def test_a_command_with_subcommands_requires_one():
    result = run_followbus("bench", timeout=30)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.strip().splitlines()[-1] == ("followbus bench: error: the following arguments are "
                                                      "required: WHAT")


def test_a_reader_that_stops_early_ends_the_command_quietly():
    """`followbus info F | head -1`: the reader is gone while the command still writes; the command stops with
    status 0 and no traceback, as any Unix tool does. (Here the reading end is closed before the command has
    written anything, so its first write meets the closed pipe.)"""
    proc = subprocess.Popen([sys.executable, "-m", "followbus.tools.cli", "schema"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err


@pytest.mark.parametrize("argv, option", [
    (["hz", "fb/capture/frame", "--seconds", "-1"], "--seconds"),  # hz said nothing and exited 1
    (["topics", "--seconds", "0"], "--seconds"),  # "no messages in 0.0 s", exit 1
    (["echo", "fb/**", "-n", "0"], "-n/--count"),
    (["record", "--duration", "nan"], "--duration"),
    (["play", "x.mcap", "--rate", "0"], "--rate"),
    (["replay", "x.mcap", "--node", "relay", "--timeout", "0"], "--timeout"),
    (["eval", "scene:overlay", "--jitter-px", "-1"], "--jitter-px"),
    (["eval", "scene:overlay", "--jitter-px", "inf"], "--jitter-px"),
    (["eval", "scene:overlay", "--max-frames", "1.5"], "--max-frames"),
    (["monitor", "--web", "70000"], "--web"),
    (["launch", "graph.yaml", "--grace", "-1"], "--grace"),
    (["bench", "chaos", "--repeat", "0"], "--repeat"),
    (["echo", "fb/*a*", "-n", "1"], "key"),  # a traceback from the subscriber, exit 1
    (["hz", "fb//frame"], "key"),
    (["play", "x.mcap", "--topics", "fb/**", "fb/"], "--topics"),
    (["record", "--exclude", "*frame"], "--exclude"),
    (["bench", "bus", "--json", "/proc/bus.json"], "--json"),  # written after the benchmark's minutes
    (["launch", "graph.yaml", "--record", "/proc/run.mcap"], "--record"),  # the recorder failed once the graph ran
    (["record", "-o", "/"], "-o/--output"),
    (["topics", "--namespace", "fb*x"], "--namespace"),  # waited on keys no graph can publish
    (["bench", "chaos", "--namespace", "a/b/"], "--namespace"),
])
def test_a_number_or_key_that_makes_no_sense_is_one_line_before_anything_starts(argv, option):
    """Nothing joins the bus or loads a graph: a negative duration, a count of 0, a NaN, a port past 65535 or a
    malformed key expression is said at once, naming the option (not a command that ends at once, or waits
    forever, in silence, nor a traceback)."""
    result = run_followbus(*argv, timeout=30)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert f"error: argument {option}: " in result.stderr.strip().splitlines()[-1], result.stderr


@pytest.mark.parametrize("argv, option", [(["launch", "graph.yaml", "--log-dir", "/proc/logs", "--duration", "2"],
                                            "--log-dir"),  # a traceback per node in the launcher's threads
                                           (["eval", "scene:overlay", "--out", "/proc/results"], "--out")])
def test_an_output_directory_that_cannot_be_made_is_one_line_before_anything_starts(argv, option):
    result = run_followbus(*argv, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    path = argv[argv.index(option) + 1]
    assert result.stderr.strip() == f"followbus: {option} {path}: cannot create {path}: No such file or directory"
    assert "started" not in result.stdout + result.stderr


def test_every_number_a_command_takes_is_checked_by_its_type():
    """Every float option of every command is a checked amount (tools/command.py: positive, non_negative), every
    int option a checked count or port, but for the few whose every value means something; every --namespace a
    checked key prefix."""
    from followbus.tools import command as checked
    from followbus.tools.cli import COMMANDS, build_parser

    unchecked_ints = {"--seed", "--laptop-nice", "--drop-wait-us", "--jpeg-quality"}
    types = {checked.positive, checked.non_negative, checked.count, checked.count_or_zero, checked.port,
             checked.bus_namespace}

    seen = set()
    for words, _command in _leaves(COMMANDS):
        parser = build_parser(list(words))
        for sub in words:
            parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[sub]
        for action in parser._actions:
            name = max(action.option_strings, key=len, default=action.dest)
            if action.type in (float, int) and name not in unchecked_ints:
                pytest.fail(f"followbus {' '.join(words)} {name}: type={action.type.__name__}, unchecked")
            if name == "--namespace" and action.type is not checked.bus_namespace:
                pytest.fail(f"followbus {' '.join(words)} --namespace: not checked as a key prefix")
            seen |= {action.type} & types
    assert seen == types


def test_bench_egomotion_refuses_a_scene_without_a_known_camera_shift():
    line = one_error_line(run_followbus("bench", "egomotion", "--scenes", "shaky,lookalike"))
    assert "lookalike" in line and "bumpy, shaky, overlay" in line
