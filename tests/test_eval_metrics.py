"""Single-target follower metrics on hand-made tracks with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from followbus.evaluation.metrics import (
    aggregate,
    box_iou,
    evaluate_single_target,
    format_markdown_table,
)


def walk(n: int, x0: float = 100.0, y0: float = 50.0, vx: float = 2.0) -> list[tuple[float, float, float, float]]:
    """A person box moving right 2 px/frame."""
    return [(x0 + vx * t, y0, 40.0, 100.0) for t in range(n)]


def shift(boxes, dx: float, dy: float = 0.0):
    return [None if b is None else (b[0] + dx, b[1] + dy, b[2], b[3]) for b in boxes]


def test_perfect_tracker() -> None:
    gt = walk(50)
    m = evaluate_single_target(gt, gt)
    assert m.tsr == 1.0 and m.cle == 0.0 and m.stability == 0.0
    assert m.precision == m.recall == m.f1 == 1.0
    assert m.missing_outputs == 0 and m.target_switches == 0 and m.reid_events == []
    assert m.mean_iou == 1.0 and m.iou_success == 1.0
    assert m.center_errors.shape == (50,) and np.all(m.center_errors == 0)


def test_constant_10px_offset() -> None:
    gt = walk(40)
    m = evaluate_single_target(shift(gt, 6.0, 8.0), gt)  # 6-8-10 triangle
    assert m.cle == pytest.approx(10.0)
    assert m.tsr == 1.0
    assert m.stability == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(m.center_errors, 10.0)


def test_25px_offset_fails_everywhere() -> None:
    gt = walk(30)
    m = evaluate_single_target(shift(gt, 25.0), gt)
    assert m.tsr == 0.0 and m.precision == 0.0 and m.recall == 0.0 and m.f1 == 0.0
    assert m.cle == pytest.approx(25.0)
    assert math.isnan(m.stability)  # no successful frame to take a std over


def test_threshold_is_strict_and_configurable() -> None:
    gt = walk(10)
    assert evaluate_single_target(shift(gt, 20.0), gt).tsr == 0.0  # e_t < τ, not <=
    assert evaluate_single_target(shift(gt, 20.0), gt, tsr_px=20.5).tsr == 1.0


def test_missing_outputs_lower_tsr_and_recall_not_precision() -> None:
    gt = walk(100)
    pred = list(gt)
    for t in range(30, 50):
        pred[t] = None
    m = evaluate_single_target(pred, gt, image_size=(640, 480))
    assert m.tsr == pytest.approx(0.8) and m.recall == pytest.approx(0.8)
    assert m.precision == 1.0
    assert m.missing_outputs == 20 and m.cle_frames == 80
    assert m.cle == 0.0  # over frames with both
    assert m.cle_all == pytest.approx(20 * 800.0 / 100)  # a miss is charged the 640x480 diagonal
    assert m.f1 == pytest.approx(2 * 1.0 * 0.8 / 1.8)
    assert np.isnan(m.center_errors[30:50]).all()
    # without an image size a missing frame makes cle_all undefined instead of silently optimistic
    assert math.isnan(evaluate_single_target(pred, gt).cle_all)


def test_output_while_target_absent_is_false_positive() -> None:
    gt: list = walk(10) + [None] * 10
    pred = walk(20)
    m = evaluate_single_target(pred, gt, min_occlusion_frames=100)
    assert m.frames == 20 and m.frames_with_gt == 10 and m.outputs == 20
    assert m.precision == pytest.approx(0.5) and m.recall == 1.0 and m.tsr == 1.0
    assert m.false_positives == 10


def test_stability_is_population_std_over_successes_only() -> None:
    gt = walk(6)
    offsets = [5.0, 15.0, 5.0, 15.0, 80.0, 5.0]  # 80 px is a failure and must not enter the std
    pred = [shift([b], dx)[0] for b, dx in zip(gt, offsets, strict=True)]
    m = evaluate_single_target(pred, gt)
    succ = np.array([5.0, 15.0, 5.0, 15.0, 5.0])
    assert m.stability == pytest.approx(succ.std(ddof=0))
    assert m.tsr == pytest.approx(5 / 6)
    assert m.cle == pytest.approx(np.mean(offsets))


def test_jump_to_distractor_counts_one_switch() -> None:
    n = 30
    gt = walk(n)
    other = shift(gt, 80.0)  # a second walker 80 px to the right
    pred = list(gt)
    for t in range(10, 20):
        pred[t] = other[t]
    m = evaluate_single_target(pred, gt, other_gt=[[b] for b in other])
    assert m.target_switches == 1
    assert m.frames_on_distractor == 10
    assert m.tsr == pytest.approx(20 / 30)
    # without distractor boxes the switch cannot be attributed
    assert evaluate_single_target(pred, gt).target_switches == 0


def test_switch_counts_transitions_even_across_lost_frames() -> None:
    n = 40
    gt = walk(n)
    other = shift(gt, 80.0)
    pred: list = list(gt)
    pred[5:8] = [None] * 3  # lost, then reacquired on the distractor: still target → distractor
    for t in range(8, 12):
        pred[t] = other[t]
    for t in range(20, 25):  # back on target in between, then a second jump
        pred[t] = other[t]
    m = evaluate_single_target(pred, gt, other_gt=[[b] for b in other])
    assert m.target_switches == 2
    assert m.frames_on_distractor == 9


def test_overlapping_neighbour_does_not_steal_a_correct_output() -> None:
    gt = walk(10)
    other = shift(gt, 15.0)  # heavily overlapping neighbour; output on the target itself
    m = evaluate_single_target(gt, gt, other_gt=[[b] for b in other])
    assert m.target_switches == 0 and m.frames_on_distractor == 0


def occlusion_case(relock_after: int | None, fps: float = 30.0):
    gt: list = walk(40)
    gt[10:20] = [None] * 10  # 10-frame occlusion, reappears at frame 20
    pred: list = list(gt)
    stop = 40 if relock_after is None else 20 + relock_after
    pred[20:stop] = [None] * (stop - 20)
    return evaluate_single_target(pred, gt, fps=fps)


def test_reid_latency_three_frames_is_100ms() -> None:
    m = occlusion_case(3)
    assert len(m.reid_events) == 1
    ev = m.reid_events[0]
    assert (ev.occlusion_start, ev.reappear_frame, ev.occluded_frames) == (10, 20, 10)
    assert ev.latency_frames == 3
    assert ev.latency_ms == pytest.approx(100.0)
    assert m.reid_latency_ms_mean == pytest.approx(100.0) and m.reid_censored == 0
    assert occlusion_case(3, fps=10.0).reid_events[0].latency_ms == pytest.approx(300.0)
    assert occlusion_case(0).reid_events[0].latency_frames == 0


def test_reid_never_relocked_is_censored() -> None:
    m = occlusion_case(None)
    assert m.reid_censored == 1 and m.reid_latencies_frames == []
    assert math.isnan(m.reid_latency_ms_mean)
    assert m.reid_events[0].observed_frames == 20


def test_short_gaps_and_leading_absence_are_not_occlusions() -> None:
    gt: list = walk(30)
    gt[0:8] = [None] * 8  # not yet in view: nothing to re-identify
    gt[15:18] = [None] * 3  # shorter than min_occlusion_frames
    m = evaluate_single_target(list(gt), gt, min_occlusion_frames=5)
    assert m.reid_events == []
    assert len(evaluate_single_target(list(gt), gt, min_occlusion_frames=3).reid_events) == 1


def test_aggregate_is_frame_weighted() -> None:
    a_gt = walk(10)
    b_gt = walk(30)
    a = evaluate_single_target(a_gt, a_gt)
    b = evaluate_single_target(shift(b_gt, 30.0), b_gt)
    overall = aggregate([a, b])
    assert overall.frames == 40
    assert overall.tsr == pytest.approx(10 / 40)  # not the sequence mean 0.5
    assert overall.cle == pytest.approx((10 * 0 + 30 * 30) / 40)
    assert overall.stability == 0.0
    with pytest.raises(ValueError):
        aggregate([])


def test_markdown_table_lists_methods_sequences_and_overall() -> None:
    gt = walk(20)
    rows = {
        "oracle": {"seqA": evaluate_single_target(gt, gt), "seqB": evaluate_single_target(gt, gt)},
        "drifty": {"seqA": evaluate_single_target(shift(gt, 25.0), gt)},
    }
    md = format_markdown_table(rows)
    assert "### seqA" in md and "### seqB" in md and "### overall" in md
    lines = [ln for ln in md.splitlines() if ln.startswith("| oracle")]
    assert len(lines) == 3 and "100.0" in lines[0]
    drifty_b = [ln for ln in md.splitlines() if ln.startswith("| drifty")][1]
    assert set(drifty_b.strip("| ").split(" | ")[1:]) == {"–"}  # missing sequence shown as dashes
    header = md.splitlines()[2]
    assert header.count("|") == md.splitlines()[3].count("|")


def test_input_validation_and_iou() -> None:
    with pytest.raises(ValueError):
        evaluate_single_target([None], [None, None])
    assert box_iou((0, 0, 10, 10), (5, 0, 10, 10)) == pytest.approx(50 / 150)
    assert box_iou((0, 0, 10, 10), (20, 0, 10, 10)) == 0.0


def test_wrong_relock_is_a_run_of_outputs_off_the_target_on_a_single_target_clip() -> None:
    gt = walk(60)
    stranger = shift(gt, 200.0)  # no overlap with the target's box
    # 12 frames on the stranger (an episode), back on the target, then 8 frames off (too short to count).
    pred = gt[:10] + stranger[10:22] + gt[22:40] + stranger[40:48] + gt[48:]
    m = evaluate_single_target(pred, gt)
    assert m.wrong_relocks == 1 and m.target_switches == 0  # no other person is annotated
    # The target hidden in the middle of a wrong episode neither ends nor extends it; a missing output ends it.
    hidden = list(gt)
    hidden[14:20] = [None] * 6
    assert evaluate_single_target(pred, hidden).wrong_relocks == 0  # 6 judged frames off the target
    assert evaluate_single_target(stranger[:15] + [None] + stranger[16:30], gt[:30]).wrong_relocks == 2
    # A partial overlap is not a wrong re-lock (a poor box on the right person).
    assert evaluate_single_target(shift(gt, 30.0), gt).wrong_relocks == 0
    assert aggregate([m, m]).wrong_relocks == 2
