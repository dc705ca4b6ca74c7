"""Wire payloads <-> the detector's arrays: ``PointCloud`` in, ``DetectedObjects`` out. Pure (no I/O, no torch).

Frames. The detector publishes in the *sensor* frame, exactly like the replay's detection-level model
(:mod:`jitterguard.sim.detection_model`): ``header`` is the scan's (stamp, seq, ``frame_id`` — ``lidar``),
``ego_pose`` is the scan's sensor pose in the world frame, positions / yaw / velocities are the network's
sensor-frame boxes (z = box centre relative to the sensor) and the covariances are the network's sensor-frame
variances. Nothing here rotates: the tracker moves each detection into the world frame itself, the 2x2 position
covariance with R Σ Rᵀ (``TrackerCore._to_world`` for gating and the measurement,
:func:`jitterguard.services.tracker.adapter.world_detections` for what it republishes), and the classifier reads
the world-frame covariance the tracker republishes on ``tracks/{id}``. Rotating here as well would rotate twice.

Covariance layout (Autoware's, row-major 6x6 over x, y, z, roll, pitch, yaw): the pose covariance carries
σ²_x at X_X, σ²_y at Y_Y and σ²_yaw at YAW_YAW; the twist covariance σ²_vx at X_X and σ²_vy at Y_Y; every
σ² = exp(log-variance). The heads predict independent axes, so the off-diagonals stay 0; z, roll and pitch have
no head and stay 0 too (as in Autoware's lidar_centerpoint, whose ``has_position_covariance`` speaks for x/y).
The vanilla model (no variance heads) publishes ``has_position_covariance = false`` and all-zero covariances,
which the tracker reads as "use the class defaults".

The service writes records (:func:`detections_payload`, :mod:`jitterguard.schemas.wire`), as the tracker does,
because building and dumping hundreds of nested models costs a tenth of the detection budget; a detection holding a
non-finite number is dropped (and counted by the caller) first, so the payload always validates on receipt.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from ...schemas import wire
from ...schemas.models import (
    COVARIANCE_SIZE,
    LABEL_BY_NAME,
    X_X,
    Y_Y,
    YAW_YAW,
    Header,
    OrientationAvailability,
    PointCloud,
    Pose,
    Shape,
)
from ...schemas.wire import DetectedColumns, write_detected_objects
from .config import CLASS_NAMES, VAR_NAMES, Detections3D
from .sweeps import pose_matrices

F32 = NDArray[np.float32]

POINT_COLUMNS = ("x", "y", "z", "intensity")
"""What the network reads, in this order (intensity 0–255; a cloud without an intensity field gets zeros)."""

INTENSITY_MAX = 255.0
"""The intensity scale the network was trained on (nuScenes' and the synthetic sensor's 0–255)."""


def scan_points(msg: PointCloud) -> tuple[F32, int]:
    """The scan as the network's (P, 4) float32 x, y, z, intensity, and how many non-finite rows were dropped.

    Columns are picked by name (replays send x, y, z, intensity, ring; other sources may order or omit them).
    The schema already checked that the buffer length matches ``num_points × len(fields)``.
    """
    ncol = len(msg.fields)
    raw = np.frombuffer(msg.data, dtype="<f4").reshape(msg.num_points, ncol)
    return points_from_fields(raw, tuple(msg.fields))


def scan_pose(msg: PointCloud) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The sensor's pose in the world at the scan's stamp as (3×3 rotation, translation): what moves earlier
    sweeps into this scan's frame (:mod:`.sweeps`)."""
    p, q = msg.ego_pose.position, msg.ego_pose.orientation
    return pose_matrices((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))


def points_from_fields(raw: NDArray[np.floating], fields: Sequence[str]) -> tuple[F32, int]:
    """(P, F) columns named ``fields`` → the network's (P, 4) float32 x, y, z, intensity (zeros where there is
    no intensity field), rows with a non-finite x, y or z dropped (a NaN intensity is read as 0, a dark return: it
    had dropped the whole point); returns the points and how many rows were dropped.

    Intensity is brought to the network's 0–255 (:func:`intensity_to_network_scale`) here, the one reader of
    the live service, the offline evaluator and ``adapt``: a KITTI scan's 0–1 reflectance had been fed as is
    live (every return nearly black to the network) but scaled in ``adapt``, and one stray return of intensity
    10⁵ could drive a head's variance beyond the wire's limit."""
    cols = [list(fields).index(c) if c in fields else -1 for c in POINT_COLUMNS]
    pts = np.zeros((len(raw), len(POINT_COLUMNS)), dtype=np.float32)
    for j, c in enumerate(cols):
        if c >= 0:
            pts[:, j] = raw[:, c]
    finite = np.isfinite(pts[:, :3]).all(axis=1)  # a return is where it is: a NaN intensity alone costs it nothing
    dropped = int(finite.size - np.count_nonzero(finite))
    if dropped:
        pts = pts[finite]
    np.nan_to_num(pts[:, 3], copy=False, nan=0.0, posinf=np.inf, neginf=0.0)  # ±inf: clipped to the scale's ends
    return intensity_to_network_scale(pts), dropped


REFLECTANCE_STRAYS = 1e-3
"""Share of a reflectance scan's intensities that may lie outside [0, 1] (stray returns): one stray of 1.2 among
35,000 values had made a KITTI-like scan read as 0–255, every return nearly black."""


