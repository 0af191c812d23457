"""``followbus bench bus``: one-way latency and CPU per message of frames through raw zenoh, through bus/ and
(``--against dora``) through dora-rs, each path in its own stream between its own two processes.

Fairness rules, the same for every path:

* one stream at a time: a path's sender and receiver are two fresh processes that carry nothing else, and
  the paths take turns, round after round (the order rotates each round), so all see the same machine load;
* the same payloads (1 KB, 100 KB, 921 KB = 640×480×3, 2.76 MB = 1280×720×3, random bytes held in a
  ``bytearray``, the way a camera driver that fills its own buffer hands them over) at the same rates (30 and
  100 Hz, paced on an absolute schedule), 5 warm-up messages per cell (2 s' worth before the first) not counted;
* the same clock: the sender stamps ``time.time_ns()`` when it starts handing the message over (raw, dora:
  the first 8 payload bytes; bus/: ``header.pub_ns``, set by ``Publisher.put`` before encoding), the
  receiver reads ``time.time_ns()`` once it holds a numpy array of the payload that stays valid after its
  handler returns (raw zenoh: a private copy, since zenoh-python 1.10 gives Python no view of a received
  buffer; bus/: what a node gets, a private copy of an inline message or, from 64 KiB of arrays between
  processes of this host, a read-only view of the publisher's lane segment, locked while referenced
  (bus/shmlane.py); dora: the zero-copy Arrow view, which dora keeps valid as long as it is referenced);
* CPU per message: ``time.process_time()`` of the sender over its counted sends plus that of the receiver
  over the same messages (every thread, zenoh's included), and for dora also the daemon's CPU over the
  receiver's window (``/proc/<pid>/task/*/schedstat``; ``dora run`` has no coordinator).

bus/ publishes typed :class:`Frame` messages through :class:`Publisher` as a node does (zenoh shared memory
from 64 KB, the same-host lane from 64 KiB of arrays when the zenoh settings have it, the default) and receives them
through :class:`Subscriber` (decode, validation, decode-error accounting); raw zenoh puts the
bytes (through a shared-memory buffer from 64 KB) and takes them out again. dora runs a dataflow the bench
writes into a temporary directory (``dora run``: daemon in one process, listening on 127.0.0.1 only), nodes
in this Python. Figures go to BENCHMARKS.md, not to tests.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("followbus.bench")

SIZES = {"1KB": 1024, "100KB": 100 * 1024, "921KB": 640 * 480 * 3, "2.76MB": 1280 * 720 * 3}
RATES = (30.0, 100.0)
WARMUP = 5
FIRST_WARMUP_S = 2.0  # the first cell's warm-up: a path's first messages set up routes and mappings
SHAPES = {640 * 480 * 3: (480, 640, 3), 1280 * 720 * 3: (720, 1280, 3)}
PATHS = ("raw", "bus")
_STAMP = 16  # payload bytes 0..8: send time (ns), 8..12: cell, 12..16: message index (raw and dora)


# --- the plan and the measurement shared by every path --------------------------------------------


def _plan(sizes: list[str], rates: list[float], count: int) -> dict[str, Any]:
    return {"cells": [[label, SIZES[label], rate] for label in sizes for rate in rates], "count": count,
            "warmup": WARMUP, "first_warmup_s": FIRST_WARMUP_S}


def _warmup(plan: dict[str, Any], cell: int) -> int:
    """Messages sent before counting starts in a cell: 2 s' worth before the first, 5 before the others."""
    return max(plan["warmup"], round(plan["first_warmup_s"] * plan["cells"][0][2])) if cell == 0 else plan["warmup"]


def _source(size: int, seed: int) -> tuple[bytearray, np.ndarray]:
    """The payload as a camera buffer: a bytearray and the image array on it (no copy between them)."""
    buf = bytearray(np.random.default_rng(seed).integers(0, 255, size=size, dtype=np.uint8).tobytes())
    arr = np.frombuffer(buf, np.uint8)
    return buf, arr.reshape(SHAPES[size]) if size in SHAPES else arr


def _stamp(buf: bytearray, cell: int, index: int) -> None:
    buf[:_STAMP] = time.time_ns().to_bytes(8, "little") + cell.to_bytes(4, "little") + index.to_bytes(4, "little")


