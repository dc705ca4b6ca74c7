"""The tracker's seam between wire and core: ``detections`` columns in; ``tracks/{id}`` and ``tracked`` payloads out.

Pure functions (no I/O), called by the service and by the offline evaluator alike, on the columns of
:func:`~jitterguard.schemas.read_detected_objects` — one form for every well-formed payload. Planar throughout:
the ego pose contributes x, y, z and yaw; detections keep their own roll and pitch (the world orientation is
``q(ego_yaw) * q_detection``).

A detection republished on ``tracks/{id}`` is moved into the world frame whole: position (the core's), orientation,
the pose covariance and the twist with its covariance (:func:`~jitterguard.geometry.rotate_cov6`, the 2x2 position
block through the very :func:`~jitterguard.geometry.rotate_cov2` the core gates with), so the classifier's z-test
sees the detector's along-beam and across-beam variances on the right world axes.
"""

from __future__ import annotations

import numpy as np

from ...geometry import (cov2_largest_variance, quaternions_about_z, rotate_cov6, rotate_xy, yaw_from_quaternion,
                         yaws_from_quaternions)
from ...schemas import wire
from ...schemas.models import (
    COVARIANCE_SIZE,
    PITCH_PITCH,
    ROLL_ROLL,
    X_X,
    X_Y,
    Y_X,
    Y_Y,
    YAW_YAW,
    Z_Z,
    Header,
    Shape,
)
from ...schemas.wire import (LIMITS, DetectedColumns, Limits, TrackedColumns, write_track_observations,
                             write_tracked_objects)
from .arrays import DetectionFrame, FrameResult

WORLD_FRAME = "map"
# Variances of what the planar tracker does not estimate (z, roll, pitch): conservative constants, not zeros,
# so a consumer never reads "known exactly" into them.
Z_VAR, ROLL_PITCH_VAR = 0.1, 0.01
# Likewise for the twist: a stopped CTRV car's velocity covariance is rank one (J Σ Jᵀ with v = 0 carries no
# lateral term) and a constant-velocity track has no yaw rate at all; published as zeros they read "known exactly"
# and a consumer's Mahalanobis test on the velocity divided by zero.
VEL_VAR_FLOOR = 0.01  # (0.1 m/s)² on each velocity axis
UNMODELLED_YAW_RATE_VAR = 1.0  # (1 rad/s)²: a CV track's yaw rate is not estimated
VZ_VAR, ROLL_PITCH_RATE_VAR = 0.01, 0.01  # (0.1 m/s)², (0.1 rad/s)²: no track here climbs or rolls, none is known to
X_YAW, Y_YAW, YAW_X, YAW_Y = 5, 11, 30, 31


def detection_frame(cols: DetectedColumns) -> DetectionFrame:
    """The core's input arrays for one ``detections`` message (sensor frame, with the ego pose)."""
    r = cols.objects
    f64 = lambda name: r[name].astype(np.float64)  # noqa: E731  (big-endian wire columns to native floats)
    dx, dy = f64(wire.LENGTH), f64(wire.WIDTH)
    cov = r[wire.POSE_COV]["v"]
    eq, ep, h = cols.ego_pose.orientation, cols.ego_pose.position, cols.header
    return DetectionFrame(
        seq=h.seq, stamp_ns=h.stamp, frame_id=h.frame_id,
        ego_x=ep.x, ego_y=ep.y, ego_z=ep.z, ego_yaw=yaw_from_quaternion(eq.x, eq.y, eq.z, eq.w),
        x=f64(wire.X), y=f64(wire.Y), z=f64(wire.Z),
        yaw=yaws_from_quaternions(r[wire.QX], r[wire.QY], r[wire.QZ], r[wire.QW]),
        length=dx, width=np.where(r[wire.SHAPE_TYPE] == Shape.CYLINDER, dx, dy), height=f64(wire.HEIGHT),
        cov_xx=cov[:, X_X].astype(np.float64), cov_xy=cov[:, X_Y].astype(np.float64),
        cov_yy=cov[:, Y_Y].astype(np.float64), var_yaw=cov[:, YAW_YAW].astype(np.float64),
        label_prob=np.maximum(f64(wire.LABEL_PROB), 1e-3), existence=f64(wire.EXISTENCE),
        label=r[wire.LABEL].astype(np.int8), has_cov=r[wire.HAS_POSITION_COV] == 0xC3,
        orientation=r[wire.ORIENTATION].astype(np.int8), area=cols.area,
        vx=f64(wire.VX), vy=f64(wire.VY), has_twist=r["kinematics.has_twist"] == 0xC3,  # msgpack's true byte:
        # read with astype(bool), false (0xC2) had been true too, and a detection without a twist its velocity 0
    )


