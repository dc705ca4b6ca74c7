"""Wire models <-> the core's arrays: ``DetectedObjects`` in, ``TrackObservation`` / ``TrackedObjects`` out.

Pure functions (no I/O). Planar throughout: the ego pose contributes x, y, z and yaw; detections keep their own
roll and pitch (the world orientation is ``q(ego_yaw) * q_detection``).

A detection republished on ``tracks/{id}`` is moved into the world frame whole: position, orientation, and
the covariance — the 2x2 position block with :func:`jitterguard.geometry.rotate_cov2` (R Σ Rᵀ), and the
position's correlations with z / roll / pitch / yaw rotated with it — so the classifier's z-test sees the
detector's along-beam and across-beam variances on the right world axes. A detection's twist, if it has one,
is rotated the same way (its linear x/y and their covariance block).
"""

from __future__ import annotations

import math

import numpy as np

from ...geometry import quaternion_from_yaw, rotate_cov2, yaw_from_quaternion
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
    DetectedObject,
    DetectedObjects,
    Header,
    ObjectClassification,
    Point,
    Pose,
    PoseWithCovariance,
    Quaternion,
    Shape,
    TrackedObject,
    TrackedObjectKinematics,
    TrackedObjects,
    TrackObservation,
    Twist,
    TwistWithCovariance,
    Vector3,
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


def frame_from_message(msg: DetectedObjects) -> DetectionFrame:
    """The core's input arrays for one ``DetectedObjects`` message (sensor frame, with the ego pose)."""
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


def _qmul(a: tuple[float, float, float, float], b: Quaternion) -> Quaternion:
    ax, ay, az, aw = a
    return Quaternion(
        x=aw * b.x + ax * b.w + ay * b.z - az * b.y,
        y=aw * b.y - ax * b.z + ay * b.w + az * b.x,
        z=aw * b.z + ax * b.y - ay * b.x + az * b.w,
        w=aw * b.w - ax * b.x - ay * b.y - az * b.z,
    )


def _rotate_cov36(cov: list[float], cxx: float, cxy: float, cyy: float, c: float, s: float) -> list[float]:
    """A 6x6 covariance with its x/y block replaced by the rotated one and its x/y cross terms rotated."""
    out = list(cov)
    out[X_X], out[X_Y], out[Y_X], out[Y_Y] = cxx, cxy, cxy, cyy
    for k in range(2, 6):
        a, b = cov[k], cov[6 + k]  # row x, row y at column k
        out[k], out[6 + k] = c * a - s * b, s * a + c * b
        a, b = cov[6 * k], cov[6 * k + 1]  # row k, columns x and y
        out[6 * k], out[6 * k + 1] = c * a - s * b, s * a + c * b
    return out


def detection_to_world(obj: DetectedObject, frame: DetectionFrame, result: FrameResult, j: int) -> DetectedObject:
    """Detection ``j`` of the frame, moved into the world frame (pose, orientation, covariances, twist)."""
    det = result.detections
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    kin = obj.kinematics
    pc = kin.pose_with_covariance
    pose = Pose(
        position=Point(x=float(det.x[j]), y=float(det.y[j]), z=float(det.z[j])),
        orientation=_qmul(quaternion_from_yaw(frame.ego_yaw), pc.pose.orientation),
    )
    cov = _rotate_cov36(pc.covariance, float(det.cov_xx[j]), float(det.cov_xy[j]), float(det.cov_yy[j]), c, s)
    tw = kin.twist_with_covariance
    lin = tw.twist.linear
    tcov = tw.covariance
    txx, txy, tyy = rotate_cov2(tcov[X_X], tcov[X_Y], tcov[Y_Y], frame.ego_yaw)
    twist = TwistWithCovariance(
        twist=Twist(linear=Vector3(x=c * lin.x - s * lin.y, y=s * lin.x + c * lin.y, z=lin.z),
                    angular=tw.twist.angular),
        covariance=_rotate_cov36(tcov, float(txx), float(txy), float(tyy), c, s),
    )
    return obj.model_copy(update={
        "kinematics": kin.model_copy(update={
            "pose_with_covariance": PoseWithCovariance(pose=pose, covariance=cov),
            "twist_with_covariance": twist,
        }),
    })


def tracked_object(result: FrameResult, i: int) -> TrackedObject:
    """Confirmed track ``i`` of the frame as Autoware's TrackedObject (world frame, twist in world axes)."""
    t = result.tracks
    P = t.pose_cov[i]
    pcov = [0.0] * COVARIANCE_SIZE
    pcov[X_X], pcov[X_Y], pcov[Y_X], pcov[Y_Y] = float(P[0, 0]), float(P[0, 1]), float(P[1, 0]), float(P[1, 1])
    pcov[YAW_YAW] = float(P[2, 2])
    pcov[X_YAW] = pcov[YAW_X] = float(P[0, 2])
    pcov[Y_YAW] = pcov[YAW_Y] = float(P[1, 2])
    pcov[Z_Z], pcov[ROLL_ROLL], pcov[PITCH_PITCH] = Z_VAR, ROLL_PITCH_VAR, ROLL_PITCH_VAR
    V = t.vel_cov[i]
    tcov = [0.0] * COVARIANCE_SIZE
    tcov[X_X], tcov[X_Y], tcov[Y_X], tcov[Y_Y] = float(V[0, 0]), float(V[0, 1]), float(V[1, 0]), float(V[1, 1])
    tcov[YAW_YAW] = float(t.yaw_rate_var[i])
    qx, qy, qz, qw = quaternion_from_yaw(float(t.yaw[i]))
    return TrackedObject(
        object_id=t.ids[i],
        existence_probability=float(t.existence[i]),
        classification=[ObjectClassification(label=int(t.label[i]), probability=float(t.label_prob[i]))],
        kinematics=TrackedObjectKinematics(
            pose_with_covariance=PoseWithCovariance(
                pose=Pose(position=Point(x=float(t.x[i]), y=float(t.y[i]), z=float(t.z[i])),
                          orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)),
                covariance=pcov,
            ),
            twist_with_covariance=TwistWithCovariance(
                twist=Twist(linear=Vector3(x=float(t.vel[i, 0]), y=float(t.vel[i, 1])),
                            angular=Vector3(z=float(t.yaw_rate[i]))),
                covariance=tcov,
            ),
            orientation_availability=int(t.orientation[i]),
            is_stationary=False,
        ),
        shape=Shape(type=Shape.BOUNDING_BOX,
                    dimensions=Vector3(x=float(t.dims[i, 0]), y=float(t.dims[i, 1]), z=float(t.dims[i, 2]))),
    )


def frame_messages(msg: DetectedObjects, frame: DetectionFrame, result: FrameResult
                   ) -> tuple[list[TrackObservation], TrackedObjects]:
    """The frame's ``tracks/{id}`` observations (in track order) and the closing ``TrackedObjects``."""
    header = Header(stamp=msg.header.stamp, frame_id=WORLD_FRAME, seq=msg.header.seq)
    tracked = [tracked_object(result, i) for i in range(len(result.tracks))]
    observations = [
        TrackObservation(header=header, detection=detection_to_world(msg.objects[int(j)], frame, result, int(j)),
                         track=tracked[int(i)])
        for i, j in zip(result.obs_track, result.obs_det)
    ]
    closing = TrackedObjects(header=header, objects=tracked, observed_track_ids=result.observed_ids)
    return observations, closing
