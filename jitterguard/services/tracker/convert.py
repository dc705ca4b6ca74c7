"""Wire payloads <-> the core's arrays: ``DetectedObjects`` in, ``TrackObservation`` / ``TrackedObjects`` out.

Pure functions (no I/O). Input is the validated model; output is msgpack-ready maps laid out exactly as the
models dump (the tests decode them with the models), because constructing hundreds of nested pydantic models
per frame would cost more than the whole tracker update. Planar throughout: the ego pose contributes x, y, z and yaw; detections keep their own
roll and pitch (the world orientation is ``q(ego_yaw) * q_detection``).

A detection republished on ``tracks/{id}`` is moved into the world frame whole: position, orientation, and
the covariance — the 2x2 position block with :func:`jitterguard.geometry.rotate_cov2` (R Σ Rᵀ), and the
position's correlations with z / roll / pitch / yaw rotated with it — so the classifier's z-test sees the
detector's along-beam and across-beam variances on the right world axes. A detection's twist, if it has one,
is rotated the same way (its linear x/y and their covariance block).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ...geometry import rotate_cov2, yaw_from_quaternion
from ...schemas.models import (
    COVARIANCE_SIZE,
    SCHEMA_VERSION,
    PITCH_PITCH,
    ROLL_ROLL,
    X_X,
    X_Y,
    Y_X,
    Y_Y,
    YAW_YAW,
    Z_Z,
    DetectedObject,
    DetectedObjects,
    Shape,
)
from .frames import DetectionFrame, FrameResult

WORLD_FRAME = "map"
# Variances of what the planar tracker does not estimate (z, roll, pitch): conservative constants, not zeros,
# so a consumer never reads "known exactly" into them.
Z_VAR, ROLL_PITCH_VAR = 0.1, 0.01
X_YAW, Y_YAW, YAW_X, YAW_Y = 5, 11, 30, 31


def highest_prob_label(obj: DetectedObject) -> tuple[int, float]:
    """Autoware's getHighestProbLabel: the most probable class (UNKNOWN if the detector gave none)."""
    if not obj.classification:
        return 0, 1.0
    best = max(obj.classification, key=lambda c: c.probability)
    return int(best.label), float(best.probability)


def shape_area(shape: Shape) -> float:
    """Footprint area as Autoware's getArea computes it (box L*W, cylinder pi r^2, polygon shoelace)."""
    if shape.type == Shape.CYLINDER:
        r = 0.5 * shape.dimensions.x
        return math.pi * r * r
    if shape.type == Shape.POLYGON:
        pts = shape.footprint
        if len(pts) < 3:
            return 0.0
        s = 0.0
        for a, b in zip(pts, pts[1:] + pts[:1]):
            s += a.x * b.y - b.x * a.y
        return abs(0.5 * s)
    return shape.dimensions.x * shape.dimensions.y


def frame_from_message(msg: DetectedObjects | Any) -> DetectionFrame:
    """The core's input arrays for one ``DetectedObjects`` message (sensor frame, with the ego pose): the model
    or its generated Struct (:mod:`jitterguard.schemas.fast`), which the service decodes into."""
    objs = msg.objects
    m = len(objs)
    cols = np.zeros((13, m))
    label = np.zeros(m, dtype=np.int8)
    has_cov = np.zeros(m, dtype=bool)
    orient = np.zeros(m, dtype=np.int8)
    for i, o in enumerate(objs):
        pc = o.kinematics.pose_with_covariance
        p, q, c = pc.pose.position, pc.pose.orientation, pc.covariance
        lbl, prob = highest_prob_label(o)
        d = o.shape.dimensions
        length, width = (d.x, d.x) if o.shape.type == Shape.CYLINDER else (d.x, d.y)
        cols[:, i] = (p.x, p.y, p.z, yaw_from_quaternion(q.x, q.y, q.z, q.w), length, width, d.z,
                      c[X_X], c[X_Y], c[Y_Y], c[YAW_YAW], prob, o.existence_probability)
        label[i] = lbl
        has_cov[i] = o.kinematics.has_position_covariance
        orient[i] = o.kinematics.orientation_availability
    area = np.array([shape_area(o.shape) for o in objs], dtype=np.float64)
    eq = msg.ego_pose.orientation
    ep = msg.ego_pose.position
    return DetectionFrame(
        seq=msg.header.seq, stamp_ns=msg.header.stamp, frame_id=msg.header.frame_id,
        ego_x=ep.x, ego_y=ep.y, ego_z=ep.z, ego_yaw=yaw_from_quaternion(eq.x, eq.y, eq.z, eq.w),
        x=cols[0], y=cols[1], z=cols[2], yaw=cols[3], length=cols[4], width=cols[5], height=cols[6],
        cov_xx=cols[7], cov_xy=cols[8], cov_yy=cols[9], var_yaw=cols[10], label_prob=np.maximum(cols[11], 1e-3),
        existence=cols[12], label=label, has_cov=has_cov, orientation=orient, area=area,
    )


