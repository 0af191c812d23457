"""Learned appearance (seed 001 §III-C/D): a CNN person descriptor and an online ridge-regression classifier
of "the target" against "the other people", trained from short-term and long-term samples.

Why beside seed 000's colour histogram: a 16×8 H-S histogram cannot tell two people in dark clothes apart
(otb-human3: S_color 0.93 on the target and 0.94 on the walker beside it), while a re-ID descriptor trained
to separate identities can; the histogram, cheap and available from the first frame, keeps deciding whenever
the choice is clear. So the classifier is consulted only when a decision needs it (:mod:`tracking.reid`):
several candidates close in M_fuse, or a re-lock after an occlusion.

* :class:`PersonEmbedder`: OSNet-x0.25 (models/README.md) on the person crops of one frame, batched,
  L2-normalised 512-d descriptors.
* :class:`TargetClassifier`: ridge regression w = (XᵀX + λI)⁻¹ Xᵀy (seed 001 §III-C, L2-regularised to
  stay sane on a few dozen samples) on descriptors labelled 1 (target) and 0 (other people), refitted when
  samples change. Its sample set is the latest ``short_term_samples`` plus ``long_term_samples`` older ones
  kept one in ``long_term_every`` (seed 001's short-long-term set, "experience replay": the latest samples
  alone over-fit the current view).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

OSNET_MODEL = "osnet_x0_25_msmt17.onnx"
CROP_W_PX, CROP_H_PX = 128, 256
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
# The normalised value of each 8-bit level per RGB channel, computed as the crop would be ((v / 255 - mean) / std in
# float32): a crop is then three table lookups, the same values at a quarter of the arithmetic's cost.
_LEVELS = ((np.arange(256, dtype=np.uint8).astype(np.float32) / 255.0)[:, None] - IMAGENET_MEAN) / IMAGENET_STD
_RGB_LEVELS = [np.ascontiguousarray(_LEVELS[:, c]) for c in range(3)]


class PersonEmbedder:
    """OSNet person descriptors of boxes in one frame (one batched inference)."""

    def __init__(self, model_path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(int(threads), 1)
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self.session = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
        self.input_name = self.session.get_inputs()[0].name

    @staticmethod
    def crops(frame_bgr: np.ndarray, boxes: Sequence[Sequence[float]]) -> np.ndarray:
        """(N, 3, 256, 128) float32: each box clamped to the frame, resized, RGB, ImageNet-normalised."""
        import cv2

        h, w = frame_bgr.shape[:2]
        out = np.zeros((len(boxes), 3, CROP_H_PX, CROP_W_PX), np.float32)
        for i, box in enumerate(boxes):
            x0, y0 = int(max(0.0, min(box[0], w - 1))), int(max(0.0, min(box[1], h - 1)))
            x1 = int(max(x0 + 1, min(box[0] + box[2], w)))
            y1 = int(max(y0 + 1, min(box[1] + box[3], h)))
            patch = cv2.resize(frame_bgr[y0:y1, x0:x1], (CROP_W_PX, CROP_H_PX), interpolation=cv2.INTER_LINEAR)
            for c in range(3):  # RGB plane c from BGR channel 2 - c
                np.take(_RGB_LEVELS[c], patch[:, :, 2 - c], out=out[i, c])
        return out

    def embed(self, frame_bgr: np.ndarray, boxes: Sequence[Sequence[float]]) -> np.ndarray:
        """(N, 512) unit descriptors; (0, 512) for no box."""
        if len(boxes) == 0:
            return np.zeros((0, 512), np.float32)
        feats = self.session.run(None, {self.input_name: self.crops(frame_bgr, boxes)})[0]
        norms = np.linalg.norm(feats, axis=1, keepdims=True)
        return (feats / np.maximum(norms, 1e-12)).astype(np.float32)


def load_embedder(threads: int = 1) -> PersonEmbedder | None:
    """The OSNet embedder from the model search path, or None (logged loudly) when the file is absent or
    refused: re-ID then decides on colour and geometry alone (seed 000)."""
    from ..vision.models import ModelError, resolve_model

    try:
        path = resolve_model(OSNET_MODEL)
    except ModelError as exc:
        log.warning("learned appearance is off: %s; re-ID falls back to colour + geometry (seed 000)", exc)
        return None
    return PersonEmbedder(path, threads)


@dataclass
class IdentityParams:
    ridge_lambda: float = 1.0  # λ of the L2-regularised ridge regression (seed 001 §III-C)
    short_term_samples: int = 24  # latest descriptors kept per label
    long_term_samples: int = 24  # older descriptors kept per label, one in long_term_every
    long_term_every: int = 5
    delta_id: float = 0.60  # δ_id: a candidate is the target above this score (seed 001 §IV, Re-ID state)
    delta_switch: float = 0.35  # δ_switch: the tracked box scoring below this is suspected of a switch


class _SampleSet:
    def __init__(self, short: int, long: int, every: int) -> None:
        self.short: deque[np.ndarray] = deque(maxlen=short)
        self.long: deque[np.ndarray] = deque(maxlen=long)
        self.every = max(every, 1)
        self.count = 0

    def add(self, x: np.ndarray) -> None:
        if len(self.short) == self.short.maxlen:
            oldest = self.short[0]
            if self.count % self.every == 0:  # experience replay: keep some of what leaves the short set
                self.long.append(oldest)
        self.short.append(x)
        self.count += 1

    def all(self) -> list[np.ndarray]:
        return list(self.long) + list(self.short)


class TargetClassifier:
    """Online ridge regression of the target's identity over person descriptors (seed 001)."""

    def __init__(self, params: IdentityParams | None = None) -> None:
        self.params = params or IdentityParams()
        p = self.params
        self.positives = _SampleSet(p.short_term_samples, p.long_term_samples, p.long_term_every)
        self.negatives = _SampleSet(p.short_term_samples, p.long_term_samples, p.long_term_every)
        self.w: np.ndarray | None = None
        self._stale = False  # samples added since w was fitted

    @property
    def ready(self) -> bool:
        """Trained on the target and on at least one other person: only then does a score separate them."""
        has_positives = len(self.positives.short) + len(self.positives.long) > 0
        return has_positives and len(self.negatives.short) + len(self.negatives.long) > 0

    def reset(self) -> None:
        self.__init__(self.params)  # type: ignore[misc]

    def add(self, target: np.ndarray | None, others: np.ndarray) -> None:
        """One frame's samples: the confidently tracked target's descriptor and the other people's."""
        if target is not None:
            self.positives.add(np.asarray(target, np.float64))
        for x in np.asarray(others, np.float64).reshape(-1, target.shape[-1] if target is not None else 512):
            self.negatives.add(x)
        self._stale = True  # refitted when next asked to score: samples come far more often than decisions

    def _fit(self) -> None:
        self._stale = False
        pos, neg = self.positives.all(), self.negatives.all()
        if not pos:
            self.w = None
            return
        x = np.array(pos + neg)
        y = np.concatenate([np.ones(len(pos)), np.zeros(len(neg))])
        # Dual form w = Xᵀ(XXᵀ + λI)⁻¹y: the same w as (XᵀX + λI)⁻¹Xᵀy, solved in the n×n sample space
        # (n ≤ 96) instead of 512×512.
        gram = x @ x.T + self.params.ridge_lambda * np.eye(len(x))
        self.w = x.T @ np.linalg.solve(gram, y)

    def score(self, descriptors: np.ndarray) -> np.ndarray:
        """Predicted target-ness (≈1 target, ≈0 others) of each descriptor; zeros when untrained."""
        d = np.asarray(descriptors, np.float64)
        if self._stale:
            self._fit()
        if self.w is None or d.size == 0:
            return np.zeros(len(d))
        return d @ self.w
