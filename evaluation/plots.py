"""PNG plots of an evaluation run (matplotlib, Agg backend: no display needed).

* ``<seq>_error.png`` — centre error over frames for every method (paper Fig. 10), occlusion spans
  shaded (gt absent, or for scenes less than half the target visible); frames where a method gave no
  output while the target was there are marked with ticks at the top.
* ``<seq>_eta.png`` — η_k of followbus (and of the "w/o adaptive η" ablation when run) over frames
  (paper Fig. 11), same shading.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np

from .runner import SequenceRun

log = logging.getLogger(__name__)


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_")


def _shade(ax, spans: list[tuple[int, int]], label: str = "occluded / absent") -> None:
    for i, (a, b) in enumerate(spans):
        ax.axvspan(a - 0.5, b + 0.5, color="0.85", zorder=0, label=label if i == 0 else None)


def plot_sequence(run: SequenceRun, out_dir: Path, tsr_px: float = 20.0) -> list[Path]:
    """Write the plots of one sequence; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    name = run.sequence.name
    spans = run.occlusion_spans()
    paths: list[Path] = []
    n = len(run.gt_boxes)
    frames = np.arange(n)
    gt_present = np.array([g is not None for g in run.gt_boxes])

    fig, ax = plt.subplots(figsize=(10, 4), dpi=100)
    _shade(ax, spans)
    ymax = tsr_px * 3
    finite_max = 0.0
    for method, mrun in run.runs.items():
        err = mrun.metrics.center_errors if mrun.metrics is not None else np.full(n, math.nan)
        if np.isfinite(err).any():
            finite_max = max(finite_max, float(np.nanmax(err)))
        lw = 1.6 if method in ("followbus", "kalman") else 0.9
        ls = "--" if " w/o " in method else "-"  # ablations dashed, peers solid
        (line,) = ax.plot(frames, err, lw=lw, ls=ls, label=method)
        missing = gt_present & np.array([b is None for b in mrun.boxes])
        if missing.any():
            ax.plot(frames[missing], np.full(missing.sum(), 1.0), "|", color=line.get_color(), ms=6,
                    transform=ax.get_xaxis_transform(), clip_on=False)
    ax.axhline(tsr_px, color="k", ls="--", lw=0.8, label=f"τ = {tsr_px:g} px")
    ax.set_ylim(0, max(ymax, min(finite_max * 1.05, 400.0)))
    ax.set_xlim(-0.5, n - 0.5)
    ax.set_xlabel("frame")
    ax.set_ylabel("centre error e_t (px)")
    ax.set_title(f"{name}: centre error ({run.detector} detections; ticks on top = no output)")
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    fig.tight_layout()
    p = out_dir / f"{_slug(name)}_error.png"
    fig.savefig(p)
    plt.close(fig)
    paths.append(p)

    eta_methods = [m for m in run.runs if m.startswith("followbus") and ("eta" in run.runs[m].infos[-1]
                                                                          if run.runs[m].infos else False)]
    eta_methods = [m for m in eta_methods if m in ("followbus", "followbus w/o adaptive η")]
    if eta_methods:
        fig, ax = plt.subplots(figsize=(10, 3), dpi=100)
        _shade(ax, spans)
        for method in eta_methods:
            ax.plot(frames, run.runs[method].series("eta"), lw=1.2, label=f"η_k {method}")
        ax.set_xlim(-0.5, n - 0.5)
        ax.set_xlabel("frame")
        ax.set_ylabel("η_k")
        ax.set_title(f"{name}: template learning rate η_k (0 = update suspended)")
        ax.legend(fontsize=7, loc="upper right")
        fig.tight_layout()
        p = out_dir / f"{_slug(name)}_eta.png"
        fig.savefig(p)
        plt.close(fig)
        paths.append(p)
    return paths
