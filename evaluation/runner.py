"""Run followers in-process over an evaluation sequence, all on the same (cached) detections.

One pass per sequence: each frame is read (or rendered) once, detections come from the cache or are
computed once, and every method is stepped on that frame in turn, so methods can never see different
inputs. Methods are initialised with the first ground-truth box (a follower is told whom to follow) on
the first frame that has one; before it they output nothing.

Sequences: ``sot/<name>`` and ``mot/<name>`` directories (see :mod:`followbus.evaluation.datasets`;
for MOT the follow target is chosen there) and ``scene:<name>`` synthetic scenes (exact ground truth,
visible fractions, the other people's boxes and the robot's ego velocity).

followbus itself is the graph: its tracking nodes run in-process (graph_follower.py), so what is scored is what
the robot runs, in the graph's own data order.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..tracking.params import KalmanParams, ReidParams
from ..vision.detector_presets import DETECTOR_PRESETS, apply_detector_preset, preset_of
from . import detcache
from .baselines import KalmanFollower, PeerFollower, peer_kind
from .datasets import load_sequence
from .graph_follower import GraphFollower
from .metrics import Box, SingleTargetMetrics, evaluate_single_target
from .mot_metrics import MotMetrics, evaluate_mot, remove_distractor_matches

log = logging.getLogger(__name__)

# Detector names (vision/detectors.py DETECTOR_PRESETS); ``graph`` = graph.yaml's own detection params, the
# detector the robot runs (the default).
DETECTORS = tuple(DETECTOR_PRESETS)
DEFAULT_DETECTOR = "graph"
# Table 6 of the paper: one switch off at a time.
ABLATIONS: dict[str, dict[str, Any]] = {
    "followbus w/o geometric cue": {"use_geometry": False},
    "followbus w/o gate": {"use_gate": False},
    "followbus w/o update suspension": {"suspend_updates": False},
    "followbus w/o adaptive η": {"adaptive_eta": False},
    # seed 002 §3.3, not a Table 6 row: the prior not warped by the camera's image motion (graph.yaml's
    # egomotion node; KalmanParams.camera_motion_compensation)
    "followbus w/o camera-motion compensation": {"camera_motion_compensation": False},
    # seed 002 §3.2: the gate at its base χ² whatever the target's speed and last detection score
    "followbus w/o adaptive gate": {"adaptive_gate": False},
    # seed 001: no OSNet descriptor / ridge-regression classifier, colour + geometry alone (= seed 000's re-ID)
    "followbus w/o learned appearance": {"learned_appearance": False},
    # seed 002 §3.1 (ByteTrack's second stage): the boxes below the detector's score threshold never considered
    "followbus w/o low-score stage": {"low_score_stage": False},
    # a partly hidden person's box taken as it is, not completed to the whole person from the prediction
    "followbus w/o partial-view completion": {"partial_view_completion": False},
    # a short box wider than the prediction completed to the predicted height too, not kept whole as a changed pose
    "followbus w/o keeping a wider pose whole": {"partial_view_keeps_wider_whole": False},
    # every motion blob over min_blob_area_px a candidate, however small a part of the predicted box it covers
    "followbus w/o the motion-blob size floor": {"motion_min_area_fraction": 0.0},
    # a box merging the target with someone in line with it taken whole, not trimmed to the target's height
    "followbus w/o merged-view trimming": {"merged_view_trimming": False},
    # a person seen beside the target never re-acquired on evidence, even after their track went through a merge
    # (two people in one box) and may have resumed on the target's own box
    "followbus w/o unsure bystanders after a merge": {"unsure_bystanders_after_merge": False},
    # re-acquisition evidence counted only where M_fuse alone makes the best clear, never the classifier
    "followbus w/o the classifier breaking evidence ties": {"reacquire_classifier_breaks_ties": False},
    # T_reid from the frame after a re-acquisition on evidence, whatever the evidence followed
    "followbus w/o holding a re-acquisition on evidence": {"reacquire_hold_on_evidence": False},
    # a re-lock after a coast of over 0.5 s keeps the velocity the filter carried through the coast, instead of the
    # displacement between the two measurements (OC-SORT's observation-centric velocity)
    "followbus w/o the re-lock's velocity from its observations": {"relock_velocity_after_coast_ms": 0.0},
    # a merged view trimmed for as long as it lasts, even alone in the gate for over 0.5 s (a turn, a changed pose)
    "followbus w/o settling a lasting merged view": {"merged_view_own_extent": False},
    # what the camera-motion estimate knows it does not know, one part at a time (each switch goes to the node that
    # reads it: egomotion, prediction or reid): the per-cell static-content map; the rival hypothesis and the
    # temporal choice between the two; the reference kept across a failed fit; the prior widened by (and held
    # against) the fit's uncertainty
    "followbus w/o static-content map": {"static_evidence": False},
    "followbus w/o rival hypothesis": {"temporal_consistency": False},
    "followbus w/o reference across failed fits": {"max_reference_age_frames": 0},
    "followbus w/o camera-motion uncertainty": {"camera_motion_uncertainty": False},
    # the coasting prediction output however uncertain it has grown (KalmanParams)
    "followbus w/o withholding an uncertain coasting box": {"occluded_output_min_overlap_probability": 0.0},
    # seed 002 §3.2: no region around the prediction re-detected at the frame's resolution (nodes/redetection.py)
    "followbus w/o local re-detection": {"local_redetection": False},
    # the prediction's single scene model (seed 002 §3.3), no "camera follows the person" model beside it (IMM)
    "followbus w/o the image motion model": {"image_motion_model": False},
    # a lone box centred in the predicted box, nobody else near, still judged by T_reid on its colours
    "followbus w/o taking an uncontested lone box": {"uncontested_lone_candidate": False},
    # the uncontested lone box only inside the predicted box itself, not grown by the prior's uncertainty
    "followbus w/o the prior's doubt around a lone box": {"uncontested_within_prior_std": False},
    # Eq. 3's ω as the seed has it when colours tie (geometry does not decide between look-alikes)
    "followbus w/o geometry deciding colour ties": {"colour_ties_to_geometry": False},
    # the coasting box output or withheld by the prediction's uncertainty alone, whatever its colours say
    "followbus w/o the coasting box's colour check": {"coasting_colour_check": False},
    # a failed corner fit is not tried again with the smeared-frame window and tolerance (phase correlation next)
    "followbus w/o the smeared-frame refit": {"smeared_refit": False},
    # no phase correlation when the corner fit fails (a smeared frame has no camera motion)
    "followbus w/o the phase-correlation fallback": {"phase_fallback": False},
    # re-acquisition only on T_reid and δ_id, not on evidence accumulated over N_id frames (tracking/reacquisition.py)
    "followbus w/o re-acquisition on evidence": {"reacquire_on_evidence": False},
    # a far re-lock on δ_switch alone (no δ_id / N_id confirmation)
    "followbus w/o identity-confirmed far re-lock": {"far_relock_needs_identity": False},
    # a far re-lock needs δ_id on n_id_frames frames even onto the only person in view
    "followbus w/o far re-lock of a person alone in view": {"far_relock_alone_in_view": False},
    # a far re-lock the classifier cannot judge taken on colour even when another candidate comes within
    # identity_margin of it in M_fuse
    "followbus w/o waiting on a far tie": {"far_relock_tie_waits": False},
    # the IMM's models mixed on every frame, also while coasting with no measurement (the textbook IMM)
    "followbus w/o unmixed coasting": {"mix_models_while_coasting": True},
    # after a crossing, colour's choice (a lone detection unscored) even when the classifier, which just told
    # the people apart, scores every contender below δ_switch
    "followbus w/o identity veto after a crossing": {"identity_veto_after_crowd_frames": 0},
}
# graph.yaml's detection node: boxes scoring score_threshold or more are "the detections" every method sees;
# those in [low_score_threshold, score_threshold) only reach a method that asks for them (``uses_low_scores``):
# followbus's re-ID (its second association stage); the peers do worse with them (see baselines.PeerFollower).
SCORE_THRESHOLD = 0.3
LOW_SCORE_THRESHOLD = 0.1
READ_AHEAD_FRAMES = 4  # decoded images held ahead of the trackers (640x480: 0.9 MB each)
LOW_VISIBILITY = 0.5  # scene frames with less of the target visible are shaded as (partial) occlusion


class Follower(Protocol):
    """A follower whose ``uses_low_scores`` attribute is true is also given ``low_detections=`` (the boxes scoring
    in [LOW_SCORE_THRESHOLD, SCORE_THRESHOLD)); every other one sees the boxes above SCORE_THRESHOLD only. One with
    a ``prepare(init_box)`` method is set up by it, untimed, before the step that carries the initial box (the
    graph is built only once it knows whom to follow); its per-frame time then counts frames only."""

    def step(self, frame_bgr: np.ndarray, detections: np.ndarray, t_ns: int, v_ego_mps: Sequence[float],
             init_box: Sequence[float] | None) -> tuple[Box | None, dict[str, Any]]: ...


class _NoEgo:
    """Adapter for followers that take no ego velocity."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.uses_low_scores = bool(getattr(inner, "uses_low_scores", False))

    def step(self, frame_bgr, detections, t_ns, v_ego_mps, init_box, **low):
        return self.inner.step(frame_bgr, detections, t_ns, init_box=init_box, **low)

    @property
    def wants_reference(self) -> bool:
        return bool(getattr(self.inner, "wants_reference", False))

    def update_reference(self, box) -> None:
        self.inner.update_reference(box)


