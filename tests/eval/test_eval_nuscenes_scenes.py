"""`jitterguard eval --nuscenes` over a dataroot of several scenes (as nuScenes' own v1.0-mini and trainval are):
one scene picked by name or token, several pooled as one drive, and a clear exit 2 for what cannot be run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from jitterguard.cli import main
from jitterguard.sim.export import export_scenario
from jitterguard.sim.world import make_scenario

SCENES = ("sim-parking-street-1", "sim-parking-street-2")


@pytest.fixture(scope="module")
def two_scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One nuScenes dataroot holding two exported synthetic scenes (tables merged by token, scans side by side)."""
    base = tmp_path_factory.mktemp("nusc")
    root = base / "both"
    tables: dict[str, dict[str, dict]] = {}
    for seed in (1, 2):
        one = base / f"s{seed}"
        export_scenario(make_scenario("parking-street", seed, duration_s=3.0, rate_hz=10.0), str(one))
        for table in (one / "v1.0-mini").glob("*.json"):
            rows = tables.setdefault(table.name, {})
            for row in json.loads(table.read_text()):
                rows.setdefault(row["token"], row)  # shared tables (category, sensor, …) once
        shutil.copytree(one / "samples", root / "samples", dirs_exist_ok=True)
    (root / "v1.0-mini").mkdir(parents=True)
    for name, rows in tables.items():
        (root / "v1.0-mini" / name).write_text(json.dumps(list(rows.values())))
    return root


def _eval(root: Path, out: Path, *argv: str) -> dict:
    """metrics.json of ``jitterguard eval`` on ``root`` (the noise model unless ``argv`` names an input)."""
    given = ["--input", "gt-noise", "--noise", "jittery"] if "--input" not in argv else []
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--nuscenes", str(root), *given, "--out", str(out), *argv])
    assert exc.value.code == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def pooled_out(two_scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The outputs of ``--scene all`` on the two-scene dataroot."""
    out = tmp_path_factory.mktemp("all") / "out"
    _eval(two_scenes, out, "--scene", "all")
    return out


@pytest.fixture(scope="module")
def pooled(pooled_out: Path) -> dict:
    return json.loads((pooled_out / "metrics.json").read_text())


def test_scene_names_resolve_in_the_order_given(two_scenes: Path) -> None:
    from jitterguard.eval.groundtruth import NuScenesError, nuscenes_scene_names

    token = next(s["token"] for s in json.loads((two_scenes / "v1.0-mini" / "scene.json").read_text())
                 if s["name"] == SCENES[1])
    assert nuscenes_scene_names(two_scenes, "all") == list(SCENES)
    assert nuscenes_scene_names(two_scenes, f"{token}, {SCENES[0]},{SCENES[1]}") == [SCENES[1], SCENES[0]]
    assert nuscenes_scene_names(two_scenes, SCENES[0]) == [SCENES[0]]
    with pytest.raises(NuScenesError, match="2 scenes"):
        nuscenes_scene_names(two_scenes, None)


def test_pooled_scenes_read_each_table_once(two_scenes: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The scenes `eval --scene all` loads are each scene's own (as loaded alone), and the tables only ground truth
    reads are parsed once for all of them (each scene, and listing the scenes, had read them again)."""
    import numpy as np

    from jitterguard.eval.groundtruth import load_nuscenes_frames, nuscenes_scenes
    from jitterguard.services.replay.sources import nuscenes as source

    alone = [load_nuscenes_frames(two_scenes, name) for name in SCENES]
    reads: list[str] = []
    real = source._load_table

    def counted(folder: Path, name: str) -> list[dict]:
        reads.append(name)
        return real(folder, name)

    monkeypatch.setattr(source, "_load_table", counted)
    pooled = nuscenes_scenes(two_scenes, "all")
    assert [name for name, _ in pooled] == list(SCENES)
    for (_, frames), (_, own) in zip(pooled, alone):
        assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in own]
        assert all(np.array_equal(f.centers, g.centers) and f.attributes == g.attributes for f, g in zip(frames, own))
    assert reads.count("sample_annotation") == reads.count("instance") == 1, reads
    assert reads.count("scene") == 1 + len(SCENES), reads  # the listing's, then each scene's replay source's own


