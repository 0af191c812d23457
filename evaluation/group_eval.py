"""``followbus eval --group``: seed 004's simulation benchmark (§4) over evaluation/group_sim.py's scenarios.

Metrics (seed 004 §4.2), over the frames after a 1 s warm-up (every method needs a few frames for a
velocity), on the frames where the method has an estimate:

* Eq. 26  RMSE = sqrt(mean ||z_c − z_gt||²)  (m)
* Eq. 27  OE = mean |θ_c − θ_gt|  (deg), θ_c the heading of the method's velocity, θ_gt the group path's.
* Eq. 28  ℓ_k = (z_c − z_gt) × v_k/||v_k|| (signed lateral offset, v_k the true group velocity),
          Lat-STD = sqrt(mean (ℓ_k − μ)²)  (m)

Plus the tracker cost per frame (ms, mean and p99) and the frames without an estimate.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..tracking.group import METHODS, GroupEstimate
from .group_sim import SCENARIOS, Scenario, make_scenario

log = logging.getLogger(__name__)

WARMUP_S = 1.0
PLOT_EVERY_S = 5.0


@dataclass
class MethodResult:
    rmse_m: float
    oe_deg: float
    lat_std_m: float
    ms_mean: float
    ms_p99: float
    frames_without_estimate: int
    centres_m: np.ndarray = field(repr=False)
    headings_rad: np.ndarray = field(repr=False)
    snapshots: list[tuple[int, GroupEstimate]] = field(default_factory=list, repr=False)

    def as_dict(self) -> dict[str, Any]:
        return {"rmse_m": _r(self.rmse_m), "oe_deg": _r(self.oe_deg), "lat_std_m": _r(self.lat_std_m),
                "ms_per_frame_mean": _r(self.ms_mean), "ms_per_frame_p99": _r(self.ms_p99),
                "frames_without_estimate": self.frames_without_estimate}


def _r(v: float) -> float | None:
    return None if not math.isfinite(v) else round(float(v), 4)


def group_metrics(centres_m: np.ndarray, headings_rad: np.ndarray, sc: Scenario, first: int
                  ) -> tuple[float, float, float]:
    """(RMSE m, OE deg, Lat-STD m) per seed 004 Eq. 26-28 over frames ``first``.. with a finite estimate."""
    c, h = centres_m[first:], headings_rad[first:]
    gt, gv = sc.gt_centre_m[first:], sc.gt_velocity_mps[first:]
    ok = np.all(np.isfinite(c), axis=1) & np.isfinite(h)
    if not ok.any():
        return math.nan, math.nan, math.nan
    err = c[ok] - gt[ok]
    rmse = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))                      # Eq. 26
    dth = (h[ok] - sc.gt_heading_rad[first:][ok] + math.pi) % (2 * math.pi) - math.pi
    oe = float(np.degrees(np.mean(np.abs(dth))))                                   # Eq. 27
    unit = gv[ok] / np.linalg.norm(gv[ok], axis=1, keepdims=True)
    lat = err[:, 0] * unit[:, 1] - err[:, 1] * unit[:, 0]                          # Eq. 28, 2-D cross
    return rmse, oe, float(np.std(lat))


def run_method(method: str, sc: Scenario) -> MethodResult:
    tracker = METHODS[method]()
    n = len(sc.frames)
    centres = np.full((n, 2), math.nan)
    heads = np.full(n, math.nan)
    ms = np.zeros(n)
    snaps: list[tuple[int, GroupEstimate]] = []
    every = max(1, int(round(PLOT_EVERY_S / (sc.t_s[1] - sc.t_s[0]))))
    for k, fr in enumerate(sc.frames):
        t0 = time.perf_counter()
        est = tracker.step(fr.t_s, fr.points_m, fr.covs_m2)
        ms[k] = (time.perf_counter() - t0) * 1000
        if est.valid:
            centres[k] = est.centre_m
            heads[k] = est.heading_rad
        if k % every == every // 2:
            snaps.append((k, est))
    first = int(round(WARMUP_S / (sc.t_s[1] - sc.t_s[0])))
    rmse, oe, lat = group_metrics(centres, heads, sc, first)
    missing = int(np.sum(~np.isfinite(centres[first:, 0])))
    return MethodResult(rmse, oe, lat, float(ms.mean()), float(np.percentile(ms, 99)), missing, centres, heads,
                        snaps)


def run_benchmark(scenarios: list[str] | None = None, methods: list[str] | None = None, seed: int = 0,
                  duration_s: float = 30.0) -> dict[str, Any]:
    """Every scenario × method; returns {"scenarios": {name: (Scenario, {method: MethodResult})}}."""
    out: dict[str, Any] = {}
    for name in scenarios or list(SCENARIOS):
        sc = make_scenario(name, seed=seed, duration_s=duration_s)
        out[name] = (sc, {m: run_method(m, sc) for m in (methods or list(METHODS))})
    return out


def _mean(xs: list[float]) -> float:
    xs = [x for x in xs if math.isfinite(x)]
    return float(np.mean(xs)) if xs else math.nan


def summary(results: dict[str, Any]) -> dict[str, Any]:
    """Mean over scenarios per method, and the paper's relative headline (OE reduction of ME-CGT-UGV)."""
    methods = list(next(iter(results.values()))[1])
    per = {m: {k: _mean([getattr(r[m], k) for _, r in results.values()]) for k in ("rmse_m", "oe_deg", "lat_std_m",
                                                                                   "ms_mean")}
           for m in methods}
    head: dict[str, float] = {}
    me = per.get("ME-CGT-UGV")
    if me is not None:
        for ref in ("SOT", "CGT-UGV", "RM-CGT-UGV", "MOT", "CGT-Mean"):
            if ref in per and per[ref]["oe_deg"] > 0:
                head[f"oe_reduction_vs_{ref}_pct"] = 100 * (1 - me["oe_deg"] / per[ref]["oe_deg"])
            if ref in per and per[ref]["lat_std_m"] > 0:
                head[f"lat_std_reduction_vs_{ref}_pct"] = 100 * (1 - me["lat_std_m"] / per[ref]["lat_std_m"])
    return {"mean_over_scenarios": per, "headline": head}


