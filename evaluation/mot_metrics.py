"""Multi-object tracking metrics implemented from their definitions: CLEAR-MOT, identity (IDF1) and HOTA.

* CLEAR-MOT (Bernardin & Stiefelhagen 2008) with the event rules of py-motmetrics: distance = 1 - IoU, a pair
  is matchable iff IoU >= ``iou_threshold``; on every frame the previous correspondences that are still
  matchable are kept, the rest is assigned by Hungarian matching (max cardinality, then min distance); an ID
  switch is a match of a gt id to a hypothesis other than the one it was last matched to (at any earlier
  time). MOTA = 1 - (FN + FP + IDSW) / #gt; MOTP = mean (1 - IoU) over matches (motmetrics' convention,
  lower is better; ``mean_match_iou`` = 1 - MOTP is TrackEval's MOTP).
* Identity metrics (Ristani et al. 2016): one global one-to-one gt-id ↔ tracker-id assignment maximising the
  number of frames where the paired boxes are matchable (= min IDFN + IDFP); IDF1 = 2 IDTP / (#gt + #pred).
* HOTA (Luiten et al. 2021, TrackEval's implementation): for α in 0.05, 0.10, …, 0.95 per-frame Hungarian
  matching on IoU weighted by the global alignment score between ids; DetA = TP / (TP + FN + FP),
  AssA = mean over TPs of the TPA / (TPA + FNA + FPA) of their id pair, HOTA_α = sqrt(DetA·AssA); HOTA, DetA,
  AssA, LocA are the means over α.

Frames are given as aligned lists of ``(ids, boxes)`` with boxes ``(x, y, w, h)``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

log = logging.getLogger(__name__)

__all__ = [
    "ClearMot",
    "FrameTracks",
    "Hota",
    "IdentityScores",
    "MotMetrics",
    "align_frames",
    "clear_mot",
    "evaluate_mot",
    "evaluate_mot_combined",
    "load_mot_regions",
    "remove_distractor_matches",
    "hota",
    "identity_scores",
    "iou_matrix",
    "load_mot_file",
]

# One frame: (ids (n,), boxes (n, 4) as x, y, w, h). Anything array-like is accepted on input.
FrameTracks = tuple[np.ndarray, np.ndarray]

HOTA_ALPHAS = np.arange(0.05, 0.99, 0.05)  # 19 thresholds, as TrackEval
PEDESTRIAN_CLASS = 1  # MOT16/17 gt class column
# MOT17 classes a tracker box may sit on without penalty (TrackEval's ``distractor_classes``): person on
# vehicle, static person, distractor, reflection.
DISTRACTOR_CLASSES = (2, 7, 8, 12)
_EPS = np.finfo(float).eps


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of (n, 4) and (m, 4) ``xywh`` boxes → (n, m). Degenerate boxes have IoU 0."""
    a = np.asarray(a, dtype=float).reshape(-1, 4)
    b = np.asarray(b, dtype=float).reshape(-1, 4)
    ax0, ay0, ax1, ay1 = a[:, 0], a[:, 1], a[:, 0] + a[:, 2], a[:, 1] + a[:, 3]
    bx0, by0, bx1, by1 = b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]
    iw = np.clip(np.minimum(ax1[:, None], bx1[None]) - np.maximum(ax0[:, None], bx0[None]), 0, None)
    ih = np.clip(np.minimum(ay1[:, None], by1[None]) - np.maximum(ay0[:, None], by0[None]), 0, None)
    inter = iw * ih
    union = (a[:, 2] * a[:, 3])[:, None] + (b[:, 2] * b[:, 3])[None] - inter
    out = np.zeros_like(inter)
    np.divide(inter, union, out=out, where=union > _EPS)
    return out


def _as_frame(frame: tuple[Iterable, Iterable] | None) -> FrameTracks:
    if frame is None:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    ids, boxes = frame
    ids = np.asarray(list(ids) if not isinstance(ids, np.ndarray) else ids, dtype=np.int64).reshape(-1)
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 4)
    if len(ids) != len(boxes):
        raise ValueError(f"{len(ids)} ids but {len(boxes)} boxes in a frame")
    if len(np.unique(ids)) != len(ids):
        raise ValueError(f"duplicate ids in a frame: {ids.tolist()}")
    return ids, boxes


