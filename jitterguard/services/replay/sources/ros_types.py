"""ROS 2 message conversions for the bag source: PointCloud2 -> float32 columns, Autoware DetectedObjects ->
the wire model, pose messages -> :class:`EgoPose`, and pose interpolation. Pure functions on the message
objects rosbags deserialises (attribute access only), so they are tested on hand-built messages.

Autoware's ``autoware_perception_msgs`` are not in any stock ROS 2 type store; bags recorded since Humble
embed their definitions and rosbags uses those. For older bags that do not, the definitions shipped in
``jitterguard/ros2/msg`` (Autoware's published ``.msg`` files) are registered on top of the Humble store.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ....geometry import yaw_from_quaternion
from ....ros2.autoware import twist_from_object_frame
from ....ros2.types import DETECTED_OBJECTS, DETECTION_TYPES, POINTCLOUD2, TF_MESSAGE, typestore  # noqa: F401
from ....schemas.models import DetectedObject, Label
from ..frames import EgoPose
POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)

def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# ------------------------------------------------------------------------------------------- PointCloud2

_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud2_to_array(msg: Any) -> tuple[NDArray[np.float32], tuple[str, ...]]:
    """(P, F) float32 with x, y, z first and every other single-count field after, in message order.

    Handles big-endian clouds, padded points (``point_step`` > fields) and padded rows (``row_step`` >
    ``width * point_step``). Raises ``ValueError`` for a buffer too short for its declared shape.
    """
    endian = ">" if msg.is_bigendian else "<"
    names: list[str] = []
    formats: list[str] = []
    offsets: list[int] = []
    for f in msg.fields:
        if f.datatype not in _DATATYPES:
            raise ValueError(f"field {f.name!r}: unknown PointField datatype {f.datatype}")
        if f.count != 1 or f.name in names or not f.name:
            continue
        size = int(_DATATYPES[f.datatype][1])
        if f.offset + size > msg.point_step:
            raise ValueError(f"field {f.name!r} at offset {f.offset} does not fit point_step {msg.point_step}")
        names.append(f.name)
        formats.append(endian + _DATATYPES[f.datatype])
        offsets.append(int(f.offset))
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise ValueError(f"PointCloud2 has no {','.join(missing)} field(s) (fields: {names})")
    n_rows, n_cols = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    if step <= 0 or row_step < n_cols * step:
        raise ValueError(f"inconsistent point_step {step} / row_step {row_step} for width {n_cols}")
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < n_rows * row_step:
        raise ValueError(f"data holds {data.size} bytes, height {n_rows} x row_step {row_step} need more: truncated")
    rows = data[: n_rows * row_step].reshape(n_rows, row_step)[:, : n_cols * step]
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    structured = np.ascontiguousarray(rows).view(dt).reshape(-1)
    order = ["x", "y", "z", *[n for n in names if n not in ("x", "y", "z")]]
    out = np.empty((structured.shape[0], len(order)), dtype=np.float32)
    for j, name in enumerate(order):
        out[:, j] = structured[name]
    return out, tuple(order)


# ------------------------------------------------------------------------------------------------ poses


def pose_of(msg: Any) -> EgoPose:
    """The pose in an Odometry, PoseStamped or PoseWithCovarianceStamped message."""
    p = msg.pose
    if hasattr(p, "pose"):  # Odometry / PoseWithCovarianceStamped wrap a PoseWithCovariance
        p = p.pose
    return EgoPose(
        float(p.position.x), float(p.position.y), float(p.position.z),
        float(p.orientation.x), float(p.orientation.y), float(p.orientation.z), float(p.orientation.w),
    )


def _slerp(a: EgoPose, b: EgoPose, u: float) -> tuple[float, float, float, float]:
    qa = np.array([a.qx, a.qy, a.qz, a.qw])
    qb = np.array([b.qx, b.qy, b.qz, b.qw])
    qa /= np.linalg.norm(qa)
    qb /= np.linalg.norm(qb)
    d = float(qa @ qb)
    if d < 0:
        qb, d = -qb, -d
    if d > 0.9995:
        q = qa + u * (qb - qa)
    else:
        th = math.acos(d)
        q = (math.sin((1 - u) * th) * qa + math.sin(u * th) * qb) / math.sin(th)
    q /= np.linalg.norm(q)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def interpolate_pose(times: Sequence[int], poses: Sequence[EgoPose], t: int) -> EgoPose:
    """The pose at ``t``: linear in position, slerp in rotation between the bracketing samples; clamped
    to the first/last sample outside their span (a LiDAR stamp a few ms past the last odometry message)."""
    if not times:
        raise ValueError("no pose samples")
    i = bisect.bisect_left(times, t)
    if i == 0:
        return poses[0]
    if i >= len(times):
        return poses[-1]
    t0, t1 = times[i - 1], times[i]
    a, b = poses[i - 1], poses[i]
    if t1 == t0:
        return b
    u = (t - t0) / (t1 - t0)
    return EgoPose(a.x + u * (b.x - a.x), a.y + u * (b.y - a.y), a.z + u * (b.z - a.z), *_slerp(a, b, u))


# -------------------------------------------------------------------------------------- DetectedObjects


def _pose_dict(p: Any) -> dict[str, Any]:
    return {
        "position": {"x": float(p.position.x), "y": float(p.position.y), "z": float(p.position.z)},
        "orientation": {
            "x": float(p.orientation.x), "y": float(p.orientation.y),
            "z": float(p.orientation.z), "w": float(p.orientation.w),
        },
    }


def _vec(v: Any) -> dict[str, float]:
    return {"x": float(v.x), "y": float(v.y), "z": float(v.z)}


def _prob(p: float) -> float:
    """float32 probabilities arrive as 1.0000000xx or -0.0; clamp that rounding, keep real violations."""
    p = float(p)
    return min(max(p, 0.0), 1.0) if -1e-6 <= p <= 1.0 + 1e-6 else p


NEWER_LABELS = {8: "ANIMAL", 9: "HAZARD", 10: "OVER_DRIVABLE", 11: "UNDER_DRIVABLE"}
"""``ObjectClassification`` labels of current autoware_msgs past the contract's ``PEDESTRIAN`` (7)."""


