"""ROS 2 bag source on bags written here by rosbags (sqlite3 and MCAP): clouds, poses, Autoware detections."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags", reason="bag tests need rosbags")

from jitterguard.services.replay.frames import DetectionFrame, EgoPose, FrameError, ScanFrame, SourceError  # noqa: E402

from jitterguard.services.replay.sources import SourceOptions, open_source  # noqa: E402

from .bagfixture import CLOUD_TOPIC, DET_TOPIC, LIDAR_MOUNT, ODOM_TOPIC, write_bag  # noqa: E402


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bag_pointclouds_round_trip_with_header_stamps(tmp_path: Path, storage: str) -> None:
    bag = write_bag(tmp_path / "bag", storage=storage)
    src = open_source(str(bag.path))
    assert src.info.kind == "points" and src.info.num_frames == 4
    frames = list(src.frames())
    assert all(isinstance(f, ScanFrame) for f in frames)
    assert [f.stamp_ns for f in frames] == bag.stamps  # header stamp, not the receive time
    for f, want in zip(frames, bag.clouds):
        assert f.fields == ("x", "y", "z", "intensity") and f.frame_id == "lidar_top"
        np.testing.assert_array_equal(f.points, want)
        assert f.pose == EgoPose()
    src.close()


def test_bare_mcap_file_opens(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", storage="mcap")
    [mcap] = list(bag.path.glob("*.mcap"))
    src = open_source(str(mcap))
    assert len(list(src.frames())) == 4
    src.close()


def test_bag_pose_topic_interpolates_odometry_to_each_scan(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag")
    src = open_source(str(bag.path), SourceOptions(pose_topic=ODOM_TOPIC))
    frames = list(src.frames())
    # odometry k is at T0 - 50 ms + k * 50 ms with x = k, so the scan at T0 + i*100 ms sits at k = 2i + 1
    for i, f in enumerate(frames):
        k = 2 * i + 1
        assert (f.pose.x, f.pose.y) == pytest.approx((1.0 * k, 0.5 * k))
        assert f.pose.yaw == pytest.approx(0.05 * k)
    src.close()


def test_bag_pose_messages_without_a_heading_are_skipped_and_said(tmp_path: Path) -> None:
    """An odometry message whose quaternion is all zeros (no heading) has no orientation to interpolate: it is
    skipped and counted, the scans take the poses around it; a topic with no usable pose is a one-line error
    (it aborted the replay with a division by zero and a validation traceback)."""
    bag = write_bag(tmp_path / "bag", headless_odom=(3,))
    src = open_source(str(bag.path), SourceOptions(pose_topic=ODOM_TOPIC))
    frames = list(src.frames())
    assert len(frames) == 4 and any("1 skipped" in n for n in src.info.notes)
    assert (frames[1].pose.x, frames[1].pose.y) == pytest.approx((3.0, 1.5))  # between odometry 2 and 4
    assert frames[1].pose.yaw == pytest.approx(0.15)
    src.close()
    none = write_bag(tmp_path / "none", headless_odom=tuple(range(9)))
    with pytest.raises(SourceError, match="no message with a usable pose"):
        open_source(str(none.path), SourceOptions(pose_topic=ODOM_TOPIC))


def test_bag_detected_objects_topic_gives_detection_frames(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag")
    src = open_source(str(bag.path), SourceOptions(topic=DET_TOPIC))
    assert src.info.kind == "detections"
    frames = list(src.frames(start=1))
    assert len(frames) == 3 and all(isinstance(f, DetectionFrame) for f in frames)
    f = frames[0]
    assert f.frame_id == "base_link" and f.stamp_ns == bag.stamps[1]
    got = [(o.kinematics.pose_with_covariance.pose.position.x, o.kinematics.pose_with_covariance.pose.position.y) for o in f.objects]
    assert got == pytest.approx(bag.det_positions[1])
    o = f.objects[0]
    assert o.classification[0].label == 1 and o.classification[0].probability == pytest.approx(0.9)
    assert o.kinematics.has_position_covariance and o.kinematics.pose_with_covariance.covariance[7] == pytest.approx(0.09)
    assert (o.shape.dimensions.x, o.shape.dimensions.y) == pytest.approx((4.5, 1.8))
    src.close()


def test_bag_garbage_message_is_a_frame_error_naming_bag_topic_and_index(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", garbage_at=2)
    src = open_source(str(bag.path))
    items = list(src.frames())
    assert [type(i).__name__ for i in items] == ["ScanFrame", "ScanFrame", "FrameError", "ScanFrame"]
    err = items[2]
    assert isinstance(err, FrameError) and err.origin == f"{bag.path}:{CLOUD_TOPIC}#2"
    src.close()


def test_bag_detection_that_fails_validation_is_a_frame_error(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", bad_label_at=1)
    src = open_source(str(bag.path), SourceOptions(topic=DET_TOPIC))
    items = list(src.frames())
    assert isinstance(items[1], FrameError) and "label" in items[1].reason
    assert isinstance(items[0], DetectionFrame) and isinstance(items[2], DetectionFrame)
    src.close()


@pytest.mark.parametrize(
    "opts,match",
    [
        (SourceOptions(topic="/nope"), "no topic '/nope'"),
        (SourceOptions(topic=ODOM_TOPIC), "not sensor_msgs/msg/PointCloud2"),
        (SourceOptions(pose_topic=CLOUD_TOPIC), "pose topic"),
        (SourceOptions(poses=Path("x")), "--poses does not apply"),
    ],
)
def test_bag_bad_topic_choices_are_one_line_source_errors(tmp_path: Path, opts: SourceOptions, match: str) -> None:
    bag = write_bag(tmp_path / "bag", n=1)
    with pytest.raises(SourceError, match=match):
        open_source(str(bag.path), opts)


def test_an_empty_cloud_topic_is_passed_over_for_the_detections(tmp_path: Path) -> None:
    """`up --input detections --record-ros2` writes a bag whose PointCloud2 topic holds nothing: replaying it by
    default had said `--start 0 is past the end`, calibrating it `no track stood still`."""
    bag = write_bag(tmp_path / "bag", n=3, empty_cloud_topic=True)
    with open_source(str(bag.path)) as src:
        assert src.topic == DET_TOPIC and len([i for i in src.frames() if not isinstance(i, FrameError)]) == 3


def test_several_cloud_topics_need_topic(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", n=1, second_cloud_topic=True)
    with pytest.raises(SourceError, match="several .* pick one with --topic"):
        open_source(str(bag.path))
    src = open_source(str(bag.path), SourceOptions(topic="/other/points"))
    assert len(list(src.frames())) == 1
    src.close()


def test_a_file_that_is_not_a_bag_is_a_source_error(tmp_path: Path) -> None:
    (tmp_path / "x.mcap").write_bytes(b"definitely not mcap")
    with pytest.raises(SourceError, match="x.mcap"):
        open_source(str(tmp_path / "x.mcap"))


def _expected_lidar(k: float) -> tuple[float, float, float, float]:
    """World pose of lidar_top when base_link is at odometry sample k (x = k, y = k/2, yaw = 0.05 k)."""
    import math

    bx, by, byaw = 1.0 * k, 0.5 * k, 0.05 * k
    mx, my, mz, myaw = LIDAR_MOUNT
    c, s = math.cos(byaw), math.sin(byaw)
    return bx + c * mx - s * my, by + s * mx + c * my, mz, byaw + myaw


@pytest.mark.parametrize("pose_topic", ["/tf", ODOM_TOPIC])
def test_bag_sensor_pose_composes_tf_static_mount_with_the_vehicle_pose(tmp_path: Path, pose_topic: str) -> None:
    bag = write_bag(tmp_path / "bag", with_tf=True)
    src = open_source(str(bag.path), SourceOptions(pose_topic=pose_topic))
    frames = list(src.frames())
    assert len(frames) == 4
    for i, f in enumerate(frames):
        x, y, z, yaw = _expected_lidar(2 * i + 1)
        assert (f.pose.x, f.pose.y, f.pose.z) == pytest.approx((x, y, z), abs=1e-9)
        assert f.pose.yaw == pytest.approx(yaw)
    src.close()


def test_bag_detections_in_base_link_get_the_vehicle_pose_from_tf(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", with_tf=True, n=1)
    src = open_source(str(bag.path), SourceOptions(pose_topic="/tf", topic=DET_TOPIC))
    [f] = list(src.frames())
    assert isinstance(f, DetectionFrame)
    # the detections are stamped T0, the time of odometry/TF sample 1 (x = 1, y = 0.5)
    assert (f.pose.x, f.pose.y, f.pose.z) == pytest.approx((1.0, 0.5, 0.0))
    src.close()


def test_bag_cloud_frame_missing_from_tf_is_a_frame_error_per_scan(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", with_tf=True, n=2, cloud_frame="velodyne")
    src = open_source(str(bag.path), SourceOptions(pose_topic="/tf"))
    items = list(src.frames())
    assert len(items) == 2 and all(isinstance(i, FrameError) and "velodyne" in i.reason for i in items)
    src.close()