def format_table(results: dict[str, Any]) -> str:
    lines = ["| Scenario | Occl. rate | Method | RMSE m | OE ° | Lat-STD m | ms/frame (mean / p99) |",
             "|---|---:|---|---:|---:|---:|---:|"]
    for name, (sc, res) in results.items():
        for m, r in res.items():
            lines.append(f"| {name} | {100 * sc.occlusion_rate:.0f} % | {m} | {r.rmse_m:.3f} | {r.oe_deg:.2f} | "
                         f"{r.lat_std_m:.3f} | {r.ms_mean:.2f} / {r.ms_p99:.2f} |")
    s = summary(results)
    lines += ["", "| Mean over scenarios | RMSE m | OE ° | Lat-STD m | ms/frame |", "|---|---:|---:|---:|---:|"]
    for m, v in s["mean_over_scenarios"].items():
        lines.append(f"| {m} | {v['rmse_m']:.3f} | {v['oe_deg']:.2f} | {v['lat_std_m']:.3f} | {v['ms_mean']:.2f} |")
    h = s["headline"]
    if "oe_reduction_vs_SOT_pct" in h and "oe_reduction_vs_CGT-UGV_pct" in h:
        lines += ["", f"ME-CGT-UGV orientation error vs SOT: {-h['oe_reduction_vs_SOT_pct']:+.1f} % "
                      f"(seed 004: −86.13 %); vs CGT-UGV (no shape model): {-h['oe_reduction_vs_CGT-UGV_pct']:+.1f} % "
                      f"(seed 004: −54.79 %)."]
    return "\n".join(lines) + "\n"


def to_json(results: dict[str, Any], command: str, seed: int) -> dict[str, Any]:
    return {"command": command, "seed": seed, "warmup_s": WARMUP_S,
            "scenarios": {name: {"description": sc.description, "frames": len(sc.frames),
                                 "occlusion_rate": round(sc.occlusion_rate, 4),
                                 "methods": {m: r.as_dict() for m, r in res.items()}}
                          for name, (sc, res) in results.items()},
            "summary": json.loads(json.dumps(summary(results), default=float))}


