"""Pure target-tracking algorithms (no bus imports).

"Seed NNN" names the method papers the code follows (../shared/seeds/NNN_*; "the paper" or a bare "§" is seed 000):

* seed 000: the rear-view tracker (Jia et al., Sensors 2026, 26(9), 2884): Kalman prior and χ² gate, colour +
  geometry fusion, the template and its learning rate η_k (kalman.py, reid.py, template.py);
* seed 001: "Following Closely" (Ye et al.): OSNet descriptors + an online ridge-regression identity
  (learned_appearance.py), width-based range (control/);
* seed 002: dual-motion-model small-object MOT: camera-motion compensation (§3.3, egomotion.py), adaptive gate and
  local re-detection (§3.2, redetection.py), low-score second stage (§3.1, ByteTrack, reid.py);
* seed 004: multi-ellipse group tracking (Drones 2025, 9(9), 620): group following (group.py, groundplane.py).

The graph's data order for frame k (seed 000 §2, with seed 002 §3.3's camera motion) lives in graph.yaml and the
nodes' synchronisers, and evaluation runs those same nodes in-process (evaluation/graph_follower.py)::

    C_k      egomotion: camera motion k-1 → k, or none
    prior_k  prediction: after frame k-1's measurement, warped by C_k
    reid_k   reid: frame k, detections k, prior_k, the template of k-1
    track_k  prediction: update only if accepted (Eq. 7 R_k), kalman.output_box
    M_k, η_k template: frame k, reid_k
"""
