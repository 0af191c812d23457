"""MOT metrics: agreement with motmetrics / TrackEval on TUD-Campus, plus small hand-made cases."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from followbus.evaluation.datasets import find_data_root
from followbus.evaluation.mot_metrics import (
    HOTA_ALPHAS,
    align_frames,
    clear_mot,
    evaluate_mot,
    hota,
    identity_scores,
    iou_matrix,
    load_mot_file,
)

mm = pytest.importorskip("motmetrics", reason="motmetrics (dev extra) provides the reference implementation")

TUD = Path(os.path.dirname(mm.__file__)) / "data" / "TUD-Campus"
TRACKEVAL_TUD_HOTA = 39.14  # % — TrackEval on the same gt/test pair (data README)


@pytest.fixture
def motmetrics_ref(monkeypatch: pytest.MonkeyPatch):
    """motmetrics 1.4 still calls np.asfarray, removed in numpy 2; shim it for the reference run only."""
    if not hasattr(np, "asfarray"):
        monkeypatch.setattr(np, "asfarray", lambda a, dtype=float: np.asarray(a, dtype=dtype), raising=False)

    def run(gt_frames, pred_frames):
        acc = mm.MOTAccumulator(auto_id=True)
        for (gid, gbox), (pid, pbox) in zip(gt_frames, pred_frames, strict=True):
            acc.update(list(gid), list(pid), mm.distances.iou_matrix(gbox, pbox, max_iou=0.5))
        names = ["mota", "motp", "idf1", "idp", "idr", "num_switches", "num_false_positives",
                 "num_misses", "num_matches", "idtp"]
        return mm.metrics.create().compute(acc, metrics=names, name="x").iloc[0].to_dict()

    return run


def _tud():
    if not (TUD / "gt.txt").is_file():
        pytest.skip(f"motmetrics wheel has no TUD-Campus data at {TUD}")
    return align_frames(load_mot_file(TUD / "gt.txt", is_gt=True), load_mot_file(TUD / "test.txt"))


def test_tud_campus_matches_motmetrics_and_trackeval(motmetrics_ref) -> None:
    gt, pred = _tud()
    ours = evaluate_mot(gt, pred)
    print("TUD-Campus:", {k: round(float(v), 5) for k, v in ours.as_dict().items()})
    assert round(ours.mota, 4) == 0.5265
    assert round(ours.idf1, 4) == 0.5577
    assert abs(100 * ours.hota.hota - TRACKEVAL_TUD_HOTA) <= 0.01

    # motmetrics' own pipeline (its loader + compare_to_groundtruth), not our frame alignment
    gt_df = mm.io.loadtxt(str(TUD / "gt.txt"), fmt="mot15-2D", min_confidence=1)
    ts_df = mm.io.loadtxt(str(TUD / "test.txt"), fmt="mot15-2D")
    acc = mm.utils.compare_to_groundtruth(gt_df, ts_df, "iou", distth=0.5)
    ref = mm.metrics.create().compute(
        acc, metrics=["mota", "motp", "idf1", "idp", "idr", "num_switches", "num_false_positives",
                      "num_misses", "num_matches", "idtp"], name="tud").iloc[0]
    c, i = ours.clear, ours.identity
    assert c.mota == pytest.approx(ref["mota"], abs=1e-12)
    assert c.motp == pytest.approx(ref["motp"], abs=1e-9)
    assert i.idf1 == pytest.approx(ref["idf1"], abs=1e-12)
    assert i.idp == pytest.approx(ref["idp"]) and i.idr == pytest.approx(ref["idr"])
    assert (c.num_switches, c.num_false_positives, c.num_misses) == (
        ref["num_switches"], ref["num_false_positives"], ref["num_misses"])
    assert c.num_tp - c.num_switches == ref["num_matches"]
    assert i.idtp == ref["idtp"]


def test_tud_hota_components_are_consistent() -> None:
    gt, pred = _tud()
    h = hota(gt, pred)
    assert len(h.hota_alpha) == len(HOTA_ALPHAS) == 19
    np.testing.assert_allclose(h.hota_alpha, np.sqrt(h.deta_alpha * h.assa_alpha))
    assert h.hota == pytest.approx(h.hota_alpha.mean())
    assert 0 < h.deta < 1 and 0 < h.assa < 1 and 0.5 < h.loca < 1


def test_shared_tud_gt_file_needs_conf_minus_one_kept() -> None:
    """The data-tree copy of the TUD gt marks every row conf=-1: motmetrics' gt setting (min_confidence=1)
    would drop all of it; our gt rule (drop conf==0 only) keeps it and reproduces the same scores."""
    try:
        root = find_data_root()
    except FileNotFoundError as exc:
        pytest.skip(f"FOLLOWBUS_DATA is set but unusable: {exc}")
    shared_gt = None if root is None else root / "mot" / "tud-campus" / "gt" / "gt.txt"
    if shared_gt is None or not shared_gt.is_file():
        pytest.skip("evaluation data (mot/tud-campus) not present")
    gt_shared = load_mot_file(shared_gt, is_gt=True)
    assert sum(len(ids) for ids, _ in gt_shared.values()) == 359
    assert load_mot_file(shared_gt, min_confidence=1) == {}
    gt, pred = align_frames(gt_shared, load_mot_file(TUD / "test.txt"))
    m = evaluate_mot(gt, pred)
    assert round(m.mota, 4) == 0.5265 and round(m.idf1, 4) == 0.5577


def test_random_sequences_agree_with_motmetrics(motmetrics_ref) -> None:
    """Jittered tracks with dropouts, false alarms and id swaps: CLEAR and ID counts must equal motmetrics'."""
    rng = np.random.default_rng(7)
    for _ in range(8):
        n_frames, n_obj = 40, 6
        pos = rng.uniform(0, 400, size=(n_obj, 2))
        vel = rng.normal(0, 3, size=(n_obj, 2))
        perm = np.arange(n_obj) + 100
        gt, pred = [], []
        for t in range(n_frames):
            pos += vel
            vis = rng.random(n_obj) > 0.15
            boxes = np.column_stack([pos, np.full((n_obj, 2), 40.0)])
            gt.append((np.arange(n_obj)[vis], boxes[vis]))
            if rng.random() < 0.1:  # two tracker ids swap targets
                a, b = rng.choice(n_obj, 2, replace=False)
                perm[[a, b]] = perm[[b, a]]
            det = (rng.random(n_obj) > 0.2) & vis
            jitter = rng.normal(0, 6, size=(n_obj, 4))
            p_ids = list(perm[det])
            p_boxes = list((boxes + jitter)[det])
            if rng.random() < 0.3:
                p_ids.append(900 + t)
                p_boxes.append(np.r_[rng.uniform(0, 400, 2), 40.0, 40.0])
            pred.append((np.array(p_ids, dtype=int), np.array(p_boxes).reshape(-1, 4)))
        ref = motmetrics_ref(gt, pred)
        c, i = clear_mot(gt, pred), identity_scores(gt, pred)
        assert c.num_switches == ref["num_switches"]
        assert (c.num_false_positives, c.num_misses) == (ref["num_false_positives"], ref["num_misses"])
        assert c.mota == pytest.approx(ref["mota"], abs=1e-12)
        assert c.motp == pytest.approx(ref["motp"], abs=1e-9)
        assert i.idf1 == pytest.approx(ref["idf1"], abs=1e-12)


