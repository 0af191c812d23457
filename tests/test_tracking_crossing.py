"""Issue 22 (otb-human3, uav-group1-3 with the live detector): a person crosses in front of the target, the detector
drops the hidden target, and the lone detection left in the gate is the other person. The classifier told the two
apart a frame earlier; colour (same clothes) cannot. The identity veto must reject that detection (the target goes
OCCLUDED) instead of taking it unscored, and must not veto while the classifier has not learnt to separate people."""

from __future__ import annotations

import numpy as np

from followbus.msgs.tracking import Prior
from followbus.tracking.params import ReidParams
from followbus.tracking.reid import Candidate, ReIdentifier, TrackState

TARGET = (100.0, 100.0, 40.0, 100.0)
OTHER = (130.0, 105.0, 40.0, 100.0)
THIRD = (60.0, 100.0, 40.0, 100.0)


class ScriptedClassifier:
    """Stands in for the learned appearance: a fixed classifier score per box."""

    ready = True

    def __init__(self, scores: dict[tuple[float, ...], float]) -> None:
        self.scores = scores

    def score(self, embs: np.ndarray) -> np.ndarray:
        return np.array([self.scores[tuple(float(v) for v in e)] for e in embs])


def tracking_reid(scores: dict[tuple[float, ...], float]) -> tuple[ReIdentifier, list[int]]:
    reid = ReIdentifier(ReidParams())
    reid.state = TrackState.TRACKING
    reid.identity = ScriptedClassifier(scores)
    embedded: list[int] = []

    def embed(frame: np.ndarray, boxes: list) -> np.ndarray:
        embedded.append(len(boxes))
        return np.array(boxes, dtype=np.float64)

    reid._embed = embed
    return reid, embedded


def candidate(box: tuple[float, ...], m_fuse: float) -> Candidate:
    return Candidate(box=box, source="detection", maha_sq=0.5, s_color=m_fuse, s_geo=m_fuse, m_fuse=m_fuse)


def decide(reid: ReIdentifier, candidates: list[Candidate]) -> tuple[tuple[float, ...], bool]:
    reid._note_crowd(len(candidates))
    best = max(candidates, key=lambda c: c.m_fuse)
    prior = Prior.of_filter(t_ns=0, state=np.array([120.0, 150.0, 0.0, 0.0]), size=(40.0, 100.0),
                  covariance=np.eye(4) * 100.0, innovation_cov=np.eye(2) * 100.0, gate_chi2=9.488)
    chosen, accepted = reid._identity_decision(np.zeros((4, 4, 3), np.uint8), candidates, best, prior)
    return chosen.box, accepted


def test_the_lone_other_person_after_a_crossing_is_rejected() -> None:
    reid, _ = tracking_reid({TARGET: 0.68, OTHER: 0.2, THIRD: 0.1})
    assert decide(reid, [candidate(TARGET, 0.90), candidate(OTHER, 0.91)]) == (TARGET, True)  # told apart
    # The target is hidden behind the other person: only their detection is left, as well coloured as the target's.
    assert decide(reid, [candidate(OTHER, 0.93)]) == (OTHER, False)
    # ... and when both are in the gate but neither looks like the target, neither is taken either.
    assert decide(reid, [candidate(OTHER, 0.93), candidate(THIRD, 0.90)]) == (OTHER, False)
    assert decide(reid, [candidate(TARGET, 0.94)]) == (TARGET, True)  # the target itself comes back


def test_no_veto_from_a_classifier_that_never_told_the_people_apart() -> None:
    reid, _ = tracking_reid({TARGET: 0.33, OTHER: 0.30})  # early, or look-alikes: everyone scores alike
    decide(reid, [candidate(TARGET, 0.90), candidate(OTHER, 0.88)])
    assert decide(reid, [candidate(TARGET, 0.92)]) == (TARGET, True)


def test_a_lone_detection_away_from_any_crowd_is_not_scored() -> None:
    reid, embedded = tracking_reid({TARGET: 0.1})
    assert decide(reid, [candidate(TARGET, 0.92)]) == (TARGET, True)
    assert embedded == []  # no descriptor cost on the common frame


def test_the_veto_ends_with_the_crowd() -> None:
    reid, _ = tracking_reid({TARGET: 0.7, OTHER: 0.2})
    decide(reid, [candidate(TARGET, 0.90), candidate(OTHER, 0.88)])
    for _ in range(reid.params.identity_veto_after_crowd_frames + 1):
        reid._note_crowd(1)
    assert decide(reid, [candidate(OTHER, 0.93)]) == (OTHER, True)  # colour + geometry alone again
