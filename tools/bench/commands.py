"""The commands that produce figures: ``bench bus|pipeline|soak|chaos`` and ``eval`` (rows of tools/cli.py's table).

Light on purpose (argparse only): every ``followbus`` run imports it; each handler imports its module."""

from __future__ import annotations

import argparse
from pathlib import Path

from ...vision.detector_presets import DETECTOR_PRESETS
from ..command import (
    Command,
    Lazy,
    bus_namespace,
    count,
    count_or_zero,
    describe,
    non_negative,
    output_file,
    port,
    positive,
)


def _bus_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "One-way latency (p50/p99) and CPU per message of 1 KB to 2.76 MB frames at 30 and 100 Hz through raw "
             "zenoh, through bus/ and, with --against dora, through dora-rs: each path in its own stream between "
             "its own two processes, rounds interleaved (BENCHMARKS.md).",
             "examples:\n  followbus bench bus\n"
             "  followbus bench bus --against dora --rounds 5 --count 100 --json bus.json\n"
             "  followbus bench bus --sizes 921KB,2.76MB --rates 30", raw=True)
    p.add_argument("--count", type=count, default=100,
                   help="counted messages per size and rate per round (default 100)")
    p.add_argument("--rounds", type=count, default=3, help="rounds; each runs every path once, in turn (default 3)")
    p.add_argument("--sizes", metavar="LIST", help="comma-separated, of 1KB,100KB,921KB,2.76MB (default: all)")
    p.add_argument("--rates", metavar="HZ,...", help="comma-separated message rates (default 30,100)")
    p.add_argument("--against", choices=("dora",),
                   help="also measure dora-rs 1.1.0 (its own dataflow; pip install 'followbus[bench]')")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write the figures as JSON")


def _pipeline_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Launch graph.yaml at 30 Hz on a synthetic scene and measure per-edge latency "
             "p50/p99 from the message headers, CPU per node and dropped frames.",
             "examples: followbus bench pipeline --duration 20 --detector yolox\n"
             "  followbus bench pipeline --set redetection.local_redetection=false   the loop without seed 002's "
             "second look")
    p.add_argument("--duration", type=positive, default=20.0, metavar="S", help="seconds of measurement (default 20)")
    p.add_argument("--detector", default="graph", choices=tuple(DETECTOR_PRESETS),
                   help="detector (default graph: graph.yaml's own detection params; yolox = YOLOX-nano@416, "
                        "yolox512, yolox640, yolox640-int8, *-openvino: the same ONNX on OpenVINO; falls back to "
                        "hog without the model)")
    p.add_argument("--scene", default="corridor-occlusion", help="synthetic scene (default corridor-occlusion)")
    p.add_argument("--resolution", default="640x480", metavar="WxH", type=_resolution,
                   help="the scene's frame size (default 640x480; e.g. 1280x720, 1920x1080)")
    p.add_argument("--lane", choices=("on", "off"), default="off",
                   help="the same-host shared-memory lane (zenoh: shm_lane; default off, as graph.yaml)")
    p.add_argument("--port", type=port, default=0, help="loopback port (default: a free one)")
    p.add_argument("--namespace", type=bus_namespace, default="", help="graph namespace (default bench<port>)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write the figures as JSON")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="override a node's parameter for this run (repeatable), as `followbus launch --set`")


def _soak_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Launch graph.yaml at 30 Hz on a looping scene and follow for --minutes, a row per --window: frames "
             "answered, capture->command p50/p99, CPU per frame, and every node's RSS, open descriptors and threads. "
             "Clean when no node restarted, RSS grew <= 30 MB per node, descriptors and threads did not grow, "
             "no window answered more than 5 points fewer frames than the first, and the last p99 is within 50 ms "
             "of the first (RELIABILITY.md): it judges drift, not the machine's speed. "
             "Exit status 0 when clean, 1 otherwise.",
             "example: followbus bench soak --minutes 10 --json soak.json")
    p.add_argument("--minutes", type=positive, default=10.0, help="how long to follow (default 10)")
    p.add_argument("--window", type=positive, default=60.0, metavar="S", help="seconds per row (default 60)")
    p.add_argument("--detector", default="graph", choices=tuple(DETECTOR_PRESETS),
                   help="detector (default graph: graph.yaml's own detection params)")
    p.add_argument("--scene", default="corridor-occlusion", help="synthetic scene (default corridor-occlusion)")
    p.add_argument("--port", type=port, default=0, help="loopback port (default: a free one)")
    p.add_argument("--namespace", type=bus_namespace, default="", help="graph namespace (default bench<port>)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write every window as JSON")


