"""Peer MOT trackers (Roboflow ``trackers``) as followers and as multi-object trackers: the follower adapter's
behaviour, MOT scoring of their output, and our MOT metrics against the TrackEval-parity code they ship."""

from __future__ import annotations

import json

import numpy as np
import pytest

from followbus.evaluation.baselines import peer_available
from followbus.evaluation.mot_metrics import evaluate_mot, iou_matrix
from followbus.evaluation.runner import gt_mot_frames, method_factories, open_sequence, run_sequence

from .conftest import SHARED, run_followbus

pytestmark = pytest.mark.skipif(peer_available() is not None, reason=f"peer trackers: {peer_available()}")

PEERS = ["peer:bytetrack", "peer:ocsort", "peer:botsort"]
TUD = SHARED / "data" / "mot" / "tud-campus"


def test_peers_follow_their_id_and_lose_the_target_at_a_full_occlusion():
    """The claim the product rests on: id-following MOT trackers drop the target when a full occlusion
    outlasts their track buffer (it comes back under a new id), while followbus re-identifies it."""
    run = run_sequence(open_sequence("scene:wall-occlusion"), method_factories(["followbus", *PEERS]), "simulated")
    fb = run.runs["followbus"].metrics
    assert fb.reid_events and all(e.latency_frames is not None for e in fb.reid_events)
    (start, end), = [s for s in run.occlusion_spans() if s[1] - s[0] > 30]
    for name in PEERS:
        r = run.runs[name]
        states = [i["state"] for i in r.infos]
        assert states.count("TRACKING") > 50, (name, states[:20])  # it did pick the target and follow it
        # through a missed detection it coasts on the tracker's prediction; that box is not MOT output
        coast = [k for k, st in enumerate(states) if st == "COASTING"]
        assert coast, name
        assert all(r.boxes[k] not in r.infos[k]["mot"][1] for k in coast)
        before = r.boxes[start - 20:start - 3]  # still on the target just before the wall
        assert sum(b is not None for b in before) >= 8, (name, before)
        after = r.boxes[end + 10:]
        assert all(b is None for b in after), f"{name} reported its old id after the occlusion"
        assert r.metrics.reid_censored == len(r.metrics.reid_events) > 0
        assert r.metrics.tsr < fb.tsr - 0.3, (name, r.metrics.tsr, fb.tsr)
        assert r.mot is None  # a scene annotates no person ids: no MOT scoring
        # on a frame it reports its id, a peer outputs a detection: never better than the nearest-detection oracle
        reported = [k for k, st in enumerate(states) if st == "TRACKING" and run.gt_boxes[k] is not None]
        assert all(run.ceiling.center_errors[k] <= r.metrics.center_errors[k] + 1e-6 for k in reported)
    # the detector misses the partly hidden target for a while; followbus coasts on its prior through those
    # frames, so it beats even the nearest-detection oracle
    assert run.ceiling.missing_outputs > 10 and fb.tsr > run.ceiling.tsr

def _trackeval(gt_frames, pred_frames):
    from trackers.eval import compute_clear_metrics, compute_hota_metrics, compute_identity_metrics

    gids = [np.asarray(g[0], dtype=int) for g in gt_frames]
    pids = [np.asarray(p[0], dtype=int) for p in pred_frames]
    sims = [iou_matrix(g[1], p[1]) for g, p in zip(gt_frames, pred_frames, strict=True)]
    return (compute_clear_metrics(gids, pids, sims), compute_identity_metrics(gids, pids, sims),
            compute_hota_metrics(gids, pids, sims))


@pytest.mark.skipif(not TUD.is_dir(), reason=f"evaluation data absent ({TUD})")
def test_peer_output_scored_on_a_mot_sequence_agrees_with_trackeval_parity_code():
    run = run_sequence(open_sequence(str(TUD)), method_factories(PEERS), "simulated")
    gt = gt_mot_frames(run.gt_people)
    assert sum(len(f[0]) for f in gt) > 250  # every annotated person, not just the follow target
    for name in PEERS:
        mot = run.runs[name].mot
        assert mot is not None and mot.clear.num_frames == run.sequence.n_frames
        pred = [i.get("mot") for i in run.runs[name].infos]
        assert mot.clear.num_predictions == sum(len(p[0]) for p in pred if p) > 0
        assert 0.3 < mot.mota <= 1.0, (name, mot.as_dict())  # gt + 4 px noise: a tracker must do well
        clear, ident, hota = _trackeval(gt, [p if p else ([], []) for p in pred])
        assert mot.mota == pytest.approx(clear["MOTA"], abs=1e-9), name
        assert mot.clear.num_switches == clear["IDSW"] and mot.clear.num_false_positives == clear["CLR_FP"]
        assert mot.idf1 == pytest.approx(ident["IDF1"], abs=1e-9), name
        assert mot.hota.hota == pytest.approx(hota["HOTA"], abs=1e-6), name
        assert mot.hota.assa == pytest.approx(hota["AssA"], abs=1e-6), name


