"""nuScenes loader: boxes equal nuscenes-devkit's ``get_sample_data`` boxes on the real scene, and a synthetic
export loads back with the boxes ``synthetic_samples`` gives (both training paths agree)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from jitterguard.services.detector.augment import points_in_boxes
from jitterguard.services.detector.config import Sample
from jitterguard.services.detector.data import synthetic_samples
from jitterguard.services.detector.data_nuscenes import (
    nuscenes_class,
    nuscenes_samples,
    scene_of,
    split_holdout,
)
from jitterguard.services.replay.frames import SourceError
from jitterguard.sim.export import export_scenario
from jitterguard.sim.world import make_scenario
from helpers import NUSC

needs_scene = pytest.mark.skipif(not (NUSC / "v1.0-mini" / "scene.json").is_file(),
                                 reason="shared nuScenes scene-0523 not present")


@pytest.fixture(scope="module")
def real() -> list[Sample]:
    return nuscenes_samples(NUSC)


@pytest.fixture(scope="module")
def devkit():
    nuscenes = pytest.importorskip("nuscenes.nuscenes")
    global quaternion_yaw
    from nuscenes.eval.common.utils import quaternion_yaw
    return nuscenes.NuScenes(version="v1.0-mini", dataroot=str(NUSC), verbose=False)


def test_category_mapping() -> None:
    assert [nuscenes_class(c) for c in ("vehicle.car", "vehicle.truck", "vehicle.trailer", "vehicle.construction",
                                        "vehicle.bus.rigid", "vehicle.bus.bendy", "vehicle.bicycle",
                                        "vehicle.motorcycle", "human.pedestrian.adult",
                                        "human.pedestrian.construction_worker")] == [0, 1, 1, 1, 2, 2, 3, 3, 4, 4]
    for dropped in ("movable_object.barrier", "movable_object.trafficcone", "static_object.bicycle_rack",
                    "animal", "vehicle.emergency"):
        assert nuscenes_class(dropped) == -1


def _devkit_sensor_velocity(nusc, sd_token: str, ann_token: str) -> np.ndarray:
    """devkit's box_velocity moved into the loader's frame — the sensor's, turned into the vehicle's axes — by
    devkit's own Box transforms (get_sample_data's boxes carry no velocity)."""
    from nuscenes.utils.data_classes import Box
    from pyquaternion import Quaternion

    ann = nusc.get("sample_annotation", ann_token)
    sd = nusc.get("sample_data", sd_token)
    ego, cs = nusc.get("ego_pose", sd["ego_pose_token"]), nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    box = Box(ann["translation"], ann["size"], Quaternion(ann["rotation"]), velocity=tuple(nusc.box_velocity(ann_token)))
    box.translate(-np.array(ego["translation"]))
    box.rotate(Quaternion(ego["rotation"]).inverse)
    box.translate(-np.array(cs["translation"]))
    return box.velocity[:2]


@needs_scene
def test_boxes_equal_devkit(real: list[Sample], devkit) -> None:
    scene = devkit.scene[0]
    tokens = []
    tok = scene["first_sample_token"]
    while tok:
        tokens.append(tok)
        tok = devkit.get("sample", tok)["next"]
    assert [s.token for s in real] == [f"nuscenes/{scene['name']}/{t}" for t in tokens]
    from pyquaternion import Quaternion

    compared = nan_seen = 0
    for s, tok in zip(real, tokens):
        lidar = devkit.get("sample", tok)["data"]["LIDAR_TOP"]
        _, boxes, _ = devkit.get_sample_data(lidar)
        ref = [b for b in boxes if nuscenes_class(b.name) >= 0]
        mount = Quaternion(devkit.get("calibrated_sensor", devkit.get("sample_data", lidar)["calibrated_sensor_token"])
                           ["rotation"])
        for b in ref:  # devkit's sensor-frame box, turned into the vehicle's axes (the loader's frame)
            b.rotate(mount)
        assert len(ref) == len(s.boxes)
        for b, row, lab, n in zip(ref, s.boxes, s.labels, s.num_points):
            assert lab == nuscenes_class(b.name)
            np.testing.assert_allclose(row[:3], b.center, atol=2e-4)
            np.testing.assert_allclose(row[3:6], [b.wlh[1], b.wlh[0], b.wlh[2]], atol=1e-5)
            # devkit's evaluation heading (the box's forward axis projected on the ground); pyquaternion's
            # yaw_pitch_roll[0] differs from it by ~1e-4 rad where the ego is pitched or rolled
            assert math.cos(row[6] - quaternion_yaw(b.orientation)) > 1 - 1e-8
            v = _devkit_sensor_velocity(devkit, lidar, b.token)
            np.testing.assert_allclose(row[7:9], np.where(np.isnan(v), 0.0, v), atol=1e-4)
            nan_seen += int(np.isnan(v).any())
            assert n == devkit.get("sample_annotation", b.token)["num_lidar_pts"]
            compared += 1
    assert compared > 1000 and 0 < nan_seen < compared / 10


@needs_scene
def test_unscored_objects_are_devkits_other_boxes(real: list[Sample], devkit) -> None:
    """Every annotation of no detector class (barriers, cones, debris) comes with its category and its centre in
    the loader's frame, as nuscenes-devkit's ``get_sample_data`` puts it there; none of them is a target."""
    from pyquaternion import Quaternion

    kinds: set[str] = set()
    for s in real:
        lidar = devkit.get("sample", s.token.rsplit("/", 1)[1])["data"]["LIDAR_TOP"]
        _, boxes, _ = devkit.get_sample_data(lidar)
        mount = Quaternion(devkit.get("calibrated_sensor", devkit.get("sample_data", lidar)["calibrated_sensor_token"])
                           ["rotation"])
        ref = [b for b in boxes if nuscenes_class(b.name) < 0]
        for b in ref:
            b.rotate(mount)
        assert [u[0] for u in s.unscored] == [b.name for b in ref]
        if ref:
            np.testing.assert_allclose([u[1:] for u in s.unscored], [b.center[:2] for b in ref], atol=2e-4)
        kinds |= {b.name for b in ref}
    assert {"movable_object.barrier", "movable_object.trafficcone", "movable_object.debris"} <= kinds


@needs_scene
def test_points_in_boxes_match_num_lidar_pts(real: list[Sample]) -> None:
    counted, stated = [], []
    for s in real[::5]:
        inside = points_in_boxes(s.points, s.boxes).sum(axis=0)
        counted.extend(inside.tolist())
        stated.extend(s.num_points.tolist())
    counted_a, stated_a = np.array(counted), np.array(stated)
    assert stated_a.sum() > 1000
    # the annotators' counts come from the same sweep; boundary points differ by a few percent at most
    assert abs(counted_a.sum() - stated_a.sum()) < 0.05 * stated_a.sum()
    big = stated_a >= 20
    assert np.median(np.abs(counted_a[big] - stated_a[big]) / stated_a[big]) < 0.1


@needs_scene
def test_points_and_holdout(real: list[Sample]) -> None:
    s = real[0]
    assert s.points.dtype == np.float32 and s.points.shape[1] == 4 and len(s.points) > 30000
    assert 0 <= s.points[:, 3].min() and s.points[:, 3].max() <= 255
    train, held = split_holdout(real, last_n=10)
    assert len(train) == 30 and len(held) == 10 and held == real[-10:]
    assert {scene_of(x.token) for x in real} == {"nuscenes/scene-0523"}


def test_split_holdout_per_scene() -> None:
    def smp(tok: str) -> Sample:
        z = np.zeros((0, 9), np.float32)
        return Sample(np.zeros((0, 4), np.float32), z, np.zeros(0, np.int64), np.zeros(0, np.int64), tok)

    xs = [smp(f"a/{i}") for i in range(5)] + [smp(f"b/{i}") for i in range(3)]
    train, held = split_holdout(xs, last_n=2)
    assert [s.token for s in train] == ["a/0", "a/1", "a/2", "b/0"]
    assert [s.token for s in held] == ["a/3", "a/4", "b/1", "b/2"]
    assert split_holdout(xs, last_n=0) == (xs, [])


def test_synthetic_export_loads_back_like_synthetic_samples(tmp_path: Path) -> None:
    sc = make_scenario("intersection", seed=4, duration_s=2.0)
    export_scenario(sc, str(tmp_path))
    loaded = nuscenes_samples(tmp_path)
    direct = list(synthetic_samples(["intersection"], [4], frames_per_scenario=len(sc), duration_s=2.0))
    assert len(loaded) == len(direct) == 20
    moving_checked = 0
    for a, b in zip(loaded, direct):
        np.testing.assert_array_equal(a.points, b.points)
        # the export lists objects instance by instance; sort both by position to compare
        ka, kb = np.lexsort(a.boxes[:, :2].T), np.lexsort(b.boxes[:, :2].T)
        A, B = a.boxes[ka], b.boxes[kb]
        np.testing.assert_allclose(A[:, :6], B[:, :6], atol=1e-4)
        assert (np.cos(A[:, 6].astype(float) - B[:, 6]) > 1 - 1e-9).all()
        np.testing.assert_array_equal(a.labels[ka], b.labels[kb])
        np.testing.assert_array_equal(a.num_points[ka], b.num_points[kb])
        # velocities: a centre difference over 0.1 s frames vs the simulator's true velocity
        fast = np.hypot(B[:, 7], B[:, 8]) > 1.0
        np.testing.assert_allclose(A[fast, 7:9], B[fast, 7:9], atol=0.3)
        moving_checked += int(fast.sum())
    assert moving_checked > 20


def test_bad_dataroot_and_scene(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="not a nuScenes dataroot"):
        nuscenes_samples(tmp_path)
    (tmp_path / "v1.0-mini").mkdir()
    (tmp_path / "v1.0-mini" / "scene.json").write_text(json.dumps([]))
    with pytest.raises(SourceError, match="table missing"):
        nuscenes_samples(tmp_path)


@needs_scene
def test_unknown_scene_is_one_line_error() -> None:
    with pytest.raises(SourceError, match="no scene scene-9999") as exc:
        nuscenes_samples(NUSC, scene_names=["scene-9999"])
    assert "\n" not in str(exc.value)