def world_detections(cols: DetectedColumns, frame: DetectionFrame, result: FrameResult,
                     limits: Limits = LIMITS) -> np.ndarray:
    """The observed detections (``result.obs_det``, then ``result.tentative_det``) as records moved into the world
    frame (copies). A detection that came without a position covariance of its own (Autoware's lidar_centerpoint
    reports none) carries the one the filter measured it with — the class's, along and across its heading — and
    says so (``has_position_covariance``): the classifier's test needs a variance to calibrate, and a zero one
    floored at 1 cm had made it call most parked cars moving.

    Turned into the world, a covariance or twist within ``limits`` in the sensor's axes can leave them (a variance
    of 1e6 on both axes with a covariance of −0.99e6 is 1.99e6 on one axis at 45°; (999, −999) m/s is 1413 m/s on
    one): every observation of it had been refused by the classifier, which then went ``failing`` for want of
    them. By the filter's own rules (:func:`~.core._screened`, whatever the ego's heading): a position covariance
    whose x-y block can give a variance over ``max_variance`` along some axis is replaced by the class's, as one not
    given, and a twist faster than ``max_abs_speed_mps`` over the ground is published as none. The filter reads
    neither the x/y covariances against z, roll, pitch and yaw nor the twist's covariance: those that rotation takes
    past the bound are published as unknown (zero; the twist's covariance not given), the rest kept."""
    rows = np.concatenate([result.obs_det, result.tentative_det])
    out = wire.DETECTED.select(cols.objects, rows)
    if not len(out):
        return out
    det, yaw = result.detections, frame.ego_yaw
    out[wire.X], out[wire.Y], out[wire.Z] = det.x[rows], det.y[rows], det.z[rows]
    q = np.column_stack([out[n] for n in (wire.QX, wire.QY, wire.QZ, wire.QW)]).astype(np.float64)
    out[wire.QX], out[wire.QY], out[wire.QZ], out[wire.QW] = quaternions_about_z(q, yaw).T
    out[wire.POSE_COV]["v"] = rotate_cov6(out[wire.POSE_COV]["v"], yaw)
    pcov = out[wire.POSE_COV]["v"]
    none = ~frame.own_covariance()[rows] | ~(cov2_largest_variance(pcov[:, X_X], pcov[:, X_Y], pcov[:, Y_Y])
                                             <= limits.max_variance)  # rotation keeps the eigenvalues: as _screened
    _unknown_beyond(pcov, limits.max_variance)
    if none.any():
        R = det.R[rows[none]]
        pcov[none] = 0.0
        pcov[none, X_X], pcov[none, Y_Y] = R[:, 0, 0], R[:, 1, 1]
        pcov[none, X_Y] = pcov[none, Y_X] = R[:, 0, 1]
        out[wire.HAS_POSITION_COV][none] = 0xC3
    out[wire.VX], out[wire.VY] = rotate_xy(out[wire.VX], out[wire.VY], yaw)
    tcov = out[wire.TWIST_COV]["v"]
    moving = np.flatnonzero(tcov.any(axis=1))  # a zero covariance (no twist reported) rotates to itself
    if moving.size:
        out[wire.TWIST_COV]["v"][moving] = rotate_cov6(tcov[moving], yaw)
    with np.errstate(invalid="ignore", over="ignore"):
        fast = ~(np.hypot(out[wire.VX], out[wire.VY]) <= limits.max_abs_speed_mps)  # as _screened
    unknown = fast | ~(cov2_largest_variance(tcov[:, X_X], tcov[:, X_Y], tcov[:, Y_Y]) <= limits.max_variance)
    if fast.any():
        out[wire.VX][fast] = out[wire.VY][fast] = 0.0
        out["kinematics.has_twist"][fast] = 0xC2
    if unknown.any():
        tcov[unknown] = 0.0
        out["kinematics.has_twist_covariance"][unknown] = 0xC2
    _unknown_beyond(tcov, limits.max_variance)
    return out


_XY_AGAINST_REST = np.array([i for k in range(2, 6) for i in (k, 6 + k, 6 * k, 6 * k + 1)])
"""The entries of a 6×6 covariance (Autoware's layout) that pair x or y with z, roll, pitch or yaw."""


def _unknown_beyond(cov: np.ndarray, bound: float) -> None:
    """Zero, in place, the x/y-against-the-rest covariances of each row where one exceeds ``bound`` (a rotation
    about z mixes each pair of them: each within the bound, their rotation can reach √2 times it)."""
    cross = cov[:, _XY_AGAINST_REST]
    over = (np.abs(cross) > bound).any(axis=1)
    if over.any():
        cross[over] = 0.0
        cov[:, _XY_AGAINST_REST] = cross


