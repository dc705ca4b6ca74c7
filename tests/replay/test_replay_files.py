"""File readers: KITTI / nuScenes raw .bin (with poses, calib, times), PCD (3 encodings), a small nuScenes
dataroot built here, and SOURCE dispatch. Corrupt files must yield one error naming the file."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from jitterguard.services.replay.frames import EgoPose, FrameError, ScanFrame, SourceError, compose
from jitterguard.services.replay.sources import SourceOptions, open_source
from jitterguard.services.replay.sources.kitti import NOMINAL_TR, BinScanSource
from jitterguard.services.replay.sources.nuscenes import NuScenesSource
from jitterguard.services.replay.sources.pcd import PcdSource, lzf_decompress, read_pcd

from .helpers import MS, write_bin


def lzf_literal(data: bytes) -> bytes:
    """The trivial valid LZF encoding (literal runs only): lets the tests write binary_compressed files."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def _scans(folder: Path, n: int, cols: int = 4, suffix: str = ".bin") -> list[np.ndarray]:
    out = []
    for i in range(n):
        pts = np.random.default_rng(i).normal(size=(10 + i, cols)).astype(np.float32)
        write_bin(folder / f"{i:06d}{suffix}", pts)
        out.append(pts)
    return out


# ------------------------------------------------------------------------------------------ KITTI .bin


def test_kitti_folder_reads_every_scan_exactly_with_identity_pose_and_10hz(tmp_path: Path) -> None:
    want = _scans(tmp_path, 3)
    frames = list(BinScanSource(tmp_path).frames())
    assert all(isinstance(f, ScanFrame) for f in frames)
    assert [f.stamp_ns for f in frames] == [0, 100 * MS, 200 * MS]
    for f, w in zip(frames, want):
        assert f.fields == ("x", "y", "z", "intensity") and f.frame_id == "velodyne"
        np.testing.assert_array_equal(f.points, w)
        assert f.pose == EgoPose()


def test_kitti_truncated_file_is_an_error_naming_it_and_the_rest_still_reads(tmp_path: Path) -> None:
    _scans(tmp_path, 3)
    bad = tmp_path / "000001.bin"
    bad.write_bytes(bad.read_bytes()[:-3])
    items = list(BinScanSource(tmp_path).frames())
    assert isinstance(items[1], FrameError) and items[1].origin == str(bad) and "whole number" in items[1].reason
    assert isinstance(items[0], ScanFrame) and isinstance(items[2], ScanFrame)


