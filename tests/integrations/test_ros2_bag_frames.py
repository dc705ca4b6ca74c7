"""The ``/tf`` of a ROS 2 bag the recorder writes, read back by a second implementation (mcap-ros2-support) and
composed as tf2 would: every frame the data names is reached from ``map`` at the sensor pose, and no transform is a
self-link or gives a frame a second parent — whatever the scans' ``frame_id`` (a LiDAR's own frame, or Autoware's
``base_link``, where its concatenated cloud and its detectors' ``DetectedObjects`` live). Real files, no network."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from jitterguard.schemas.models import DetectedObjects, Header, PointCloud, Pose, TrackedObjects  # noqa: E402
from jitterguard.services.bridge.joiner import JoinedFrame  # noqa: E402
from jitterguard.services.foxglove.scene import frame_transforms  # noqa: E402
from jitterguard.services.recorder.rosbag import DETECTIONS_TOPIC, POINTS_TOPIC, TF_TOPIC, Rosbag2Sink  # noqa: E402

from .decoding import protobuf_class  # noqa: E402

STAMP = 1_700_000_000_123_456_789


def _pose() -> Pose:
    """A sensor on a map with elevation (Autoware's maps are not at z = 0), rolled, pitched and turned."""
    x, y, z, w = Rotation.from_euler("ZYX", [2.1, 0.03, -0.02]).as_quat()
    return Pose.model_validate({"position": {"x": 81.5, "y": -12.25, "z": 41.7},
                                "orientation": {"x": x, "y": y, "z": z, "w": w}})


def _frame(frame_id: str) -> JoinedFrame:
    pose = _pose()
    pts = np.array([[1.0, 2.0, 0.5, 7.0]], dtype="<f4")
    points = PointCloud(header=Header(stamp=STAMP, seq=3, frame_id=frame_id), ego_pose=pose,
                        fields=["x", "y", "z", "intensity"], num_points=1, data=pts.tobytes())
    dets = DetectedObjects(header=Header(stamp=STAMP, seq=3, frame_id=frame_id), ego_pose=pose)
    return JoinedFrame(seq=3, stamp_ns=STAMP, objects=TrackedObjects(header=Header(stamp=STAMP, seq=3, frame_id="map")),
                       points=points, detections=dets)


def _compose(transforms: dict[str, tuple[str, np.ndarray, Rotation]], frame: str, root: str) -> tuple[np.ndarray,
                                                                                                      Rotation]:
    """The pose of ``frame`` in ``root`` through child → (parent, translation, rotation), as tf2 chains them."""
    t, r = np.zeros(3), Rotation.identity()
    seen = set()
    while frame != root:
        assert frame in transforms and frame not in seen, f"no TF path from {root} to {frame}"
        seen.add(frame)
        parent, tt, rr = transforms[frame]
        t, r = rr.apply(t) + tt, rr * r
        frame = parent
    return t, r


def _check_chain(edges: list[tuple[str, str, np.ndarray, Rotation]], data_frame: str) -> None:
    by_child: dict[str, tuple[str, np.ndarray, Rotation]] = {}
    for parent, child, t, r in edges:
        assert parent != child, f"self-transform {parent} -> {child} (tf2 refuses it)"
        assert child not in by_child, f"{child} has two parents"
        by_child[child] = (parent, t, r)
    t, r = _compose(by_child, data_frame, "map")
    want = _pose()
    p, q = want.position, want.orientation
    assert t == pytest.approx([p.x, p.y, p.z], abs=1e-9)
    assert (r * Rotation.from_quat([q.x, q.y, q.z, q.w]).inv()).magnitude() < 1e-9


@pytest.mark.parametrize("frame_id", ["lidar", "LIDAR_TOP_vehicle_axes", "base_link"])
def test_the_bags_tf_puts_the_datas_frame_at_the_sensor_pose(tmp_path, frame_id) -> None:
    sink = Rosbag2Sink(tmp_path / "bag")
    sink.write(_frame(frame_id))
    sink.close()
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    got: dict[str, list] = {}
    with open(mcap_file, "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            got.setdefault(channel.topic, []).append(msg)
    assert [m.header.frame_id for m in got[POINTS_TOPIC] + got[DETECTIONS_TOPIC]] == [frame_id, frame_id]
    (tf,) = got[TF_TOPIC]
    edges = []
    for tr in tf.transforms:
        assert tr.header.stamp.sec * 10**9 + tr.header.stamp.nanosec == STAMP
        tt, rr = tr.transform.translation, tr.transform.rotation
        edges.append((tr.header.frame_id, tr.child_frame_id, np.array([tt.x, tt.y, tt.z]),
                      Rotation.from_quat([rr.x, rr.y, rr.z, rr.w])))
    _check_chain(edges, frame_id)


@pytest.mark.parametrize("frame_id", ["lidar", "base_link", "ego"])
def test_foxglove_tf_puts_the_datas_frame_at_the_sensor_pose(frame_id) -> None:
    ft = frame_transforms(_frame(frame_id))
    assert ft is not None
    schema = ft.get_schema()  # decoded by Google's protobuf runtime on the schema the SDK embeds
    ft = protobuf_class(schema.name, schema.data).FromString(ft.encode())
    edges = [(t.parent_frame_id, t.child_frame_id, np.array([t.translation.x, t.translation.y, t.translation.z]),
              Rotation.from_quat([t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w])) for t in ft.transforms]
    _check_chain(edges, frame_id)


def test_data_in_the_world_frame_gets_no_transform_to_itself(tmp_path) -> None:
    assert frame_transforms(_frame("map")) is None  # map -> ego -> map would be a cycle
    sink = Rosbag2Sink(tmp_path / "bag")
    sink.write(_frame("map"))
    sink.close()
    assert TF_TOPIC not in sink.counts and sink.counts[POINTS_TOPIC] == 1


def test_a_cloud_with_non_finite_values_is_not_written_dense(tmp_path) -> None:
    """PointCloud2's is_dense says the cloud holds no invalid (NaN) points, and PCL readers trust it: the bag had said so
    of every scan, though the wire does not promise it (jitterguard's replay drops such rows; another publisher may
    not)."""
    sink = Rosbag2Sink(tmp_path / "bag")
    for k, row in enumerate(([1.0, 2.0, 0.5, 7.0], [np.nan, np.nan, np.nan, 0.0])):
        f = _frame("lidar")
        pts = np.array([[3.0, 4.0, 0.1, 9.0], row], dtype="<f4")
        f.points = f.points.model_copy(update={"num_points": 2, "data": pts.tobytes(),
                                               "header": Header(stamp=STAMP + k, seq=3 + k, frame_id="lidar")})
        sink.write(f)
    sink.close()
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    with open(mcap_file, "rb") as fh:
        dense = [m.is_dense for _, ch, _, m in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
                 if ch.topic == POINTS_TOPIC]
    assert dense == [True, False]
