"""The parts of the monitor's snapshot: what it shows of each message, as JSON-friendly views (the terminal
dashboard, the web view and the Foxglove bridge read these): the target, the prior with its gate ellipse, re-ID's
measurement, the motor command, the followed group in the robot frame, and the nodes' health."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bus.health import node_state
from ..msgs.group import GroundPoints, GroupState
from ..msgs.robot import MotorCommand
from ..msgs.tracking import Measurement, Prior, Template, Track
from ..tracking.groundplane import CameraGeometry, rotation, to_robot_frame
from .drawing import GROUP_SIGMA, ellipse_outline, floor_pixels, gate_ellipse

STATUS_FRESH_NS = 3_000_000_000  # a node's topic statistics older than this are not shown


def _box(value: Any) -> list[float] | None:
    return None if value is None else [round(float(v), 1) for v in np.asarray(value).reshape(-1)[:4]]


def _centre(box: Any) -> tuple[float, float]:
    b = np.asarray(box, dtype=float).reshape(-1)
    return float(b[0] + b[2] / 2), float(b[1] + b[3] / 2)


def _rounded(a: Any, nd: int = 3) -> list:
    return np.round(np.asarray(a, dtype=float), nd).tolist()



def group_view(group: GroupState, pose: tuple[float, float, float] | None, points: GroundPoints | None,
               camera: CameraGeometry | None = None) -> dict[str, Any]:
    """The followed group in the robot frame (x forward, y left; the robot at the origin), for the web view,
    and with ``camera`` (the groundplane node's geometry) its floor shapes in image pixels too.

    GroupState is in the odometry frame; the pose of the same frame's GroundPoints (by frame_seq) takes it into
    the robot frame (inverse of seed 004 Eq. 4: p_r = Rᵀ(p − t), extents Rᵀ X R). Without that pose (its points
    not received) the shape is not placed: only the centre, which the group node gives in the robot frame."""
    out: dict[str, Any] = {"frame_seq": group.header.frame_seq, "valid": bool(group.valid), "lost": bool(group.lost),
                           "step_ms": round(float(group.step_ms), 2), "posed": pose is not None,
                           "sigma": GROUP_SIGMA}
    if points is not None:  # the latest detections on the floor, whatever the tracker made of them
        out["points"] = {"frame_seq": points.header.frame_seq, "robot_m": _rounded(points.points_robot_m)}
    if not group.valid:
        return out
    centre = np.asarray(group.centre_robot_m, dtype=float).reshape(2)
    out.update(centre_robot_m=_rounded(centre), speed_mps=round(float(np.hypot(*group.velocity_mps)), 3),
               members=int(len(group.members_m)), others=int(len(group.others_m)))
    out["centre_px"] = (floor_pixels(centre, camera) or [None])[0]
    if pose is None:
        return out
    x, y, theta = pose
    rot = rotation(theta)
    ellipses = []
    for m, ext, w in zip(group.ellipse_centres_m, group.ellipse_extents_m2, group.ellipse_weights, strict=True):
        c_r, ext_r = to_robot_frame(m, x, y, theta)[0], rot.T @ ext @ rot
        ellipses.append({"centre_m": _rounded(c_r), "extent_m2": _rounded(ext_r, 4), "weight": round(float(w), 4),
                         "outline_px": floor_pixels(ellipse_outline(c_r, ext_r), camera)})
    out["ellipses"] = ellipses
    out["members_robot_m"] = _rounded(to_robot_frame(group.members_m, x, y, theta))
    out["others_robot_m"] = _rounded(to_robot_frame(group.others_m, x, y, theta))
    out["members_px"] = floor_pixels(to_robot_frame(group.members_m, x, y, theta), camera)
    out["orientation_robot_rad"] = round(float(group.orientation_rad - theta), 4)
    return out



def node_row(name: str, node: Any, now_ns: int) -> dict[str, Any]:
    """One node's health (a :class:`viewing.monitor.NodeView`) as the viewers list it."""
    st = node.status
    fresh = st is not None and now_ns - node.status_ns < STATUS_FRESH_NS
    return {
        "name": name, "alive": node.alive, "state": node_state(node.alive, st.extra if st and fresh else None),
        "since_ns": node.since_ns, "restarts": node.restarts, "ups": node.ups,
        "pid": st.pid if st else None, "uptime_s": st.uptime_s if st else None,
        "status_age_s": (now_ns - node.status_ns) / 1e9 if st else None,
        "topics": (st.topics if st and fresh else {}),
        "handler_errors": st.extra.get("handler_errors", 0) if st else 0,
        "trust": node.trust, "trust_reason": node.trust_reason,
        "extra": dict(st.extra) if st else {},  # e.g. capture's done: the web view's "source ended"
    }


def target_view(track: Track) -> dict[str, Any]:
    return {"state": track.state, "box": _box(track.box), "filtered_box": _box(track.filtered_box),
            "velocity": [round(float(v), 1) for v in track.velocity], "measured": track.measured,
            "frame_seq": track.header.frame_seq, "stamp_ns": track.header.stamp_ns}


def prior_view(prior: Prior) -> dict[str, Any]:
    """The prior with its gate ellipse computed (viewing/drawing.py): viewers draw it, none recomputes it."""
    return {"initialised": prior.initialised, "centre": [float(v) for v in prior.state[:2]],
            "innovation_cov": np.asarray(prior.innovation_cov, float).tolist(),
            "gate_chi2": prior.gate_chi2, "box": _box(prior.box), "frame_seq": prior.header.frame_seq,
            "gate": gate_ellipse(prior.state[:2], prior.innovation_cov, prior.gate_chi2) if prior.initialised
            else None}


def measurement_view(meas: Measurement) -> dict[str, Any]:
    cands = np.asarray(meas.candidates, float).reshape(-1, 5) if np.size(meas.candidates) else []
    return {"state": meas.state, "accepted": meas.accepted, "box": _box(meas.box), "m_fuse": meas.m_fuse,
            "candidates": [[round(float(v), 2) for v in c] for c in cands], "frame_seq": meas.header.frame_seq}


def command_view(command: MotorCommand) -> dict[str, Any]:
    return {"vx_mps": command.vx_mps, "vy_mps": command.vy_mps, "wz_radps": command.wz_radps,
            "range_m": command.range_m, "bearing_rad": command.bearing_rad, "reason": command.reason,
            "frame_seq": command.header.frame_seq,
            "latency_ms": ((command.header.pub_ns - command.header.stamp_ns) / 1e6
                           if command.header.stamp_ns > 0 else None)}


def latest_views(latest: dict[str, Any], poses: dict[int, tuple[float, float, float]],
                  camera: CameraGeometry | None) -> dict[str, Any]:
    """The views of the latest messages (by watched name: track, prior, measurement, template, command, group)."""
    out: dict[str, Any] = {}
    makers = (("track", Track, "target", target_view), ("prior", Prior, "prior", prior_view),
              ("measurement", Measurement, "measurement", measurement_view),
              ("command", MotorCommand, "command", command_view))
    for name, kind, key, make in makers:
        if isinstance(latest.get(name), kind):
            out[key] = make(latest[name])
    template = latest.get("template")
    if isinstance(template, Template):
        out["eta"] = template.eta if template.initialised else None
        out["p_specular"] = template.p_specular
    group, points = latest.get("group"), latest.get("points")
    if isinstance(group, GroupState):
        out["group"] = group_view(group, poses.get(group.header.frame_seq),
                                  points if isinstance(points, GroundPoints) else None, camera)
    return out
