"""What the tracker outputs for a frame.

The graph's data order for frame k (seed 000 §2, with seed 002 §3.3's camera motion) is not written here: it is
the graph's, in graph.yaml and the nodes' synchronisers, and evaluation runs those same nodes in-process
(evaluation/graph_follower.py)::

    C_k      egomotion: camera motion k-1 → k, or none
    prior_k  prediction: after frame k-1's measurement, warped by C_k
    reid_k   reid: frame k, detections k, prior_k, the template of k-1
    track_k  prediction: update only if accepted (Eq. 7 R_k), output_box below
    M_k, η_k template: frame k, reid_k
"""

from __future__ import annotations

import numpy as np

from ..msgs.tracking import Measurement, Prior, TrackState


def output_box(reid: Measurement, prior: Prior | None) -> np.ndarray | None:
    """The tracker's output for a frame: the accepted box; while OCCLUDED the predicted box (§2.3:
    keep following the hidden trajectory: the likeliest motion model's) as long as it still locates the person
    (Prior.locates_person: it more likely overlaps them than not, KalmanParams.occluded_output_min_overlap_probability);
    None when LOST, before initialisation or when the prediction no longer locates the person. The prediction node
    publishes exactly this as its Track message's ``box``."""
    if reid.accepted:
        return reid.box
    if reid.state != TrackState.OCCLUDED or prior is None or not prior.initialised or not prior.locates_person:
        return None
    return prior.box if prior.likeliest_box is None else prior.likeliest_box