def method_factories(methods: Sequence[str], ablations: bool = False, trace: bool = False,
                     detector: str = DEFAULT_DETECTOR) -> dict[str, Callable[[float], Follower]]:
    """Method name → factory(fps) of a fresh follower. Unknown names raise ValueError. ``trace``: followbus and
    its ablations record every frame's prior, candidates, camera motion and reason (info["trace"])."""
    out: dict[str, Callable[[float], Follower]] = {}
    for m in methods:
        if m == "followbus":
            out[m] = lambda fps: GraphFollower(trace=trace, detector=detector)
        elif m == "kalman":
            out[m] = lambda fps: _NoEgo(_kalman_baseline())
        elif m.startswith("peer:"):
            kind = peer_kind(m.split(":", 1)[1])
            out[m] = lambda fps, k=kind: _NoEgo(PeerFollower(k, fps))
        elif m in ABLATIONS:  # one ablation on its own
            out[m] = _ablation(ABLATIONS[m], trace, detector)
        else:
            raise ValueError(f"unknown method {m!r} (followbus, kalman, peer:bytetrack|ocsort|botsort, or an "
                             f"ablation: {', '.join(repr(a) for a in ABLATIONS)})")
    if ablations:
        for name, switches in ABLATIONS.items():
            out[name] = _ablation(switches, trace, detector)
    return out


