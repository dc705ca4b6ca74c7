"""The scans of a ROS 2 bag the recorder writes, in the layout Autoware's LiDAR pipeline takes: ``PointXYZIRC``
(float32 x, y, z; uint8 intensity; uint8 return_type; uint16 channel; 16-byte points), read back by a second
implementation (mcap-ros2-support) and checked with Autoware's own layout rule, restated here from
``autoware_pointcloud_preprocessor``'s ``is_data_layout_compatible_with_point_xyzirc`` (the first six fields by name,
offset, datatype and count). The float32 layout as the wire sent it stays an option, and jitterguard's bag reader
(rosbags) takes both. Real files, no network."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from jitterguard.schemas.models import Header, PointCloud, Pose, TrackedObjects  # noqa: E402
from jitterguard.services.bridge.joiner import JoinedFrame  # noqa: E402
from jitterguard.services.recorder.rosbag import POINTS_TOPIC, Rosbag2Sink  # noqa: E402
from jitterguard.services.replay.frames import ScanFrame  # noqa: E402
from jitterguard.services.replay.sources.bag import BagSource  # noqa: E402

STAMP = 1_700_000_000_000_000_000
FLOAT32, UINT8, UINT16 = 7, 2, 4  # sensor_msgs/msg/PointField
XYZIRC = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, UINT8),
          ("return_type", 13, UINT8), ("channel", 14, UINT16)]
"""autoware_point_types::PointXYZIRC: name, offsetof, datatype of each field, in PointXYZIRCIndex order."""

# x, y, z, intensity, ring: intensities beyond 0..255, fractional and NaN; a ring beyond uint16 and a NaN one
ROWS = np.array([[1.0, 2.0, 0.5, 7.0, 3.0],
                 [-4.25, 0.125, -1.5, 300.0, 31.0],
                 [10.0, -20.0, 2.0, -3.0, 70000.0],
                 [0.5, 0.25, 0.75, 127.6, np.nan],
                 [2.0, 3.0, 4.0, np.nan, 5.0]], dtype="<f4")


def _frame(rows: np.ndarray = ROWS, fields: tuple[str, ...] = ("x", "y", "z", "intensity", "ring")) -> JoinedFrame:
    points = PointCloud(header=Header(stamp=STAMP, seq=1, frame_id="lidar"), ego_pose=Pose(), fields=list(fields),
                        num_points=len(rows), data=np.ascontiguousarray(rows, dtype="<f4").tobytes())
    return JoinedFrame(seq=1, stamp_ns=STAMP, objects=TrackedObjects(header=Header(stamp=STAMP, seq=1, frame_id="map")),
                       points=points)


def _written_cloud(tmp_path, frame: JoinedFrame, **sink_kw):  # type: ignore[no-untyped-def]
    sink = Rosbag2Sink(tmp_path / "bag", **sink_kw)
    sink.write(frame)
    sink.close()
    (mcap_file,) = (tmp_path / "bag").glob("*.mcap")
    with open(mcap_file, "rb") as fh:
        (cloud,) = [m for _, ch, _, m in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
                    if ch.topic == POINTS_TOPIC]
    return cloud


def _autoware_takes_it_as_xyzirc(cloud) -> bool:  # type: ignore[no-untyped-def]
    if len(cloud.fields) < 6:
        return False
    return all((f.name, f.offset, f.datatype, f.count) == (name, offset, datatype, 1)
               for f, (name, offset, datatype) in zip(cloud.fields, XYZIRC))


def test_the_bags_scans_are_autowares_point_xyzirc(tmp_path) -> None:
    cloud = _written_cloud(tmp_path, _frame())
    assert _autoware_takes_it_as_xyzirc(cloud)
    assert len(cloud.fields) == 6 and cloud.point_step == 16  # memcpy-able into PointXYZIRC, nothing after it
    assert (cloud.height, cloud.width, cloud.row_step, cloud.is_bigendian) == (1, len(ROWS), 16 * len(ROWS), False)
    data = bytes(cloud.data)
    assert len(data) == cloud.row_step
    rec = np.frombuffer(data, dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"),
                                              ("return_type", "u1"), ("channel", "<u2")]))
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], axis=1), ROWS[:, :3])
    # intensity on Autoware's drivers' 0..255 scale: rounded, clamped, a NaN one dark
    assert rec["intensity"].tolist() == [7, 255, 0, 128, 0]
    assert rec["return_type"].tolist() == [0] * len(ROWS)  # unknown: 0
    assert rec["channel"].tolist() == [3, 31, 65535, 0, 5]  # the ring is the laser's channel
    assert cloud.is_dense is True  # every x, y, z finite; the NaN intensity went out as 0


def test_a_reflectance_scan_goes_out_on_the_drivers_0_to_255_scale(tmp_path) -> None:
    """A KITTI scan's intensity is a 0–1 reflectance; rounded into uint8 as is, every return had gone out 0 or 1 —
    black to Autoware. It is brought to 0–255 by the rule the detector reads scans with."""
    rows = np.array([[1.0, 2.0, 0.5, 0.0, 0.0], [3.0, 4.0, 0.5, 0.5, 0.0], [5.0, 6.0, 0.5, 0.99, 0.0]], dtype=np.float32)
    rec = np.frombuffer(bytes(_written_cloud(tmp_path, _frame(rows)).data), dtype=np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("return_type", "u1"), ("channel", "<u2")]))
    assert rec["intensity"].tolist() == [0, 128, 252]


def test_a_scan_without_intensity_or_ring_gets_zeros_and_a_non_finite_point_is_not_dense(tmp_path) -> None:
    rows = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0]], dtype="<f4")
    cloud = _written_cloud(tmp_path, _frame(rows, ("x", "y", "z")))
    assert _autoware_takes_it_as_xyzirc(cloud) and cloud.point_step == 16 and cloud.is_dense is False
    rec = np.frombuffer(bytes(cloud.data), dtype=np.dtype([("xyz", "<f4", 3), ("i", "u1"), ("r", "u1"), ("c", "<u2")]))
    np.testing.assert_array_equal(rec["xyz"], rows)
    assert (rec["i"].tolist(), rec["r"].tolist(), rec["c"].tolist()) == ([0, 0], [0, 0], [0, 0])


def test_float32_layout_stays_an_option_with_the_wires_bytes(tmp_path) -> None:
    cloud = _written_cloud(tmp_path, _frame(), points_layout="float32")
    assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
        (n, 4 * j, FLOAT32, 1) for j, n in enumerate(("x", "y", "z", "intensity", "ring"))]
    assert cloud.point_step == 20 and bytes(cloud.data) == ROWS.tobytes() and cloud.is_dense is False
    assert not _autoware_takes_it_as_xyzirc(cloud)


def test_an_unknown_layout_is_refused() -> None:
    from jitterguard.services.recorder.rosbag import RosbagError

    with pytest.raises(RosbagError, match="points layout"):
        Rosbag2Sink("/nonexistent/never-made", points_layout="xyzi")


@pytest.mark.parametrize("layout", ["xyzirc", "float32"])
def test_jitterguard_replay_reads_either_layout_back(tmp_path, layout) -> None:
    sink = Rosbag2Sink(tmp_path / "bag", points_layout=layout)
    sink.write(_frame())
    sink.close()
    with BagSource(tmp_path / "bag", topic=POINTS_TOPIC) as src:
        (scan,) = list(src.frames())
    assert isinstance(scan, ScanFrame)
    np.testing.assert_array_equal(scan.points[:, :3], ROWS[:, :3])
    if layout == "xyzirc":
        assert scan.fields == ("x", "y", "z", "intensity", "return_type", "channel")
        assert scan.points[:, 3].tolist() == [7, 255, 0, 128, 0] and scan.points[:, 5].tolist() == [3, 31, 65535, 0, 5]
    else:
        assert scan.fields == ("x", "y", "z", "intensity", "ring")
        np.testing.assert_array_equal(scan.points, np.nan_to_num(ROWS))  # the reader zeroes a NaN beside x, y, z