def _egomotion_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "How well the camera-motion estimate (the egomotion node's) measures the camera: on the scenes whose "
             "camera shifts the whole image by a known amount (overlay pans, bumpy jolts, shaky re-aims with "
             "smeared frames), the error of each frame's estimate at the image centre, how many smeared frames "
             "it measured to 5 px, and its CPU ms a frame; as graph.yaml runs it and without its smeared-frame "
             "refit (BENCHMARKS.md, \"Camera motion on smeared frames\").",
             "example: followbus bench egomotion --scenes shaky,bumpy --json egomotion.json")
    p.add_argument("--scenes", metavar="LIST", help="comma-separated, of bumpy,shaky,overlay (default: all)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write the figures as JSON")


def _detector_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "The cost of each detector side by side: CPU and wall ms per inference on frames of the built-in "
             "scenes, with graph.yaml's detection threads, every detector once per round (BENCHMARKS.md, "
             "\"Detectors side by side\").",
             "example: followbus bench detector --detectors yolox,yolox512,yolox640 --rounds 4")
    p.add_argument("--detectors", default="yolox,yolox512,yolox640,yolox640-int8,yolox416-openvino,"
                   "yolox512-openvino,yolox640-openvino", metavar="LIST",
                   help="comma-separated --detector names (default: every YOLOX variant; the first is the unit)")
    p.add_argument("--rounds", type=count, default=4, help="rounds (default 4)")
    p.add_argument("--frames", type=count, default=7, metavar="N", help="frames per scene, 3 scenes (default 7)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write the figures as JSON")


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1280x720, not {text!r}") from None
    if not (32 <= w <= 7680 and 32 <= h <= 4320):
        raise argparse.ArgumentTypeError(f"{text}: width 32-7680 and height 32-4320 pixels")
    return w, h


def _record_views_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Feed a recording's bus messages through the recorder's convert and write work, in one process, "
             "with the views as they were (base64 JPEG JSON, annotations) and as they are (ROS 2 CDR, JSON of "
             "every message, annotations, the .ros2.mcap companion); per frame, rounds alternated.",
             "example: followbus launch graph.yaml --duration 20 --record run.mcap --set detection.backend=simulated\n"
             "         followbus bench record-views run.mcap --rounds 3", raw=True)
    p.add_argument("file", help="a recording (followbus record / launch --record)")
    p.add_argument("--rounds", type=count, default=3, help="rounds of before, now (default 3)")
    p.add_argument("--frame-output", default="frame", metavar="NAME",
                   help="frames are counted on the keys <node>/NAME (default frame)")


