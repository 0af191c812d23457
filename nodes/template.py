"""template: owns the reference appearance model M (16x8 H-S histogram).

M ← (1-η_k)M + η_k C* (Alg. 1 line 12) with η_k = η_base·exp(-λ P_specular) when the target is
tracked securely and 0 under occlusion (Eq. 9-10). Publishes M and η_k every frame; saves M to
``state_file`` (atomically, every ``save_every_s`` and at shutdown) and restores it when the node is restarted
within the same launch (a crash, the launcher's restart policy), so re-ID does not have to learn the target
again. A file saved by another launch is not restored unless it is at most ``restore_other_launch_max_age_s``
old (default 0: never): a new launch may follow another person, and a stale template would make re-ID refuse
the target it was just told to follow, while the first secure frames re-learn M anyway. Without M (a restart
without a state file), it learns M back from re-ID's next secure lock: re-ID follows on with the last M it was
sent. ``{namespace}`` in ``state_file`` is the graph's namespace (graph.yaml: ``state/{namespace}/template.npz``):
two graphs launched from one directory keep their own template.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..bus.node import In, Node, Out
from ..bus.node_runtime import LAUNCH_ID_ENV
from ..bus.schemas import Frame, Message
from ..msgs.tracking import Measurement, Template
from ..tracking.params import TemplateParams, check_ranges
from ..tracking.template import TemplateUpdater


@dataclass
class TemplateNodeParams:
    # e.g. state/{namespace}/template.npz ({namespace}: the graph's); empty: do not persist
    state_file: str = field(default="", metadata={"state_file": True})
    save_every_s: float = 5.0
    # A template saved by another launch (not this launch's earlier process) is restored only if at most this
    # old; 0: never (a new launch learns its target afresh).
    restore_other_launch_max_age_s: float = 0.0

    def __post_init__(self) -> None:
        check_ranges(self, positive=("save_every_s",), non_negative=("restore_other_launch_max_age_s",))


def state_path(state_file: str, namespace: str) -> Path | None:
    """Where the template is kept: ``state_file`` with ``{namespace}`` replaced (None: not persisted)."""
    return Path(state_file.replace("{namespace}", namespace)) if state_file else None


class TemplateNode(Node):
    INPUTS = {"frame": In(Frame, required=True), "measurement": In(Measurement, required=True)}
    OUTPUTS = {"template": Out(Template)}
    Params = (TemplateNodeParams, TemplateParams)

    def setup(self) -> None:
        self.node_params, template_params = self.params
        self.updater = TemplateUpdater(template_params)
        self.last_save = time.monotonic()
        self.save_failures = 0
        self.eta = 0.0
        self.p_specular = 0.0
        self.launch_id = os.environ.get(LAUNCH_ID_ENV, "")
        path = self._state_path()
        if path is not None and path.exists():
            try:
                self.updater.load(path)
                saved_by = self.updater.saved_by
                age_s = time.time() - path.stat().st_mtime
                same_launch = bool(self.launch_id) and saved_by == self.launch_id
                if same_launch or age_s <= self.node_params.restore_other_launch_max_age_s:
                    self.log.info("restored template from %s (%s)", path,
                                  "this launch's earlier process" if same_launch else f"saved {age_s:.0f} s ago")
                else:
                    self.updater.reset()
                    self.log.info("not restoring the template in %s: saved by another launch %.0f s ago "
                                  "(restore_other_launch_max_age_s %.0f); learning the target afresh", path, age_s,
                                  self.node_params.restore_other_launch_max_age_s)
            except Exception as exc:  # a corrupt file must not stop the robot: start fresh
                self.updater.reset()
                self.log.warning("could not restore template from %s (%s); starting without one", path, exc)

    def _state_path(self) -> Path | None:
        return state_path(self.node_params.state_file, self.runtime.graph.namespace)

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        frame, meas = inputs["frame"], inputs["measurement"]
        assert isinstance(frame, Frame) and isinstance(meas, Measurement)
        hist, self.eta, self.p_specular = self.updater.step(frame.data, meas)
        msg = Template(initialised=hist is not None, hist=None if hist is None else np.asarray(hist),
                       eta=float(self.eta), p_specular=float(self.p_specular))
        self.publish("template", msg)
        if time.monotonic() - self.last_save >= self.node_params.save_every_s:
            self._save()

    def _save(self) -> None:
        path = self._state_path()
        self.last_save = time.monotonic()
        if path is None or not self.updater.initialised:
            return
        tmp = path.with_name(path.stem + ".tmp.npz")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.updater.save(tmp, saved_by=self.launch_id)
            os.replace(tmp, path)
        except OSError as exc:  # a full disk or a file made read-only: the robot follows on; a restart learns afresh
            self.save_failures += 1
            if self.save_failures == 1 or self.save_failures % 100 == 0:
                self.log.warning("cannot save the template to %s (%s; %d failures so far): a restarted template node "
                                 "will learn the target afresh", path, exc.strerror or exc, self.save_failures)

    def teardown(self) -> None:
        self._save()

    def status(self) -> dict[str, Any]:
        return {"eta": round(self.eta, 5), "p_specular": round(self.p_specular, 4),
                "initialised": self.updater.initialised, "save_failures": self.save_failures}


NODE = TemplateNode
