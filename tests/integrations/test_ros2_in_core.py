"""The live ROS 2 input's pure core: keys as zenoh-bridge-ros2dds names them, topic names checked, an odometry topic
posing scans with the static mount, and a scan not yet covered by the poses said so (CDR from mcap-ros2-support)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import xxhash

from jitterguard.services.replay.frames import DetectionFrame, FrameError, ScanFrame
from jitterguard.services.replay.sources.ros_types import typestore
from jitterguard.services.ros2live.ros_keys import (RosEndpoint, RosNaming, RosQos, check_key_prefix, check_topic, dds_type_name,
                                                   entity_gid, rmw_attachment, ros_key, ros_node)
from jitterguard.services.ros2live.scans_in import LiveScans, UndecodableMessage

mcap_ros2_dynamic = pytest.importorskip("mcap_ros2._dynamic")


def _enc(msgtype: str, msg: dict) -> bytes:
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return bytes(mcap_ros2_dynamic.serialize_dynamic(msgtype, text)[msgtype](msg))


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _odom(t: int, x: float) -> bytes:
    pose = {"position": {"x": x, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
    twist = {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
    return _enc("nav_msgs/msg/Odometry", {"header": {"stamp": _stamp(t), "frame_id": "map"}, "child_frame_id": "base_link",
                                          "pose": {"pose": pose, "covariance": [0.0] * 36},
                                          "twist": {"twist": twist, "covariance": [0.0] * 36}})


def _link(parent: str, child: str, t: int, x: float) -> bytes:
    """A TF message of one transform ``parent`` -> ``child`` at ``t`` (ns): ``x`` m along x, no rotation."""
    return _enc("tf2_msgs/msg/TFMessage", {"transforms": [
        {"header": {"stamp": _stamp(t), "frame_id": parent}, "child_frame_id": child,
         "transform": {"translation": {"x": x, "y": 0.0, "z": 0.0},
                       "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]})


def _cloud(t: int, frame: str = "lidar") -> bytes:
    pts = np.array([[1.0, 2.0, 3.0]], dtype="<f4")
    return _enc("sensor_msgs/msg/PointCloud2", {
        "header": {"stamp": _stamp(t), "frame_id": frame}, "height": 1, "width": 1,
        "fields": [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate("xyz")],
        "is_bigendian": False, "point_step": 12, "row_step": 12, "data": pts.tobytes(), "is_dense": True})


def test_keys_and_topic_names():
    assert ros_key("", "/sensing/lidar/top/pointcloud") == "sensing/lidar/top/pointcloud"
    assert ros_key("/robot1/", "/tf") == "robot1/tf"
    assert check_topic("--points-topic", " /points ") == "/points"
    assert check_topic("--points-topic", "/sensing/lidar/top/pointcloud_raw_ex") == "/sensing/lidar/top/pointcloud_raw_ex"
    # an empty token, a trailing '/' and a token that starts with a digit break rcl's rules; '/a//b' had passed and
    # failed later as a Zenoh key, in a traceback (and ros2-in --pose-topic /a//b had hung after it)
    for bad in ("points", "/", "/a/*", "/a b", "/@ros2_lv", "/a//b", "/a/", "/9lidar", "/a-b"):
        with pytest.raises(ValueError, match="--points-topic"):
            check_topic("--points-topic", bad)
    assert check_key_prefix("--key-prefix", "/robot1/") == "robot1" and check_key_prefix("--key-prefix", "") == ""
    assert check_key_prefix("--key-prefix", "fleet/car-2.a") == "fleet/car-2.a"
    for bad in ("a//b", "a/*", "**", "a/$*b", "a b"):  # an empty chunk, wildcards: they had been published on
        with pytest.raises(ValueError, match="--key-prefix"):
            check_key_prefix("--key-prefix", bad)


def test_rmw_zenoh_keys_and_attachments_are_the_middlewares_own():
    """The key of a topic as rmw_zenoh names it, with the type hash rosbags computes (REP 2011) — for PointCloud2 the
    hash ROS 2 Jazzy's nodes announce — and the attachment its subscriptions require, as zenoh-ext serialises the
    same three values (an implementation independent of the struct layout the service writes)."""
    zext = pytest.importorskip("zenoh.ext")
    store = typestore()
    naming = RosNaming("rmw_zenoh", domain_id=7)
    assert dds_type_name("sensor_msgs/msg/PointCloud2") == "sensor_msgs::msg::dds_::PointCloud2_"
    assert naming.publication("/sensing/lidar/top/pointcloud", "sensor_msgs/msg/PointCloud2",
                              store.hash_rihs01("sensor_msgs/msg/PointCloud2")) == (
        "7/sensing/lidar/top/pointcloud/sensor_msgs::msg::dds_::PointCloud2_/"
        "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5")
    assert naming.subscription("/tf_static") == "7/tf_static/*/*"
    assert naming.attaches and not RosNaming().attaches
    assert RosNaming(prefix="/robot1/").publication("/tf", "x/msg/Y", "h") == "robot1/tf"  # the bridge: no type
    humble = RosNaming("rmw_zenoh", type_hashes=False)  # Humble's rmw_zenoh: no type hashes
    assert humble.publication("/tf", "tf2_msgs/msg/TFMessage", "RIHS01_x") == (
        "0/tf/tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported")
    gid = bytes(range(16))
    expected = zext.z_serialize((zext.Int64(3), zext.Int64(1_700_000_000_123_456_789), gid)).to_bytes()
    assert rmw_attachment(3, 1_700_000_000_123_456_789, gid) == expected and len(expected) == 33
    with pytest.raises(ValueError, match="domain ID 233"):
        RosNaming("rmw_zenoh", domain_id=233)
    with pytest.raises(ValueError, match="16 bytes"):
        rmw_attachment(1, 0, b"short")


def test_rmw_zenoh_graph_tokens_are_laid_out_as_its_graph_cache_reads_them():
    """The liveliness tokens that put a node and its endpoints in rmw_zenoh's ROS graph, spelt out: node id 0, entity
    ids from 1, the default enclave and the namespace with ``%`` for ``/``, the QoS with rmw_zenoh's defaults left
    empty (depth 42, reliable, volatile); every token passes the test helper's reading of rmw_zenoh's parser."""
    from ros2_side import read_graph_token

    assert RosQos().chunk() == "::,:,:,:,,"
    assert RosQos(depth=1).chunk() == "::,1:,:,:,,"
    assert RosQos(reliable=False, depth=5).chunk() == "2::,5:,:,:,,"
    assert RosQos(transient_local=True, depth=100).chunk() == ":1:,100:,:,:,,"
    assert ros_node("ros2-out", "bay-2") == ("/jitterguard/bay_2", "ros2_out")
    endpoints = [RosEndpoint("MP", "/perception/objects", "autoware_perception_msgs/msg/TrackedObjects", "RIHS01_ab",
                             RosQos(depth=1)),
                 RosEndpoint("MS", "/tf_static", "tf2_msgs/msg/TFMessage", "RIHS01_cd", RosQos(transient_local=True))]
    tokens = RosNaming("rmw_zenoh", domain_id=4).graph_tokens("a1b2", "ros2_out", "/jitterguard/default", endpoints)
    assert tokens == [
        "@ros2_lv/4/a1b2/0/0/NN/%/%jitterguard%default/ros2_out",
        "@ros2_lv/4/a1b2/0/1/MP/%/%jitterguard%default/ros2_out/%perception%objects/"
        "autoware_perception_msgs::msg::dds_::TrackedObjects_/RIHS01_ab/::,1:,:,:,,",
        "@ros2_lv/4/a1b2/0/2/MS/%/%jitterguard%default/ros2_out/%tf_static/tf2_msgs::msg::dds_::TFMessage_/"
        "RIHS01_cd/:1:,:,:,:,,"]
    read = [read_graph_token(t) for t in tokens]
    assert [r["entity"] for r in read] == ["node", "publisher", "subscription"]
    assert read[2]["qos"] == {"reliability": 1, "durability": 1, "history": 1, "depth": 42}
    humble = RosNaming("rmw_zenoh", type_hashes=False).graph_tokens("a1b2", "n", "/", endpoints[:1])
    assert humble[0] == "@ros2_lv/0/a1b2/0/0/NN/%/%/n" and "/TypeHashNotSupported/" in humble[1]
    assert RosNaming("bridge").graph_tokens("a1b2", "n", "/", endpoints) == []  # a bridge announces DDS endpoints
    # the GID: XXH3-128 of the token, its low 64 bits first, little-endian (xxhash's canonical digest is big-endian)
    assert entity_gid(tokens[1]) == xxhash.xxh3_128_digest(tokens[1].encode())[::-1]
    assert entity_gid(tokens[1]) != entity_gid(tokens[2])


def test_an_odometry_topic_poses_scans_with_the_static_mount_and_says_when_it_lags():
    core = LiveScans("nav_msgs/msg/Odometry")
    mount = {"header": {"stamp": _stamp(0), "frame_id": "base_link"}, "child_frame_id": "lidar",
             "transform": {"translation": {"x": 1.0, "y": 0.0, "z": 2.0},
                           "rotation": {"x": 0.0, "y": 0.0, "z": math.sin(math.pi / 4), "w": math.cos(math.pi / 4)}}}
    core.tf(_enc("tf2_msgs/msg/TFMessage", {"transforms": [mount]}), 0, static=True)
    t0 = 5_000_000_000
    core.pose(_odom(t0, 10.0), 0)
    core.pose(_odom(t0 + 200_000_000, 12.0), 0)
    assert core.covered(t0 + 100_000_000) and not core.covered(t0 + 300_000_000)
    msg, stamp = core.stamp_of(_cloud(t0 + 100_000_000))
    frame = core.scan(msg, "test#1", 0)
    assert isinstance(frame, ScanFrame) and stamp == t0 + 100_000_000
    # the lidar's x points along base_link's y (yawed 90° on its mount): turned into base_link's axes at the sensor
    assert frame.frame_id == "lidar_vehicle_axes"
    np.testing.assert_allclose(frame.points[0, :3], [-2.0, 1.0, 3.0], atol=1e-6)
    # the vehicle half-way between its two odometry samples (x 11), the sensor 1 m ahead and 2 m up
    assert (frame.pose.x, frame.pose.y, frame.pose.z) == pytest.approx((12.0, 0.0, 2.0))
    assert any("mount tilt 0.0°, yaw 90.0°" in n for n in core.notes()) and core.notes() == []


def test_payloads_of_another_type_are_refused_and_a_frame_without_tf_is_an_error():
    core = LiveScans("tf2_msgs/msg/TFMessage")
    with pytest.raises(UndecodableMessage, match="not a CDR sensor_msgs/msg/PointCloud2"):
        core.stamp_of(b"\x00\x01\x00\x00\xff")
    msg, _ = core.stamp_of(_cloud(1))
    out = core.scan(msg, "test#2", 0)
    assert isinstance(out, FrameError) and "no TF for the scan" in out.reason
    with pytest.raises(ValueError, match="cannot pose a scan"):
        LiveScans("sensor_msgs/msg/Imu")


def _detected_objects(t: int, frame: str, x: float, yaw: float, labels: tuple[int, ...] = (1,)) -> bytes:
    """One car as Autoware's detector reports it: in the vehicle's frame, no position covariance (lidar_centerpoint
    leaves it out), moving along its own heading (Autoware's twist is in the object's frame)."""
    pose = {"position": {"x": x, "y": 2.0, "z": 0.8},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}}
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    car = {"existence_probability": 0.7, "classification": [{"label": 1, "probability": 0.9}],
           "kinematics": {"pose_with_covariance": {"pose": pose, "covariance": [0.0] * 36},
                          "has_position_covariance": False, "orientation_availability": 1,
                          "twist_with_covariance": {"twist": {"linear": {"x": 5.0, "y": 0.0, "z": 0.0},
                                                              "angular": zero}, "covariance": [0.0] * 36},
                          "has_twist": True, "has_twist_covariance": False},
           "shape": {"type": 0, "footprint": {"points": []}, "dimensions": {"x": 4.5, "y": 1.9, "z": 1.6}}}
    return _enc("autoware_perception_msgs/msg/DetectedObjects",
                {"header": {"stamp": _stamp(t), "frame_id": frame},
                 "objects": [{**car, "classification": [{"label": lab, "probability": 0.9}]} for lab in labels]})


def test_the_vehicles_own_detected_objects_are_posed_as_a_bag_of_them_would_be():
    """A DetectedObjects topic (the vehicle's own detector) in place of scans: each message a posed frame of its boxes,
    left in their frame (the tracker moves them into the world by the pose), the twist turned onto the frame's axes;
    a scan's payload on that topic is refused."""
    core = LiveScans("tf2_msgs/msg/TFMessage", "autoware_perception_msgs/msg/DetectedObjects")
    t0 = 5_000_000_000
    pose = {"header": {"stamp": _stamp(t0), "frame_id": "map"}, "child_frame_id": "base_link",
            "transform": {"translation": {"x": 100.0, "y": 50.0, "z": 0.0},
                          "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
    core.tf(_enc("tf2_msgs/msg/TFMessage", {"transforms": [pose]}), 0, static=False)
    assert core.covered(t0) and not core.covered(t0 + 1)
    msg, stamp = core.stamp_of(_detected_objects(t0, "base_link", 12.0, math.pi / 2))
    frame = core.scan(msg, "objects#1", 0)
    assert isinstance(frame, DetectionFrame) and stamp == t0 and frame.frame_id == "base_link"
    assert (frame.pose.x, frame.pose.y, frame.pose.z) == pytest.approx((100.0, 50.0, 0.0))
    (car,) = frame.objects
    assert car.kinematics.pose_with_covariance.pose.position.x == pytest.approx(12.0)
    assert car.kinematics.has_position_covariance is False
    lin = car.kinematics.twist_with_covariance.twist.linear  # heading +y: 5 m/s along the frame's y
    assert (lin.x, lin.y) == pytest.approx((0.0, 5.0), abs=1e-9)
    with pytest.raises(UndecodableMessage, match="not a CDR autoware_perception_msgs/msg/DetectedObjects"):
        core.stamp_of(_cloud(t0))
    unposed = core.scan(core.stamp_of(_detected_objects(t0, "radar", 1.0, 0.0))[0], "objects#2", 0)
    assert isinstance(unposed, FrameError) and "no TF for the scan" in unposed.reason
    with pytest.raises(ValueError, match="carries sensor_msgs/msg/PointCloud2 or"):
        LiveScans(None, "sensor_msgs/msg/Imu")


def test_current_autowares_newer_classes_are_read_as_unknown_not_refused():
    """Current autoware_msgs has ANIMAL, HAZARD, OVER_DRIVABLE and UNDER_DRIVABLE (8-11) past the contract's
    PEDESTRIAN: such a box is taken as UNKNOWN (said once), and the frame's other boxes go on; one of them had the whole
    frame refused as invalid. A label that is no Autoware class still refuses it."""
    core = LiveScans(None, "autoware_perception_msgs/msg/DetectedObjects")
    msg, _ = core.stamp_of(_detected_objects(5_000_000_000, "base_link", 12.0, 0.0, labels=(1, 8, 9, 10, 11, 7)))
    frame = core.scan(msg, "objects#1", 0)
    assert isinstance(frame, DetectionFrame)
    assert [o.classification[0].label for o in frame.objects] == [1, 0, 0, 0, 0, 7]
    assert core.notes() == ["classes ANIMAL, HAZARD, OVER_DRIVABLE, UNDER_DRIVABLE (newer autoware_msgs labels) "
                            "read as UNKNOWN"]
    assert isinstance(core.scan(msg, "objects#2", 0), DetectionFrame) and core.notes() == []  # said once
    bad, _ = core.stamp_of(_detected_objects(5_000_000_000, "base_link", 12.0, 0.0, labels=(1, 12)))
    refused = core.scan(bad, "objects#3", 0)
    assert isinstance(refused, FrameError) and "classification.0.label" in refused.reason


def test_a_cloud_in_the_odometrys_own_frame_is_posed_by_it_without_a_note():
    """Autoware's concatenated cloud is in base_link, the odometry's child frame: its pose is the odometry's, and no
    note claims that the vehicle pose stands in for a sensor's (it had, with no /tf_static on the bus)."""
    core = LiveScans("nav_msgs/msg/Odometry")
    core.pose(_odom(1_000_000_000, 5.0), 0)
    frame = core.scan(core.stamp_of(_cloud(1_000_000_000, "base_link"))[0], "scan#1", 0)
    assert isinstance(frame, ScanFrame) and frame.frame_id == "base_link" and frame.pose.x == 5.0
    assert core.notes() == []
    core.scan(core.stamp_of(_cloud(1_000_000_000, "lidar"))[0], "scan#2", 0)  # a sensor frame without its mount: said
    assert [n for n in core.notes() if "stands in for the sensor's" in n]


def test_a_scan_is_covered_only_once_the_tf_links_above_its_own_frame_reach_its_stamp():
    """A /tf carrying other, faster links (a wheel's joint; NDT's map -> ndt_base_link stamped at its scan) says nothing
    of the vehicle's pose: a scan waits until map -> base_link itself has a sample at or after its stamp. The newest of
    any transform had counted, and such a scan was posed at once, clamped to the older vehicle pose."""
    core = LiveScans("tf2_msgs/msg/TFMessage")
    mount = {"header": {"stamp": _stamp(0), "frame_id": "base_link"}, "child_frame_id": "lidar",
             "transform": {"translation": {"x": 1.0, "y": 0.0, "z": 2.0},
                           "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
    core.tf(_enc("tf2_msgs/msg/TFMessage", {"transforms": [mount]}), 0, static=True)

    t0 = 5_000_000_000
    core.tf(_link("map", "base_link", t0, 100.0), 0, static=False)
    core.tf(_link("base_link", "wheel", t0 + 50_000_000, 0.0), 0, static=False)  # newer, but another link
    core.tf(_link("map", "ndt_base_link", t0 + 60_000_000, 0.0), 0, static=False)
    scan_t = t0 + 30_000_000
    assert core.covered(t0, "lidar") and not core.covered(scan_t, "lidar") and not core.covered(scan_t, "/lidar")
    assert not core.covered(scan_t, "radar")  # a frame not in the tree (yet)
    core.tf(_link("map", "base_link", t0 + 40_000_000, 104.0), 0, static=False)
    assert core.covered(scan_t, "lidar")
    frame = core.scan(core.stamp_of(_cloud(scan_t))[0], "scan#1", 0)
    # base_link 100 -> 104 over 40 ms, at 30 ms 103; the LiDAR 1 m ahead of it
    assert isinstance(frame, ScanFrame) and frame.pose.x == pytest.approx(104.0)


def test_a_scan_is_refused_while_nothing_puts_the_vehicle_in_the_world():
    """Before localization publishes map -> base_link (a live stack waiting for its initial pose), the TF tree's root is
    the vehicle's own frame: such a scan is refused as one that cannot be posed. It had gone out with its mount in
    base_link for its world pose, the vehicle standing at the world's origin until localization started."""
    core = LiveScans("tf2_msgs/msg/TFMessage")
    mount = {"header": {"stamp": _stamp(0), "frame_id": "base_link"}, "child_frame_id": "lidar",
             "transform": {"translation": {"x": 1.0, "y": 0.0, "z": 2.0},
                           "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
    core.tf(_enc("tf2_msgs/msg/TFMessage", {"transforms": [mount]}), 0, static=True)
    t = 5_000_000_000
    for frame_id in ("lidar", "base_link"):
        out = core.scan(core.stamp_of(_cloud(t, frame_id))[0], "scan#1", 0)
        assert isinstance(out, FrameError) and "nothing puts the vehicle in the world" in out.reason
    pose = {"header": {"stamp": _stamp(t), "frame_id": "map"}, "child_frame_id": "base_link",
            "transform": {"translation": {"x": 100.0, "y": 50.0, "z": 0.0},
                          "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}
    core.tf(_enc("tf2_msgs/msg/TFMessage", {"transforms": [pose]}), 0, static=False)
    frame = core.scan(core.stamp_of(_cloud(t))[0], "scan#2", 0)
    assert isinstance(frame, ScanFrame) and (frame.pose.x, frame.pose.z) == pytest.approx((101.0, 2.0))


def test_a_live_scan_whose_sensor_kit_is_not_linked_to_base_link_is_refused_naming_the_link():
    """The live twin of the bag's check: localization has map -> base_link, the sensor kit's mount is on /tf_static,
    but the link base_link -> sensor_kit_base_link is not (a vehicle description not loaded). The scan had gone out
    posed at its mount near the world's origin; it is refused, one line naming the missing link, until it comes."""
    core = LiveScans("tf2_msgs/msg/TFMessage")

    t = 5_000_000_000
    core.tf(_link("sensor_kit_base_link", "lidar", 0, 0.5), 0, static=True)
    core.tf(_link("map", "base_link", t, 100.0), 0, static=False)
    out = core.scan(core.stamp_of(_cloud(t))[0], "scan#1", 0)
    assert isinstance(out, FrameError) and not out.invalid and "\n" not in out.reason
    assert "the link from 'base_link' (or a frame under it) to 'sensor_kit_base_link' is missing" in out.reason
    core.tf(_link("base_link", "sensor_kit_base_link", 0, 1.0), 0, static=True)
    frame = core.scan(core.stamp_of(_cloud(t))[0], "scan#2", 0)
    assert isinstance(frame, ScanFrame) and frame.pose.x == pytest.approx(101.5)