def _prepare(gt_frames: Sequence, pred_frames: Sequence) -> tuple[list[FrameTracks], list[FrameTracks]]:
    if len(gt_frames) != len(pred_frames):
        raise ValueError(f"gt has {len(gt_frames)} frames, tracker {len(pred_frames)}: align them first")
    return [_as_frame(f) for f in gt_frames], [_as_frame(f) for f in pred_frames]


# --------------------------------------------------------------------------- CLEAR-MOT


@dataclass(frozen=True)
class ClearMot:
    num_frames: int
    num_objects: int  # gt detections
    num_predictions: int
    num_tp: int  # matched pairs incl. switches (TrackEval CLR_TP); motmetrics' num_matches = num_tp - IDSW
    num_false_positives: int
    num_misses: int
    num_switches: int
    mota: float
    motp: float  # mean (1 - IoU) over matches, motmetrics convention
    mean_match_iou: float  # = 1 - motp (TrackEval's MOTP)


def _max_card_min_cost(dist: np.ndarray, valid: np.ndarray) -> list[tuple[int, int]]:
    """Hungarian matching restricted to valid pairs: maximum number of pairs first, then minimum distance.

    Invalid pairs get a cost larger than any sum of valid costs (as motmetrics' solver does) so one more valid
    pair always beats any cost saving, then they are dropped from the result.
    """
    if not valid.any():
        return []
    big = float(dist[valid].sum()) + 1.0
    cost = np.where(valid, dist, big * (1 + min(dist.shape)))
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if valid[r, c]]


def clear_mot(gt_frames: Sequence, pred_frames: Sequence, *, iou_threshold: float = 0.5) -> ClearMot:
    gts, preds = _prepare(gt_frames, pred_frames)
    max_dist = 1.0 - iou_threshold
    last_match: dict[int, int] = {}  # gt id -> tracker id it was last matched to (kept across gaps)
    n_obj = n_pred = n_tp = n_fp = n_miss = n_sw = 0
    dist_sum = 0.0
    for (gid, gbox), (pid, pbox) in zip(gts, preds, strict=True):
        n_obj += len(gid)
        n_pred += len(pid)
        matched_g = np.zeros(len(gid), bool)
        matched_p = np.zeros(len(pid), bool)
        if len(gid) and len(pid):
            dist = 1.0 - iou_matrix(gbox, pbox)
            valid = dist <= max_dist  # same test as motmetrics (distance, not IoU, compared)
            # 1. keep still-valid correspondences from earlier frames
            for i, g in enumerate(gid):
                h = last_match.get(int(g))
                if h is None:
                    continue
                js = np.flatnonzero((pid == h) & ~matched_p)
                if js.size and valid[i, js[0]]:
                    j = int(js[0])
                    matched_g[i] = matched_p[j] = True
                    n_tp += 1
                    dist_sum += dist[i, j]
            # 2. Hungarian on the rest; a new partner for a previously matched gt id is a switch
            free = valid & ~matched_g[:, None] & ~matched_p[None, :]
            for i, j in _max_card_min_cost(dist, free):
                g, h = int(gid[i]), int(pid[j])
                if g in last_match and last_match[g] != h:
                    n_sw += 1
                last_match[g] = h
                matched_g[i] = matched_p[j] = True
                n_tp += 1
                dist_sum += dist[i, j]
        n_miss += int((~matched_g).sum())
        n_fp += int((~matched_p).sum())
    mota = 1.0 - (n_miss + n_fp + n_sw) / n_obj if n_obj else float("nan")
    motp = float(dist_sum / n_tp) if n_tp else float("nan")
    return ClearMot(num_frames=len(gts), num_objects=n_obj, num_predictions=n_pred, num_tp=n_tp,
                    num_false_positives=n_fp, num_misses=n_miss, num_switches=n_sw, mota=mota, motp=motp,
                    mean_match_iou=1.0 - motp)


