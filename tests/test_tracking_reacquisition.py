"""Re-acquisition on accumulated evidence (tracking/reacquisition.py) and its use by re-ID (tracking/reid.py)."""

from __future__ import annotations

import numpy as np

from followbus.msgs.box import box_tuple
from followbus.msgs.tracking import Prior, TrackState
from followbus.tracking.params import ReidParams
from followbus.tracking.reacquisition import BystanderTracks, PersonTrack, ReacquisitionEvidence
from followbus.tracking.reid import ReIdentifier


def test_a_person_continues_where_its_velocity_carries_it():
    walker = PersonTrack((100.0, 100.0, 40.0, 100.0), 0).moved_to((130.0, 100.0, 40.0, 100.0), 1)
    assert walker.velocity == (30.0, 0.0)
    assert walker.continues((160.0, 102.0, 40.0, 100.0), 2, 0.5)  # on course
    assert walker.continues((220.0, 100.0, 40.0, 100.0), 4, 0.5)  # on course after a gap
    assert not walker.continues((130.0, 100.0, 40.0, 100.0), 2, 0.5 * 0.5)  # stopped dead: 30 px off, 25 allowed
    assert not walker.continues((160.0, 100.0, 40.0, 160.0), 2, 0.5)  # another size: someone else


def test_evidence_needs_enough_frames_of_one_person_within_the_window():
    evidence = ReacquisitionEvidence(frames_needed=3, window_frames=4, max_step_heights=0.5)
    assert not evidence.observe((100.0, 100.0, 40.0, 100.0), 1)
    assert not evidence.observe((110.0, 100.0, 40.0, 100.0), 2)
    assert evidence.observe((120.0, 100.0, 40.0, 100.0), 3)
    evidence.reset()
    assert not evidence.observe((100.0, 100.0, 40.0, 100.0), 1)
    assert not evidence.observe((600.0, 100.0, 40.0, 100.0), 2)  # someone else far away: counting starts again
    assert evidence.count == 1
    assert not evidence.observe((600.0, 100.0, 40.0, 100.0), 3)
    assert not evidence.observe((600.0, 100.0, 40.0, 100.0), 9)  # beyond the window: the old frames no longer count
    assert evidence.count == 1


def test_only_people_seen_beside_the_target_are_bystanders():
    tracks = BystanderTracks(max_age_frames=5, max_step_heights=0.5)
    target, other = (100.0, 100.0, 40.0, 100.0), (400.0, 100.0, 40.0, 100.0)
    flags = tracks.link([target, other], 1)
    tracks.adopt([target, other], flags, target, 1)  # the target tracked: the other is a bystander
    assert tracks.link([(420.0, 100.0, 40.0, 100.0)], 2) == [True]
    assert tracks.link([(440.0, 100.0, 40.0, 100.0), (800.0, 90.0, 40.0, 100.0)], 3) == [True, False]
    assert tracks.link([(700.0, 100.0, 40.0, 100.0)], 20) == [False]  # unseen too long: forgotten


def _prior(box: tuple[float, float, float, float], std_px: float) -> Prior:
    x, y, w, h = box
    cov = np.diag([std_px**2, std_px**2, 1e4, 1e4])
    return Prior.of_filter(0, np.array([x + w / 2, y + h / 2, 0.0, 0.0]), (w, h), cov,
                           cov[:2, :2] + 64.0 * np.eye(2), 9.488)


def _frame_with(boxes_colours: list[tuple[tuple[float, ...], tuple[int, int, int]]],
                legs: tuple[int, int, int] | None = None) -> np.ndarray:
    """Boxes of one colour each on grey; ``legs``: the first box's lower half in that colour."""
    frame = np.full((480, 640, 3), 90, np.uint8)
    for (x, y, w, h), bgr in boxes_colours:
        frame[int(y):int(y + h), int(x):int(x + w)] = bgr
    if legs is not None:
        x, y, w, h = boxes_colours[0][0]
        frame[int(y + h / 2):int(y + h), int(x):int(x + w)] = legs
    return frame