def _frames(*per_frame):
    return [(np.array(ids, dtype=int), np.array(boxes, dtype=float).reshape(-1, 4)) for ids, boxes in per_frame]


BOX_A = [0.0, 0.0, 50.0, 100.0]
BOX_B = [200.0, 0.0, 50.0, 100.0]


def test_perfect_tracking_scores_one() -> None:
    gt = _frames(*[([1, 2], [BOX_A, BOX_B])] * 5)
    pred = _frames(*[([7, 9], [BOX_A, BOX_B])] * 5)
    m = evaluate_mot(gt, pred)
    assert m.mota == 1.0 and m.idf1 == 1.0 and m.hota.hota == pytest.approx(1.0)
    assert m.hota.loca == pytest.approx(1.0) and m.clear.num_switches == 0 and m.clear.motp == 0.0


def test_one_id_switch() -> None:
    gt = _frames(*[([1], [BOX_A])] * 4)
    pred = _frames(([10], [BOX_A]), ([10], [BOX_A]), ([11], [BOX_A]), ([11], [BOX_A]))
    m = evaluate_mot(gt, pred)
    assert m.clear.num_switches == 1
    assert m.mota == pytest.approx(1 - 1 / 4)
    assert m.idf1 == pytest.approx(0.5)  # best single id pairing covers 2 of 4 frames
    assert m.hota.deta == pytest.approx(1.0)
    assert m.hota.assa == pytest.approx(0.5)  # each pair: 2 / (4 + 2 - 2)
    assert m.hota.hota == pytest.approx(np.sqrt(0.5))