def plot_scenario(sc: Scenario, res: dict[str, MethodResult], out_dir: Path) -> Path:
    """Trajectories of every method over the ground truth, ME-CGT-UGV's ellipses (2σ) and selected points at
    a few frames (left); heading error over time (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse as EllipsePatch

    out_dir.mkdir(parents=True, exist_ok=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw={"width_ratios": [1.6, 1]})
    ax.plot(sc.gt_centre_m[:, 0], sc.gt_centre_m[:, 1], "k--", lw=2, label="ground truth centre")
    for m, r in res.items():
        ax.plot(r.centres_m[:, 0], r.centres_m[:, 1], lw=1.2, label=m)
    me = res.get("ME-CGT-UGV")
    if me is not None:
        for k, est in me.snapshots:
            fr = sc.frames[k]
            sel = est.selected if len(est.selected) == len(fr.points_m) else np.zeros(len(fr.points_m), bool)
            ax.scatter(fr.points_m[~sel, 0], fr.points_m[~sel, 1], s=10, c="0.6", zorder=3)
            ax.scatter(fr.points_m[sel, 0], fr.points_m[sel, 1], s=12, c="tab:green", zorder=4)
            for e in est.ellipses:
                w, v = np.linalg.eigh(e.extent_m2)
                ang = math.degrees(math.atan2(v[1, 1], v[0, 1]))
                ax.add_patch(EllipsePatch(tuple(e.centre_m), 4 * math.sqrt(w[1]), 4 * math.sqrt(w[0]), angle=ang,
                                          fill=False, ec="tab:red", lw=1.0, zorder=5))
    ax.plot(sc.robot_m[:, 0], sc.robot_m[:, 1], ":", c="0.4", lw=1, label="robot")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, odometry frame)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{sc.name}: trajectories; ME-CGT-UGV ellipses (2σ), selected (green) / rejected (grey) points")
    ax.legend(fontsize=7, loc="best")
    first = int(round(WARMUP_S / (sc.t_s[1] - sc.t_s[0])))
    for m, r in res.items():
        d = (r.headings_rad - sc.gt_heading_rad + math.pi) % (2 * math.pi) - math.pi
        ax2.plot(sc.t_s[first:], np.degrees(np.abs(d[first:])), lw=1, label=m)
    ax2.set_xlabel("t (s)")
    ax2.set_ylabel("|θ_c − θ_gt| (deg)")
    ax2.set_yscale("symlog", linthresh=5)
    ax2.set_title("orientation error (Eq. 27 per frame)")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    path = out_dir / f"group_{sc.name}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def cmd_eval_group(out: Path, seed: int, command: str, scenarios: list[str] | None = None,
                   plots: bool = True) -> int:
    """Run the benchmark, print the table, write group.md, group.json and plots under ``out``."""
    t0 = time.perf_counter()
    results = run_benchmark(scenarios, seed=seed)
    table = format_table(results)
    out.mkdir(parents=True, exist_ok=True)
    paths = [plot_scenario(sc, res, out / "plots") for sc, res in results.values()] if plots else []
    wall = time.perf_counter() - t0
    (out / "group.json").write_text(json.dumps({**to_json(results, command, seed), "wall_s": round(wall, 1)},
                                               indent=1))
    (out / "group.md").write_text(f"# Group tracking benchmark (seed 004 §4)\n\n```\n{command}\n```\n\n{table}")
    print(table, end="")
    print(f"\nwrote {out / 'group.md'}, {out / 'group.json'}" + (f" and {len(paths)} plots in {out / 'plots'}"
                                                                  if paths else "") + f" ({wall:.1f} s)")
    return 0


def mean_over_runs(json_paths: list[Path]) -> str:
    """The per-scenario table averaged over several ``group.json`` (one per ``--seed``): the figures
    EVALUATION.md reports, since one seed's OE moves by several degrees from run to run."""
    docs = [json.loads(Path(p).read_text()) for p in json_paths]
    seeds = sorted(d["seed"] for d in docs)
    scen = list(docs[0]["scenarios"])
    methods = list(docs[0]["scenarios"][scen[0]]["methods"])
    keys = ("rmse_m", "oe_deg", "lat_std_m", "ms_per_frame_mean")

    def avg(sc: str, m: str, k: str) -> float:
        return _mean([d["scenarios"][sc]["methods"][m][k] if d["scenarios"][sc]["methods"][m][k] is not None
                      else math.nan for d in docs])

    lines = [f"Mean over seeds {', '.join(map(str, seeds))}", "",
             "| Scenario | Occl. rate | Method | RMSE m | OE ° | Lat-STD m | ms/frame |",
             "|---|---:|---|---:|---:|---:|---:|"]
    for sc in scen:
        occ = _mean([d["scenarios"][sc]["occlusion_rate"] for d in docs])
        for m in methods:
            r, o, la, ms = (avg(sc, m, k) for k in keys)
            lines.append(f"| {sc} | {100 * occ:.0f} % | {m} | {r:.3f} | {o:.2f} | {la:.3f} | {ms:.2f} |")
    lines += ["", "| Mean over scenarios and seeds | RMSE m | OE ° | Lat-STD m | ms/frame |",
              "|---|---:|---:|---:|---:|"]
    for m in methods:
        r, o, la, ms = (_mean([avg(sc, m, k) for sc in scen]) for k in keys)
        lines.append(f"| {m} | {r:.3f} | {o:.2f} | {la:.3f} | {ms:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    import sys

    if len(sys.argv) < 2:
        print("usage: python -m followbus.evaluation.group_eval RUN/group.json ...", file=sys.stderr)
        raise SystemExit(2)
    print(mean_over_runs([Path(a) for a in sys.argv[1:]]), end="")
