"""Reference appearance model M and its adaptive update (paper §2.4, Eq. 9-10, Alg. 1 line 12)."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

import numpy as np

from ..msgs.tracking import Measurement
from .appearance import hs_histogram, learning_rate, specular_penalty
from .params import TemplateParams

logger = logging.getLogger(__name__)


class TemplateUpdater:
    """Owns M (bins_h x bins_s H-S histogram, float32, sums to 1).

    η_k (Eq. 10) is η_base·exp(-λ·P_specular) on a secure match and 0 otherwise (occluded, lost,
    re-lock not yet confirmed, ambiguous or motion-blob match). Ablations: ``adaptive_eta=False``
    uses η_base on every accepted match (no specular penalty, no security check);
    ``suspend_updates=False`` also blends in the best rejected candidate.
    """

    def __init__(self, params: TemplateParams | None = None) -> None:
        self.params = params or TemplateParams()
        self.hist: np.ndarray | None = None
        self.saved_by = ""  # of the file :meth:`load` read last

    @property
    def initialised(self) -> bool:
        return self.hist is not None

    def initialise(self, frame_bgr: np.ndarray, box: Sequence[float]) -> np.ndarray:
        """M ← histogram of the initial ROI (§2.1)."""
        p = self.params
        self.hist = hs_histogram(frame_bgr, box, p.bins_h, p.bins_s)
        logger.info("template initialised from box %s", tuple(round(float(v), 1) for v in box[:4]))
        return self.hist.copy()

    def step(self, frame_bgr: np.ndarray, measurement: Measurement) -> tuple[np.ndarray | None, float, float]:
        """Apply frame k's re-ID measurement; returns (M_k, η_k, P_specular)."""
        p = self.params
        if measurement.init_box is not None:
            p_specular = specular_penalty(frame_bgr, measurement.init_box, p.tau_v, p.tau_s)
            if measurement.source == "template" and self.hist is not None:
                return self.hist.copy(), 0.0, p_specular  # re-locked with this very template: keep it
            return self.initialise(frame_bgr, measurement.init_box), 0.0, p_specular
        if self.hist is None:
            if measurement.accepted and measurement.secure and measurement.box is not None:
                # Restarted without M while re-ID follows on with the M sent before: learn the target back from
                # re-ID's secure lock (that is, the target as the old M recognised it), not from a new init.
                return self.initialise(frame_bgr, measurement.box), 0.0, 0.0
            return None, 0.0, 0.0
        if measurement.accepted and measurement.box is not None:
            box, secure = measurement.box, measurement.secure
        elif not p.suspend_updates and measurement.best_box is not None:
            box, secure = measurement.best_box, True  # ablation: no occlusion-triggered freeze
        else:
            return self.hist.copy(), 0.0, 0.0  # Eq. 10 second branch: occlusion persists, η = 0
        p_specular = specular_penalty(frame_bgr, box, p.tau_v, p.tau_s)  # Eq. 9
        # Eq. 10; the ablation without adaptive η uses η_base on every update.
        eta = learning_rate(p_specular, secure, p.eta_base, p.lambda_specular) if p.adaptive_eta else p.eta_base
        if eta > 0.0:
            c_star = measurement.candidate_hist
            if c_star is None:
                c_star = hs_histogram(frame_bgr, box, p.bins_h, p.bins_s)
            self.hist = self.blend(self.hist, c_star, eta)
        return self.hist.copy(), eta, p_specular

    @staticmethod
    def blend(m: np.ndarray, c_star: np.ndarray, eta: float) -> np.ndarray:
        """Alg. 1 line 12: M ← (1 - η) M + η C*, renormalised against float drift."""
        new = (1.0 - eta) * np.asarray(m, dtype=np.float64) + eta * np.asarray(c_star, dtype=np.float64)
        total = new.sum()
        if total > 0.0:
            new /= total
        return new.astype(np.float32)

    def reset(self) -> None:
        """Forget M: the next accepted target box initialises it again."""
        self.hist = None

    def save(self, path: str | os.PathLike[str], saved_by: str = "") -> None:
        """Write M to an .npz (atomically, so a crash never leaves a torn file for the restart); ``saved_by``
        names the run that saved it (the template node: its launch), read back as :attr:`saved_by`."""
        if self.hist is None:
            raise ValueError("no template to save: TemplateUpdater is not initialised")
        path = os.fspath(path)
        tmp = f"{path}.tmp"
        with open(tmp, "wb") as f:
            np.savez(f, hist=self.hist, bins=np.array([self.params.bins_h, self.params.bins_s]),
                     saved_by=np.array(saved_by))
        os.replace(tmp, path)

    def load(self, path: str | os.PathLike[str]) -> np.ndarray:
        """Restore M saved by :meth:`save`; the bin layout must match these params. Sets :attr:`saved_by`
        ("" for files written before it was stored)."""
        with np.load(os.fspath(path)) as data:
            hist = np.asarray(data["hist"], dtype=np.float32)
            self.saved_by = str(data["saved_by"]) if "saved_by" in data.files else ""
        expected = (self.params.bins_h, self.params.bins_s)
        if hist.shape != expected:
            raise ValueError(f"template in {os.fspath(path)!r} has shape {hist.shape}, expected {expected}")
        if not np.all(np.isfinite(hist)) or hist.min() < 0.0 or hist.sum() <= 0.0:
            raise ValueError(f"template in {os.fspath(path)!r} is not a histogram")
        self.hist = (hist / hist.sum()).astype(np.float32)
        return self.hist.copy()
