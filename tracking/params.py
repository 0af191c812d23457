"""Parameters of the seed-000 target tracker (paper Table 1 plus documented additions), one class per node.

Each tracking node reads its own class and nothing else, so a setting a node never reads is an unknown
parameter of that node (graph validation names its file:line): :class:`KalmanParams` is the prediction node's
(tracking/kalman.py), :class:`ReidParams` the re-ID node's (tracking/reid.py), :class:`TemplateParams` the
template node's (tracking/template.py). Every default is written once, here: a value two nodes read (Δt, the
histogram's bins, the update-suspension switch) is a field of a small base class both inherit, not a copy.

Table 1 values are marked "Table 1"; everything else is not given by the paper and is chosen here, each choice
explained next to its field. Pixel values assume the paper's 1280x720 camera; the H/S/V thresholds use OpenCV's
8-bit HSV scale (H 0-179, S,V 0-255).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any


class InvalidParam(ValueError):
    """A parameter value out of its range; ``key`` names the parameter, so graph validation points at its line."""

    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(message)


def check_ranges(params: Any, *, positive: Iterable[str] = (), non_negative: Iterable[str] = (),
                 unit_interval: Iterable[str] = ()) -> None:
    """Raise InvalidParam for the first named field of ``params`` outside its range."""
    what = type(params).__name__
    rules = ((positive, lambda v: v > 0, "> 0"), (non_negative, lambda v: v >= 0, ">= 0"),
             (unit_interval, lambda v: 0.0 <= v <= 1.0, "in [0, 1]"))
    for names, holds, bound in rules:
        for name in names:
            value = getattr(params, name)
            if not holds(value):
                raise InvalidParam(name, f"{what}.{name} must be {bound}, got {value!r}")


def fields_of(cls: type) -> frozenset[str]:
    """The parameter names a params class declares."""
    return frozenset(f.name for f in dataclasses.fields(cls))


# --- shared by two nodes: each default once ------------------------------------------------------


@dataclass
class _FramePeriod:
    dt_ms: float = 33.0  # Table 1 Δt (Eq. 5): the frame period assumed when no previous stamp exists


@dataclass
class _ColourHistogram:
    # Table 1 Bins_H x Bins_S: hue and saturation quantisation of the H-S histogram (§2.2.1). Re-ID's S_color and
    # the template's M must use the same bins.
    bins_h: int = 16
    bins_s: int = 8


@dataclass
class _UpdateSuspension:
    # Ablation switch (paper Table 6): False: the Kalman filter and the template also update on a rejected best
    # candidate.
    suspend_updates: bool = True


@dataclass
class SearchScaleParams:
    """Seed 002 §3.2's adaptive search scale k (tracking/redetection.py search_scale), read by re-ID for its gate
    (χ² × k²) and by the redetection node for the side of its region: 1 for a slow target last seen on a confident
    detection, gate_scale_max when it moves fast in the image (gate_fast_height_fraction of its height a frame or
    more) or its last detection was weak (score gate_low_score or less; gate_high_score or more is confident)."""

    adaptive_gate: bool = True
    gate_scale_max: float = 1.5  # the seed's k in [1, 1.5]
    gate_fast_height_fraction: float = 0.05
    gate_high_score: float = 0.7
    gate_low_score: float = 0.3


# --- prediction ----------------------------------------------------------------------------------


@dataclass
class KalmanParams(_FramePeriod, _UpdateSuspension):
    """What the prediction node's constant-velocity Kalman filter reads (seed 000 Eq. 4-8, seed 002 §3.3)."""

    gate_chi2: float = 9.488  # Table 1 χ²_p of the Mahalanobis gate (Eq. 8); re-ID gates with the prior's
    # Kalman process noise (white acceleration, Eq. 4 W_k): a walking person at 2-4 m changes
    # image velocity by a few hundred px/s within a second at 1280x720.
    accel_std_px_s2: float = 500.0
    # R0 of Eq. 7: detector centre jitter ~8 px (1 σ) on person boxes at 1280x720.
    r0_px2: float = 64.0
    # κ of Eq. 7: at 1 m/s ego speed chassis vibration adds ~20 px (1 σ) of centre jitter.
    kappa_px2_per_mps2: float = 400.0
    # Initial velocity uncertainty (the first box carries no velocity information).
    init_velocity_std_px_s: float = 300.0
    # Box size (w, h) is smoothed separately from the centre filter: w,h ← (1-a)·w,h + a·z_wh.
    size_smoothing: float = 0.3
    # Seed 002 §3.3 (optical-flow-corrected Kalman): warp the prior by the frame-to-frame image motion
    # measured on the background (tracking/egomotion.py) before gating, so a panning, turning or zooming
    # camera does not carry the target out of a gate that is only right in a still image. graph.yaml runs
    # the egomotion node that measures it; `followbus eval --ablations` scores "followbus w/o camera-motion
    # compensation".
    camera_motion_compensation: bool = True
    # With compensation, a second motion model beside it (tracking/kalman.py Predictor, an IMM): the target keeping
    # its course in the image whatever the camera does, as under a camera that follows it (a robot turning towards
    # the person, a drone tracking a boat). The models' probabilities switch by model_switch_probability a frame.
    image_motion_model: bool = True
    model_switch_probability: float = 0.05
    # The IMM's mixing (each model restarting from the mixture of all) on frames with no measurement. Mixing moves
    # each model's state some 5 % a frame towards the other's, so after a second of coasting the "image" model
    # carries the "scene" model's velocity (otb-diving 93-125: -25 px/s became -47, and the next coast rose 20-50 px
    # off the tumbling diver). With no measurement nothing says which model is right: False keeps their states
    # apart while coasting (the probabilities still relax towards even, and the prior is still their mixture).
    mix_models_while_coasting: bool = False
    # A re-lock after a coast of at least relock_velocity_after_coast_ms takes as each model's velocity the
    # displacement between the last measured centre (carried by the camera's motion in the "scene" model) and the
    # new one over the time between them (OC-SORT's observation-centric re-update, seed 002 ref. 32): the velocity
    # the filter carried through the coast is that of a second ago, and one re-lock corrects it by only a little.
    # Shorter gaps keep the filter's velocity: over one missed frame the displacement is mostly detector jitter.
    # 0: never.
    relock_velocity_after_coast_ms: float = 500.0
    # Issue 22: the camera motion's uncertainty (egomotion's std_px) widens the prior's position covariance by
    # std² (and so the gate); a fit more doubtful than camera_motion_doubt_px does not move a coasting prior
    # (no detection matched on the previous frame), it widens it by the displacement it would have applied.
    # (A frame without a transform is not widened: whether one came in time depends on live timing.)
    camera_motion_uncertainty: bool = True
    camera_motion_doubt_px: float = 4.0
    # While OCCLUDED the output is the coasting prediction (seed 000 §2.3) only while it more likely overlaps the
    # person than not: the prior's position covariance puts the person's box in touch with it with at least this
    # probability (Prior.overlap_probability). Past it the box is as likely on nobody, or on a neighbour, as on the
    # person (a wrong re-lock is an output not touching the target), so none is output (the controller stops; the
    # gate keeps searching). 0: always output it.
    occluded_output_min_overlap_probability: float = 0.5

    def __post_init__(self) -> None:
        check_ranges(self, positive=("dt_ms", "gate_chi2", "r0_px2", "camera_motion_doubt_px"),
                     non_negative=("accel_std_px_s2", "kappa_px2_per_mps2", "init_velocity_std_px_s",
                                   "relock_velocity_after_coast_ms"),
                     unit_interval=("size_smoothing", "model_switch_probability",
                                    "occluded_output_min_overlap_probability"))


