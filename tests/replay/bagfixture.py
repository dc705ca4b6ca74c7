"""Write small ROS 2 bags with rosbags, so the bag source is tested without external recordings.

``write_bag`` makes a bag with a ``sensor_msgs/PointCloud2`` topic (with a padding byte per point, like
real drivers), a ``nav_msgs/Odometry`` topic and an Autoware ``DetectedObjects`` topic, optionally with one
garbage message, and returns what a reader should get back. With ``with_tf`` it has ``/tf`` (``map → base_link``)
and ``/tf_static`` (``base_link → lidar_top``, :data:`LIDAR_MOUNT` or a tilted mount given as roll, pitch, yaw);
with ``ground`` the clouds are points of the flat, level ground under the vehicle, seen from the LiDAR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jitterguard.services.replay.sources.ros_types import DETECTED_OBJECTS, POINTCLOUD2, typestore

CLOUD_TOPIC = "/sensing/lidar/top/pointcloud"
ODOM_TOPIC = "/localization/kinematic_state"
DET_TOPIC = "/perception/object_recognition/detection/objects"
T0 = 1_700_000_000 * 10**9
LIDAR_MOUNT = (1.0, 0.0, 2.0, 0.5)  # base_link -> lidar_top: x, y, z, yaw (what /tf_static says)


@dataclass
class BagContents:
    path: Path
    clouds: list[np.ndarray] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)
    odom: list[tuple[int, float, float, float]] = field(default_factory=list)  # t, x, y, yaw
    det_positions: list[list[tuple[float, float]]] = field(default_factory=list)
    mount_q: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # base_link -> lidar_top rotation (x, y, z, w)


def quaternion_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll), as tf2's ``setRPY``."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def _header(ts: Any, t_ns: int, frame_id: str) -> Any:
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame_id)


def _cloud(ts: Any, t_ns: int, pts: np.ndarray, frame_id: str = "lidar_top") -> Any:
    """x, y, z, intensity float32 + one padding byte per point (point_step 17), one row."""
    PointField = ts.types["sensor_msgs/msg/PointField"]
    PointCloud2 = ts.types[POINTCLOUD2]
    n = pts.shape[0]
    dt = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4"] * 4, "offsets": [0, 4, 8, 12], "itemsize": 17})
    rec = np.zeros(n, dtype=dt)
    for j, name in enumerate(("x", "y", "z", "intensity")):
        rec[name] = pts[:, j]
    fields = [PointField(name=nm, offset=4 * j, datatype=7, count=1) for j, nm in enumerate(("x", "y", "z", "intensity"))]
    return PointCloud2(
        header=_header(ts, t_ns, frame_id), height=1, width=n, fields=fields, is_bigendian=False,
        point_step=17, row_step=17 * n, data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=True,
    )


def _odom(ts: Any, t_ns: int, x: float, y: float, yaw: float | None) -> Any:
    """``yaw`` None: no heading (an all-zero quaternion, as a GNSS fix without one)."""
    g = ts.types
    qz, qw = (0.0, 0.0) if yaw is None else (math.sin(yaw / 2), math.cos(yaw / 2))
    pose = g["geometry_msgs/msg/Pose"](
        position=g["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=g["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=qz, w=qw),
    )
    zero3 = g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return g["nav_msgs/msg/Odometry"](
        header=_header(ts, t_ns, "map"), child_frame_id="base_link",
        pose=g["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=g["geometry_msgs/msg/TwistWithCovariance"](twist=g["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)),
    )


TF = "tf2_msgs/msg/TFMessage"


def _tf(ts: Any, edges: list[tuple[int, str, str, float, float, float, Any]]) -> Any:
    """Each edge's last item is a yaw or an (x, y, z, w) quaternion."""
    g = ts.types
    out = []
    for t, parent, child, x, y, z, yaw in edges:
        qx, qy, qz, qw = yaw if isinstance(yaw, tuple) else (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        tr = g["geometry_msgs/msg/Transform"](
            translation=g["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=g["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )
        out.append(g["geometry_msgs/msg/TransformStamped"](header=_header(ts, t, parent), child_frame_id=child, transform=tr))
    return g[TF](transforms=out)


def _detections(ts: Any, t_ns: int, positions: list[tuple[float, float]], label: int = 1, prob: float = 0.9) -> Any:
    g = ts.types
    P = "autoware_perception_msgs/msg/"
    zero3 = g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    objs = []
    for x, y in positions:
        cov = np.zeros(36)
        cov[0], cov[7] = 0.04, 0.09
        pose = g["geometry_msgs/msg/Pose"](
            position=g["geometry_msgs/msg/Point"](x=x, y=y, z=0.5),
            orientation=g["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        kin = g[P + "DetectedObjectKinematics"](
            pose_with_covariance=g["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            has_position_covariance=True, orientation_availability=2,
            twist_with_covariance=g["geometry_msgs/msg/TwistWithCovariance"](twist=g["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)),
            has_twist=False, has_twist_covariance=False,
        )
        shape = g[P + "Shape"](type=0, footprint=g["geometry_msgs/msg/Polygon"](points=[]), dimensions=g["geometry_msgs/msg/Vector3"](x=4.5, y=1.8, z=1.5))
        objs.append(g[P + "DetectedObject"](
            existence_probability=prob, classification=[g[P + "ObjectClassification"](label=label, probability=prob)],
            kinematics=kin, shape=shape,
        ))
    return g[DETECTED_OBJECTS](header=_header(ts, t_ns, "base_link"), objects=objs)


def write_bag(
    path: Path,
    *,
    storage: str = "sqlite3",
    n: int = 4,
    points: int = 50,
    garbage_at: int | None = None,
    bad_label_at: int | None = None,
    second_cloud_topic: bool = False,
    with_tf: bool = False,
    cloud_frame: str = "lidar_top",
    headless_odom: tuple[int, ...] = (),
    empty_cloud_topic: bool = False,
    mount_rpy: tuple[float, float, float] | None = None,
    ground: bool = False,
    torn_pose_at: int | None = None,
    poses_from_ns: int = 0,
) -> BagContents:
    """Write the bag at ``path`` (a folder that must not exist) and return what it holds. ``empty_cloud_topic``:
    the cloud topic is declared but holds no message (a stack fed detections records one so). ``mount_rpy``: the
    LiDAR's rotation in base_link (roll, pitch, yaw) instead of :data:`LIDAR_MOUNT`'s yaw, at its translation.
    ``ground``: each cloud is ``points`` returns of the ground z = 0 around the (level) vehicle, in the LiDAR's
    frame; else random points. ``torn_pose_at``: that odometry (and /tf) message is bytes that do not decode, as a
    recorder killed mid-write leaves. ``poses_from_ns``: no odometry or /tf sample before ``T0 + poses_from_ns`` (the
    localization started late)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    out = BagContents(path)
    rng = np.random.default_rng(7)
    mx, my, mz, myaw = LIDAR_MOUNT
    out.mount_q = quaternion_rpy(*mount_rpy) if mount_rpy is not None else quaternion_rpy(0.0, 0.0, myaw)
    from jitterguard.geometry import rotation_from_quaternion

    mount_r = rotation_from_quaternion(*out.mount_q)
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c_cloud = w.add_connection(CLOUD_TOPIC, POINTCLOUD2, typestore=ts)
        c_odom = w.add_connection(ODOM_TOPIC, "nav_msgs/msg/Odometry", typestore=ts)
        c_det = w.add_connection(DET_TOPIC, DETECTED_OBJECTS, typestore=ts)
        c_cloud2 = w.add_connection("/other/points", POINTCLOUD2, typestore=ts) if second_cloud_topic else None
        if with_tf:
            c_tf = w.add_connection("/tf", TF, typestore=ts)
            c_static = w.add_connection("/tf_static", TF, typestore=ts)
            mount = out.mount_q if mount_rpy is not None else myaw
            w.write(c_static, T0 - 10**9, ts.serialize_cdr(_tf(ts, [(T0, "base_link", "lidar_top", mx, my, mz, mount)]), TF))
        for k in range(2 * n + 1):  # odometry at 20 Hz, starting 50 ms before the first cloud
            t = T0 - 50_000_000 + k * 50_000_000
            x, y, yaw = 1.0 * k, 0.5 * k, 0.05 * k
            out.odom.append((t, x, y, yaw))
            if t < T0 + poses_from_ns:
                continue
            torn = k == torn_pose_at
            w.write(c_odom, t, b"\x00\x01 torn" if torn else ts.serialize_cdr(
                _odom(ts, t, x, y, None if k in headless_odom else yaw), "nav_msgs/msg/Odometry"))
            if with_tf:
                w.write(c_tf, t, b"\x00\x01 torn" if torn else ts.serialize_cdr(
                    _tf(ts, [(t, "map", "base_link", x, y, 0.0, yaw)]), TF))
        for i in range(n):
            t = T0 + i * 100_000_000
            pts = rng.normal(size=(points, 4)).astype(np.float32)
            if ground:  # p_lidar = Rᵀ (p_base_link - t): the ground as the tilted LiDAR sees it
                flat = np.column_stack([rng.uniform(-20.0, 20.0, size=(points, 2)), np.zeros(points)])
                pts[:, :3] = (flat - np.array([mx, my, mz])) @ mount_r
            out.clouds.append(pts)
            out.stamps.append(t)
            raw = b"\x00\x01\x02 not cdr" if i == garbage_at else ts.serialize_cdr(_cloud(ts, t, pts, cloud_frame), POINTCLOUD2)
            if not empty_cloud_topic:
                w.write(c_cloud, t + 1_000_000, raw)  # received 1 ms after the sensor stamp
            positions = [(10.0 + i, 2.0), (-5.0, 3.0 - i)]
            out.det_positions.append(positions)
            label = 42 if i == bad_label_at else 1  # no Autoware class (9, HAZARD, is read as UNKNOWN)
            w.write(c_det, t + 30_000_000, ts.serialize_cdr(_detections(ts, t, positions, label=label), DETECTED_OBJECTS))
            if c_cloud2 is not None:
                w.write(c_cloud2, t, ts.serialize_cdr(_cloud(ts, t, pts), POINTCLOUD2))
    return out
