"""The wire contract's perception messages as Autoware's ``autoware_perception_msgs`` (and back, for twists).

The wire models mirror Autoware's field names, so the conversion is a field copy with three exceptions, each what
Autoware's own nodes expect:

- **Twist frame.** Autoware states an object's twist in the object's frame (``linear.x`` along its heading, ``y``
  to its left); the contract states it on the axes of the message's frame (the sensor for detections, the world
  for tracks). The linear x/y are rotated by −yaw, and the twist covariance with them (T Σ Tᵀ, T rotating x/y).
  Static objects carry zero twist and stay zero.
- **Widths.** ROS probabilities are float32; covariances and poses float64 as on the wire.
- **IDs.** The 32-hex-digit track ID is the 16-byte ``unique_identifier_msgs/UUID`` it spells.

Pose covariances are copied unchanged: the contract uses Autoware's layout (row-major 6×6 over x, y, z, roll,
pitch, yaw in the message's frame). Functions take the rosbags type store (:func:`.types.typestore`) so this
module imports no ROS library itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..geometry import yaw_from_quaternion
from ..schemas.models import (
    AccelWithCovariance,
    DetectedObject,
    DetectedObjects,
    ObjectClassification,
    Pose,
    PoseWithCovariance,
    Shape,
    TrackedObject,
    TrackedObjects,
    TwistWithCovariance,
)
from .types import DETECTED_OBJECTS, TRACKED_OBJECTS


def _rotation6(yaw: float) -> np.ndarray:
    """6×6 rotating the (x, y) components of a twist by ``yaw`` (everything else unchanged)."""
    t = np.eye(6)
    c, s = math.cos(yaw), math.sin(yaw)
    t[:2, :2] = ((c, -s), (s, c))
    return t


def twist_to_object_frame(linear: Any, covariance: Sequence[float], yaw: float) -> tuple[tuple[float, float, float],
                                                                                        list[float]]:
    """A twist on a frame's axes → on the axes of an object with heading ``yaw`` in that frame (Autoware)."""
    t = _rotation6(-yaw)
    v = t[:2, :2] @ np.array([linear.x, linear.y])
    cov = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    if cov.any():
        cov = t @ cov @ t.T
    return (float(v[0]), float(v[1]), float(linear.z)), [float(x) for x in cov.reshape(-1)]


def twist_from_object_frame(linear: Any, covariance: Sequence[float], yaw: float) -> tuple[dict[str, float],
                                                                                          list[float]]:
    """The inverse of :func:`twist_to_object_frame`: an Autoware object-frame twist on its message frame's axes."""
    t = _rotation6(yaw)
    v = t[:2, :2] @ np.array([float(linear.x), float(linear.y)])
    cov = np.asarray([float(c) for c in covariance], dtype=np.float64).reshape(6, 6)
    if cov.any():
        cov = t @ cov @ t.T
    return {"x": float(v[0]), "y": float(v[1]), "z": float(linear.z)}, [float(x) for x in cov.reshape(-1)]


def object_yaw(pose: Pose) -> float:
    q = pose.orientation
    return yaw_from_quaternion(q.x, q.y, q.z, q.w)


def uuid_bytes(track_id: str) -> np.ndarray:
    """The 16 bytes of a 32-hex-digit track ID (``unique_identifier_msgs/UUID.uuid``)."""
    return np.frombuffer(bytes.fromhex(track_id), dtype=np.uint8).copy()