# --- re-ID ---------------------------------------------------------------------------------------


@dataclass
class ReidParams(_FramePeriod, _ColourHistogram, SearchScaleParams):
    """What the re-ID node's Algorithm 1 reads (seed 000 Alg. 1 with seeds 001 and 002)."""

    diff_threshold: int = 25  # Table 1 Thresh_diff: frame-difference grey-level threshold (§2.1)
    morph_kernel_px: int = 5  # Table 1 K_morph: 5x5 morphology kernel for motion ROIs (§2.1)
    # Table 1 Thresh_reid on M_fuse (Alg. 1 line 9). Read on every decision (tracking/reid.py): followbus param set
    # changes it on the next frame.
    reid_threshold: float = dataclasses.field(default=0.75, metadata={"live": True})
    tau_occ: float = 0.60  # Table 1 τ_occ: sigmoid centre of the appearance weight (Eq. 3)
    # Eq. 3 gain. Bhattacharyya scores of the same person typically lie in 0.8-0.95 and of other
    # people in 0.2-0.5; γ=10 maps C_t=0.9 to ω≈0.95 and C_t=0.3 to ω≈0.05, i.e. the sigmoid
    # switches over the range the coefficient actually spans rather than acting as a step.
    gamma: float = 10.0
    # S_geo Euclidean scale as a fraction of the predicted box diagonal (see reid.geometric_score).
    geo_scale: float = 0.5
    # A match is "ambiguous" (not secure, template frozen) if another candidate's M_fuse is
    # within this margin of the best one.
    ambiguity_margin: float = 0.05
    # Eq. 3's ω scaled by how far the two best colour scores are apart (in ambiguity_margins, at most 1): between
    # candidates whose colours tie, geometry decides (reid.ReIdentifier._colour_separation). False: the seed's ω.
    colour_ties_to_geometry: bool = True
    # Adaptive search region (seed 002 §3.2): the gate's χ² is scaled by k² (SearchScaleParams above).
    # Seed 002 / ByteTrack's second association stage: when no detection in the gate matches, the low-score
    # ones (the detection node's low_boxes, score in [low_score_threshold, score_threshold)) are tried, never
    # as training samples, and with ByteTrack's caution: only for a target matched on the previous frame (not
    # OCCLUDED or LOST) and only a box overlapping the predicted box by low_score_min_iou (its second stage's
    # IoU 0.5): without that caution a stranger's weak box in the gate of an occluded target is taken for it.
    low_score_stage: bool = True
    low_score_min_iou: float = 0.5
    # A re-initialisation of a target this re-ID has followed (a prediction reset or restart) takes the detection
    # matching its template or lying where it just was, else waits (LOST); never the person nearest the image
    # bottom-centre, the start-up rule (ReIdentifier._follows_someone); nor the configured init_box when someone
    # else stands there (a camera restarted mid-run: ReIdentifier._init_box_holds_the_target).
    reinitialise_only_on_the_target: bool = True
    # Partial views (reid.complete_partial_view): a detector box under partial_max_extent_ratio of the predicted
    # height, its top or bottom within partial_edge_tolerance (of the predicted height) of the prediction's and
    # the other edge short of it, is the visible part of the target: it is scored, measured and output as the
    # whole person (the predicted height from the agreeing edge), never as a training sample.
    partial_view_completion: bool = True
    # ... except in a box wider than the prediction by over 1 / partial_max_extent_ratio: a changed pose (crouching,
    # bending, tucked), kept whole, for no occluder makes a person wider (otb-diving's tucked diver, EVALUATION.md).
    partial_view_keeps_wider_whole: bool = True
    partial_max_extent_ratio: float = 0.8
    partial_edge_tolerance: float = 0.15
    # Merged views (reid.trim_merged_view): a detector box over merged_min_extent_ratio of the predicted height with
    # one edge agreeing (partial_edge_tolerance) boxes the target with someone in line: it is measured and output
    # as the predicted height from that edge, never as a training sample.
    merged_view_trimming: bool = True
    merged_min_extent_ratio: float = 1.5
    # ... until such boxes, accepted on every frame with no one else in the gate, have gone on for
    # merged_view_own_extent_after_ms: then the extent is the target's own (a turn, a changed pose) and the box is
    # measured whole, for a trimmed box measures the old extent back and would keep it for good (otb-diving's
    # tucked diver). Its geometry is still scored as trimmed: the extent it outgrew is no evidence against it.
    merged_view_own_extent: bool = True
    merged_view_own_extent_after_ms: float = 500.0
    # The coasting box's colours (ReIdentifier._coasting_colours_seen): while OCCLUDED, the output box is checked
    # against the template and the boxes around it (appearance.colour_contrast). The target's colours there (S_color
    # above reid_threshold and coasting_colour_margin above everything around it), with no other person's box on
    # it: the target is still there, unseen by the detector (an odd pose), and the box is output however uncertain
    # the prediction (Prior.locates_person). Colours missing there prove nothing: an occluder hides them too.
    coasting_colour_check: bool = True
    coasting_colour_margin: float = 0.1
    # Learned appearance (seed 001, tracking/learned_appearance.py): an OSNet descriptor and an online ridge-regression
    # classifier of the target against the other people decide when colour + geometry cannot: between
    # candidates within identity_margin of the best M_fuse, and on a re-lock after an occlusion.
    learned_appearance: bool = True
    identity_margin: float = 0.10
    identity_sample_every_frames: int = 5  # training samples from every n-th secure frame (descriptor cost)
    identity_max_crops: int = 6  # descriptors per frame at most (~3-6 ms each on one core)
    ridge_lambda: float = 1.0  # λ of the ridge regression (seed 001 §III-C)
    delta_iou: float = 0.5  # δ_iou: no sample while the target box overlaps another person more (seed 001 §IV)
    delta_id: float = 0.60  # δ_id: a contender scoring above it is the target (seed 001 §IV)
    delta_switch: float = 0.35  # δ_switch: below it a box is taken for someone else (seed 001 §III-D)
    # Issue 22: re-locking after an occlusion onto a person far from the prior (more than
    # relock_far_height_fraction of the target's height from its predicted centre) needs identification-level
    # evidence: the classifier's score at δ_id or above on n_id_frames consecutive frames (seed 001's N_id), not
    # δ_switch.
    far_relock_needs_identity: bool = True
    # ... except for a person alone in view (no other confident detection in the frame): who else could it be? The
    # classifier still vetoes them below δ_switch, and T_reid still wants the target's colours. Without it a target
    # that comes back after a long coast, far from where the stale velocity carried the prior, waits for a δ_id the
    # classifier rarely gives a changed pose (a tumbling diver: one frame in ten).
    far_relock_alone_in_view: bool = True
    relock_far_height_fraction: float = 0.5
    # A far re-lock the classifier cannot judge (not trained yet, or off) waits while another candidate comes within
    # identity_margin of the best in M_fuse: far from the prior S_geo is 0 and colour alone would choose between
    # look-alikes (otb-skiing 42: a pine tree, and the skier merged with it, at S_color 0.84 and 0.83). Seed 001
    # leaves such contenders to the classifier; with none to ask, nothing tells them apart. Re-acquisition on
    # evidence asks the same lead (_clear_best). False: colour's choice is taken.
    far_relock_tie_waits: bool = True
    n_id_frames: int = dataclasses.field(default=2, metadata={"was": "n_id"})
    # Re-acquisition on accumulated evidence (tracking/reacquisition.py): while OCCLUDED or LOST, a detection that
    # is, on reacquire_frames frames (seed 001's N_id = 5) within reacquire_window_frames, re-ID's best candidate
    # among those that are none of the people seen beside the target, ahead of the others by identity_margin in
    # M_fuse, with the target's colours (S_color >= τ_occ), not rejected by the classifier (>= δ_switch) and moving
    # consistently (within reacquire_max_step_heights of its height a frame of where its velocity carries it, the
    # height within a factor 1.5), is re-acquired, however far from the prior and whatever T_reid says: the target
    # came back looking a little different. False: only T_reid and δ_id re-lock.
    reacquire_on_evidence: bool = True
    # A lone detector box centred inside the predicted box of a target matched on the last frame, while
    # no other detection has shared the gate for identity_veto_after_crowd_frames, is accepted below T_reid: the
    # target alone, whose colours changed (reid.ReIdentifier._uncontested). False: T_reid decides.
    uncontested_lone_candidate: bool = True
    # ... the predicted box grown by one standard deviation of the prior's centre on each axis (to twice its size
    # at most): where the prediction puts the person, as sure as it is. A small person moving fast (a skier 26 px
    # tall moving 9 px a frame, seen first with no velocity) leaves the predicted box itself within two frames.
    # False: the predicted box alone.
    uncontested_within_prior_std: bool = True
    reacquire_frames: int = 5
    reacquire_window_frames: int = 10
    reacquire_max_step_heights: float = 0.5
    # A person seen beside the target is never re-acquired on evidence, unless their track went through a merge
    # (hidden with someone in one box too tall for them alone; it may resume on the target's own box): their box then
    # needs twice reacquire_frames within twice reacquire_window_frames, and blocks no one else's evidence. False: a
    # bystander's track stays sure whatever it went through.
    unsure_bystanders_after_merge: bool = True
    # Where other people come within identity_margin of the best in M_fuse (colour alone decides far from the prior:
    # S_geo is 0), the classifier may still tell the best apart: δ_switch or more, ahead of each of them by
    # identity_margin (seed 001). False: M_fuse alone says which candidate is clear.
    reacquire_classifier_breaks_ties: bool = True
    # Just re-acquired on evidence, the prior has one measurement and no velocity: a frame whose best falls under
    # T_reid still takes it while it is the clear best and continues the person the evidence followed, until the
    # state is TRACKING (reacquired_hold_frames). False: T_reid from the next frame on.
    reacquire_hold_on_evidence: bool = True
    # While TRACKING, colour + geometry's choice stands when the classifier scores every contender below δ_switch,
    # and a lone contender is not even scored. Both fail in a crossing or a group: the target hides behind another
    # person of the same colours, the detector drops or merges it, and the lone (or best) detection in the gate is
    # the other person. So for identity_veto_after_crowd_frames frames after another detection shared the gate,
    # provided the classifier then told the people apart (scored the chosen one δ_id or more), contenders that all
    # score below δ_switch are rejected, a lone one included: the target goes OCCLUDED instead of the track (and
    # the classifier's training samples) moving onto the other person. 0: off.
    identity_veto_after_crowd_frames: int = 30
    # Motion blobs smaller than this (after morphology) are ignored as noise.
    min_blob_area_px: int = 64
    # A motion blob covering less than this fraction of the predicted box's area is a moving part of a person (a
    # limb, the head, spray: a forearm or a head covers under a tenth of a standing person's box), not the person:
    # its centre can be anywhere in their box, so it is no candidate (Alg. 1 line 2 takes the moving region for the
    # target; taken, a fragment re-locks a coasting target 20-30 px off and gives it a velocity the next coast carries
    # on: otb-diving frames 121-134, EVALUATION.md). 0: every blob over min_blob_area_px is one.
    motion_min_area_fraction: float = 0.25
    # OCCLUDED turns into LOST after this long without an accepted match.
    lost_after_ms: float = 3000.0
    # Number of accepted frames reported as REACQUIRED before returning to TRACKING; the
    # template is not updated during them (the re-lock is not yet confirmed).
    reacquired_hold_frames: int = 3
    # Once LOST the prior no longer says where the target is (a panning camera, a long occlusion):
    # re-detect over the whole image instead of inside the gate. Candidates outside the gate get
    # S_geo = 0, so only a strong appearance match (ω → 1 by Eq. 3) can pass T_reid.
    global_search_when_lost: bool = True
    # Alg. 1 line 2 (background subtraction) presumes a still background. When more than this fraction
    # of the whole frame changed since the previous one, the camera moved (a pan, a turning robot) and the
    # blobs are background, not the target: no motion candidates that frame. A person walking through a
    # still scene changes a few % of a 640x480 frame (the synthetic scenes, even with ego-motion: ≤ 12 %);
    # a camera panning with the target changes 30-55 % (otb-couple).
    motion_max_changed_fraction: float = 0.2
    # Ablation switches (paper Table 6).
    use_geometry: bool = True  # False: S_geo off, ω = 1 (M_fuse = S_color)
    use_gate: bool = True  # False: no Mahalanobis gate, every detection/blob is a candidate

    def __post_init__(self) -> None:
        check_ranges(
            self,
            positive=("morph_kernel_px", "bins_h", "bins_s", "dt_ms", "gamma", "lost_after_ms",
                      "motion_max_changed_fraction", "identity_sample_every_frames", "identity_max_crops",
                      "ridge_lambda", "gate_scale_max", "gate_fast_height_fraction", "relock_far_height_fraction",
                      "n_id_frames", "reacquire_frames", "reacquire_window_frames", "reacquire_max_step_heights",
                      "merged_view_own_extent_after_ms"),
            non_negative=("diff_threshold", "geo_scale", "ambiguity_margin", "min_blob_area_px",
                          "reacquired_hold_frames", "identity_margin", "identity_veto_after_crowd_frames",
                          "coasting_colour_margin"),
            unit_interval=("reid_threshold", "tau_occ", "gate_high_score", "gate_low_score", "delta_iou", "delta_id",
                           "delta_switch", "low_score_min_iou", "partial_max_extent_ratio", "partial_edge_tolerance",
                           "motion_min_area_fraction"))
        if not self.merged_min_extent_ratio > 1.0:  # at 1 or under, every box taller than predicted would be cut
            raise InvalidParam("merged_min_extent_ratio", "ReidParams.merged_min_extent_ratio must be > 1, "
                               f"got {self.merged_min_extent_ratio!r}")