# --------------------------------------------------------------------------- identity


@dataclass(frozen=True)
class IdentityScores:
    idtp: int
    idfp: int
    idfn: int
    idf1: float
    idp: float
    idr: float
    id_pairs: dict[int, int] = field(default_factory=dict)  # gt id -> tracker id of the global assignment


def _id_index(frames: list[FrameTracks]) -> dict[int, int]:
    ids = sorted({int(i) for f_ids, _ in frames for i in f_ids})
    return {i: k for k, i in enumerate(ids)}


def identity_scores(gt_frames: Sequence, pred_frames: Sequence, *, iou_threshold: float = 0.5) -> IdentityScores:
    gts, preds = _prepare(gt_frames, pred_frames)
    gidx, pidx = _id_index(gts), _id_index(preds)
    # co-occurrence counts: frames where gt id g and tracker id h are matchable (IoU >= threshold)
    tp = np.zeros((len(gidx), len(pidx)))
    n_gt = sum(len(f[0]) for f in gts)
    n_pred = sum(len(f[0]) for f in preds)
    max_dist = 1.0 - iou_threshold
    for (gid, gbox), (pid, pbox) in zip(gts, preds, strict=True):
        if len(gid) and len(pid):
            ok = (1.0 - iou_matrix(gbox, pbox)) <= max_dist
            r, c = np.nonzero(ok)
            np.add.at(tp, ([gidx[int(g)] for g in gid[r]], [pidx[int(h)] for h in pid[c]]), 1)
    pairs: dict[int, int] = {}
    idtp = 0
    if tp.size:
        # min IDFN + IDFP over one-to-one id assignments == max total IDTP
        rows, cols = linear_sum_assignment(-tp)
        inv_g = {k: i for i, k in gidx.items()}
        inv_p = {k: i for i, k in pidx.items()}
        for r, c in zip(rows, cols, strict=True):
            if tp[r, c] > 0:
                pairs[inv_g[r]] = inv_p[c]
                idtp += int(tp[r, c])
    idfn, idfp = n_gt - idtp, n_pred - idtp
    nan = float("nan")
    return IdentityScores(
        idtp=idtp, idfp=idfp, idfn=idfn,
        idf1=2 * idtp / (n_gt + n_pred) if n_gt + n_pred else nan,
        idp=idtp / n_pred if n_pred else nan, idr=idtp / n_gt if n_gt else nan, id_pairs=pairs)


# --------------------------------------------------------------------------- HOTA


@dataclass(frozen=True)
class Hota:
    hota: float
    deta: float
    assa: float
    loca: float
    detre: float
    detpr: float
    assre: float
    asspr: float
    hota_alpha: np.ndarray  # per α in HOTA_ALPHAS
    deta_alpha: np.ndarray
    assa_alpha: np.ndarray
    loca_alpha: np.ndarray
    hota0: float  # HOTA at α = 0.05 ("HOTA(0)" in TrackEval)