def test_an_empty_bin_is_an_empty_scan_as_a_pcd_of_0_points_is(tmp_path: Path) -> None:
    """A raw scan has no header: 0 bytes is exactly how it writes 0 points (a LiDAR blocked or covered returns
    nothing), as a PCD says ``POINTS 0``. The .bin had been an unreadable frame (skipped, so the tracker saw a gap)
    while the PCD went out as an empty scan (the detector counts it ``empty_scans``): both are empty scans now."""
    (tmp_path / "000000.bin").write_bytes(b"")
    [item] = list(BinScanSource(tmp_path).frames())
    assert isinstance(item, ScanFrame) and item.points.shape == (0, 4), item
    pcd = tmp_path / "p"
    pcd.mkdir()
    (pcd / "0.pcd").write_text("VERSION .7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                               "WIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA binary\n")
    [p] = list(PcdSource(pcd).frames())
    assert isinstance(p, ScanFrame) and p.points.shape == (0, 4) and p.fields == item.fields


def test_a_bin_larger_than_a_scan_may_be_is_refused_from_its_size_unread(tmp_path: Path) -> None:
    """A .bin is read whole: a mistaken or huge file (a 4 GB disk image named .bin) had been read into memory, and one
    over the detector's 64 MiB max_scan_bytes published for the detector to refuse. Its size from the file's stat is
    held to that cap before a byte is read: one unreadable frame naming the file, the rest of the folder reads."""
    from jitterguard.services.detector.config import DetectorParams
    from jitterguard.services.replay.frames import MAX_SCAN_BYTES

    assert MAX_SCAN_BYTES == DetectorParams.model_fields["max_scan_bytes"].default  # the detector's own default
    _scans(tmp_path, 2)
    big = tmp_path / "000002.bin"
    with big.open("wb") as f:  # sparse: no disk, and no memory unless read
        f.truncate(MAX_SCAN_BYTES + 16)
    items = list(BinScanSource(tmp_path).frames())
    assert isinstance(items[0], ScanFrame) and isinstance(items[1], ScanFrame)
    assert isinstance(items[2], FrameError) and items[2].origin == str(big)
    assert "over the 64 MiB" in items[2].reason and "max_scan_bytes" in items[2].reason and "\n" not in str(items[2])


def test_start_skips_without_reading(tmp_path: Path) -> None:
    _scans(tmp_path, 4)
    (tmp_path / "000000.bin").write_bytes(b"xx")  # corrupt, but before --start
    items = list(BinScanSource(tmp_path).frames(start=2))
    assert [Path(i.origin).name for i in items] == ["000002.bin", "000003.bin"]


def test_non_finite_xyz_rows_are_dropped(tmp_path: Path) -> None:
    pts = np.array([[1, 2, 3, 0.5], [np.nan, 0, 0, 1], [4, 5, 6, np.inf]], dtype=np.float32)
    write_bin(tmp_path / "000000.bin", pts)
    [f] = list(BinScanSource(tmp_path).frames())
    np.testing.assert_array_equal(f.points, [[1, 2, 3, 0.5], [4, 5, 6, 0.0]])


def _pose_line(m: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in m[:3, :].reshape(-1))


def test_kitti_poses_with_calib_give_the_lidar_pose_in_a_z_up_world(tmp_path: Path) -> None:
    scans = tmp_path / "velodyne"
    _scans(scans, 2)
    # Camera 0 drives 2 m forward (camera z) and turns 90° left (about camera -y, which is "up" negated).
    p0 = np.eye(4)
    yaw = math.pi / 2
    p1 = np.eye(4)
    p1[:3, :3] = [[math.cos(yaw), 0, -math.sin(yaw)], [0, 1, 0], [math.sin(yaw), 0, math.cos(yaw)]]
    p1[:3, 3] = [0, 0, 2.0]
    (tmp_path / "poses.txt").write_text(_pose_line(p0) + "\n" + _pose_line(p1) + "\n")
    (tmp_path / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\nTr: " + _pose_line(NOMINAL_TR) + "\n")
    src = BinScanSource(scans, poses=tmp_path / "poses.txt")
    f0, f1 = list(src.frames())
    assert f0.pose.x == pytest.approx(0) and f0.pose.yaw == pytest.approx(0)
    assert (f1.pose.x, f1.pose.y, f1.pose.z) == pytest.approx((2.0, 0.0, 0.0), abs=1e-9)  # forward is +x
    assert f1.pose.yaw == pytest.approx(yaw)  # left turn is +yaw about +z
    assert any("calib.txt" in n for n in src.info.notes)


def test_kitti_times_file_gives_stamps_and_numbered_files_index_rows(tmp_path: Path) -> None:
    write_bin(tmp_path / "000005.bin", np.zeros((2, 4)))
    write_bin(tmp_path / "000007.bin", np.zeros((2, 4)))
    (tmp_path / "times.txt").write_text("\n".join(f"{0.1037 * i:.6e}" for i in range(10)) + "\n")
    stamps = [f.stamp_ns for f in BinScanSource(tmp_path).frames()]
    assert stamps == [int(round(0.1037 * 5 * 1e9)), int(round(0.1037 * 7 * 1e9))]


def test_kitti_times_past_an_int64_stamp_are_a_source_error_naming_the_line(tmp_path: Path) -> None:
    """9.3e9 s is 9.3e18 ns, past int64: it had reached the replay's Header and failed there with a traceback."""
    write_bin(tmp_path / "000000.bin", np.zeros((2, 4)))
    (tmp_path / "times.txt").write_text("0.0\n9.3e9\n")
    with pytest.raises(SourceError, match=r"times.txt:2: time 9.3e\+09 s is past what an int64 stamp"):
        BinScanSource(tmp_path)


def test_kitti_missing_pose_row_is_a_frame_error(tmp_path: Path) -> None:
    _scans(tmp_path / "s", 2)
    (tmp_path / "poses.txt").write_text(_pose_line(np.eye(4)) + "\n")
    items = list(BinScanSource(tmp_path / "s", poses=tmp_path / "poses.txt").frames())
    assert isinstance(items[0], ScanFrame) and isinstance(items[1], FrameError) and "no pose" in items[1].reason


@pytest.mark.parametrize("content,match", [("1 2 3\n", "12 finite numbers, got 3"), ("a b c\n", "not 12 numbers"),
                                           ("", "no pose"),
                                           ("1 0 0 nan 0 1 0 0 0 0 1 0\n", r"got a non-finite one \(nan\)")])  # had: got 12
def test_bad_poses_file_is_a_source_error_naming_it(tmp_path: Path, content: str, match: str) -> None:
    _scans(tmp_path / "s", 1)
    (tmp_path / "p.txt").write_text(content)
    with pytest.raises(SourceError, match=match) as exc:
        BinScanSource(tmp_path / "s", poses=tmp_path / "p.txt")
    assert "p.txt" in str(exc.value)



@pytest.mark.parametrize("rotation", [np.diag([1.0, 1.0, -1.0]), np.zeros((3, 3))], ids=["reflection", "zeros"])
def test_a_pose_or_calib_line_that_is_no_rotation_is_a_source_error_naming_its_line(tmp_path: Path,
                                                                                     rotation: np.ndarray) -> None:
    """A poses line whose 3x3 part is a reflection had ended the replay with "matrix is a reflection, not a
    rotation", naming neither the file nor the line; an all-zero placeholder line was silently replaced by whatever
    rotation its re-orthonormalisation gave. Both are refused naming the file and line; so is such a Tr in calib.txt."""
    _scans(tmp_path / "s", 2)
    bad = np.eye(4)
    bad[:3, :3] = rotation
    (tmp_path / "p.txt").write_text(_pose_line(np.eye(4)) + "\n" + _pose_line(bad) + "\n")
    with pytest.raises(SourceError, match=r"p\.txt:2: pose line's 3x3 part is no rotation"):
        BinScanSource(tmp_path / "s", poses=tmp_path / "p.txt")
    (tmp_path / "ok.txt").write_text(_pose_line(np.eye(4)) + "\n")
    (tmp_path / "calib.txt").write_text("Tr: " + _pose_line(bad) + "\n")
    with pytest.raises(SourceError, match=r"calib\.txt: no valid 'Tr:' line"):
        BinScanSource(tmp_path / "s", poses=tmp_path / "ok.txt", calib=tmp_path / "calib.txt")

def test_pcd_bin_suffix_means_five_nuscenes_columns(tmp_path: Path) -> None:
    want = _scans(tmp_path, 1, cols=5, suffix=".pcd.bin")
    [f] = list(BinScanSource(tmp_path).frames())
    assert f.fields == ("x", "y", "z", "intensity", "ring") and f.frame_id == "LIDAR_TOP"
    np.testing.assert_array_equal(f.points, want[0])


# ------------------------------------------------------------------------------------------------- PCD

PCD_HEADER = """# .PCD v0.7 - Point Cloud Data file format
VERSION 0.7
FIELDS x y z intensity _ normal
SIZE 4 4 4 2 1 4
TYPE F F F U U F
COUNT 1 1 1 1 1 3
WIDTH {n}
HEIGHT 1
VIEWPOINT 1 2 3 {qw} 0 0 {qz}
POINTS {n}
DATA {data}
"""


def _pcd_points(n: int) -> np.ndarray:
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<u2"), ("pad", "u1"), ("normal", "<f4", (3,))])
    arr = np.zeros(n, dtype=dt)
    rng = np.random.default_rng(0)
    arr["x"], arr["y"], arr["z"] = rng.normal(size=(3, n)).astype(np.float32)
    arr["intensity"] = np.arange(n) * 7
    arr["normal"] = 1.0
    return arr


def _write_pcd(path: Path, arr: np.ndarray, data: str) -> None:
    yaw = 0.5
    head = PCD_HEADER.format(n=len(arr), data=data, qw=math.cos(yaw / 2), qz=math.sin(yaw / 2)).encode()
    if data == "binary":
        body = arr.tobytes()
    elif data == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(arr[name]).tobytes() for name in arr.dtype.names)
        comp = lzf_literal(raw)
        body = struct.pack("<II", len(comp), len(raw)) + comp
    else:
        body = "".join(
            f"{r['x']:.9g} {r['y']:.9g} {r['z']:.9g} {r['intensity']} 0 1 1 1\n" for r in arr
        ).encode()
    path.write_bytes(head + body)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_pcd_encodings_read_the_same_columns_and_viewpoint(tmp_path: Path, data: str) -> None:
    arr = _pcd_points(50)
    _write_pcd(tmp_path / "a.pcd", arr, data)
    pts, names, pose = read_pcd(tmp_path / "a.pcd")
    assert names == ("x", "y", "z", "intensity")  # padding and the 3-count normal are dropped
    np.testing.assert_allclose(pts[:, 0], arr["x"], rtol=1e-6)
    np.testing.assert_array_equal(pts[:, 3], arr["intensity"].astype(np.float32))
    assert (pose.x, pose.y, pose.z) == (1, 2, 3) and pose.yaw == pytest.approx(0.5)


def test_pcd_truncated_binary_is_an_error_naming_the_file(tmp_path: Path) -> None:
    _write_pcd(tmp_path / "a.pcd", _pcd_points(20), "binary")
    (tmp_path / "b.pcd").write_bytes((tmp_path / "a.pcd").read_bytes()[:-10])
    items = list(PcdSource(tmp_path).frames())
    assert isinstance(items[0], ScanFrame)
    assert isinstance(items[1], FrameError) and items[1].origin.endswith("b.pcd") and "truncated" in items[1].reason


@pytest.mark.parametrize("blob", [b"", b"\x00\x01garbage" * 100, b"VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nWIDTH 1\nHEIGHT 1\nDATA binary\n"])
def test_pcd_garbage_is_a_frame_error(tmp_path: Path, blob: bytes) -> None:
    (tmp_path / "x.pcd").write_bytes(blob)
    [item] = list(PcdSource(tmp_path / "x.pcd").frames())
    assert isinstance(item, FrameError) and "not a valid PCD" in item.reason


def test_a_pcd_claiming_more_points_than_a_scan_may_hold_is_refused_before_it_is_decoded(tmp_path: Path) -> None:
    """A few KB of ``binary_compressed`` data whose header claims 3 million points (each 2-byte back reference of
    LZF expands to 264 bytes): it had been expanded, its buffer allocated, before the claim was checked."""
    n = 3_000_000
    itemsize = _pcd_points(1).dtype.itemsize
    head = PCD_HEADER.format(n=n, data="binary_compressed", qw=1.0, qz=0.0).encode()
    comp = bytes([0]) + b"\x00" + bytes([(7 << 5), 255, 0]) * 1000
    (tmp_path / "bomb.pcd").write_bytes(head + struct.pack("<II", len(comp), n * itemsize) + comp)
    [item] = list(PcdSource(tmp_path / "bomb.pcd").frames())
    assert isinstance(item, FrameError) and item.reason == (
        f"not a valid PCD file: its {n} points of {itemsize} bytes ({n * itemsize / (1 << 20):.4g} MiB) are over the "
        f"64 MiB a scan may be (the detector's max_scan_bytes): not decoded")


def test_a_pcd_file_over_its_bound_is_refused_unread(tmp_path: Path) -> None:
    """Its size is taken from ``fstat``: a sparse 4 GiB file named ``.pcd`` is refused without a byte read."""
    path = tmp_path / "huge.pcd"
    with open(path, "wb") as f:
        f.truncate(4 << 30)
    [item] = list(PcdSource(path).frames())
    assert isinstance(item, FrameError) and item.reason == (
        "not a valid PCD file: 4294967296 bytes (4096 MiB) is over the 256 MiB a PCD file of a scan may be "
        "(4 × the detector's max_scan_bytes): not read")


def test_lzf_back_references_including_overlapping_runs() -> None:
    # literal "abc", then copy 6 bytes from 3 back (overlapping): "abcabcabc"; then a long ref (len 9+) of "abcabcabc"
    data = bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2]) + bytes([(7 << 5) | 0, 9 - 7 - 2 + 0, 8])
    assert lzf_decompress(data, 18) == b"abc" * 6
    with pytest.raises(ValueError):
        lzf_decompress(bytes([(1 << 5), 40]), 3)  # reference before the start
    with pytest.raises(ValueError):
        lzf_decompress(bytes([5]) + b"ab", 6)  # truncated literal