def _ablation(switches: dict[str, Any], trace: bool, detector: str) -> Callable[[float], Follower]:
    """The factory of followbus with ``switches`` (an ABLATIONS entry) applied."""
    return lambda fps: GraphFollower(switches, trace=trace, detector=detector)


def _kalman_baseline() -> KalmanFollower:
    """The prediction node's Kalman filter alone, with the prediction and re-ID nodes' default settings."""
    kalman, reid = KalmanParams(), ReidParams()
    return KalmanFollower(accel_std_px_s2=kalman.accel_std_px_s2, r_px2=kalman.r0_px2,
                          init_velocity_std_px_s=kalman.init_velocity_std_px_s, size_smoothing=kalman.size_smoothing,
                          lost_after_ms=reid.lost_after_ms)


# --------------------------------------------------------------------------- sequences


@dataclass
class FrameItem:
    bgr: np.ndarray
    t_ns: int
    gt_box: Box | None
    others: list[Box]
    visible_fraction: float | None  # scenes only
    truth: list[tuple[list[float], float]]  # simulated-detector input (mirrors nodes/detection.py)
    v_ego_mps: tuple[float, float] = (0.0, 0.0)
    people: list[tuple[int, Box]] = field(default_factory=list)  # every annotated person (id, box); MOT scoring


@dataclass
class EvalSequence:
    name: str
    kind: str  # sot | mot | scene
    key: str  # identity for the detection cache
    fps: float
    width: int
    height: int
    n_frames: int
    frames: Callable[[], Iterator[FrameItem]]
    # MOT16/17: per frame every gt row and which are distractors (MOT scoring preprocessing); else empty
    gt_regions: list[Any] = field(default_factory=list)


