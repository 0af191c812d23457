"""``followbus param get|set`` on a running node (bus/live_params.py): the value it runs with, a live-tunable one
changed and validated as at launch, the change in its status and on its parameter-events key (recorded)."""

from __future__ import annotations

import json
import re
import subprocess
import time

import pytest

from .conftest import REPO, followbus_argv, run_followbus

pytestmark = pytest.mark.slow

NODES = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {rate_hz: 20}
"""


def test_param_get_set_on_a_running_node(graph_file):
    graph = str(graph_file(NODES, namespace="o1lp"))
    up = run_followbus("up", graph, timeout=60)
    assert up.returncode == 0, up.stderr
    pid = re.search(r"pid (\d+)", up.stdout)[1]
    events = subprocess.Popen(followbus_argv("echo", "o1lp/ticker/parameter_events", "-n", "1", "--graph", graph,
                                             "--seconds", "30"), cwd=REPO, stdout=subprocess.PIPE, text=True,
                              stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    try:
        got = run_followbus("param", "get", "ticker.rate_hz", "--graph", graph)
        assert (got.returncode, got.stdout.strip()) == (0, "ticker.rate_hz = 20.0")
        # Set until the echo (a process that takes a moment to subscribe) has heard the event.
        deadline = time.monotonic() + 30
        while events.poll() is None and time.monotonic() < deadline:
            done = _set(graph, "5")
            assert done.returncode == 0 and done.stdout.strip().endswith("-> 5.0"), done.stderr
            time.sleep(1.0)
        assert run_followbus("param", "get", "ticker.rate_hz", "--graph", graph).stdout.strip() == \
            "ticker.rate_hz = 5.0"
        status = run_followbus("echo", "o1lp/@status/ticker", "-n", "1", "--graph", graph, "--timeout", "5")
        assert '"params_set": {"rate_hz": 5.0}' in status.stdout, status.stdout
        line = events.communicate(timeout=5)[0]
        event = json.loads(line.split(": ", 1)[1])
        assert event["state"] == "param_set" and event["extra"]["param"] == "rate_hz"
        assert event["extra"]["value"] == 5.0
        # Validated as at launch; a parameter the node does not declare live is refused; each one line, exit 2.
        for value, param, said in (("abc", "rate_hz", "must be float"), ("-1", "rate_hz", "rate_hz must be > 0"),
                                   ("3", "payload_bytes", "is not live-tunable (live: rate_hz)")):
            refused = run_followbus("param", "set", f"ticker.{param}", value, "--graph", graph)
            assert refused.returncode == 2 and said in refused.stderr and len(refused.stderr.splitlines()) == 1
        absent = run_followbus("param", "get", "nobody.x", "--graph", graph)
        assert absent.returncode == 2 and "node 'nobody' is not running in namespace o1lp" in absent.stderr
    finally:
        events.kill()
        events.wait()
        assert run_followbus("down", pid).returncode == 0


def _set(graph: str, value: str) -> subprocess.CompletedProcess:
    return run_followbus("param", "set", "ticker.rate_hz", value, "--graph", graph)


def test_reid_threshold_is_set_on_the_object_reid_reads():
    """The per-node params classes are plain dataclasses: a live value lands in the ReidParams the node's
    ReIdentifier reads on its next frame (a frozen class refused it), validated by that class as at launch."""
    import types

    from followbus.bus.graph import load_graph
    from followbus.bus.live_params import LiveParams
    from followbus.bus.node_checks import validate_node
    from followbus.bus.session import ZenohSettings, open_session
    from followbus.tracking.params import ReidParams
    from followbus.tracking.reid import ReIdentifier

    graph = load_graph(REPO / "graph.yaml")
    spec = graph.nodes["reid"]
    cls, params = validate_node(graph, spec)
    events = []
    session = open_session(ZenohSettings(listen=[], connect=[], shm=False))
    try:
        runtime = types.SimpleNamespace(session=session, graph=graph, spec=spec, cls=cls, params=params)
        live = LiveParams(runtime, lambda key, msg: events.append((key, msg)))
        reid_params = next(p for p in params if isinstance(p, ReidParams))
        reads = ReIdentifier(reid_params).params
        assert live.get("reid_threshold") == {"ok": True, "value": 0.75, "live": True}
        assert live.set("reid_threshold", 0.8)["ok"] and reads.reid_threshold == 0.8
        assert events and events[-1][0] == f"{graph.namespace}/reid/parameter_events"
        refused = live.set("reid_threshold", 1.5)
        assert not refused["ok"] and "must be in [0, 1]" in refused["error"] and reads.reid_threshold == 0.8
        assert "is not live-tunable" in live.set("lost_after_ms", 10.0)["error"]
        assert live.get("gate_chi2") == {"ok": False, "error": "node 'reid' has no parameter 'gate_chi2'"}
        live.close()
    finally:
        session.close()