def _read_stamp(arr: np.ndarray) -> tuple[int, int, int]:
    head = arr[:_STAMP].tobytes()
    return (int.from_bytes(head[:8], "little"), int.from_bytes(head[8:12], "little"),
            int.from_bytes(head[12:16], "little"))


def _task_cpu_ns(pid: int) -> int | None:
    """CPU time of every thread of a process, in ns (schedstat: finer than /proc/<pid>/stat's 10 ms ticks)."""
    total = 0
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            try:
                total += int(Path(f"/proc/{pid}/task/{task}/schedstat").read_text().split()[0])
            except (OSError, ValueError, IndexError):
                continue  # a thread that ended meanwhile
    except OSError:
        return None
    return total


def _send_loop(plan: dict[str, Any], send: Callable[[int, int, bytearray, np.ndarray], None]) -> dict[str, Any]:
    """Send every cell of the plan on an absolute schedule; the sender's CPU over each cell's counted sends."""
    count = plan["count"]
    cpu = []
    for ci, (_label, size, rate) in enumerate(plan["cells"]):
        warm = _warmup(plan, ci)
        buf, image = _source(size, ci)
        period = 1.0 / rate
        cpu0 = 0.0
        t_next = time.perf_counter()
        for i in range(warm + count):
            if i == warm:
                cpu0 = time.process_time()
            delay = t_next - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            send(ci, i, buf, image)
            t_next += period
        cpu.append(time.process_time() - cpu0)
        time.sleep(0.3)  # the receiver drains the cell before the next one starts
    return {"sender_cpu_s": cpu}


class _Recorder:
    """The receiving end's figures: latency per message, its own (and the daemon's) CPU over each cell."""

    def __init__(self, plan: dict[str, Any], daemon_pid: int | None = None):
        n = len(plan["cells"])
        self.warm = [_warmup(plan, ci) for ci in range(n)]
        self.count = plan["count"]
        self.lat: list[list[float]] = [[] for _ in range(n)]
        self.cpu: list[list[float | None]] = [[None, None] for _ in range(n)]
        self.daemon: list[list[int | None]] = [[None, None] for _ in range(n)]
        self.daemon_pid = daemon_pid

    def record(self, cell: int, index: int, sent_ns: int, now_ns: int) -> None:
        warm = self.warm[cell]
        if index >= warm:
            self.lat[cell].append((now_ns - sent_ns) / 1e6)
        # CPU window: from the end of the last warm-up message to the end of the last counted one.
        if index in (warm - 1, warm + self.count - 1):
            slot = 0 if index < warm else 1
            self.cpu[cell][slot] = time.process_time()
            if self.daemon_pid:
                self.daemon[cell][slot] = _task_cpu_ns(self.daemon_pid)

    def result(self) -> dict[str, Any]:
        out = []
        for ci, lat in enumerate(self.lat):
            (c0, c1), (d0, d1) = self.cpu[ci], self.daemon[ci]
            complete = c0 is not None and c1 is not None
            out.append({"lat_ms": lat, "receiver_cpu_s": (c1 - c0) if complete else None,
                        "daemon_cpu_s": (d1 - d0) / 1e9 if complete and d0 is not None and d1 is not None
                        else None})
        return {"cells": out}


# --- the three paths: child processes -------------------------------------------------------------


def _settings(port: int, listen: bool) -> Any:
    from ...bus.session import ZenohSettings

    endpoint = f"tcp/127.0.0.1:{port}"
    return ZenohSettings(mode="peer", listen=[endpoint] if listen else [], connect=[] if listen else [endpoint])


