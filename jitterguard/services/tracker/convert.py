"""Wire payloads <-> the core's arrays: ``DetectedObjects`` in, ``TrackObservation`` / ``TrackedObjects`` out.

Pure functions (no I/O). Input is the validated message (the model, or the Struct the service decodes into);
output is payload bytes (:func:`frame_payloads`): the arithmetic on arrays, the ``TrackedObject``s and track
states as records (:mod:`jitterguard.schemas.tracked_layout`), because building and encoding hundreds of nested
maps per frame cost more than the tracker update itself; the tests decode the payloads with the models.
Planar throughout: the ego pose contributes x, y, z and yaw; detections keep their own roll and pitch (the
world orientation is ``q(ego_yaw) * q_detection``).

A detection republished on ``tracks/{id}`` is moved into the world frame whole: position, orientation, and
the covariance — the 2x2 position block with :func:`jitterguard.geometry.rotate_cov2` (R Σ Rᵀ), and the
position's correlations with z / roll / pitch / yaw rotated with it — so the classifier's z-test sees the
detector's along-beam and across-beam variances on the right world axes. A detection's twist, if it has one,
is rotated the same way (its linear x/y and their covariance block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from ...geometry import rotate_cov2, yaw_from_quaternion, yaws_from_quaternions
from ...schemas import tracked_layout as tl
from ...schemas.fast import StructCodec, block_rows, raw_blocks
from ...schemas.layout import RecordLayout
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


COV_BLOCK = 16
"""Covariances (36 floats) decoded by :func:`detections_codec` stay raw msgpack bytes (``raw_float_blocks``)."""


def detections_codec() -> StructCodec:
    """How the tracker decodes ``detections``: the generated Structs, covariances left as raw bytes (validated
    for the whole message at once; read and rewritten as arrays here, no Python float per entry)."""
    return StructCodec(DetectedObjects, raw_float_blocks=COV_BLOCK)


def covariance_rows(covs: list[Any]) -> np.ndarray:
    """``(M, 36)`` float64 from covariances as tuples (models, plain Structs) or raw blocks (:func:`detections_codec`)."""
    if not covs:
        return np.zeros((0, COVARIANCE_SIZE))
    if isinstance(covs[0], msgspec.Raw):
        return block_rows(covs, COVARIANCE_SIZE)
    return np.array(covs, dtype=np.float64).reshape(len(covs), COVARIANCE_SIZE)


def decode_detections(codec: StructCodec, data: bytes) -> tl.DetectedRecords | Any:
    """How the tracker service reads a ``detections`` payload: as records when it has the usual shape (one
    classification, no footprint — :func:`~jitterguard.schemas.tracked_layout.decode_detected_records`), else
    as the generated Structs of ``codec`` (:func:`detections_codec`), which decide and name what is invalid.

    Raises :class:`~jitterguard.schemas.DecodeError` for an invalid payload.
    """
    fast = tl.decode_detected_records(data)
    return fast if fast is not None else codec.decode(data)


def _frame_from_records(msg: tl.DetectedRecords) -> DetectionFrame:
    """:func:`frame_from_message` for records: the same arrays, computed column-wise."""
    r = msg.records
    f64 = lambda name: r[name].astype(np.float64)  # noqa: E731  (big-endian wire columns to native floats)
    kind = r[tl.SHAPE_TYPE]
    dx, dy = f64(tl.LENGTH), f64(tl.WIDTH)
    cylinder = kind == Shape.CYLINDER
    area = np.where(cylinder, math.pi * (0.5 * dx) * (0.5 * dx), np.where(kind == Shape.POLYGON, 0.0, dx * dy))
    cov = r[tl.POSE_COV]["v"]  # no footprint in this shape: a polygon's area is 0, as getArea gives
    eq, ep = msg.ego_pose.orientation, msg.ego_pose.position
    return DetectionFrame(
        seq=msg.header.seq, stamp_ns=msg.header.stamp, frame_id=msg.header.frame_id,
        ego_x=ep.x, ego_y=ep.y, ego_z=ep.z, ego_yaw=yaw_from_quaternion(eq.x, eq.y, eq.z, eq.w),
        x=f64(tl.X), y=f64(tl.Y), z=f64(tl.Z), yaw=yaws_from_quaternions(r[tl.QX], r[tl.QY], r[tl.QZ], r[tl.QW]),
        length=dx, width=np.where(cylinder, dx, dy), height=f64(tl.HEIGHT),
        cov_xx=cov[:, X_X].astype(np.float64), cov_xy=cov[:, X_Y].astype(np.float64),
        cov_yy=cov[:, Y_Y].astype(np.float64), var_yaw=cov[:, YAW_YAW].astype(np.float64),
        label_prob=np.maximum(f64(tl.LABEL_PROB), 1e-3), existence=f64(tl.EXISTENCE),
        label=r[tl.LABEL].astype(np.int8), has_cov=r[tl.HAS_POSITION_COV] == 0xC3,
        orientation=r[tl.ORIENTATION].astype(np.int8), area=area,
    )


def frame_from_message(msg: DetectedObjects | tl.DetectedRecords | Any) -> DetectionFrame:
    """The core's input arrays for one ``DetectedObjects`` message (sensor frame, with the ego pose): the model,
    or what :func:`decode_detections` gives (records or the generated Struct)."""
    if isinstance(msg, tl.DetectedRecords):
        return _frame_from_records(msg)
    objs = msg.objects
    m = len(objs)
    cols = np.zeros((9, m))
    label = np.zeros(m, dtype=np.int8)
    has_cov = np.zeros(m, dtype=bool)
    orient = np.zeros(m, dtype=np.int8)
    covs = []
    for i, o in enumerate(objs):
        pc = o.kinematics.pose_with_covariance
        p, q = pc.pose.position, pc.pose.orientation
        covs.append(pc.covariance)
        lbl, prob = highest_prob_label(o)
        d = o.shape.dimensions
        length, width = (d.x, d.x) if o.shape.type == Shape.CYLINDER else (d.x, d.y)
        cols[:, i] = (p.x, p.y, p.z, yaw_from_quaternion(q.x, q.y, q.z, q.w), length, width, d.z,
                      prob, o.existence_probability)
        label[i] = lbl
        has_cov[i] = o.kinematics.has_position_covariance
        orient[i] = o.kinematics.orientation_availability
    cov = covariance_rows(covs)
    area = np.array([shape_area(o.shape) for o in objs], dtype=np.float64)
    eq = msg.ego_pose.orientation
    ep = msg.ego_pose.position
    return DetectionFrame(
        seq=msg.header.seq, stamp_ns=msg.header.stamp, frame_id=msg.header.frame_id,
        ego_x=ep.x, ego_y=ep.y, ego_z=ep.z, ego_yaw=yaw_from_quaternion(eq.x, eq.y, eq.z, eq.w),
        x=cols[0], y=cols[1], z=cols[2], yaw=cols[3], length=cols[4], width=cols[5], height=cols[6],
        cov_xx=cov[:, X_X], cov_xy=cov[:, X_Y], cov_yy=cov[:, Y_Y], var_yaw=cov[:, YAW_YAW],
        label_prob=np.maximum(cols[7], 1e-3), existence=cols[8], label=label, has_cov=has_cov, orientation=orient,
        area=area,
    )


def _rotate_cov36(cov: np.ndarray, cxx: np.ndarray, cxy: np.ndarray, cyy: np.ndarray, c: float,
                  s: float) -> np.ndarray:
    """6x6 covariances ``(M, 36)`` with the x/y block replaced by the rotated one and the x/y cross terms
    rotated with it (R Σ Rᵀ for a rotation about z by the angle with cosine ``c`` and sine ``s``)."""
    out = cov.copy()
    out[:, X_X], out[:, X_Y], out[:, Y_X], out[:, Y_Y] = cxx, cxy, cxy, cyy
    for k in range(2, 6):
        a, b = cov[:, k], cov[:, 6 + k]  # rows x and y at column k
        out[:, k], out[:, 6 + k] = c * a - s * b, s * a + c * b
        a, b = cov[:, 6 * k], cov[:, 6 * k + 1]  # row k at columns x and y
        out[:, 6 * k], out[:, 6 * k + 1] = c * a - s * b, s * a + c * b
    return out


@dataclass
class _WorldColumns:
    """Observed detections' world-frame values (one row each), computed on arrays."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    q: np.ndarray  # (M, 4) x, y, z, w
    pose_cov: np.ndarray  # (M, 36)
    vx: np.ndarray
    vy: np.ndarray
    twist_cov: np.ndarray  # (M, 36); rows that were all zero stay zero
    moving: np.ndarray  # rows whose twist covariance was not all zero (the only ones that change)


