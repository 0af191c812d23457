"""reid: seed 000 Algorithm 1 for every frame: candidates inside the Mahalanobis gate (detections,
or frame-difference blobs when the detector gives none), S_color (Eq. 1) and S_geo fused with the
sigmoid weight of Eq. 3 (Eq. 2), accept above T_reid, else report OCCLUDED; LOST after
``lost_after_ms``. Initialises the target on the first frame (``init_box`` param, else the
detection nearest the image centre-bottom, else the frame-difference ROI).

When colour and geometry cannot tell candidates apart (or on a re-lock after an occlusion), the learned
appearance of seed 001 decides: OSNet descriptors and an online ridge-regression classifier of the target
against the other people (tracking/learned_appearance.py; ``learned_appearance: false`` turns it off, and without the
model the node warns once and goes on with colour).

Inputs joined by frame: frame k, detections k, prior k, the region re-detected around prior k (the redetection
node, seed 002 §3.2: optional) and the template learnt at frame k-1 (offset -1). If that template is missing (a
dropped frame upstream), the last one received is used; after this node initialised the target, that is the
histogram of the initial box (what the template node learns from it), until the template node's own comes back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bus.background import BackgroundJob
from ..bus.node import Node, ParamError
from ..bus.schemas import Frame, Message
from ..msgs.perception import Detections, RegionDetections
from ..msgs.tracking import Measurement, Prior, Template
from ..tracking.params import ReidParams
from ..tracking.redetection import RegionBoxes
from ..tracking.reid import ReIdentifier

# init_box describes the target at the start of the source: a re-ID node (re)started later in the run, or
# joining a capture that restarted long ago, re-acquires the target from its template instead.
INIT_BOX_MAX_FRAME = 10


@dataclass
class ReidNodeParams:
    init_box: list[float] = field(default_factory=list)  # [x, y, w, h] of the target on the first frame


class Reid(Node):
    INPUTS = {"frame": Frame, "detections": Detections, "prior": Prior, "template": Template,
              "region": RegionDetections}
    REQUIRED_INPUTS = frozenset({"frame", "detections", "prior"})
    OUTPUTS = {"measurement": Measurement}
    INIT_BOX_PARAM = "init_box"  # followbus demo sets it from the source's first ground-truth box
    Params = (ReidNodeParams, ReidParams)
    RENAMED_PARAMS = {"n_id": "n_id_frames"}  # issue 24: units in the names
    # Read from the ReidParams object on every decision (tracking/reid.py), so `followbus param set` takes effect
    # on the next frame.
    LIVE_PARAMS = frozenset({"reid_threshold"})

    @classmethod
    def parse_params(cls, raw: dict[str, Any]) -> tuple[ReidNodeParams, ReidParams]:
        node_params, reid_params = super().parse_params(raw)
        if node_params.init_box and len(node_params.init_box) != 4:
            raise ParamError("init_box", "init_box must be [x, y, w, h]")
        return node_params, reid_params

    def setup(self) -> None:
        self.node_params, reid_params = self.params
        self.reid = ReIdentifier(reid_params)
        self.learned_appearance = self.reid.prepare()  # the model loads here, not on a frame
        self.template_hist: np.ndarray | None = None
        self.frames = 0
        self.epoch_ns: int | None = None  # the capture session of the frames handled so far
        self.last: Measurement | None = None
        self.initialised_at: tuple[int, int] | None = None  # (epoch_ns, frame_seq) of this node's last initialisation
        # The learned appearance's training sample (OSNet descriptors of several people: a 20-30 ms burst every
        # identity_sample_every_frames frames) below the loop's priority: at the loop's, on two cores, the
        # detector skips a frame at each burst (bus/background.py).
        if not hasattr(self, "learner"):  # setup runs again on a reset (below): one worker thread per process
            self.learner = BackgroundJob("reid-learning")

    def reset(self) -> None:
        try:
            self.learner.wait()  # the old identifier's last sample: dropped with it
        except Exception as exc:  # noqa: BLE001 - a reset is already the recovery from a failure
            self.log.warning("reset: the last learning sample failed: %s", exc)
        super().reset()

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        frame, dets, prior = inputs["frame"], inputs["detections"], inputs["prior"]
        assert isinstance(frame, Frame) and isinstance(dets, Detections) and isinstance(prior, Prior)
        template = inputs.get("template")
        if isinstance(template, Template) and not self._learnt_before_initialisation(template):
            self.template_hist = None if not template.initialised or template.hist is None else np.array(template.hist)
        self.learner.wait()  # the previous frame's sample is learnt before this frame is decided: results as in order
        new_source = frame.header.epoch_ns != self.epoch_ns
        self.epoch_ns = frame.header.epoch_ns
        init_box = None
        if self.node_params.init_box and new_source and frame_seq < INIT_BOX_MAX_FRAME:
            init_box = self.node_params.init_box
        region = inputs.get("region")
        result = self.reid.step(frame.data, dets.boxes, prior if prior.initialised else None, self.template_hist,
                                frame.header.stamp_ns, init_box=init_box, defer_learning=True,
                                low_detections=dets.low_boxes,  # the second stage's (low_score_stage)
                                region=_region_boxes(region))
        self.frames += 1
        if result.init_box is not None and result.candidate_hist is not None:
            # The template node initialises its template from this box (tracking/template.py); until that template
            # comes back, match against the same histogram: without one every frame re-initialises, and a re-ID
            # restarted with a backlog would re-initialise frame after frame, maybe on a bystander.
            self.template_hist = np.array(result.candidate_hist)
            self.initialised_at = (frame.header.epoch_ns, frame_seq)
        self.last = result
        self.publish("measurement", result, like=frame)
        # The learned appearance's sample (OSNet descriptors) after the measurement is out: off the motor's path.
        self.learner.submit(self.reid.learn_pending)

    def _learnt_before_initialisation(self, template: Template) -> bool:
        """A template the template node learnt before this node's last initialisation (a fallback to an older
        feedback): it describes the lock before, not the target now being followed."""
        if self.initialised_at is None:
            return False
        epoch_ns, frame_seq = self.initialised_at
        return template.header.epoch_ns == epoch_ns and template.header.frame_seq < frame_seq

    def teardown(self) -> None:
        self.learner.wait()

    def status_extra(self) -> dict[str, Any]:
        if self.last is None:
            return {"frames": 0}
        return {"frames": self.frames, "state": self.last.state, "m_fuse": round(self.last.m_fuse, 3),
                "learned_appearance": self.learned_appearance, "identity_decisions": self.reid.identity_decisions}


def _region_boxes(msg: Message | None) -> RegionBoxes | None:
    """What the redetection node found around the prediction (seed 002 §3.2), when it looked."""
    if not isinstance(msg, RegionDetections) or not msg.reason:
        return None
    x0, y0, x1, y1 = (int(v) for v in msg.region)
    return RegionBoxes((x0, y0, x1, y1), np.asarray(msg.boxes), np.asarray(msg.low_boxes))


NODE = Reid