def scene_truth(gt_box: Any, visible_fraction: float, others: Any,
                others_visible: Any) -> list[tuple[list[float], float]]:
    """The simulated detector's truth list exactly as nodes/detection.py builds it from a GroundTruth
    message (float64 arrays → lists; the target only when its box exists; others' visibility 1 when the
    counts disagree)."""
    truth: list[tuple[list[float], float]] = []
    if gt_box is not None:
        truth.append((np.asarray(gt_box, dtype=np.float64).tolist(), float(visible_fraction)))
    o = np.asarray(others if others is not None else [], dtype=np.float64).reshape(-1, 4)
    vis = np.asarray(others_visible if others_visible is not None else [], dtype=np.float64).reshape(-1)
    if vis.size != len(o):
        vis = np.ones(len(o))
    truth.extend((box.tolist(), float(v)) for box, v in zip(o, vis, strict=True))
    return truth


def open_sequence(spec: str, *, seed: int = 0, width: int = 640, height: int = 480,
                  max_frames: int = 0) -> EvalSequence:
    """``scene:<name>`` or a sot/mot directory."""
    if spec.startswith("scene:"):
        from ..vision.sources import SceneSource

        name = spec.split(":", 1)[1]
        probe = SceneSource(name, seed=seed, width=width, height=height)
        n = len(probe) if not max_frames else min(max_frames, len(probe))

        def scene_frames() -> Iterator[FrameItem]:
            src = SceneSource(name, seed=seed, width=width, height=height)
            for i, f in enumerate(src):
                if i >= n:
                    break
                vf = float(f.extras.get("visible_fraction", 1.0 if f.gt_box is not None else 0.0))
                others = [tuple(float(v) for v in b) for b in (f.extras.get("distractor_boxes") or [])]
                gt = None if f.gt_box is None else tuple(float(v) for v in f.gt_box)
                truth = scene_truth(f.gt_box, vf, others, f.extras.get("distractor_visible_fractions"))
                ego = f.extras.get("ego_velocity_mps") or (0.0, 0.0)
                yield FrameItem(f.bgr, f.t_ns, gt, others, vf, truth, (float(ego[0]), float(ego[1])))
            src.close()

        return EvalSequence(f"scene:{name}", "scene", f"scene:{name}:seed{seed}:{width}x{height}", probe.fps,
                            width, height, n, scene_frames)

    import cv2

    from ..vision.sources import synthetic_stamp_ns

    seq = load_sequence(spec)
    others_all = seq.other_boxes()
    n = seq.frames if not max_frames else min(max_frames, seq.frames)

    def read(i: int) -> np.ndarray:
        bgr = cv2.imread(str(seq.image_paths[i]), cv2.IMREAD_COLOR)
        if bgr is None:
            raise OSError(f"cannot read {seq.image_paths[i]}")
        bgr.flags.writeable = False  # every method reads the same image: none may change it for the next
        return bgr

    def disk_frames() -> Iterator[FrameItem]:
        for i, bgr in enumerate(read_ahead(read, n)):
            gt = seq.gt_boxes[i]
            truth = [(list(b), 1.0) for _, b in seq.all_gt[i]]
            yield FrameItem(bgr, synthetic_stamp_ns(i, seq.fps), gt, list(others_all[i]), None, truth,
                            people=list(seq.all_gt[i]))

    label = f"{seq.kind}/{Path(spec).name}"
    return EvalSequence(label, seq.kind, str(Path(spec).resolve()), seq.fps, seq.width, seq.height, n, disk_frames,
                        gt_regions=seq.gt_regions[:n])


def read_ahead(read: Callable[[int], Any], n: int, depth: int = READ_AHEAD_FRAMES) -> Iterator[Any]:
    """``read(0) … read(n-1)`` in order, read by a helper thread up to ``depth`` items ahead: decoding an
    image (OpenCV releases the GIL) then overlaps with the trackers' work on the previous frames, on the
    other core, instead of adding to it (otb-human3 from the cache: ~1 ms a frame). A read error is raised
    where the item would have been; leaving the loop early stops the reader."""
    items: queue.Queue[tuple[bool, Any]] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def reader() -> None:
        for i in range(n):
            try:
                item = (True, read(i))
            except BaseException as exc:  # handed to the consumer, raised there
                item = (False, exc)
            while not stop.is_set():
                try:
                    items.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if stop.is_set() or not item[0]:
                return

    thread = threading.Thread(target=reader, name="read-ahead", daemon=True)
    thread.start()
    try:
        for _ in range(n):
            ok, value = items.get()
            if not ok:
                raise value
            yield value
    finally:
        stop.set()
        thread.join()


# --------------------------------------------------------------------------- detectors