# --- re-detection --------------------------------------------------------------------------------


@dataclass
class RedetectionParams(_FramePeriod, SearchScaleParams):
    """What the redetection node reads (seed 002 §3.2, tracking/redetection.py)."""

    # Ablation switch: False: no region is ever re-detected (the node publishes empty results).
    local_redetection: bool = True
    # A person predicted shorter than this at the detector's input scale is re-detected at the frame's resolution
    # every frame: YOLOX-nano's finest stride is 8 px, and under ~48 px a person's box becomes unreliable (it
    # merges with a neighbour or is missed); a 1280x720 frame inferred at 416 makes a 150 px person 48 px.
    min_resolvable_px: float = 48.0
    # What one second look may cost: its input at most this fraction of the frame pass's pixels (at 416: 256 px
    # square on a 4:3 frame, 224 on 16:9). Tail latency, not the mean, is what a larger one costs on two cores
    # (BENCHMARKS.md, the second look's cost).
    region_budget_fraction: float = 0.6

    def __post_init__(self) -> None:
        check_ranges(self, positive=("dt_ms", "gate_scale_max", "gate_fast_height_fraction"),
                     non_negative=("min_resolvable_px",),
                     unit_interval=("region_budget_fraction", "gate_high_score", "gate_low_score"))


# --- template ------------------------------------------------------------------------------------