def wire_label(label: int) -> int:
    """An Autoware label as the contract holds it: 0–7 as they are; :data:`NEWER_LABELS` become ``UNKNOWN``, as a node
    that does not know a class takes it (one such box had the whole frame refused as invalid). Other values are kept
    (and refused by validation: not Autoware's)."""
    return int(Label.UNKNOWN) if label in NEWER_LABELS else label


def detected_object_from_ros(obj: Any) -> DetectedObject:
    """An ``autoware_perception_msgs/DetectedObject`` as the wire model (validated: may raise ValidationError).

    Autoware states an object's twist in the object's own frame (x along its heading); the contract states it on the
    axes of the message's frame. The linear x/y and their covariance block are rotated by the object's yaw
    (:func:`jitterguard.ros2.autoware.twist_from_object_frame`). Labels past ``PEDESTRIAN`` become ``UNKNOWN``
    (:func:`wire_label`)."""
    k = obj.kinematics
    o = k.pose_with_covariance.pose.orientation
    lin, tcov = twist_from_object_frame(k.twist_with_covariance.twist.linear, k.twist_with_covariance.covariance,
                                        yaw_from_quaternion(float(o.x), float(o.y), float(o.z), float(o.w)))
    return DetectedObject.model_validate(
        {
            "existence_probability": _prob(obj.existence_probability),
            "classification": [{"label": wire_label(int(c.label)), "probability": _prob(c.probability)}
                               for c in obj.classification],
            "kinematics": {
                "pose_with_covariance": {
                    "pose": _pose_dict(k.pose_with_covariance.pose),
                    "covariance": [float(v) for v in k.pose_with_covariance.covariance],
                },
                "has_position_covariance": bool(k.has_position_covariance),
                "orientation_availability": int(k.orientation_availability),
                "twist_with_covariance": {
                    "twist": {"linear": lin, "angular": _vec(k.twist_with_covariance.twist.angular)},
                    "covariance": tcov,
                },
                "has_twist": bool(k.has_twist),
                "has_twist_covariance": bool(k.has_twist_covariance),
            },
            "shape": {
                "type": int(obj.shape.type),
                "footprint": [_vec(p) for p in obj.shape.footprint.points],
                "dimensions": _vec(obj.shape.dimensions),
            },
        }
    )