def detection_params(name: str) -> dict[str, Any]:
    """graph.yaml's detection-node params switched to the detector ``name`` (``graph``: as they are)."""
    from ..nodes.detection import resolve_input_size
    from .graph_follower import detector_params

    return resolve_input_size(apply_detector_preset(detector_params(), name))


def detector_key(name: str) -> str:
    """The identity of the detector ``name`` in the detection cache and the reports: its preset name (``graph``
    resolved to the preset graph.yaml amounts to, so both share a cache), else its params."""
    if name != "graph":
        return name
    params = detection_params(name)
    found = preset_of(params)
    if found is not None:
        return found
    keys = ("backend", "model_file", "input_size_px", "runtime", "input_shape")
    return "graph-" + "-".join(str(params.get(k, "")) for k in keys)


def make_eval_detector(name: str, seed: int = 0, score_threshold: float = SCORE_THRESHOLD):
    """The detector ``name`` as the detection node builds it from its params (model, input size, runtime,
    threads), down to ``score_threshold``."""
    from ..nodes.detection import detection_params as parse_detection_params
    from ..nodes.detection import detector_from_params

    if name not in DETECTORS:
        raise ValueError(f"unknown detector {name!r}; choose one of {', '.join(DETECTORS)}")
    params = detection_params(name)
    params.update(score_threshold=SCORE_THRESHOLD, low_score_threshold=score_threshold, seed=seed)
    return detector_from_params(parse_detection_params(params))


# --------------------------------------------------------------------------- running


@dataclass
class MethodRun:
    boxes: list[Box | None]
    infos: list[dict[str, Any]]
    tracker_ms: list[float]
    metrics: SingleTargetMetrics | None = None
    mot: MotMetrics | None = None  # multi-object trackers on MOT sequences: their whole output vs every person
    mot_frames: list[Any] | None = None  # that output per frame as scored (distractor matches removed)

    @property
    def tracker_ms_mean(self) -> float:
        return float(np.mean(self.tracker_ms)) if self.tracker_ms else math.nan

    def series(self, key: str) -> np.ndarray:
        return np.array([float(i.get(key, math.nan)) for i in self.infos])


@dataclass
class SequenceRun:
    sequence: EvalSequence
    detector: str
    gt_boxes: list[Box | None]
    other_gt: list[list[Box]]
    visible: list[float | None]
    detector_ms: np.ndarray
    detections_cached: bool
    runs: dict[str, MethodRun] = field(default_factory=dict)
    gt_people: list[list[tuple[int, Box]]] = field(default_factory=list)
    # An oracle that outputs, on every frame with a target, the detection nearest to it: the best a follower
    # that only ever outputs one of these detections can score. A follower that coasts on its prediction
    # through missed detections (followbus, kalman, the peers) can beat it on such frames.
    ceiling: SingleTargetMetrics | None = None

    @property
    def detector_ms_mean(self) -> float:
        return float(np.mean(self.detector_ms)) if self.detector_ms.size else math.nan

    def occlusion_spans(self) -> list[tuple[int, int]]:
        """Inclusive frame ranges where the target is absent from gt or (scenes) mostly hidden."""
        hidden = [g is None or (v is not None and v < LOW_VISIBILITY) for g, v in zip(self.gt_boxes, self.visible,
                                                                                      strict=True)]
        spans, start = [], None
        for i, h in enumerate(hidden):
            if h and start is None:
                start = i
            elif not h and start is not None:
                spans.append((start, i - 1))
                start = None
        if start is not None:
            spans.append((start, len(hidden) - 1))
        return spans