def hota(gt_frames: Sequence, pred_frames: Sequence) -> Hota:
    gts, preds = _prepare(gt_frames, pred_frames)
    na = len(HOTA_ALPHAS)
    gidx, pidx = _id_index(gts), _id_index(preds)
    ng, npr = len(gidx), len(pidx)
    n_gt_dets = sum(len(f[0]) for f in gts)
    n_pred_dets = sum(len(f[0]) for f in preds)
    tp = np.zeros(na)
    fn = np.zeros(na)
    fp = np.zeros(na)
    loc = np.zeros(na)

    def result(tp, fn, fp, loca, assa, assre, asspr) -> Hota:
        detre = tp / np.maximum(1, tp + fn)
        detpr = tp / np.maximum(1, tp + fp)
        deta = tp / np.maximum(1, tp + fn + fp)
        h = np.sqrt(deta * assa)
        return Hota(hota=float(h.mean()), deta=float(deta.mean()), assa=float(assa.mean()),
                    loca=float(loca.mean()), detre=float(detre.mean()), detpr=float(detpr.mean()),
                    assre=float(assre.mean()), asspr=float(asspr.mean()), hota_alpha=h, deta_alpha=deta,
                    assa_alpha=assa, loca_alpha=loca, hota0=float(h[0]))

    zeros, ones = np.zeros(na), np.ones(na)
    if n_pred_dets == 0 or n_gt_dets == 0:  # TrackEval's early exits (LocA defined as 1)
        return result(zeros, n_gt_dets * ones, n_pred_dets * ones, ones, zeros, zeros, zeros)

    frames = []
    for (gid, gbox), (pid, pbox) in zip(gts, preds, strict=True):
        gi = np.array([gidx[int(i)] for i in gid], dtype=np.int64)
        pi = np.array([pidx[int(i)] for i in pid], dtype=np.int64)
        frames.append((gi, pi, iou_matrix(gbox, pbox)))

    # Global alignment between ids: soft co-occurrence, each frame's IoU normalised like a Jaccard index.
    potential = np.zeros((ng, npr))
    g_count = np.zeros((ng, 1))
    p_count = np.zeros((1, npr))
    for gi, pi, sim in frames:
        denom = sim.sum(0)[None, :] + sim.sum(1)[:, None] - sim
        sim_iou = np.zeros_like(sim)
        mask = denom > _EPS
        sim_iou[mask] = sim[mask] / denom[mask]
        potential[gi[:, None], pi[None, :]] += sim_iou
        g_count[gi] += 1
        p_count[0, pi] += 1
    alignment = potential / (g_count + p_count - potential)

    matches = np.zeros((na, ng, npr))
    for gi, pi, sim in frames:
        if len(gi) == 0 or len(pi) == 0:
            fp += len(pi)
            fn += len(gi)
            continue
        # One assignment per frame for all α: it maximises alignment-weighted similarity, then each α
        # keeps only the pairs whose IoU reaches it.
        rows, cols = linear_sum_assignment(-(alignment[gi[:, None], pi[None, :]] * sim))
        s = sim[rows, cols]
        for a, alpha in enumerate(HOTA_ALPHAS):
            keep = s >= alpha - _EPS
            k = int(keep.sum())
            tp[a] += k
            fn[a] += len(gi) - k
            fp[a] += len(pi) - k
            if k:
                loc[a] += s[keep].sum()
                matches[a, gi[rows[keep]], pi[cols[keep]]] += 1

    assa = np.zeros(na)
    assre = np.zeros(na)
    asspr = np.zeros(na)
    for a in range(na):
        m = matches[a]
        denom_tp = max(1.0, tp[a])
        assa[a] = np.sum(m * (m / np.maximum(1, g_count + p_count - m))) / denom_tp
        assre[a] = np.sum(m * (m / np.maximum(1, g_count))) / denom_tp
        asspr[a] = np.sum(m * (m / np.maximum(1, p_count))) / denom_tp
    loca = np.maximum(1e-10, loc) / np.maximum(1e-10, tp)
    return result(tp, fn, fp, loca, assa, assre, asspr)


# --------------------------------------------------------------------------- all together


@dataclass(frozen=True)
class MotMetrics:
    clear: ClearMot
    identity: IdentityScores
    hota: Hota

    @property
    def mota(self) -> float:
        return self.clear.mota

    @property
    def idf1(self) -> float:
        return self.identity.idf1

    @property
    def hota_score(self) -> float:
        return self.hota.hota

    def as_dict(self) -> dict[str, float | int]:
        c, i, h = self.clear, self.identity, self.hota
        return {
            "frames": c.num_frames, "gt_dets": c.num_objects, "pred_dets": c.num_predictions,
            "tp": c.num_tp, "fp": c.num_false_positives, "fn": c.num_misses,
            "idsw": c.num_switches, "mota": c.mota, "motp": c.motp, "idtp": i.idtp, "idfp": i.idfp,
            "idfn": i.idfn, "idf1": i.idf1, "idp": i.idp, "idr": i.idr, "hota": h.hota, "deta": h.deta,
            "assa": h.assa, "loca": h.loca,
        }