def _reid_lost_in_a_wide_gate(params: ReidParams) -> tuple[ReIdentifier, np.ndarray]:
    """A re-ID that has tracked a red person at the left with a grey one at the right, then lost them both."""
    reid = ReIdentifier(params)
    red, grey = (60.0, 200.0, 40.0, 100.0), (500.0, 200.0, 40.0, 100.0)
    frame = _frame_with([(red, (0, 0, 200)), (grey, (60, 60, 60))])
    dets = np.array([[*red, 0.9], [*grey, 0.9]], np.float32)
    first = reid.step(frame, dets, None, None, 0, init_box=red)
    template = first.candidate_hist
    for k in range(1, 4):
        reid.step(frame, dets, _prior(red, 10.0), template, k * 33_000_000)
    t = 4 * 33_000_000
    for _ in range(3):  # nobody detected in a still image: the target is occluded
        assert not reid.step(frame, np.zeros((0, 5), np.float32), _prior(red, 10.0), template, t).accepted
        t += 33_000_000
    assert reid.state is TrackState.OCCLUDED
    return reid, template


def test_a_returning_target_far_from_the_prior_is_reacquired_on_evidence_and_a_bystander_never():
    params = ReidParams(learned_appearance=False, reacquire_frames=4)
    reid, template = _reid_lost_in_a_wide_gate(params)
    far_prior = _prior((60.0, 200.0, 40.0, 100.0), 400.0)  # the gate covers the image: both are candidates
    accepted_at = None
    for k in range(8):
        red, grey = (300.0 + 5 * k, 150.0, 40.0, 100.0), (520.0 + 5 * k, 200.0, 40.0, 100.0)
        # The returning target shows other legs (S_color ~0.7: the target's colours, M_fuse below T_reid).
        frame = _frame_with([(red, (0, 0, 200)), (grey, (60, 60, 60))], legs=(200, 0, 0))
        result = reid.step(frame, np.array([[*red, 0.9], [*grey, 0.9]], np.float32), far_prior, template,
                           (8 + k) * 33_000_000)
        if result.accepted:
            accepted_at = k
            assert box_tuple(result.box) == red  # the target, never the grey bystander
            break
    assert accepted_at == params.reacquire_frames - 1


def test_without_evidence_the_same_target_is_never_reacquired():
    params = ReidParams(learned_appearance=False, reacquire_frames=4, reacquire_on_evidence=False)
    reid, template = _reid_lost_in_a_wide_gate(params)
    far_prior = _prior((60.0, 200.0, 40.0, 100.0), 400.0)
    for k in range(8):
        red, grey = (300.0 + 5 * k, 150.0, 40.0, 100.0), (520.0 + 5 * k, 200.0, 40.0, 100.0)
        frame = _frame_with([(red, (0, 0, 200)), (grey, (60, 60, 60))], legs=(200, 0, 0))
        assert not reid.step(frame, np.array([[*red, 0.9], [*grey, 0.9]], np.float32), far_prior, template,
                             (8 + k) * 33_000_000).accepted


def test_a_look_alike_seen_beside_the_target_is_never_reacquired_on_evidence():
    params = ReidParams(learned_appearance=False, reacquire_frames=4)
    reid = ReIdentifier(params)
    target, twin = (60.0, 200.0, 40.0, 100.0), (300.0, 200.0, 40.0, 100.0)
    frame = _frame_with([(target, (0, 0, 200)), (twin, (0, 0, 200))])
    template = reid.step(frame, np.array([[*target, 0.9], [*twin, 0.9]], np.float32), None, None, 0,
                         init_box=target).candidate_hist
    t = 33_000_000
    for _ in range(3):  # tracked, the twin beside it
        assert reid.step(frame, np.array([[*target, 0.9], [*twin, 0.9]], np.float32), _prior(target, 10.0),
                         template, t).accepted
        t += 33_000_000
    far_prior = _prior(target, 400.0)
    for k in range(10):  # the target gone; the twin walks on, with other legs now (below T_reid)
        twin = (300.0 + 5 * k, 200.0, 40.0, 100.0)
        frame = _frame_with([(twin, (0, 0, 200))], legs=(200, 0, 0))
        assert not reid.step(frame, np.array([[*twin, 0.9]], np.float32), far_prior, template, t).accepted
        t += 33_000_000