def test_several_scenes_pool_as_one_drive(two_scenes: Path, pooled: dict, pooled_out: Path, tmp_path: Path) -> None:
    alone = [_eval(two_scenes, tmp_path / name, "--scene", name, *(["--nuscenes-version", "v1.0-mini"] if i else []))
             for i, name in enumerate(SCENES)]
    assert [m["run"]["scenes"] for m in alone] == [[SCENES[0]], [SCENES[1]]]
    # the table folder is part of what reproduces the run: recorded when given
    assert [m["run"]["nuscenes_version"] for m in alone] == [None, "v1.0-mini"]
    assert pooled["run"]["scenes"] == list(SCENES)
    assert all(name in pooled["run"]["source"] for name in SCENES)
    assert pooled["run"]["frames"] == sum(m["run"]["frames"] for m in alone) == 60
    for group in ("vehicle", "pedestrian"):
        for key in ("n_static", "n_dynamic"):  # every row of both scenes scored once, none merged
            assert pooled["motion"][group][key] == sum(m["motion"][group][key] for m in alone) > 0, (group, key)
    # one drive: the second scene starts with what the first taught the calibration
    blocks = [m["calibration"]["counts"]["blocks"] for m in alone]
    assert pooled["calibration"]["counts"]["blocks"] == sum(blocks) and min(blocks) > 0
    # each scene's own figures: the first ran exactly as alone (both start cold), the second on its own rows
    assert list(pooled["by_run"]) == list(SCENES) and alone[0]["by_run"] is None
    for group in ("vehicle", "pedestrian"):
        first, own = pooled["by_run"][SCENES[0]][group], alone[0]["motion"][group]
        assert {k: first[k] for k in own if k in first} == {k: own[k] for k in own if k in first}
        assert first["ghost_n"] == alone[0]["ghost"][group]["n"]
        assert first["ghost_false_dynamic_speed"] == alone[0]["ghost"][group]["false_dynamic_speed"]
        second = pooled["by_run"][SCENES[1]][group]
        assert second["n_static"] == alone[1]["motion"][group]["n_static"]
        assert second["false_dynamic_speed"] == alone[1]["motion"][group]["false_dynamic_speed"]  # no calibration
    assert f"| {SCENES[1]} | vehicle | {pooled['by_run'][SCENES[1]]['vehicle']['n_static']} |" in \
        (pooled_out / "report.md").read_text()


@pytest.mark.parametrize(("argv", "says"), [
    ([], "2 scenes, pick with --scene"),
    (["--scene", "scene-0523"], "no scene 'scene-0523'"),
    (["--scene", ","], "no scene"),
    (["--scene", "all", "--runs", "2"], "--runs pools noise draws of one scene"),
    (["--scene", "all", "--sweeps"], "--sweeps needs --nuscenes and --input detector"),
])
def test_what_cannot_be_run_is_one_line_exit_2(two_scenes: Path, tmp_path: Path, capsys: pytest.CaptureFixture,
                                               argv: list[str], says: str) -> None:
    earlier = tmp_path / "x" / "run-1.mcap"  # an earlier run's frames: a refused run writes nothing, so keeps them
    earlier.parent.mkdir()
    earlier.write_bytes(b"an earlier run's frames")
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--nuscenes", str(two_scenes), "--input", "gt-noise", "--out", str(tmp_path / "x"), *argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err, err
    assert earlier.read_bytes() == b"an earlier run's frames"  # --runs with several scenes had deleted them
    if not argv:
        assert all(name in err for name in SCENES)  # the message lists what there is to pick


