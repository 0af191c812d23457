"""The chaos bench's fault catalogue: each fault injects itself into the running graph through the runner
(reliability/chaos.py) and says what it did (an Injection, with its own checks); ``resolve_faults`` picks them by
name (``--faults``)."""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from ..bus.codec import pack
from ..bus.graph import Graph
from ..bus.node_checks import unread_inputs, validate_node
from ..bus.schemas import Frame, Message, Tick, encode
from ..msgs.perception import Detections
from ..msgs.tracking import Measurement, Track
from .chaos import ChaosRunner, wait_for
from .judging import (
    FRAME_PERIOD_NS,
    MS,
    NS,
    ChaosError,
    Fault,
    Injection,
    check,
)

log = logging.getLogger("followbus.chaos")


def _kill(node: str) -> Callable[[ChaosRunner], Injection]:
    def inject(run: ChaosRunner) -> Injection:
        return run.kill_and_wait(node)
    return inject


def _kill_capture(run: ChaosRunner) -> Injection:
    before = run.observer.last_truth()
    inj = run.kill_and_wait("capture")
    first = wait_for(lambda: next((g for g in run.observer.window(inj.end_ns, time.time_ns())[2]), None), 5.0)
    restarted = first is not None and before is not None and first.frame_seq < before.frame_seq
    check(inj.checks, "frame_seq restarted", restarted,
           f"capture's frame_seq went {before.frame_seq if before else '?'} -> "
           f"{first.frame_seq if first else 'nothing'} across the restart")
    return inj


def _stop_prediction(run: ChaosRunner) -> Injection:
    start = time.time_ns()
    run.stall("prediction", 2.0)
    return Injection(start, time.time_ns(), expect_pause=True, notes=["prediction SIGSTOPped for 2 s"])


def _load(run: ChaosRunner) -> Injection:
    # The run's background burners (--burners) are the load; this stretch measures following under it.
    start = time.time_ns()
    time.sleep(run.options.load_s)
    end = time.time_ns()
    return Injection(start, end, load_window=(start, end), check_load_processed=True,
                     notes=[f"{run.options.burners} background CPU burners on {os.cpu_count()} cores, "
                            f"load average {os.getloadavg()[0]:.1f}, {run.options.load_s:.0f} s measured"])


def _detector_delay(run: ChaosRunner) -> Injection:
    # The whole launch runs with the slow detector; the fault window is a stretch of it.
    start = time.time_ns()
    time.sleep(run.options.load_s)
    end = time.time_ns()
    inj = Injection(start, start, load_window=(start, end), notes=["detection takes >= 80 ms per frame"])
    return inj


def _future_stamp_track(run: ChaosRunner) -> Injection:
    last = run.observer.last_track()
    pub = run.publisher("prediction", "track")
    track = Track(state="TRACKING", box=np.array([280.0, 110.0, 80.0, 220.0]), filtered_box=None, measured=True)
    track.header.stamp_ns = time.time_ns() + 3600 * NS
    track.header.frame_seq = (last.frame_seq + 1) if last else 0
    start = time.time_ns()
    pub.put(track)
    inj = run.kill_and_wait("prediction", start_ns=start)
    inj.injected_stamps.add(track.header.stamp_ns)
    inj.notes.insert(0, "a TRACKING track stamped +1 h on the track key, then prediction SIGKILLed")
    return inj


def _future_seq(node: str, output: str) -> Callable[[ChaosRunner], Injection]:
    def inject(run: ChaosRunner) -> Injection:
        truth = run.observer.last_truth()
        seq = (truth.frame_seq if truth else 0) + 10**9
        if output == "frame":
            frame = run.observer.latest_frame()
            if frame is None:
                raise ChaosError("no frame seen on the bus to copy")
            msg: Message = Frame(width=frame.width, height=frame.height, encoding=frame.encoding,
                                 data=np.array(frame.data))
        else:
            msg = Detections(boxes=np.zeros((0, 5), np.float32), backend="chaos")
        msg.header.frame_seq = seq
        msg.header.stamp_ns = time.time_ns()
        start = time.time_ns()
        run.publisher(node, output).put(msg)
        # A far-future frame_seq can lie dormant in a synchroniser while frames keep coming, and bite at the
        # next hiccup longer than a sync timeout: so a 0.3 s camera stall follows, as cameras do stall.
        time.sleep(0.5)
        run.stall("capture", 0.3)
        return Injection(start, time.time_ns(),
                         notes=[f"one valid {msg.TYPE} with frame_seq {seq}, then capture stalled 0.3 s"])
    return inject