def test_our_metrics_agree_with_trackeval_parity_code_on_random_tracks():
    rng = np.random.default_rng(7)
    gt, pred = [], []
    for _ in range(60):
        n = int(rng.integers(0, 6))
        ids = rng.choice(8, size=n, replace=False)
        boxes = np.column_stack([ids * 40.0 + rng.normal(0, 3, n), rng.normal(100, 3, n),
                                 np.full(n, 30.0), np.full(n, 80.0)])
        gt.append((ids.tolist(), boxes.tolist()))
        keep = rng.random(n) > 0.2  # misses
        pid = (ids[keep] + rng.integers(0, 2, keep.sum()) * 10).tolist()  # some identity swaps
        pb = (boxes[keep] + rng.normal(0, 2.5, (keep.sum(), 4))).tolist()
        if rng.random() < 0.3:  # a false positive
            pid.append(99)
            pb.append([500.0, 100.0, 30.0, 80.0])
        pred.append((pid, pb))
    ours = evaluate_mot(gt, pred)
    clear, ident, hota = _trackeval(gt, pred)
    assert 0.0 < ours.mota < 1.0 and ours.clear.num_switches > 0  # a non-trivial case
    assert ours.mota == pytest.approx(clear["MOTA"], abs=1e-9)
    assert ours.clear.num_switches == clear["IDSW"]
    assert ours.idf1 == pytest.approx(ident["IDF1"], abs=1e-9)
    assert ours.hota.hota == pytest.approx(hota["HOTA"], abs=1e-6)
    assert ours.hota.deta == pytest.approx(hota["DetA"], abs=1e-6)
    assert ours.hota.loca == pytest.approx(hota["LocA"], abs=1e-6)


@pytest.mark.slow
@pytest.mark.skipif(not TUD.is_dir(), reason=f"evaluation data absent ({TUD})")
def test_eval_cli_reports_mot_metrics_for_peers(tmp_path):
    out = tmp_path / "res"
    res = run_followbus("eval", str(TUD), "--detector", "simulated", "--method", "followbus",
                        "--method", "peer:bytetrack", "--out", str(out), timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    md = (out / "results.md").read_text()
    assert "Multi-object metrics" in md and "| mot/tud-campus | 71 | peer:bytetrack |" in md
    assert "| **combined** | 71 | peer:bytetrack |" in md
    assert "| mot/tud-campus | 71 | followbus |" not in md.split("Multi-object metrics")[1].split("###")[0]
    methods = json.loads((out / "results.json").read_text())["sequences"]["mot/tud-campus"]["methods"]
    assert "mot" not in methods["followbus"] and 0.0 < methods["peer:bytetrack"]["mot"]["mota"] <= 1.0


MOT17 = SHARED / "data" / "mot" / "mot17-mini-02"  # YOLOX finds two of its static people


@pytest.mark.skipif(not MOT17.is_dir(), reason=f"evaluation data absent ({MOT17})")
def test_mot17_scoring_with_distractors_matches_trackeval_parity_evaluation(tmp_path):
    """The whole MOTChallenge protocol, preprocessing included, against ``trackers.eval.evaluate_mot_sequence``
    run on the files: a real detector finds the static people that MOT17 marks as distractors."""
    from trackers.eval import evaluate_mot_sequence

    from followbus.evaluation.mot_metrics import load_mot_regions

    regions = load_mot_regions(MOT17 / "gt" / "gt.txt")
    assert any(d.any() for _, d in regions.values()), "this excerpt has distractor rows"
    run = run_sequence(open_sequence(str(MOT17)), method_factories(["peer:bytetrack"]), "yolox640")
    mine = run.runs["peer:bytetrack"]
    raw = sum(len(i["mot"][0]) for i in mine.infos if "mot" in i)
    scored = sum(len(f[0]) for f in mine.mot_frames)
    assert scored < raw, "no tracker box was on a distractor: the preprocessing was not exercised"
    rows = [f"{k + 1},{i},{b[0]:.6f},{b[1]:.6f},{b[2]:.6f},{b[3]:.6f},1,-1,-1,-1"
            for k, info in enumerate(mine.infos) if "mot" in info for i, b in zip(*info["mot"], strict=True)]
    (tmp_path / "bt.txt").write_text("\n".join(rows) + "\n")
    ref = evaluate_mot_sequence(MOT17 / "gt" / "gt.txt", tmp_path / "bt.txt", metrics=["CLEAR", "HOTA", "Identity"])
    assert mine.mot.mota == pytest.approx(ref.CLEAR.MOTA, abs=1e-6)
    assert mine.mot.clear.num_false_positives == ref.CLEAR.CLR_FP
    assert mine.mot.idf1 == pytest.approx(ref.Identity.IDF1, abs=1e-6)
    assert mine.mot.hota.hota == pytest.approx(ref.HOTA.HOTA, abs=1e-6)


@pytest.mark.parametrize("use_current_box", [True, False])
def test_a_peer_that_starts_unassigned_chooses_against_the_targets_box_of_that_frame(use_current_box):
    """The target is missed on the init frame and then seen 150 px away, while a stranger walks into the
    init box. Choosing against the frame-1 box latches onto the stranger (the old start, kept here as the
    control); against the target's box of the frame where a track is first confirmed, the target is taken."""
    from followbus.evaluation.baselines import PeerFollower

    peer = PeerFollower("bytetrack", fps=30.0)
    init = (100.0, 100.0, 40.0, 100.0)
    target = (250.0, 100.0, 40.0, 100.0)
    assert peer.step(None, np.zeros((0, 5), np.float32), 0, init_box=init)[0] is None
    box = None
    for k in range(1, 12):
        dets = np.array([[*target, 0.9], [*init, 0.9]], np.float32)  # the stranger stands in the init box
        if use_current_box and peer.wants_reference:
            peer.update_reference(target)
        box, _ = peer.step(None, dets, k * 33_000_000)
    assert box is not None
    on_target = abs(box[0] - target[0]) < 5
    assert on_target == use_current_box