def test_previous_correspondence_is_kept_while_still_valid() -> None:
    # Frame 1: tracker 20 is a better fit for gt 1 than tracker 10, but 10 still overlaps >= 0.5 → no switch.
    gt = _frames(([1], [BOX_A]), ([1], [BOX_A]))
    near = [5.0, 0.0, 50.0, 100.0]  # IoU 0.818 with BOX_A
    pred = _frames(([10], [near]), ([10, 20], [near, BOX_A]))
    c = clear_mot(gt, pred)
    assert c.num_switches == 0 and c.num_false_positives == 1


def test_switch_is_remembered_across_a_gap() -> None:
    # motmetrics semantics: gt 1 was last matched to 10; matching it to 11 after frames unmatched is a switch.
    gt = _frames(([1], [BOX_A]), ([1], [BOX_A]), ([1], [BOX_A]))
    pred = _frames(([10], [BOX_A]), ([], []), ([11], [BOX_A]))
    assert clear_mot(gt, pred).num_switches == 1


def test_hota_averages_over_alpha() -> None:
    # identical ids, every box IoU 0.72: matched for α = 0.05..0.70 (14 of 19 thresholds) only
    shifted = [0.0, 0.0, 50.0, 72.0]  # IoU with BOX_A = 72*50 / (100*50)
    assert iou_matrix(np.array([BOX_A]), np.array([shifted]))[0, 0] == pytest.approx(0.72)
    gt = _frames(*[([1], [BOX_A])] * 3)
    pred = _frames(*[([5], [shifted])] * 3)
    h = hota(gt, pred)
    assert h.hota == pytest.approx(14 / 19)
    assert h.loca_alpha[0] == pytest.approx(0.72)


def test_empty_tracker() -> None:
    gt = _frames(*[([1], [BOX_A])] * 3)
    pred = _frames(*[([], [])] * 3)
    m = evaluate_mot(gt, pred)
    assert m.mota == 0.0 and m.idf1 == 0.0 and m.hota.hota == 0.0 and m.clear.num_misses == 3


def test_load_mot_file_confidence_and_class_rules(tmp_path: Path) -> None:
    p = tmp_path / "gt.txt"
    p.write_text("1,1,10,10,5,5,1,1,1\n1,2,20,20,5,5,0,3,1\n1,3,30,30,5,5,-1,-1,-1\n"
                 "2,1,11,10,5,5,1,7,1\n3 1 12 10 5 5 1 1 1\n")
    def count(d):
        return sum(len(ids) for ids, _ in d.values())
    assert count(load_mot_file(p)) == 5  # tracker-style: keep all
    gt = load_mot_file(p, is_gt=True)
    assert count(gt) == 4 and 2 not in gt[1][0]  # conf 0 = ignore
    assert count(load_mot_file(p, min_confidence=1)) == 3  # motmetrics' gt setting also drops conf -1
    assert count(load_mot_file(p, is_gt=True, classes={1})) == 3  # class 7 dropped, class -1 kept
    np.testing.assert_allclose(gt[3][1], [[12, 10, 5, 5]])  # whitespace-separated rows parse too
    bad = tmp_path / "bad.txt"
    bad.write_text("1,1,10,10,5,5,1\n1,1,12,10,5,5,1\n")
    with pytest.raises(ValueError, match="twice"):
        load_mot_file(bad)


