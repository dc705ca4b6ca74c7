"""``jitterguard ros2-out``: the classifier's ``objects`` on a live ROS 2 topic's Zenoh key as Autoware's
``TrackedObjects`` — decoded here by mcap-ros2-support, an implementation independent of the rosbags typestore the
service encodes with, and compared field by field with what went in (real router, real ``ros2-out`` process)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import xxhash

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import decode, encode, keys
from jitterguard.schemas.models import (Header, Heartbeat, ObjectClassification, Pose, PoseWithCovariance, Quaternion,
                                        TrackedObject, TrackedObjectKinematics, TrackedObjects, Twist,
                                        TwistWithCovariance, Vector3, Point)
from jitterguard.services.replay.sources.ros_types import typestore

from helpers import stop_process, wait_until
from ros2_side import graph

mcap_ros2_dynamic = pytest.importorskip("mcap_ros2._dynamic")
pytestmark = pytest.mark.integration

TOPIC = "/perception/object_recognition/tracking/objects"
TOPIC_KEY = TOPIC.lstrip("/")


def _object(track_id: str, x: float, y: float, yaw: float, vx: float, vy: float, static: bool, label: int) -> TrackedObject:
    pose = Pose(position=Point(x=x, y=y, z=0.8), orientation=Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2)))
    return TrackedObject(object_id=track_id, existence_probability=0.9,
                         classification=[ObjectClassification(label=label, probability=0.8)],
                         kinematics=TrackedObjectKinematics(
                             pose_with_covariance=PoseWithCovariance(pose=pose),
                             twist_with_covariance=TwistWithCovariance(twist=Twist(linear=Vector3(x=vx, y=vy))),
                             is_stationary=static))


def test_objects_go_out_as_autowares_tracked_objects_on_the_ros2_topic_key():
    ns, endpoint = f"r2o{os.getpid()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    procs = [subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", endpoint],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL),
             subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "ros2-out", "--ns", ns, "--connect", endpoint],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    text, _ = typestore().generate_msgdef("autoware_perception_msgs/msg/TrackedObjects", ros_version=2)
    decode_ros = mcap_ros2_dynamic.generate_dynamic("autoware_perception_msgs/msg/TrackedObjects", text)[
        "autoware_perception_msgs/msg/TrackedObjects"]
    session = None
    try:
        session = open_session(build_config(ZenohOptions(ns=ns, connect=(endpoint,))))
        got: list = []
        session.declare_subscriber(TOPIC_KEY, lambda s: got.append(decode_ros(s.payload.to_bytes())))
        beats: list[Heartbeat] = []
        session.declare_subscriber(keys.heartbeat(ns, "ros2-out"),
                                   lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        assert wait_until(lambda: bool(beats), timeout=60, period=0.2)
        moving = _object("0123456789abcdef0123456789abcdef", 10.0, 5.0, math.pi / 2, 0.0, 4.0, False, 1)
        parked = _object("fedcba9876543210fedcba9876543210", -3.0, 2.0, 0.4, 0.0, 0.0, True, 7)
        sent = TrackedObjects(header=Header(stamp=1_700_000_000_123_000_000, frame_id="map", seq=7),
                              objects=[moving, parked])
        session.put(keys.objects(ns), b"\x93not an objects message")  # refused, counted; the next one goes out
        session.put(keys.objects(ns), encode(sent))
        assert wait_until(lambda: bool(got), timeout=30, period=0.1), beats[-1].counters if beats else None
        msg = got[0]
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 123_000_000, "map")
        assert len(msg.objects) == 2
        out_moving, out_parked = msg.objects
        assert bytes(out_moving.object_id.uuid) == bytes.fromhex(moving.object_id)
        assert out_moving.kinematics.is_stationary is False and out_parked.kinematics.is_stationary is True
        assert out_moving.classification[0].label == 1 and out_parked.classification[0].label == 7
        assert out_moving.classification[0].probability == pytest.approx(0.8, abs=1e-6)
        p = out_moving.kinematics.pose_with_covariance.pose.position
        assert (p.x, p.y, p.z) == (10.0, 5.0, 0.8)
        # Autoware states the twist in the object's frame: 4 m/s along +y of the world is +x of an object heading +y
        lin = out_moving.kinematics.twist_with_covariance.twist.linear
        np.testing.assert_allclose([lin.x, lin.y], [4.0, 0.0], atol=1e-9)
        assert out_parked.kinematics.twist_with_covariance.twist.linear.x == 0.0
        assert wait_until(lambda: beats[-1].counters.get("rejected.objects", 0) == 1
                          and beats[-1].counters.get("published", 0) == 1, timeout=30, period=0.2), beats[-1].counters
        assert procs[1].poll() is None
    finally:
        if session is not None:
            session.close()
        for p in reversed(procs):
            stop_process(p)


def test_objects_reach_ros2_nodes_on_rmw_zenoh_on_the_typed_key_with_their_attachment():
    """rmw_zenoh's subscriptions listen on the exact key — domain, topic, type, the type's REP 2011 hash — and drop
    a sample without the attachment its publishers send; ros2-out puts both, on a client session of the ROS 2 system's
    own router (``--ros-connect``; a second router here plays rmw_zenohd). The attachment is read back with
    zenoh-ext's deserializer: sequence numbers 1, 2, the time of publication, one GID."""
    zext = pytest.importorskip("zenoh.ext")
    ns, domain = f"r2z{os.getpid()}", 5
    jg_endpoint, ros_endpoint = f"tcp/127.0.0.1:{free_tcp_port()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", ep], **quiet)
             for ep in (jg_endpoint, ros_endpoint)]
    procs.append(subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "ros2-out", "--ns", ns, "--connect",
                                   jg_endpoint, "--middleware", "rmw_zenoh", "--domain-id", str(domain),
                                   "--ros-distro", "jazzy", "--ros-connect", ros_endpoint], **quiet))
    msgtype = "autoware_perception_msgs/msg/TrackedObjects"
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    decode_ros = mcap_ros2_dynamic.generate_dynamic(msgtype, text)[msgtype]
    key = (f"{domain}/{TOPIC_KEY}/autoware_perception_msgs::msg::dds_::TrackedObjects_/"
           f"{typestore().hash_rihs01(msgtype)}")
    sessions = []
    try:
        ros = open_session(build_config(ZenohOptions(ns=ns, connect=(ros_endpoint,))))
        jg = open_session(build_config(ZenohOptions(ns=ns, connect=(jg_endpoint,))))
        sessions += [ros, jg]
        got: list = []
        ros.declare_subscriber(key, lambda s: got.append((decode_ros(s.payload.to_bytes()), s.attachment)))
        beats: list[Heartbeat] = []
        jg.declare_subscriber(keys.heartbeat(ns, "ros2-out"),
                              lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        assert wait_until(lambda: bool(beats), timeout=60, period=0.2)
        parked = _object("fedcba9876543210fedcba9876543210", -3.0, 2.0, 0.4, 0.0, 0.0, True, 7)
        before = time.time_ns()
        for seq in (1, 2):
            jg.put(keys.objects(ns), encode(TrackedObjects(header=Header(stamp=1_700_000_000_000_000_000 + seq,
                                                                         frame_id="map", seq=seq), objects=[parked])))
            assert wait_until(lambda: len(got) >= seq, timeout=30, period=0.05), beats[-1].counters
        after = time.time_ns()
        attached = [zext.z_deserialize(tuple[zext.Int64, zext.Int64, bytes], a) for _, a in got]
        assert [int(n) for n, _, _ in attached] == [1, 2]
        assert all(before <= int(t) <= after for _, t, _ in attached)
        assert attached[0][2] == attached[1][2] and len(attached[0][2]) == 16
        assert [m.header.stamp.nanosec for m, _ in got] == [1, 2]
        assert got[1][0].objects[0].kinematics.is_stationary is True
        # in the ROS graph: its node, and its publisher of the topic with the type, the hash and Autoware's QoS
        entities = {e["entity"]: e for e in graph(ros, domain)}
        assert set(entities) == {"node", "publisher"}, entities
        node, pub = entities["node"], entities["publisher"]
        assert (node["namespace"], node["node"], node["enclave"]) == (f"/jitterguard/{ns}", "ros2_out", "/")
        assert (pub["namespace"], pub["node"], pub["nid"], pub["zid"]) == (node["namespace"], "ros2_out", node["nid"],
                                                                          node["zid"])
        assert (pub["topic"], pub["type"], pub["type_hash"]) == (
            TOPIC, "autoware_perception_msgs::msg::dds_::TrackedObjects_", typestore().hash_rihs01(msgtype))
        assert pub["qos"] == {"reliability": 1, "durability": 2, "history": 1, "depth": 1}
        # its GID, as rmw_zenoh derives one: XXH3-128 of the token, low 64 bits first
        assert attached[0][2] == xxhash.xxh3_128_intdigest(pub["token"].encode()).to_bytes(16, "little")
        assert procs[-1].poll() is None
        stop_process(procs.pop())  # gone from the graph when it stops
        assert wait_until(lambda: not graph(ros, domain), timeout=20, period=0.2)
    finally:
        for s in sessions:
            s.close()
        for p in reversed(procs):
            stop_process(p)
