"""Joined frames (:mod:`..bridge`) as a rosbag2 for Autoware: MCAP storage, ``metadata.yaml``, and the topics
Autoware's perception and prediction use:

| topic | type | what |
|---|---|---|
| ``/sensing/lidar/top/pointcloud`` | ``sensor_msgs/msg/PointCloud2`` | the scan (sensor frame; Autoware's ``PointXYZIRC`` layout, or float32 columns as sent: :mod:`jitterguard.ros2.points`) |
| ``/perception/object_recognition/detection/objects`` | ``autoware_perception_msgs/msg/DetectedObjects`` | the detector's output (sensor frame, with its variances) |
| ``/perception/object_recognition/tracking/objects`` | ``autoware_perception_msgs/msg/TrackedObjects`` | the classifier's ``objects``: what Autoware's prediction subscribes to |
| ``/tf`` | ``tf2_msgs/msg/TFMessage`` | ``map → base_link → <sensor frame>`` per frame (:mod:`..bridge.frames`; data in ``base_link`` itself: ``map → base_link``, the whole pose) |

Each message is written at its header stamp (the sensor's time), so ``ros2 bag play`` replays sensor time. The
object conversions are :mod:`jitterguard.ros2.autoware`'s (twists in the object frame, as Autoware states them);
static objects arrive from the classifier with zero twist, the window-mean pose and ``is_stationary`` set, and are
written as they are. The bag is complete (``metadata.yaml`` written) when the recorder stops cleanly (SIGINT or
SIGTERM); a killed recorder leaves an MCAP file without it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...ros2.autoware import RosBuilder
from ...ros2.points import DEFAULT_LAYOUT, LAYOUTS, cloud_layout
from ...ros2.types import DETECTED_OBJECTS, POINTCLOUD2, TF_MESSAGE, TRACKED_OBJECTS, typestore
from ...schemas.models import PointCloud, Pose
from ..bridge.frames import sensor_chain
from ..bridge.joiner import JoinedFrame

POINTS_TOPIC = "/sensing/lidar/top/pointcloud"
DETECTIONS_TOPIC = "/perception/object_recognition/detection/objects"
TRACKING_TOPIC = "/perception/object_recognition/tracking/objects"
TF_TOPIC = "/tf"
BASE_FRAME = "base_link"


class RosbagError(RuntimeError):
    """The bag cannot be written (the folder exists, rosbags missing, a write failed)."""


def pointcloud2(b: RosBuilder, pc: PointCloud, layout: str = DEFAULT_LAYOUT) -> Any:
    """The wire scan as a PointCloud2, one row, in ``layout`` (:mod:`jitterguard.ros2.points`): Autoware's
    ``PointXYZIRC`` by default (its LiDAR pipeline refuses any other layout), or every column float32 as the wire
    sent it. ``is_dense`` only when every point is finite (the wire does not promise it: a publisher other than
    jitterguard's replay may send NaN rows, and a PCL reader trusts ``is_dense`` and skips its NaN checks)."""
    g = b.t
    fields, step, data, dense = cloud_layout(pc.fields, pc.data, layout)
    return g[POINTCLOUD2](header=b.header(pc.header.stamp, pc.header.frame_id), height=1, width=pc.num_points,
                          fields=[g["sensor_msgs/msg/PointField"](name=name, offset=offset, datatype=datatype, count=1)
                                  for name, offset, datatype in fields],
                          is_bigendian=False, point_step=step, row_step=step * pc.num_points,
                          data=np.frombuffer(data, dtype=np.uint8), is_dense=dense)


def tf_message(b: RosBuilder, stamp_ns: int, world: str, sensor_frame: str, pose: Pose) -> Any | None:
    """``world → base_link`` (the sensor pose on the ground plane) and ``base_link → sensor`` (the rest); for data
    in ``base_link`` itself ``world → base_link``, the whole pose (:func:`..bridge.frames.sensor_chain`); None for
    data in the world frame."""
    g = b.t
    links = sensor_chain(pose, world, BASE_FRAME, sensor_frame)
    if not links:
        return None
    return g[TF_MESSAGE](transforms=[
        g["geometry_msgs/msg/TransformStamped"](
            header=b.header(stamp_ns, parent), child_frame_id=child,
            transform=g["geometry_msgs/msg/Transform"](translation=b.vector3(*xyz),
                                                       rotation=g["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
        for parent, child, xyz, q in links])


class Rosbag2Sink:
    """Writes joined frames into a new rosbag2 folder ``path`` (MCAP storage)."""

    def __init__(self, path: str | Path, *, points: bool = True, points_layout: str = DEFAULT_LAYOUT) -> None:
        if points_layout not in LAYOUTS:
            raise RosbagError(f"points layout {points_layout!r}: use one of {', '.join(LAYOUTS)}")
        self.points_layout = points_layout
        try:
            from rosbags.rosbag2 import StoragePlugin, Writer
        except ImportError:
            raise RosbagError("writing ROS 2 bags needs the 'rosbags' package (pip install 'jitterguard[ros2]')") from None
        self.path = Path(path)
        if self.path.exists():
            raise RosbagError(f"{self.path} exists (rosbag2 writes a new folder)")
        self.store = typestore()
        self.builder = RosBuilder(self.store)
        self.points = points
        self._new_writer = lambda: Writer(self.path, version=8, storage_plugin=StoragePlugin.MCAP)
        self.writer: Any = None
        self._closed = False
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def _open(self) -> None:
        """The bag's folder is made with its first frame (or an empty bag at :meth:`close`), not at construction:
        a recorder stopped while it waited for its router had left a folder holding a 0-byte MCAP and no
        ``metadata.yaml`` — no bag any reader opens, and one the next run refused as existing."""
        if self.writer is not None:
            return
        writer = self._new_writer()
        writer.open()
        for topic, msgtype in ((TRACKING_TOPIC, TRACKED_OBJECTS), (DETECTIONS_TOPIC, DETECTED_OBJECTS),
                               (TF_TOPIC, TF_MESSAGE), *(((POINTS_TOPIC, POINTCLOUD2),) if self.points else ())):
            self._conns[topic] = writer.add_connection(topic, msgtype, typestore=self.store)
        self.writer = writer

    def _write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        self._open()
        conn = self._conns[topic]
        self.writer.write(conn, stamp_ns, bytes(self.store.serialize_cdr(msg, conn.msgtype)))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def write(self, frame: JoinedFrame) -> None:
        b = self.builder
        pose = frame.sensor_pose
        tf = None if pose is None else tf_message(b, frame.stamp_ns, frame.world_frame, frame.sensor_frame, pose)
        if tf is not None:
            self._write(TF_TOPIC, frame.stamp_ns, tf)
        if self.points and frame.points is not None:
            self._write(POINTS_TOPIC, frame.points.header.stamp, pointcloud2(b, frame.points, self.points_layout))
        if frame.detections is not None:
            self._write(DETECTIONS_TOPIC, frame.detections.header.stamp, b.detected_objects(frame.detections))
        self._write(TRACKING_TOPIC, frame.objects.header.stamp, b.tracked_objects(frame.objects))

    def close(self) -> None:
        """Close the bag (its ``metadata.yaml`` written); a run that wrote no frame leaves a valid empty bag."""
        if self._closed:
            return
        self._closed = True
        self._open()
        self.writer.close()  # writes metadata.yaml
        self.writer = None
