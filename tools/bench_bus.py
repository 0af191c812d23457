"""``followbus bench bus``: one-way latency and throughput through bus/ and through raw zenoh
put/subscribe, in the same run, for 1 KB, 100 KB, 921 KB (VGA BGR) and 2.76 MB (720p BGR).

Publisher and subscriber are separate processes (a real hop). The subscriber measures one-way
latency from the publish wall clock (same host, same clock) to the moment the message is usable:
for bus/ that is decoded into a typed Frame; for raw zenoh, bytes in hand.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import platform
import time

import numpy as np

SIZES = {"1KB": 1024, "100KB": 100 * 1024, "921KB": 640 * 480 * 3, "2.76MB": 1280 * 720 * 3}


def _settings(port: int, listen: bool):
    from ..bus.session import ZenohSettings

    endpoint = f"tcp/127.0.0.1:{port}"
    return ZenohSettings(mode="peer", listen=[endpoint] if listen else [], connect=[] if listen else [endpoint])


def _frame_shape(size: int) -> tuple[int, ...]:
    if size % 3 == 0 and size >= 640 * 480 * 3:
        return {640 * 480 * 3: (480, 640, 3), 1280 * 720 * 3: (720, 1280, 3)}[size]
    return (size,)


def _subscriber(port: int, ready, results, expected: int) -> None:
    from ..bus.pubsub import Subscriber, direct_callback, payload_bytes
    from ..bus.schemas import Frame
    from ..bus.session import open_session

    session = open_session(_settings(port, listen=False))
    lat: dict[str, list[float]] = {}

    def on_bus(msg: Frame) -> None:
        now = time.time_ns()
        _ = msg.data.shape  # the typed array is ready to use
        lat.setdefault(f"bus/{msg.encoding}", []).append((now - msg.header.pub_ns) / 1e6)

    def on_raw(sample) -> None:
        data = payload_bytes(sample)
        now = time.time_ns()
        sent = int.from_bytes(data[:8], "little")
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        lat.setdefault(f"raw/{name}", []).append((now - sent) / 1e6)

    subs = [Subscriber(session, "bench/bus/**", on_bus, schema=Frame),
            session.declare_subscriber("bench/raw/*", direct_callback(on_raw))]
    ready.set()
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        total = sum(len(v) for v in lat.values())
        if total >= expected:
            break
        time.sleep(0.05)
    time.sleep(0.2)
    results.put(dict(lat))
    for sub in subs:
        sub.undeclare()
    session.close()


def run_bench_bus(args) -> int:
    from ..bus.pubsub import Publisher, ShmPool
    from ..bus.schemas import Frame
    from ..bus.session import open_session

    ctx = mp.get_context("spawn")
    ready, results = ctx.Event(), ctx.Queue()
    expected = 2 * args.count * len(SIZES)
    session = open_session(_settings(args.port, listen=True))
    proc = ctx.Process(target=_subscriber, args=(args.port, ready, results, expected), daemon=True)
    proc.start()
    if not ready.wait(30):
        print("subscriber did not start")
        return 1
    time.sleep(1.0)  # let the peers connect and declarations propagate
    shm = ShmPool()
    period = 1.0 / args.rate
    throughput: dict[str, float] = {}
    for label, size in SIZES.items():
        shape = _frame_shape(size)
        image = np.random.default_rng(0).integers(0, 255, size=shape, dtype=np.uint8)
        bus_pub = Publisher(session, f"bench/bus/{label}", "bench", shm=shm)
        raw_pub = session.declare_publisher(f"bench/raw/{label}")
        raw_body = bytearray(image.tobytes())
        time.sleep(0.3)
        # Interleave the two paths so both see the same machine load.
        spent = {"bus": 0.0, "raw": 0.0}
        for _ in range(args.count):
            t0 = time.perf_counter()
            bus_pub.put(Frame(width=shape[1] if len(shape) > 1 else size, height=shape[0], encoding=label,
                              data=image))
            spent["bus"] += time.perf_counter() - t0
            time.sleep(period / 2)
            t0 = time.perf_counter()
            raw_body[:8] = time.time_ns().to_bytes(8, "little")
            body = bytes(raw_body)
            buf = shm.buffer_with(body) if len(body) >= 64 * 1024 else None
            raw_pub.put(buf if buf is not None else body)
            spent["raw"] += time.perf_counter() - t0
            time.sleep(period / 2)
        for path in spent:
            throughput[f"{path}/{label}"] = args.count * size / max(spent[path], 1e-9) / 1e6
        bus_pub.undeclare()
        raw_pub.undeclare()
    lat = results.get(timeout=120)
    proc.join(timeout=10)
    session.close()

    rows = []
    print(f"followbus bench bus — {args.count} msgs per size at {args.rate:.0f} Hz, peer-to-peer over loopback, "
          f"SHM for payloads >= 64 KB; {platform.node()} {platform.processor() or platform.machine()}")
    print(f"{'size':>7} | {'bus p50':>8} {'bus p99':>8} | {'raw p50':>8} {'raw p99':>8} | {'ratio p50':>9} | "
          f"{'recv bus/raw':>12} | {'publish MB/s bus/raw':>20}")
    for label in SIZES:
        b = np.array(lat.get(f"bus/{label}", []))
        r = np.array(lat.get(f"raw/{label}", []))
        if not b.size or not r.size:
            print(f"{label:>7} | lost: bus {b.size}, raw {r.size}")
            continue
        row = {"size": label, "bus_p50_ms": float(np.percentile(b, 50)), "bus_p99_ms": float(np.percentile(b, 99)),
               "raw_p50_ms": float(np.percentile(r, 50)), "raw_p99_ms": float(np.percentile(r, 99)),
               "received_bus": int(b.size), "received_raw": int(r.size),
               "publish_mb_s_bus": throughput[f"bus/{label}"], "publish_mb_s_raw": throughput[f"raw/{label}"]}
        row["ratio_p50"] = row["bus_p50_ms"] / row["raw_p50_ms"]
        rows.append(row)
        print(f"{label:>7} | {row['bus_p50_ms']:8.3f} {row['bus_p99_ms']:8.3f} | {row['raw_p50_ms']:8.3f} "
              f"{row['raw_p99_ms']:8.3f} | {row['ratio_p50']:9.2f} | {b.size:>5}/{r.size:<6} | "
              f"{row['publish_mb_s_bus']:>9.0f}/{row['publish_mb_s_raw']:<10.0f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": platform.node(), "date": time.strftime("%Y-%m-%d"), "rows": rows}, fh, indent=2)
    return 0 if len(rows) == len(SIZES) else 1
