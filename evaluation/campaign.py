"""An evaluation campaign (``followbus eval SEQ...``): the sequences named on the command line, each run through
every method on the same detections (evaluation/runner.py), plotted and traced, and the notes its report carries."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .runner import SequenceRun

log = logging.getLogger("followbus.eval")


def expand_sequences(specs: list[str]) -> list[str]:
    """``all`` → every sequence under the data root; ``scene:<name>`` and directories pass through."""
    from .datasets import find_data_root, list_sequences

    out: list[str] = []
    for s in specs:
        if s == "all":
            root = find_data_root()
            if root is None:
                raise FileNotFoundError("'all': no evaluation data found: set FOLLOWBUS_DATA to a folder holding "
                                        "sot/ and/or mot/ (the layouts of ../shared/data/README.md)")
            found = [str(p) for p in list_sequences(root)]
            if not found:
                raise FileNotFoundError(f"'all': no sequences under {root}/sot or {root}/mot")
            out += found
        elif s.startswith("scene:"):
            from ..vision.scenes import SCENES

            if s.split(":", 1)[1] not in SCENES:
                raise ValueError(f"unknown scene {s!r}; available: {', '.join(SCENES)}")
            out.append(s)
        else:
            out += _sequence_folders(s)
    return out


def _sequence_folders(spec: str) -> list[str]:
    """A sequence folder of any layout, or a folder of them (a benchmark's root); each read before any work
    starts (no pixels: cheap), so a folder that is not a sequence is one line naming what is missing."""
    from .datasets import detect_layout, load_sequence, sequences_in

    path = Path(spec)
    if not path.is_dir():
        raise FileNotFoundError(f"{spec}: not a directory (a sequence folder, scene:<name> or all)")
    folders = [path] if detect_layout(path) is not None else sequences_in(path) or [path]
    for folder in folders:
        try:
            load_sequence(folder)
        except (OSError, ValueError) as exc:
            raise ValueError(str(exc)) from exc
    return [str(f) for f in folders]



def run_campaign(seqs: list[str], factories: dict[str, Any], detector: str, out: Path, *, seed: int,
                 max_frames: int, write_frames: Callable[[SequenceRun], None],
                 jitter_px: float = 0.0) -> list[SequenceRun]:
    """Every sequence through every method (a progress bar over the sequences), plotted in ``out``/plots;
    ``write_frames`` writes what the command asked per run (traces, videos). A missing model raises ModelError."""
    from tqdm import tqdm

    from ..vision.models import ModelError
    from .plots import plot_sequence
    from .runner import open_sequence, run_sequence

    runs: list[SequenceRun] = []
    # delay: a run that fails at once (no model) shows its one line without a progress bar before it
    for spec in tqdm(seqs, desc="sequences", unit="seq", file=sys.stderr, delay=1.0):
        seq = open_sequence(spec, max_frames=max_frames)
        try:
            run = run_sequence(seq, factories, detector, cache_dir=out / "cache", seed=seed, progress=True,
                               jitter_px=jitter_px)
        except ModelError as exc:
            exc.sequence = spec  # type: ignore[attr-defined]  # the command's hint depends on its kind
            raise
        runs.append(run)
        plot_sequence(run, out / "plots")
        write_frames(run)
        fb = run.runs.get("followbus")
        if fb is not None and fb.metrics is not None:
            log.info("%s: followbus TSR %.3f CLE %.1f px", seq.name, fb.metrics.tsr, fb.metrics.cle)
    return runs


def campaign_notes(runs: list[SequenceRun], detector: str) -> list[str]:
    """What a reader of the report must know to read its numbers."""
    notes: list[str] = []
    if any(r.sequence.kind == "mot" for r in runs):
        notes.append("MOT sequences are scored as single-target following of the target chosen by "
                     "evaluation/datasets.py (feet nearest the image bottom-centre on the first annotated frame); "
                     "MOTA/IDF1/HOTA are multi-object metrics: reported only for the peer MOT trackers (their "
                     "whole output), never for single-target followers.")
    if detector == "simulated":
        notes.append("simulated detector = ground truth + noise: tracking numbers only, never detection accuracy.")
    if any(r.detections_cached for r in runs):
        notes.append("detector ms/frame of cached sequences is the time measured when the cache was filled.")
    notes.append("detector ceiling = the detection nearest the target on every frame (an oracle): the best a "
                 "follower that only outputs detections can do; followbus, kalman and the peers coast on their "
                 "prediction through missed detections and can exceed it there.")
    notes.append("Miss = gt frames without an output; Switch = output moved from the target onto another "
                 "annotated person (SOT sequences annotate only the target, so switches there are always 0); "
                 "Wrong re-lock = an episode of >= 10 frames with an output that does not overlap the target's box "
                 "(following someone else; counted on every sequence); Missed re-acq. = gt frames without an output "
                 "while re-ID's best-scoring candidate was a detection on the target (a robot that stops although "
                 "the person it follows is the best thing it sees; followbus only).")
    return notes
