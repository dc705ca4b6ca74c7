"""ros2-in and ros2-out against an independent implementation of rmw_zenoh's protocol: zenoh-ros2-sdk (ROBOTIS' pure
Python ROS 2 over Zenoh, "publishers and subscribers appear in ros2 topic list and work with ROS 2 nodes using
rmw_zenoh"). It builds its own keys and attachments, computes REP 2011 type hashes with its own code from the message
definitions, declares and reads rmw_zenoh's graph tokens its own way — none of it shared with jitterguard's
``ros_keys``. A second router plays ``rmw_zenohd``; the SDK is a peer of it, multicast scouting off."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import (DetectedObjects, Header, Heartbeat, ObjectClassification, Point, PointCloud,
                                        Pose, PoseWithCovariance, TrackedObject, TrackedObjectKinematics,
                                        TrackedObjects, Twist, TwistWithCovariance, Vector3)

from helpers import stop_process, wait_until
from ros2_side import sdk_messages

sdk = pytest.importorskip("zenoh_ros2_sdk")

OBJECTS_TOPIC = "/perception/object_recognition/tracking/objects"
TRACKED_OBJECTS = "autoware_perception_msgs/msg/TrackedObjects"
POINTS_TOPIC = "/sensing/lidar/top/pointcloud"
RAW = np.array([[10.0, 0.0, -1.5, 7.0], [12.0, 3.0, 0.2, 30.0], [-4.0, -6.0, 1.0, 2.0]], dtype="<f4")
MOUNT = (0.9, 0.1, 1.8)


@pytest.fixture()
def ros_side(tmp_path, monkeypatch):
    """Two routers (jitterguard's, the ROS system's) and the SDK set to read its message definitions from a folder and
    to reach the ROS router; its singletons (session, message registry) are reset before and after."""
    from zenoh_ros2_sdk import message_registry, session

    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", "scouting/multicast/enabled=false")
    monkeypatch.setattr(message_registry, "_registry", None)
    monkeypatch.setattr(session.ZenohSession, "_instance", None)
    sdk.get_registry(str(sdk_messages(tmp_path / "msg", (TRACKED_OBJECTS, "sensor_msgs/msg/PointCloud2",
                                                          "tf2_msgs/msg/TFMessage"))))
    jg_port, ros_port = free_tcp_port(), free_tcp_port()
    procs = [subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", f"tcp/127.0.0.1:{p}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for p in (jg_port, ros_port)]
    try:
        session.ZenohSession.get_instance(router_port=ros_port)  # the SDK's one session: the first call's port wins
        yield procs, jg_port, ros_port
    finally:
        if session.ZenohSession._instance is not None:
            session.ZenohSession._instance.close()
        for p in reversed(procs):
            stop_process(p)


def _service(name: str, ns: str, jg_port: int, ros_port: int, domain: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", name, "--ns", ns, "--connect",
                             f"tcp/127.0.0.1:{jg_port}", "--middleware", "rmw_zenoh", "--domain-id", str(domain),
                             "--ros-distro", "jazzy", "--ros-connect", f"tcp/127.0.0.1:{ros_port}", *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _listen(jg_port: int, ns: str, key: str, model: type) -> tuple[Any, list, list[Heartbeat]]:
    """A session on jitterguard's router collecting what ``key`` carries (decoded as ``model``), once ros2-in's
    heartbeat says it is up."""
    jg = open_session(build_config(ZenohOptions(ns=ns, connect=(f"tcp/127.0.0.1:{jg_port}",))))
    got: list = []
    jg.declare_subscriber(key, lambda s: got.append(decode(model, s.payload.to_bytes())))
    beats: list[Heartbeat] = []
    jg.declare_subscriber(keys.heartbeat(ns, "ros2-in"), lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
    assert wait_until(lambda: bool(beats), timeout=60, period=0.2)
    return jg, got, beats


class _Msgs:
    """The SDK's message classes (rosbags' dataclasses of the definitions it loaded), by short name, and the pieces
    a ROS 2 node would publish."""

    def __init__(self, *msgtypes: str) -> None:
        common = ("std_msgs/msg/Header", "builtin_interfaces/msg/Time", "geometry_msgs/msg/TransformStamped",
                  "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion")
        self.c = {t.rsplit("/", 1)[1]: sdk.get_message_class(t) for t in (*common, *msgtypes)}

    def header(self, t: int, frame: str) -> Any:
        return self.c["Header"](stamp=self.c["Time"](sec=t // 1_000_000_000, nanosec=t % 1_000_000_000),
                                frame_id=frame)

    def transforms(self, parent: str, child: str, t: int, xyz: tuple[float, float, float]) -> list:
        """One level transform ``parent`` → ``child`` at ``xyz`` (a TFMessage's ``transforms``)."""
        return [self.c["TransformStamped"](
            header=self.header(t, parent), child_frame_id=child, transform=self.c["Transform"](
                translation=self.c["Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                rotation=self.c["Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))]


def _object(track_id: str, x: float, static: bool, label: int) -> TrackedObject:
    return TrackedObject(object_id=track_id, existence_probability=0.9,
                         classification=[ObjectClassification(label=label, probability=0.8)],
                         kinematics=TrackedObjectKinematics(
                             pose_with_covariance=PoseWithCovariance(pose=Pose(position=Point(x=x, y=2.0, z=0.8))),
                             twist_with_covariance=TwistWithCovariance(twist=Twist(linear=Vector3(x=0.0 if static
                                                                                                 else 3.0))),
                             is_stationary=static))


def test_ros2_out_reaches_an_independent_rmw_zenoh_subscriber_and_its_graph(ros_side):
    """The SDK's subscriber, on the key it builds with the type hash it computes, receives ros2-out's TrackedObjects
    (it requires the attachment as rmw_zenoh does), and its ``ros2 topic info -v`` finds ros2-out's node publishing
    the topic with the same type, hash and QoS."""
    procs, jg_port, ros_port = ros_side
    ns, domain = f"sdk{os.getpid()}", 6
    procs.append(_service("ros2-out", ns, jg_port, ros_port, domain))
    got: list = []
    sub = sdk.ROS2Subscriber(OBJECTS_TOPIC, TRACKED_OBJECTS, got.append, domain_id=domain, router_port=ros_port)
    jg = open_session(build_config(ZenohOptions(ns=ns, connect=(f"tcp/127.0.0.1:{jg_port}",))))
    try:
        beats: list[Heartbeat] = []
        jg.declare_subscriber(keys.heartbeat(ns, "ros2-out"),
                              lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        assert wait_until(lambda: bool(beats), timeout=60, period=0.2)
        sent = TrackedObjects(header=Header(stamp=1_700_000_000_250_000_000, frame_id="map", seq=1),
                              objects=[_object("0123456789abcdef0123456789abcdef", 12.0, False, 1),
                                       _object("fedcba9876543210fedcba9876543210", -3.0, True, 7)])

        def delivered() -> bool:  # the SDK's subscription may be routed a moment after ros2-out is up: put again
            jg.put(keys.objects(ns), encode(sent))
            return bool(got)
        assert wait_until(delivered, timeout=30, period=0.5), beats[-1].counters
        msg = got[0]
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 250_000_000,
                                                                                         "map")
        assert [bytes(o.object_id.uuid).hex() for o in msg.objects] == ["0123456789abcdef0123456789abcdef",
                                                                         "fedcba9876543210fedcba9876543210"]
        assert [o.kinematics.is_stationary for o in msg.objects] == [False, True]
        assert [o.classification[0].label for o in msg.objects] == [1, 7]
        assert msg.objects[0].kinematics.twist_with_covariance.twist.linear.x == pytest.approx(3.0)

        info = sdk.get_topic_info(OBJECTS_TOPIC, domain_id=domain, router_port=ros_port, timeout=2.0, verbose=True)
        assert info is not None and info.topic_types == [TRACKED_OBJECTS] and info.publisher_count == 1
        pub = info.publishers[0]
        assert (pub.node_namespace, pub.node_name) == (f"/jitterguard/{ns}", "ros2_out")
        assert pub.type_hash == sub.type_hash  # the SDK's own REP 2011 hash of the same definitions
        assert pub.qos == "::,1:,:,:,,"  # reliable, volatile, keep last 1: Autoware's tracker
        assert procs[-1].poll() is None
    finally:
        jg.close()


def test_ros2_in_takes_scans_from_independent_rmw_zenoh_publishers(ros_side):
    """The SDK publishes a LiDAR's mount on a latched /tf_static, the vehicle's pose on /tf and the scans, as ROS 2
    nodes on rmw_zenoh would; ros2-in puts each scan on ``points``, posed where the TF chain puts its points, and the
    SDK's graph lists ros2-in's node among the scans' subscribers with ROS 2's sensor-data QoS."""
    procs, jg_port, ros_port = ros_side
    ns, domain = f"sdki{os.getpid()}", 8
    procs.append(_service("ros2-in", ns, jg_port, ros_port, domain, "--points-topic", POINTS_TOPIC,
                          "--tf-wait-s", "0.5"))
    jg, got, beats = _listen(jg_port, ns, keys.points(ns), PointCloud)
    try:
        m = _Msgs("sensor_msgs/msg/PointField")
        tf_static = sdk.ROS2Publisher("/tf_static", "tf2_msgs/msg/TFMessage", domain_id=domain, router_port=ros_port,
                                      qos=":1:,1:,:,:,,")  # latched: transient local, keep last 1
        tf = sdk.ROS2Publisher("/tf", "tf2_msgs/msg/TFMessage", domain_id=domain, router_port=ros_port)
        scans = sdk.ROS2Publisher(POINTS_TOPIC, "sensor_msgs/msg/PointCloud2", domain_id=domain, router_port=ros_port,
                                  qos="2::,5:,:,:,,")
        fields = [m.c["PointField"](name=n, offset=4 * i, datatype=7, count=1)
                  for i, n in enumerate(("x", "y", "z", "intensity"))]
        t0 = 1_700_000_000_000_000_000
        stamps = [t0 + k * 100_000_000 for k in range(1, 6)]
        for k, t in enumerate(stamps):
            vehicle = (100.0 + 0.8 * k, 50.0, 0.0)
            tf_static.publish(transforms=m.transforms("base_link", "velodyne", 0, MOUNT))
            tf.publish(transforms=m.transforms("map", "base_link", t, vehicle))
            time.sleep(0.02)
            scans.publish(header=m.header(t, "velodyne"), height=1, width=len(RAW), fields=fields, is_bigendian=False,
                          point_step=16, row_step=16 * len(RAW), data=np.frombuffer(RAW.tobytes(), np.uint8),
                          is_dense=True)
            time.sleep(0.3)
        assert wait_until(lambda: len(got) >= 2, timeout=30, period=0.1), beats[-1].counters if beats else None
        for msg in got:  # every scan that went out is posed by the TF chain (the first may precede the mount)
            k = stamps.index(msg.header.stamp)
            pts = np.frombuffer(msg.data, dtype="<f4").reshape(msg.num_points, len(msg.fields))[:, :3]
            p = msg.ego_pose.position
            world = pts.astype(float) + np.array([p.x, p.y, p.z])  # level mount, no yaw: a translation
            np.testing.assert_allclose(world, RAW[:, :3] + np.array(MOUNT) + np.array([100.0 + 0.8 * k, 50.0, 0.0]),
                                       atol=2e-4)
        info = sdk.get_topic_info(POINTS_TOPIC, domain_id=domain, router_port=ros_port, timeout=2.0, verbose=True)
        assert info is not None and info.topic_types == ["sensor_msgs/msg/PointCloud2"]
        ours = [s for s in info.subscribers if s.node_name == "ros2_in"]
        assert len(ours) == 1 and ours[0].node_namespace == f"/jitterguard/{ns}" and ours[0].qos == "2::,5:,:,:,,"
        assert ours[0].type_hash == scans.type_hash  # the SDK's hash of PointCloud2, computed its own way
        assert procs[-1].poll() is None
    finally:
        jg.close()


def test_ros2_in_tracks_the_vehicles_own_detected_objects_from_an_independent_publisher(ros_side):
    """``ros2-in --objects-topic``: the SDK publishes the vehicle's detector's DetectedObjects (in base_link, no
    position covariance, as Autoware's lidar_centerpoint) and the vehicle's pose on /tf; ros2-in puts them on
    ``detections``, posed, for jitterguard's tracker, and the SDK's graph lists its subscription of that type."""
    procs, jg_port, ros_port = ros_side
    ns, domain = f"sdko{os.getpid()}", 9
    topic = "/perception/object_recognition/detection/objects"
    procs.append(_service("ros2-in", ns, jg_port, ros_port, domain, "--objects-topic", topic, "--tf-wait-s", "0.5"))
    jg, got, beats = _listen(jg_port, ns, keys.detections(ns), DetectedObjects)
    try:
        m = _Msgs("geometry_msgs/msg/Point", "geometry_msgs/msg/Pose", "geometry_msgs/msg/PoseWithCovariance",
                  "geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistWithCovariance", "geometry_msgs/msg/Polygon",
                  "autoware_perception_msgs/msg/DetectedObject",
                  "autoware_perception_msgs/msg/DetectedObjectKinematics",
                  "autoware_perception_msgs/msg/ObjectClassification", "autoware_perception_msgs/msg/Shape")
        c = m.c
        zero = c["Vector3"](x=0.0, y=0.0, z=0.0)
        car = c["DetectedObject"](
            existence_probability=0.7, classification=[c["ObjectClassification"](label=1, probability=0.9)],
            kinematics=c["DetectedObjectKinematics"](
                pose_with_covariance=c["PoseWithCovariance"](
                    pose=c["Pose"](position=c["Point"](x=12.0, y=2.0, z=0.8),
                                   orientation=c["Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
                    covariance=np.zeros(36)),
                has_position_covariance=False, orientation_availability=1,
                twist_with_covariance=c["TwistWithCovariance"](twist=c["Twist"](linear=zero, angular=zero),
                                                               covariance=np.zeros(36)),
                has_twist=False, has_twist_covariance=False),
            shape=c["Shape"](type=0, footprint=c["Polygon"](points=[]), dimensions=c["Vector3"](x=4.5, y=1.9, z=1.6)))
        tf = sdk.ROS2Publisher("/tf", "tf2_msgs/msg/TFMessage", domain_id=domain, router_port=ros_port)
        boxes = sdk.ROS2Publisher(topic, "autoware_perception_msgs/msg/DetectedObjects", domain_id=domain,
                                  router_port=ros_port, qos="::,1:,:,:,,")
        t0 = 1_700_000_000_000_000_000
        stamps = [t0 + k * 100_000_000 for k in range(1, 6)]
        for k, t in enumerate(stamps):
            tf.publish(transforms=m.transforms("map", "base_link", t, (100.0 + 0.8 * k, 50.0, 0.0)))
            time.sleep(0.02)
            boxes.publish(header=m.header(t, "base_link"), objects=[car])
            time.sleep(0.2)
        assert wait_until(lambda: len(got) >= 3, timeout=30, period=0.1), beats[-1].counters if beats else None
        for msg in got:
            k = stamps.index(msg.header.stamp)
            assert msg.header.frame_id == "base_link"
            assert (msg.ego_pose.position.x, msg.ego_pose.position.y) == pytest.approx((100.0 + 0.8 * k, 50.0))
            (obj,) = msg.objects
            assert obj.kinematics.pose_with_covariance.pose.position.x == pytest.approx(12.0)
            assert obj.classification[0].label == 1 and obj.kinematics.has_position_covariance is False
        info = sdk.get_topic_info(topic, domain_id=domain, router_port=ros_port, timeout=2.0, verbose=True)
        assert info is not None and info.topic_types == ["autoware_perception_msgs/msg/DetectedObjects"]
        ours = [s for s in info.subscribers if s.node_name == "ros2_in"]
        assert len(ours) == 1 and ours[0].type_hash == boxes.type_hash and ours[0].qos == "::,1:,:,:,,"
        assert procs[-1].poll() is None
    finally:
        jg.close()
