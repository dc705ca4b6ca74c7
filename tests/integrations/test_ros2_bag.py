"""The ROS 2 bag of a real run (``RecorderService`` = ``jitterguard record --ros2``), decoded by a second
implementation (``mcap-ros2-support``, reading the definitions the bag embeds) and compared field by field with what
the pipeline published; then ``jitterguard replay`` of that bag feeds a real tracker."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml
import zenoh

pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from jitterguard.runtime import build_config, free_tcp_port, loopback_options  # noqa: E402
from jitterguard.schemas import keys  # noqa: E402
from jitterguard.schemas.models import DetectedObjects, TrackedObjects  # noqa: E402
from jitterguard.services.recorder.rosbag import DETECTIONS_TOPIC, POINTS_TOPIC, TF_TOPIC, TRACKING_TOPIC  # noqa: E402

from helpers import collector  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def _decoded(bag) -> dict[str, list]:
    (mcap_file,) = bag.glob("*.mcap")
    out: dict[str, list] = {}
    with open(mcap_file, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
            assert schema.encoding == "ros2msg"
            out.setdefault(channel.topic, []).append((message.log_time, schema.name, msg))
    return out


@pytest.fixture(scope="module")
def bag_messages(pipeline_run):
    return _decoded(pipeline_run.bag)


def _yaw(q) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def _back_to_frame_axes(linear, cov, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Autoware's object-frame twist on the message frame's axes (rotation by +yaw), written independently."""
    c, s = math.cos(yaw), math.sin(yaw)
    t = np.eye(6)
    t[:2, :2] = ((c, -s), (s, c))
    return t[:2, :2] @ np.array([linear.x, linear.y]), t @ np.asarray(cov).reshape(6, 6) @ t.T


def _f32(x: float) -> float:
    return float(np.float32(x))


def test_the_bag_has_metadata_and_autowares_topics_and_types(pipeline_run, bag_messages) -> None:
    meta = yaml.safe_load((pipeline_run.bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == "mcap"
    types = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"] for t in meta["topics_with_message_count"]}
    assert types == {TRACKING_TOPIC: "autoware_perception_msgs/msg/TrackedObjects",
                     DETECTIONS_TOPIC: "autoware_perception_msgs/msg/DetectedObjects",
                     POINTS_TOPIC: "sensor_msgs/msg/PointCloud2", TF_TOPIC: "tf2_msgs/msg/TFMessage"}
    frames = pipeline_run.recorder_counters["frames"]
    assert frames >= 8
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == dict.fromkeys(types, frames)
    assert {t: len(v) for t, v in bag_messages.items()} == counts


def test_tracked_objects_are_field_by_field_what_the_classifier_put_on_objects(pipeline_run, bag_messages) -> None:
    n_static = n_moving = 0
    for log_time, schema, msg in bag_messages[TRACKING_TOPIC]:
        assert schema == "autoware_perception_msgs/msg/TrackedObjects"
        ref: TrackedObjects = pipeline_run.objects[log_time]
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert stamp == ref.header.stamp == log_time and msg.header.frame_id == ref.header.frame_id == "map"
        assert len(msg.objects) == len(ref.objects)
        for got, want in zip(msg.objects, ref.objects):
            assert bytes(got.object_id.uuid).hex() == want.object_id
            assert got.existence_probability == _f32(want.existence_probability)
            assert [(c.label, c.probability) for c in got.classification] == [
                (c.label, _f32(c.probability)) for c in want.classification]
            gk, wk = got.kinematics, want.kinematics
            gp, wp = gk.pose_with_covariance.pose, wk.pose_with_covariance.pose
            assert (gp.position.x, gp.position.y, gp.position.z) == (wp.position.x, wp.position.y, wp.position.z)
            assert (gp.orientation.x, gp.orientation.y, gp.orientation.z, gp.orientation.w) == (
                wp.orientation.x, wp.orientation.y, wp.orientation.z, wp.orientation.w)
            assert list(gk.pose_with_covariance.covariance) == list(wk.pose_with_covariance.covariance)
            assert gk.is_stationary == wk.is_stationary
            assert gk.orientation_availability == wk.orientation_availability
            v, cov = _back_to_frame_axes(gk.twist_with_covariance.twist.linear, gk.twist_with_covariance.covariance,
                                         _yaw(wp.orientation))
            wv = wk.twist_with_covariance.twist.linear
            assert v == pytest.approx([wv.x, wv.y], abs=1e-9)
            assert cov.reshape(-1) == pytest.approx(list(wk.twist_with_covariance.covariance), abs=1e-9)
            ga, wa = gk.twist_with_covariance.twist.angular, wk.twist_with_covariance.twist.angular
            assert (ga.x, ga.y, ga.z) == (wa.x, wa.y, wa.z)
            assert list(gk.acceleration_with_covariance.covariance) == list(wk.acceleration_with_covariance.covariance)
            assert got.shape.type == want.shape.type
            d = got.shape.dimensions
            assert (d.x, d.y, d.z) == (want.shape.dimensions.x, want.shape.dimensions.y, want.shape.dimensions.z)
            if wk.is_stationary:  # what Autoware's prediction gets for a parked car: no velocity at all
                n_static += 1
                lin = gk.twist_with_covariance.twist.linear
                assert (lin.x, lin.y, lin.z) == (0.0, 0.0, 0.0)
            elif math.hypot(wv.x, wv.y) > 0.5:
                n_moving += 1
                # Autoware's convention: a vehicle moving along its heading has its speed on linear.x
                lin = gk.twist_with_covariance.twist.linear
                assert math.hypot(lin.x, lin.y) == pytest.approx(math.hypot(wv.x, wv.y), rel=1e-9)
    assert n_static > 10 and n_moving > 0


def test_detections_points_and_tf_match_what_was_published(pipeline_run, bag_messages) -> None:
    for log_time, _, msg in bag_messages[DETECTIONS_TOPIC]:
        ref: DetectedObjects = pipeline_run.detections[log_time]
        assert msg.header.frame_id == ref.header.frame_id == "lidar"
        assert len(msg.objects) == len(ref.objects)
        for got, want in zip(msg.objects, ref.objects):
            gp = got.kinematics.pose_with_covariance
            assert gp.pose.position.x == want.kinematics.pose_with_covariance.pose.position.x
            assert list(gp.covariance) == list(want.kinematics.pose_with_covariance.covariance)  # the variances
            assert got.kinematics.has_position_covariance == want.kinematics.has_position_covariance is True
    for log_time, _, msg in bag_messages[POINTS_TOPIC]:
        ref = pipeline_run.points[log_time]
        # Autoware's PointXYZIRC (float32 x, y, z; uint8 intensity, return_type; uint16 channel: the ring)
        assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
            ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 2, 1), ("return_type", 13, 2, 1),
            ("channel", 14, 4, 1)]
        assert msg.width == ref.num_points and msg.point_step == 16 and len(msg.data) == 16 * ref.num_points
        got = np.frombuffer(bytes(msg.data), dtype=[("xyz", "<f4", 3), ("i", "u1"), ("r", "u1"), ("c", "<u2")])
        want = np.frombuffer(ref.data, dtype="<f4").reshape(ref.num_points, len(ref.fields))
        assert ref.fields == ["x", "y", "z", "intensity", "ring"]
        np.testing.assert_array_equal(got["xyz"], want[:, :3])
        assert (got["i"] == want[:, 3]).all() and (got["c"] == want[:, 4]).all() and not got["r"].any()
    for log_time, _, msg in bag_messages[TF_TOPIC]:
        a, b = msg.transforms
        assert (a.header.frame_id, a.child_frame_id, b.header.frame_id, b.child_frame_id) == (
            "map", "base_link", "base_link", "lidar")
        ego = pipeline_run.points[log_time].ego_pose
        assert (a.transform.translation.x, a.transform.translation.y) == pytest.approx(
            (ego.position.x, ego.position.y), abs=1e-12)
        assert b.transform.translation.z == pytest.approx(ego.position.z, abs=1e-12)