def _chaos_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Launch graph.yaml on a private loopback port (scene looping at 30 Hz, the real YOLOX-nano\n"
             "detector), optionally under --burners background CPU burners for the whole run, and try one\n"
             "fault at a time. After each fault it requires:\n"
             "  - 0 unsafe motor commands (a non-finite field, a speed beyond the motor's limits);\n"
             "  - a zero command <= 200 ms after the last track whenever tracks stop;\n"
             "  - the robot following again (TRACKING) within --recovery-bound of the fault's end (node\n"
             "    back up, or injection over; time the scene itself hides the target is added), then\n"
             "    tracking most of the next --hold seconds;\n"
             "  - under load: p99 capture->command <= 250 ms, and >= 50 % of frames answered (load).\n"
             "It prints the load (1-min load average through the run, /proc/loadavg at the end) with the\n"
             "figures: survival, unsafe commands, worst stop, following p99, frames answered.\n"
             "A fault the loop does not survive is followed by a fresh launch of the graph.\n\n"
             "faults (--faults, comma-separated; 'all' is the default, 'ci' the tests' subset):\n"
             "  kill-capture (capture-restart), kill-detection, kill-prediction, kill-reid, kill-template,\n"
             "  kill-motor          SIGKILL the node; the launcher restarts it\n"
             "  stop-prediction-2s  SIGSTOP prediction for 2 s\n"
             "  load                --load-seconds of following under the run's load (--burners)\n"
             "  detector-delay-80ms detection takes 80 ms a frame (simulated sim_delay_ms; own launch)\n"
             "  future-stamp-track  a TRACKING track stamped +1 h, then SIGKILL prediction\n"
             "  future-seq-frame, future-seq-detections\n"
             "                      one message with frame_seq +10**9, then a 0.3 s camera stall\n"
             "  nan-measurement     an accepted TRACKING measurement with a NaN box\n"
             "  malformed           garbage/wrong-type/truncated/wrong-field payloads on every input key\n"
             "  flood               300 valid frames as fast as possible on capture/frame\n"
             "  kill-recorder       SIGKILL the recorder (only with --record)\n"
             "Exit status 0 when every fault was survived, 1 otherwise.",
             "examples:\n  followbus bench chaos                                   every fault, the table\n"
             "  followbus bench chaos --faults kill-reid,nan-measurement --repeat 3\n"
             "  followbus bench chaos --faults load --burners 4 --load-seconds 20 --json chaos.json\n"
             "  followbus bench chaos --record --faults kill-recorder",
             raw=True)
    p.add_argument("--faults", metavar="NAME,...", help="faults to try, in order (default: all)")
    p.add_argument("--detector", default="yolox416", choices=("yolox416", "simulated"),
                   help="detection backend (default yolox416: the real detector, models/yolox_nano_416.onnx; "
                        "simulated: deterministic and light, adds detector-delay-80ms)")
    p.add_argument("--scene", default="corridor-occlusion", help="synthetic scene (default corridor-occlusion)")
    p.add_argument("--burners", type=count_or_zero, default=0, metavar="N",
                   help="processes spinning a CPU each for the whole run: every fault under that load (default 0)")
    p.add_argument("--load-seconds", type=positive, default=10.0, metavar="S",
                   help="how long the load fault and the detector delay are measured (default 10)")
    p.add_argument("--repeat", type=count, default=1, metavar="N", help="run the fault list N times (default 1)")
    p.add_argument("--record", action="store_true", help="run a recorder with the graph (adds kill-recorder)")
    p.add_argument("--recovery-bound", type=positive, default=2.0, metavar="S",
                   help="seconds from the fault's end to following again (default 2)")
    p.add_argument("--hold", type=positive, default=3.0, metavar="S",
                   help="after recovery, seconds that must be tracked most of the time (default 3)")
    p.add_argument("--malformed-per-key", type=count, default=10_000, metavar="N",
                   help="malformed payloads per input key (default 10000)")
    p.add_argument("--port", type=port, default=0, help="loopback port (default: a free one)")
    p.add_argument("--namespace", type=bus_namespace, default="", help="the graph's namespace (default chaos<port>)")
    p.add_argument("--log", type=output_file, default="state/chaos.log",
                   help="where node logs go (default state/chaos.log)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write every run's checks and figures as JSON")


def _link_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "The robot graph (graph.robot.yaml) in one network namespace, a laptop in another with its own\n"
             "/dev/shm, a veth pair shaped with htb to --rate-mbit each way. Per case, alternated round by round:\n"
             "the robot's capture->command p50/p99 and frames answered (a probe on the robot), and what the\n"
             "laptop's recording holds (received, dropped, seq gaps per key). Cases: none (no laptop),\n"
             "monitor (monitor --web), record-all (record --raw-frames), record (the remote default: raw frames\n"
             "left out), watch (plain subscribers to the command, the track and the preview: per key received/s,\n"
             "lost, age on arrival), frames (the same and the raw frame key). Needs root (ip netns, tc); exit\n"
             "status 2 without.",
             "examples:\n  followbus bench link --rate-mbit 2 --seconds 20 --rounds 3\n"
             "  followbus bench link --rate-mbit 2,20,100 --cases none,watch,frames --rounds 2", raw=True)
    p.add_argument("--rate-mbit", default="2", metavar="R[,R...]",
                   help="link rate each way, or several comma-separated (a robot launch each; default 2)")
    p.add_argument("--seconds", type=positive, default=20.0, metavar="S", help="measured seconds per case (default 20)")
    p.add_argument("--rounds", type=count, default=3, help="rounds of every case, alternated (default 3)")
    p.add_argument("--cases", metavar="LIST",
                   help="comma-separated, of none,monitor,record-all,record,watch,frames (default all)")
    p.add_argument("--large-rule", choices=("block_first", "drop"), default="block_first",
                   help="what the robot's router does with large messages (raw frames) to the laptop: BLOCK_FIRST "
                        "at data_low (bus/netif.py, the default), or DROP as every other message (as before)")
    p.add_argument("--detector", default="simulated", choices=("simulated", "hog", "yolox"),
                   help="detection backend of the robot graph (default simulated)")
    p.add_argument("--port", type=port, default=21650, help="the robot's port, inside its namespace (default 21650)")
    p.add_argument("--unprotected", action="store_true",
                   help="the robot's links to the laptop keep BLOCK congestion control (bus/netif.py off): "
                        "shows what a laptop recording raw frames does to an unprotected robot")
    p.add_argument("--log", type=output_file, default="state/link.log",
                   help="the robot graph's log (default state/link.log)")
    p.add_argument("--drop-wait-us", type=int, metavar="US",
                   help="the robot's zenoh wait_before_drop and max_wait_before_drop_fragments (default "
                        "graph.robot.yaml's: 1000 us both; zenoh's own: 1000 and 50000): how long its router waits "
                        "on a full link before dropping")
    p.add_argument("--laptop-nice", type=int, default=19, metavar="N",
                   help="CPU priority of the laptop's processes (default 19: on this one machine they take only "
                        "the CPU the robot leaves, as a separate laptop would; 0: the robot's equal)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write every run's figures as JSON")


