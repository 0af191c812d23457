"""The single-target tracker's messages (seed 000): the Kalman prior, the re-ID measurement, the posterior track
and the appearance template, with the track states they share.

The algorithms (tracking/) read and write these types themselves: the prior is what prediction publishes and
re-ID gates against, a measurement is what prediction and template update consume.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import ClassVar

import numpy as np

from ..bus.schemas import Message, check_shape, require
from .box import box_array, centre_size_to_box, check_boxes


class TrackState(str, Enum):
    UNINITIALISED = "UNINITIALISED"  # no target chosen yet
    TRACKING = "TRACKING"
    OCCLUDED = "OCCLUDED"  # no acceptable match: Kalman update suspended, template frozen
    REACQUIRED = "REACQUIRED"  # first accepted frame(s) after OCCLUDED/LOST
    LOST = "LOST"  # occluded for longer than lost_after_ms; still searching


TRACK_STATES = frozenset(s.value for s in TrackState)


def mahalanobis_sq_from_cov(z: Sequence[float], centre: Sequence[float], S: np.ndarray) -> float:
    """(Z - Ẑ)ᵀ S⁻¹ (Z - Ẑ) of Eq. 8."""
    d = np.array([float(z[0]) - float(centre[0]), float(z[1]) - float(centre[1])])
    return float(d @ np.linalg.solve(S, d))


# Measurement sources that are detector boxes, of the whole frame or of the region re-detected around the prediction
# (seed 002 §3.2): the same association and identity rules apply to both, and both measure the person's size.
DETECTOR_SOURCES = ("detection", "redetection")


@dataclass
class Prior(Message):
    """Kalman prior for a frame (seed 000 Eq. 4-8): what re-identification gates and scores against.

    ``state`` X̂⁻ (x, y, vx, vy; px, px/s), ``size`` the smoothed (w, h), ``covariance`` the 4x4 P⁻,
    ``innovation_cov`` the 2x2 S = H P⁻ Hᵀ + R used by the gate (Eq. 8), ``box`` the predicted box."""

    TYPE: ClassVar[str] = "Prior"
    ADDED: ClassVar[frozenset[str]] = frozenset({"likeliest_box", "locates_person"})
    initialised: bool = False
    state: np.ndarray = field(default_factory=lambda: np.zeros(4))  # x, y, vx, vy (px, px/s)
    size: np.ndarray = field(default_factory=lambda: np.zeros(2))  # w, h (px)
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((4, 4)))  # P_k
    innovation_cov: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))  # S = H P H^T + R
    gate_chi2: float = 9.488
    box: np.ndarray | None = None
    # The box of the likeliest motion model (tracking/kalman.py's IMM; None: one model, the ``box``): the state, its
    # covariance and ``box`` are the models' mixture, which can lie between two places the person may be and be at
    # neither, so a coasting output is this one.
    likeliest_box: np.ndarray | None = None
    # The predicted box more likely overlaps the person than not (KalmanParams.occluded_output_min_overlap_probability
    # on overlap_probability): a coast worth following, and where a lone box is the person's (tracking/reid.py).
    locates_person: bool = True

    @classmethod
    def of_filter(cls, t_ns: int, state: np.ndarray, size: Sequence[float], covariance: np.ndarray,
                  innovation_cov: np.ndarray, gate_chi2: float) -> Prior:
        """The prior of a filter at stamp ``t_ns`` (its box follows from the state's centre and the size)."""
        centre = (float(state[0]), float(state[1]))
        prior = cls(initialised=True, state=np.asarray(state, dtype=np.float64),
                    size=np.asarray(size, dtype=np.float64), covariance=np.asarray(covariance, dtype=np.float64),
                    innovation_cov=np.asarray(innovation_cov, dtype=np.float64), gate_chi2=float(gate_chi2),
                    box=box_array(centre_size_to_box(*centre, float(size[0]), float(size[1]))))
        prior.header.stamp_ns = int(t_ns)
        return prior

    @property
    def centre(self) -> tuple[float, float]:
        return (float(self.state[0]), float(self.state[1]))

    @property
    def centre_std_px(self) -> float:
        """The centre's 1 σ along its most uncertain direction (P_k's position block), px."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.covariance[:2, :2]).max()), 0.0))

    def coasting_box(self) -> np.ndarray | None:
        """The box output while the target is OCCLUDED: the likeliest motion model's prediction."""
        return self.box if self.likeliest_box is None else self.likeliest_box

    def overlap_probability(self) -> float:
        """The probability that the predicted box still overlaps the person's, under P_k's position block: that the
        centres are less than one box width and height apart, erf(w / (√2 σx)) · erf(h / (√2 σy)) (its marginals
        along x and y)."""
        sx, sy = (math.sqrt(max(float(self.covariance[i, i]), 1e-12)) for i in (0, 1))
        w, h = float(self.size[0]), float(self.size[1])
        return math.erf(w / (math.sqrt(2.0) * sx)) * math.erf(h / (math.sqrt(2.0) * sy))

    @property
    def velocity_px_s(self) -> tuple[float, float]:
        return (float(self.state[2]), float(self.state[3]))

    def mahalanobis_sq(self, z: Sequence[float]) -> float:
        return mahalanobis_sq_from_cov(z, self.centre, self.innovation_cov)

    def check(self) -> None:
        for name, shape in (("state", (4,)), ("covariance", (4, 4)), ("innovation_cov", (2, 2))):
            check_shape(self, name, getattr(self, name), shape)
        check_boxes(self, "box", "likeliest_box")


@dataclass
class Measurement(Message):
    """Re-identification result for a frame (seed 000 Algorithm 1), stamped with the frame's capture."""

    TYPE: ClassVar[str] = "Measurement"
    ADDED: ClassVar[frozenset[str]] = frozenset({"detector_score", "coasting_colours_seen"})
    state: str = "LOST"  # a TrackState value
    accepted: bool = False
    secure: bool = False
    box: np.ndarray | None = None  # the accepted box (Alg. 1 line 11)
    best_box: np.ndarray | None = None  # argmax M_fuse, even when rejected
    # Where the chosen box came from: "detection", "redetection", "low-score" or "motion"; on an initialisation frame
    # "init" (a new target, the given box or a motion blob: the template restarts from it), "nearest" (a new target:
    # the detection nearest the image bottom-centre), "template" (the detection matching a kept template), "prior"
    # (the gated detection nearest a kept prior) or "last" (the detection on re-ID's last accepted box).
    source: str = ""
    m_fuse: float = 0.0
    s_color: float = 0.0
    s_geo: float = 0.0
    omega: float = 0.0
    c_t: float = 0.0
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))  # x,y,w,h,m_fuse
    candidate_sources: list[str] = field(default_factory=list)
    candidate_hist: np.ndarray | None = None  # H-S histogram C* of the chosen candidate
    init_box: np.ndarray | None = None  # set on the frame the target was initialised
    # The detector's score of the box the target was last accepted on (-1: none, or not a detector box): what seed
    # 002 §3.2's search scale doubts (tracking/redetection.py search_scale).
    detector_score: float = -1.0
    # While OCCLUDED: re-ID saw the target's colours at the coasting box (Prior.coasting_box), and no one else's
    # detector box on it (ReIdentifier._coasting_colours_seen): the target is there, unseen by the detector.
    coasting_colours_seen: bool = False

    def check(self) -> None:
        require(self.state in TRACK_STATES, self, f"unknown state {self.state!r}")
        check_boxes(self, "box", "best_box", "init_box")


@dataclass
class Track(Message):
    """Posterior target track published by prediction after each measurement."""

    TYPE: ClassVar[str] = "Track"
    state: str = "LOST"  # a TrackState value
    box: np.ndarray | None = None  # the tracker's output: accepted box, predicted box while OCCLUDED, else None
    filtered_box: np.ndarray | None = None  # Kalman posterior box
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))  # px/s
    measured: bool = False  # this frame's measurement updated the filter

    def check(self) -> None:
        require(self.state in TRACK_STATES, self, f"unknown state {self.state!r}")
        check_boxes(self, "box", "filtered_box")


@dataclass
class Template(Message):
    """Reference appearance model M and its learning rate eta_k (seed 000 Eq. 9-10)."""

    TYPE: ClassVar[str] = "Template"
    initialised: bool = False
    hist: np.ndarray | None = None  # bins_h x bins_s, sums to 1
    eta: float = 0.0
    p_specular: float = 0.0
