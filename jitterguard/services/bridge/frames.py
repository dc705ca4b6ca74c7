"""The frames a bridge publishes around the sensor pose the wire carries.

The contract's ``ego_pose`` is the *sensor's* pose in the world. Viewers and ROS tools want a gravity-aligned
vehicle frame too; the wire does not carry the vehicle's own extrinsic, so the bridges derive one: the sensor pose
projected onto the ground plane (x, y and yaw; z = 0, no roll or pitch), named ``ego`` in Foxglove and
``base_link`` in ROS 2 bags. The remainder (height, roll, pitch) is the ``ego → sensor`` transform; composed, the
two are the sensor pose exactly. Where the data's own frame already has the ground frame's name (Autoware's
concatenated cloud and its detectors' ``DetectedObjects`` are in ``base_link``) the sensor pose is that frame's
whole pose, written as the one transform ``world → frame`` (:func:`sensor_chain`): a ``base_link → base_link`` link
is one tf2 refuses, and the ground-plane ``base_link`` had put such data at z = 0, level.
"""

from __future__ import annotations

import math
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


Link = tuple[str, str, tuple[float, float, float], tuple[float, float, float, float]]
"""(parent, child, translation, rotation as x, y, z, w)."""


def sensor_chain(pose: Pose, world: str, ground: str, sensor: str) -> list[Link]:
    """The transforms that put frame ``sensor`` at ``pose`` in ``world``: ``world → ground`` (the ground split's x, y
    and yaw) and ``ground → sensor`` (the rest); ``world → sensor`` (the whole pose) when ``sensor`` is ``ground``
    itself; none when it is ``world`` (data already in the world frame). No frame is its own parent."""
    if sensor == world:
        return []
    if sensor == ground:
        p, q = pose.position, pose.orientation
        return [(world, sensor, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w))]
    s = ground_split(pose)
    half = s.yaw / 2
    return [(world, ground, (s.x, s.y, 0.0), (0.0, 0.0, math.sin(half), math.cos(half))),
            (ground, sensor, (0.0, 0.0, s.z), s.rest)]