def _world_columns(frame: DetectionFrame, result: FrameResult, rows: np.ndarray, q: np.ndarray,
                   pose_cov: np.ndarray, lin: np.ndarray, twist_cov: np.ndarray) -> _WorldColumns:
    """Detections moved into the world frame: position (the core's), orientation ``q(ego_yaw) * q``, pose
    covariance (R Σ Rᵀ via rotate_cov2 — the core's — with the cross terms rotated) and the twist's linear x/y
    with its covariance. ``rows`` indexes each detection's row in ``result.detections``."""
    det = result.detections
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    az, aw = math.sin(0.5 * frame.ego_yaw), math.cos(0.5 * frame.ego_yaw)
    qw = np.column_stack([aw * q[:, 0] - az * q[:, 1], aw * q[:, 1] + az * q[:, 0],
                          aw * q[:, 2] + az * q[:, 3], aw * q[:, 3] - az * q[:, 2]])
    pcov = _rotate_cov36(pose_cov, det.cov_xx[rows], det.cov_xy[rows], det.cov_yy[rows], c, s)
    moving = np.flatnonzero(twist_cov.any(axis=1))  # a zero twist covariance rotates to itself
    tcov = twist_cov.copy()
    if moving.size:
        sub = twist_cov[moving]
        txx, txy, tyy = rotate_cov2(sub[:, X_X], sub[:, X_Y], sub[:, Y_Y], frame.ego_yaw)
        tcov[moving] = _rotate_cov36(sub, txx, txy, tyy, c, s)
    return _WorldColumns(det.x[rows], det.y[rows], det.z[rows], qw, pcov, c * lin[:, 0] - s * lin[:, 1],
                         s * lin[:, 0] + c * lin[:, 1], tcov, moving)