def test_jitterguard_replay_of_the_bag_feeds_the_tracker(pipeline_run) -> None:
    from jitterguard.services.tracker.service import TrackerService

    ns, port = "fox_bag_replay", free_tcp_port()
    tracker = TrackerService(loopback_options(ns, port, listen_self=True))
    client = zenoh.open(build_config(loopback_options(ns, port)))
    got: dict[str, list] = {"tracked": [], "detections": []}
    lock = threading.Lock()

    subs = [client.declare_subscriber(keys.tracked(ns), collector(got, lock, "tracked", TrackedObjects)),
            client.declare_subscriber(keys.detections(ns), collector(got, lock, "detections", DetectedObjects))]
    try:
        time.sleep(0.5)
        res = subprocess.run(
            [sys.executable, "-m", "jitterguard.cli", "replay", str(pipeline_run.bag), "--topic", DETECTIONS_TOPIC,
             "--pose-topic", TF_TOPIC, "--rate", "max", "--ns", ns, "--connect", f"tcp/127.0.0.1:{port}",
             "--no-progress"], capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        frames = pipeline_run.recorder_counters["frames"]
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(got["tracked"]) < frames:
            time.sleep(0.05)
    finally:
        for s in subs:
            s.undeclare()
        client.close()
        tracker.close()
    assert len(got["detections"]) == frames and len(got["tracked"]) == frames
    assert max(len(t.objects) for t in got["tracked"]) > 10  # the tracker confirmed tracks from the bag's detections
    # the replayed detections are the recorded ones: pose from /tf, objects round-tripped through Autoware's layout
    recorded = sorted(pipeline_run.detections.items())
    replayed = {d.header.stamp: d for d in got["detections"]}
    for stamp, ref in recorded:
        if stamp not in replayed:
            continue
        d = replayed[stamp]
        assert d.ego_pose.position.x == pytest.approx(ref.ego_pose.position.x, abs=1e-9)
        for a, b in zip(d.objects, ref.objects):
            pa, pb = a.kinematics.pose_with_covariance, b.kinematics.pose_with_covariance
            assert pa.pose.position.x == pb.pose.position.x and list(pa.covariance) == list(pb.covariance)
            ta, tb = a.kinematics.twist_with_covariance.twist.linear, b.kinematics.twist_with_covariance.twist.linear
            assert (ta.x, ta.y) == pytest.approx((tb.x, tb.y), abs=1e-9)
