"""followbus eval: metric plumbing on synthetic scenes, the Kalman baseline, ablations, the CLI on a real
sequence, and in-process vs launched-graph agreement."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from followbus.evaluation.runner import method_factories, open_sequence, run_sequence

from .conftest import SHARED, processes_matching, run_followbus, wait_until


def _run(scene: str, methods: list[str], ablations: bool = False, keep: set[str] | None = None, **kw):
    factories = method_factories(methods, ablations=ablations)
    if keep is not None:
        factories = {k: v for k, v in factories.items() if k in keep}
    return run_sequence(open_sequence(f"scene:{scene}", **kw), factories, "simulated")


def test_followbus_relocks_after_wall_occlusion_and_kalman_differs():
    run = _run("wall-occlusion", ["followbus", "kalman"])
    fb = run.runs["followbus"].metrics
    assert fb.frames == run.sequence.n_frames == len(run.runs["followbus"].boxes)
    assert fb.tsr > 0.8, fb.as_dict()
    assert fb.reid_events, "the wall hides the target completely: there must be an occlusion event"
    assert all(e.latency_frames is not None for e in fb.reid_events), fb.reid_events
    assert math.isfinite(run.runs["followbus"].tracker_ms_mean) and run.detector_ms.size == fb.frames
    # the occlusion span is shaded in the plots
    spans = run.occlusion_spans()
    assert any(b - a + 1 >= fb.reid_events[0].occluded_frames for a, b in spans)
    kal = run.runs["kalman"]
    assert kal.metrics.frames == fb.frames
    differ = [k for k, (a, b) in enumerate(zip(run.runs["followbus"].boxes, kal.boxes, strict=True))
              if (a is None) != (b is None) or (a is not None and not np.allclose(a, b))]
    assert len(differ) > 10 and kal.metrics.cle != fb.cle


def test_ablations_change_measurable_behaviour():
    # Adaptive η (Eq. 10) is what the puddles are for: without it η stays at η_base on specular frames.
    run = _run("night-puddles", ["followbus"], ablations=True, keep={"followbus", "followbus w/o adaptive η"})
    eta = np.nanmean(run.runs["followbus"].series("eta"))
    eta_abl = np.nanmean(run.runs["followbus w/o adaptive η"].series("eta"))
    assert eta < 0.75 * eta_abl, (eta, eta_abl)
    # Update suspension: on the wall occlusion, updating on rejected candidates drags the box (higher CLE).
    run = _run("wall-occlusion", ["followbus"], ablations=True,
               keep={"followbus", "followbus w/o update suspension"})
    assert run.runs["followbus w/o update suspension"].metrics.cle > run.runs["followbus"].metrics.cle + 1.0


def test_one_ablation_runs_on_its_own_by_name():
    factories = method_factories(["followbus w/o partial-view completion"])
    assert list(factories) == ["followbus w/o partial-view completion"]
    with pytest.raises(ValueError, match="followbus w/o gate"):  # the error lists the names
        method_factories(["followbus w/o everything"])


SOT_SEQ = SHARED / "data" / "sot" / "otb-crossing"


@pytest.mark.slow
@pytest.mark.skipif(not SOT_SEQ.is_dir(), reason=f"evaluation data absent ({SOT_SEQ})")
def test_eval_cli_on_a_real_sequence(tmp_path):
    out = tmp_path / "res"
    result = run_followbus("eval", str(SOT_SEQ), "--detector", "yolox", "--out", str(out), timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    md = (out / "results.md").read_text()
    assert "followbus eval" in md and str(SOT_SEQ) in md and "| kalman |" in md and "overall" in md
    data = json.loads((out / "results.json").read_text())
    seq = data["sequences"]["sot/otb-crossing"]
    assert seq["frames"] == 120 and set(seq["methods"]) == {"followbus", "kalman"}
    assert 0.0 <= seq["methods"]["followbus"]["tsr"] <= 1.0 and seq["detector_ms"] > 0
    assert (out / "plots" / "sot_otb-crossing_error.png").stat().st_size > 1000
    assert (out / "plots" / "sot_otb-crossing_eta.png").stat().st_size > 1000
    assert list((out / "cache").glob("*.npz")), "detections were not cached"
    # a second run reuses the cache and gives the same numbers
    again = run_followbus("eval", str(SOT_SEQ), "--detector", "yolox", "--out", str(out), timeout=120)
    assert again.returncode == 0, again.stderr
    data2 = json.loads((out / "results.json").read_text())
    assert data2["sequences"]["sot/otb-crossing"]["detections_cached"] is True
    assert data2["sequences"]["sot/otb-crossing"]["methods"]["followbus"]["tsr"] == seq["methods"]["followbus"]["tsr"]
    assert "detector ceiling" in md and 0.5 < seq["detector_ceiling"]["tsr"] <= 1.0


@pytest.mark.slow
def test_launched_graph_matches_in_process_tracker(port):
    from followbus.tools.bench.eval import graph_check

    res = graph_check("scene:wall-occlusion", max_frames=120, port=port, timeout_s=90)
    assert res["compared"] == 120 and res["missing"] == 0, {k: res[k] for k in ("compared", "missing")}
    assert res["mismatches"] == 0, (res["first_mismatch"], res["graph"][res["first_mismatch"]],
                                    res["inproc"][res["first_mismatch"]])
    assert sum(b is not None for b in res["graph"]) > 100  # not trivially equal (all None)
    assert wait_until(lambda: not processes_matching("followbus-graphcheck-"), 10)


@pytest.mark.slow
@pytest.mark.skipif(not SOT_SEQ.is_dir(), reason=f"evaluation data absent ({SOT_SEQ})")
def test_launched_graph_matches_in_process_on_a_real_sequence_with_real_inference(port):
    """The detection node runs YOLOX on the frames it receives over the bus; in-process runs it on the
    frames read from disk: the tracks must still agree bit for bit."""
    from followbus.tools.bench.eval import graph_check

    res = graph_check(str(SOT_SEQ), detector="yolox", max_frames=60, port=port, timeout_s=90)
    assert res["detector"] == "yolox" and res["compared"] == 60 and res["missing"] == 0, res["missing"]
    assert res["mismatches"] == 0, (res["first_mismatch"], res["graph"][res["first_mismatch"]],
                                    res["inproc"][res["first_mismatch"]])
    assert sum(b is not None for b in res["graph"]) == 60


def test_unknown_methods_are_a_usage_error(tmp_path):
    for method in ("peer:foo", "nonsense"):
        res = run_followbus("eval", "scene:wall-occlusion", "--method", method, "--detector", "simulated",
                            "--out", str(tmp_path), timeout=60)
        assert res.returncode == 2 and "unknown" in res.stderr and "Traceback" not in res.stderr, res.stderr


def test_graph_check_refuses_what_it_cannot_reproduce(tmp_path):
    res = run_followbus("eval", "all", "--graph-check", "--out", str(tmp_path), timeout=60)
    assert res.returncode == 2 and "not 'all'" in res.stderr, res.stderr
    if SOT_SEQ.is_dir():
        res = run_followbus("eval", str(SOT_SEQ), "--graph-check", "--detector", "simulated",
                            "--out", str(tmp_path), timeout=60)
        assert res.returncode == 2 and "scenes only" in res.stderr, res.stderr


def test_read_ahead_gives_every_item_in_order_and_raises_a_read_error_in_its_place():
    from followbus.evaluation.runner import read_ahead

    assert list(read_ahead(lambda i: i * i, 20, depth=3)) == [i * i for i in range(20)]

    def read(i: int) -> int:
        if i == 3:
            raise OSError("cannot read frame 3")
        return i

    got = []
    with pytest.raises(OSError, match="frame 3"):
        for item in read_ahead(read, 10, depth=2):
            got.append(item)
    assert got == [0, 1, 2]


def test_read_ahead_stops_reading_when_the_loop_is_left():
    import threading

    from followbus.evaluation.runner import read_ahead

    reads = []
    items = read_ahead(lambda i: reads.append(i) or i, 1000, depth=2)
    assert [next(items), next(items)] == [0, 1]
    items.close()  # the consumer breaks out of its loop
    assert len(reads) <= 2 + 2 + 1  # what it took, the queue, the one in hand
    assert not any(t.name == "read-ahead" for t in threading.enumerate())


def test_a_follower_is_prepared_untimed_once_it_knows_whom_to_follow():
    """A follower with prepare() (the graph, which builds its nodes once it is told whom to follow) is set up
    before the step that carries the initial box, outside the time that step is charged with."""
    calls = []

    class Spy:
        def prepare(self, init_box):
            calls.append(("prepare", init_box))
            import time

            time.sleep(0.2)  # a set-up that takes long: must not show in the per-frame time

        def step(self, frame_bgr, detections, t_ns, v_ego_mps, init_box, **low):
            calls.append(("step", init_box))
            return None, {}

    res = run_sequence(open_sequence("scene:wall-occlusion", max_frames=5), {"spy": lambda fps: Spy()}, "simulated")
    first_step = next(i for i, (what, _) in enumerate(calls) if what == "step")
    assert calls[first_step - 1][0] == "prepare" and calls[first_step - 1][1] == calls[first_step][1] is not None
    assert max(res.runs["spy"].tracker_ms) < 100


def test_jitter_moves_every_detection_by_seeded_noise() -> None:
    """--jitter-px: N(0, px) on x, y, w, h, N(0, px/200) on the score, sizes >= 1 px, scores in [0, 1];
    the same seed gives the same noise, 0 gives the rows themselves."""
    from followbus.evaluation.runner import jitter_detections

    rows = np.array([[10.0, 20.0, 30.0, 60.0, 0.9], [5.0, 5.0, 0.5, 0.5, 0.999]] * 500, np.float32)
    assert jitter_detections(rows, 0.0, np.random.default_rng(0)) is rows
    a = jitter_detections(rows, 2.0, np.random.default_rng(7))
    np.testing.assert_array_equal(a, jitter_detections(rows, 2.0, np.random.default_rng(7)))
    assert not np.array_equal(a, jitter_detections(rows, 2.0, np.random.default_rng(8)))
    moved = (a - rows)[0::2]  # the large boxes: nothing clipped
    assert moved[:, :4].std() == pytest.approx(2.0, rel=0.1) and abs(moved[:, :4].mean()) < 0.2
    assert moved[:, 4].std() == pytest.approx(0.01, rel=0.1)
    assert a[:, 2:4].min() >= 1.0 and a[:, 4].min() >= 0.0 and a[:, 4].max() <= 1.0
    assert a.dtype == np.float32 and a.shape == rows.shape
