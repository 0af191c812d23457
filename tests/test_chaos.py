"""The chaos suite (issue 14): the launched tracking graph must survive faults, with tracking resumed,
0 unsafe motor commands and the watchdog's stop in time. The CI subset runs here on one launched graph;
``followbus bench chaos`` runs every fault (RELIABILITY.md). The first tests check the harness's own
judgement on made-up observations, so that a fault it calls survived really was."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from followbus.bus.codec import DecodeError
from followbus.bus.graph import load_graph
from followbus.bus.node_params import ParamError
from followbus.bus.schemas import SCHEMAS, decode
from followbus.reliability import faults as chaos
from followbus.reliability.chaos import ChaosRunner
from followbus.reliability.faults import CI_FAULTS, FAULTS, resolve_faults
from followbus.reliability.judging import (
    INJECTOR,
    ChaosOptions,
    CommandObs,
    FaultResult,
    Limits,
    TrackObs,
    TruthObs,
    first_follow_ns,
    format_headline,
    headline,
    on_target_fraction,
    tracking_coverage,
    watchdog_report,
)
from followbus.tools.bench.chaos import ChaosGraph

from .conftest import REPO, free_port, run_followbus

MS = 1_000_000
T0 = 1_000_000 * MS  # an arbitrary wall-clock origin for made-up observations


def _track(t_ms: float, state: str = "TRACKING", source: str = "prediction", seq: int = 0) -> TrackObs:
    return TrackObs(T0 + int(t_ms * MS), seq, T0 + int(t_ms * MS) - 30 * MS, state, source, T0 + int(t_ms * MS))


def _cmd(t_ms: float, vx: float = 0.2, reason: str = "tracking", seq: int = 0, stamp_ms: float | None = None,
         wz: float = 0.1) -> CommandObs:
    stamp = T0 + int((t_ms - 30 if stamp_ms is None else stamp_ms) * MS)
    wheels = (0.0,) * 4 if vx == 0 and wz == 0 else (1.0, 2.0, 1.0, 2.0)
    return CommandObs(T0 + int(t_ms * MS), seq, stamp, T0 + int(t_ms * MS), vx, 0.0, wz, wheels, None, None, reason)


def _stream(until_ms: float, state: str = "TRACKING") -> tuple[list[TrackObs], list[CommandObs]]:
    """Tracks and their commands every 33 ms up to ``until_ms``."""
    times = np.arange(0.0, until_ms, 33.0)
    return ([_track(t, state, seq=i) for i, t in enumerate(times)],
            [_cmd(t + 1, seq=i) for i, t in enumerate(times)])


# ----------------------------------------------------------------------------- the harness's judgement


def test_limits_come_from_the_graph_and_flag_unsafe_commands():
    limits = Limits.from_graph(load_graph(REPO / "graph.yaml"))
    assert limits.max_forward_mps > 0 and limits.max_reverse_mps >= 0 and limits.max_wheel_radps > 0
    assert limits.unsafe(_cmd(0, vx=0.5 * limits.max_forward_mps)) == []
    assert limits.unsafe(_cmd(0, vx=limits.max_forward_mps + 0.01))
    assert limits.unsafe(_cmd(0, vx=-limits.max_reverse_mps - 0.01))
    assert limits.unsafe(_cmd(0, vx=float("nan"))) == ["non-finite field"]
    assert limits.unsafe(_cmd(0, wz=limits.max_yaw_radps * 1.5))
    bad_wheels = _cmd(0)
    bad_wheels.wheel_radps = (limits.max_wheel_radps * 2, 0.0, 0.0, 0.0)
    assert limits.unsafe(bad_wheels)


def test_watchdog_report_wants_a_stop_within_the_bound_of_the_last_track():
    tracks, commands = _stream(1000)
    last = tracks[-1].recv_ns
    on_time = [*commands, _cmd((last - T0) / MS + 150, vx=0.0, wz=0.0, reason="watchdog", seq=-1)]
    report = watchdog_report(tracks, on_time, T0, T0 + 3000 * MS, timeout_ms=130, bound_ms=200)
    assert not report.violations and report.worst_ms == pytest.approx(150, abs=1)
    late = [*commands, _cmd((last - T0) / MS + 260, vx=0.0, wz=0.0, reason="watchdog", seq=-1)]
    report = watchdog_report(tracks, late, T0, T0 + 3000 * MS, timeout_ms=130, bound_ms=200)
    assert report.violations and "260 ms" in report.violations[0]
    report = watchdog_report(tracks, commands, T0, T0 + 3000 * MS, timeout_ms=130, bound_ms=200)
    assert report.violations and "no zero command" in report.violations[0]
    # After a LOST track the motor has already stopped: a pause then needs no watchdog.
    lost = [*tracks[:-1], _track((last - T0) / MS, "LOST")]
    assert not watchdog_report(lost, commands, T0, T0 + 3000 * MS, 130, 200).violations
    # A motor already stopped that does not move on the last track (it found it stale, say) has nothing to stop;
    # one that moved on it, or moves later in the pause, has.
    stopped_before = [*commands[:-1], _cmd((last - T0) / MS - 20, vx=0.0, wz=0.0, reason="watchdog", seq=-1)]
    assert not watchdog_report(tracks, stopped_before, T0, T0 + 3000 * MS, 130, 200).violations
    moves_later = [*stopped_before, _cmd((last - T0) / MS + 500)]
    assert watchdog_report(tracks, moves_later, T0, T0 + 3000 * MS, 130, 200).violations
    # While the motor process itself is dead (kill-motor) no stop can reach the bus: the MCU's hold_ms covers it.
    down = (last - 50 * MS, last + 2000 * MS)
    assert not watchdog_report(tracks, commands, T0, T0 + 3000 * MS, 130, 200, motor_down=down).violations


def test_recovery_ignores_commands_answering_injected_tracks():
    injected_stamp = T0 + 500 * MS
    commands = [_cmd(510, stamp_ms=500), _cmd(900, reason="watchdog", seq=-1, vx=0, wz=0), _cmd(1500)]
    assert first_follow_ns(commands, T0 + 400 * MS, [injected_stamp]) == T0 + 1500 * MS
    assert first_follow_ns(commands, T0 + 400 * MS) == T0 + 510 * MS
    assert first_follow_ns(commands, T0 + 1600 * MS) is None


def test_tracking_coverage_counts_stale_tracks_as_lost_and_skips_a_hidden_target():
    tracks, _ = _stream(1000)
    truth = [TruthObs(t.recv_ns, t.frame_seq, t.stamp_ns, True) for t in tracks]
    assert tracking_coverage(tracks, truth, T0, T0 + 1000 * MS) > 0.95
    # Tracks stop at 495 ms: samples 0..700 ms still see a fresh track (< 300 ms old), 800..2000 ms do not.
    assert tracking_coverage(tracks[:16], truth, T0, T0 + 2000 * MS) == pytest.approx(8 / 21)
    # OCCLUDED while the scene hides the target is not held against the tracker.
    occluded = [dataclasses.replace(t, state="OCCLUDED") for t in tracks]
    hidden = [TruthObs(g.recv_ns, g.frame_seq, g.stamp_ns, False) for g in truth]
    assert tracking_coverage(occluded, hidden, T0, T0 + 1000 * MS) is None
    assert tracking_coverage(occluded, truth, T0, T0 + 1000 * MS) == 0.0
    # Injected tracks do not count as tracking.
    spoofed = [dataclasses.replace(t, source=INJECTOR) for t in tracks]
    assert tracking_coverage(spoofed, truth, T0, T0 + 1000 * MS) == 0.0


def test_on_target_counts_followed_frames_whose_box_is_on_the_target():
    """A loop that recovers onto a bystander is tracking but not following its person (a restarted re-ID that
    initialised on the detection nearest a coasted prior: chaos kill-reid, 2026-11-28)."""
    tracks, _ = _stream(1000)
    target, bystander = (100.0, 50.0, 40.0, 120.0), (200.0, 50.0, 40.0, 120.0)
    truth = [TruthObs(t.recv_ns, t.frame_seq, t.stamp_ns, True, target) for t in tracks]
    on = [dataclasses.replace(t, box=(105.0, 60.0, 30.0, 100.0)) for t in tracks]
    assert on_target_fraction(on, truth, T0, T0 + 1000 * MS) == 1.0
    # The second half on the bystander.
    half = on[: len(on) // 2] + [dataclasses.replace(t, box=bystander) for t in tracks[len(on) // 2:]]
    assert on_target_fraction(half, truth, T0, T0 + 1000 * MS) == pytest.approx(0.5, abs=0.05)
    # Only followed tracks with a box count, on frames with the target in view; injected tracks never.
    occluded = [dataclasses.replace(t, state="OCCLUDED", box=bystander) for t in tracks]
    assert on_target_fraction(occluded, truth, T0, T0 + 1000 * MS) is None
    hidden = [dataclasses.replace(g, visible=False) for g in truth]
    assert on_target_fraction(half, hidden, T0, T0 + 1000 * MS) is None
    spoofed = [dataclasses.replace(t, source=INJECTOR, box=bystander) for t in tracks]
    assert on_target_fraction(spoofed + on, truth, T0, T0 + 1000 * MS) == 1.0


@pytest.mark.parametrize("schema", sorted(SCHEMAS.values(), key=lambda c: c.TYPE), ids=lambda c: c.TYPE)
def test_malformed_payloads_are_all_undecodable(schema):
    payloads = chaos.malformed_payloads(schema, 40, np.random.default_rng(0))
    for payload in payloads:
        with pytest.raises(DecodeError):
            decode(payload, schema)


def test_fault_lists():
    assert [f.name for f in resolve_faults("ci", record=False, detector="simulated")] == list(CI_FAULTS)
    assert "kill-recorder" not in [f.name for f in resolve_faults(None, record=False, detector="simulated")]
    everything = resolve_faults("all", record=True, detector="simulated")
    assert everything[-1].name == "kill-recorder" and len(everything) == len(FAULTS)
    assert [f.name for f in resolve_faults("capture-restart,burners-2", record=False, detector="simulated")] == [
        "kill-capture", "load"]
    with pytest.raises(ValueError, match="needs --record"):
        resolve_faults("kill-recorder", record=False, detector="simulated")
    with pytest.raises(ValueError, match="unknown fault 'kill-everything'"):
        resolve_faults("kill-everything", record=False, detector="simulated")


def test_cli_usage_errors_and_help():
    result = run_followbus("bench", "chaos", "--faults", "kill-everything", timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "unknown fault 'kill-everything'" in result.stderr
    for bad in (["--repeat", "0"], ["--scene", "nowhere"], ["--faults", "kill-recorder"]):
        result = run_followbus("bench", "chaos", *bad, timeout=60)
        assert result.returncode == 2 and "Traceback" not in result.stderr, bad
        assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    helptext = run_followbus("bench", "chaos", "--help", timeout=60).stdout
    for name in FAULTS:
        assert name in helptext


def test_the_headline_states_load_survival_and_the_bounds():
    """Issue 25: a figure without its load says nothing; the bench prints what a re-run on a quiet machine
    compares: load, survival, unsafe commands, worst stop, following p99, frames answered."""
    def result(name: str, **kw) -> FaultResult:
        base = dict(fault=name, description="", survived=True, checks={}, failures=[], unsafe_commands=0,
                    commands=100, watchdog_ms=None, watchdog_bound_ms=200.0, back_s=None, recovery_s=0.5,
                    recovery_bound_s=2.0, hidden_s=0.0, held=1.0, load1=6.5)
        return FaultResult(**{**base, **kw})

    results = [result("kill-reid", watchdog_ms=161.0), result("load", latency_p99_ms=212.0, processed=0.62),
               result("flood", survived=False, unsafe_commands=1)]
    head = headline(results, [5.0, 7.0, 9.0], ChaosOptions(burners=4))
    assert head["detector"] == "yolox416" and head["burners"] == 4
    assert (head["survived"], head["runs"], head["unsafe_commands"]) == (2, 3, 1)
    assert (head["stop_max_ms"], head["following_p99_ms"], head["frames_answered_min"]) == (161.0, 212.0, 0.62)
    assert head["load1_mean"] == pytest.approx(7.0) and head["load1_max"] == 9.0
    text = format_headline(head, launches=2, elapsed_s=300)
    for needle in ("4 background burners", "7.0 mean, 9.0 max", "/proc/loadavg", "survived: 2 of 3",
                   "unsafe commands: 1 of 300", "stop latency max: 161 ms", "following p99: 212 ms",
                   "frames answered: 62 %"):
        assert needle in text, (needle, text)


def test_simulated_detector_delay_is_a_pure_delay():
    from followbus.nodes.detection import detection_params, detector_from_params

    truth = [((100.0, 50.0, 40.0, 120.0), 1.0), ((300.0, 60.0, 30.0, 90.0), 0.8)]
    image = np.zeros((240, 480, 3), np.uint8)
    fast = detector_from_params(detection_params({"backend": "simulated"}))
    slow = detector_from_params(detection_params({"backend": "simulated", "sim_delay_ms": 40}))
    t0 = time.perf_counter()
    boxes = [slow.detect(image, truth) for _ in range(3)]
    assert time.perf_counter() - t0 >= 3 * 0.040  # a sleep never returns early
    for got in boxes:
        assert np.array_equal(got, fast.detect(image, truth))
    with pytest.raises(ParamError, match="sim_delay_ms"):
        detection_params({"backend": "simulated", "sim_delay_ms": -1})
    with pytest.raises(ParamError, match="only applies to backend 'simulated'"):
        detection_params({"backend": "hog", "sim_delay_ms": 80})


# ----------------------------------------------------------------------------- the live graph under faults


@pytest.fixture(scope="module")
def runner(tmp_path_factory):
    # One launched graph for the whole module; the runner relaunches it only after a fault it did not survive.
    workdir = tmp_path_factory.mktemp("chaos")
    options = ChaosOptions(detector="simulated", port=free_port(), workdir=workdir, log_file=workdir / "nodes.log",
                           hold_s=2.0, malformed_per_key=400, warmup_s=6.0,
                           # The test proves the loop comes back; how fast is the bench's figure (2 s bar,
                           # RELIABILITY.md). Beside another test worker on 2 cores, in a slow hour of this VM,
                           # a recovery that ran into the scene's own occlusion took 5-7 s (fresh-clone suites,
                           # 2026-11-26); never coming back still fails.
                           recovery_bound_s=10.0)
    with ChaosRunner(options, launch=ChaosGraph) as r:
        yield r


@pytest.mark.slow
@pytest.mark.parametrize("name", CI_FAULTS)
def test_fault_is_survived(runner, name):
    result = runner.run(FAULTS[name])
    log_tail = ""
    if not result.survived and runner.options.log_file is not None and runner.options.log_file.exists():
        lines = runner.options.log_file.read_text(errors="replace").splitlines()
        log_tail = "\n".join([line for line in lines if "track state" not in line][-25:])
    assert result.survived, result.explain() + "\n--- node log (tail) ---\n" + log_tail
    assert result.unsafe_commands == 0
    assert result.recovery_s is not None and result.recovery_s <= result.recovery_bound_s + result.hidden_s
    if result.watchdog_ms is not None:
        assert result.watchdog_ms <= result.watchdog_bound_ms
