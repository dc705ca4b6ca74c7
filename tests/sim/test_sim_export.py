"""Export to a nuScenes dataroot: the official devkit loads it and reads back the ground truth we wrote."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from jitterguard.sim import make_scenario
from jitterguard.sim.export import ATTRIBUTE_TOKENS, export_scenario, nuscenes_tables
from helpers import iter_scans


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory):
    sc = make_scenario("intersection", 2, duration_s=3.0, rate_hz=2.0)
    root = str(tmp_path_factory.mktemp("nusc"))
    sizes = export_scenario(sc, root, seed=1)
    return sc, root, sizes


def test_tables_link_up_and_reexport_is_identical(exported, tmp_path) -> None:
    sc, root, sizes = exported
    assert sizes["sample"] == sc.num_frames == 6 and sizes["scene"] == 1
    anns = json.load(open(os.path.join(root, "v1.0-mini", "sample_annotation.json")))
    by_token = {a["token"]: a for a in anns}
    for a in anns:
        if a["next"]:
            assert by_token[a["next"]]["instance_token"] == a["instance_token"]
            assert by_token[a["next"]]["prev"] == a["token"]
        assert a["attribute_tokens"][0] in ATTRIBUTE_TOKENS.values()
        w, l, h = a["size"]
        assert w <= l or w < 1.0  # nuScenes order: width, length, height
    export_scenario(sc, str(tmp_path), seed=1)
    for name in os.listdir(os.path.join(root, "v1.0-mini")):
        assert open(os.path.join(root, "v1.0-mini", name)).read() == open(
            os.path.join(tmp_path, "v1.0-mini", name)).read()


def test_min_points_filters_annotations() -> None:
    sc = make_scenario("parking-street", 1, duration_s=1.0, rate_hz=2.0)
    pairs = list(iter_scans(sc))
    all_t, _ = nuscenes_tables(sc.name, sc.seed, pairs, sc.categories)
    some, _ = nuscenes_tables(sc.name, sc.seed, pairs, sc.categories, min_points=5)
    assert len(some["sample_annotation"]) < len(all_t["sample_annotation"])
    assert all(a["num_lidar_pts"] >= 5 for a in some["sample_annotation"])


def test_nuscenes_devkit_loads_the_export(exported) -> None:
    nuscenes = pytest.importorskip("nuscenes.nuscenes")
    from nuscenes.utils.data_classes import LidarPointCloud

    sc, root, _ = exported
    nusc = nuscenes.NuScenes(version="v1.0-mini", dataroot=root, verbose=False)
    assert len(nusc.scene) == 1 and len(nusc.sample) == sc.num_frames
    sample = nusc.get("sample", nusc.scene[0]["first_sample_token"])
    frame = None
    k = 0
    while sample:
        frame = sc.frame(k)
        sd = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])
        pc = LidarPointCloud.from_file(nusc.get_sample_data_path(sd["token"]))
        assert pc.points.shape[0] == 4 and pc.points.shape[1] > 20_000
        raw = np.fromfile(nusc.get_sample_data_path(sd["token"]), dtype=np.float32).reshape(-1, 5)
        assert set(np.unique(raw[:, 4]).astype(int)) <= set(range(32))
        pose = nusc.get("ego_pose", sd["ego_pose_token"])
        assert pose["translation"][:2] == pytest.approx([frame.ego_x, frame.ego_y])
        n_ann = 0
        for ann_tok in sample["anns"]:
            ann = nusc.get("sample_annotation", ann_tok)
            n_ann += 1
            box = nusc.get_box(ann_tok)
            assert box.wlh[1] >= box.wlh[0] * 0.9 or box.wlh[1] < 1.0
            attr = nusc.get("attribute", ann["attribute_tokens"][0])["name"]
            assert attr.split(".")[0] in ("vehicle", "pedestrian", "cycle")
        assert n_ann == frame.num_objects
        k += 1
        sample = nusc.get("sample", sample["next"]) if sample["next"] else None
    assert k == sc.num_frames
    # the devkit's velocity estimate from consecutive annotations agrees with the ground truth
    f1 = sc.frame(2)
    checked = 0
    for ann in nusc.sample_annotation:
        if nusc.get("attribute", ann["attribute_tokens"][0])["name"] != "vehicle.moving" or not ann["prev"] \
                or not ann["next"]:
            continue
        s = nusc.get("sample", ann["sample_token"])
        if s["timestamp"] != f1.stamp_ns // 1000:
            continue
        v = nusc.box_velocity(ann["token"])
        inst = [i for i in nusc.instance if i["token"] == ann["instance_token"]][0]
        row = [n for n in range(f1.num_objects) if ann["translation"][0] == pytest.approx(f1.centers[n, 0])
               and ann["translation"][1] == pytest.approx(f1.centers[n, 1])]
        assert len(row) == 1 and inst
        gt = f1.velocities[row[0]]
        assert math.hypot(v[0] - gt[0], v[1] - gt[1]) < 0.15 * math.hypot(*gt) + 0.3
        checked += 1
    assert checked > 0


@pytest.mark.parametrize("duration_s, rate_hz, frames", [(0.96, 10.0, 9), (0.07, 10.0, 0), (0.3, 10.0, 3),
                                                         (0.4, 2.0, 0), (1.0, 0.5, 0), (2.9, 10.0, 29), (0.7, 20.0, 14)])
def test_frame_count_is_whole_frames(duration_s: float, rate_hz: float, frames: int) -> None:
    """One count for the world, the sim CLI's check and the synthetic source's probe: whole frames only (0.96 s at
    10 Hz is 9, not a rounded 10; 0.3 s at 10 Hz is 3 although 0.3 · 10 lands just under 3)."""
    from jitterguard.sim.world import frame_count

    assert frame_count(duration_s, rate_hz) == frames
    if frames:
        assert make_scenario("mixed", 0, duration_s=duration_s, rate_hz=rate_hz).num_frames == frames


def test_export_mounts_the_sensor_at_its_own_height(tmp_path) -> None:
    """The calibrated sensor sits at the exported LiDAR's mount height, not the HDL-32E's 1.84 m: replayed through
    the nuScenes source, the scans' ground lands at world z = 0 (it was 0.66 m below it at a 2.5 m mount)."""
    import dataclasses

    from jitterguard.services.replay.sources.nuscenes import NuScenesSource
    from jitterguard.sim.sensors import hdl32e

    sc = make_scenario("parking-street", 4, duration_s=1.0, rate_hz=2.0)
    export_scenario(sc, str(tmp_path), dataclasses.replace(hdl32e(), mount_height_m=2.5), seed=4)
    calib = json.load(open(tmp_path / "v1.0-mini" / "calibrated_sensor.json"))
    assert calib[0]["translation"] == [0.0, 0.0, 2.5]
    frames = list(NuScenesSource(tmp_path).frames())
    assert len(frames) == 2
    for f in frames:
        assert f.pose.z == pytest.approx(2.5)
        world_z = f.points[:, 2] + f.pose.z  # a level sensor: roll and pitch are zero
        assert np.percentile(world_z, 5) == pytest.approx(0.0, abs=0.1)  # the ground, the lowest returns