def _nan_measurement(run: ChaosRunner) -> Injection:
    last = run.observer.last_track()
    nan = np.full(4, np.nan)
    msg = Measurement(state="TRACKING", accepted=True, secure=True, box=nan, best_box=nan.copy(), source="detection",
                      m_fuse=1.0, s_color=1.0, s_geo=1.0, omega=0.5, c_t=1.0)
    msg.header.frame_seq = (last.frame_seq + 1) if last else 0
    msg.header.stamp_ns = (last.stamp_ns + FRAME_PERIOD_NS) if last else time.time_ns()
    start = time.time_ns()
    run.publisher("reid", "measurement").put(msg)
    inj = Injection(start, time.time_ns(),
                    notes=[f"an accepted TRACKING measurement with a NaN box for frame {msg.header.frame_seq}"])
    inj.injected_stamps.add(msg.header.stamp_ns)
    return inj


def malformed_payloads(schema: type[Message], n: int, rng: np.random.Generator) -> list[bytes]:
    """n undecodable payloads for a key carrying ``schema``, in turn: garbage bytes, a valid message of
    another type, a valid message cut short, and a well-formed map of the right type with wrong field types."""
    valid = encode(schema())
    other = encode(Tick(value=7) if schema is not Tick else Track())
    wrong_fields: dict[str, Any] = {"_t": schema.TYPE, "_v": 1, "header": "not a header"}
    wrong_fields.update({f.name: {"bad": 1} for f in dataclasses.fields(schema) if f.name != "header"})
    kinds = [lambda: rng.integers(0, 256, size=int(rng.integers(0, 200)), dtype=np.uint8).tobytes(),
             lambda: other,
             lambda: valid[: int(rng.integers(0, len(valid)))],
             lambda: pack(wrong_fields)]
    return [kinds[i % len(kinds)]() for i in range(n)]


def _malformed_consumers(graph: Graph) -> dict[str, list[str]]:
    """Each input key -> the nodes that subscribe to it (not detection's ground truth with a real detector)."""
    consumers: dict[str, list[str]] = {}
    for spec in graph.nodes.values():
        cls, params = validate_node(graph, spec)
        unread = unread_inputs(cls, params)
        for inp in spec.inputs.values():
            if inp.name not in unread:
                consumers.setdefault(graph.key(inp.source_node, inp.source_output), []).append(spec.name)
    return consumers


def _uncounted(run: ChaosRunner, consumers: dict[str, list[str]], before: dict, n: int) -> list[tuple[str, str]]:
    """(node, '<node> counted <k> on <key>') for each consumer that has not yet counted all n payloads of a key."""
    now = run.statuses()
    short = []
    for key, names in sorted(consumers.items()):
        for name in names:
            counted = (now.get(name, {}).get(key, {}).get("decode_errors", 0)
                       - before.get(name, {}).get(key, {}).get("decode_errors", 0))
            if counted < n:
                short.append((name, f"{name} counted {counted} on {key}"))
    return short


def _wait_counted(run: ChaosRunner, consumers: dict[str, list[str]], before: dict, n: int, puts_end: int) -> int:
    """When the garbage was last seen still being worked through: the fault's end. The last put returns long
    before a loaded node has decoded thousands of payloads (each in its receive thread, ahead of the real
    frames); so the end is the newest status (once a second) that still showed a payload uncounted."""
    end = puts_end
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        short = _uncounted(run, consumers, before, n)
        if not short:
            break
        end = max(end, *(run.status_ns(name) for name, _ in short))
        time.sleep(0.05)
    return end


