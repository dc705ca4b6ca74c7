"""What weights have seen of a real dataroot, read from their metadata and its lineage (provenance.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from jitterguard.services.detector import data_nuscenes
from jitterguard.services.detector.provenance import (
    MAX_LINEAGE,
    adapted_on_scans,
    init_provenance,
    lineage,
    seen_scenes,
)

SCENES = ["scene-0001", "scene-0002", "scene-0523"]


def test_a_held_out_tail_still_makes_every_scene_seen(tmp_path: Path) -> None:
    (tmp_path / "root").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "root")
    meta = {"source": {"nuscenes": str(tmp_path / "root"), "split": None, "holdout_last": 10}}
    assert seen_scenes(meta, tmp_path / "link", SCENES) == SCENES  # another spelling of the same dataroot
    assert seen_scenes(meta, tmp_path, SCENES) == []  # another dataroot
    assert seen_scenes({"source": {"scenarios": ["mixed"]}}, tmp_path / "root", SCENES) == []  # synthetic


def test_split_training_sees_its_split_and_validation_scenes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    splits = {"train": ["scene-0001"], "val": ["scene-0002"]}
    monkeypatch.setattr(data_nuscenes, "official_split", lambda name: splits[name])
    meta = {"source": {"nuscenes": str(tmp_path), "split": "train", "val_split": "val"}}
    assert seen_scenes(meta, tmp_path, SCENES) == ["scene-0001", "scene-0002"]
    assert seen_scenes({"source": {"nuscenes": str(tmp_path), "split": "train"}}, tmp_path, SCENES) == ["scene-0001"]

    def unknown(name: str) -> list[str]:
        raise ValueError(name)

    monkeypatch.setattr(data_nuscenes, "official_split", unknown)  # cannot tell which: every scene counts as seen
    assert seen_scenes(meta, tmp_path, SCENES) == SCENES


def test_a_fine_tune_keeps_what_its_init_saw(tmp_path: Path) -> None:
    """``train --init W`` on synthetic scans: W's nuScenes training and adaptation stay on record, generations back."""
    real = {"source": {"nuscenes": str(tmp_path), "holdout_last": 10}, "epochs": 3, "command": "jitterguard train"}
    adapted = {"source": {"scenarios": ["mixed"]}, "unlabelled_scans": [{"recording": f"{tmp_path}#scene-0523"}]}
    assert init_provenance({"epochs": 3, "command": "x"}) is None  # nothing to carry
    child = {"source": {"scenarios": ["mixed"]}, "init_provenance": init_provenance(real)}
    grandchild = {"source": {"scenarios": ["mixed"]}, "init_provenance": init_provenance(child)}
    assert init_provenance(real) == {"source": real["source"]}
    assert seen_scenes(grandchild, tmp_path, SCENES) == SCENES and not adapted_on_scans(grandchild, tmp_path)
    after_adapt = {"source": {"scenarios": ["mixed"]}, "init_provenance": init_provenance(adapted)}
    assert adapted_on_scans(after_adapt, tmp_path) and seen_scenes(after_adapt, tmp_path, SCENES) == []
    assert not adapted_on_scans(after_adapt, tmp_path / "other")


def test_a_lineage_that_nests_without_end_is_read_to_a_bound() -> None:
    meta: dict = {}
    meta["init_provenance"] = meta  # a hand-edited or corrupt file
    assert len(list(lineage(meta))) == MAX_LINEAGE
    assert list(lineage({"init_provenance": "junk"})) == [{"init_provenance": "junk"}]


def test_scans_read_from_inside_a_dataroot_count_as_adapted_on_it(tmp_path: Path) -> None:
    """``adapt --scans DATAROOT/samples/LIDAR_TOP`` (or one of its files) reads the key frames ``eval-detector
    --nuscenes DATAROOT`` scores; only the dataroot itself had been recognised, so such a score went unflagged."""
    root = tmp_path / "nuscenes"
    lidar = root / "samples" / "LIDAR_TOP"
    lidar.mkdir(parents=True)
    (tmp_path / "nuscenes-other").mkdir()
    (tmp_path / "link").symlink_to(lidar)
    for recording in (lidar, lidar / "n008__LIDAR_TOP__1.pcd.bin", tmp_path / "link", f"{root}#scene-0523"):
        meta = {"unlabelled_scans": [{"recording": str(recording), "scans": 1}]}
        assert adapted_on_scans(meta, root), recording
        assert not adapted_on_scans(meta, tmp_path / "nuscenes-other"), recording  # a sibling, not a parent
    assert not adapted_on_scans({"unlabelled_scans": [{"recording": str(tmp_path)}]}, root)  # the folder above