@dataclass
class TemplateParams(_ColourHistogram, _UpdateSuspension):
    """What the template node's reference-model update reads (seed 000 Alg. 1 line 12, Eq. 9-10)."""

    tau_v: int = 220  # Table 1 τ_v: specular Value threshold (Eq. 9)
    tau_s: int = 45  # Table 1 τ_s: specular Saturation threshold (Eq. 9)
    eta_base: float = 0.02  # Table 1 η_base: base template learning rate (Eq. 10)
    # Eq. 10 penalty gain: 10% specular pixels cut η to 37% of η_base, 30% to 5%, 50% to <1%,
    # which matches the paper's "η_k → 0 under severe reflections".
    lambda_specular: float = 10.0
    adaptive_eta: bool = True  # ablation switch (Table 6). False: η = η_base on every update (no specular penalty)

    def __post_init__(self) -> None:
        check_ranges(self, positive=("bins_h", "bins_s"), non_negative=("eta_base", "lambda_specular"),
                     unit_interval=("eta_base",))
        for name in ("tau_v", "tau_s"):  # thresholds on 8-bit HSV channels
            if not 0 <= getattr(self, name) <= 255:
                raise InvalidParam(name, f"TemplateParams.{name} must be in [0, 255], got {getattr(self, name)!r}")