def _malformed(run: ChaosRunner) -> Injection:
    graph = run.graph.graph
    n = run.options.malformed_per_key
    consumers = _malformed_consumers(graph)
    producers = {graph.key(n_, o): n_ for n_, s in graph.nodes.items() for o in s.outputs}
    before = run.statuses()
    ups = {name: h.ups for name, h in run.health.snapshot().items()}
    pids = {name: run.graph.pid(name) for name in graph.nodes}
    rng = np.random.default_rng(14)
    start = time.time_ns()
    for key in sorted(consumers):
        node = producers[key]
        cls = graph_output_schema(graph, node, key.rsplit("/", 1)[1])
        pub = run.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        try:
            for payload in malformed_payloads(cls, n, rng):
                pub.put(payload)
        finally:
            pub.undeclare()
    puts_end = time.time_ns()
    end = _wait_counted(run, consumers, before, n, puts_end)
    inj = Injection(start, end, notes=[f"{n} malformed payloads on each of {len(consumers)} input keys",
                                       f"all counted {(end - puts_end) / NS:.1f} s after the last put"])

    def after() -> None:
        fresh = wait_for(lambda: all(run.status_ns(name) > end + NS for ks in consumers.values() for name in ks), 6.0)
        short = _uncounted(run, consumers, before, n)
        check(inj.checks, "counted in decode_errors", bool(fresh) and not short,
              "every consumer counted every payload" if not short else "; ".join(line for _, line in short[:4]))
        same_ups = {name: h.ups for name, h in run.health.snapshot().items()}
        restarted = [name for name in graph.nodes
                     if same_ups.get(name) != ups.get(name) or run.graph.pid(name) != pids.get(name)]
        check(inj.checks, "no node restarted", not restarted, ", ".join(restarted) or "all pids unchanged")

    inj.after = after
    return inj


def graph_output_schema(graph: Graph, node: str, output: str) -> type[Message]:
    from ..bus.node_checks import load_node_class

    return load_node_class(graph.nodes[node].run).OUTPUTS[output].type


def _flood(run: ChaosRunner) -> Injection:
    frame = run.observer.latest_frame()
    truth = run.observer.last_truth()
    if frame is None or truth is None:
        raise ChaosError("no frame seen on the bus to copy")
    pub = run.publisher("capture", "frame", congestion="block", shm=True)
    data = np.array(frame.data)
    run.observer.watching_injected = True
    try:
        start = time.time_ns()
        for i in range(run.options.flood_frames):
            msg = Frame(width=frame.width, height=frame.height, encoding=frame.encoding, data=data)
            msg.header.frame_seq = truth.frame_seq + 1 + i
            msg.header.stamp_ns = time.time_ns()
            pub.put(msg)
        sent = time.time_ns()
        end = _delivered_ns(run, sent)
    finally:
        run.observer.watching_injected = False
    return Injection(start, end, notes=[f"{run.options.flood_frames} valid frames in {(sent - start) / MS:.0f} ms, "
                                        f"delivered {(end - sent) / MS:.0f} ms later, "
                                        f"frame_seq {truth.frame_seq + 1}..."])


def _delivered_ns(run: ChaosRunner, sent_ns: int, quiet_s: float = 0.5, bound_s: float = 15.0) -> int:
    """When the bus delivered the last injected frame to the harness's own subscriber: put() returns once a
    frame is queued, and without shared memory a flood's megabytes are still draining through every link
    for seconds after that; the graph cannot recover before its inputs are its own again."""
    deadline = time.monotonic() + bound_s
    while time.monotonic() < deadline:
        if time.time_ns() - max(sent_ns, run.observer.injected_frame_ns) > quiet_s * 1e9:
            break
        time.sleep(0.05)
    return max(sent_ns, run.observer.injected_frame_ns)


def _kill_recorder(run: ChaosRunner) -> Injection:
    from ..bus.barrier import RECORDER_NAME

    pid = run.require_pid(RECORDER_NAME)
    start = time.time_ns()
    os.kill(pid, signal.SIGKILL)
    time.sleep(3.0)
    inj = Injection(start, time.time_ns(), notes=["recorder SIGKILLed; the loop must still follow 3 s later"])
    alive = run.graph.running and run.health.alive() >= set(run.graph.graph.nodes)
    check(inj.checks, "graph kept running", alive,
           "launcher and every node up" if alive else f"launcher running={run.graph.running}, "
                                                      f"failed={run.graph.failed()}")
    path = run.graph.record_path
    try:
        result = run.graph.recover_recording() if path is not None else None
        ok = result is not None and result.messages > 0
        detail = f"{result.messages} messages recovered" if result is not None else "no file"
    except Exception as exc:  # a file the recover tool cannot read is the finding
        ok, detail = False, f"recover failed: {exc}"
    check(inj.checks, "recording recoverable", ok, detail)
    return inj


