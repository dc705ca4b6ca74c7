"""The ROS 2 type store every bag reader and writer of jitterguard uses: ROS 2 Humble's standard messages plus
Autoware's ``autoware_perception_msgs`` from the ``.msg`` files shipped in ``jitterguard/ros2/msg/`` (Autoware's
published interface; field order is what CDR serialisation follows).

Bags recorded since Humble embed their own definitions and rosbags prefers those; the shipped ones serve bags that
do not, and every bag jitterguard writes (whose metadata then carries exactly these definitions).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

MSG_DIR = Path(__file__).with_name("msg")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
DETECTED_OBJECTS = "autoware_perception_msgs/msg/DetectedObjects"
TRACKED_OBJECTS = "autoware_perception_msgs/msg/TrackedObjects"
DETECTED_OBJECTS_AUTO = "autoware_auto_perception_msgs/msg/DetectedObjects"
"""The same message under Autoware's name before autoware_msgs 1.0 (2024): bags recorded then carry it. Read by its
fields' names, from the definitions such a bag embeds."""
DETECTION_TYPES = (DETECTED_OBJECTS, DETECTED_OBJECTS_AUTO)


def shipped_definitions() -> dict[str, str]:
    """``{"pkg/msg/Name": text}`` of every shipped ``.msg`` file."""
    out: dict[str, str] = {}
    for f in sorted(MSG_DIR.glob("*/msg/*.msg")):
        out[f"{f.parent.parent.name}/msg/{f.stem}"] = f.read_text()
    return out


def typestore() -> Any:
    """A fresh ROS 2 Humble type store with Autoware's perception messages registered (fresh: readers register a
    bag's own definitions into the store they are given)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in shipped_definitions().items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store
