"""A vehicle's ROS 2 side as zenoh-bridge-ros2dds shows it to Zenoh — each topic's key (the topic without its leading
'/') carrying the message's CDR bytes — played by a Zenoh session. CDR is encoded and decoded by mcap-ros2-support,
an implementation independent of the rosbags typestore jitterguard's ROS 2 services use."""

from __future__ import annotations

from typing import Any

import zenoh

from jitterguard.schemas.models import PointCloud, Pose
from jitterguard.services.replay.sources.ros_types import typestore


def codec(msgtype: str, *, encode: bool) -> Any:
    """mcap-ros2-support's encoder (dict → CDR bytes) or decoder (CDR bytes → message) of ``msgtype``."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return (serialize_dynamic if encode else generate_dynamic)(msgtype, text)[msgtype]


def stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def transform(parent: str, child: str, t: int, p: Pose) -> dict:
    return {"header": {"stamp": stamp(t), "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": {"x": p.position.x, "y": p.position.y, "z": p.position.z},
                          "rotation": {"x": p.orientation.x, "y": p.orientation.y, "z": p.orientation.z,
                                       "w": p.orientation.w}}}


class RosSide:
    """Puts a LiDAR's scans with ``/tf`` (map → base_link, the scan's pose) and ``/tf_static`` (base_link → lidar,
    level) on their topics' keys."""

    def __init__(self, session: zenoh.Session, points_topic: str) -> None:
        self.session = session
        self.points_key = points_topic.strip("/")
        self.tf = codec("tf2_msgs/msg/TFMessage", encode=True)
        self.cloud = codec("sensor_msgs/msg/PointCloud2", encode=True)
        self.static = bytes(self.tf({"transforms": [transform("base_link", "lidar", 0, Pose())]}))

    def send(self, pc: PointCloud, t: int) -> None:
        """One wire scan (sensor frame, its world pose) as the ROS 2 side would have it, stamped ``t``."""
        self.session.put("tf_static", self.static)
        self.session.put("tf", bytes(self.tf({"transforms": [transform("map", "base_link", t, pc.ego_pose)]})))
        fields = [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate(pc.fields)]
        self.session.put(self.points_key, bytes(self.cloud({
            "header": {"stamp": stamp(t), "frame_id": "lidar"}, "height": 1, "width": pc.num_points, "fields": fields,
            "is_bigendian": False, "point_step": 4 * len(fields), "row_step": 4 * len(fields) * pc.num_points,
            "data": pc.data, "is_dense": True})))