def _flood_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "The robot graph (graph.robot.yaml) on loopback and a flooder joined as the read-only `monitor`\n"
             "identity (at nice 19) that declares --subscribers subscribers on distinct keys, holds them and\n"
             "leaves. Per phase (before, declaring, held, left): the robot's capture->command p99, frames answered,\n"
             "the motor's watchdog stops, and the RSS of the launcher (the hub) and of each node against before.",
             "example: followbus bench flood --subscribers 10000 --seconds 10", raw=True)
    p.add_argument("--subscribers", type=count, default=10_000, metavar="N",
                   help="subscribers declared (default 10000)")
    p.add_argument("--seconds", type=positive, default=10.0, metavar="S",
                   help="seconds per measured window (default 10)")
    p.add_argument("--detector", default="simulated", choices=("simulated", "hog", "yolox"),
                   help="detection backend of the robot graph (default simulated)")
    p.add_argument("--port", type=port, default=21680, help="the robot's port on loopback (default 21680)")
    p.add_argument("--log", type=output_file, default="state/flood.log",
                   help="the robot graph's log (default state/flood.log)")
    p.add_argument("--json", type=output_file, metavar="FILE", help="also write the figures as JSON")


def _eval_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Run followbus, the Kalman baseline, ablations and peer trackers in-process "
             "over SOT/MOT sequences and synthetic scenes on the same cached detections; "
             "write results.md, results.json and PNG plots. Peers (Roboflow trackers: "
             "ByteTrack, OC-SORT, BoT-SORT) follow the id of the track overlapping the "
             "first ground-truth box; on MOT sequences they also get MOTA/IDF1/HOTA of "
             "their whole output. `make` installs them (requirements-peers.txt).",
             "examples:\n  followbus eval all --ablations              graph.yaml's detector\n"
             "  followbus eval all --method followbus --detector yolox640-openvino\n"
             "  followbus eval ../shared/data/sot/otb-jogging scene:wall-occlusion "
             "--method followbus\n"
             "  followbus eval ~/data/OTB100/Human3 --trace --video     an OTB folder, every frame, an MP4\n"
             "  followbus eval ~/data/LaSOT/person                     every sequence of a folder\n"
             "  followbus eval ../shared/data/mot/tud-campus --method followbus "
             "--method peer:bytetrack --method peer:botsort\n"
             "  followbus eval scene:wall-occlusion --graph-check\n"
             "  followbus eval --group --out results/group\n"
             "  followbus eval --group --camera --out results/group\n"
             "  followbus eval ../shared/data/sot/otb-crossing --graph-check --detector yolox",
             raw=True)
    p.add_argument("sequences", nargs="*", metavar="SEQ",
                   help="sequence dir (sot/<name>, mot/<name>), scene:<name>, or 'all' (every sequence of the data)")
    p.add_argument("--group", action="store_true",
                   help="instead: seed 004's group-tracking benchmark on simulated squads (RMSE, OE, Lat-STD of "
                        "ME-CGT-UGV and its comparison methods per scenario; group.md, group.json, plots)")
    p.add_argument("--camera", action="store_true",
                   help="with --group: the same methods on the camera group sequences (SEQ dirs, default "
                        "sot/uav-group* and every mot/ clip): image-plane group-centre error; group_camera.md/json")
    p.add_argument("--method", action="append", metavar="M",
                   help="followbus | kalman | peer:bytetrack|ocsort|botsort | one ablation by its name (as --ablations "
                        "lists them, e.g. 'followbus w/o partial-view completion'); repeatable (default followbus + "
                        "kalman)")
    p.add_argument("--ablations", action="store_true", help="also run the paper's Table 6 ablations of followbus")
    p.add_argument("--detector", default=None, choices=tuple(DETECTOR_PRESETS),
                   help="detections for every method (default graph: graph.yaml's own detection params, what the "
                        "robot runs; yolox = YOLOX-nano@416, yolox512, yolox640, yolox640-int8 (static INT8), "
                        "yolox*-openvino (the same ONNX on OpenVINO), hog, simulated; with --graph-check: "
                        "simulated for scenes, graph for sequence dirs)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output directory (default results/)")
    p.add_argument("--trace", action="store_true",
                   help="also write, per sequence and method, every frame: trace/<seq>/<method>.jsonl (output, "
                        "state, prior and its gate, candidates with colour/geometry/classifier scores, camera "
                        "motion, reason) and tracker_results/<method>/<seq>.txt (OTB toolkit format)")
    p.add_argument("--video", action="store_true",
                   help="also write videos/<seq>-<method>.mp4 of the first method's run: ground truth (green), "
                        "output (red), gate (cyan), candidates with their fused scores (implies the trace data)")
    p.add_argument("--max-frames", type=count_or_zero, default=0, metavar="N",
                   help="only the first N frames per sequence")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the simulated detector and of --jitter-px (default 0)")
    p.add_argument("--jitter-px", type=non_negative, default=0.0, metavar="PX",
                   help="move every detection's x, y, w, h by Gaussian noise of PX px (1 sigma; its score by PX/200) "
                        "before any method sees it: does a result survive the last-digit differences of another "
                        "CPU's detector? Run several --seed values (default 0: the detections as they are)")
    p.add_argument("--graph-check", action="store_true",
                   help="instead: run the scene(s) through the launched graph and in-process, require identical boxes")
    p.set_defaults(argv=None)