def _zenoh_receiver(path: str, plan: dict[str, Any], port: int, ready: Path, done: Path) -> dict[str, Any]:
    from ...bus.pubsub import Subscriber, direct_callback, payload_bytes
    from ...bus.schemas import Frame
    from ...bus.session import open_session

    rec = _Recorder(plan)
    session = open_session(_settings(port, listen=True))
    subs: list[Any] = []
    if path == "raw":
        def on_raw(sample: Any) -> None:
            arr = np.frombuffer(payload_bytes(sample), np.uint8)  # the private copy bus/ makes of inline messages
            now = time.time_ns()
            sent, cell, index = _read_stamp(arr)
            rec.record(cell, index, sent, now)

        subs.append(session.declare_subscriber("bench/raw/*", direct_callback(on_raw)))
    else:
        def on_bus(cell: int) -> Callable[[Frame], None]:
            def cb(msg: Frame) -> None:
                _ = msg.data.shape  # decoded and validated: the typed array is ready
                rec.record(cell, msg.header.frame_seq, msg.header.pub_ns, time.time_ns())
            return cb

        subs.extend(Subscriber(session, f"bench/bus/c{ci}", on_bus(ci), schema=Frame)
                    for ci in range(len(plan["cells"])))
    ready.touch()
    deadline = time.monotonic() + 3600
    while not done.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    for sub in subs:
        sub.undeclare()
    session.close()
    return rec.result()


def _zenoh_sender(path: str, plan: dict[str, Any], port: int) -> dict[str, Any]:
    from ...bus.pubsub import SHM_THRESHOLD_BYTES, Publisher, ShmPool
    from ...bus.schemas import Frame
    from ...bus.session import open_session

    session = open_session(_settings(port, listen=False))
    shm = ShmPool()
    shm.warm_up()
    time.sleep(1.0)  # the peers connect and the subscriptions propagate
    if path == "raw":
        pubs = [session.declare_publisher(f"bench/raw/c{ci}") for ci in range(len(plan["cells"]))]

        def send(ci: int, i: int, buf: bytearray, image: np.ndarray) -> None:
            _stamp(buf, ci, i)
            body = shm.buffer_with(buf) if len(buf) >= SHM_THRESHOLD_BYTES else None
            pubs[ci].put(body if body is not None else buf)
    else:
        # As a node publishes (bus/node.py): with the same-host lane when the settings have it (the default).
        settings = _settings(port, listen=False)
        pubs = [Publisher(session, f"bench/bus/c{ci}", "bench", shm=shm, lane=settings.shm_lane)
                for ci in range(len(plan["cells"]))]

        def send(ci: int, i: int, buf: bytearray, image: np.ndarray) -> None:
            jpeg = image.ndim == 1  # the two small sizes travel as what they would be: compressed images
            msg = Frame(width=1 if jpeg else image.shape[1], height=1 if jpeg else image.shape[0],
                        encoding="jpeg" if jpeg else "bgr8", data=image)
            msg.header.frame_seq = i
            pubs[ci].put(msg)
    result = _send_loop(plan, send)
    for pub in pubs:
        pub.undeclare()
    session.close()
    return result


def _dora_sender(plan: dict[str, Any]) -> dict[str, Any]:
    import pyarrow as pa
    from dora import Node

    node = Node()
    # The receiver says when it listens (as the zenoh paths' ready file): a fixed sleep would lose the first
    # messages on a loaded machine, where the receiver's imports alone can take seconds.
    for event in node:
        if event["type"] == "INPUT" and event["id"] == "ready":
            break
        if event["type"] == "STOP":
            raise RuntimeError("dora stopped the dataflow before the receiver was ready")

    def send(ci: int, i: int, buf: bytearray, image: np.ndarray) -> None:
        _stamp(buf, ci, i)
        node.send_output("frames", pa.array(image.reshape(-1)))  # wraps the array; dora copies it once

    return _send_loop(plan, send)


def _dora_receiver(plan: dict[str, Any]) -> dict[str, Any]:
    import pyarrow as pa
    from dora import Node

    rec = _Recorder(plan, daemon_pid=os.getppid())  # `dora run` is the daemon and the nodes' parent
    node = Node()
    node.send_output("ready", pa.array([1]))
    for event in node:
        if event["type"] == "INPUT":
            arr = event["value"].to_numpy(zero_copy_only=True)  # valid while referenced
            now = time.time_ns()
            sent, cell, index = _read_stamp(arr)
            rec.record(cell, index, sent, now)
        elif event["type"] == "STOP":
            break
    return rec.result()


def _child(argv: list[str]) -> int:
    """Entry of the child processes: ``--child ROLE PATH PLAN OUT [PORT READY DONE]``."""
    role, path, plan_file, out = argv[:4]
    plan = json.loads(Path(plan_file).read_text())
    if path == "dora":
        result = _dora_sender(plan) if role == "send" else _dora_receiver(plan)
    elif role == "send":
        result = _zenoh_sender(path, plan, int(argv[4]))
    else:
        result = _zenoh_receiver(path, plan, int(argv[4]), Path(argv[5]), Path(argv[6]))
    Path(out).write_text(json.dumps(result))
    return 0