def tracked_records(result: FrameResult) -> np.ndarray:
    """Every confirmed track as a ``TrackedObject`` record (world frame, twist linear x/y = world vx, vy,
    angular z = yaw rate)."""
    t = result.tracks
    n = len(t)
    P, V = t.pose_cov, t.vel_cov
    pcov = np.zeros((n, COVARIANCE_SIZE))
    pcov[:, X_X], pcov[:, X_Y], pcov[:, Y_X], pcov[:, Y_Y] = P[:, 0, 0], P[:, 0, 1], P[:, 0, 1], P[:, 1, 1]
    pcov[:, YAW_YAW] = P[:, 2, 2]
    pcov[:, X_YAW] = pcov[:, YAW_X] = P[:, 0, 2]
    pcov[:, Y_YAW] = pcov[:, YAW_Y] = P[:, 1, 2]
    pcov[:, Z_Z], pcov[:, ROLL_ROLL], pcov[:, PITCH_PITCH] = Z_VAR, ROLL_PITCH_VAR, ROLL_PITCH_VAR
    tcov = np.zeros((n, COVARIANCE_SIZE))
    tcov[:, X_X], tcov[:, X_Y], tcov[:, Y_X], tcov[:, Y_Y] = V[:, 0, 0], V[:, 0, 1], V[:, 0, 1], V[:, 1, 1]
    tcov[:, X_X] += VEL_VAR_FLOOR  # added, not a maximum: the sum stays positive definite with the cross term
    tcov[:, Y_Y] += VEL_VAR_FLOOR
    tcov[:, YAW_YAW] = np.where(t.yaw_rate_var > 0.0, t.yaw_rate_var, UNMODELLED_YAW_RATE_VAR)
    tcov[:, Z_Z], tcov[:, ROLL_ROLL], tcov[:, PITCH_PITCH] = VZ_VAR, ROLL_PITCH_RATE_VAR, ROLL_PITCH_RATE_VAR
    half = 0.5 * np.asarray(t.yaw, dtype=np.float64)
    return wire.TRACKED.pack(n, {
        wire.ID: t.ids, wire.EXISTENCE: t.existence, wire.LABEL: t.label, wire.LABEL_PROB: t.label_prob,
        wire.X: t.x, wire.Y: t.y, wire.Z: t.z, wire.QZ: np.sin(half), wire.QW: np.cos(half), wire.POSE_COV: pcov,
        wire.VX: t.vel[:, 0], wire.VY: t.vel[:, 1], wire.WZ: t.yaw_rate, wire.TWIST_COV: tcov,
        wire.ORIENTATION: t.orientation, wire.STATIONARY: np.zeros(n, dtype=bool),
        wire.SHAPE_TYPE: Shape.BOUNDING_BOX, wire.LENGTH: t.dims[:, 0], wire.WIDTH: t.dims[:, 1],
        wire.HEIGHT: t.dims[:, 2],
    })


def track_state_records(result: FrameResult) -> np.ndarray:
    """The observed tracks' compact ``TrackState`` records (``result.observed_ids`` order: the confirmed ones in
    ``result.obs_track`` order, then the tentative ones)."""
    c, i, t = result.tracks, result.obs_track, result.tentative
    cat = lambda name: np.concatenate([getattr(c, name)[i], getattr(t, name)])  # noqa: E731
    vel = np.concatenate([c.vel[i], t.vel])
    return wire.TRACK_STATE.pack(len(i) + len(t), {
        "object_id": result.observed_ids, "label": cat("label"), "existence_probability": cat("existence"),
        "x": cat("x"), "y": cat("y"), "yaw": cat("yaw"), "vx": vel[:, 0], "vy": vel[:, 1], "hits": cat("hits"),
        "age_s": np.maximum(0.0, (result.stamp_ns - cat("born_ns")) * 1e-9),
    })


def observation_payloads(cols: DetectedColumns, frame: DetectionFrame, result: FrameResult,
                         limits: Limits = LIMITS) -> list[tuple[str, bytes]]:
    """The frame's ``tracks/{id}`` payloads as ``(track_id, TrackObservation payload)``, in track order."""
    payloads = write_track_observations(_header(frame), world_detections(cols, frame, result, limits),
                                        track_state_records(result))
    return list(zip(result.observed_ids, payloads))


def tracked_payload(cols: DetectedColumns, frame: DetectionFrame, result: FrameResult) -> bytes:
    """The frame's closing ``TrackedObjects`` payload: every confirmed track, the IDs observed this frame, and
    the ego pose of the ``detections`` it came from."""
    return write_tracked_objects(TrackedColumns(_header(frame), cols.ego_pose, tracked_records(result),
                                                result.observed_ids))


def _header(frame: DetectionFrame) -> Header:
    return Header(stamp=frame.stamp_ns, frame_id=WORLD_FRAME, seq=frame.seq)
