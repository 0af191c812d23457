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
A template node that restarted knowing no target does not erase it: it re-learns the target from this node.

A re-ID (re)started while the graph follows someone (prediction's prior is initialised) has no template: the last
one went out before it subscribed. It publishes "no target" (UNINITIALISED: prediction coasts, the motor stops) for
up to ``template_wait_ms`` while the template node answers those measurements with its template, then re-acquires
the target by its appearance inside the gate. Without a template by then (no template node, or one that learnt
nothing), it initialises on the gated detection nearest the prior and says so in a warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bus.background import BackgroundJob
from ..bus.node import In, Node, Out
from ..bus.node_params import ParamError
from ..bus.schemas import Frame, Message
from ..msgs.perception import Detections, RegionDetections
from ..msgs.tracking import Measurement, Prior, Template, TrackState
from ..tracking.params import ReidParams
from ..tracking.redetection import RegionBoxes
from ..tracking.reid import ReIdentifier, measurement

# init_box describes the target at the start of the source: a re-ID node (re)started later in the run, or
# joining a capture that restarted long ago, re-acquires the target from its template instead. A capture that
# restarts (a new session) offers it again, and a re-ID that follows someone takes it only if the target stands
# there (ReIdentifier._init_box_holds_the_target): after a live camera's restart a passer-by may.
INIT_BOX_MAX_FRAME = 10


@dataclass
class ReidNodeParams:
    # [x, y, w, h] of the target on the first frame (followbus demo sets it from the source's first ground-truth box)
    init_box: list[float] = field(default_factory=list, metadata={"demo": "init_box"})
    # How long a re-ID that joins a graph already following someone waits for the template node's template before
    # it initialises on the detection nearest the prior alone (capture time; the template comes one frame after
    # the first measurement, more under load). 0: do not wait.
    template_wait_ms: float = 500.0

    def __post_init__(self) -> None:
        if self.init_box and len(self.init_box) != 4:
            raise ParamError("init_box", "init_box must be [x, y, w, h]")
        if not self.template_wait_ms >= 0.0:
            raise ParamError("template_wait_ms", "template_wait_ms must be >= 0")


class Reid(Node):
    INPUTS = {"frame": In(Frame, required=True), "detections": In(Detections, required=True),
              "prior": In(Prior, required=True), "template": In(Template), "region": In(RegionDetections)}
    OUTPUTS = {"measurement": Out(Measurement)}
    Params = (ReidNodeParams, ReidParams)

    def setup(self) -> None:
        # The learned appearance's training sample (OSNet descriptors of several people: a 20-30 ms burst every
        # identity_sample_every_frames frames) below the loop's priority: at the loop's, on two cores, the
        # detector skips a frame at each burst (bus/background.py). One worker thread per process: setup runs
        # again when the runtime rebuilds the node's state, and the old identifier's last sample is dropped then.
        if hasattr(self, "learner"):
            self._drop_last_sample()
        else:
            self.learner = BackgroundJob("reid-learning")
        self.node_params, reid_params = self.params
        self.reid = ReIdentifier(reid_params)
        self.learned_appearance = self.reid.prepare()  # the model loads here, not on a frame
        self.template_hist: np.ndarray | None = None
        self.frames = 0
        self.epoch_ns: int | None = None  # the capture session of the frames handled so far
        self.last: Measurement | None = None
        self.initialised_at: tuple[int, int] | None = None  # (epoch_ns, frame_seq) of this node's last initialisation
        self.template_seen = False  # any template message since setup: the template node answers this node
        self.template_forgotten = False  # the template node restarted knowing no target; this node keeps its M
        self.waiting_since_ns: int | None = None  # capture stamp of the first frame spent waiting for a template

    def _drop_last_sample(self) -> None:
        try:
            self.learner.wait()
        except Exception as exc:  # noqa: BLE001 - a rebuild is already the recovery from a failure
            self.log.warning("reset: the last learning sample failed: %s", exc)

    def on_frame(self, frame_seq: int, inputs: dict[str, Message | None]) -> None:
        frame, dets, prior = inputs["frame"], inputs["detections"], inputs["prior"]
        assert isinstance(frame, Frame) and isinstance(dets, Detections) and isinstance(prior, Prior)
        template = inputs.get("template")
        if isinstance(template, Template) and not self._learnt_before_initialisation(template):
            self._take_template(template, frame.header.stamp_ns)
        if self._waits_for_template(prior, frame.header.stamp_ns):
            self.last = measurement(frame.header.stamp_ns, TrackState.UNINITIALISED)
            self.publish("measurement", self.last)
            return
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
        self.publish("measurement", result)
        # The learned appearance's sample (OSNet descriptors) after the measurement is out: off the motor's path.
        self.learner.submit(self.reid.learn_pending)

    def _take_template(self, template: Template, stamp_ns: int) -> None:
        """The template node's M. One that knows no target never erases the histogram this node matches against:
        a template node restarted without its state would otherwise make this node re-initialise on whoever is
        nearest the prior, and learn that person; it re-learns the target from this node's next secure lock."""
        if template.initialised and template.hist is not None:
            self.template_hist, self.template_forgotten = np.array(template.hist), False
        elif self.template_hist is not None and not self.template_forgotten:
            self.template_forgotten = True
            self.log.warning("the template node knows no target (restarted without its state file?): matching "
                             "against the last template, from which it re-learns the target")
        if not self.template_seen and self.waiting_since_ns is not None:
            self.log.info("template %s after %.0f ms of waiting", "received" if self.template_hist is not None
                          else "node knows no target", (stamp_ns - self.waiting_since_ns) / 1e6)
        self.template_seen = True

    def _waits_for_template(self, prior: Prior, stamp_ns: int) -> bool:
        """This node joined a graph that follows someone (the prior is initialised) and has heard nothing from the
        template node yet: initialising now would take the detection nearest a prior that coasted through the
        restart, maybe a bystander, and the template node would then re-learn the target from that box."""
        if self.template_seen or not prior.initialised or self.initialised_at is not None:
            return False
        if self.waiting_since_ns is None:
            self.waiting_since_ns = stamp_ns
            self.log.info("joined a graph that is following someone: waiting up to %.0f ms for the template before "
                          "re-acquiring the target", self.node_params.template_wait_ms)
        if (stamp_ns - self.waiting_since_ns) / 1e6 < self.node_params.template_wait_ms:
            return True
        self.template_seen = True  # waited long enough: do not wait again
        self.log.warning("no template from the template node within %.0f ms: initialising on the detection "
                         "nearest the prediction, whoever it is", self.node_params.template_wait_ms)
        return False

    def _learnt_before_initialisation(self, template: Template) -> bool:
        """A template the template node learnt before this node's last initialisation (a fallback to an older
        feedback): it describes the lock before, not the target now being followed."""
        if self.initialised_at is None:
            return False
        epoch_ns, frame_seq = self.initialised_at
        return template.header.epoch_ns == epoch_ns and template.header.frame_seq < frame_seq

    def teardown(self) -> None:
        self.learner.wait()

    def status(self) -> dict[str, Any]:
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
