"""``jitterguard ros2-in``: a live ROS 2 LiDAR topic, as zenoh-bridge-ros2dds carries it into Zenoh (key = the topic
without its leading '/', payload = the message's CDR bytes), posed by /tf and published on ``points``.

A real router and a real ``ros2-in`` process; the ROS 2 side is a Zenoh client of the router putting CDR messages
encoded by mcap-ros2-support — an implementation independent of the rosbags typestore the service decodes with.
The sensor sits on a pitched mount (``/tf_static``, published once before ``ros2-in`` starts, as a bridge that came
first serves a latched topic: from a zenoh-ext advanced publisher's cache, since bridge 1.1; from a publication cache
answering queries, in 1.0 and 0.x) on a vehicle driving and turning (``/tf``). What must hold: every published
scan's points, put into the world by its published pose, are the raw points put into the world by the TF chain; a
scan whose TF comes a little after it is posed by that TF; a payload that is not a PointCloud2 is refused, counted,
and the next scan goes out.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh.ext

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import decode, keys
from jitterguard.schemas.models import Heartbeat, PointCloud
from jitterguard.services.replay.sources.ros_types import typestore

from helpers import stop_process, wait_until
from ros2_side import graph, rmw_attachment, rmw_key

mcap_ros2_dynamic = pytest.importorskip("mcap_ros2._dynamic")
pytestmark = pytest.mark.integration

CLOUD_KEY = "sensing/lidar/top/pointcloud"
MOUNT_XYZ = (0.9, 0.1, 1.8)
MOUNT_PITCH = math.radians(3.0)  # a LiDAR tilted forward on its mount
RAW = np.array([[10.0, 0.0, -1.5, 7.0], [12.0, 3.0, 0.2, 30.0], [-4.0, -6.0, 1.0, 2.0]], dtype="<f4")


def _encoder(msgtype: str):  # type: ignore[no-untyped-def]
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return mcap_ros2_dynamic.serialize_dynamic(msgtype, text)[msgtype]


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _transform(parent: str, child: str, t_ns: int, xyz, q) -> dict:  # type: ignore[no-untyped-def]
    return {"header": {"stamp": _stamp(t_ns), "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": dict(zip("xyz", xyz)), "rotation": dict(zip("xyzw", q))}}


def _vehicle(t_ns: int, t0: int) -> tuple[tuple[float, float, float], tuple[float, float, float, float], float]:
    """map → base_link: driving at 8 m/s while turning at 0.2 rad/s."""
    s = (t_ns - t0) * 1e-9
    yaw = 0.3 + 0.2 * s
    return (100.0 + 8.0 * s, 50.0 + 2.0 * s, 0.0), (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)), yaw


def _cloud(t_ns: int) -> dict:
    return {"header": {"stamp": _stamp(t_ns), "frame_id": "velodyne"}, "height": 1, "width": len(RAW),
            "fields": [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1}
                       for i, n in enumerate(("x", "y", "z", "intensity"))],
            "is_bigendian": False, "point_step": 16, "row_step": 16 * len(RAW), "data": RAW.tobytes(), "is_dense": True}


def _rot(q) -> np.ndarray:  # type: ignore[no-untyped-def]
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _world_truth(t_ns: int, t0: int) -> np.ndarray:
    """The raw points in the world by the TF chain map → base_link → velodyne, computed here from the definitions."""
    xyz, q, _ = _vehicle(t_ns, t0)
    mount_q = (0.0, math.sin(MOUNT_PITCH / 2), 0.0, math.cos(MOUNT_PITCH / 2))
    in_base = RAW[:, :3].astype(float) @ _rot(mount_q).T + np.array(MOUNT_XYZ)
    return in_base @ _rot(q).T + np.array(xyz)


def _world_of(msg: PointCloud) -> np.ndarray:
    pts = np.frombuffer(msg.data, dtype="<f4").reshape(msg.num_points, len(msg.fields))
    p = msg.ego_pose
    r = _rot((p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
    return pts[:, :3].astype(float) @ r.T + np.array([p.position.x, p.position.y, p.position.z])


def _static_tf() -> bytes:
    mount_q = (0.0, math.sin(MOUNT_PITCH / 2), 0.0, math.cos(MOUNT_PITCH / 2))
    return bytes(_encoder("tf2_msgs/msg/TFMessage")(
        {"transforms": [_transform("base_link", "velodyne", 0, MOUNT_XYZ, mount_q)]}))


def _bridge_session(ns: str, endpoint: str):  # type: ignore[no-untyped-def]
    """The ROS 2 side: a Zenoh client of the router, timestamping on as the bridge's advanced publishers need."""
    config = build_config(ZenohOptions(ns=ns, connect=(endpoint,)))
    config.insert_json5("timestamping/enabled", "true")
    return open_session(config)