def run_sequence(seq: EvalSequence, factories: dict[str, Callable[[float], Follower]], detector: str, *,
                 cache_dir: Path | None = None, seed: int = 0, progress: bool = False,
                 use_ego_velocity: bool = True, low_score_threshold: float = LOW_SCORE_THRESHOLD,
                 jitter_px: float = 0.0) -> SequenceRun:
    """Detect once (or load the cache), then step every method on every frame; score each method.

    The detector runs down to ``low_score_threshold`` (= SCORE_THRESHOLD: no low-score boxes); the cache then
    holds those boxes too (a key of its own). ``jitter_px`` > 0 moves every box by Gaussian noise (seeded by
    ``seed``, :func:`jitter_detections`) before anyone sees it; the cache keeps them as detected."""
    from ..vision.detectors import split_by_score

    low_score_threshold = min(float(low_score_threshold), SCORE_THRESHOLD)
    source = _FrameDetections(seq, detector, cache_dir, seed, low_score_threshold)
    followers = {name: make(seq.fps) for name, make in factories.items()}
    runs = {name: MethodRun([], [], []) for name in factories}
    truth = _Truth()
    initialised = False
    rng = np.random.default_rng(seed)
    for k, item in enumerate(_frames(seq, progress)):
        rows = jitter_detections(source.detect(k, item), jitter_px, rng)
        dets, low_dets = split_by_score(rows, SCORE_THRESHOLD, low_score_threshold)  # as the node
        truth.add(item, dets)
        init_box = None
        if not initialised:
            if item.gt_box is None:
                _not_yet_told(runs)
                continue
            init_box, initialised = item.gt_box, True
        v_ego = item.v_ego_mps if use_ego_velocity else (0.0, 0.0)
        for name, follower in followers.items():
            _step_follower(follower, runs[name], item, dets, low_dets, v_ego, init_box)
    for follower in followers.values():
        close = getattr(follower, "close", None)
        if close is not None:
            close()  # the graph's nodes tear down (nothing is saved: no template file in eval)
    result = SequenceRun(seq, detector, truth.gts, truth.others, truth.visible, source.finish().ms,
                         source.from_cache, runs, truth.people)
    _score_methods(result, truth)
    return result


def jitter_detections(rows: np.ndarray, jitter_px: float, rng: np.random.Generator) -> np.ndarray:
    """Detections (N x 5: x, y, w, h, score) with N(0, jitter_px) added to x, y, w, h and N(0, jitter_px / 200)
    to the score (w, h kept >= 1 px, the score in [0, 1]): another CPU's detector differs from this one's in
    such last digits, which can move where a tracker's one mistake happens. ``jitter_px`` 0: ``rows`` as given."""
    if jitter_px <= 0.0 or len(rows) == 0:
        return rows
    out = rows.astype(np.float64, copy=True)
    out[:, :4] += rng.normal(0.0, jitter_px, (len(out), 4))
    out[:, 4] += rng.normal(0.0, jitter_px / 200.0, len(out))
    out[:, 2:4] = np.maximum(out[:, 2:4], 1.0)
    out[:, 4] = np.clip(out[:, 4], 0.0, 1.0)
    return out.astype(np.float32)


class _FrameDetections:
    """Each frame's detections down to the low-score threshold: from the cache, or detected once and then cached."""

    def __init__(self, seq: EvalSequence, detector: str, cache_dir: Path | None, seed: int,
                 low_score_threshold: float) -> None:
        self.cached: detcache.CachedDetections | None = None
        self.path: Path | None = None
        if cache_dir is not None:
            # simulated detections depend on the seed: it is part of the key
            det_key = detector_key(detector)
            det_key = f"{det_key}-seed{seed}" if det_key == "simulated" else det_key
            if low_score_threshold < SCORE_THRESHOLD:
                det_key += f"-low{low_score_threshold:g}"
            self.path = detcache.cache_path(cache_dir, seq.key, det_key, seq.n_frames)
            self.cached = detcache.load(self.path, seq.n_frames)
        self.from_cache = self.cached is not None
        self.det = None if self.from_cache else make_eval_detector(detector, seed, low_score_threshold)
        if self.cached is not None:
            log.info("%s: detections from cache %s", seq.name, self.path)
        self.frames: list[np.ndarray] = []  # every box down to low_score_threshold (what the cache holds)
        self.ms: list[float] = []

    def detect(self, k: int, item: FrameItem) -> np.ndarray:
        if self.cached is not None:
            return self.cached.per_frame[k]
        t0 = time.perf_counter()
        simulated = getattr(self.det, "is_simulated", False)
        rows = self.det.detect(item.bgr, item.truth) if simulated else self.det.detect(item.bgr)
        self.ms.append((time.perf_counter() - t0) * 1e3)
        rows = np.asarray(rows, dtype=np.float32).reshape(-1, 5)
        self.frames.append(rows)
        return rows

    def finish(self) -> detcache.CachedDetections:
        """The sequence's detections; saved to the cache when they were detected here."""
        if self.cached is None:
            self.cached = detcache.CachedDetections(self.frames, np.asarray(self.ms))
            if self.path is not None:
                detcache.save(self.path, self.cached)
        return self.cached


