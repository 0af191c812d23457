"""The graph's node classes driven through the in-process runtime (bus/inproc.py): hand-made messages in,
published messages out, on a simulated clock. No processes, no Zenoh."""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest

from followbus.bus.graph import GraphError, apply_overrides, load_graph
from followbus.bus.inproc import InProcessError, InProcessGraph
from followbus.bus.schemas import Frame, Message, ReplayHint, Tick, encode
from followbus.msgs.perception import Detections
from followbus.msgs.robot import Odometry
from followbus.msgs.tracking import Measurement, Prior, Track

from .conftest import REPO

DT_NS = 33_333_333  # 30 fps
MS = 1_000_000
EPOCH_NS = 1_600_000_000_000_000_000
W, H = 320, 240


def tracking_graph(*overrides: str):
    graph = load_graph(REPO / "graph.yaml")
    # Never the repository's state/template.npz: a test neither reads nor writes it.
    apply_overrides(graph, ["template.state_file=", *overrides])
    return graph


def stamped(msg: Message, k: int, stamp_ns: int) -> Message:
    msg.header.frame_seq, msg.header.stamp_ns, msg.header.epoch_ns = k, stamp_ns, EPOCH_NS
    return msg


def person_frame(box: tuple[int, int, int, int], shirt=(40, 40, 200), wall: bool = False) -> np.ndarray:
    """A textured floor and wall with one figure (shirt over trousers) at ``box``; ``wall``: a grey panel
    hides the figure."""
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.stack([60 + (xx * 7 + yy * 3) % 40, 90 + (xx * 5) % 30, 70 + (yy * 11) % 50], axis=-1).astype(np.uint8)
    x, y, w, h = box
    img[y:y + h // 2, x:x + w] = shirt
    img[y + h // 2:y + h, x:x + w] = (120, 60, 20)
    if wall:
        img[:, x - 20:x + w + 20] = (128, 128, 128)
    return img


def frame_msg(k: int, stamp_ns: int, bgr: np.ndarray) -> Frame:
    return stamped(Frame(width=bgr.shape[1], height=bgr.shape[0], encoding="bgr8", data=bgr), k, stamp_ns)


def dets_msg(k: int, stamp_ns: int, *boxes) -> Detections:
    rows = np.array([[*b, 0.9] for b in boxes], dtype=np.float32).reshape(-1, 5)
    return stamped(Detections(boxes=rows, backend="hand-made"), k, stamp_ns)


def measurement(k: int, stamp_ns: int, state: str, box=None, *, init: bool = False, secure: bool = True,
                best_box=None) -> Measurement:
    b = None if box is None else np.asarray(box, dtype=np.float64)
    msg = Measurement(state=state, accepted=b is not None, secure=secure and b is not None, box=b,
                      best_box=b if best_box is None else np.asarray(best_box, dtype=np.float64),
                      source="init" if init else "detection", init_box=b if init else None)
    return stamped(msg, k, stamp_ns)


def states(msgs) -> list[str]:
    return [m.state for m in msgs]


# --------------------------------------------------------------------------- prediction


def test_prediction_prior_waits_for_the_previous_measurement_then_times_out_on_the_simulated_clock():
    with InProcessGraph(tracking_graph(), nodes=["prediction"]) as g:
        t0 = g.now_ns
        box = (100.0, 60.0, 30.0, 80.0)
        g.inject("detection/detections", dets_msg(0, t0, box))
        g.deliver()
        priors = g.outputs("prediction", "prior")
        assert [p.header.frame_seq for p in priors] == [0]
        assert not priors[0].initialised  # nothing measured yet

        # Frame 1's prior is computed after frame 0's measurement (offset -1), however late that comes.
        g.inject("detection/detections", dets_msg(1, t0 + DT_NS, box))
        g.deliver()
        assert len(g.outputs("prediction", "prior")) == 1
        g.inject("reid/measurement", measurement(0, t0, "TRACKING", box, init=True))
        g.deliver()
        priors = g.outputs("prediction", "prior")
        assert [p.header.frame_seq for p in priors] == [0, 1]
        assert priors[1].initialised and priors[1].header.feedback["measurement"] == 0
        assert priors[1].gate_chi2 == 9.488  # graph.yaml's gate, which re-ID applies to this prior
        assert np.all(np.linalg.eigvalsh(priors[1].innovation_cov) > 0)
        tracks = g.outputs("prediction", "track")
        assert states(tracks) == ["TRACKING"] and tracks[0].header.frame_seq == 0

        # Measurement 1 never comes: frame 2's set waits sync_timeout_ms (300) of simulated time, no more.
        g.inject("detection/detections", dets_msg(2, t0 + 2 * DT_NS, box))
        g.deliver()
        waiting_since = g.now_ns
        g.run_until(waiting_since + 299 * MS)
        assert len(g.outputs("prediction", "prior")) == 2
        g.run_until(waiting_since + 300 * MS)
        priors = g.outputs("prediction", "prior")
        assert [p.header.frame_seq for p in priors] == [0, 1, 2]
        assert priors[2].header.feedback["measurement"] == 0  # the newest one it had
        assert g.status("prediction")["extra"]["sync_feedback_fallbacks"] == 1


def _prior_of_frame_1(odometry: list[tuple[int, float]]) -> Prior:
    """Frame 1's prior after frame 0 initialised the filter, with odometry samples (stamp offset, vx) given
    in this order, all arriving before frame 1's detections."""
    with InProcessGraph(tracking_graph(), nodes=["prediction"]) as g:
        t0 = g.now_ns
        box = (100.0, 60.0, 30.0, 80.0)
        g.inject("detection/detections", dets_msg(0, t0, box))
        g.inject("reid/measurement", measurement(0, t0, "TRACKING", box, init=True))
        for offset_ns, vx in odometry:
            g.inject("motor/odometry", stamped(Odometry(vx_mps=vx), -1, t0 + offset_ns))
        g.inject("detection/detections", dets_msg(1, t0 + DT_NS, box))
        g.deliver()
        priors = g.outputs("prediction", "prior")
        assert [p.header.frame_seq for p in priors] == [0, 1]
        return priors[1]


def test_prediction_takes_the_odometry_sample_by_stamp_not_the_last_to_arrive():
    before, after = DT_NS - 10 * MS, DT_NS + 5 * MS  # around frame 1's capture stamp
    prior = _prior_of_frame_1([(before, 0.2), (after, 3.0)])
    t0 = prior.header.stamp_ns - DT_NS
    assert prior.header.feedback["odometry"] == t0 + before  # noted, so a replay repeats the choice
    # Eq. 7: R_k grows with the ego speed; the sample stamped after the frame must not count.
    same = _prior_of_frame_1([(before, 0.2)])
    assert np.array_equal(prior.innovation_cov, same.innovation_cov)
    fast = _prior_of_frame_1([(before, 3.0)])
    assert fast.innovation_cov[0, 0] > prior.innovation_cov[0, 0]


# --------------------------------------------------------------------------- re-ID (with prediction, template)


def _run_reid(frames: list[tuple[np.ndarray, list]], *overrides: str) -> InProcessGraph:
    g = InProcessGraph(tracking_graph(*overrides), nodes=["prediction", "reid", "template"])
    t0 = g.now_ns
    for k, (bgr, boxes) in enumerate(frames):
        stamp = t0 + k * DT_NS
        g.run_until(stamp)
        g.inject("capture/frame", frame_msg(k, stamp, bgr))
        g.inject("detection/detections", dets_msg(k, stamp, *boxes))
        g.deliver()
    g.close()
    return g


def test_reid_initialises_on_the_detection_nearest_the_bottom_centre_and_goes_lost_after_lost_after_ms():
    target = (150, 120, 24, 80)
    bystander = (20, 10, 20, 60)  # far from the bottom centre
    frames = [(person_frame((150 + 2 * k, 120, 24, 80)), [(150 + 2 * k, 120, 24, 80)] + ([bystander] if k == 0
                                                                                         else []))
              for k in range(8)]
    still = person_frame((164, 120, 24, 80))  # then it stands still, undetected: no detection, no motion
    frames += [(still, [])] * 12
    g = _run_reid(frames, "reid.lost_after_ms=200")
    meas = g.outputs("reid", "measurement")
    assert len(meas) == 20
    assert meas[0].init_box is not None and tuple(meas[0].init_box) == target
    assert states(meas[:8]) == ["TRACKING"] * 8 and all(m.accepted for m in meas[:8])
    # OCCLUDED while no more than 200 ms have passed since the last accepted frame (7), LOST after.
    lost = [k for k in range(8, 20) if (k - 7) * DT_NS > 200 * MS]
    assert states(meas[8:]) == ["OCCLUDED" if k not in lost else "LOST" for k in range(8, 20)]
    assert states(g.outputs("prediction", "track")) == states(meas)
    # The feedback edge: frame k's re-ID used the template learnt on frame k-1.
    assert [m.header.feedback.get("template") for m in meas] == [-1] + list(range(19))


def test_reid_gate_drops_a_detection_far_from_the_prior():
    far = (20, 20, 24, 80)
    frames = [(person_frame((150 + 2 * k, 120, 24, 80)), [(150 + 2 * k, 120, 24, 80)]) for k in range(6)]
    # Frame 6: the same-looking figure, but far outside the χ² gate of the prior; frame 7: where expected.
    frames.append((person_frame(far), [far]))
    frames.append((person_frame((164, 120, 24, 80)), [(164, 120, 24, 80)]))
    meas = _run_reid(frames).outputs("reid", "measurement")
    assert not meas[6].accepted and meas[6].state == "OCCLUDED"
    assert far not in [tuple(c[:4]) for c in meas[6].candidates]
    assert meas[7].accepted and tuple(meas[7].box) == (164, 120, 24, 80)
    # Without the gate the look-alike far away is taken: the gate is what kept it out.
    ungated = _run_reid(frames, "reid.use_gate=false").outputs("reid", "measurement")
    assert ungated[6].accepted and tuple(ungated[6].box) == far


def _prior(k: int, stamp_ns: int, box: tuple[float, float, float, float]) -> Prior:
    """Prediction's prior for frame k, centred on ``box`` (S = 25 px², so a gate radius of about 15 px)."""
    x, y, w, h = box
    prior = Prior.of_filter(stamp_ns, np.array([x + w / 2, y + h / 2, 0.0, 0.0]), (w, h), np.eye(4) * 25.0,
                            np.eye(2) * 25.0, 9.488)
    return stamped(prior, k, stamp_ns)


def test_reid_initialised_without_a_template_tracks_on_instead_of_initialising_every_frame():
    # A re-ID restarted while prediction kept the track, with no template node to answer it (template_wait_ms
    # over at once), and a backlog of sets arriving at once. It initialises once (on the prior) and then tracks
    # with the initial box's histogram; before, every set without a template initialised again (six in a row,
    # the last on a bystander: CI, 2026-11-26).
    target, bystander = (150, 120, 24, 80), (30, 100, 40, 120)
    with InProcessGraph(tracking_graph("reid.template_wait_ms=0"), nodes=["reid"]) as g:
        t0 = g.now_ns
        for k in range(6):
            stamp = t0 + k * DT_NS
            box = (target[0] + 2 * k, *target[1:])
            g.inject("capture/frame", frame_msg(k, stamp, person_frame(box)))
            g.inject("detection/detections", dets_msg(k, stamp, box, bystander))
            g.inject("prediction/prior", _prior(k, stamp, tuple(map(float, box))))
        g.deliver()
        g.run_until(t0 + 6 * DT_NS + 400 * MS)  # the feedback waits, if any, have ended
        meas = g.outputs("reid", "measurement")
    assert len(meas) == 6
    assert meas[0].source == "prior" and meas[0].init_box is not None
    assert all(m.init_box is None for m in meas[1:])
    assert states(meas) == ["TRACKING"] * 6 and all(m.accepted for m in meas)
    assert [tuple(m.box) for m in meas] == [(target[0] + 2 * k, *target[1:]) for k in range(6)]


def two_people_frame(target: tuple[int, int, int, int], bystander: tuple[int, int, int, int]) -> np.ndarray:
    img = person_frame(target)  # red shirt
    x, y, w, h = bystander
    img[y:y + h // 2, x:x + w] = (200, 120, 30)  # blue shirt
    img[y + h // 2:y + h, x:x + w] = (120, 60, 20)
    return img


@pytest.mark.parametrize("template_node_knows_the_target", [True, False])
def test_a_restarted_reid_waits_for_the_template_before_it_re_acquires(template_node_knows_the_target: bool):
    # re-ID joins a graph that follows someone (a restart): the prior coasted through the restart and now lies
    # nearer a bystander than the target. It publishes "no target" until the template node, answering those
    # measurements, sends the template; then the target is re-acquired by its colours, and the template node
    # keeps the target it knew instead of re-learning from the bystander. A template node that knows no target
    # answers at once with none, and re-ID initialises on the prior as before.
    from followbus.tracking.appearance import hs_histogram

    target, bystander = (150, 120, 24, 80), (104, 120, 24, 80)
    frame = two_people_frame(target, bystander)
    known = hs_histogram(frame, target, 16, 8)
    with InProcessGraph(tracking_graph(), nodes=["reid", "template"]) as g:
        g.start()
        if template_node_knows_the_target:
            g.node("template").updater.hist = known.copy()
        t0 = g.now_ns
        for k in range(6):
            stamp = t0 + k * DT_NS
            g.run_until(stamp)
            g.inject("capture/frame", frame_msg(k, stamp, frame))
            g.inject("detection/detections", dets_msg(k, stamp, target, bystander))
            # Centred 12 px from the bystander and 34 px from the target; a gate wide enough for both.
            prior = Prior.of_filter(stamp, np.array([128.0, 160.0, 0.0, 0.0]), (24.0, 80.0), np.eye(4) * 900.0,
                                    np.eye(2) * 900.0, 9.488)
            g.inject("prediction/prior", stamped(prior, k, stamp))
            g.deliver()
        g.run_until(g.now_ns + 400 * MS)
        meas = g.outputs("reid", "measurement")
        learnt = g.node("template").updater.hist
    assert len(meas) == 6
    assert meas[0].state == "UNINITIALISED" and not meas[0].accepted  # prediction coasts, the motor stops
    if template_node_knows_the_target:
        assert meas[1].init_box is None and meas[1].accepted and tuple(meas[1].box) == target
        assert all(m.accepted and tuple(m.box) == target for m in meas[1:])
        assert learnt is not None and float(np.minimum(learnt, known).sum()) > 0.9
    else:
        assert meas[1].source == "prior" and tuple(meas[1].init_box) == bystander


def test_a_template_node_restarted_without_its_state_does_not_make_reid_forget_the_target():
    # Following the target; from frame 4 the template node answers "no template" (restarted with no state file:
    # it re-learns from re-ID's next secure lock, tests/test_tracking_template.py). re-ID keeps matching against
    # the last template it had, so it stays on the target although a bystander now stands nearer the prior.
    from followbus.msgs.tracking import Template
    from followbus.tracking.appearance import hs_histogram

    target, bystander = (150, 120, 24, 80), (104, 120, 24, 80)
    frame = two_people_frame(target, bystander)
    known = hs_histogram(frame, target, 16, 8)
    with InProcessGraph(tracking_graph(), nodes=["reid"]) as g:
        t0 = g.now_ns
        for k in range(10):
            stamp = t0 + k * DT_NS
            g.run_until(stamp)
            if k:  # the template node's answer to frame k-1
                template = Template(initialised=k <= 4, hist=known.copy() if k <= 4 else None)
                g.inject("template/template", stamped(template, k - 1, stamp))
            g.inject("capture/frame", frame_msg(k, stamp, frame))
            g.inject("detection/detections", dets_msg(k, stamp, target, bystander))
            centre = (162.0, 160.0) if k < 5 else (128.0, 160.0)  # then 12 px from the bystander, 34 from the target
            prior = Prior.of_filter(stamp, np.array([*centre, 0.0, 0.0]), (24.0, 80.0), np.eye(4) * 900.0,
                                    np.eye(2) * 900.0, 9.488)
            g.inject("prediction/prior", stamped(prior if k else Prior(), k, stamp))  # frame 0: a new launch
            g.deliver()
        g.run_until(g.now_ns + 400 * MS)
        meas = g.outputs("reid", "measurement")
    assert len(meas) == 10 and meas[0].init_box is not None
    assert [m.header.feedback.get("template") for m in meas[5:]] == [4, 5, 6, 7, 8]  # "no template" was used
    assert all(m.init_box is None and m.accepted and tuple(m.box) == target for m in meas[1:])


def test_reid_ignores_a_template_learnt_before_it_initialised():
    # Frames 0-4 show nobody (no detection, no motion): re-ID is not initialised. Frame 5 initialises it on the
    # target. Then a template from frame 3 (someone else's look) arrives, the newest the template node sent:
    # frame 6's set falls back to it once its own feedback times out. It describes no lock of this re-ID: the
    # initial box's histogram stays the reference, and the target is tracked on.
    from followbus.msgs.tracking import Template
    from followbus.tracking.appearance import hs_histogram

    target = (150, 120, 24, 80)
    with InProcessGraph(tracking_graph(), nodes=["reid"]) as g:
        t0 = g.now_ns
        for k in range(7):
            stamp = t0 + k * 400 * MS  # each set's feedback wait (300 ms) is over before the next frame
            g.run_until(stamp)
            g.inject("capture/frame", frame_msg(k, stamp, person_frame(target if k >= 5 else (0, 0, 0, 0))))
            g.inject("detection/detections", dets_msg(k, stamp, *([target] if k >= 5 else [])))
            g.inject("prediction/prior", _prior(k, stamp, tuple(map(float, target))))
            g.deliver()
            if k == 5:
                g.run_until(stamp + 350 * MS)  # frame 5 handled
                other_look = hs_histogram(person_frame(target, shirt=(200, 160, 20)), target, 16, 8)
                g.inject("template/template", stamped(Template(initialised=True, hist=other_look), 3, stamp))
        g.run_until(g.now_ns + 400 * MS)
        meas = {m.header.frame_seq: m for m in g.outputs("reid", "measurement")}
    assert {meas[k].state for k in meas if k < 5} == {"UNINITIALISED"}
    assert meas[5].init_box is not None
    assert meas[6].header.feedback.get("template") == 3  # the stale template was the set's feedback...
    assert meas[6].init_box is None and meas[6].state == "TRACKING" and tuple(meas[6].box) == target
    assert meas[6].s_color > 0.9  # ...but the colours were compared with the initial box's, not with it


# --------------------------------------------------------------------------- template


def test_template_freezes_under_occlusion():
    box = (150.0, 120.0, 24.0, 80.0)
    steps = [  # (frame, measurement state, accepted box, best (rejected) box)
        (person_frame((150, 120, 24, 80)), "TRACKING", box, None),  # initialisation
        (person_frame((150, 120, 24, 80), shirt=(40, 200, 40)), "TRACKING", box, None),
        (person_frame((150, 120, 24, 80), shirt=(200, 40, 40)), "OCCLUDED", None, None),
        (person_frame((150, 120, 24, 80), shirt=(200, 40, 40)), "OCCLUDED", None, box),  # a rejected candidate
        (person_frame((150, 120, 24, 80), shirt=(40, 200, 40)), "TRACKING", box, None),
    ]
    with InProcessGraph(tracking_graph(), nodes=["template"]) as g:
        t0 = g.now_ns
        for k, (bgr, state, accepted, best) in enumerate(steps):
            stamp = t0 + k * DT_NS
            g.inject("capture/frame", frame_msg(k, stamp, bgr))
            g.inject("reid/measurement", measurement(k, stamp, state, accepted, init=k == 0, best_box=best))
            g.run_until(stamp + DT_NS)
        out = g.outputs("template", "template")
    assert [t.header.frame_seq for t in out] == [0, 1, 2, 3, 4]
    assert all(t.initialised for t in out)
    assert out[0].eta == 0.0  # initialised from the box, nothing blended
    assert out[1].eta > 0.0 and not np.array_equal(out[1].hist, out[0].hist)
    # Occluded (Eq. 10): η = 0 and M is exactly the last one learnt, whatever the frame shows.
    for occluded in out[2:4]:
        assert occluded.eta == 0.0 and np.array_equal(occluded.hist, out[1].hist)
    assert out[4].eta > 0.0 and not np.array_equal(out[4].hist, out[1].hist)


@pytest.mark.parametrize(("saved_by", "max_age_s", "restored"), [
    ("launch-A", 0.0, True),  # this launch's earlier process: a restart resumes with the learnt M
    ("launch-B", 0.0, False),  # another launch: may be another person, learn afresh
    ("launch-B", 3600.0, True),  # ... unless the graph allows recent files from other launches
])
def test_template_restores_only_its_own_launch_by_default(tmp_path, monkeypatch, saved_by, max_age_s, restored):
    from followbus.bus.node_runtime import LAUNCH_ID_ENV
    from followbus.tracking.params import TemplateParams
    from followbus.tracking.template import TemplateUpdater

    saved = TemplateUpdater(TemplateParams())
    saved.initialise(person_frame((150, 120, 24, 80)), (150.0, 120.0, 24.0, 80.0))
    path = tmp_path / "template.npz"
    saved.save(path, saved_by=saved_by)
    monkeypatch.setenv(LAUNCH_ID_ENV, "launch-A")
    graph = tracking_graph(f"template.state_file={path}", f"template.restore_other_launch_max_age_s={max_age_s}")
    with InProcessGraph(graph, nodes=["template"]) as g:
        stamp = g.now_ns
        g.inject("capture/frame", frame_msg(0, stamp, person_frame((150, 120, 24, 80), wall=True)))
        g.inject("reid/measurement", measurement(0, stamp, "OCCLUDED", None))
        g.run_until(stamp + DT_NS)
        out = g.outputs("template", "template")
    assert len(out) == 1 and out[0].initialised is restored
    if restored:
        np.testing.assert_allclose(out[0].hist, saved.hist, atol=1e-6)


def test_a_template_that_cannot_be_saved_is_said_once_and_still_goes_out(tmp_path, caplog):
    """A state file that cannot be written (a full disk, a file where its directory should be) costs the restart
    its learnt template, never the frame's: the template is published, the failure counted and logged once
    (it raised in on_frame: a traceback on every save)."""
    blocked = tmp_path / "state"
    blocked.write_text("a file where the state directory should be")
    box = (150.0, 120.0, 24.0, 80.0)
    graph = tracking_graph(f"template.state_file={blocked}/template.npz", "template.save_every_s=1e-9")
    with caplog.at_level(logging.WARNING), InProcessGraph(graph, nodes=["template"]) as g:
        t0 = g.now_ns
        for k in range(3):
            stamp = t0 + k * DT_NS
            g.inject("capture/frame", frame_msg(k, stamp, person_frame((150, 120, 24, 80))))
            g.inject("reid/measurement", measurement(k, stamp, "TRACKING", box, init=k == 0))
            g.run_until(stamp + DT_NS)
        out = g.outputs("template", "template")
        status = g.status("template")["extra"]
    assert [t.header.frame_seq for t in out] == [0, 1, 2] and all(t.initialised for t in out)
    assert status["save_failures"] == 3 and status["handler_errors"] == 0, status
    said = [r for r in caplog.records if "cannot save the template" in r.getMessage()]
    assert len(said) == 1 and str(blocked) in said[0].getMessage()


# --------------------------------------------------------------------------- motor


def _track(k: int, stamp_ns: int, state: str = "TRACKING") -> Track:
    box = np.array([280.0, 120.0, 80.0, 240.0]) if state != "LOST" else None
    return stamped(Track(state=state, box=box, filtered_box=box), k, stamp_ns)


def _is_zero(cmd) -> bool:
    return cmd.vx_mps == 0.0 and cmd.vy_mps == 0.0 and cmd.wz_radps == 0.0 and not np.any(cmd.wheel_radps)


@pytest.mark.parametrize("stamp_offset_ns", [0, 3600 * 1_000_000_000, -400 * MS],
                         ids=["stamped-now", "stamped-an-hour-ahead", "stamped-400ms-ago"])
def test_motor_watchdog_stops_within_200ms_of_simulated_time_after_the_last_track(stamp_offset_ns):
    with InProcessGraph(tracking_graph(), nodes=["motor"]) as g:
        t0 = g.now_ns
        for k in range(10):  # tracks keep it going: no stop meanwhile
            g.run_until(t0 + k * DT_NS)
            g.inject("prediction/track", _track(k, g.now_ns + stamp_offset_ns))
            g.deliver()
        last_rx = g.now_ns
        g.run_until(last_rx + 400 * MS)
        cmds = g.outputs("motor", "command")
    moving = [c for c in cmds if c.header.pub_ns <= last_rx]
    assert len(moving) == 10 and all(c.reason != "watchdog" and not _is_zero(c) for c in moving)
    stops = [c for c in cmds if c.reason == "watchdog"]
    assert stops, "the watchdog never stopped the robot"
    first = stops[0]
    assert _is_zero(first)
    assert 130 * MS <= first.header.pub_ns - last_rx <= 200 * MS  # not before its timeout, within the promise
    assert all(_is_zero(c) for c in cmds if c.header.pub_ns >= first.header.pub_ns)


def test_motor_does_not_act_on_stale_tracks_and_says_why(caplog):
    """Tracks captured longer than max_track_age_ms (500) ago steer nothing: the motor never moves on them, counts
    them and says, once, that the graph is behind or the capturing host's clock is (they were only counted)."""
    with caplog.at_level(logging.WARNING), InProcessGraph(tracking_graph(), nodes=["motor"]) as g:
        t0 = g.now_ns
        for k in range(5):
            g.run_until(t0 + k * DT_NS)
            g.inject("prediction/track", _track(k, g.now_ns - 600 * MS))
            g.deliver()
        g.run_until(t0 + 300 * MS)
        cmds = g.outputs("motor", "command")
        status = g.status("motor")["extra"]
    assert cmds and all(_is_zero(c) for c in cmds)
    assert status["too_old"] == 5, status
    said = [r.getMessage() for r in caplog.records if "not acting on a track" in r.getMessage()]
    assert len(said) == 1 and "captured 600 ms ago (max_track_age_ms 500" in said[0] and "NTP" in said[0], said


def test_motor_stops_at_once_on_a_lost_target():
    with InProcessGraph(tracking_graph(), nodes=["motor"]) as g:
        t0 = g.now_ns
        g.inject("prediction/track", _track(0, t0))
        g.deliver()
        g.run_until(t0 + DT_NS)
        g.inject("prediction/track", _track(1, g.now_ns, "LOST"))
        g.deliver()
        cmds = g.outputs("motor", "command")
    assert not _is_zero(cmds[0])
    assert _is_zero(cmds[-1]) and cmds[-1].header.frame_seq == 1 and cmds[-1].header.pub_ns == t0 + DT_NS


def test_motor_odometry_ticks_on_the_simulated_clock():
    with InProcessGraph(tracking_graph(), nodes=["motor"]) as g:
        t0 = g.now_ns
        g.run_until(t0 + 100 * MS)
        odom = g.outputs("motor", "odometry")
    assert [o.header.stamp_ns - t0 for o in odom] == [10 * MS * i for i in range(1, 11)]


# --------------------------------------------------------------------------- the whole graph


def _scene_graph(frames: int, *extra: str):
    return tracking_graph("detection.backend=simulated", "capture.source=scene:wall-occlusion",
                          f"capture.max_frames={frames}", *extra)


def test_whole_graph_runs_bit_identically_twice_with_or_without_the_bytes():
    """Run twice: once with every message encoded and decoded (wire=True), once with the subscribers' copies
    made without the bytes (the default): every node must publish the same bytes."""
    runs = []
    for wire in (True, False):
        with InProcessGraph(_scene_graph(60), wire=wire, record=["prediction/track", "motor/command",
                                                                  "reid/measurement", "template/template"]) as g:
            assert g.run_frames(60) == 60
            runs.append({t: g.payloads(*t.split("/")) for t in ("prediction/track", "motor/command",
                                                                 "reid/measurement", "template/template")})
            tracks = g.outputs("prediction", "track")
    assert len(runs[0]["prediction/track"]) == 60 and runs[0]["motor/command"]
    assert {"TRACKING", "OCCLUDED"} <= set(states(tracks))  # the run exercises more than straight tracking
    for topic, payloads in runs[0].items():
        assert payloads == runs[1][topic], f"{topic} differs between two runs"


def test_whole_graph_agrees_with_what_eval_runs():
    """`followbus eval` runs the graph's tracking nodes fed with frames and detections it publishes itself
    (evaluation/graph_follower.py); the graph with its own capture and detection nodes (motor left out: no
    odometry, v_ego = 0, as eval's graph check) must give the same boxes, bit for bit."""
    from followbus.evaluation.graph_follower import GraphFollower
    from followbus.evaluation.runner import open_sequence
    from followbus.vision.detectors import SimulatedDetector

    n = 60
    seq = open_sequence("scene:wall-occlusion", max_frames=n)
    detector, follower = SimulatedDetector(seed=0), GraphFollower(detector="simulated")  # the node's defaults
    expected, init_box = [], None
    for item in seq.frames():
        box, _ = follower.step(item.bgr, detector.detect(item.bgr, item.truth), item.t_ns, (0.0, 0.0),
                               None if init_box else item.gt_box)
        init_box = init_box or list(item.gt_box)
        expected.append(box)
    graph = _scene_graph(n, f"reid.init_box={init_box}")
    with InProcessGraph(graph, nodes=[n for n in graph.nodes if n != "motor"], record=["prediction/track"]) as g:
        g.run_frames(n)
        got = [None if t.box is None else tuple(float(v) for v in t.box) for t in g.outputs("prediction", "track")]
        prediction = g.status("prediction")["extra"]
    assert len(got) == n
    assert got == expected
    # Camera-motion compensation is in the graph: only frame 0 (egomotion's first message comes after that set
    # went out, bus/sync.py) has no transform; every later prior waited for it and was warped.
    assert prediction["sync_without_optional"] == 1 and prediction["sync_timeouts"] == 0
    assert prediction["priors_warped"] == n - 1


# --------------------------------------------------------------------------- runtime semantics


def _relay_graph(queue: int, policy: str):
    text = f"""
name: t
nodes:
  ticker: {{run: followbus.nodes.diagnostics, outputs: [tick]}}
  relay:
    run: followbus.nodes.diagnostics_relay
    inputs: {{tick: {{from: ticker/tick, queue: {queue}, policy: {policy}}}}}
    outputs: [tick]
  sink:
    run: followbus.nodes.diagnostics_sink
    inputs: {{tick: {{from: relay/tick, sync: none}}}}
"""
    return load_graph("<test>", text=text)


def _ticks(g: InProcessGraph, n: int) -> None:
    for k in range(n):
        g.inject("ticker/tick", stamped(Tick(value=k), k, g.now_ns + k * MS))


def test_drop_oldest_queue_keeps_the_newest_of_a_burst():
    with InProcessGraph(_relay_graph(1, "drop_oldest"), nodes=["relay", "sink"]) as g:
        _ticks(g, 3)  # a burst larger than the queue, before the relay gets to run
        g.deliver()
        assert [m.value for m in g.outputs("relay", "tick")] == [2]
        assert g.status("relay")["topics"]["fb/ticker/tick"]["drops"] == 2
        assert g.node("sink").received == 1


def test_block_queue_loses_nothing():
    with InProcessGraph(_relay_graph(1, "block"), nodes=["relay", "sink"]) as g:
        _ticks(g, 3)
        g.deliver()
        assert [m.value for m in g.outputs("relay", "tick")] == [0, 1, 2]
        assert g.node("sink").last_value == 2


def test_malformed_message_is_counted_and_dropped():
    with InProcessGraph(_relay_graph(4, "drop_oldest"), nodes=["relay", "sink"]) as g:
        g.inject_bytes("ticker/tick", b"not a followbus message")
        g.inject_bytes("ticker/tick", encode(stamped(Detections(), 0, g.now_ns)))  # the wrong type
        g.inject("ticker/tick", stamped(Detections(), 0, g.now_ns))  # the same, as a message (no bytes made)
        g.inject("ticker/tick", stamped(Tick(value=1), -5, g.now_ns))  # a header out of range
        _ticks(g, 1)
        g.deliver()
        assert g.status("relay")["topics"]["fb/ticker/tick"]["decode_errors"] == 4
        assert g.status("relay")["extra"]["handler_errors"] == 0
        assert [m.value for m in g.outputs("relay", "tick")] == [0]


def test_stamps_clock_follows_replay_hints():
    with InProcessGraph(tracking_graph(), nodes=["prediction"], clock="stamps") as g:
        box = (100.0, 60.0, 30.0, 80.0)
        t0 = EPOCH_NS
        g.hint("prediction", stamped(ReplayHint(skip=True), 1, t0 + DT_NS))  # the live run skipped frame 1
        g.inject("detection/detections", dets_msg(0, t0, box))
        g.inject("reid/measurement", measurement(0, t0, "TRACKING", box, init=True))
        g.inject("detection/detections", dets_msg(1, t0 + DT_NS, box))
        g.inject("detection/detections", dets_msg(2, t0 + 2 * DT_NS, box))
        g.deliver()
        priors = g.outputs("prediction", "prior")
        assert [p.header.frame_seq for p in priors] == [0, 2]
        assert priors[1].header.feedback["measurement"] == 0
        assert g.node("prediction").runtime.clock.now_ns() == t0 + 2 * DT_NS  # the node clock is the newest stamp


def test_a_node_that_cannot_start_is_an_error_not_an_exit():
    graph = load_graph("<test>", text="""
name: t
nodes:
  capture: {run: followbus.nodes.capture, outputs: [frame]}
  detection:
    run: followbus.nodes.detection
    inputs: {frame: capture/frame}
    outputs: [detections]
    params: {backend: simulated}
""")
    g = InProcessGraph(graph, nodes=["detection"])
    with pytest.raises(InProcessError, match="detection"):
        g.start()  # simulated detections need the ground_truth input: live, the node exits with status 1


def test_unknown_node_or_topic_is_refused():
    graph = tracking_graph()
    with pytest.raises(GraphError, match="no node named 'nope'"):
        InProcessGraph(graph, nodes=["nope"])
    with InProcessGraph(graph, nodes=["motor"]) as g, pytest.raises(ValueError, match="no topic"):
        g.inject("prediction/nope", _track(0, g.now_ns))


def test_detection_publishes_low_score_boxes_apart_from_its_detections():
    """The detection node (YOLOX-nano 640 on a real frame with a partly hidden person) publishes the boxes scoring
    in [low_score_threshold, score_threshold) as ``low_boxes``, and as ``boxes`` exactly what it published with
    no low boxes (so every consumer of ``boxes`` sees what it saw before); low_score_threshold = score_threshold
    publishes none."""
    import cv2

    from .conftest import SHARED

    img = SHARED / "data" / "sot" / "otb-human3" / "img" / "000002.jpg"
    if not img.is_file():
        pytest.skip(f"real data absent: {img}")
    bgr = cv2.imread(str(img))
    out = {}
    for low in (0.1, 0.3):
        graph = tracking_graph("detection.backend=yolox", "detection.input_size_px=640",
                               f"detection.low_score_threshold={low}")
        with InProcessGraph(graph, nodes=["detection"], record=["detection/detections"]) as g:
            g.inject("capture/frame", frame_msg(0, g.now_ns, bgr))
            g.deliver()
            (out[low],) = g.outputs("detection", "detections")
    with_low, without = out[0.1], out[0.3]
    assert np.array_equal(with_low.boxes, without.boxes) and len(without.boxes) >= 1
    assert (with_low.boxes[:, 4] >= 0.3).all() and without.low_boxes.shape == (0, 5)
    assert len(with_low.low_boxes) >= 1
    assert ((with_low.low_boxes[:, 4] >= 0.1) & (with_low.low_boxes[:, 4] < 0.3)).all()


def test_a_looping_scene_capture_replays_the_same_frames_without_reopening_its_source():
    """At the end of a pass a looping capture re-iterates a scene rather than re-opening it: re-opening
    redrew the scene's assets, a ~180 ms stall at every pass (300+ ms under load), which broke the latency
    bound of the chaos burners run once per 20 s."""
    graph = tracking_graph("capture.source=scene:wall-occlusion", "capture.fps=5", "capture.width_px=160",
                           "capture.height_px=120", "capture.loop=true")
    with InProcessGraph(graph, nodes=["capture"], record=["capture/frame"]) as g:
        g.start()
        source = g.node("capture").source
        n = len(source)
        assert g.run_frames(n + 3) == n + 3
        assert g.node("capture").source is source
        frames = g.outputs("capture", "frame")
    for k in range(3):
        assert frames[n + k].header.frame_seq == n + k  # numbering goes on across passes
        assert np.array_equal(frames[n + k].data, frames[k].data)
    spacing_ns = frames[1].header.stamp_ns - frames[0].header.stamp_ns
    assert frames[n].header.stamp_ns - frames[n - 1].header.stamp_ns == spacing_ns


def test_a_slow_detector_costs_no_feedback_wait():
    """Detections 110 ms after their frame, for one frame in three (a detector slower than the camera): every
    measurement still gets its template (the frame waits for it as long as re-ID waits) and re-ID never waits in
    vain for a template that will not come. With template's default 100 ms, frame sets expired before their
    measurement, no template went out, and re-ID's next set waited its whole 300 ms (chaos detector-delay-80ms:
    p99 capture->command 300 ms)."""
    box = (140, 80, 30, 80)
    graph = tracking_graph(f"reid.init_box={list(map(float, box))}")
    with InProcessGraph(graph, nodes=["egomotion", "prediction", "reid", "template"],
                        record=["reid/measurement", "template/template", "prediction/track"]) as g:
        t0 = g.now_ns
        events = []
        for k in range(30):
            stamp = t0 + k * DT_NS
            events.append((stamp, 0, "capture/frame", frame_msg(k, stamp, person_frame(box))))
            if k % 3 == 0:
                events.append((stamp + 110 * MS, 1, "detection/detections", dets_msg(k, stamp, box)))
        for t, _, topic, msg in sorted(events, key=lambda e: (e[0], e[1])):
            g.run_until(t)
            g.inject(topic, msg)
            g.deliver()
        g.run_for(1000 * MS)
        measurements = g.outputs("reid", "measurement")
        templates = g.outputs("template", "template")
        reid = g.status("reid")["extra"]
    assert [m.header.frame_seq for m in measurements] == list(range(0, 30, 3))
    assert [t.header.frame_seq for t in templates] == list(range(0, 30, 3))
    assert reid["sync_timeouts"] == 0 and reid["sync_feedback_fallbacks"] == 0, reid


def test_two_graphs_launched_from_one_directory_keep_their_own_template_file(tmp_path, monkeypatch):
    """Issue 25: graph.yaml's state_file was state/template.npz for every graph: a second graph (another
    namespace) launched from the same directory restored and overwrote the first one's template."""
    from pathlib import Path

    monkeypatch.chdir(tmp_path)
    paths = []
    for namespace in ("r2a", "r2b"):
        graph = load_graph(REPO / "graph.yaml")
        graph.namespace = namespace
        with InProcessGraph(graph, nodes=["template"]) as g:
            g.start()  # the node's setup
            paths.append(g.node("template")._state_path())
    assert paths == [Path("state/r2a/template.npz"), Path("state/r2b/template.npz")]


def test_a_reset_reid_keeps_its_one_learning_thread():
    """A node reset runs setup again (NodeHost, after on_frame keeps failing); re-ID's background learner is one
    thread per process, not one per reset."""
    with InProcessGraph(tracking_graph(), nodes=["reid"]) as g:
        g.start()
        node = g.node("reid")
        learner = node.learner
        threads = threading.active_count()
        for _ in range(3):
            node.setup()
        assert node.learner is learner and threading.active_count() == threads


def test_the_in_process_graph_times_each_node_on_its_own():
    """handler_s: each node's time on the messages delivered to it, what `followbus eval` reports per part."""
    from followbus.evaluation.graph_follower import GraphFollower

    follower = GraphFollower()
    frame = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    box = (60.0, 30.0, 20.0, 60.0)
    for k in range(3):
        _box, info = follower.step(frame, np.array([[*box, 0.9]], np.float32), k * 33_333_333,
                                   init_box=box if k == 0 else None)
    parts = info["part_ms"]
    assert {"egomotion", "prediction", "reid", "template"} <= set(parts)
    assert all(ms >= 0.0 for ms in parts.values()) and parts["reid"] > 0.0
    assert sum(follower.graph.handler_s.values()) > 0.0
    follower.close()
