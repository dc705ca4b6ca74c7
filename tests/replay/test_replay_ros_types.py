"""The bag source's pure helpers on hand-built messages: PointCloud2 decoding and pose interpolation (no rosbags)."""

from __future__ import annotations

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from jitterguard.services.replay.frames import EgoPose
from jitterguard.services.replay.sources.ros_types import interpolate_pose, pointcloud2_to_array

# --------------------------------------------------------------------- pure helpers (no rosbags needed)


def _pc2(rec: np.ndarray, fields: list[tuple[str, int, int]], *, big: bool = False, row_pad: int = 0, height: int = 1) -> NS:
    step = rec.dtype.itemsize
    width = rec.size // height
    rows = rec.tobytes()
    if row_pad:
        rows = b"".join(rows[r * width * step : (r + 1) * width * step] + b"\xee" * row_pad for r in range(height))
    return NS(
        is_bigendian=big, point_step=step, row_step=width * step + row_pad, width=width, height=height,
        fields=[NS(name=n, offset=o, datatype=d, count=1) for n, o, d in fields], data=np.frombuffer(rows, np.uint8),
    )


def test_pointcloud2_puts_xyz_first_and_handles_padding_and_row_padding() -> None:
    dt = np.dtype({"names": ["intensity", "x", "y", "z", "ring"], "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
                   "offsets": [0, 4, 8, 12, 16], "itemsize": 20})
    rec = np.zeros(6, dtype=dt)
    rec["x"], rec["y"], rec["z"], rec["intensity"], rec["ring"] = np.arange(6), 10 + np.arange(6), -1, 0.5, np.arange(6) % 2
    msg = _pc2(rec, [("intensity", 0, 7), ("x", 4, 7), ("y", 8, 7), ("z", 12, 7), ("ring", 16, 4)], row_pad=3, height=2)
    pts, names = pointcloud2_to_array(msg)
    assert names == ("x", "y", "z", "intensity", "ring")
    np.testing.assert_array_equal(pts[:, 0], np.arange(6))
    np.testing.assert_array_equal(pts[:, 1], 10 + np.arange(6))
    np.testing.assert_array_equal(pts[:, 4], np.arange(6) % 2)


def test_pointcloud2_big_endian_and_float64() -> None:
    dt = np.dtype([("x", ">f8"), ("y", ">f8"), ("z", ">f8")])
    rec = np.array([(1.5, -2.0, 3.25)], dtype=dt)
    pts, names = pointcloud2_to_array(_pc2(rec, [("x", 0, 8), ("y", 8, 8), ("z", 16, 8)], big=True))
    assert names == ("x", "y", "z") and pts.tolist() == [[1.5, -2.0, 3.25]]


@pytest.mark.parametrize("change,match", [("no_z", "no z"), ("short", "truncated"), ("bad_type", "datatype"), ("offset", "does not fit")])
def test_pointcloud2_malformed_messages_raise_value_error(change: str, match: str) -> None:
    rec = np.zeros(4, dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    if change == "no_z":
        fields = fields[:2]
    if change == "bad_type":
        fields[0] = ("x", 0, 42)
    if change == "offset":
        fields[2] = ("z", 10, 7)
    msg = _pc2(rec, fields)
    if change == "short":
        msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match=match):
        pointcloud2_to_array(msg)


def test_interpolate_pose_is_linear_in_position_and_slerps_yaw() -> None:
    a, b = EgoPose.from_yaw(0.0, 0.0, 0.0), EgoPose.from_yaw(10.0, -4.0, 1.0)
    mid = interpolate_pose([100, 200], [a, b], 125)
    assert (mid.x, mid.y) == pytest.approx((2.5, -1.0)) and mid.yaw == pytest.approx(0.25)
    assert interpolate_pose([100, 200], [a, b], 50) == a  # clamped before the first sample
    assert interpolate_pose([100, 200], [a, b], 900) == b


def test_interpolate_pose_takes_the_short_way_round() -> None:
    a, b = EgoPose.from_yaw(0, 0, math.pi - 0.1), EgoPose.from_yaw(0, 0, -math.pi + 0.1)
    mid = interpolate_pose([0, 2], [a, b], 1)
    assert abs(mid.yaw) == pytest.approx(math.pi, abs=1e-6)



def test_tf_tree_composes_static_and_interpolated_dynamic_links() -> None:
    from jitterguard.services.replay.sources.tf import TfTree

    tf = TfTree()
    tf.add("map", "base_link", 0, EgoPose.from_yaw(0.0, 0.0, 0.0))
    tf.add("map", "base_link", 100, EgoPose.from_yaw(10.0, 0.0, math.pi / 2))
    tf.add("/base_link", "lidar", 0, EgoPose.from_yaw(1.0, 0.0, 0.0, z=2.0), static=True)
    p = tf.lookup("lidar", 100)
    assert (p.x, p.y, p.z) == pytest.approx((10.0, 1.0, 2.0)) and p.yaw == pytest.approx(math.pi / 2)
    mid = tf.lookup("lidar", 50)
    assert mid.yaw == pytest.approx(math.pi / 4) and mid.x == pytest.approx(5.0 + math.cos(math.pi / 4))
    assert tf.lookup("lidar", 50, ancestor="base_link").x == pytest.approx(1.0)
    assert tf.root("lidar") == "map"
    with pytest.raises(KeyError, match="not in the TF tree"):
        tf.lookup("camera", 0)
    with pytest.raises(KeyError, match="not above"):
        tf.lookup("base_link", 0, ancestor="lidar")