def detections_to_world(objects: list[Any], frame: DetectionFrame, result: FrameResult,
                        rows: np.ndarray) -> None:
    """Move detections (generated ``DetectedObject`` Structs, edited in place) into the world frame
    (:func:`_world_columns`; the arithmetic on arrays, only the writes per object)."""
    if not objects:
        return
    kins = [o.kinematics for o in objects]
    pcs = [k.pose_with_covariance for k in kins]
    twists = [k.twist_with_covariance for k in kins]
    q = np.array([(p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w)
                  for p in pcs])
    lin = np.array([(t.twist.linear.x, t.twist.linear.y) for t in twists], dtype=np.float64)
    w = _world_columns(frame, result, rows, q, covariance_rows([p.covariance for p in pcs]), lin,
                       covariance_rows([t.covariance for t in twists]))
    raw = isinstance(pcs[0].covariance, msgspec.Raw)  # decoded by detections_codec: write raw blocks back
    pack = raw_blocks if raw else (lambda a: a.tolist())
    pcov = pack(w.pose_cov)
    px, py, pz = w.x.tolist(), w.y.tolist(), w.z.tolist()
    qx, qy, qz, qw = w.q.T.tolist()
    vx, vy = w.vx.tolist(), w.vy.tolist()
    for i, (pc, tw) in enumerate(zip(pcs, twists)):
        pose = pc.pose
        pos, ori = pose.position, pose.orientation
        pos.x, pos.y, pos.z = px[i], py[i], pz[i]
        ori.x, ori.y, ori.z, ori.w = qx[i], qy[i], qz[i], qw[i]
        pc.covariance = pcov[i]
        v = tw.twist.linear
        v.x, v.y = vx[i], vy[i]
    if w.moving.size:
        for i, cov in zip(w.moving.tolist(), pack(w.twist_cov[w.moving])):
            twists[i].covariance = cov


def _world_records(msg: tl.DetectedRecords, frame: DetectionFrame, result: FrameResult,
                   rows: np.ndarray) -> np.ndarray:
    """The observed detections' records (copies of ``rows``) moved into the world frame."""
    layout = tl.detected_object_layout()
    src = msg.records
    out = np.ascontiguousarray(src.view(np.uint8).reshape(len(src), layout.itemsize)[rows]).reshape(-1) \
        .view(layout.dtype)  # whole rows, the bytes between fields included
    if not len(out):
        return out
    q = np.column_stack([out[tl.QX], out[tl.QY], out[tl.QZ], out[tl.QW]]).astype(np.float64)
    lin = np.column_stack([out[tl.VX], out[tl.VY]]).astype(np.float64)
    w = _world_columns(frame, result, rows, q, out[tl.POSE_COV]["v"].astype(np.float64), lin,
                       out[tl.TWIST_COV]["v"].astype(np.float64))
    out[tl.X], out[tl.Y], out[tl.Z] = w.x, w.y, w.z
    out[tl.QX], out[tl.QY], out[tl.QZ], out[tl.QW] = w.q.T
    out[tl.POSE_COV]["v"] = w.pose_cov
    out[tl.VX], out[tl.VY] = w.vx, w.vy
    out[tl.TWIST_COV]["v"] = w.twist_cov
    return out