def intensity_to_network_scale(pts: F32) -> F32:
    """``pts`` (P, 4, owned by the caller) with column 3 on the network's 0–255 scale, in place: a scan whose
    intensities lie in [0, 1] but for at most 0.1 % strays, some of them fractional, is a reflectance (KITTI's
    HDL-64E) and is multiplied by 255 (a scan of whole-number intensities 0 and 1 is a dark 0–255 scan and stays);
    values then outside 0–255 (16-bit sensors, stray returns) are clipped to it. A sensor whose intensities mean something
    else is the case for a model trained without intensity (``train --no-intensity``)."""
    if not len(pts):
        return pts
    col = pts[:, 3]
    strays = np.count_nonzero((col > 1.0) | (col < 0.0))
    if strays <= REFLECTANCE_STRAYS * len(col) and bool(np.any(col != np.round(col))):
        col *= INTENSITY_MAX
    np.clip(col, 0.0, INTENSITY_MAX, out=col)
    return pts


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
    return det.subset(ok), dropped


def detections_within_limits(det: Detections3D, limits: wire.Limits = wire.LIMITS) -> tuple[Detections3D, int]:
    """``det`` (finite: :func:`finite_detections`) without rows the tracker's reader would refuse the whole frame
    for — a centre beyond ``max_abs_coordinate_m``, a velocity beyond ``max_abs_speed_mps``, a variance beyond
    ``max_variance`` (a stray return of absurd intensity can drive a head there) — and how many went. The rows
    are judged as written (:func:`detected_records`) by the readers' own rule (:func:`wire.within_limits`)."""
    ok = wire.within_limits(detected_records(det), limits)
    dropped = int(ok.size - np.count_nonzero(ok))
    return (det, 0) if not dropped else (det.subset(ok), dropped)


def publishable_detections(detect: Callable[[np.ndarray], Detections3D], points: np.ndarray, *,
                           uncertainty: bool) -> tuple[Detections3D, int, int]:
    """``detect`` (e.g. ``Detector.detect``) run on the network's input ``points`` — an empty scan gives no
    detections: the network is not run on nothing — and its detections as the service publishes them: without rows
    holding a non-finite number (:func:`finite_detections`) or lying beyond the wire's limits
    (:func:`detections_within_limits`), with how many of each went. The one step of the live service and the
    offline evaluator (``eval.detector_input.detect_scan``)."""
    det = detect(points) if len(points) else Detections3D.empty(uncertainty)
    det, nonfinite = finite_detections(det)
    det, beyond = detections_within_limits(det)
    return det, nonfinite, beyond


def detections_payload(
    det: Detections3D,
    header: Header,
    ego_pose: Pose,
    class_names: Sequence[str] = CLASS_NAMES,
    *,
    has_twist: bool = True,
) -> bytes:
    """One scan's ``DetectedObjects`` payload (sensor frame, see the module doc), written as records.

    ``det`` must be finite (:func:`finite_detections`); ``header`` and ``ego_pose`` are the scan's and are
    carried over unchanged. Scores become both ``existence_probability`` and the single class's probability
    (CenterPoint has one score per box). ``has_twist`` says whether the network's velocity heads are meant to be
    used; the twist is the sensor-frame (vx, vy), as the replay's detection model writes it. Valid by
    construction (finite rows, scores clipped to [0, 1], variances = exp(·) ≥ 0); every receiver reads it with
    :func:`~jitterguard.schemas.read_detected_objects`, and the tests validate it with the model.
    """
    objects = detected_records(det, class_names, has_twist=has_twist)
    return write_detected_objects(DetectedColumns(header, ego_pose, objects, np.zeros(len(det))))


def detected_records(det: Detections3D, class_names: Sequence[str] = CLASS_NAMES, *,
                     has_twist: bool = True) -> np.ndarray:
    """``det`` as the ``DetectedObject`` records :func:`detections_payload` writes (see there)."""
    labels = np.asarray(class_labels(class_names), dtype=np.int64)
    n = len(det)
    b = det.boxes.astype(np.float64)
    scores = np.clip(det.scores.astype(np.float64), 0.0, 1.0)
    half = 0.5 * b[:, 6]
    lv = det.log_variances
    var = np.exp(lv.astype(np.float64)) if lv is not None else np.zeros((n, len(VAR_NAMES)))  # x, y, vx, vy, yaw
    pose_cov, twist_cov = np.zeros((n, COVARIANCE_SIZE)), np.zeros((n, COVARIANCE_SIZE))
    pose_cov[:, X_X], pose_cov[:, Y_Y], pose_cov[:, YAW_YAW] = var[:, 0], var[:, 1], var[:, 4]
    if has_twist:
        twist_cov[:, X_X], twist_cov[:, Y_Y] = var[:, 2], var[:, 3]
    return wire.DETECTED.pack(n, {
        wire.EXISTENCE: scores, wire.LABEL: labels[det.labels.astype(np.int64)], wire.LABEL_PROB: scores,
        wire.X: b[:, 0], wire.Y: b[:, 1], wire.Z: b[:, 2], wire.QZ: np.sin(half), wire.QW: np.cos(half),
        wire.POSE_COV: pose_cov, wire.HAS_POSITION_COV: np.full(n, lv is not None),
        wire.ORIENTATION: int(OrientationAvailability.AVAILABLE),
        wire.VX: b[:, 7] if has_twist else 0.0, wire.VY: b[:, 8] if has_twist else 0.0, wire.TWIST_COV: twist_cov,
        "kinematics.has_twist": np.full(n, has_twist), "kinematics.has_twist_covariance": np.full(n, lv is not None and has_twist),
        wire.SHAPE_TYPE: Shape.BOUNDING_BOX, wire.LENGTH: b[:, 3], wire.WIDTH: b[:, 4], wire.HEIGHT: b[:, 5],
    })