class RosBuilder:
    """Builds ROS 2 messages (rosbags dataclasses) from wire models with one type store."""

    def __init__(self, store: Any) -> None:
        self.store = store
        self.t = store.types

    # ------------------------------------------------------------------------------------ geometry_msgs

    def time(self, stamp_ns: int) -> Any:
        return self.t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self.t["std_msgs/msg/Header"](stamp=self.time(stamp_ns), frame_id=frame_id)

    def vector3(self, x: float, y: float, z: float) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def pose(self, p: Pose) -> Any:
        g = self.t
        return g["geometry_msgs/msg/Pose"](
            position=g["geometry_msgs/msg/Point"](x=p.position.x, y=p.position.y, z=p.position.z),
            orientation=g["geometry_msgs/msg/Quaternion"](x=p.orientation.x, y=p.orientation.y, z=p.orientation.z,
                                                          w=p.orientation.w))

    def pose_with_covariance(self, pwc: PoseWithCovariance) -> Any:
        return self.t["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(pwc.pose),
                                                              covariance=np.asarray(pwc.covariance, dtype=np.float64))

    def twist_with_covariance(self, twc: TwistWithCovariance, yaw: float) -> Any:
        (vx, vy, vz), cov = twist_to_object_frame(twc.twist.linear, twc.covariance, yaw)
        a = twc.twist.angular
        twist = self.t["geometry_msgs/msg/Twist"](linear=self.vector3(vx, vy, vz), angular=self.vector3(a.x, a.y, a.z))
        return self.t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.asarray(cov))

    def accel_with_covariance(self, awc: AccelWithCovariance) -> Any:
        lin, ang = awc.accel.linear, awc.accel.angular
        accel = self.t["geometry_msgs/msg/Accel"](linear=self.vector3(lin.x, lin.y, lin.z),
                                                  angular=self.vector3(ang.x, ang.y, ang.z))
        return self.t["geometry_msgs/msg/AccelWithCovariance"](accel=accel,
                                                               covariance=np.asarray(awc.covariance, dtype=np.float64))

    # ------------------------------------------------------------------------------------ autoware_perception_msgs

    def classification(self, cs: list[ObjectClassification]) -> list[Any]:
        oc = self.t["autoware_perception_msgs/msg/ObjectClassification"]
        return [oc(label=int(c.label), probability=float(c.probability)) for c in cs]

    def shape(self, s: Shape) -> Any:
        g = self.t
        pts = [g["geometry_msgs/msg/Point32"](x=p.x, y=p.y, z=p.z) for p in s.footprint]
        return g["autoware_perception_msgs/msg/Shape"](type=int(s.type), footprint=g["geometry_msgs/msg/Polygon"](points=pts),
                                                       dimensions=self.vector3(s.dimensions.x, s.dimensions.y, s.dimensions.z))

    def detected_object(self, o: DetectedObject) -> Any:
        k = o.kinematics
        kin = self.t["autoware_perception_msgs/msg/DetectedObjectKinematics"](
            pose_with_covariance=self.pose_with_covariance(k.pose_with_covariance),
            has_position_covariance=bool(k.has_position_covariance),
            orientation_availability=int(k.orientation_availability),
            twist_with_covariance=self.twist_with_covariance(k.twist_with_covariance,
                                                             object_yaw(k.pose_with_covariance.pose)),
            has_twist=bool(k.has_twist), has_twist_covariance=bool(k.has_twist_covariance))
        return self.t["autoware_perception_msgs/msg/DetectedObject"](
            existence_probability=float(o.existence_probability), classification=self.classification(o.classification),
            kinematics=kin, shape=self.shape(o.shape))

    def detected_objects(self, msg: DetectedObjects) -> Any:
        return self.t[DETECTED_OBJECTS](header=self.header(msg.header.stamp, msg.header.frame_id),
                                        objects=[self.detected_object(o) for o in msg.objects])

    def tracked_object(self, o: TrackedObject) -> Any:
        k = o.kinematics
        kin = self.t["autoware_perception_msgs/msg/TrackedObjectKinematics"](
            pose_with_covariance=self.pose_with_covariance(k.pose_with_covariance),
            twist_with_covariance=self.twist_with_covariance(k.twist_with_covariance,
                                                             object_yaw(k.pose_with_covariance.pose)),
            acceleration_with_covariance=self.accel_with_covariance(k.acceleration_with_covariance),
            orientation_availability=int(k.orientation_availability), is_stationary=bool(k.is_stationary))
        return self.t["autoware_perception_msgs/msg/TrackedObject"](
            object_id=self.t["unique_identifier_msgs/msg/UUID"](uuid=uuid_bytes(o.object_id)),
            existence_probability=float(o.existence_probability), classification=self.classification(o.classification),
            kinematics=kin, shape=self.shape(o.shape))

    def tracked_objects(self, msg: TrackedObjects) -> Any:
        return self.t[TRACKED_OBJECTS](header=self.header(msg.header.stamp, msg.header.frame_id),
                                       objects=[self.tracked_object(o) for o in msg.objects])