def _qmul_yaw(yaw: float, q: dict) -> dict:
    """``q(yaw) * q`` for a quaternion map: the detection's orientation carried into the world frame."""
    az, aw = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
    bx, by, bz, bw = q["x"], q["y"], q["z"], q["w"]
    return {"x": aw * bx - az * by, "y": aw * by + az * bx, "z": aw * bz + az * bw, "w": aw * bw - az * bz}


def _rotate_cov36(cov: Sequence[float], cxx: float, cxy: float, cyy: float, c: float, s: float) -> list[float]:
    """A 6x6 covariance with its x/y block replaced by the rotated one and its x/y cross terms rotated."""
    out = list(cov)
    out[X_X], out[X_Y], out[Y_X], out[Y_Y] = cxx, cxy, cxy, cyy
    for k in range(2, 6):
        a, b = cov[k], cov[6 + k]  # rows x and y at column k
        out[k], out[6 + k] = c * a - s * b, s * a + c * b
        a, b = cov[6 * k], cov[6 * k + 1]  # row k at columns x and y
        out[6 * k], out[6 * k + 1] = c * a - s * b, s * a + c * b
    return out


def detection_to_world(raw: dict, frame: DetectionFrame, result: FrameResult, j: int) -> dict:
    """Detection ``j`` (its validated msgpack map, edited in place and returned) moved into the world frame:
    position, orientation, pose covariance (R Σ Rᵀ via rotate_cov2) and twist with its covariance."""
    det = result.detections
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    kin = raw["kinematics"]
    pc = kin["pose_with_covariance"]
    pc["pose"] = {
        "position": {"x": float(det.x[j]), "y": float(det.y[j]), "z": float(det.z[j])},
        "orientation": _qmul_yaw(frame.ego_yaw, pc["pose"]["orientation"]),
    }
    pc["covariance"] = _rotate_cov36(pc["covariance"], float(det.cov_xx[j]), float(det.cov_xy[j]),
                                     float(det.cov_yy[j]), c, s)
    tw = kin["twist_with_covariance"]
    lin = tw["twist"]["linear"]
    lin["x"], lin["y"] = c * lin["x"] - s * lin["y"], s * lin["x"] + c * lin["y"]
    tc = tw["covariance"]
    if any(tc):
        txx, txy, tyy = rotate_cov2(tc[X_X], tc[X_Y], tc[Y_Y], frame.ego_yaw)
        tw["covariance"] = _rotate_cov36(tc, float(txx), float(txy), float(tyy), c, s)
    return raw