def evaluate_mot(gt_frames: Sequence, pred_frames: Sequence, *, iou_threshold: float = 0.5) -> MotMetrics:
    """CLEAR-MOT + identity at ``iou_threshold``, HOTA over its own α range (threshold not used)."""
    return MotMetrics(clear=clear_mot(gt_frames, pred_frames, iou_threshold=iou_threshold),
                      identity=identity_scores(gt_frames, pred_frames, iou_threshold=iou_threshold),
                      hota=hota(gt_frames, pred_frames))


def evaluate_mot_combined(sequences: Iterable[tuple[Sequence, Sequence]], *,
                          iou_threshold: float = 0.5) -> MotMetrics:
    """Several sequences as one benchmark, as TrackEval combines them: counts summed, AssA and LocA weighted
    by true positives. Computed on the concatenated frames with ids made disjoint per sequence, which is
    exactly that: every id pair lives within one sequence, so matching and alignment never cross them."""
    gt_all: list[FrameTracks] = []
    pred_all: list[FrameTracks] = []
    offset = 0
    for gt_frames, pred_frames in sequences:
        gts, preds = _prepare(gt_frames, pred_frames)
        top = max([int(f[0].max()) for f in gts + preds if len(f[0])] + [0])
        low = min([int(f[0].min()) for f in gts + preds if len(f[0])] + [0])
        shift = offset - low
        gt_all += [(ids + shift, boxes) for ids, boxes in gts]
        pred_all += [(ids + shift, boxes) for ids, boxes in preds]
        offset += top - low + 1
    return evaluate_mot(gt_all, pred_all, iou_threshold=iou_threshold)


# --------------------------------------------------------------------------- MOTChallenge text files

_SPLIT = re.compile(r"[,\s]+")


def _mot_rows(path: str | Path) -> Iterator[list[float]]:
    """The numeric fields of each row of a MOTChallenge text file (blank and # lines skipped)."""
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = [p for p in _SPLIT.split(line) if p]
            if len(parts) < 6:
                raise ValueError(f"{path}:{lineno}: expected >= 6 fields, got {len(parts)}")
            yield [float(p) for p in parts]


def load_mot_file(
    path: str | Path,
    *,
    is_gt: bool = False,
    min_confidence: float | None = None,
    classes: Iterable[int] | None = None,
) -> dict[int, FrameTracks]:
    """Read a MOTChallenge text file ``frame,id,x,y,w,h,conf[,class,visibility,...]`` → {frame: (ids, boxes)}.

    Row filtering:

    * ``min_confidence`` given: keep rows with ``conf >= min_confidence`` — exactly motmetrics'
      ``load_motchallenge`` (its default -1 keeps everything; its MOTChallenge app passes 1 for gt).
    * otherwise, for ``is_gt``: drop rows whose conf is 0, the MOTChallenge "ignore this box" flag
      (TrackEval's zero-marked rule). On gt whose conf column is 0/1 (MOT16/17, motmetrics' TUD-Campus copy)
      this equals motmetrics' ``min_confidence=1``; but MOT15 files that mark every gt row conf = -1 (e.g. the
      TUD-Campus gt in our data tree) would lose *every* row with ``min_confidence=1``, so -1 is kept.
    * tracker files (``is_gt`` False, no ``min_confidence``): keep everything (conf is a score).
    * ``classes``: keep only these class ids when a class column exists and is positive (MOT16+); rows with
      a missing or -1 class (MOT15) are kept. Default: no class filter, like motmetrics' mot15-2D loader.

    Coordinates are returned as written (MOTChallenge is 1-based; motmetrics subtracts 1 from x and y, which
    IoU-based metrics do not see). Frames absent from the file are absent from the dict.
    """
    keep_classes = None if classes is None else {int(c) for c in classes}
    rows: list[tuple[int, int, float, float, float, float]] = []
    for vals in _mot_rows(path):
        conf = vals[6] if len(vals) > 6 else 1.0
        if min_confidence is not None:
            if conf < min_confidence:
                continue
        elif is_gt and conf == 0:
            continue
        if keep_classes is not None and len(vals) > 7 and vals[7] > 0 and int(vals[7]) not in keep_classes:
            continue
        rows.append((int(vals[0]), int(vals[1]), vals[2], vals[3], vals[4], vals[5]))
    out: dict[int, tuple[list[int], list[list[float]]]] = {}
    for fr, tid, x, y, w, h in rows:
        ids, boxes = out.setdefault(fr, ([], []))
        if tid in ids:
            raise ValueError(f"{path}: id {tid} appears twice in frame {fr}")
        ids.append(tid)
        boxes.append([x, y, w, h])
    log.debug("loaded %s: %d rows in %d frames", path, len(rows), len(out))
    return {fr: (np.asarray(ids, dtype=np.int64), np.asarray(boxes, dtype=float).reshape(-1, 4))
            for fr, (ids, boxes) in sorted(out.items())}


