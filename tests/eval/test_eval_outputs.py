"""What ``jitterguard eval`` hands an engineer: report.md says what metrics.json holds, metrics.json's ``run`` block
is enough to run the same evaluation again, and a run that could score nothing is refused before it starts."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
import torch

from jitterguard.cli import main
from jitterguard.eval.cli import evaluate
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.detector.config import LITE
from jitterguard.services.detector.inference import save_weights
from jitterguard.services.detector.network import CenterPointNet
from jitterguard.services.tracker.config import TrackerConfig, load_config

TINY = LITE.model_copy(update=dict(  # test_eval_detector's network: cheap enough for a few scans
    name="tiny", point_cloud_range=(-12.8, -12.8, -3.0, 12.8, 12.8, 3.0), voxel_size=(0.2, 0.2, 6.0),
    pfn_channels=8, backbone_layers=(1, 1, 1), backbone_channels=(8, 16, 16), neck_channels=(8, 8, 8),
    head_channels=8, max_pillars=4000,
))
LATENCIES = (("time_to_first_correct_s_median_z", "never_correct_fraction_z"),
             ("time_to_first_correct_s_median_speed", "never_correct_fraction_speed"),
             ("time_to_dynamic_s_median_z", "never_dynamic_fraction_z"),
             ("time_to_dynamic_s_median_speed", "never_dynamic_fraction_speed"))


def _eval(argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict:
    with pytest.raises(SystemExit) as exc:
        main(["eval", *argv, "--json"])
    assert exc.value.code == 0
    return json.loads(capsys.readouterr().out)


def test_report_latencies_show_the_pairs_that_never_got_there(tmp_path: Path, capsys) -> None:
    """A median time to a decision is over the pairs that reached it: report.md gives, beside it, the share that
    never did, as metrics.json holds it (it had shown 0.200 s for pedestrians 80 % of whom were never called
    dynamic on this run)."""
    out = tmp_path / "ev"
    m = _eval(["--scenario", "parking-street", "--seed", "0", "--duration", "5", "--out", str(out)], capsys)
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]]
            for line in (out / "report.md").read_text().split("\n## ")[0].splitlines() if line.startswith("| ")}
    seen_never = 0
    for g, block in m["motion"].items():
        cells = rows[g][-4:]  # the four latency columns, in LATENCIES' order
        for cell, (time_key, never_key) in zip(cells, LATENCIES):
            t, never = block[time_key], block[never_key]
            assert cell.startswith("—" if t is None else f"{t:.3f}"), (g, time_key, cell)
            if never:
                seen_never += 1
                shown = re.search(r"\((\d+|< 1) % never\)", cell)
                assert shown, (g, never_key, cell)
                if shown.group(1) != "< 1":
                    assert int(shown.group(1)) == round(100 * never), (g, never_key, cell)
            else:
                assert "never" not in cell, (g, never_key, cell)
    assert seen_never  # the run has pairs that never got there (pedestrians: most of them)
    assert m["motion"]["pedestrian"]["never_dynamic_fraction_z"] > 0.5


def test_the_run_block_reruns_the_same_evaluation(tmp_path: Path, capsys) -> None:
    """metrics.json's ``run`` names the seeds, scenario, length and rate as fields, the preset, the tracker file
    (path and hash), the whole classifier and tracker configs and the software; evaluating again from those
    fields alone gives the same motion figures. (The tracker file had been recorded only as its measurement
    scale, the preset not at all, the length and rate only inside a sentence.)"""
    cfg = tmp_path / "tracker.yaml"
    cfg.write_text("measurement_scale: online\nconfirm_hits: 3\n")
    m = _eval(["--scenario", "mixed", "--seed", "4", "--runs", "2", "--duration", "3", "--preset", "hold",
               "--tracker-config", str(cfg), "--out", str(tmp_path / "a")], capsys)
    run = m["run"]
    assert run["seeds"] == [4, 5] and run["scenario"] == "mixed"
    assert run["duration_s"] == 3.0 and run["rate_hz"] == 10.0 and run["preset"] == "hold"
    assert hashlib.sha256(cfg.read_bytes()).hexdigest()[:12] in run["tracker_config"]
    assert str(cfg) in run["tracker_config"]
    assert run["tracker"] == load_config(cfg).model_dump(mode="json")
    assert run["tracker"]["confirm_hits"] == 3
    assert run["classifier"]["dynamic_hold_s_per_class"]  # the preset's hold, in the config recorded
    sw = run["software"]
    assert sw["jitterguard"] and sw["python"] and sw["numpy"] and {"git_commit", "git_dirty"} <= set(sw)
    again = evaluate(tmp_path / "b", scenario=run["scenario"], seed=run["seeds"][0], noise=run["noise"],
                     nuscenes=None, scene=None, duration=run["duration_s"], rate=run["rate_hz"],
                     classifier=ClassifierConfig.model_validate(run["classifier"]),
                     extra_seeds=tuple(run["seeds"][1:]), tracker=TrackerConfig.model_validate(run["tracker"]))
    assert again["motion"] == m["motion"] and again["ghost"] == m["ghost"]
    shipped = _eval(["--scenario", "mixed", "--seed", "4", "--duration", "3", "--out", str(tmp_path / "c")],
                    capsys)["run"]
    assert shipped["tracker_config"] is None and shipped["preset"] is None
    assert shipped["tracker"] == load_config(None).model_dump(mode="json")


def test_the_run_block_records_the_detectors_threads(tmp_path: Path, capsys) -> None:
    """The synthetic runs are deterministic given seeds *and thread count* (results.md): the count is recorded."""
    torch.manual_seed(0)
    weights = tmp_path / "tiny.pt"
    save_weights(weights, CenterPointNet(TINY))
    try:
        m = _eval(["--scenario", "parking-street", "--duration", "0.3", "--input", "detector", "--weights",
                   str(weights), "--threads", "2", "--out", str(tmp_path / "d")], capsys)
    finally:
        torch.set_num_threads(1)
    assert m["run"]["detector"]["threads"] == 2
    assert "torch" in m["run"]["software"]


@pytest.mark.parametrize("argv", [
    ["eval", "--duration", "0.05"],
    ["eval", "--duration", "0.5", "--rate", "1"],
    ["eval-study", "--duration", "0.05"],
])
def test_a_run_of_no_whole_frame_is_refused_before_its_folder(tmp_path: Path, capsys, argv: list[str]) -> None:
    """It had run, scored nothing and written a report of 0 frames, exit 0."""
    out = tmp_path / "x"
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no whole frame" in err[0]
    assert not out.exists()
