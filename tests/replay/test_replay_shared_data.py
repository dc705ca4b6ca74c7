"""Readers on the real recordings in ../shared/data (skipped when that folder is absent).

The nuScenes reader reads the JSON tables itself; here it must agree with nuscenes-devkit (when installed)
on every key frame: file, timestamp and the LiDAR's world pose built from devkit's own records.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jitterguard.services.replay.frames import ScanFrame
from jitterguard.services.replay.sources import open_source

from helpers import NUSC, SHARED_DATA

KITTI = SHARED_DATA / "kitti-velodyne-6"
SINGLE = SHARED_DATA / "single-frames"

needs_nusc = pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
needs_kitti = pytest.mark.skipif(not KITTI.is_dir(), reason="../shared/data/kitti-velodyne-6 absent")


@needs_nusc
def test_nuscenes_scene_reads_40_keyframes_of_about_34k_points() -> None:
    src = open_source(str(NUSC))
    frames = list(src.frames())
    assert len(frames) == 40 and all(isinstance(f, ScanFrame) for f in frames)
    stamps = [f.stamp_ns for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert all(30_000 < f.points.shape[0] < 40_000 for f in frames)
    assert frames[0].fields == ("x", "y", "z", "intensity", "ring")
    # the LiDAR sits ~1.84 m above the ego origin, which nuScenes puts on the ground
    assert all(1.5 < f.pose.z < 2.2 for f in frames)


@needs_nusc
def test_nuscenes_reader_agrees_with_devkit() -> None:
    nuscenes = pytest.importorskip("nuscenes.nuscenes", reason="nuscenes-devkit not installed")
    from pyquaternion import Quaternion

    nusc = nuscenes.NuScenes(version="v1.0-mini", dataroot=str(NUSC), verbose=False)
    scene = nusc.scene[0]
    want = []
    token = scene["first_sample_token"]
    while token:
        sample = nusc.get("sample", token)
        sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        ego = nusc.get("ego_pose", sd["ego_pose_token"])
        cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
        q = Quaternion(ego["rotation"]) * Quaternion(cs["rotation"])  # devkit's sensor → world
        t = np.array(ego["translation"]) + Quaternion(ego["rotation"]).rotate(np.array(cs["translation"]))
        want.append((sd["filename"], sd["timestamp"] * 1000, t, q, Quaternion(ego["rotation"])))
        token = sample["next"]
    frames = list(open_source(str(NUSC)).frames())
    assert len(frames) == len(want)
    for f, (fname, stamp, t, q, q_ego) in zip(frames, want):
        assert f.origin.endswith(fname) and f.stamp_ns == stamp
        np.testing.assert_allclose([f.pose.x, f.pose.y, f.pose.z], t, atol=1e-9)
        # published in the vehicle's axes at the LiDAR: the pose turns like the ego, and pose ∘ point is devkit's
        # world point of the raw return (ego_pose ∘ calibrated_sensor ∘ p)
        np.testing.assert_allclose(f.pose.matrix()[:3, :3], q_ego.rotation_matrix, atol=1e-9)
        pts = np.fromfile(NUSC / fname, dtype=np.float32).reshape(-1, 5)
        raw = pts[np.isfinite(pts[:, :3]).all(axis=1)]
        np.testing.assert_array_equal(f.points[:, 3:], raw[:, 3:])
        world = f.points[:, :3].astype(np.float64) @ f.pose.matrix()[:3, :3].T + t
        np.testing.assert_allclose(world, raw[:, :3].astype(np.float64) @ q.rotation_matrix.T + t, atol=2e-5)


@needs_kitti
def test_kitti_six_scans_read_with_identity_pose_and_10hz() -> None:
    frames = list(open_source(str(KITTI)).frames())
    assert len(frames) == 6 and all(isinstance(f, ScanFrame) for f in frames)
    assert [f.stamp_ns for f in frames] == [i * 100_000_000 for i in range(6)]
    assert all(100_000 < f.points.shape[0] < 150_000 and f.points.shape[1] == 4 for f in frames)
    assert all(f.pose.x == 0 and f.pose.qw == 1 for f in frames)


@pytest.mark.skipif(not SINGLE.is_dir(), reason="../shared/data/single-frames absent")
def test_single_frames_pick_their_column_count_from_the_name() -> None:
    files = {p.name: p for p in SINGLE.iterdir()}
    nusc = next(p for n, p in files.items() if n.endswith(".pcd.bin"))
    kitti = next(p for n, p in files.items() if n.endswith(".bin") and not n.endswith(".pcd.bin"))
    [fn] = list(open_source(str(nusc)).frames())
    [fk] = list(open_source(str(kitti)).frames())
    assert fn.points.shape[1] == 5 and fk.points.shape[1] == 4
    assert fn.points.shape[0] * 20 == Path(nusc).stat().st_size


@needs_nusc
def test_a_malformed_annotation_costs_the_ground_truth_not_the_scans(tmp_path: Path) -> None:
    """One annotation row with a null translation: the labels cannot be built, but the scans read fine. Its
    TypeError had left the first pass ("reading failed after frame 0"), so not one scan was published."""
    import json
    import shutil

    from jitterguard.services.replay.runner import ReplayPlan, run_replay

    root = tmp_path / "nusc"
    shutil.copytree(NUSC / "v1.0-mini", root / "v1.0-mini")
    (root / "samples").symlink_to((NUSC / "samples").resolve())
    table = root / "v1.0-mini" / "sample_annotation.json"
    rows = json.loads(table.read_text())
    rows[0]["translation"] = None
    table.write_text(json.dumps(rows))
    with open_source(str(root)) as src:
        got: list[tuple[int, object]] = []
        stats = run_replay(src, ReplayPlan(rate=None), lambda f, seq, _stamp: got.append((seq, f.truth)))
    assert stats.errors == 0 and stats.published == 40
    assert [seq for seq, _ in got] == list(range(40)) and all(truth is None for _, truth in got)


@needs_nusc
@pytest.mark.parametrize("inner", ["v1.0-mini", "samples"])
def test_a_folder_inside_a_nuscenes_dataroot_is_refused_naming_the_dataroot(inner: str) -> None:
    """Its table folder had been refused as holding "no nuScenes tables" — the very tables it holds."""
    import re

    from jitterguard.services.replay.frames import SourceError

    with pytest.raises(SourceError, match=re.escape(f"inside the nuScenes dataroot {NUSC}: give the dataroot as SOURCE")):
        open_source(str(NUSC / inner))