# --- the parent: rounds, processes, figures -------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _child_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", __name__, "--child", *args]


def _stop(proc: subprocess.Popen, group: bool = False) -> None:
    """End a process the bench started (and, for dora, the nodes it spawned), politely first."""
    if proc.poll() is not None:
        return
    for sig, wait in ((signal.SIGINT, 10), (signal.SIGTERM, 5), (signal.SIGKILL, 5)):
        try:
            if group:
                os.killpg(proc.pid, sig)
            else:
                proc.send_signal(sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _run_zenoh_pair(path: str, plan_file: Path, tmp: Path, timeout_s: float) -> dict[str, Any]:
    port = _free_port()
    ready, done = tmp / f"{path}.ready", tmp / f"{path}.done"
    for f in (ready, done):
        f.unlink(missing_ok=True)
    recv_out, send_out = tmp / f"{path}.recv.json", tmp / f"{path}.send.json"
    log_file = (tmp / f"{path}.log").open("w")
    recv = subprocess.Popen(_child_cmd("recv", path, str(plan_file), str(recv_out), str(port), str(ready),
                                       str(done)), stdout=log_file, stderr=subprocess.STDOUT)
    send = None
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            if recv.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{path} receiver did not start (see {log_file.name})")
            time.sleep(0.05)
        send = subprocess.Popen(_child_cmd("send", path, str(plan_file), str(send_out), str(port)),
                                stdout=log_file, stderr=subprocess.STDOUT)
        if send.wait(timeout_s) != 0:
            raise RuntimeError(f"{path} sender failed (exit {send.returncode})")
        time.sleep(0.5)
        done.touch()
        if recv.wait(30) != 0:
            raise RuntimeError(f"{path} receiver failed (exit {recv.returncode})")
    finally:
        for proc in (send, recv):
            if proc is not None:
                _stop(proc)
        log_file.close()
    return _merge(json.loads(recv_out.read_text()), json.loads(send_out.read_text()))


_DATAFLOW = """\
nodes:
  - id: sender
    path: {python}
    args: -m {module} --child send dora {plan} {send_out}
    inputs:
      ready: receiver/ready
    outputs: [frames]
  - id: receiver
    path: {python}
    args: -m {module} --child recv dora {plan} {recv_out}
    inputs:
      frames:
        source: sender/frames
        queue_size: 1000  # dora's default (10) discards a slow receiver's backlog; zenoh's paths drop nothing
    outputs: [ready]
"""


def _run_dora(plan_file: Path, tmp: Path, timeout_s: float) -> dict[str, Any]:
    recv_out, send_out = tmp / "dora.recv.json", tmp / "dora.send.json"
    dataflow = tmp / "dataflow.yml"
    dataflow.write_text(_DATAFLOW.format(python=sys.executable, module=__name__, plan=plan_file,
                                         send_out=send_out, recv_out=recv_out))
    dora = shutil.which("dora", path=str(Path(sys.executable).parent)) or shutil.which("dora")
    with (tmp / "dora.log").open("w") as log_file:
        # Its own process group: on a timeout the daemon and both nodes are ended together.
        proc = subprocess.Popen([str(dora), "run", str(dataflow)], cwd=tmp, stdout=log_file,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            code = proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            code = None
        finally:
            _stop(proc, group=True)
    if code != 0 or not recv_out.exists() or not send_out.exists():
        raise RuntimeError(f"dora run failed (exit {code}); its log: {tmp / 'dora.log'}")
    return _merge(json.loads(recv_out.read_text()), json.loads(send_out.read_text()))


def _merge(recv: dict[str, Any], send: dict[str, Any]) -> dict[str, Any]:
    for cell, cpu in zip(recv["cells"], send["sender_cpu_s"], strict=True):
        cell["sender_cpu_s"] = cpu
    return recv


def dora_available() -> str | None:
    """None when dora-rs and its CLI can run here, else why not."""
    try:
        import dora  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError as exc:
        return f"dora-rs is not installed ({exc.name}); pip install 'followbus[bench]'"
    if not (shutil.which("dora", path=str(Path(sys.executable).parent)) or shutil.which("dora")):
        return "the dora CLI is not installed; pip install 'followbus[bench]'"
    return None


def _summary(per_round: list[dict[str, Any]], plan: dict[str, Any]) -> list[dict[str, Any]]:
    """Per cell: latencies pooled over rounds (p50, p99), CPU per message as the median over rounds."""
    rows = []
    count = plan["count"]
    for ci, (label, _size, rate) in enumerate(plan["cells"]):
        lat = np.concatenate([np.asarray(r["cells"][ci]["lat_ms"], float) for r in per_round])
        cpu = []
        for r in per_round:
            c = r["cells"][ci]
            parts = [c["sender_cpu_s"], c["receiver_cpu_s"]]
            if "daemon_cpu_s" in c and c.get("daemon_cpu_s") is not None:
                parts.append(c["daemon_cpu_s"])
            if None not in parts:
                cpu.append(sum(parts) / count * 1e3)
        daemon = [r["cells"][ci]["daemon_cpu_s"] / count * 1e3 for r in per_round
                  if r["cells"][ci].get("daemon_cpu_s") is not None]
        rows.append({"size": label, "rate_hz": rate, "n": int(lat.size),
                     "expected": count * len(per_round),
                     "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
                     "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
                     "round_p50_ms": [float(np.median(r["cells"][ci]["lat_ms"])) if r["cells"][ci]["lat_ms"]
                                      else float("nan") for r in per_round],
                     "cpu_ms_per_msg": float(np.median(cpu)) if cpu else float("nan"),
                     "daemon_cpu_ms_per_msg": float(np.median(daemon)) if daemon else None})
    return rows


def run_bench_bus(args: Any) -> int:
    args.rounds = getattr(args, "rounds", 3)
    paths, why_not = _paths_to_bench(args)
    if why_not:
        print(f"bench bus --against dora: {why_not}")
        return 2
    grid = _sizes_and_rates(args)
    if grid is None:
        print(f"bench bus: sizes are {', '.join(SIZES)}; rates > 0; --count >= 2; --rounds >= 1")
        return 2
    plan = _plan(*grid, args.count)
    per_cell_s = sum((_warmup(plan, ci) + args.count) / rate + 0.3 for ci, (_l, _s, rate) in enumerate(plan["cells"]))
    load0 = os.getloadavg()
    print(f"bench bus: {len(paths)} paths x {args.rounds} rounds x {len(plan['cells'])} cells, "
          f"~{per_cell_s * len(paths) * args.rounds / 60:.1f} min", flush=True)
    results = _run_rounds(paths, plan, args.rounds, per_cell_s + 120)
    if results is None:
        return 1
    load1 = os.getloadavg()
    table = {p: _summary(results[p], plan) for p in paths}
    _print_table(table, paths, args, load0, load1)
    if args.json:
        Path(args.json).write_text(json.dumps({
            "machine": platform.node(), "date": time.strftime("%Y-%m-%d"), "count": args.count,
            "rounds": args.rounds, "load_before": load0, "load_after": load1, "paths": table}, indent=1))
    return _bus_loss_status(table, load1)


def _paths_to_bench(args: Any) -> tuple[list[str], str | None]:
    """The paths to measure, and why not when --against dora asks for a dora-rs that cannot run here."""
    paths = list(PATHS)
    if getattr(args, "against", None) == "dora":
        why = dora_available()
        if why:
            return paths, why
        paths.append("dora")
    return paths, None


def _sizes_and_rates(args: Any) -> tuple[list[str], list[float]] | None:
    """The sizes and rates to measure (the defaults unless given), or None when any of them, --count or
    --rounds is out of range."""
    sizes = args.sizes.split(",") if getattr(args, "sizes", None) else list(SIZES)
    try:
        rates = [float(r) for r in args.rates.split(",")] if getattr(args, "rates", None) else list(RATES)
    except ValueError:
        rates = []
    unknown = [s for s in sizes if s not in SIZES]
    if unknown or not rates or any(not r > 0 for r in rates) or args.count < 2 or args.rounds < 1:
        return None
    return sizes, rates


def _run_rounds(paths: list[str], plan: dict[str, Any], rounds: int,
                timeout_s: float) -> dict[str, list[dict[str, Any]]] | None:
    """Every path once a round, its result per round; None when a run failed (said on stderr)."""
    results: dict[str, list[dict[str, Any]]] = {p: [] for p in paths}
    with tempfile.TemporaryDirectory(prefix="followbus-bench-bus-") as tmp_name:
        tmp = Path(tmp_name)
        plan_file = tmp / "plan.json"
        plan_file.write_text(json.dumps(plan))
        for rnd in range(rounds):
            order = paths[rnd % len(paths):] + paths[:rnd % len(paths)]  # rotated: no path always first
            for path in order:
                t0 = time.monotonic()
                try:
                    res = _run_path(path, plan_file, tmp, timeout_s)
                except RuntimeError as exc:
                    print(f"bench bus: failed: {exc}", file=sys.stderr)
                    return None
                results[path].append(res)
                print(f"  round {rnd + 1} {path}: {time.monotonic() - t0:.0f} s, load {os.getloadavg()[0]:.2f}",
                      flush=True)
    return results


def _run_path(path: str, plan_file: Path, tmp: Path, timeout_s: float) -> dict[str, Any]:
    if path == "dora":
        return _run_dora(plan_file, tmp, timeout_s)
    return _run_zenoh_pair(path, plan_file, tmp, timeout_s)


def _bus_loss_status(table: dict[str, list[dict[str, Any]]], load1: tuple[float, ...]) -> int:
    """Exit 1 when bus/ lost messages (what the bench is for); a loss of raw zenoh or dora shows in the table
    only."""
    short = [f"{row['size']} at {row['rate_hz']:.0f} Hz: {row['n']} of {row['expected']} received"
             for row in table["bus"] if row["n"] < row["expected"]]
    if short:
        print(f"bench bus: failed: bus/ lost messages ({'; '.join(short)}); under load "
              f"{load1[0]:.2f} on {os.cpu_count()} cores a subscriber may fall behind: rerun on a quieter machine, "
              "or with --rates lower", file=sys.stderr)
        return 1
    return 0


def _print_table(table: dict[str, list[dict[str, Any]]], paths: list[str], args: Any,
                 load0: tuple[float, ...], load1: tuple[float, ...]) -> None:
    print(f"\nfollowbus bench bus: {args.count} msgs per cell x {args.rounds} rounds, one stream at a time, "
          f"peer-to-peer over loopback; load {load0[0]:.2f} -> {load1[0]:.2f}; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    head = "| size | Hz | " + " | ".join(f"{p} p50 | {p} p99" for p in paths) + " | bus/raw p50"
    head += " | bus/dora p50" if "dora" in paths else ""
    head += " | CPU ms/msg " + "/".join(paths) + " |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for i, row in enumerate(table["raw"]):
        cells = {p: table[p][i] for p in paths}
        line = f"| {row['size']} | {row['rate_hz']:.0f} | "
        line += " | ".join(f"{cells[p]['p50_ms']:.3f} | {cells[p]['p99_ms']:.3f}" for p in paths)
        line += f" | {cells['bus']['p50_ms'] / cells['raw']['p50_ms']:.2f}"
        if "dora" in paths:
            line += f" | {cells['bus']['p50_ms'] / cells['dora']['p50_ms']:.2f}"
        line += " | " + "/".join(f"{cells[p]['cpu_ms_per_msg']:.2f}" for p in paths) + " |"
        lost = [f"{p} {cells[p]['expected'] - cells[p]['n']} of {cells[p]['expected']}" for p in paths
                if cells[p]["n"] < cells[p]["expected"]]
        print(line + (f" lost (not received): {', '.join(lost)}" if lost else ""))
    if "dora" in paths:
        d = [r["daemon_cpu_ms_per_msg"] for r in table["dora"] if r["daemon_cpu_ms_per_msg"] is not None]
        if d:
            print(f"(dora CPU includes its daemon: {min(d):.2f}-{max(d):.2f} ms/msg of it)")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        sys.exit(_child(sys.argv[2:]))
    print("usage: followbus bench bus (this module's own entry point is for its child processes)")
    sys.exit(2)