def _router(endpoint: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "router", "--listen", endpoint],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _start_ros2_in(ns: str, endpoint: str, log) -> subprocess.Popen:  # type: ignore[no-untyped-def]
    return subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "ros2-in", "--ns", ns, "--connect", endpoint,
                             "--points-topic", "/" + CLOUD_KEY, "--pose-topic", "/tf", "--tf-wait-s", "0.5"],
                            stdout=log.open("wb"), stderr=subprocess.STDOUT)


def test_a_live_ros2_lidar_topic_is_posed_by_tf_and_published_on_points(tmp_path):
    ns, endpoint = f"r2i{os.getpid()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    procs = [_router(endpoint)]
    log = tmp_path / "ros2-in.log"
    session = None
    try:
        session = _bridge_session(ns, endpoint)
        tf_enc, cloud_enc = _encoder("tf2_msgs/msg/TFMessage"), _encoder("sensor_msgs/msg/PointCloud2")
        # the latched /tf_static, published once before ros2-in starts, as a bridge since 1.1 keeps it: in an advanced
        # publisher's cache, with publisher detection
        latched = zenoh.ext.declare_advanced_publisher(session, "tf_static", cache=zenoh.ext.CacheConfig(max_samples=1),
                                                       publisher_detection=True)
        latched.put(_static_tf())
        procs.append(_start_ros2_in(ns, endpoint, log))
        got: list[PointCloud] = []
        session.declare_subscriber(keys.points(ns), lambda s: got.append(decode(PointCloud, s.payload.to_bytes())))
        beats: list[Heartbeat] = []
        session.declare_subscriber(keys.heartbeat(ns, "ros2-in"),
                                   lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        assert wait_until(lambda: bool(beats), timeout=60, period=0.2), log.read_text()[-2000:]
        assert wait_until(lambda: beats[-1].counters.get("tf_static", 0) >= 1, timeout=30, period=0.2), \
            log.read_text()[-2000:]

        t0 = 1_700_000_000_000_000_000
        stamps = [t0 + k * 100_000_000 for k in range(1, 6)]
        for k, t in enumerate(stamps):
            tf = bytes(tf_enc({"transforms": [_transform("map", "base_link", t, *_vehicle(t, t0)[:2])]}))
            if k == 2:  # this scan's TF comes after it: the service waits for it
                session.put(CLOUD_KEY, bytes(cloud_enc(_cloud(t))))
                time.sleep(0.05)
                session.put("tf", tf)
            else:
                session.put("tf", tf)
                time.sleep(0.02)
                session.put(CLOUD_KEY, bytes(cloud_enc(_cloud(t))))
            time.sleep(0.15)
        assert wait_until(lambda: len(got) >= len(stamps), timeout=30, period=0.1), log.read_text()[-2000:]
        for msg in got[: len(stamps)]:
            assert msg.header.stamp in stamps
            assert msg.header.frame_id == "velodyne_vehicle_axes"  # turned into base_link's axes at the sensor
            assert msg.fields == ["x", "y", "z", "intensity"]
            np.testing.assert_allclose(_world_of(msg), _world_truth(msg.header.stamp, t0), atol=2e-4)
            pts = np.frombuffer(msg.data, dtype="<f4").reshape(-1, 4)
            np.testing.assert_array_equal(pts[:, 3], RAW[:, 3])
        assert [m.header.seq for m in got[: len(stamps)]] == sorted(m.header.seq for m in got[: len(stamps)])

        # a payload that is not a PointCloud2: refused and counted per key; the next scan still goes out
        session.put(CLOUD_KEY, b"\x00\x01\x00\x00garbage")
        t = stamps[-1] + 100_000_000
        session.put("tf", bytes(tf_enc({"transforms": [_transform("map", "base_link", t, *_vehicle(t, t0)[:2])]})))
        time.sleep(0.05)
        session.put(CLOUD_KEY, bytes(cloud_enc(_cloud(t))))
        assert wait_until(lambda: any(m.header.stamp == t for m in got), timeout=30, period=0.1), log.read_text()[-2000:]
        assert wait_until(lambda: beats[-1].counters.get(f"rejected.{CLOUD_KEY}", 0) == 1, timeout=30, period=0.2), \
            beats[-1].counters
        assert procs[1].poll() is None
    finally:
        if session is not None:
            session.close()
        for p in reversed(procs):
            stop_process(p)


@pytest.mark.parametrize("cache_key", ["@/0123abcd/@ros2_pub_cache/tf_static",  # zenoh-bridge-ros2dds 1.0
                                       "@ros2_pub_cache/0123abcd/tf_static"])   # 0.x
def test_the_latched_tf_static_of_an_older_bridge_is_fetched_from_its_publication_cache(tmp_path, cache_key):
    """Bridges before 1.1 keep a latched topic's history in a publication cache that answers queries only; each
    names it differently, and ros2-in asks both until the mount has come."""
    ns, endpoint = f"r2q{os.getpid()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    procs, log, session = [_router(endpoint)], tmp_path / "ros2-in.log", None
    try:
        session = _bridge_session(ns, endpoint)
        static = _static_tf()
        asked: list[str] = []

        def answer(query) -> None:  # type: ignore[no-untyped-def]
            asked.append(str(query.selector))
            query.reply(cache_key, static)
        session.declare_queryable(cache_key, answer)
        beats: list[Heartbeat] = []
        session.declare_subscriber(keys.heartbeat(ns, "ros2-in"),
                                   lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        procs.append(_start_ros2_in(ns, endpoint, log))
        assert wait_until(lambda: bool(beats) and beats[-1].counters.get("tf_static", 0) >= 1, timeout=60,
                          period=0.2), log.read_text()[-2000:]
        assert asked, "the mount came some other way than the cache's queryable"
        assert not beats[-1].counters.get("rejected.tf_static")
    finally:
        if session is not None:
            session.close()
        for p in reversed(procs):
            stop_process(p)


def test_ros2_nodes_on_rmw_zenoh_feed_ros2_in_through_their_own_router(tmp_path):
    """ROS 2 nodes on rmw_zenoh publish on their router (rmw_zenohd; a second router here): keys with the domain, the
    type and its hash, each sample with rmw_zenoh's attachment, the latched mount in an advanced publisher's cache
    put before ros2-in starts. ros2-in reads them on a client session of that router (``--ros-connect``) and
    publishes posed scans on jitterguard's router, where no ROS 2 key appears."""
    ns, domain = f"r2z{os.getpid()}", 3
    jg_endpoint, ros_endpoint = f"tcp/127.0.0.1:{free_tcp_port()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    procs, log, sessions = [_router(jg_endpoint), _router(ros_endpoint)], tmp_path / "ros2-in.log", []
    try:
        ros = _bridge_session(ns, ros_endpoint)
        sessions.append(ros)
        tf_enc, cloud_enc = _encoder("tf2_msgs/msg/TFMessage"), _encoder("sensor_msgs/msg/PointCloud2")
        seq = iter(range(1, 1000))

        def attachment() -> bytes:  # what rmw_zenoh's publishers attach (its subscriptions drop a sample without)
            return rmw_attachment(next(seq))
        latched = zenoh.ext.declare_advanced_publisher(
            ros, rmw_key("tf_static", "tf2_msgs/msg/TFMessage", domain),
            cache=zenoh.ext.CacheConfig(max_samples=1), publisher_detection=True)
        latched.put(_static_tf(), attachment=attachment())
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "jitterguard.cli", "ros2-in", "--ns", ns, "--connect", jg_endpoint,
             "--middleware", "rmw_zenoh", "--domain-id", str(domain), "--ros-connect", ros_endpoint,
             "--points-topic", "/" + CLOUD_KEY, "--tf-wait-s", "0.5"], stdout=log.open("wb"), stderr=subprocess.STDOUT))
        jg = open_session(build_config(ZenohOptions(ns=ns, connect=(jg_endpoint,))))
        sessions.append(jg)
        got: list[PointCloud] = []
        jg.declare_subscriber(keys.points(ns), lambda s: got.append(decode(PointCloud, s.payload.to_bytes())))
        leaked: list[str] = []
        jg.declare_subscriber(f"{domain}/**", lambda s: leaked.append(str(s.key_expr)))
        beats: list[Heartbeat] = []
        jg.declare_subscriber(keys.heartbeat(ns, "ros2-in"),
                              lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        assert wait_until(lambda: bool(beats) and beats[-1].counters.get("tf_static", 0) >= 1, timeout=60,
                          period=0.2), log.read_text()[-2000:]

        t0 = 1_700_000_000_000_000_000
        stamps = [t0 + k * 100_000_000 for k in range(1, 4)]
        tf_key = rmw_key("tf", "tf2_msgs/msg/TFMessage", domain)
        cloud_key = rmw_key(CLOUD_KEY, "sensor_msgs/msg/PointCloud2", domain)
        for t in stamps:
            ros.put(tf_key, bytes(tf_enc({"transforms": [_transform("map", "base_link", t, *_vehicle(t, t0)[:2])]})),
                    attachment=attachment())
            time.sleep(0.02)
            ros.put(cloud_key, bytes(cloud_enc(_cloud(t))), attachment=attachment())
            time.sleep(0.15)
        assert wait_until(lambda: len(got) >= len(stamps), timeout=30, period=0.1), log.read_text()[-2000:]
        for msg in got[: len(stamps)]:
            np.testing.assert_allclose(_world_of(msg), _world_truth(msg.header.stamp, t0), atol=2e-4)
        assert leaked == [], leaked[:3]
        # in the ROS graph: its node subscribing the scans (sensor-data QoS), /tf_static (latched) and /tf
        entities = graph(ros, domain)
        assert [e["node"] for e in entities] == ["ros2_in"] * 4, entities
        assert {e["namespace"] for e in entities} == {f"/jitterguard/{ns}"}
        subs = {e["topic"]: (e["type"], e["type_hash"], e["qos"]) for e in entities if e["entity"] == "subscription"}
        hashes = {t: typestore().hash_rihs01(t) for t in ("sensor_msgs/msg/PointCloud2", "tf2_msgs/msg/TFMessage")}
        assert subs == {
            "/" + CLOUD_KEY: ("sensor_msgs::msg::dds_::PointCloud2_", hashes["sensor_msgs/msg/PointCloud2"],
                              {"reliability": 2, "durability": 2, "history": 1, "depth": 5}),
            "/tf_static": ("tf2_msgs::msg::dds_::TFMessage_", hashes["tf2_msgs/msg/TFMessage"],
                           {"reliability": 1, "durability": 1, "history": 1, "depth": 100}),
            "/tf": ("tf2_msgs::msg::dds_::TFMessage_", hashes["tf2_msgs/msg/TFMessage"],
                    {"reliability": 1, "durability": 2, "history": 1, "depth": 100})}, entities
        assert procs[-1].poll() is None
    finally:
        for s in sessions:
            s.close()
        for p in reversed(procs):
            stop_process(p)


def test_refused_payloads_on_rmw_zenoh_are_counted_per_subscription_not_per_key_put():
    """Under rmw_zenoh ros2-in subscribes the topic under any type and hash (``<domain>/<topic>/*/*``): a payload that
    does not decode is counted under that subscription. Counted under each key it came on, 40 made-up type chunks
    had made 40 counters (unbounded; a heartbeat beyond 512 entries is refused by every reader, so the service would
    have vanished from the stack's view)."""
    from jitterguard.runtime import loopback_options
    from jitterguard.services.ros2live.in_service import Ros2InService
    from jitterguard.services.ros2live.ros_keys import RosNaming

    ns, port, domain = f"r2k{os.getpid()}", free_tcp_port(), 3
    service = Ros2InService(loopback_options(ns, port, listen_self=True), topic="/" + CLOUD_KEY, pose_topic=None,
                            pose_type=None, naming=RosNaming("rmw_zenoh", domain_id=domain))
    client = open_session(build_config(loopback_options(ns, port)))
    try:
        time.sleep(0.5)
        for i in range(40):
            client.put(f"{domain}/{CLOUD_KEY}/made::msg::dds_::T{i}_/RIHS01_{i:064x}", b"\x00\x01\x00\x00garbage")
            time.sleep(0.01)
        sub = f"{domain}/{CLOUD_KEY}/*/*"
        assert wait_until(lambda: service.counters.get("rejected") + service.counters.get(f"dropped_queue.{sub}")
                          == 40, timeout=30, period=0.1), service.counters.snapshot()
        per_key = {k: v for k, v in service.counters.snapshot().items() if k.startswith("rejected.")}
        assert per_key == {f"rejected.{sub}": service.counters.get("rejected")} and per_key[f"rejected.{sub}"] > 0
    finally:
        client.close()
        service.close()


def _objects(t_ns: int, existence: float) -> dict:
    """One car as Autoware's detector reports it, in base_link; ``existence`` beyond [0, 1] breaks the contract."""
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    car = {"existence_probability": existence, "classification": [{"label": 1, "probability": 0.9}],
           "kinematics": {"pose_with_covariance": {"pose": {"position": {"x": 12.0, "y": 2.0, "z": 0.8},
                                                            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                                                   "covariance": [0.0] * 36},
                          "has_position_covariance": False, "orientation_availability": 1,
                          "twist_with_covariance": {"twist": {"linear": zero, "angular": zero},
                                                    "covariance": [0.0] * 36},
                          "has_twist": False, "has_twist_covariance": False},
           "shape": {"type": 0, "footprint": {"points": []}, "dimensions": {"x": 4.5, "y": 1.9, "z": 1.6}}}
    return {"header": {"stamp": _stamp(t_ns), "frame_id": "base_link"}, "objects": [car]}


@pytest.mark.parametrize("msgtype", ["sensor_msgs/msg/PointCloud2", "autoware_perception_msgs/msg/DetectedObjects"])
def test_a_message_that_fails_validation_is_counted_invalid_not_unposed_and_the_service_goes_on(msgtype):
    """A message that decodes but breaks the contract (a cloud without z; a box whose existence probability is 5) is
    the sender's fault, not the poses': it is counted ``invalid`` in the heartbeat (it had been counted ``unposed``,
    which sends an operator looking at TF), and it is dealt with, not a failure of progress — a run of them left the
    service ``failing`` and its watchdog restarted it, which no restart can mend. The next valid message goes out."""
    from jitterguard.runtime import loopback_options
    from jitterguard.services.ros2live.in_service import Ros2InService

    ns, port = f"r2v{os.getpid()}{msgtype[0]}", free_tcp_port()
    topic = "/" + CLOUD_KEY if msgtype.startswith("sensor") else "/perception/object_recognition/detection/objects"
    service = Ros2InService(loopback_options(ns, port, listen_self=True), topic=topic, pose_topic=None, pose_type=None,
                            msgtype=msgtype)
    client = open_session(build_config(loopback_options(ns, port)))
    enc = _encoder(msgtype)
    out_key = keys.points(ns) if msgtype.startswith("sensor") else keys.detections(ns)
    got: list[bytes] = []
    beats: list[Heartbeat] = []
    try:
        client.declare_subscriber(out_key, lambda s: got.append(s.payload.to_bytes()))
        client.declare_subscriber(keys.heartbeat(ns, "ros2-in"),
                                  lambda s: beats.append(decode(Heartbeat, s.payload.to_bytes())))
        time.sleep(0.5)
        t0 = 1_700_000_000_000_000_000
        for k in range(6):  # more than the five in a row that make a service failing
            if msgtype.startswith("sensor"):
                bad = {**_cloud(t0 + k), "fields": [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1}
                                                    for i, n in enumerate(("x", "y"))]}
            else:
                bad = _objects(t0 + k, 5.0)
            client.put(topic[1:], bytes(enc(bad)))
            time.sleep(0.05)
        assert wait_until(lambda: service.counters.get("invalid") == 6, timeout=30, period=0.05), \
            service.counters.snapshot()
        assert service.counters.get("unposed") == 0 and not got
        assert service.health().ok, service.health()
        good = _cloud(t0 + 10) if msgtype.startswith("sensor") else _objects(t0 + 10, 0.7)
        client.put(topic[1:], bytes(enc(good)))
        assert wait_until(lambda: len(got) == 1, timeout=30, period=0.05), service.counters.snapshot()
        assert wait_until(lambda: bool(beats) and beats[-1].counters.get("invalid") == 6
                          and beats[-1].counters.get("published") == 1, timeout=30, period=0.1)
        assert beats[-1].health == "ok"
    finally:
        client.close()
        service.close()