def tracked_records(result: FrameResult) -> np.ndarray:
    """Every confirmed track as a ``TrackedObject`` record (:mod:`jitterguard.schemas.tracked_layout`; world
    frame, twist linear x/y = world vx, vy, angular z = yaw rate).

    Records, not maps: ~200 nested maps per frame cost milliseconds to build and encode; the records are a few
    column assignments. The tests decode them with the models to keep them honest.
    """
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
    tcov[:, YAW_YAW] = t.yaw_rate_var
    half = 0.5 * np.asarray(t.yaw, dtype=np.float64)
    return tl.tracked_object_layout().pack(n, {
        tl.ID: t.ids, tl.EXISTENCE: t.existence, tl.LABEL: t.label, tl.LABEL_PROB: t.label_prob,
        tl.X: t.x, tl.Y: t.y, tl.Z: t.z, tl.QZ: np.sin(half), tl.QW: np.cos(half), tl.POSE_COV: pcov,
        tl.VX: t.vel[:, 0], tl.VY: t.vel[:, 1], tl.WZ: t.yaw_rate, tl.TWIST_COV: tcov,
        tl.ORIENTATION: t.orientation, tl.STATIONARY: np.zeros(n, dtype=bool), tl.SHAPE_TYPE: Shape.BOUNDING_BOX,
        tl.LENGTH: t.dims[:, 0], tl.WIDTH: t.dims[:, 1], tl.HEIGHT: t.dims[:, 2],
    })


def track_state_records(result: FrameResult) -> np.ndarray:
    """The observed tracks' compact ``TrackState`` records (in ``result.obs_track`` order)."""
    t, i = result.tracks, result.obs_track
    return tl.track_state_layout().pack(len(i), {
        "object_id": [t.ids[k] for k in i.tolist()], "label": t.label[i], "existence_probability": t.existence[i],
        "x": t.x[i], "y": t.y[i], "yaw": t.yaw[i], "vx": t.vel[i, 0], "vy": t.vel[i, 1], "hits": t.hits[i],
        "age_s": np.maximum(0.0, (result.stamp_ns - t.born_ns[i]) * 1e-9),
    })


_ENCODER = msgspec.msgpack.Encoder()
_TRACK_KEY = _ENCODER.encode("track")


def _header(frame: DetectionFrame) -> dict[str, Any]:
    return {"stamp": frame.stamp_ns, "frame_id": WORLD_FRAME, "seq": frame.seq}


def observation_payloads(msg: Any, frame: DetectionFrame, result: FrameResult) -> list[tuple[str, bytes]]:
    """The frame's ``tracks/{id}`` payloads as ``(track_id, TrackObservation payload)``, in track order.

    ``msg`` is the frame as :func:`decode_detections` gives it: records (the observed rows are copied and moved
    into the world frame column-wise) or the generated Struct (the observed detections are moved into the world
    frame in place and encoded by msgspec) — the same bytes either way. The track state beside each is a record
    (:mod:`jitterguard.schemas.tracked_layout`).
    """
    rows = result.obs_det
    if isinstance(msg, tl.DetectedRecords):
        recs = _world_records(msg, frame, result, rows)
        det_raw, det_size = RecordLayout.to_bytes(recs), recs.dtype.itemsize
        det_bytes = [det_raw[k * det_size:(k + 1) * det_size] for k in range(len(recs))]
    else:
        dets = [msg.objects[j] for j in rows.tolist()]
        detections_to_world(dets, frame, result, rows)
        det_bytes = [_ENCODER.encode(d) for d in dets]
    prefix = b"".join((b"\x84", _ENCODER.encode("schema_version"), _ENCODER.encode(SCHEMA_VERSION),
                       _ENCODER.encode("header"), _ENCODER.encode(_header(frame)), _ENCODER.encode("detection")))
    states = track_state_records(result)
    raw, size = RecordLayout.to_bytes(states), states.dtype.itemsize
    ids = result.observed_ids
    return [(ids[k], b"".join((prefix, d, _TRACK_KEY, raw[k * size:(k + 1) * size]))) for k, d in enumerate(det_bytes)]


def ego_pose_map(msg: Any) -> dict[str, Any] | None:
    """The ``ego_pose`` of a decoded ``detections`` message (model, Struct or records) as a plain map."""
    return tl.pose_map(getattr(msg, "ego_pose", None))


def tracked_payload(frame: DetectionFrame, result: FrameResult, ego_pose: dict[str, Any] | None = None) -> bytes:
    """The frame's closing ``TrackedObjects`` payload (every confirmed track, :func:`tracked_records`), with
    the ``ego_pose`` of the detections it came from (:func:`ego_pose_map`)."""
    return tl.encode_tracked_objects(_header(frame), tracked_records(result), result.observed_ids, ego_pose)


def frame_payloads(msg: Any, frame: DetectionFrame, result: FrameResult) -> tuple[list[tuple[str, bytes]], bytes]:
    """:func:`observation_payloads` and :func:`tracked_payload` together (the service builds ``tracked`` only
    once the observations are out, so the classifier starts on them sooner)."""
    return observation_payloads(msg, frame, result), tracked_payload(frame, result, ego_pose_map(msg))