@dataclass
class _Truth:
    """The ground truth of every frame, and the detections every method saw (for the ceiling)."""

    gts: list[Box | None] = field(default_factory=list)
    others: list[list[Box]] = field(default_factory=list)
    people: list[list[tuple[int, Box]]] = field(default_factory=list)
    visible: list[float | None] = field(default_factory=list)
    detections: list[np.ndarray] = field(default_factory=list)

    def add(self, item: FrameItem, detections: np.ndarray) -> None:
        self.detections.append(detections)
        self.gts.append(item.gt_box)
        self.others.append(item.others)
        self.people.append(item.people)
        self.visible.append(item.visible_fraction)


def _frames(seq: EvalSequence, progress: bool) -> Iterator[FrameItem]:
    frames = seq.frames()
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=seq.n_frames, desc=seq.name, unit="fr", leave=False)
    return frames


def _not_yet_told(runs: dict[str, MethodRun]) -> None:
    """A frame before the first one with a ground-truth box: no method knows whom to follow yet."""
    for run in runs.values():
        run.boxes.append(None)
        run.infos.append({"state": "WAITING"})
        run.tracker_ms.append(0.0)


def _step_follower(follower: Follower, run: MethodRun, item: FrameItem, dets: np.ndarray, low_dets: np.ndarray,
                   v_ego: Sequence[float], init_box: Box | None) -> None:
    """One method on one frame, timed (its set-up, when this frame tells it whom to follow, is not)."""
    if item.gt_box is not None and getattr(follower, "wants_reference", False):
        follower.update_reference(item.gt_box)  # a peer still choosing whom to follow: this frame's box
    low = {"low_detections": low_dets} if getattr(follower, "uses_low_scores", False) else {}
    prepare = getattr(follower, "prepare", None)
    if init_box is not None and prepare is not None:
        prepare(init_box)
    t0 = time.perf_counter()
    box, info = follower.step(item.bgr, dets, item.t_ns, v_ego, init_box, **low)
    run.tracker_ms.append((time.perf_counter() - t0) * 1e3)
    run.boxes.append(box)
    run.infos.append(info)


def _score_methods(result: SequenceRun, truth: _Truth) -> None:
    """Every method's metrics, and the ceiling of the boxes every method sees (those above SCORE_THRESHOLD),
    comparable across runs."""
    seq, gts, others = result.sequence, truth.gts, truth.others
    result.ceiling = evaluate_single_target(nearest_detections(truth.detections, gts), gts, other_gt=others,
                                            fps=seq.fps, image_size=(seq.width, seq.height))
    for run in result.runs.values():
        reports_candidates = any("best_candidate" in info for info in run.infos)
        best = [info.get("best_candidate") for info in run.infos] if reports_candidates else None
        run.metrics = evaluate_single_target(run.boxes, gts, other_gt=others, fps=seq.fps,
                                             image_size=(seq.width, seq.height), best_candidates=best)
        if seq.kind == "mot" and any("mot" in info for info in run.infos):
            run.mot_frames = [info.get("mot") for info in run.infos]
            if seq.gt_regions:
                run.mot_frames = remove_distractor_matches(run.mot_frames, seq.gt_regions)
            run.mot = evaluate_mot(gt_mot_frames(truth.people), run.mot_frames)


def nearest_detections(per_frame: Sequence[np.ndarray], gts: Sequence[Box | None]) -> list[Box | None]:
    """Per frame, the detection whose centre is nearest the target's (None without target or detections)."""
    out: list[Box | None] = []
    for dets, gt in zip(per_frame, gts, strict=True):
        d = np.asarray(dets, dtype=np.float64).reshape(-1, 5)
        if gt is None or not len(d):
            out.append(None)
            continue
        gx, gy = gt[0] + gt[2] / 2, gt[1] + gt[3] / 2
        k = int(np.argmin(np.hypot(d[:, 0] + d[:, 2] / 2 - gx, d[:, 1] + d[:, 3] / 2 - gy)))
        out.append(tuple(float(v) for v in d[k, :4]))
    return out


def gt_mot_frames(people: Sequence[Sequence[tuple[int, Box]]]) -> list[tuple[list[int], list[Box]]]:
    """Per-frame ``(ids, boxes)`` of every annotated person, the layout :mod:`mot_metrics` takes."""
    return [([int(i) for i, _ in frame], [tuple(b) for _, b in frame]) for frame in people]