COMMANDS = (
    Command("bench", "benchmarks that write figures (see BENCHMARKS.md)", subcommands=(
        Command("bus", "one-way latency and CPU per message: raw zenoh, bus/ (and dora-rs)", _bus_args,
                Lazy("bench.bus", "run_bench_bus")),
        Command("pipeline", "end-to-end latency capture -> motor command through the launched graph", _pipeline_args,
                Lazy("bench.pipeline", "run_bench_pipeline")),
        Command("soak", "minutes of following: memory, descriptors, threads and latency must not grow", _soak_args,
                Lazy("bench.soak", "run_bench_soak")),
        Command("detector", "CPU and wall ms per inference of each detector, side by side", _detector_args,
                Lazy("bench.detector", "run_bench_detector")),
        Command("egomotion", "the camera-motion estimate against scenes of known camera motion", _egomotion_args,
                Lazy("bench.egomotion", "run_bench_egomotion")),
        Command("link", "a laptop on a slow link: the robot's latency, and what the laptop's recording lost",
                _link_args, Lazy("bench.link", "cmd_bench_link")),
        Command("flood", "a read-only laptop declaring thousands of subscribers: the robot's p99 and memory",
                _flood_args, Lazy("bench.flood", "cmd_bench_flood")),
        Command("chaos", "fault injection: does the live loop always recover? (RELIABILITY.md)", _chaos_args,
                Lazy("bench.chaos", "run_bench_chaos")),
        Command("record-views", "what the recorder's views cost per frame (convert and write), before and now",
                _record_views_args, Lazy("bench.record_views", "run_bench_record_views")),
    )),
    Command("eval", "score followers on sequences (paper metrics, baselines, ablations, plots)", _eval_args,
            Lazy("bench.eval", "cmd_eval")),
)
