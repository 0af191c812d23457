"""The report of ``followbus eval``: results.md (the tables, the exact command, the notes) and results.json."""

from __future__ import annotations

import json
import math
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from .metrics import SingleTargetMetrics, aggregate, format_markdown_table
from .runner import SequenceRun
from .trace import worst_episodes_markdown


def _num(v: Any) -> Any:
    if isinstance(v, float | np.floating):
        return None if not math.isfinite(float(v)) else round(float(v), 6)
    if isinstance(v, np.integer):
        return int(v)
    return v


def _metrics_json(m: SingleTargetMetrics) -> dict[str, Any]:
    d = {k: _num(v) for k, v in m.as_dict().items()}
    d["reid"] = [{"occlusion_start": e.occlusion_start, "reappear_frame": e.reappear_frame,
                  "occluded_frames": e.occluded_frames, "latency_frames": e.latency_frames,
                  "latency_ms": _num(e.latency_ms) if e.latency_ms is not None else None}
                 for e in m.reid_events]
    return d


def _fmt(v: float, spec: str = ".2f") -> str:
    return "–" if not math.isfinite(v) else format(v, spec)


def _parts_line(runs: list[SequenceRun], method: str) -> str:
    """The tracker's time per node over every frame of ``method`` (graph methods only): where the ms/frame go."""
    infos = [i for r in runs if method in r.runs for i in r.runs[method].infos]
    if not any("part_ms" in i for i in infos):
        return ""
    parts: dict[str, float] = {}
    for info in infos:
        for node, ms in info.get("part_ms", {}).items():
            parts[node] = parts.get(node, 0.0) + ms
    total = sum(t for r in runs if method in r.runs for t in r.runs[method].tracker_ms)
    n = len(infos)
    shares = ", ".join(f"{node} {ms / n:.2f}" for node, ms in parts.items())
    return (f"\n{method}, tracker ms/frame per part over all {n} frames: {shares}; the rest (the evaluation feeding "
            f"the graph and collecting its outputs) {(total - sum(parts.values())) / n:.2f}.")


def timing_table(runs: list[SequenceRun], methods: list[str]) -> str:
    """Re-ID latency in frames, censored events, detector and tracker ms per frame."""
    lines = ["### Re-ID latency and timing", "",
             "| Sequence | Frames | Detector ms/fr | Method | Re-ID frames (mean) | Re-ID censored | Tracker ms/fr |",
             "|---|---:|---:|---|---:|---:|---:|"]
    for r in runs:
        for m in methods:
            mr = r.runs.get(m)
            if mr is None or mr.metrics is None:
                continue
            cached = " (cached)" if r.detections_cached else ""
            lines.append(f"| {r.sequence.name} | {r.sequence.n_frames} | {_fmt(r.detector_ms_mean)}{cached} | {m} | "
                         f"{_fmt(mr.metrics.reid_latency_frames_mean, '.1f')} | {mr.metrics.reid_censored} | "
                         f"{_fmt(mr.tracker_ms_mean)} |")
    total = sum(r.sequence.n_frames for r in runs)
    det = sum(r.detector_ms_mean * r.sequence.n_frames for r in runs if math.isfinite(r.detector_ms_mean))
    for m in methods:
        ms = [t for r in runs if m in r.runs for t in r.runs[m].tracker_ms]
        agg = aggregate([r.runs[m].metrics for r in runs if m in r.runs and r.runs[m].metrics is not None])
        lines.append(f"| overall | {total} | {_fmt(det / total if total else math.nan)} | {m} | "
                     f"{_fmt(agg.reid_latency_frames_mean, '.1f')} | {agg.reid_censored} | "
                     f"{_fmt(float(np.mean(ms)) if ms else math.nan)} |")
    lines += [line for m in methods if (line := _parts_line(runs, m))]
    return "\n".join(lines) + "\n"


CEILING = "detector ceiling"


def summary_matrix(runs: list[SequenceRun], methods: list[str]) -> str:
    """Sequences × methods, each cell "TSR % / CLE px", with the frame-weighted overall row and, last, the
    detector ceiling (the detection nearest the target on every frame: the bound of any follower that
    outputs detections; one that coasts on a prediction through misses can exceed it)."""
    lines = ["### TSR@20px % / CLE px, sequences × methods", "",
             "| Sequence | Frames | " + " | ".join(methods) + f" | {CEILING} |",
             "|---|---:|" + "---:|" * (len(methods) + 1)]

    def cell(m: SingleTargetMetrics | None) -> str:
        return "–" if m is None else f"{_fmt(100 * m.tsr, '.1f')} / {_fmt(m.cle, '.0f')}"

    for r in runs:
        cells = [cell(r.runs[m].metrics if m in r.runs else None) for m in methods] + [cell(r.ceiling)]
        lines.append(f"| {r.sequence.name} | {r.sequence.n_frames} | " + " | ".join(cells) + " |")
    scored = [[r.runs[m].metrics for r in runs if m in r.runs and r.runs[m].metrics is not None] for m in methods]
    scored.append([r.ceiling for r in runs if r.ceiling is not None])
    overall = [aggregate(ms) if ms else None for ms in scored]
    total = sum(r.sequence.n_frames for r in runs)
    lines.append(f"| **overall (frame-weighted)** | {total} | "
                 + " | ".join(f"**{cell(m)}**" for m in overall) + " |")
    return "\n".join(lines) + "\n"