def test_a_bystander_hidden_with_someone_in_one_box_is_unsure_of_whom_it_follows_after():
    """Two people in one box too tall for the bystander alone: the track may come out of it on either, so the box it
    continues on is unsure; a track that is merely not detected for a frame stays sure."""
    def tracks_after(middle: list[tuple[float, float, float, float]], merges_unsure: bool = True) -> BystanderTracks:
        tracks = BystanderTracks(max_age_frames=5, max_step_heights=0.5, merges_unsure=merges_unsure)
        target, other = (100.0, 100.0, 40.0, 100.0), (300.0, 100.0, 40.0, 100.0)
        tracks.adopt([target, other], tracks.link([target, other], 1), target, 1)
        tracks.link(middle, 2)
        return tracks

    merged = [(250.0, 0.0, 120.0, 210.0)]  # covers the bystander's place, twice their height
    came_out = [(320.0, 100.0, 40.0, 100.0)]
    after_merge = tracks_after(merged)
    assert after_merge.link(came_out, 3) == [True] and after_merge.unsure == [True]
    missed = tracks_after([])  # not detected on frame 2: nothing says whom it follows changed
    assert missed.link(came_out, 3) == [True] and missed.unsure == [False]
    elsewhere = tracks_after([(500.0, 0.0, 120.0, 210.0)])  # two people in one box, but not where the bystander is
    assert elsewhere.link(came_out, 3) == [True] and elsewhere.unsure == [False]
    switched_off = tracks_after(merged, merges_unsure=False)
    assert switched_off.link(came_out, 3) == [True] and switched_off.unsure == [False]


def test_evidence_on_an_unsure_bystander_needs_twice_the_frames():
    evidence = ReacquisitionEvidence(frames_needed=3, window_frames=4, max_step_heights=0.5)
    assert not any(evidence.observe((100.0 + 5 * k, 100.0, 40.0, 100.0), k, scale=2) for k in range(1, 6))
    assert evidence.observe((130.0, 100.0, 40.0, 100.0), 6, scale=2)  # 6 of 8 frames
    evidence.reset()
    counted = [evidence.observe((100.0 + 5 * k, 100.0, 40.0, 100.0), k, scale=2) for k in (1, 3, 5, 7, 9, 11, 13)]
    assert not any(counted)  # one frame in two: never 6 within 8


def _lost_beside_a_bystander_who_then_merges_with_it(params: ReidParams) -> tuple[ReIdentifier, np.ndarray, int]:
    """A red target tracked beside a grey bystander; then both hidden, and one box too tall for either covers the
    bystander's place (the two in one box); then only the target comes out, where the bystander's track resumes."""
    reid = ReIdentifier(params)
    red, grey = (200.0, 200.0, 40.0, 100.0), (300.0, 200.0, 40.0, 100.0)
    frame = _frame_with([(red, (0, 0, 200)), (grey, (60, 60, 60))])
    dets = np.array([[*red, 0.9], [*grey, 0.9]], np.float32)
    template = reid.step(frame, dets, None, None, 0, init_box=red).candidate_hist
    t = 33_000_000
    for _ in range(3):
        assert reid.step(frame, dets, _prior(red, 10.0), template, t).accepted
        t += 33_000_000
    both = (195.0, 100.0, 150.0, 210.0)
    frame = _frame_with([(both, (0, 0, 120))])
    reid.step(frame, np.array([[*both, 0.9]], np.float32), _prior(red, 10.0), template, t)
    return reid, template, t + 33_000_000


def test_the_target_taken_for_a_bystander_after_a_merge_is_reacquired_on_twice_the_evidence():
    params = ReidParams(learned_appearance=False, reacquire_frames=4)
    reid, template, t = _lost_beside_a_bystander_who_then_merges_with_it(params)
    far_prior = _prior((200.0, 200.0, 40.0, 100.0), 400.0)
    accepted_at = None
    for k in range(12):  # the target comes out where the bystander was; its legs changed (below T_reid)
        red = (300.0 + 3 * k, 200.0, 40.0, 100.0)
        frame = _frame_with([(red, (0, 0, 200))], legs=(200, 0, 0))
        if reid.step(frame, np.array([[*red, 0.9]], np.float32), far_prior, template, t).accepted:
            accepted_at = k
            break
        t += 33_000_000
    assert accepted_at == 2 * params.reacquire_frames  # the first frame finds the target gone, then twice the evidence


