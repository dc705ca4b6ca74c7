"""The frames a bridge publishes around the sensor pose the wire carries.

The contract's ``ego_pose`` is the *sensor's* pose in the world. Viewers and ROS tools want a gravity-aligned
vehicle frame too; the wire does not carry the vehicle's own extrinsic, so the bridges derive one: the sensor pose
projected onto the ground plane (x, y and yaw; z = 0, no roll or pitch), named ``ego`` in Foxglove and
``base_link`` in ROS 2 bags. The remainder (height, roll, pitch) is the ``ego → sensor`` transform; composed, the
two are the sensor pose exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

from ...geometry import quaternion_from_yaw, yaw_from_quaternion
from ...schemas.models import Pose
from ..replay.frames import quaternion_multiply


@dataclass(frozen=True)
class GroundSplit:
    """``world → ego``: (x, y, 0) and the yaw; ``ego → sensor``: (0, 0, z) and the rotation left (x, y, z, w)."""

    x: float
    y: float
    yaw: float
    z: float
    rest: tuple[float, float, float, float]


def ground_split(pose: Pose) -> GroundSplit:
    q = pose.orientation
    yaw = yaw_from_quaternion(q.x, q.y, q.z, q.w)
    rest = quaternion_multiply(quaternion_from_yaw(-yaw), (q.x, q.y, q.z, q.w))
    return GroundSplit(pose.position.x, pose.position.y, yaw, pose.position.z, rest)