def _faults() -> dict[str, Fault]:
    faults = [
        Fault("kill-capture", "SIGKILL capture; the launcher restarts it and frame_seq starts again at 0 "
                              "(capture-restart)", _kill_capture),
        *(Fault(f"kill-{n}", f"SIGKILL {n}; the launcher restarts it", _kill(n))
          for n in ("detection", "prediction", "reid", "template", "motor")),
        Fault("stop-prediction-2s", "SIGSTOP prediction for 2 s, then SIGCONT", _stop_prediction),
        Fault("load", "--load-seconds of following under the run's load (--burners background CPU burners): "
                      "p99 capture->command and frames answered", _load),
        Fault("detector-delay-80ms", "the simulated detector takes 80 ms per frame (sim_delay_ms: 80)",
              _detector_delay, variant="delay80", simulated_only=True),
        Fault("future-stamp-track", "a TRACKING track stamped one hour ahead on prediction/track, then SIGKILL "
                                    "prediction: the motor must still stop", _future_stamp_track),
        Fault("future-seq-frame", "one valid frame with frame_seq +10**9 on capture/frame, then a 0.3 s camera "
                                  "stall", _future_seq("capture", "frame")),
        Fault("future-seq-detections", "one valid Detections with frame_seq +10**9 on detection/detections, then "
                                       "a 0.3 s camera stall", _future_seq("detection", "detections")),
        Fault("nan-measurement", "an accepted TRACKING Measurement with NaN box and best_box on reid/measurement",
              _nan_measurement),
        Fault("malformed", "garbage, wrong-type, truncated and wrong-field payloads, --malformed-per-key on every "
                           "input key", _malformed),
        Fault("flood", "300 valid frames (plausible frame_seqs) as fast as the bus takes them on capture/frame",
              _flood),
        Fault("kill-recorder", "SIGKILL the recorder of --record: the graph keeps going, the file is recoverable",
              _kill_recorder, needs_record=True),
    ]
    return {f.name: f for f in faults}


FAULTS: dict[str, Fault] = _faults()
ALIASES = {"capture-restart": "kill-capture", "burners": "load", "burners-2": "load"}
CI_FAULTS = ("future-stamp-track", "future-seq-frame", "future-seq-detections", "nan-measurement", "kill-capture",
             "kill-reid", "malformed", "flood")


def resolve_faults(spec: str | None, *, record: bool, detector: str) -> list[Fault]:
    """Fault list from ``--faults`` (names, aliases, ``all``, ``ci``); raises ValueError naming an unknown one."""
    names: list[str] = []
    for item in (spec or "all").split(","):
        item = item.strip()
        if not item:
            continue
        if item == "all":
            names += [n for n, f in FAULTS.items() if (record or not f.needs_record)
                      and (detector == "simulated" or not f.simulated_only)]
        elif item == "ci":
            names += list(CI_FAULTS)
        elif ALIASES.get(item, item) in FAULTS:
            names.append(ALIASES.get(item, item))
        else:
            raise ValueError(f"unknown fault {item!r} (known: all, ci, {', '.join([*FAULTS, *ALIASES])})")
    out = list(dict.fromkeys(names))
    for name in out:
        if FAULTS[name].needs_record and not record:
            raise ValueError(f"fault {name!r} needs --record")
        if FAULTS[name].simulated_only and detector != "simulated":
            raise ValueError(f"fault {name!r} needs --detector simulated")
    # Faults needing another launch of the graph go after the others, the recorder's death last.
    order = {"base": 0, "delay80": 1}
    return sorted((FAULTS[n] for n in out), key=lambda f: (f.needs_record, order.get(f.variant, 2)))