# ------------------------------------------------------------------------------------ nuScenes dataroot


def _quat_wxyz(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def make_nuscenes_root(root: Path, n: int = 3, drop_file: int | None = None) -> Path:
    """A dataroot with one scene of ``n`` LIDAR_TOP key frames (plus one CAM_FRONT sample_data to ignore)."""
    tables = root / "v1.0-mini"
    tables.mkdir(parents=True)
    (root / "samples" / "LIDAR_TOP").mkdir(parents=True)
    sensors = [{"token": "s-lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
               {"token": "s-cam", "channel": "CAM_FRONT", "modality": "camera"}]
    calib = [{"token": "c-lidar", "sensor_token": "s-lidar", "translation": [1.0, 0.0, 1.8], "rotation": _quat_wxyz(-math.pi / 2), "camera_intrinsic": []},
             {"token": "c-cam", "sensor_token": "s-cam", "translation": [0, 0, 0], "rotation": [1, 0, 0, 0], "camera_intrinsic": []}]
    samples, sds, egos = [], [], []
    for i in range(n):
        ts = 1_500_000_000_000_000 + i * 500_000
        samples.append({"token": f"smp{i}", "timestamp": ts, "prev": f"smp{i-1}" if i else "", "next": f"smp{i+1}" if i < n - 1 else "", "scene_token": "scn"})
        egos.append({"token": f"ego{i}", "timestamp": ts, "translation": [10.0 + i, 20.0, 0.0], "rotation": _quat_wxyz(math.pi / 2)})
        fname = f"samples/LIDAR_TOP/scan{i}.pcd.bin"
        sds.append({"token": f"sd{i}", "sample_token": f"smp{i}", "ego_pose_token": f"ego{i}", "calibrated_sensor_token": "c-lidar",
                    "timestamp": ts, "fileformat": "pcd", "is_key_frame": True, "filename": fname,
                    "prev": f"sd{i-1}" if i else "", "next": f"sd{i+1}" if i < n - 1 else ""})
        if i != drop_file:
            write_bin(root / fname, np.full((4 + i, 5), i, dtype=np.float32))
    sds.append({"token": "cam0", "sample_token": "smp0", "ego_pose_token": "ego0", "calibrated_sensor_token": "c-cam",
                "timestamp": samples[0]["timestamp"], "fileformat": "jpg", "is_key_frame": True, "filename": "samples/CAM_FRONT/x.jpg", "prev": "", "next": ""})
    scene = [{"token": "scn", "log_token": "log", "nbr_samples": n, "first_sample_token": "smp0", "last_sample_token": f"smp{n-1}", "name": "scene-0001", "description": ""}]
    # Tables listed out of order on purpose: the chain, not the file order, decides.
    for name, table in {"scene": scene, "sample": samples[::-1], "sample_data": sds[::-1], "ego_pose": egos,
                        "calibrated_sensor": calib, "sensor": sensors}.items():
        (tables / f"{name}.json").write_text(json.dumps(table))
    return root


def test_nuscenes_walks_the_scene_and_composes_the_lidar_world_pose(tmp_path: Path) -> None:
    root = make_nuscenes_root(tmp_path / "nusc")
    src = NuScenesSource(root)
    frames = list(src.frames())
    # each scan's points are (i, i, i, i, i) in the LiDAR's axes, published in the vehicle's: turned by the mount's -90°
    assert [tuple(f.points[0]) for f in frames] == [(i, -i, i, i, i) for i in range(3)]
    assert [f.stamp_ns for f in frames] == [1_500_000_000_000_000_000 + i * 500_000_000 for i in range(3)]
    f1 = frames[1]
    # ego at (11, 20) facing +y; the LiDAR sits 1 m ahead (-> +y in the world), 1.8 m up; the published pose has
    # the LiDAR's position and the vehicle's axes (heading +y)
    assert (f1.pose.x, f1.pose.y, f1.pose.z) == pytest.approx((11.0, 21.0, 1.8))
    assert f1.pose.yaw == pytest.approx(math.pi / 2, abs=1e-9)
    # pose ∘ published point is the world point of devkit's chain ego_pose ∘ calibrated_sensor ∘ raw point
    chain = compose(EgoPose.from_yaw(11.0, 20.0, math.pi / 2), EgoPose.from_yaw(1.0, 0.0, -math.pi / 2, 1.8))
    np.testing.assert_allclose(f1.pose.matrix() @ np.r_[f1.points[0, :3], 1.0], chain.matrix() @ [1.0, 1.0, 1.0, 1.0],
                               atol=1e-6)
    assert f1.fields == ("x", "y", "z", "intensity", "ring") and f1.frame_id == "LIDAR_TOP_vehicle_axes"


def test_nuscenes_missing_scan_file_is_a_frame_error_naming_it(tmp_path: Path) -> None:
    root = make_nuscenes_root(tmp_path / "nusc", drop_file=1)
    items = list(NuScenesSource(root).frames())
    assert isinstance(items[1], FrameError) and items[1].origin.endswith("scan1.pcd.bin")


def test_nuscenes_unknown_scene_lists_the_scenes(tmp_path: Path) -> None:
    root = make_nuscenes_root(tmp_path / "nusc")
    with pytest.raises(SourceError, match="scene-0001"):
        NuScenesSource(root, scene="scene-9999")


def test_nuscenes_broken_table_is_a_source_error_naming_it(tmp_path: Path) -> None:
    root = make_nuscenes_root(tmp_path / "nusc")
    (root / "v1.0-mini" / "ego_pose.json").write_text("{not json")
    with pytest.raises(SourceError, match="ego_pose.json"):
        NuScenesSource(root)


def test_compose_matches_matrix_product() -> None:
    a = EgoPose(1, 2, 3, *(0.1, 0.2, 0.3, 0.9))
    b = EgoPose(-1, 0.5, 2, *(0.0, 0.6, 0.0, 0.8))
    c = compose(a, b)
    np.testing.assert_allclose(c.matrix(), a.matrix() @ b.matrix(), atol=1e-12)


# ----------------------------------------------------------------------------------------- dispatch


def test_upper_case_bin_names_are_scans_too(tmp_path: Path) -> None:
    """Windows tools and some loggers write ``000000.BIN`` / ``.PCD.BIN``: the suffix is not case-sensitive."""
    want = _scans(tmp_path / "kitti", 2, suffix=".BIN")
    frames = list(open_source(str(tmp_path / "kitti")).frames())
    assert len(frames) == 2 and frames[1].fields == ("x", "y", "z", "intensity")
    np.testing.assert_array_equal(frames[1].points, want[1])
    [one] = list(open_source(str(tmp_path / "kitti" / "000001.BIN")).frames())
    np.testing.assert_array_equal(one.points, want[1])
    nusc = _scans(tmp_path / "nusc", 1, cols=5, suffix=".PCD.BIN")
    [f] = list(open_source(str(tmp_path / "nusc")).frames())
    assert f.fields == ("x", "y", "z", "intensity", "ring")
    np.testing.assert_array_equal(f.points, nusc[0])


def test_open_source_picks_the_reader_from_the_path(tmp_path: Path) -> None:
    _scans(tmp_path / "kitti", 1)
    (tmp_path / "pcds").mkdir()
    _write_pcd(tmp_path / "pcds" / "a.pcd", _pcd_points(3), "binary")
    root = make_nuscenes_root(tmp_path / "nusc")
    assert type(open_source(str(tmp_path / "kitti"))).__name__ == "BinScanSource"
    assert type(open_source(str(tmp_path / "pcds"))).__name__ == "PcdSource"
    assert type(open_source(str(tmp_path / "pcds" / "a.pcd"))).__name__ == "PcdSource"
    assert type(open_source(str(root))).__name__ == "NuScenesSource"


@pytest.mark.parametrize(
    "spec,opts,match",
    [
        ("nowhere", SourceOptions(), "no such file"),
        ("synthetic:moon", SourceOptions(), "unknown scenario"),
        ("{kitti}", SourceOptions(scene="x"), "--scene does not apply"),
        ("{kitti}", SourceOptions(level="detections"), "--level detections"),
        ("{empty}", SourceOptions(), "cannot tell"),
        ("{kitti}/readme.txt", SourceOptions(), "unknown recording type"),
    ],
)
def test_open_source_refuses_bad_input_with_one_line(tmp_path: Path, spec: str, opts: SourceOptions, match: str) -> None:
    _scans(tmp_path / "kitti", 1)
    (tmp_path / "kitti" / "readme.txt").write_text("hi")
    (tmp_path / "empty").mkdir()
    spec = spec.format(kitti=tmp_path / "kitti", empty=tmp_path / "empty")
    with pytest.raises(SourceError, match=match) as exc:
        open_source(spec, opts)
    assert "\n" not in str(exc.value)


def test_nuscenes_sweeps_adds_the_non_key_frames_between_key_frames(tmp_path: Path) -> None:
    root = make_nuscenes_root(tmp_path / "nusc")
    # a keyframes-only dataroot (as ../shared/data's): --sweeps replays the key frames, and says so
    assert any("holds no sweeps between its key frames" in w for w in NuScenesSource(root, sweeps=True).info.warnings)
    path = root / "v1.0-mini" / "sample_data.json"
    sds = json.loads(path.read_text())
    by = {sd["token"]: sd for sd in sds}
    sweep = dict(by["sd0"], token="sw0", is_key_frame=False, sample_token="smp1", timestamp=by["sd0"]["timestamp"] + 250_000,
                 filename="sweeps/LIDAR_TOP/sw0.pcd.bin", prev="sd0", next="sd1")
    by["sd0"]["next"], by["sd1"]["prev"] = "sw0", "sw0"
    write_bin(root / sweep["filename"], np.full((3, 5), 9, dtype=np.float32))
    path.write_text(json.dumps([*by.values(), sweep]))
    keyframes = [f.points[0, 0] for f in NuScenesSource(root).frames()]
    everything = [f.points[0, 0] for f in NuScenesSource(root, sweeps=True).frames()]
    assert keyframes == [0, 1, 2]
    assert everything == [0, 9, 1, 2]
    assert not NuScenesSource(root, sweeps=True).info.warnings


def test_nuscenes_sweeps_resume_at_the_next_key_frame_after_a_missing_row(tmp_path: Path) -> None:
    """A sweep whose ``next`` names a row the table lacks ends that stretch, not the scene: the next key frame
    starts the next one, and the source warns."""
    root = make_nuscenes_root(tmp_path / "nusc", n=4)
    path = root / "v1.0-mini" / "sample_data.json"
    by = {sd["token"]: sd for sd in json.loads(path.read_text())}
    by["sd0"]["next"] = "gone"  # the row after key frame 0 is missing
    path.write_text(json.dumps(list(by.values())))
    src = NuScenesSource(root, sweeps=True)
    assert [f.points[0, 0] for f in src.frames()] == [0, 1, 2, 3]  # until 3 Dec: [0] alone, silently
    assert any("sweep chain breaks" in w for w in src.info.warnings)


def test_a_folder_plays_in_numeric_order_skips_hidden_files_and_reads_each_layout(tmp_path: Path) -> None:
    """``2.bin`` before ``10.bin``; macOS' ``._*`` companions are not scans; a nuScenes ``.pcd.bin`` beside KITTI
    ``.bin`` scans (as ../shared/data/single-frames holds) is read in its own five columns and frame."""
    for k in (1, 2, 10):
        write_bin(tmp_path / f"{k}.bin", np.full((3, 4), k, dtype=np.float32))
    (tmp_path / "._2.bin").write_bytes(b"\x00" * 4096)  # AppleDouble metadata: 256 "points" of zeros
    write_bin(tmp_path / "z.pcd.bin", np.full((2, 5), 7, dtype=np.float32))
    src = BinScanSource(tmp_path)
    frames = list(src.frames())
    assert [f.points[0, 0] for f in frames] == [1, 2, 10, 7]
    assert [f.stamp_ns for f in frames[:3]] == [0, 100 * MS, 200 * MS]
    assert frames[3].points.shape == (2, 5) and frames[3].fields[-1] == "ring" and frames[3].frame_id == "LIDAR_TOP"
    assert frames[0].frame_id == "velodyne" and any("mixes nuScenes" in w for w in src.info.warnings)
    pcd = tmp_path / "pcd"
    pcd.mkdir()
    for k in (3, 20):
        (pcd / f"scan_{k}.pcd").write_text(f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\n"
                                           f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n{k} 0 0\n")
    (pcd / "._scan_3.pcd").write_bytes(b"\x00\x05\x16\x07")
    assert [f.points[0, 0] for f in PcdSource(pcd).frames()] == [3, 20]


def test_a_dataroots_scan_folder_replayed_alone_is_warned_about(tmp_path: Path) -> None:
    """`replay DATAROOT/samples/LIDAR_TOP` (the scans, not the dataroot) published them in LIDAR_TOP's own frame —
    x to the right — at the identity pose without a word about the frame: the detector, which works x-forward,
    got every scan turned by 90°. The warning names the dataroot that replays them right."""
    root = make_nuscenes_root(tmp_path / "nu root")
    src = open_source(str(root / "samples" / "LIDAR_TOP"))
    [warning] = [w for w in src.info.warnings if "LIDAR_TOP's own frame" in w]
    assert f"replay the dataroot {root} instead" in warning
    assert [f.frame_id for f in src.frames()] == ["LIDAR_TOP"] * 3
    loose = tmp_path / "loose"
    write_bin(loose / "a.pcd.bin", np.zeros((2, 5), dtype=np.float32))
    [warning] = [w for w in open_source(str(loose / "a.pcd.bin")).info.warnings if "LIDAR_TOP's own frame" in w]
    assert "replay the dataroot" not in warning
    write_bin(tmp_path / "kitti" / "000000.bin", np.zeros((2, 4), dtype=np.float32))
    assert not open_source(str(tmp_path / "kitti")).info.warnings


def test_kitti_scans_past_the_end_of_times_txt_are_skipped_not_stamped_back_in_time(tmp_path: Path) -> None:
    """times.txt with 3 lines beside 5 scans: scans 3 and 4 took row × 0.1 s (0.3 s, 0.4 s) after the file's 2 s — time
    going back, which the replay then published 1 ns apart. They are frame errors now, as a missing pose is."""
    for k in range(5):
        write_bin(tmp_path / "velodyne" / f"{k:06d}.bin", np.full((3, 4), k, dtype=np.float32))
    (tmp_path / "times.txt").write_text("0.0\n1.0\n2.0\n")
    src = BinScanSource(tmp_path / "velodyne")
    assert any("3 times for scan rows up to 4" in w for w in src.info.warnings), src.info.warnings
    items = list(src.frames())
    assert [f.stamp_ns for f in items[:3]] == [0, 10**9, 2 * 10**9]
    assert all(isinstance(i, FrameError) and "no time for scan row" in i.reason for i in items[3:]) and len(items) == 5


def _lzf_bytewise(data: bytes) -> bytes:
    """liblzf's decoder as its C source reads, one byte at a time: the reference for the copies by repeat."""
    out, ip = bytearray(), 0
    while ip < len(data):
        ctrl = data[ip]
        ip += 1
        if ctrl < 32:
            out += data[ip : ip + ctrl + 1]
            ip += ctrl + 1
            continue
        length = ctrl >> 5
        if length == 7:
            length += data[ip]
            ip += 1
        ref = len(out) - ((ctrl & 0x1F) << 8) - 1 - data[ip]
        ip += 1
        for k in range(length + 2):
            out.append(out[ref + k])
    return bytes(out)


def test_lzf_overlapping_back_references_repeat_their_pattern() -> None:
    """Back references that overlap what they write (distance < length: an organised cloud's empty returns) give
    the bytes a byte-by-byte copy gives, for every distance and length, on seeded random streams."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        stream = bytearray([31]) + rng.integers(0, 256, 32, dtype=np.uint8).tobytes()
        size = 32
        for _ in range(int(rng.integers(1, 12))):
            dist = int(rng.integers(1, min(size, 40) + 1))
            length = int(rng.integers(3, 265))
            field = min(length - 2, 7)
            stream.append((field << 5) | ((dist - 1) >> 8))
            if field == 7:
                stream.append(length - 9)
            stream.append((dist - 1) & 0xFF)
            size += length
        want = _lzf_bytewise(bytes(stream))
        assert len(want) == size
        assert lzf_decompress(bytes(stream), size) == want


def test_a_name_with_a_superscript_digit_sorts_and_does_not_refuse_the_folder(tmp_path: Path) -> None:
    """``scan_1²2.bin``: the superscript is no decimal digit, but ``str.isdigit`` had said it was, and ``int('²')``
    refused the whole folder ("cannot open: ValueError")."""
    write_bin(tmp_path / "scan_2.bin", np.full((2, 4), 2, dtype=np.float32))
    write_bin(tmp_path / "scan_1²2.bin", np.full((2, 4), 1, dtype=np.float32))
    write_bin(tmp_path / "scan_10.bin", np.full((2, 4), 10, dtype=np.float32))
    frames = list(open_source(str(tmp_path)).frames())
    assert [f.points[0, 0] for f in frames] == [1, 2, 10]


def test_a_large_ascii_pcd_is_parsed_without_a_python_string_per_value(tmp_path: Path, monkeypatch) -> None:
    """An ascii PCD's values had been split into one Python string each, all at once: 2 GB for a 5-million-point
    (160 MB) file. Parsed in whole-line chunks, the peak is a few times the file, and every value is read."""
    import tracemalloc

    from jitterguard.services.replay.sources import pcd

    monkeypatch.setattr(pcd, "ASCII_CHUNK_BYTES", 64 << 10, raising=False)
    pts = np.random.default_rng(3).normal(scale=20.0, size=(100_000, 4)).astype(np.float32)
    path = tmp_path / "big.pcd"
    with path.open("w") as fh:
        fh.write("FIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 100000\nHEIGHT 1\nDATA ascii\n")
        np.savetxt(fh, pts, fmt="%.4f")
    size = path.stat().st_size
    tracemalloc.start()
    try:
        got, names, _ = read_pcd(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert names == ("x", "y", "z", "intensity") and got.shape == (100_000, 4)
    assert np.allclose(got, pts, atol=1e-4)
    assert peak < 6 * size, (peak, size)  # about 4x; 12x before
