"""Stacked sweeps (services/detector/sweeps.py): the geometry, the live stacker's history rules, the nuScenes loader
and the live path agreeing on one dataroot, and a five-field model fed through every path."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from jitterguard.geometry import quaternion_from_yaw, rotation_from_quaternion
from jitterguard.services.detector.config import PRESETS
from jitterguard.services.detector.data_nuscenes import NuScenesKeyframes
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.network import CenterPointNet
from jitterguard.services.detector.sweeps import (DEFAULT_SWEEPS, SweepStacker, pose_matrices, relative_transform,
                                                  sweeps_of)
from jitterguard.services.replay.frames import ScanFrame
from jitterguard.services.replay.sources.nuscenes import NuScenesSource

MS = 1_000_000


def _random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    q = rng.normal(size=4)
    return rotation_from_quaternion(*q), rng.uniform(-50, 50, size=3)


def _seen_from(world: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """World points in the frame of a sensor at (rotation, translation), with an intensity column."""
    local = (world - translation) @ rotation  # R^T (p - t), row-wise
    return np.column_stack([local, np.full(len(world), 7.0)]).astype(np.float32)


def test_a_static_world_point_stacks_onto_itself_whatever_the_poses() -> None:
    rng = np.random.default_rng(0)
    world = rng.uniform(-30, 30, size=(50, 3))
    r_new, t_new = _random_pose(rng)
    r_old, t_old = _random_pose(rng)
    rot, trans = relative_transform(r_new, t_new, r_old, t_old)
    old = _seen_from(world, r_old, t_old)
    moved = old[:, :3].astype(np.float64) @ rot.T + trans
    np.testing.assert_allclose(moved, _seen_from(world, r_new, t_new)[:, :3], atol=1e-4)


def test_the_stacker_gives_each_sweep_its_lag_and_keeps_to_the_window() -> None:
    rng = np.random.default_rng(1)
    world = rng.uniform(5, 30, size=(20, 3))
    st = SweepStacker(sweeps=3, max_lag_s=0.55)
    poses = [pose_matrices((i * 0.7, 0.1 * i, 1.8), quaternion_from_yaw(0.05 * i)) for i in range(6)]
    for i, (r, t) in enumerate(poses):
        st.add(i * 100 * MS, r, t, _seen_from(world, r, t))
    assert len(st) == 3  # bounded by sweeps
    r, t = poses[5]
    out = st.stack(500 * MS, r, t, _seen_from(world, r, t))
    # the newest (lag 0) plus two earlier ones, newest first: 0.1 s and 0.2 s
    assert out.shape == (60, 5) and st.last_stacked == 3
    np.testing.assert_allclose(out[:, 4], np.repeat([0.0, 0.1, 0.2], 20), atol=1e-6)
    # every sweep of the static points lands on the newest scan's view of them
    np.testing.assert_allclose(out[:, :3], np.tile(_seen_from(world, r, t)[:, :3], (3, 1)), atol=1e-3)
    np.testing.assert_allclose(out[:, 3], 7.0)


def test_older_than_the_lag_is_left_out_and_a_rewind_clears_the_history() -> None:
    pts = np.array([[10.0, 0.0, 0.0, 1.0]], np.float32)
    eye, zero = np.eye(3), np.zeros(3)
    st = SweepStacker(sweeps=10, max_lag_s=0.35)
    for ms in (0, 100, 200, 300, 400):
        st.add(ms * MS, eye, zero, pts)
    lags = st.stack(400 * MS, eye, zero, pts)[:, 4]
    np.testing.assert_allclose(lags, [0.0, 0.1, 0.2, 0.3], atol=1e-6)  # 0.4 s is beyond the lag
    st.add(400 * MS, eye, zero, pts * 2)  # the same scan again: the first copy stays
    assert len(st) == 5 and st.resets == 0
    st.add(50 * MS, eye, zero, pts)  # time went back (a replay rewound)
    assert st.resets == 1 and len(st) == 1
    assert st.stack(60 * MS, eye, zero, pts)[:, 4].tolist() == pytest.approx([0.0, 0.01])


@pytest.mark.parametrize("position, yaw", [((1000.0, 0.0, 0.0), 0.0), ((6.0, 0.0, 0.0), 0.0), ((0.5, 0.0, 0.0), 3.0)])
def test_a_pose_that_jumps_clears_the_history(position: tuple, yaw: float) -> None:
    """A relocalisation 50 ms after the last scan (1 km, 6 m: faster than a vehicle drives; a heading turned by
    3 rad): the earlier sweep had been stacked across it — a kilometre off, out of range and yet counted as a sweep
    of the input; metres off, a ghost copy of the scene."""
    pts = np.array([[10.0, 0.0, 0.0, 1.0]], np.float32)
    st = SweepStacker(sweeps=2)
    st.add(0, *pose_matrices((0.0, 0.0, 0.0), quaternion_from_yaw(0.0)), pts)
    r, t = pose_matrices(position, quaternion_from_yaw(yaw))
    st.add(50 * MS, r, t, pts)
    assert st.resets == 1 and len(st) == 1
    assert st.stack(50 * MS, r, t, pts).shape == (1, 5) and st.last_stacked == 1
    # driving on from there (20 m/s, turning at 0.5 rad/s) stacks again
    r2, t2 = pose_matrices(np.add(position, (1.0, 0.0, 0.0)), quaternion_from_yaw(yaw + 0.025))
    st.add(100 * MS, r2, t2, pts)
    assert st.resets == 1 and st.stack(100 * MS, r2, t2, pts).shape == (2, 5) and st.last_stacked == 2


def test_earlier_sweeps_lose_their_own_body_returns_the_newest_keeps_them() -> None:
    near = np.array([[0.5, 0.2, 0.0, 1.0], [8.0, 0.0, 0.0, 1.0]], np.float32)
    eye, zero = np.eye(3), np.zeros(3)
    st = SweepStacker(sweeps=2, min_range_m=1.0)
    st.add(0, eye, zero, near)
    st.add(50 * MS, eye, zero, near)
    out = st.stack(50 * MS, eye, zero, near)
    assert out.shape == (3, 5) and out[:, 4].tolist() == pytest.approx([0.0, 0.0, 0.05])


def test_one_sweep_holds_nothing_and_gives_a_zero_lag_column() -> None:
    st = SweepStacker(sweeps=1)
    pts = np.ones((4, 4), np.float32)
    st.add(0, np.eye(3), np.zeros(3), pts)
    st.add(50 * MS, np.eye(3), np.zeros(3), pts)
    assert len(st) == 0
    out = st.stack(50 * MS, np.eye(3), np.zeros(3), pts)
    assert out.shape == (4, 5) and not out[:, 4].any()


@pytest.mark.parametrize("kwargs", [{"sweeps": 0}, {"sweeps": 2, "max_lag_s": 0.0}])
def test_bad_stacker_settings_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        SweepStacker(**kwargs)


def test_sweeps_of_reads_the_weights_metadata() -> None:
    assert sweeps_of(4, {"source": {"sweeps": 10}}) == 1  # a four-field model reads no lag
    assert sweeps_of(5, {"source": {"sweeps": 6}}) == 6
    assert sweeps_of(5, {}) == DEFAULT_SWEEPS
    assert sweeps_of(5, {"source": {"sweeps": "x"}}) == DEFAULT_SWEEPS


# ------------------------------------------------------------------------- the loader and the live path agree


def _quat_wxyz(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def _write_bin(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    arr.astype(np.float32).tofile(path)


def _dataroot_with_sweeps(root: Path, n: int = 5) -> Path:
    """One scene: LIDAR_TOP sample_data 50 ms apart (every other one a key frame), the ego driving and turning,
    the sensor mounted turned −90° and 1.8 m up, each scan a few points of random geometry."""
    tables = root / "v1.0-mini"
    tables.mkdir(parents=True)
    rng = np.random.default_rng(3)
    calib = [{"token": "c", "sensor_token": "s", "translation": [1.0, 0.2, 1.8], "rotation": _quat_wxyz(-math.pi / 2),
              "camera_intrinsic": []}]
    samples, sds, egos = [], [], []
    keys = [i for i in range(n) if i % 2 == 0]
    for i in range(n):
        ts = 1_500_000_000_000_000 + i * 50_000
        egos.append({"token": f"e{i}", "timestamp": ts, "translation": [10.0 + 0.6 * i, 20.0 + 0.1 * i, 0.0],
                     "rotation": _quat_wxyz(0.3 + 0.04 * i)})
        key = i in keys
        fname = f"{'samples' if key else 'sweeps'}/LIDAR_TOP/s{i}.pcd.bin"
        k = keys.index(i) if key else None
        sample_tok = f"smp{k}" if key else f"smp{min(j for j in keys if j > i) // 2}"
        sds.append({"token": f"sd{i}", "sample_token": sample_tok, "ego_pose_token": f"e{i}",
                    "calibrated_sensor_token": "c", "timestamp": ts, "fileformat": "pcd", "is_key_frame": key,
                    "filename": fname, "prev": f"sd{i-1}" if i else "", "next": f"sd{i+1}" if i < n - 1 else ""})
        pts = np.column_stack([rng.uniform(-20, 20, size=(30, 3)), rng.uniform(0, 50, 30), np.zeros(30)])
        _write_bin(root / fname, pts)
        if key:
            samples.append({"token": f"smp{k}", "timestamp": ts, "scene_token": "scn",
                            "prev": f"smp{k-1}" if k else "", "next": f"smp{k+1}" if i + 2 < n else ""})
    scene = [{"token": "scn", "log_token": "log", "nbr_samples": len(keys), "first_sample_token": "smp0",
              "last_sample_token": f"smp{len(keys) - 1}", "name": "scene-0001", "description": ""}]
    for name, table in {"scene": scene, "sample": samples, "sample_data": sds, "ego_pose": egos,
                        "calibrated_sensor": calib, "sensor": [{"token": "s", "channel": "LIDAR_TOP",
                                                                 "modality": "lidar"}],
                        "sample_annotation": [], "instance": [], "category": []}.items():
        (tables / f"{name}.json").write_text(json.dumps(table))
    return root


def test_the_loader_and_a_live_stream_of_the_same_dataroot_stack_alike(tmp_path: Path) -> None:
    root = _dataroot_with_sweeps(tmp_path / "nusc")
    loader = NuScenesKeyframes(root, sweeps=3)
    assert len(loader) == 3
    live = SweepStacker(sweeps=3)
    stacks = []
    for f in NuScenesSource(root, sweeps=True).frames():  # what `jitterguard replay DATAROOT --sweeps` publishes
        assert isinstance(f, ScanFrame)
        p = f.pose
        r, t = pose_matrices((p.x, p.y, p.z), (p.qx, p.qy, p.qz, p.qw))
        pts = np.ascontiguousarray(f.points[:, :4])
        live.add(f.stamp_ns, r, t, pts)
        stacks.append(live.stack(f.stamp_ns, r, t, pts))
    assert len(stacks) == 5
    for k, i in enumerate((0, 2, 4)):  # key frames are sample_data 0, 2, 4
        want = loader.points(k)
        assert want.shape[1] == 5 and want.shape == stacks[i].shape
        np.testing.assert_allclose(stacks[i], want, atol=2e-4)
    assert sorted(set(np.round(loader.points(2)[:, 4], 3))) == [0.0, 0.05, 0.1]


# ------------------------------------------------------------------------------------- a five-field model


@pytest.fixture(scope="module")
def five_field() -> Detector:
    torch.manual_seed(0)
    net = CenterPointNet(PRESETS["lite"].model_copy(update={"num_point_features": 5}))
    return Detector(net, meta={"source": {"sweeps": 4}}, threads=1, score_threshold=0.05)


def test_a_five_field_model_takes_a_bare_scan_as_the_newest_sweep_alone(five_field: Detector) -> None:
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-30, 30, (3000, 2)), rng.uniform(-1.5, 0.5, 3000),
                           rng.uniform(0, 60, 3000)]).astype(np.float32)
    assert five_field.sweeps == 4
    bare = five_field.detect(pts)
    padded = five_field.detect(np.column_stack([pts, np.zeros(len(pts), np.float32)]))
    assert len(bare) == len(padded) > 0
    np.testing.assert_array_equal(bare.boxes, padded.boxes)
    lagged = five_field.detect(np.column_stack([pts, np.full(len(pts), 0.3, np.float32)]))
    assert not np.array_equal(lagged.scores, bare.scores)  # the lag column is read


def test_the_evaluator_stacks_each_scan_with_the_earlier_ones_of_its_stream() -> None:
    from jitterguard.eval.detector_input import detector_frames, synthetic_scans
    from jitterguard.services.detector.config import Detections3D
    from jitterguard.sim.world import make_scenario

    seen: list[np.ndarray] = []

    def detect(points: np.ndarray) -> Detections3D:
        seen.append(points)
        return Detections3D.empty(True)

    scans = list(synthetic_scans(make_scenario("parking-street", 0, duration_s=0.5, rate_hz=10.0), 0))
    frames = list(detector_frames(scans, detect, sweeps=3))
    assert len(frames) == len(scans) == len(seen) == 5
    lags = [sorted(np.unique(np.round(p[:, 4].astype(np.float64), 3)).tolist()) for p in seen]
    assert lags == [[0.0], [0.0, 0.1], [0.0, 0.1, 0.2], [0.0, 0.1, 0.2], [0.0, 0.1, 0.2]]
    assert all(p.shape[1] == 5 for p in seen)
    # without sweeps the network gets each scan's own four fields
    seen.clear()
    list(detector_frames(scans, detect))
    assert all(p.shape[1] == 4 for p in seen)
