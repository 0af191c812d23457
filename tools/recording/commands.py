"""The recording commands: ``record``, ``play``, ``replay``, ``info``, ``recover`` (rows of tools/cli.py's table).

Light on purpose (argparse only): every ``followbus`` run imports it; each handler imports its module."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..command import (
    Command,
    Lazy,
    connect_args,
    count_or_zero,
    describe,
    key_expression,
    load_graph,
    non_negative,
    output_file,
    positive,
    settings,
)


def _record_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Join the bus as a client and store every message losslessly (its exact frame bytes, one channel per "
             "key) in an MCAP file, plus views every MCAP reader decodes without followbus: frames as "
             "sensor_msgs/CompressedImage, the command as geometry_msgs/Twist, odometry as nav_msgs/Odometry, "
             "detections as vision_msgs/Detection2DArray (ROS 2 CDR: Foxglove, rosbags, ros2 bag), every message "
             "as JSON with a JSON Schema (<key>/json), detections, the Kalman gate and the target as "
             "foxglove.ImageAnnotations. --split-size/--split-duration start a new file (<name>_0.mcap, "
             "<name>_1.mcap, ...) as rosbag2 does. Ctrl-C/SIGTERM finalise the file; a "
             "killed recorder leaves one that `followbus recover` repairs. A write error (full disk) ends it at "
             "once: the file is finalised at its last complete chunk, one line says what was lost, exit "
             "status 1. Ends with received/written/dropped counts and the messages lost upstream "
             "(header.seq gaps).",
             "examples:\n  followbus record -o recordings/run1.mcap --duration 60\n"
             "  followbus record --topics 'fb/capture/**' 'fb/prediction/**' --status\n"
             "  followbus record -o recordings/day.mcap --split-size 1000    # day_0.mcap, day_1.mcap, ... of 1 GB",
             raw=True)
    p.add_argument("-o", "--output", type=output_file, metavar="FILE",
                   help="output file (default recordings/<graph>-<time>.mcap)")
    p.add_argument("--topics", nargs="+", type=key_expression, metavar="PATTERN",
                   help="key expressions to record (default <ns>/**)")
    p.add_argument("--exclude", action="append", type=key_expression, metavar="PATTERN",
                   help="leave out keys matching this key expression, e.g. 'fb/capture/frame' (raw frames; the "
                        "JPEG preview stays); repeatable")
    p.add_argument("--raw-frames", action="store_true",
                   help="over a network (an endpoint beyond loopback) record the raw frames too; by default a "
                        "remote recording leaves every <node>/frame out (a Wi-Fi link cannot carry them) and "
                        "keeps the JPEG preview")
    p.add_argument("--duration", type=positive, metavar="S", help="stop after S seconds")
    p.add_argument("--status", action="store_true", help="also record the @status keys (node statistics)")
    p.add_argument("--compression", choices=("lz4", "zstd", "none"), default="none",
                   help="chunk compression (default none: raw frames do not compress with lz4, and uncompressed "
                        "chunks are read 3x faster by replay; zstd for archives at low rates)")
    p.add_argument("--chunk-mb", type=positive, default=4.0, metavar="MB",
                   help="close a chunk at this size (default 4)")
    p.add_argument("--chunk-seconds", type=positive, default=1.0, metavar="S",
                   help="close and flush a chunk at least this often: all a SIGKILL can lose (default 1)")
    p.add_argument("--jpeg-quality", type=int, default=80, metavar="Q",
                   help="JPEG quality of the image views of bgr8 frames (default 80)")
    p.add_argument("--no-foxglove", "--no-views", action="store_true", dest="no_foxglove",
                   help="store the bus messages only (no ROS 2 / JSON / Foxglove views)")
    p.add_argument("--raw-images", action="store_true",
                   help="view bgr8 frames as sensor_msgs/Image (lossless; as many bytes again as the frames) "
                        "instead of JPEG sensor_msgs/CompressedImage")
    p.add_argument("--no-ros2-file", action="store_true",
                   help="no <name>.ros2.mcap beside the recording (its ROS 2 channels again, in a file of profile "
                        "ros2 that rosbags and `ros2 bag` open; the main file's other encodings stop them)")
    p.add_argument("--split-size", type=positive, metavar="MB",
                   help="start a new file when this one reaches MB megabytes (<name>_0.mcap, <name>_1.mcap, ...)")
    p.add_argument("--split-duration", type=positive, metavar="S",
                   help="start a new file every S seconds of recording")
    p.add_argument("--max-queue-mb", type=positive, default=256.0, metavar="MB",
                   help="memory the writer queue may hold before the recorder drops, counted per key (default 256)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", dest="overrides",
                   help="parameter overrides the graph runs with (as given to launch), stored in the metadata")
    connect_args(p)


def _play_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Publish the stored bus messages (their exact bytes) on their keys, or remapped ones, paced by "
             "their stamps. In a terminal: space pauses/resumes, s steps one message while paused, q quits.",
             "examples:\n  followbus play recordings/run1.mcap --topics 'fb/capture/**' --rate 0.5\n"
             "  followbus play recordings/run1.mcap --remap fb=fb2 --fast --loop",
             raw=True)
    p.add_argument("file", help="MCAP recording")
    p.add_argument("--topics", nargs="+", type=key_expression, metavar="PATTERN",
                   help="only keys matching these key expressions")
    p.add_argument("--remap", action="append", metavar="FROM=TO", help="key prefix remap, e.g. fb=fb2; repeatable")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--rate", type=positive, default=1.0, metavar="R", help="speed factor (default 1)")
    speed.add_argument("--fast", action="store_true", help="as fast as the bus takes them")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.add_argument("--start-paused", action="store_true", help="wait for space (or s) before the first message")
    p.add_argument("--status", action="store_true", help="also publish recorded @status messages")
    _on_corrupt_arg(p)
    connect_args(p)


def _replay_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Host the node in this process (its spec and params as recorded, --param overrides) with its "
             "clock driven by message stamps and feed it its recorded inputs in the order they were "
             "published, with what the live run did (skipped frames, feedback joined). --isolated runs the "
             "deployed node as a process in a private graph over Zenoh instead. --verify diffs its outputs "
             "with the recorded ones (exact for integers and strings, --rtol/--atol for floats) and exits 1 "
             "on a difference.",
             "examples:\n  followbus replay recordings/run1.mcap --node reid --verify\n"
             "  followbus replay recordings/run1.mcap --node reid,prediction --verify\n"
             "  followbus replay recordings/run1.mcap --node reid --verify --isolated\n"
             "  followbus replay recordings/run1.mcap --node prediction --param gate_chi2=5.99 --report out.json",
             raw=True)
    p.add_argument("file", help="MCAP recording")
    p.add_argument("--node", required=True,
                   help="node to replay; several, comma-separated, run together (their edges in-process)")
    p.add_argument("--isolated", action="store_true",
                   help="run the node as its own process over Zenoh (the deployed node), not in-process")
    p.add_argument("--graph", default=None, help="graph file (default: the graph.yaml stored in the recording)")
    p.add_argument("--param", action="append", metavar="KEY=VALUE",
                   help="override a parameter (YAML value); with several nodes NODE.KEY=VALUE")
    p.add_argument("--verify", action="store_true", help="compare outputs with the recording; exit 1 on a mismatch")
    p.add_argument("--report", type=output_file, metavar="FILE", help="write a JSON summary")
    p.add_argument("--rtol", type=non_negative, default=1e-6, help="relative tolerance for floats (default 1e-6)")
    p.add_argument("--atol", type=non_negative, default=1e-6, help="absolute tolerance for floats (default 1e-6)")
    p.add_argument("--timeout", type=positive, default=5.0, metavar="S",
                   help="--isolated: seconds to wait for a frame's outputs (default 5)")
    p.add_argument("--startup-timeout", type=positive, default=60.0, metavar="S",
                   help="--isolated: seconds to wait for the node to come up (default 60)")
    p.add_argument("--max-frames", type=count_or_zero, default=0, metavar="N", help="only the first N frames")
    _on_corrupt_arg(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _on_corrupt_arg(p: argparse.ArgumentParser) -> None:
    from ...bus.recording import ON_CORRUPT

    p.add_argument("--on-corrupt", choices=ON_CORRUPT, default="refuse",
                   help="a chunk failing its CRC (checked before anything is used): refuse (the default: exit 2 "
                        "naming the chunk and its time range) or skip it with a warning")


def _info_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             None,
             "example: followbus info recordings/run1.mcap")
    p.add_argument("file", help="MCAP recording")


def _recover_args(p: argparse.ArgumentParser) -> None:
    describe(p,
             "Copy every complete chunk and metadata record of a truncated MCAP file (a "
             "recorder killed with SIGKILL, a full disk) into a new, finalised file.",
             "example: followbus recover recordings/run1.mcap -o recordings/run1-fixed.mcap")
    p.add_argument("file", help="truncated MCAP file")
    p.add_argument("-o", "--output", type=output_file, metavar="FILE",
                   help="output (default: FILE with .recovered.mcap)")
    p.add_argument("--compression", choices=("lz4", "zstd", "none"), help="default: the input's")

def _record(args: argparse.Namespace) -> int:
    from ...bus.graph import apply_overrides
    from .record import cmd_record

    graph = load_graph(args.graph) if Path(args.graph).exists() else None
    if graph is not None:
        apply_overrides(graph, args.overrides)
    return cmd_record(args, settings(args), graph)


def _play(args: argparse.Namespace) -> int:
    from .play import cmd_play

    return cmd_play(args, settings(args))


COMMANDS = (
    Command("record", "record the bus to an MCAP file that opens in Foxglove", _record_args, _record),
    Command("play", "publish a recording's bus messages again", _play_args, _play),
    Command("replay", "replay a recording into one node or a few (regression test with --verify)", _replay_args,
            Lazy("recording.replay", "cmd_replay")),
    Command("info", "topics, counts, rates, duration and metadata of a recording", _info_args,
            Lazy("recording.mcap_io", "cmd_info")),
    Command("recover", "rewrite a killed recorder's file into a valid MCAP", _recover_args,
            Lazy("recording.mcap_io", "cmd_recover")),
)