def _vec(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> dict:
    return {"x": x, "y": y, "z": z}


_ZERO36 = [0.0] * COVARIANCE_SIZE


def tracked_object_dicts(result: FrameResult) -> list[dict]:
    """Every confirmed track as a ``TrackedObject`` map (world frame; twist linear x/y = world vx, vy).

    Maps, not models: building ~200 nested pydantic models per frame costs tens of milliseconds, and the
    receivers validate anyway; the tests decode these maps with the models to keep them honest.
    """
    t = result.tracks
    n = len(t)
    if n == 0:
        return []
    P = t.pose_cov
    V = t.vel_cov
    cols = {
        "pxx": P[:, 0, 0], "pxy": P[:, 0, 1], "pyy": P[:, 1, 1], "pyaw": P[:, 2, 2], "pxyaw": P[:, 0, 2],
        "pyyaw": P[:, 1, 2], "vxx": V[:, 0, 0], "vxy": V[:, 0, 1], "vyy": V[:, 1, 1], "wvar": t.yaw_rate_var,
        "x": t.x, "y": t.y, "z": t.z, "yaw": t.yaw, "vx": t.vel[:, 0], "vy": t.vel[:, 1], "w": t.yaw_rate,
        "L": t.dims[:, 0], "W": t.dims[:, 1], "H": t.dims[:, 2], "ex": t.existence, "lp": t.label_prob,
    }
    lst = {k: np.asarray(v, dtype=np.float64).tolist() for k, v in cols.items()}
    labels = t.label.tolist()
    orient = t.orientation.tolist()
    out = []
    for i in range(n):
        pcov = list(_ZERO36)
        pcov[X_X], pcov[X_Y], pcov[Y_X], pcov[Y_Y] = lst["pxx"][i], lst["pxy"][i], lst["pxy"][i], lst["pyy"][i]
        pcov[YAW_YAW] = lst["pyaw"][i]
        pcov[X_YAW] = pcov[YAW_X] = lst["pxyaw"][i]
        pcov[Y_YAW] = pcov[YAW_Y] = lst["pyyaw"][i]
        pcov[Z_Z], pcov[ROLL_ROLL], pcov[PITCH_PITCH] = Z_VAR, ROLL_PITCH_VAR, ROLL_PITCH_VAR
        tcov = list(_ZERO36)
        tcov[X_X], tcov[X_Y], tcov[Y_X], tcov[Y_Y] = lst["vxx"][i], lst["vxy"][i], lst["vxy"][i], lst["vyy"][i]
        tcov[YAW_YAW] = lst["wvar"][i]
        half = 0.5 * lst["yaw"][i]
        out.append({
            "object_id": t.ids[i],
            "existence_probability": lst["ex"][i],
            "classification": [{"label": labels[i], "probability": lst["lp"][i]}],
            "kinematics": {
                "pose_with_covariance": {
                    "pose": {"position": _vec(lst["x"][i], lst["y"][i], lst["z"][i]),
                             "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}},
                    "covariance": pcov,
                },
                "twist_with_covariance": {
                    "twist": {"linear": _vec(lst["vx"][i], lst["vy"][i]), "angular": _vec(0.0, 0.0, lst["w"][i])},
                    "covariance": tcov,
                },
                "acceleration_with_covariance": {"accel": {"linear": _vec(), "angular": _vec()},
                                                 "covariance": list(_ZERO36)},
                "orientation_availability": orient[i],
                "is_stationary": False,
            },
            "shape": {"type": Shape.BOUNDING_BOX, "footprint": [],
                      "dimensions": _vec(lst["L"][i], lst["W"][i], lst["H"][i])},
        })
    return out


def track_state_dict(result: FrameResult, i: int) -> dict:
    """Confirmed track ``i`` as the compact ``TrackState`` map that rides along with each observation."""
    t = result.tracks
    return {
        "object_id": t.ids[i], "label": int(t.label[i]), "existence_probability": float(t.existence[i]),
        "x": float(t.x[i]), "y": float(t.y[i]), "yaw": float(t.yaw[i]),
        "vx": float(t.vel[i, 0]), "vy": float(t.vel[i, 1]), "hits": int(t.hits[i]),
        "age_s": max(0.0, (result.stamp_ns - int(t.born_ns[i])) * 1e-9),
    }


def frame_messages(raw_msg: dict, frame: DetectionFrame, result: FrameResult) -> tuple[list[dict], dict]:
    """The frame's ``TrackObservation`` maps (in track order) and the closing ``TrackedObjects`` map.

    ``raw_msg`` is the validated msgpack map of the ``DetectedObjects`` message; the observed detections in it
    are edited in place into the world frame. Encode the results with :func:`jitterguard.schemas.encode`.
    """
    header = {"stamp": frame.stamp_ns, "frame_id": WORLD_FRAME, "seq": frame.seq}
    objects = raw_msg["objects"]
    observations = [
        {"schema_version": SCHEMA_VERSION, "header": header,
         "detection": detection_to_world(objects[j], frame, result, j), "track": track_state_dict(result, i)}
        for i, j in zip(result.obs_track.tolist(), result.obs_det.tolist())
    ]
    closing = {"schema_version": SCHEMA_VERSION, "header": header, "objects": tracked_object_dicts(result),
               "observed_track_ids": result.observed_ids}
    return observations, closing