def test_without_unsure_bystanders_the_target_taken_for_one_is_never_reacquired():
    params = ReidParams(learned_appearance=False, reacquire_frames=4, unsure_bystanders_after_merge=False)
    reid, template, t = _lost_beside_a_bystander_who_then_merges_with_it(params)
    far_prior = _prior((200.0, 200.0, 40.0, 100.0), 400.0)
    for k in range(12):
        red = (300.0 + 3 * k, 200.0, 40.0, 100.0)
        frame = _frame_with([(red, (0, 0, 200))], legs=(200, 0, 0))
        assert not reid.step(frame, np.array([[*red, 0.9]], np.float32), far_prior, template, t).accepted
        t += 33_000_000


def test_just_reacquired_on_evidence_the_person_it_followed_is_held_under_t_reid():
    """The frame after a re-acquisition on evidence the prior has one measurement: the returning target's next box,
    still under T_reid, is taken while it continues the person the evidence followed; without the hold it is not."""
    for hold in (True, False):
        params = ReidParams(learned_appearance=False, reacquire_frames=4, reacquire_hold_on_evidence=hold)
        reid, template = _reid_lost_in_a_wide_gate(params)
        far_prior = _prior((60.0, 200.0, 40.0, 100.0), 400.0)
        results = []
        for k in range(params.reacquire_frames + 1):
            red, grey = (300.0 + 5 * k, 150.0, 40.0, 100.0), (520.0 + 5 * k, 200.0, 40.0, 100.0)
            frame = _frame_with([(red, (0, 0, 200)), (grey, (60, 60, 60))], legs=(200, 0, 0))
            results.append(reid.step(frame, np.array([[*red, 0.9], [*grey, 0.9]], np.float32), far_prior, template,
                                     (8 + k) * 33_000_000))
        assert results[-2].accepted  # re-acquired on evidence
        assert results[-1].accepted == hold
        if hold:
            assert box_tuple(results[-1].box) == red


def test_the_classifier_makes_the_best_clear_where_colours_tie():
    """Two people in the target's colours come back far from the prior, within identity_margin of each other in
    M_fuse: evidence is never clear on colour alone. The classifier, trained on the target and on the other one
    (real OSNet descriptors of these crops), tells them apart: the target is re-acquired."""
    from followbus.tracking.learned_appearance import load_embedder

    if load_embedder() is None:
        raise AssertionError("models/osnet_x0_25_msmt17.onnx ships with the repository")
    for breaks_ties in (True, False):
        params = ReidParams(reacquire_frames=4, reacquire_classifier_breaks_ties=breaks_ties)
        reid = ReIdentifier(params)
        red = (60.0, 200.0, 40.0, 100.0)
        frame = _frame_with([(red, (0, 0, 200))])
        template = reid.step(frame, np.array([[*red, 0.9]], np.float32), None, None, 0, init_box=red).candidate_hist
        for k in range(1, 4):  # tracked alone: nobody seen beside it (no bystander)
            assert reid.step(frame, np.array([[*red, 0.9]], np.float32), _prior(red, 10.0), template,
                             k * 33_000_000).accepted
        for k in range(4, 7):  # then hidden
            reid.step(frame, np.zeros((0, 5), np.float32), _prior(red, 10.0), template, k * 33_000_000)
        far_prior = _prior(red, 400.0)

        def scene(k: int) -> tuple[np.ndarray, tuple[float, ...], tuple[float, ...]]:
            target, other = (200.0 + 5 * k, 150.0, 40.0, 100.0), (420.0 + 5 * k, 150.0, 40.0, 100.0)
            # Both in the target's red with other (blue) legs now: S_color ~0.7, M_fuse under T_reid, a tie.
            frame = _frame_with([(target, (0, 0, 200)), (other, (0, 0, 200))], legs=(200, 0, 0))
            frame[200:250, int(other[0]):int(other[0] + 40)] = (200, 0, 0)
            frame[160:170, int(target[0]):int(target[0] + 40)] = (0, 200, 200)  # the target's yellow cap
            frame[160:170, int(other[0]):int(other[0] + 40)] = (200, 200, 0)  # the other one's cyan cap
            return frame, target, other

        frame, target, other = scene(0)
        embs = reid._embed(frame, [target, other])
        reid.identity.reset()
        for _ in range(5):
            reid.identity.add(embs[0], embs[1:])
        accepted = None
        for k in range(8):
            frame, target, other = scene(k)
            result = reid.step(frame, np.array([[*target, 0.9], [*other, 0.9]], np.float32), far_prior, template,
                               (8 + k) * 33_000_000)
            if result.accepted:
                accepted = box_tuple(result.box)
                break
        assert accepted == (target if breaks_ties else None)
