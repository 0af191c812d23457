"""``followbus bench egomotion``: the camera-motion estimate against the scenes' known shift, as graph.yaml runs it
and without its smeared-frame refit (evaluation/camera_motion.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

SETTINGS = {"as graph.yaml": {}, "w/o smeared-frame refit": {"smeared_refit": False}}


def _print_row(label: str, row: dict[str, Any]) -> None:
    print(f"{label:26s} {row['scene']:8s} frames {row['frames']:3d}  error mean {row['mean_err_px']:5.2f} px "
          f"p95 {row['p95_err_px']:5.2f} px  smeared {row['smeared_measured']:2d}/{row['smeared']:2d} measured "
          f"({row['smeared_unmeasured']} without estimate)  CPU {row['cpu_ms_median']:.2f} ms "
          f"(p99 {row['cpu_ms_p99']:.2f})", flush=True)


def run_bench_egomotion(args) -> int:
    from ...evaluation.camera_motion import SHIFT_SCENES, score_settings

    scenes = tuple(s.strip() for s in args.scenes.split(",") if s.strip()) if args.scenes else SHIFT_SCENES
    unknown = [s for s in scenes if s not in SHIFT_SCENES]
    if unknown:
        print(f"followbus: bench egomotion: {', '.join(unknown)}: not a scene with a known camera shift "
              f"(one of {', '.join(SHIFT_SCENES)})", file=sys.stderr)
        return 2
    result = score_settings(SETTINGS, scenes, progress=_print_row)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0
