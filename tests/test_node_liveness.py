"""A node that stops working is seen and restarted (bus/liveness.py): a source whose poll raised was never polled
again (bus/node.py returned None, "no next poll", for an exception), while its process and token said "up"."""

from __future__ import annotations

import subprocess

import pytest

from followbus.bus.graph import load_graph
from followbus.bus.inproc import InProcessGraph
from followbus.bus.liveness import STOPPED_WORKING_EXIT, FailureBudget, ProductionWatch

from .conftest import followbus_argv

TICKER = """\
  ticker:
    run: followbus.nodes.diagnostics
    outputs: [tick]
    params: {{rate_hz: 20, {params}}}
    restart: {{policy: on-failure, max_restarts: 4, backoff_ms: 100}}
  sink: {{run: followbus.nodes.diagnostics_sink, inputs: {{tick: ticker/tick}}}}
"""


def test_a_source_whose_poll_raises_once_recovers(graph_file):
    graph = load_graph(graph_file(TICKER.format(params="raise_once_at: 3")))
    with InProcessGraph(graph) as g:
        g.run_for(2_000_000_000)
        values = [t.value for t in g.outputs("ticker", "tick")]
        status = g.status("ticker")
    assert values[:3] == [0, 1, 2] and len(values) > 20, values  # on main: [0, 1, 2] and nothing after
    assert status["extra"]["handler_errors"] == 1 and status["extra"]["poll_failures"] == 0, status


def test_backoff_doubles_and_the_budget_is_bounded():
    budget = FailureBudget(limit=4, first_backoff_s=0.05, max_backoff_s=0.15)
    assert [budget.failed() for _ in range(3)] == [0.05, 0.1, 0.15] and not budget.exhausted
    budget.failed()
    assert budget.exhausted
    budget.succeeded()
    assert budget.streak == 0 and not budget.exhausted


def test_a_source_is_silent_only_past_many_of_its_own_periods():
    watch = ProductionWatch(periods=10, min_s=0.5)
    assert watch.silent_s(100.0) is None  # not armed before the first publication
    for i in range(20):
        watch.published(i * 0.1)
    assert watch.bound_s() == pytest.approx(1.0)
    assert watch.silent_s(1.9 + 0.9) is None and watch.silent_s(1.9 + 1.1) == pytest.approx(1.1)


@pytest.mark.slow
@pytest.mark.parametrize("fault, why", [("raise_from: 10", "poll failed 6 times in a row"),
                                        ("silent_from: 10", "published nothing for")])
def test_a_source_that_stops_working_is_restarted_and_launch_exits_nonzero(graph_file, fault, why):
    """Keeps raising, or keeps polling without publishing: the node exits with STOPPED_WORKING_EXIT, the launcher
    restarts it, and `launch --duration` says so and exits non-zero (on main: exit 0, ticker "up" throughout)."""
    graph = graph_file(TICKER.format(params=fault))
    result = subprocess.run(followbus_argv("launch", str(graph), "--duration", "8"), capture_output=True,
                            text=True, timeout=90, stdin=subprocess.DEVNULL)
    output = result.stdout + result.stderr
    assert result.returncode != 0, output
    assert why in output and f"ticker exited with status {STOPPED_WORKING_EXIT}" in output, output
    assert "restarting ticker" in output, output
    assert "followbus launch: ticker" in output, output
