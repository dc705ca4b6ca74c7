"""The offline pipeline end to end: determinism, both classifier rules on identical inputs, the CLI's files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jitterguard.cli import main
from jitterguard.eval.pipeline import NOISE_PRESETS, run_pipeline
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import DYNAMIC, STATIC, UNDECIDED
from jitterguard.sim.world import make_scenario

NUSC = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "nuscenes-scene-0523"
GROUP_KEYS = ("ap_z", "ap_speed", "false_dynamic_z", "false_dynamic_speed", "missed_dynamic_z",
              "missed_dynamic_speed", "n_static", "n_dynamic")


@pytest.fixture(scope="module")
def records():
    sc = make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0)
    return run_pipeline(sc, NOISE_PRESETS["jittery"](), 3, ClassifierConfig())


def test_pipeline_is_deterministic(records) -> None:
    again = run_pipeline(make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0),
                         NOISE_PRESETS["jittery"](), 3, ClassifierConfig())
    for k, v in records.__dict__.items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(v, getattr(again, k), err_msg=k)
    other = run_pipeline(make_scenario("parking-street", 3, duration_s=5.0, rate_hz=10.0),
                         NOISE_PRESETS["jittery"](), 4, ClassifierConfig())
    assert len(other) != len(records) or not np.array_equal(other.z, records.z)


def test_both_rules_decide_identical_rows(records) -> None:
    assert len(records) > 100
    assert (records.gt_instance >= 0).mean() > 0.8  # most tracks sit on a real object
    decided = records.window >= records.min_window
    z_dyn = records.state_z == DYNAMIC
    np.testing.assert_array_equal(z_dyn[decided], records.z[decided] > records.alpha[decided])
    assert (records.state_z[~decided] == UNDECIDED).all()
    np.testing.assert_array_equal(records.state_v == DYNAMIC, records.speed > records.velocity_threshold)
    assert set(np.unique(records.state_v)) <= {STATIC, DYNAMIC}
    # GT labels are both present in this scenario (parked cars, moving traffic)
    veh = records.group == "vehicle"
    assert records.gt_dynamic[veh].any() and (~records.gt_dynamic[veh]).any()


def test_cli_writes_report_metrics_and_figures(tmp_path: Path, capsys) -> None:
    out = tmp_path / "ev"
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--scenario", "parking-street", "--seed", "1", "--duration", "5", "--noise", "clean",
              "--input", "gt-noise", "--out", str(out), "--json"])
    assert exc.value.code == 0
    printed = json.loads(capsys.readouterr().out)
    on_disk = json.loads((out / "metrics.json").read_text())
    assert printed == on_disk
    for g in ("vehicle", "pedestrian"):
        for k in GROUP_KEYS:
            assert k in on_disk["motion"][g], (g, k)
    assert on_disk["motion"]["vehicle"]["ap_z"] > 0.9  # clean noise: motion is easy to see
    for name in ("report.md", "speed_vs_z.png", "pr_curves.png", "alpha_sweep.png"):
        assert (out / name).stat().st_size > 0
    assert "| vehicle |" in (out / "report.md").read_text()


@pytest.mark.parametrize("argv", [
    ["--input", "detector", "--noise", "clean"],
    ["--input", "lidar"],
    ["--noise", "loud"],
    ["--scenario", "moon"],
    ["--nuscenes", "/nonexistent/dataroot"],
])
def test_cli_bad_input_is_one_line_exit_2(tmp_path: Path, capsys, argv: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["eval", "--out", str(tmp_path / "x"), *argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    if "detector" in argv:
        assert "--noise applies to --input gt-noise" in err


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_nuscenes_scene_loads_and_scores(tmp_path: Path) -> None:
    from jitterguard.eval.groundtruth import load_nuscenes_frames
    from jitterguard.eval.metrics import compute_metrics

    name, frames = load_nuscenes_frames(NUSC)
    assert name == "scene-0523" and len(frames) >= 30
    f = frames[0]
    assert f.num_objects > 0 and (f.sizes[:, 0] >= f.sizes[:, 1] - 1e-6).mean() > 0.8  # (length, width, h)
    rec = run_pipeline(frames, NOISE_PRESETS["clean"](), 0, ClassifierConfig())
    m = compute_metrics(rec)
    assert m["vehicle"]["n_static"] > 0 and m["vehicle"]["n_dynamic"] > 0
    assert m["vehicle"]["ap_z"] is not None and m["vehicle"]["ap_z"] > 0.8


def test_pooled_runs_keep_tracks_apart(records) -> None:
    from jitterguard.eval.pipeline import concat_records

    pooled = concat_records([records, records], ["0", "1"])
    assert len(pooled) == 2 * len(records)
    n_tracks = len(np.unique(records.track_id))
    assert len(np.unique(pooled.track_id)) == 2 * n_tracks  # same IDs in both runs, never merged
    np.testing.assert_array_equal(pooled.z[: len(records)], records.z)
