"""Wire payloads <-> the detector's arrays: ``PointCloud`` in, ``DetectedObjects`` out. Pure (no I/O, no torch).

Frames. The detector publishes in the *sensor* frame, exactly like the replay's detection-level model
(:mod:`jitterguard.sim.detection_model`): ``header`` is the scan's (stamp, seq, ``frame_id`` — ``lidar``),
``ego_pose`` is the scan's sensor pose in the world frame, positions / yaw / velocities are the network's
sensor-frame boxes (z = box centre relative to the sensor) and the covariances are the network's sensor-frame
variances. Nothing here rotates: the tracker moves each detection into the world frame itself, the 2x2 position
covariance with R Σ Rᵀ (``TrackerCore._to_world`` for gating and the measurement,
:func:`jitterguard.services.tracker.convert.detections_to_world` for what it republishes), and the classifier reads
the world-frame covariance the tracker republishes on ``tracks/{id}``. Rotating here as well would rotate twice.

Covariance layout (Autoware's, row-major 6x6 over x, y, z, roll, pitch, yaw): the pose covariance carries
σ²_x at X_X, σ²_y at Y_Y and σ²_yaw at YAW_YAW; the twist covariance σ²_vx at X_X and σ²_vy at Y_Y; every
σ² = exp(log-variance). The heads predict independent axes, so the off-diagonals stay 0; z, roll and pitch have
no head and stay 0 too (as in Autoware's lidar_centerpoint, whose ``has_position_covariance`` speaks for x/y).
The vanilla model (no variance heads) publishes ``has_position_covariance = false`` and all-zero covariances,
which the tracker reads as "use the class defaults".

The service publishes plain maps (:func:`detections_map`), as the tracker does, because building and dumping
hundreds of nested models costs a tenth of the detection budget; a detection holding a non-finite number is
dropped (and counted by the caller) first, so the map always validates on receipt.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ...schemas.models import (
    COVARIANCE_SIZE,
    LABEL_BY_NAME,
    SCHEMA_VERSION,
    X_X,
    Y_Y,
    YAW_YAW,
    DetectedObjects,
    Header,
    OrientationAvailability,
    PointCloud,
    Pose,
    Shape,
)
from .config import CLASS_NAMES, Detections3D

F32 = NDArray[np.float32]

POINT_COLUMNS = ("x", "y", "z", "intensity")
"""What the network reads, in this order (intensity 0–255; a cloud without an intensity field gets zeros)."""


def scan_points(msg: PointCloud) -> tuple[F32, int]:
    """The scan as the network's (P, 4) float32 x, y, z, intensity, and how many non-finite rows were dropped.

    Columns are picked by name (replays send x, y, z, intensity, ring; other sources may order or omit them).
    The schema already checked that the buffer length matches ``num_points × len(fields)``.
    """
    ncol = len(msg.fields)
    raw = np.frombuffer(msg.data, dtype="<f4").reshape(msg.num_points, ncol)
    return points_from_fields(raw, tuple(msg.fields))


def points_from_fields(raw: NDArray[np.floating], fields: Sequence[str]) -> tuple[F32, int]:
    """(P, F) columns named ``fields`` → the network's (P, 4) float32 x, y, z, intensity (zeros where there is
    no intensity field), non-finite rows dropped; returns the points and how many rows were dropped."""
    cols = [list(fields).index(c) if c in fields else -1 for c in POINT_COLUMNS]
    pts = np.zeros((len(raw), len(POINT_COLUMNS)), dtype=np.float32)
    for j, c in enumerate(cols):
        if c >= 0:
            pts[:, j] = raw[:, c]
    finite = np.isfinite(pts).all(axis=1)
    dropped = int(finite.size - np.count_nonzero(finite))
    if dropped:
        pts = pts[finite]
    return pts, dropped


def class_labels(class_names: Sequence[str] = CLASS_NAMES) -> tuple[int, ...]:
    """Autoware label of each class index of a detector config (by name, so a config's class order is honoured)."""
    try:
        return tuple(int(LABEL_BY_NAME[n]) for n in class_names)
    except KeyError as exc:
        raise ValueError(f"detector class {exc.args[0]!r} has no Autoware label") from None


def finite_detections(det: Detections3D) -> tuple[Detections3D, int]:
    """``det`` without rows that hold a non-finite number (box, score or log-variance), and how many went.

    A log-variance that overflows ``exp`` (> ~709) counts as non-finite: such a variance says nothing usable.
    """
    ok = np.isfinite(det.boxes).all(axis=1) & np.isfinite(det.scores)
    if det.log_variances is not None:
        with np.errstate(over="ignore"):
            ok &= np.isfinite(np.exp(det.log_variances.astype(np.float64))).all(axis=1)
    dropped = int(ok.size - np.count_nonzero(ok))
    if not dropped:
        return det, 0
    lv = det.log_variances[ok] if det.log_variances is not None else None
    return Detections3D(det.boxes[ok], det.scores[ok], det.labels[ok], lv), dropped


def _cov(entries: dict[int, float]) -> list[float]:
    c = [0.0] * COVARIANCE_SIZE
    for k, v in entries.items():
        c[k] = v
    return c


def detections_map(
    det: Detections3D,
    header: Header,
    ego_pose: Pose,
    class_names: Sequence[str] = CLASS_NAMES,
    *,
    has_twist: bool = True,
) -> dict:
    """One scan's ``DetectedObjects`` as a msgpack-ready map (sensor frame, see the module doc).

    ``det`` must be finite (:func:`finite_detections`); ``header`` and ``ego_pose`` are the scan's and are
    carried over unchanged. Scores become both ``existence_probability`` and the single class's probability
    (CenterPoint has one score per box). ``has_twist`` says whether the network's velocity heads are meant to be
    used; the twist is the sensor-frame (vx, vy), as the replay's detection model writes it.

    A map, not a model: validating and dumping 300 nested models costs ~10 ms a scan, a tenth of the lite
    detector's budget, and every receiver validates anyway. The map is valid by construction (finite rows,
    scores clipped to [0, 1], variances = exp(·) ≥ 0); :func:`detections_message` validates it, and the tests
    hold the two together.
    """
    labels = class_labels(class_names)
    n = len(det)
    boxes = det.boxes.astype(np.float64).tolist()
    scores = np.clip(det.scores.astype(np.float64), 0.0, 1.0).tolist()
    lbl = [labels[int(i)] for i in det.labels.tolist()]
    half = 0.5 * det.boxes[:, 6].astype(np.float64)
    qz, qw = np.sin(half).tolist(), np.cos(half).tolist()
    lv = det.log_variances
    has_cov = lv is not None
    var = np.exp(lv.astype(np.float64)).tolist() if lv is not None else None  # x, y, vx, vy, yaw
    zero = [0.0] * COVARIANCE_SIZE
    objects = []
    for i in range(n):
        x, y, z, length, width, height, _yaw, vx, vy = boxes[i]
        v = var[i] if var is not None else None
        pose_cov = _cov({X_X: v[0], Y_Y: v[1], YAW_YAW: v[4]}) if v is not None else list(zero)
        twist_cov = _cov({X_X: v[2], Y_Y: v[3]}) if (v is not None and has_twist) else list(zero)
        objects.append({
            "existence_probability": scores[i],
            "classification": [{"label": lbl[i], "probability": scores[i]}],
            "kinematics": {
                "pose_with_covariance": {
                    "pose": {"position": {"x": x, "y": y, "z": z},
                             "orientation": {"x": 0.0, "y": 0.0, "z": qz[i], "w": qw[i]}},
                    "covariance": pose_cov,
                },
                "has_position_covariance": has_cov,
                "orientation_availability": int(OrientationAvailability.AVAILABLE),
                "twist_with_covariance": {
                    "twist": {"linear": {"x": vx if has_twist else 0.0, "y": vy if has_twist else 0.0, "z": 0.0},
                              "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                    "covariance": twist_cov,
                },
                "has_twist": has_twist,
                "has_twist_covariance": has_cov and has_twist,
            },
            "shape": {"type": Shape.BOUNDING_BOX, "footprint": [],
                      "dimensions": {"x": length, "y": width, "z": height}},
        })
    return {
        "schema_version": SCHEMA_VERSION,
        "header": header.model_dump(),
        "ego_pose": ego_pose.model_dump(),
        "objects": objects,
    }


def detections_message(
    det: Detections3D,
    header: Header,
    ego_pose: Pose,
    class_names: Sequence[str] = CLASS_NAMES,
    *,
    has_twist: bool = True,
) -> DetectedObjects:
    """:func:`detections_map` validated into the ``DetectedObjects`` model."""
    return DetectedObjects.model_validate(detections_map(det, header, ego_pose, class_names, has_twist=has_twist))