def load_mot_regions(path: str | Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Every gt row of a MOT16/17 file, ignored ones included: {frame: (boxes (n, 4), is_distractor (n,))},
    the input of :func:`remove_distractor_matches`. Files without a positive class column (MOT15) have no
    distractors: {}."""
    rows: dict[int, tuple[list[list[float]], list[bool]]] = {}
    for vals in _mot_rows(path):
        if len(vals) < 8 or vals[7] <= 0:
            continue
        boxes, distractor = rows.setdefault(int(vals[0]), ([], []))
        boxes.append(vals[2:6])
        distractor.append(int(vals[7]) in DISTRACTOR_CLASSES)
    if not any(any(d) for _, d in rows.values()):
        return {}
    return {fr: (np.asarray(b, dtype=float).reshape(-1, 4), np.asarray(d, dtype=bool)) for fr, (b, d) in rows.items()}


def remove_distractor_matches(pred_frames: Sequence, regions: Sequence[tuple[np.ndarray, np.ndarray] | None], *,
                              iou_threshold: float = 0.5) -> list[FrameTracks]:
    """MOTChallenge preprocessing (TrackEval ``get_preprocessed_seq_data``): per frame, tracker boxes are
    matched one-to-one (Hungarian, IoU >= 0.5) against *all* gt rows, ignored ones included, and those
    matched to a distractor-class row are removed: neither a false positive nor a true positive."""
    if len(regions) != len(pred_frames):
        raise ValueError(f"{len(regions)} region frames for {len(pred_frames)} tracker frames")
    out: list[FrameTracks] = []
    for frame, region in zip(pred_frames, regions, strict=True):
        ids, boxes = _as_frame(frame)
        if region is None or not len(ids) or not region[1].any():
            out.append((ids, boxes))
            continue
        all_boxes, distractor = region
        iou = iou_matrix(all_boxes, boxes)
        iou[iou < iou_threshold - _EPS] = 0.0
        rows, cols = linear_sum_assignment(-iou)
        matched = iou[rows, cols] > _EPS
        drop = cols[matched][distractor[rows[matched]]]
        keep = np.ones(len(ids), dtype=bool)
        keep[drop] = False
        out.append((ids[keep], boxes[keep]))
    return out


def align_frames(
    gt: dict[int, FrameTracks], pred: dict[int, FrameTracks], *, first: int | None = None,
    last: int | None = None,
) -> tuple[list[FrameTracks], list[FrameTracks]]:
    """Turn two {frame: (ids, boxes)} dicts into aligned lists over frames ``first..last`` (default: the
    union of both files' frame ranges); a frame missing from one side becomes an empty frame."""
    frames = set(gt) | set(pred)
    if not frames and (first is None or last is None):
        return [], []
    lo = min(frames) if first is None else first
    hi = max(frames) if last is None else last
    empty: FrameTracks = (np.zeros(0, dtype=np.int64), np.zeros((0, 4)))
    return ([gt.get(t, empty) for t in range(lo, hi + 1)], [pred.get(t, empty) for t in range(lo, hi + 1)])
