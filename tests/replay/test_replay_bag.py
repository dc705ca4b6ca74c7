"""ROS 2 bag source on bags written here by rosbags (sqlite3 and MCAP): clouds, poses, Autoware detections."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags", reason="bag tests need rosbags")

from jitterguard.services.replay.frames import DetectionFrame, EgoPose, FrameError, ScanFrame, SourceError  # noqa: E402

from jitterguard.services.replay.frames import compose  # noqa: E402
from jitterguard.services.replay.sources import SourceOptions, open_source  # noqa: E402
from jitterguard.services.replay.sources.nuscenes import FRAME_SUFFIX  # noqa: E402

from .bagfixture import CLOUD_TOPIC, DET_TOPIC, LIDAR_MOUNT, ODOM_TOPIC, T0, write_bag  # noqa: E402


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


@pytest.mark.parametrize("pose_topic", [ODOM_TOPIC, "/tf"])
def test_a_torn_pose_or_tf_message_is_skipped_not_the_whole_bag(tmp_path: Path, pose_topic: str) -> None:
    """One odometry or /tf message that does not decode (a recorder killed mid-write): skipped and counted as a
    non-finite sample is, the scans posed by the samples around it. It had refused the whole bag at open."""
    whole = write_bag(tmp_path / "whole", with_tf=True)
    torn = write_bag(tmp_path / "torn", with_tf=True, torn_pose_at=3)  # between the 2nd and 3rd scans
    opts = SourceOptions(pose_topic=pose_topic)
    with open_source(str(whole.path), opts) as src:
        want = list(src.frames())
    with open_source(str(torn.path), opts) as src:
        warnings = src.info.warnings
        got = list(src.frames())
    assert any(f"1 undecodable message(s) on {pose_topic} skipped" in w for w in warnings), warnings
    assert all(isinstance(f, ScanFrame) for f in got) and len(got) == len(want) == 4
    for g, w in zip(got, want):  # positions are linear in time: interpolating over the gap gives the same
        assert (g.pose.x, g.pose.y, g.pose.z) == pytest.approx((w.pose.x, w.pose.y, w.pose.z), abs=1e-9)


@pytest.mark.parametrize("pose_topic", [ODOM_TOPIC, "/tf"])
def test_scans_long_before_the_first_pose_are_unreadable_not_posed_at_it(tmp_path: Path, pose_topic: str) -> None:
    """Localization began 0.75 s after the LiDAR: the scans more than 0.5 s before its first sample have no pose
    (unreadable frames naming why); they had all gone out at that first pose, a moving vehicle standing still. A
    scan within 0.5 s of it is clamped to it, as before."""
    bag = write_bag(tmp_path / "bag", n=10, with_tf=True, poses_from_ns=750_000_000)
    with open_source(str(bag.path), SourceOptions(pose_topic=pose_topic)) as src:
        items = list(src.frames())
    assert [type(i).__name__ for i in items] == ["FrameError"] * 3 + ["ScanFrame"] * 7
    assert "no pose yet: the scan is 0.75 s before" in items[0].reason, items[0]
    first = next(o for o in bag.odom if o[0] >= T0 + 750_000_000)
    assert items[3].pose.x == pytest.approx(first[1] + LIDAR_MOUNT[0] * math.cos(first[3]), abs=1e-6)


def test_up_reads_past_the_scans_before_localization_began(tmp_path: Path) -> None:
    """`up`'s pre-start check had refused a bag whose localization began more than ~1 s after the LiDAR ("none of
    the first 10 frame(s) reads; … no pose yet"), though the replay skips those scans and goes on: it now reads past
    them. A bag whose pose topic holds no pose is still refused, saying why."""
    from jitterguard.services.replay.sources import probe_source

    late = write_bag(tmp_path / "late", n=25, with_tf=True, poses_from_ns=2_000_000_000)  # 15 scans without a pose
    assert probe_source(str(late.path), SourceOptions(pose_topic=ODOM_TOPIC)).kind
    never = write_bag(tmp_path / "never", n=5, with_tf=True, poses_from_ns=10_000_000_000)
    with pytest.raises(SourceError, match="holds no message with a usable pose"):
        probe_source(str(never.path), SourceOptions(pose_topic=ODOM_TOPIC))


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
        # a bag's stamps are its own: --hz, a scenario's --duration and its --seed had been ignored in silence
        (SourceOptions(rate_hz=5.0), "--hz does not apply to a bag source"),
        (SourceOptions(duration_s=5.0, seed=2), "--duration, --seed do not apply to a bag source"),
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
    """The LiDAR's position is base_link's pose composed with the /tf_static mount; the mount's yaw (0.5 rad) is
    turned into the points, so the scans go out with base_link's heading (in base_link's axes at the sensor)."""
    bag = write_bag(tmp_path / "bag", with_tf=True)
    src = open_source(str(bag.path), SourceOptions(pose_topic=pose_topic))
    frames = list(src.frames())
    assert len(frames) == 4
    for i, f in enumerate(frames):
        x, y, z, yaw = _expected_lidar(2 * i + 1)
        assert (f.pose.x, f.pose.y, f.pose.z) == pytest.approx((x, y, z), abs=1e-9)
        assert f.pose.yaw == pytest.approx(yaw - LIDAR_MOUNT[3])
        assert f.frame_id == "lidar_top" + FRAME_SUFFIX
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


def test_an_empty_topic_chosen_by_name_is_said_to_be_empty(tmp_path: Path) -> None:
    """`--topic` naming a topic that holds no message (the scans of an `up --input detections` recording) said
    `--start 0 is past the end of ... (0 frames)`; it names the topic and the ones that have messages."""
    bag = write_bag(tmp_path / "bag", n=2, empty_cloud_topic=True)
    with pytest.raises(SourceError, match=f"topic {CLOUD_TOPIC} holds no messages .*{DET_TOPIC}"):
        open_source(str(bag.path), SourceOptions(topic=CLOUD_TOPIC))


def test_a_ros1_style_leading_slash_is_not_part_of_the_frame_id(tmp_path: Path) -> None:
    """A ROS 1 driver's "/lidar_top" is the frame "lidar_top": the TF lookup already read it so, but the scan went
    out with the slash, into the bridges' /tf and the recorded bag (ROS 2's tf2 refuses such frame IDs)."""
    bag = write_bag(tmp_path / "bag", with_tf=True, n=2, cloud_frame="/lidar_top")
    with open_source(str(bag.path), SourceOptions(pose_topic="/tf")) as src:
        frames = list(src.frames())
    assert len(frames) == 2 and all(isinstance(f, ScanFrame) for f in frames)
    assert [f.frame_id for f in frames] == ["lidar_top" + FRAME_SUFFIX] * 2  # the mount's yaw turned out (no slash)
    x, y, z, _ = _expected_lidar(1)
    assert (frames[0].pose.x, frames[0].pose.y, frames[0].pose.z) == pytest.approx((x, y, z), abs=1e-9)


def test_a_bag_folder_without_metadata_names_its_file(tmp_path: Path) -> None:
    """A recorder killed with SIGKILL leaves the MCAP without metadata.yaml (docs/integrations.md): replaying the
    folder said only "cannot tell what this folder is"; it names the file, which opens on its own."""
    bag = write_bag(tmp_path / "my bag", storage="mcap", n=2)
    (bag.path / "metadata.yaml").unlink()
    [mcap] = list(bag.path.glob("*.mcap"))
    with pytest.raises(SourceError, match=f"no metadata.yaml, but it holds {mcap.name}: give that file as SOURCE"):
        open_source(str(bag.path))
    with open_source(str(mcap)) as src:
        assert len([f for f in src.frames() if isinstance(f, ScanFrame)]) == 2


def test_an_mcap_cut_short_says_how_to_recover_it(tmp_path: Path) -> None:
    """What a SIGKILLed recorder leaves (no footer, no metadata.yaml) failed with rosbags' bare "File end magic is
    invalid."; the line now says what happened and what rewrites the file whole."""
    bag = write_bag(tmp_path / "bag", storage="mcap", n=3)
    [mcap] = list(bag.path.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
    with pytest.raises(SourceError, match="cut short.*mcap recover"):
        open_source(str(cut))


def test_a_tf_rotation_that_is_no_unit_quaternion_is_skipped_not_composed(tmp_path: Path) -> None:
    """A /tf_static mount with an all-zero rotation (a hand-written static transform) was composed into every scan's
    pose: the scans went out with orientation (0, 0, 0, 0) — an ego pose each consumer refuses — and the replay said
    "0 unreadable". tf2 ignores such a transform; so does the bag source now, and each scan says why it has none."""
    import math

    from rosbags.rosbag2 import StoragePlugin, Writer

    from jitterguard.services.replay.sources.ros_types import POINTCLOUD2, typestore

    from .bagfixture import TF, T0, _cloud, _header, _tf

    ts = typestore()
    g = ts.types
    path = tmp_path / "bag"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c_static = w.add_connection("/tf_static", TF, typestore=ts)
        zero = g["geometry_msgs/msg/Transform"](translation=g["geometry_msgs/msg/Vector3"](x=1.0, y=0.0, z=2.0),
                                                 rotation=g["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0))
        w.write(c_static, T0, ts.serialize_cdr(g[TF](transforms=[g["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, T0, "base_link"), child_frame_id="lidar_top", transform=zero)]), TF))
        c_tf = w.add_connection("/tf", TF, typestore=ts)
        c_cloud = w.add_connection(CLOUD_TOPIC, POINTCLOUD2, typestore=ts)
        for i in range(2):
            t = T0 + i * 100_000_000
            w.write(c_tf, t, ts.serialize_cdr(_tf(ts, [(t, "map", "base_link", float(i), 0.0, 0.0, 0.1)]), TF))
            w.write(c_cloud, t, ts.serialize_cdr(_cloud(ts, t, np.zeros((3, 4), np.float32)), POINTCLOUD2))
    with open_source(str(path), SourceOptions(pose_topic="/tf")) as src:
        items = list(src.frames())
        assert any("not a unit quaternion" in w and "'lidar_top'" in w for w in src.info.warnings), src.info.warnings
    assert len(items) == 2 and all(isinstance(i, FrameError) for i in items), items
    assert all("lidar_top" in i.reason and "not a unit quaternion" in i.reason for i in items)
    for f in items:  # never a pose that is no rotation
        assert not isinstance(f, ScanFrame) or math.isclose(
            math.hypot(f.pose.qx, f.pose.qy, f.pose.qz, f.pose.qw), 1.0, abs_tol=1e-6)


def _world(pose: EgoPose, pts: np.ndarray) -> np.ndarray:
    """pose ∘ point for each row's x, y, z (float64)."""
    m = pose.matrix()
    return pts[:, :3].astype(np.float64) @ m[:3, :3].T + m[:3, 3]


TILT = (np.radians(3.0), np.radians(-2.0), np.radians(90.0))  # roll, pitch, yaw of lidar_top in base_link


@pytest.mark.parametrize("pose_topic", ["/tf", ODOM_TOPIC])
def test_a_tilted_lidar_is_published_level_in_base_link_axes(tmp_path: Path, pose_topic: str) -> None:
    """A LiDAR mounted rolled 3°, pitched −2° and turned 90° under base_link reached the detector tilted: the
    flat ground sloped across the scan. Its points are turned into base_link's axes at the sensor, as the nuScenes
    reader does, with the frame named so, and the pose turned back so every world point stays where it was."""
    bag = write_bag(tmp_path / "bag", with_tf=True, mount_rpy=TILT, ground=True, points=400)
    with open_source(str(bag.path), SourceOptions(pose_topic=pose_topic)) as src:
        frames = list(src.frames())
        notes = src.info.notes
    assert any("turned into base_link's axes at the sensor" in n and "lidar_top" + FRAME_SUFFIX in n
               and "tilt 3.6°" in n for n in notes), notes
    assert len(frames) == 4
    raw_mount = EgoPose(LIDAR_MOUNT[0], LIDAR_MOUNT[1], LIDAR_MOUNT[2], *bag.mount_q)
    for i, (f, raw) in enumerate(zip(frames, bag.clouds)):
        assert isinstance(f, ScanFrame) and f.frame_id == "lidar_top" + FRAME_SUFFIX
        assert f.points.dtype == np.float32 and f.fields == ("x", "y", "z", "intensity")
        # level: the ground is a plane z = −mount height in the published frame
        z = f.points[:, 2].astype(np.float64)
        assert np.ptp(z) < 0.01 and np.mean(z) == pytest.approx(-LIDAR_MOUNT[2], abs=0.01)
        centred = f.points[:, :3].astype(np.float64) - f.points[:, :3].mean(axis=0)
        normal = np.linalg.svd(centred)[2][-1]
        assert np.degrees(np.arccos(abs(normal[2]))) < 0.1
        np.testing.assert_array_equal(f.points[:, 3], raw[:, 3])  # intensity untouched
        # the world points of the raw cloud at the raw sensor pose (base_link ∘ the tilted mount)
        bx, by, byaw = 1.0 * (2 * i + 1), 0.5 * (2 * i + 1), 0.05 * (2 * i + 1)
        raw_pose = compose(EgoPose.from_yaw(bx, by, byaw), raw_mount)
        np.testing.assert_allclose(_world(f.pose, f.points), _world(raw_pose, raw), atol=1e-5)
        # the published pose: the sensor's position, base_link's orientation
        assert (f.pose.x, f.pose.y, f.pose.z) == pytest.approx((raw_pose.x, raw_pose.y, raw_pose.z), abs=1e-9)
        np.testing.assert_allclose(f.pose.matrix()[:3, :3], EgoPose.from_yaw(0, 0, byaw).matrix()[:3, :3],
                                   atol=1e-9)


@pytest.mark.parametrize("pose_topic", ["/tf", ODOM_TOPIC, None])
def test_a_level_x_forward_mount_changes_nothing(tmp_path: Path, pose_topic: str | None) -> None:
    """A translation-only chain base_link -> lidar_top: the scans go out exactly as before (own frame, the same
    bytes, the pose of the cloud's frame) and no note speaks of a turn."""
    bag = write_bag(tmp_path / "bag", with_tf=True, mount_rpy=(0.0, 0.0, 0.0), ground=True)
    with open_source(str(bag.path), SourceOptions(pose_topic=pose_topic)) as src:
        frames = list(src.frames())
        assert not any("turned" in n for n in src.info.notes), src.info.notes
    assert len(frames) == 4
    for i, (f, raw) in enumerate(zip(frames, bag.clouds)):
        assert isinstance(f, ScanFrame) and f.frame_id == "lidar_top"
        assert f.points.dtype == raw.dtype and f.points.tobytes() == raw.tobytes()
        if pose_topic is None:
            assert f.pose == EgoPose()
            continue
        k = 2 * i + 1
        want = compose(EgoPose.from_yaw(1.0 * k, 0.5 * k, 0.05 * k), EgoPose(*LIDAR_MOUNT[:3]))
        assert (f.pose.x, f.pose.y, f.pose.z, f.pose.yaw) == pytest.approx((want.x, want.y, want.z, want.yaw),
                                                                           abs=1e-9)


def test_a_tilted_mount_without_pose_topic_or_in_detections_is_left_as_it_is(tmp_path: Path) -> None:
    """Without --pose-topic there is no vehicle frame to turn into, and DetectedObjects are never turned."""
    bag = write_bag(tmp_path / "bag", with_tf=True, mount_rpy=TILT, ground=True, n=2)
    with open_source(str(bag.path)) as src:
        frames = list(src.frames())
    assert [f.frame_id for f in frames] == ["lidar_top"] * 2
    np.testing.assert_array_equal(frames[0].points, bag.clouds[0])
    with open_source(str(bag.path), SourceOptions(pose_topic="/tf", topic=DET_TOPIC)) as src:
        dets = list(src.frames())
        assert not any("turned" in n for n in src.info.notes)
    assert [f.frame_id for f in dets] == ["base_link"] * 2


def test_a_dynamic_link_under_base_link_leaves_the_clouds_in_their_own_axes(tmp_path: Path) -> None:
    """Only a static chain from base_link is levelled (module doc): a mount published on /tf keeps the cloud in
    its own frame, with the pose of that frame, and a note says why."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from jitterguard.services.replay.sources.ros_types import POINTCLOUD2, typestore

    from .bagfixture import TF, T0, _cloud, _tf, quaternion_rpy

    ts = typestore()
    path = tmp_path / "bag"
    q = quaternion_rpy(*TILT)
    pts = np.random.default_rng(1).normal(size=(20, 4)).astype(np.float32)
    with Writer(path, version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        c_tf = w.add_connection("/tf", TF, typestore=ts)
        c_cloud = w.add_connection(CLOUD_TOPIC, POINTCLOUD2, typestore=ts)
        for i in range(2):
            t = T0 + i * 100_000_000
            w.write(c_tf, t, ts.serialize_cdr(_tf(ts, [(t, "map", "base_link", float(i), 0.0, 0.0, 0.1),
                                                       (t, "base_link", "lidar_top", 1.0, 0.0, 2.0, q)]), TF))
            w.write(c_cloud, t, ts.serialize_cdr(_cloud(ts, t, pts), POINTCLOUD2))
    with open_source(str(path), SourceOptions(pose_topic="/tf")) as src:
        frames = list(src.frames())
        assert any("kept in lidar_top's own axes" in n and "not static" in n for n in src.info.notes), src.info.notes
    assert [f.frame_id for f in frames] == ["lidar_top"] * 2
    np.testing.assert_array_equal(frames[1].points, pts)
    want = compose(EgoPose.from_yaw(1.0, 0.0, 0.1), EgoPose(1.0, 0.0, 2.0, *q))
    np.testing.assert_allclose(frames[1].pose.matrix(), want.matrix(), atol=1e-9)


@pytest.mark.parametrize("pose_topic", [ODOM_TOPIC, "/tf"])
def test_a_pose_sample_with_a_nan_position_is_skipped_and_the_scans_take_the_poses_around_it(
        tmp_path: Path, pose_topic: str) -> None:
    """An odometry (or /tf) sample whose position is NaN (a localiser not yet initialised, a filter that diverged)
    was interpolated into the scans around it: the replay ended there with a validation error. It is skipped and
    counted as tf2 skips a NaN transform; the scan at its stamp takes the poses around it, and nothing is lost."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from jitterguard.services.replay.sources.ros_types import POINTCLOUD2, typestore

    from .bagfixture import TF, T0, _cloud, _odom, _tf

    ts = typestore()
    path = tmp_path / "bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_odom = w.add_connection(ODOM_TOPIC, "nav_msgs/msg/Odometry", typestore=ts)
        c_tf = w.add_connection("/tf", TF, typestore=ts)
        c_cloud = w.add_connection(CLOUD_TOPIC, POINTCLOUD2, typestore=ts)
        for k in range(7):  # 20 Hz from 50 ms before the first scan; sample 3 is the second scan's own stamp
            t, x = T0 - 50_000_000 + k * 50_000_000, float("nan") if k == 3 else float(k)
            w.write(c_odom, t, ts.serialize_cdr(_odom(ts, t, x, 0.0, 0.0), "nav_msgs/msg/Odometry"))
            w.write(c_tf, t, ts.serialize_cdr(_tf(ts, [(t, "map", "lidar_top", x, 0.0, 0.0, 0.0)]), TF))
        for i in range(3):
            t = T0 + i * 100_000_000
            w.write(c_cloud, t, ts.serialize_cdr(_cloud(ts, t, np.ones((3, 4), np.float32)), POINTCLOUD2))
    with open_source(str(path), SourceOptions(pose_topic=pose_topic)) as src:
        said = src.info.notes + src.info.warnings
        frames = list(src.frames())
    assert all(isinstance(f, ScanFrame) for f in frames), frames
    assert [f.pose.x for f in frames] == pytest.approx([1.0, 3.0, 5.0])  # scan 1 between samples 2 and 4
    assert any("1 skipped" in n or "1 to 'lidar_top'" in n for n in said), said


AUTO_DETECTED = "autoware_auto_perception_msgs/msg/DetectedObjects"


def _auto_bag(path: Path, storage: str) -> Path:
    """A bag of Autoware before autoware_msgs 1.0 (2024): DetectedObjects under autoware_auto_perception_msgs, one car,
    its definitions embedded as rosbag2 records them (the same fields as autoware_perception_msgs' DetectedObjects)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg

    from jitterguard.ros2.types import shipped_definitions, typestore

    ts = typestore()
    ts.register({k: v for n, text in shipped_definitions().items()
                 for k, v in get_types_from_msg(text, n.replace("autoware_perception_msgs",
                                                                "autoware_auto_perception_msgs")).items()})
    t = ts.types
    pwc = t["geometry_msgs/msg/PoseWithCovariance"](
        pose=t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=12.0, y=2.0, z=0.8),
                                         orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
        covariance=np.zeros(36))
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    twc = t["geometry_msgs/msg/TwistWithCovariance"](twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                     covariance=np.zeros(36))
    a = "autoware_auto_perception_msgs/msg/"
    car = t[a + "DetectedObject"](
        existence_probability=0.7, classification=[t[a + "ObjectClassification"](label=1, probability=0.9)],
        kinematics=t[a + "DetectedObjectKinematics"](pose_with_covariance=pwc, has_position_covariance=False,
                                                     orientation_availability=1, twist_with_covariance=twc,
                                                     has_twist=False, has_twist_covariance=False),
        shape=t[a + "Shape"](type=0, footprint=t["geometry_msgs/msg/Polygon"](points=[]),
                             dimensions=t["geometry_msgs/msg/Vector3"](x=4.5, y=1.9, z=1.6)))
    w = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    w.open()
    conn = w.add_connection(DET_TOPIC, AUTO_DETECTED, typestore=ts)
    for i in range(2):
        header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=i), frame_id="base_link")
        w.write(conn, 10**9 + i, bytes(ts.serialize_cdr(t[AUTO_DETECTED](header=header, objects=[car]), AUTO_DETECTED)))
    w.close()
    return path


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_of_autowares_older_detected_objects_is_read_like_the_current_one(tmp_path: Path, storage: str) -> None:
    """Bags recorded before autoware_msgs 1.0 carry autoware_auto_perception_msgs/msg/DetectedObjects (the message
    renamed since): picked without --topic and read by its fields' names. It had been refused as 'not
    autoware_perception_msgs/msg/DetectedObjects', and passed over when picking a topic."""
    bag = _auto_bag(tmp_path / "bag", storage)
    with open_source(str(bag)) as src:
        assert src.topic == DET_TOPIC and src.info.kind == "detections"
        frames = list(src.frames())
    assert [type(f) for f in frames] == [DetectionFrame, DetectionFrame]
    (car,) = frames[0].objects
    assert car.kinematics.pose_with_covariance.pose.position.x == 12.0 and car.shape.dimensions.x == pytest.approx(4.5)
    assert car.classification[0].label == 1 and frames[0].frame_id == "base_link"
    with open_source(str(bag), SourceOptions(topic=DET_TOPIC)) as src:
        assert len(list(src.frames())) == 2


def test_a_bag_without_the_definition_of_its_topics_type_is_one_source_error(tmp_path: Path) -> None:
    """A sqlite3 bag whose recorder kept no message definitions (rosbag2 before Iron) holding a type jitterguard ships
    no definition of: refused once, naming it, rather than every message undecodable."""
    import sqlite3

    bag = _auto_bag(tmp_path / "bag", "sqlite3")
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM message_definitions")
    with pytest.raises(SourceError, match=f"no definition of {AUTO_DETECTED}"):
        open_source(str(bag))


def _bag_with_tf(path: Path, static: list[tuple[str, str]], dynamic: list[tuple[str, str]]) -> None:
    """Two clouds in lidar_top, with the /tf_static links ``static`` and the /tf links ``dynamic`` (parent, child)
    at each cloud's stamp (identity rotations, 1 m apart along x)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from jitterguard.services.replay.sources.ros_types import POINTCLOUD2, typestore

    from .bagfixture import TF, _cloud, _tf

    ts = typestore()
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c_static = w.add_connection("/tf_static", TF, typestore=ts)
        w.write(c_static, T0, ts.serialize_cdr(_tf(ts, [(T0, p, c, 1.0, 0.0, 0.5, 0.0) for p, c in static]), TF))
        c_tf = w.add_connection("/tf", TF, typestore=ts)
        c_cloud = w.add_connection(CLOUD_TOPIC, POINTCLOUD2, typestore=ts)
        for i in range(2):
            t = T0 + i * 100_000_000
            if dynamic:
                w.write(c_tf, t, ts.serialize_cdr(_tf(ts, [(t, p, c, 10.0 + i, 0.0, 0.0, 0.0) for p, c in dynamic]), TF))
            w.write(c_cloud, t, ts.serialize_cdr(_cloud(ts, t, np.zeros((3, 4), np.float32)), POINTCLOUD2))


@pytest.mark.parametrize(("static", "dynamic", "missing"), [
    # the sensor kit's link to the vehicle missing: lidar_top -> sensor_kit_base_link hangs apart from map -> base_link
    ([("sensor_kit_base_link", "lidar_top")], [("map", "base_link")],
     "the link from 'base_link' (or a frame under it) to 'sensor_kit_base_link' is missing"),
    # two links up the chain, and the vehicle itself not placed yet either: the link nearest the sensor is named
    ([("sensor_kit_base_link", "lidar_top"), ("sensor_mount", "sensor_kit_base_link")], [],
     "the link from the world to 'sensor_mount' is missing"),
    # the vehicle's frame reached, nothing above it (localization has no pose yet): as before
    ([("sensor_kit_base_link", "lidar_top"), ("base_link", "sensor_kit_base_link")], [], "map -> base_link"),
])
def test_up_refuses_a_tf_tree_whose_chain_from_the_sensor_to_the_world_is_broken_anywhere(
        tmp_path: Path, static, dynamic, missing) -> None:
    """`up`'s pre-start check (and each scan) refused a TF tree only when its root was base_link: a chain broken
    below it (the sensor kit's link to base_link missing) went unnoticed, its top frame was taken for the world and
    every scan went out posed at its mount near the world's origin. Every link from the cloud's frame up to the world
    is now needed; the refusal is one line naming the missing link."""
    from jitterguard.services.replay.sources import probe_source

    path = tmp_path / "bag"
    _bag_with_tf(path, static, dynamic)
    with pytest.raises(SourceError) as err:
        probe_source(str(path), SourceOptions(pose_topic="/tf"))
    msg = str(err.value)
    assert "\n" not in msg and missing in msg, msg


def test_a_sensor_under_the_world_frame_directly_or_through_base_link_is_posed(tmp_path: Path) -> None:
    """What the check must let through: lidar_top -> sensor_kit_base_link -> base_link -> map, and a sensor posed in
    the world directly (map -> lidar_top) beside a vehicle whose frame hangs elsewhere."""
    from jitterguard.services.replay.sources import probe_source

    _bag_with_tf(tmp_path / "a", [("sensor_kit_base_link", "lidar_top"), ("base_link", "sensor_kit_base_link")],
                 [("map", "base_link")])
    with open_source(str(tmp_path / "a"), SourceOptions(pose_topic="/tf")) as src:
        frames = list(src.frames())
    assert all(isinstance(f, ScanFrame) for f in frames) and frames[1].pose.x == pytest.approx(13.0)
    _bag_with_tf(tmp_path / "b", [("base_link", "imu")], [("map", "lidar_top")])
    assert probe_source(str(tmp_path / "b"), SourceOptions(pose_topic="/tf")).kind == "points"