def test_align_frames_fills_gaps() -> None:
    gt = {1: (np.array([1]), np.array([BOX_A])), 4: (np.array([1]), np.array([BOX_A]))}
    pred = {2: (np.array([3]), np.array([BOX_B]))}
    g, p = align_frames(gt, pred)
    assert len(g) == len(p) == 4 and len(g[1][0]) == 0 and len(p[0][0]) == 0
    with pytest.raises(ValueError):
        clear_mot(g, p[:2])


def test_combined_sequences_sum_counts_like_trackeval() -> None:
    from followbus.evaluation.mot_metrics import evaluate_mot_combined

    a_gt = [([1, 2], [[0, 0, 10, 20], [50, 0, 10, 20]]), ([1, 2], [[1, 0, 10, 20], [51, 0, 10, 20]])]
    a_pr = [([7, 8], [[0, 0, 10, 20], [50, 0, 10, 20]]), ([8], [[1, 0, 10, 20]])]  # a switch and a miss
    b_gt = [([1], [[0, 0, 10, 20]]), ([1], [[0, 0, 10, 20]]), ([1], [[0, 0, 10, 20]])]
    b_pr = [([7], [[0, 0, 10, 20]]), ([7], [[200, 0, 10, 20]]), ([], [])]  # same ids as in a, other people
    one = evaluate_mot_combined([(a_gt, a_pr)])
    assert one.as_dict() == evaluate_mot(a_gt, a_pr).as_dict()
    both = evaluate_mot_combined([(a_gt, a_pr), (b_gt, b_pr)])
    ea, eb = evaluate_mot(a_gt, a_pr), evaluate_mot(b_gt, b_pr)
    for key in ("gt_dets", "pred_dets", "tp", "fp", "fn", "idsw", "idtp", "idfp", "idfn"):
        assert both.as_dict()[key] == ea.as_dict()[key] + eb.as_dict()[key], key
    # ids 1 and 7 exist in both sequences: were they shared, sequence b would add an id switch or IDTP
    assert both.clear.num_switches == 1 and both.identity.idtp == ea.identity.idtp + eb.identity.idtp
    # HOTA: DetA from summed counts, AssA weighted by true positives (per α). TP_α follows from
    # DetA_α = TP / (TP + FN + FP) = TP / (#gt + #pred - TP).
    def tp(m):
        n = m.clear.num_objects + m.clear.num_predictions
        return m.hota.deta_alpha * n / (1 + m.hota.deta_alpha)

    tpa, tpb = tp(ea), tp(eb)
    n_all = both.clear.num_objects + both.clear.num_predictions
    np.testing.assert_allclose(both.hota.deta_alpha, (tpa + tpb) / (n_all - tpa - tpb), atol=1e-9)
    np.testing.assert_allclose(both.hota.assa_alpha,
                               (ea.hota.assa_alpha * tpa + eb.hota.assa_alpha * tpb) / (tpa + tpb), atol=1e-9)


def test_distractor_matches_are_removed_before_scoring() -> None:
    from followbus.evaluation.mot_metrics import remove_distractor_matches

    # gt rows of one frame: a pedestrian, a static person (distractor class 7), a car (ignored, not a distractor)
    region = (np.array([[0, 0, 10, 20], [50, 0, 10, 20], [100, 0, 40, 20]], float), np.array([False, True, False]))
    pred = ([1, 2, 3, 4], [[0, 0, 10, 20], [51, 0, 10, 20], [100, 0, 40, 20], [200, 0, 10, 20]])
    (ids, boxes), = remove_distractor_matches([pred], [region])
    assert ids.tolist() == [1, 3, 4]  # only the box on the static person goes; the car box stays a FP
    gt = [([7], [[0, 0, 10, 20]])]
    m = evaluate_mot(gt, [(ids, boxes)])
    assert (m.clear.num_tp, m.clear.num_false_positives) == (1, 2)
    # one tracker box on both a pedestrian and an overlapping distractor: the one-to-one match decides
    region = (np.array([[0, 0, 10, 20], [1, 0, 10, 20]], float), np.array([False, True]))
    (ids2, _), = remove_distractor_matches([([5], [[0, 0, 10, 20]])], [region])
    assert ids2.tolist() == [5]  # best IoU is with the pedestrian (1.0 vs 0.82)
