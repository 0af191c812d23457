"""``followbus eval --group``: seed 004's simulation benchmark, run as the user runs it (a real process)."""

from __future__ import annotations

import json

import numpy as np

from followbus.evaluation.group_eval import group_metrics
from followbus.evaluation.group_sim import SCENARIOS, make_scenario
from followbus.tracking.group import METHODS
from tests.conftest import run_followbus


def test_simulator_is_seeded_and_has_ground_truth() -> None:
    a, b = make_scenario("straight", seed=3, duration_s=5), make_scenario("straight", seed=3, duration_s=5)
    assert len(a.frames) == 50
    np.testing.assert_array_equal(a.frames[20].points_m, b.frames[20].points_m)
    assert 7 <= a.member[:, 0].sum() <= 10
    # Points are incomplete (misses, occlusion) and include non-members (clutter, obstacles).
    n_members = a.member.sum(axis=0)
    seen = np.array([f.is_member.sum() for f in a.frames])
    assert np.all(seen <= n_members) and np.any(seen < n_members)
    assert any((~f.is_member).any() for f in a.frames)


def test_metrics_of_the_ground_truth_are_zero_and_of_an_offset_are_the_offset() -> None:
    sc = make_scenario("turning", seed=0, duration_s=20)
    heads = sc.gt_heading_rad
    assert group_metrics(sc.gt_centre_m, heads, sc, 0) == (0.0, 0.0, 0.0)
    rmse, oe, lat = group_metrics(sc.gt_centre_m + [0.0, 1.0], heads + np.radians(5), sc, 0)
    assert abs(rmse - 1.0) < 1e-9 and abs(oe - 5.0) < 1e-9
    assert lat > 0.01  # the offset is lateral on the straight and longitudinal after the turn: it varies


def test_eval_group_table_and_disturbance_behaviour(tmp_path) -> None:
    out = tmp_path / "group"
    res = run_followbus("eval", "--group", "disturbance", "--out", str(out), timeout=180)
    assert res.returncode == 0, res.stderr
    # The printed table: one row per method for the scenario, then the means and the headline line.
    rows = [line for line in res.stdout.splitlines() if line.startswith("| disturbance |")]
    assert [r.split("|")[3].strip() for r in rows] == list(METHODS)
    assert "orientation error vs SOT" in res.stdout
    data = json.loads((out / "group.json").read_text())
    m = data["scenarios"]["disturbance"]["methods"]
    assert set(m) == set(METHODS)
    for v in m.values():
        assert {"rmse_m", "oe_deg", "lat_std_m", "ms_per_frame_mean"} <= set(v)
        assert v["frames_without_estimate"] == 0
    # With non-members walking through, the group tracker heads where the group goes better than
    # following one member does.
    assert m["ME-CGT-UGV"]["oe_deg"] < m["SOT"]["oe_deg"]
    assert m["ME-CGT-UGV"]["rmse_m"] < m["SOT"]["rmse_m"]
    assert (out / "plots" / "group_disturbance.png").stat().st_size > 10_000
    assert (out / "group.md").read_text().count("| disturbance |") == len(METHODS)


def test_eval_group_mistakes_are_one_line(tmp_path) -> None:
    res = run_followbus("eval", "--group", "nowhere", "--out", str(tmp_path))
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0
    assert "unknown group scenario 'nowhere'" in res.stderr and SCENARIOS[0] in res.stderr
    res = run_followbus("eval", "--out", str(tmp_path))
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0 and "--group" in res.stderr


def test_mean_over_runs_averages_every_scenario_and_method(tmp_path) -> None:
    from followbus.evaluation.group_eval import mean_over_runs

    def run(seed: int, oe: float) -> str:
        m = {"rmse_m": 0.5, "oe_deg": oe, "lat_std_m": 0.2, "ms_per_frame_mean": 1.0}
        doc = {"seed": seed, "scenarios": {"straight": {"occlusion_rate": 0.2, "methods": {"ME-CGT-UGV": m}}}}
        path = tmp_path / f"s{seed}.json"
        path.write_text(json.dumps(doc))
        return str(path)

    text = mean_over_runs([run(1, 4.0), run(0, 6.0)])
    assert text.startswith("Mean over seeds 0, 1")
    assert "| straight | 20 % | ME-CGT-UGV | 0.500 | 5.00 | 0.200 | 1.00 |" in text
    assert "| ME-CGT-UGV | 0.500 | 5.00 | 0.200 | 1.00 |" in text