def mot_table(runs: list[SequenceRun], methods: list[str]) -> str:
    """MOTA/IDF1/HOTA of the multi-object trackers' whole output on the MOT sequences; "" when none ran."""
    from .mot_metrics import evaluate_mot_combined
    from .runner import gt_mot_frames

    mot_runs = [r for r in runs if any(mr.mot is not None for mr in r.runs.values())]
    if not mot_runs:
        return ""
    lines = ["### Multi-object metrics (MOT sequences, every annotated person)", "",
             "| Sequence | Frames | Method | MOTA % | IDF1 % | HOTA % | DetA % | AssA % | IDSW | FP | FN |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def row(name: str, frames: int, m: str, mm) -> str:
        c = mm.clear
        return (f"| {name} | {frames} | {m} | {_fmt(100 * c.mota, '.1f')} | {_fmt(100 * mm.idf1, '.1f')} | "
                f"{_fmt(100 * mm.hota.hota, '.1f')} | {_fmt(100 * mm.hota.deta, '.1f')} | "
                f"{_fmt(100 * mm.hota.assa, '.1f')} | {c.num_switches} | {c.num_false_positives} | {c.num_misses} |")

    for r in mot_runs:
        lines += [row(r.sequence.name, r.sequence.n_frames, m, r.runs[m].mot) for m in methods
                  if m in r.runs and r.runs[m].mot is not None]
    for m in methods:
        pairs = [(gt_mot_frames(r.gt_people), r.runs[m].mot_frames)
                 for r in mot_runs if m in r.runs and r.runs[m].mot is not None]
        if pairs:
            frames = sum(len(g) for g, _ in pairs)
            lines.append(row("**combined**", frames, m, evaluate_mot_combined(pairs)))
    lines += ["", "Scored as MOTChallenge/TrackEval do: IoU ≥ 0.5 for CLEAR and identity, HOTA over α = 0.05…0.95; "
              "gt = pedestrian rows not flagged 0; a tracker box matched to a distractor (person on vehicle, static "
              "person, distractor, reflection) is removed before scoring. Combined = all MOT sequences as one "
              "benchmark (counts summed).", ""]
    return "\n".join(lines) + "\n"


def _episode_json(boxes: list, run: SequenceRun) -> dict[str, Any] | None:
    from .trace import worst_episode

    ep = worst_episode(boxes, run.gt_boxes, run.other_gt)
    return None if ep is None else {"first_frame": ep.first, "frames": ep.length, "followed": ep.followed}


def write_report(runs: list[SequenceRun], methods: list[str], out: Path, command: str, detector: str,
                 notes: list[str]) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict[str, SingleTargetMetrics]] = {m: {} for m in methods}
    for r in runs:
        for m in methods:
            if m in r.runs and r.runs[m].metrics is not None:
                rows[m][r.sequence.name] = r.runs[m].metrics
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    md = [f"# followbus eval — {stamp}", "", f"Command: `{command}`", "",
          f"Detector: {detector} (the same cached detections for every method); "
          f"methods initialised with the first ground-truth box.", ""]
    md.append(summary_matrix(runs, methods))
    md.append(format_markdown_table(rows))
    md.append(mot_table(runs, methods))
    md.append(worst_episodes_markdown(runs, methods))
    md.append(timing_table(runs, methods))
    md += ["### Notes", ""] + [f"- {n}" for n in notes] + [""]
    md_path = out / "results.md"
    md_path.write_text("\n".join(md), encoding="utf-8")
    data: dict[str, Any] = {"command": command, "detector": detector, "date": stamp, "notes": notes,
                            "sequences": {}, "overall": {}}
    for r in runs:
        data["sequences"][r.sequence.name] = {
            "kind": r.sequence.kind, "frames": r.sequence.n_frames, "fps": r.sequence.fps,
            "size": [r.sequence.width, r.sequence.height], "detector_ms": _num(r.detector_ms_mean),
            "detections_cached": r.detections_cached,
            "detector_ceiling": _metrics_json(r.ceiling) if r.ceiling is not None else None,
            "methods": {m: {**_metrics_json(mr.metrics), "tracker_ms": _num(mr.tracker_ms_mean),
                            "worst_episode": _episode_json(mr.boxes, r),
                            **({"mot": {k: _num(v) for k, v in mr.mot.as_dict().items()}} if mr.mot else {})}
                        for m, mr in r.runs.items() if mr.metrics is not None},
        }
    for m, per_seq in rows.items():
        if per_seq:
            data["overall"][m] = _metrics_json(aggregate(per_seq.values()))
    ceilings = [r.ceiling for r in runs if r.ceiling is not None]
    if ceilings:
        data["overall"][CEILING] = _metrics_json(aggregate(ceilings))
    json_path = out / "results.json"
    json_path.write_text(json.dumps(data, indent=1, ensure_ascii=False), encoding="utf-8")
    return md_path, json_path