@pytest.fixture(scope="module")
def full_download(two_scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The two-scene dataroot as a full download lists it: after every LIDAR_TOP key frame a non-key sweep (a copy
    of its scan and pose, 50 ms later, in the sample_data chain between the key frames) and a camera image."""
    full = tmp_path_factory.mktemp("full") / "root"
    shutil.copytree(two_scenes, full)
    tables = full / "v1.0-mini"
    data = json.loads((tables / "sample_data.json").read_text())
    poses = json.loads((tables / "ego_pose.json").read_text())
    sensors = json.loads((tables / "sensor.json").read_text())
    calibs = json.loads((tables / "calibrated_sensor.json").read_text())
    sensors.append({"token": "cam-sensor", "channel": "CAM_FRONT", "modality": "camera"})
    calibs.append({**calibs[0], "token": "cam-calib", "sensor_token": "cam-sensor"})
    (full / "sweeps" / "LIDAR_TOP").mkdir(parents=True)
    extra = []
    by_token = {row["token"]: row for row in data}
    for i, row in enumerate(list(data)):
        pose = next(p for p in poses if p["token"] == row["ego_pose_token"])
        for kind, calib, key, name in (("sweep", row["calibrated_sensor_token"], False,
                                        f"sweeps/LIDAR_TOP/{i}.pcd.bin"),
                                       ("cam", "cam-calib", True, f"samples/CAM_FRONT/{i}.jpg")):
            poses.append({**pose, "token": f"{kind}-pose-{i}", "timestamp": pose["timestamp"] + 50_000})
            extra.append({**row, "token": f"{kind}-{i}", "ego_pose_token": f"{kind}-pose-{i}", "is_key_frame": key,
                          "calibrated_sensor_token": calib, "timestamp": row["timestamp"] + 50_000, "filename": name,
                          "fileformat": "jpg" if kind == "cam" else "pcd", "prev": "", "next": ""})
        sweep = extra[-2]  # key frame → its sweep → the next key frame
        sweep["next"], sweep["prev"] = row["next"], row["token"]
        if row["next"]:
            by_token[row["next"]]["prev"] = sweep["token"]
        row["next"] = sweep["token"]
        shutil.copy(full / row["filename"], full / sweep["filename"])
    for name, table in (("sample_data", extra[::-1] + data), ("ego_pose", poses), ("sensor", sensors),
                        ("calibrated_sensor", calibs)):
        (tables / f"{name}.json").write_text(json.dumps(table))
    return full


def test_non_key_sweeps_and_other_channels_change_nothing(full_download: Path, pooled: dict, tmp_path: Path) -> None:
    """A full download's ``sample_data`` also lists the sweeps between key frames and the cameras; the evaluator
    scores the key frames of LIDAR_TOP exactly as in a key-frame-only extract."""
    with_sweeps = _eval(full_download, tmp_path / "with-sweeps", "--scene", "all")
    assert with_sweeps["run"]["frames"] == pooled["run"]["frames"] == with_sweeps["run"]["scans"]
    assert with_sweeps["motion"] == pooled["motion"] and with_sweeps["ghost"] == pooled["ghost"]


@pytest.mark.slow
def test_sweeps_feed_every_scan_and_score_the_key_frames(full_download: Path, tmp_path: Path) -> None:
    """``--sweeps``: the detector, tracker and classifier see every sweep, as the live stack fed by ``replay
    --sweeps`` does; only the labelled key frames are scored (the detection figures are the key frames' own)."""
    argv = ("--scene", SCENES[0], "--input", "detector", "--threads", "2")
    keys = _eval(full_download, tmp_path / "keys", *argv)
    every = _eval(full_download, tmp_path / "every", *argv, "--sweeps")
    assert keys["run"]["sweeps"] is False and every["run"]["sweeps"] is True
    assert every["run"]["frames"] == keys["run"]["frames"] == keys["run"]["scans"] == 30
    assert every["run"]["scans"] == 59  # 30 key frames and the 29 sweeps between them (none after the last)
    assert every["detection"] == keys["detection"]  # scored on the same 30 labelled scans
    assert every["motion"]["vehicle"]["n_static"] > 0
    # the tracker ran at twice the rate: its tracks are not the key-frame run's, yet every row is a key frame's
    assert every["motion"] != keys["motion"]
