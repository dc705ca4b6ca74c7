"""`jitterguard train` / `eval-detector`: flags, exit-2 one-liners, and a tiny real run end to end."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from jitterguard.services.detector.inference import load_weights
from jitterguard.services.detector.train_cli import parse_seeds


def _jg(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})


def test_parse_seeds_ranges_and_lists() -> None:
    assert parse_seeds("0-3,7,2", "--x") == [0, 1, 2, 3, 7]
    assert parse_seeds("5", "--x") == [5]


@pytest.mark.parametrize("args, flag", [
    (["train", "--out", "OUT", "--train-seeds", "9-2"], "--train-seeds"),
    (["train", "--out", "OUT", "--train-seeds", "0-4", "--val-seeds", "3"], "--val-seeds"),
    (["train", "--out", "OUT", "--scenarios", "moon"], "--scenarios"),
    (["train", "--out", "OUT", "--preset", "huge"], "--preset"),
    (["train", "--out", "OUT", "--init", "/nonexistent.pt"], "--init"),
    (["train", "--out", "OUT", "--distill-from", "/nonexistent.pt"], "--distill-from"),
    (["train", "--out", "OUT", "--distill-from", "SHIPPED", "--distill-classes", "moped"], "--distill-classes"),
    (["train", "--out", "OUT", "--distill-weight", "2"], "--distill-classes/--distill-weight: only with"),
    (["train", "--out", "OUT", "--distill-from", "SHIPPED", "--preset", "paper"], "--distill-from: the teacher's"),
    # --init fixes the network: a --preset of another architecture had been ignored without a word
    (["train", "--out", "OUT", "--init", "SHIPPED", "--preset", "paper"], "--preset: 'paper' contradicts --init"),
    (["eval-detector", "--out", "OUT", "--weights", "/nonexistent.pt"], "--weights"),
    (["eval-detector", "--out", "OUT", "--seeds", "x"], "--seeds"),
    (["eval-detector", "--out", "OUT", "--effects", "fog"], "--effects"),
    (["eval-detector", "--out", "OUT", "--effects", "none+random"], "--effects"),
    (["eval-detector", "--out", "OUT", "--sweeps", "3"], "--sweeps"),
    (["train", "--out", "OUT", "--gt-sample", "--gt-sample-count", "moped=2"], "--gt-sample-count"),
    (["train", "--out", "OUT", "--gt-sample", "--gt-sample-count", "car=-1"], "--gt-sample-count"),
    (["train", "--out", "OUT", "--gt-sample-count", "bicycle=0"], "--gt-sample-count"),
    (["train", "--out", "OUT", "--level-scans", "--gt-sample"], "--level-scans: not with --gt-sample"),
    (["recalibrate-detector", "--out", "OUT", "--weights", "/nonexistent.pt"], "--weights"),
    (["recalibrate-detector", "--out", "OUT", "--weights", "SHIPPED", "--effects", "fog"], "--effects"),
    (["recalibrate-detector", "--out", "OUT", "--weights", "SHIPPED", "--seeds", "5-1"], "--seeds"),
    # the detector's hold-out seeds (1000+) never fit weights nor their recalibration
    (["recalibrate-detector", "--out", "OUT", "--weights", "SHIPPED", "--seeds", "990-1000"], "--seeds"),
    (["train", "--out", "OUT", "--train-seeds", "1000-1004"], "--train-seeds"),
    (["train", "--out", "OUT", "--val-seeds", "1003"], "--val-seeds"),
    (["adapt", "--out", "OUT", "--weights", "SHIPPED", "--scans", "SHIPPED", "--synthetic-seeds", "1000"],
     "--synthetic-seeds"),
    (["adapt", "--out", "OUT", "--weights", "SHIPPED", "--scans", "SHIPPED", "--recalibration-seeds", "0-1001"],
     "--recalibration-seeds"),
    # one scan cannot fill the two micro-batches of a step: refused before any scan is cast, not a traceback
    (["train", "--out", "OUT", "--scenarios", "parking-street", "--train-seeds", "0", "--frames-per-scenario", "1",
      "--accumulate", "2"], "--train-seeds"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: list[str], flag: str) -> None:
    from jitterguard.services.detector.inference import shipped_weights

    subst = {"OUT": str(tmp_path / "o"), "SHIPPED": str(shipped_weights("lite"))}
    res = _jg(*[subst.get(a, a) for a in args], timeout=120)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and flag in lines[0]


@pytest.mark.slow
def test_tiny_training_run_writes_weights_history_and_report(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = _jg("train", "--out", str(out), "--scenarios", "parking-street", "--train-seeds", "0",
              "--val-seeds", "1", "--frames-per-scenario", "2", "--epochs", "1", "--batch-size", "2",
              "--threads", "1", "--progress")
    assert res.returncode == 0, res.stderr[-2000:]
    # with the bar drawn (as on a terminal) its epoch line goes beside it to stderr: stdout had begun with
    # "epoch 1/1: loss …" before the JSON, so `train … > result.json` wrote a file no JSON reader opened
    summary = json.loads(res.stdout)
    assert "epoch 1/1:" in res.stderr
    assert summary["epochs"] == 1 and Path(summary["weights"]).is_file()
    history = json.loads((out / "history.json").read_text())
    assert len(history) == 1 and history[0]["loss"] > 0 and "mAP" in history[0]["eval"]
    model, rec, meta = load_weights(out / "weights.pt")
    assert model.config.uncertainty and "train" in meta["command"]
    assert summary["recalibration"] is None and rec is None  # not asked for (--fit-recalibration)
    assert (out / "report" / "validation.json").is_file() and (out / "report" / "validation_pr.png").is_file()
    # the same weights through eval-detector on one hold-out seed
    ev = _jg("eval-detector", "--out", str(tmp_path / "ev"), "--weights", str(out / "weights.pt"),
             "--scenarios", "parking-street", "--seeds", "7", "--frames-per-scenario", "1", "--threads", "1",
             "--no-progress")
    assert ev.returncode == 0, ev.stderr[-2000:]
    rep = json.loads(ev.stdout.strip().splitlines()[-1])
    assert rep["samples"] == 1 and 0.0 <= (rep["car_ap"] or 0.0) <= 1.0
    ideal = json.loads((tmp_path / "ev" / "holdout.json").read_text())
    assert ideal["scored_on"]["synthetic"]["effects"] == "none"
    # the same seed cast with sim-to-real effects: its own cache, and the report says what it was scored on
    fx = _jg("eval-detector", "--out", str(tmp_path / "ev"), "--weights", str(out / "weights.pt"),
             "--scenarios", "parking-street", "--seeds", "7", "--frames-per-scenario", "1", "--threads", "1",
             "--effects", "random,vegetation", "--name", "fx", "--no-progress")
    assert fx.returncode == 0, fx.stderr[-2000:]
    with_fx = json.loads((tmp_path / "ev" / "fx.json").read_text())
    assert "vegetation" in with_fx["scored_on"]["synthetic"]["effects"]
    assert len(list((tmp_path / "ev").glob("cache-*"))) == 2


def test_joined_samples_index_through_their_parts() -> None:
    from jitterguard.services.detector.train_cli import _Joined

    j = _Joined([["a", "b"], [], ["c"], ["d", "e"]])
    assert len(j) == 5 and [j[i] for i in range(5)] == list("abcde")
    with pytest.raises(IndexError):
        j[5]


@pytest.mark.slow
def test_mixed_effect_sets_train_on_both_and_say_so(tmp_path: Path) -> None:
    """``--effects none+random`` casts the training seeds once per set and trains on both; validation is the first
    set's; the weights name the recipe (and, with ``--gt-sample``, the database the run pasted from and how many
    objects of each class a scan got)."""
    out = tmp_path / "run"
    res = _jg("train", "--out", str(out), "--scenarios", "parking-street", "--train-seeds", "0",
              "--val-seeds", "1", "--frames-per-scenario", "1", "--epochs", "1", "--batch-size", "2",
              "--effects", "none+random", "--threads", "1", "--no-progress", "--gt-sample",
              "--gt-sample-count", "bicycle=0", "--gt-sample-count", "car=3")
    assert res.returncode == 0, res.stderr[-2000:]
    caches = [json.loads((p / "index.json").read_text()) for p in out.glob("cache-*")]
    recipes = sorted(c.get("meta", {}).get("recipe", {}).get("effects", "none") for c in caches)
    assert len(caches) == 3 and recipes.count("none") == 2 and len(recipes) == 3  # train ×2 sets, val ×1 (none)
    _, _, meta = load_weights(out / "weights.pt")
    assert meta["source"]["effects"].startswith("none+") and "glass" in meta["source"]["effects"]
    assert meta["gt_sample"]["objects"] > 0 and meta["gt_sample"]["per_scan"] == [3, 3, 4, 0, 2]  # CenterPoint's
    # (2, 3, 4, 6, 2) with the two --gt-sample-count items over it
    res = _jg("train", "--out", str(tmp_path / "bad"), "--effects", "none+moon")
    assert res.returncode == 2 and "--effects" in res.stderr


@pytest.mark.slow
def test_no_intensity_fine_tunes_a_network_that_ignores_intensity(tmp_path: Path) -> None:
    """``train --init W --no-intensity`` keeps W's layers, stores ``use_intensity: false`` in the weights, and the
    detector built from them gives the same boxes whatever intensities a scan carries (the shipped one does not)."""
    import numpy as np

    from jitterguard.bench.detector import bench_scans
    from jitterguard.services.detector.inference import Detector, shipped_weights

    out = tmp_path / "run"
    res = _jg("train", "--out", str(out), "--init", str(shipped_weights("lite")), "--no-intensity",
              "--scenarios", "parking-street", "--train-seeds", "0", "--val-seeds", "1", "--frames-per-scenario", "1",
              "--epochs", "1", "--batch-size", "1", "--max-steps-per-epoch", "1", "--threads", "1", "--no-progress")
    assert res.returncode == 0, res.stderr[-2000:]
    model, _, meta = load_weights(out / "weights.pt")
    assert model.config.use_intensity is False and "--no-intensity" in meta["command"]
    # what the init network had seen stays on record (it had been dropped: eval-detector could not tell)
    assert meta["init_provenance"]["source"] == load_weights(shipped_weights("lite"))[2]["source"]
    scan = bench_scans(1, seed=5)[0]
    dark = scan.copy()
    dark[:, 3] = np.where(scan[:, 3] > 20, 0.0, 200.0)
    for weights, same in ((out / "weights.pt", True), (shipped_weights("lite"), False)):
        det = Detector.load(str(weights), "lite", threads=1)
        a, b = det.detect(scan), det.detect(dark)
        equal = a.boxes.shape == b.boxes.shape and bool(np.array_equal(a.boxes, b.boxes))
        assert equal is same, weights


@pytest.mark.slow
def test_recalibrate_detector_refits_only_the_variance_scales(tmp_path: Path) -> None:
    """The network is copied bit for bit; the new file carries score-binned scales, what they were fitted on and
    where it came from; the report shows the calibration before and after on the fitting scans."""
    from jitterguard.services.detector.inference import shipped_weights

    src = shipped_weights("lite")
    out = tmp_path / "rc"
    res = _jg("recalibrate-detector", "--weights", str(src), "--out", str(out), "--scenarios", "parking-street",
              "--seeds", "60-61", "--frames-per-scenario", "4", "--effects", "none+random", "--bins", "2",
              "--threads", "1", "--workers", "2", "--no-progress")  # the scans ray-cast in two processes
    assert res.returncode == 0, res.stderr[-2000:]
    report = json.loads(res.stdout.strip().splitlines()[-1])
    before, after = load_weights(src), load_weights(out / "weights.pt")
    for (name, a), b in zip(before[0].state_dict().items(), after[0].state_dict().values()):
        assert (a == b).all(), name
    rec = after[1]
    assert rec is not None and rec.to_payload() == report["recalibration"]
    assert after[2]["recalibration_fit_on"]["scans"] == 16 and after[2]["recalibration_fit_on"]["seeds"] == "60-61"
    assert after[2]["recalibrated_from"]["path"] == str(src)
    # fitted on these scans, the NLL there cannot get worse than with the raw variances
    assert report["after"]["nll"] <= report["before"]["nll"]
    assert (out / "recalibration.json").is_file() and (out / "after_calibration.png").is_file()


def test_a_recalibration_fitted_on_too_few_matches_says_so(tmp_path: Path) -> None:
    """One scan, five bins asked: the fit falls back to one global scale on a few dozen boxes — said in a warning
    and in the file's ``recalibration_fit_on.matches``, where only ``bins: 1`` in the report had told it."""
    from jitterguard.services.detector.inference import shipped_weights

    res = _jg("recalibrate-detector", "--weights", str(shipped_weights("lite")), "--out", str(tmp_path / "rc"),
              "--scenarios", "parking-street", "--seeds", "60", "--frames-per-scenario", "1", "--effects", "none",
              "--bins", "5", "--threads", "1", "--no-progress")
    assert res.returncode == 0, res.stderr[-2000:]
    fit_on = load_weights(tmp_path / "rc" / "weights.pt")[2]["recalibration_fit_on"]
    assert fit_on["scans"] == 1 and fit_on["bins"] == 1 and 0 < fit_on["matches"] < 200
    assert f"1 score bin(s), 5 asked, on {fit_on['matches']} matched boxes of 1 scans" in res.stderr


@pytest.mark.slow
def test_sweeps_fine_tunes_single_sweep_weights_into_a_stacked_sweep_model(tmp_path: Path) -> None:
    """``train --init W --sweeps 2`` on synthetic scans: the weights come out five-field with the stack recorded
    (so the live service and the evaluators stack as trained), and ``eval-detector`` scores them on stacked scans;
    ``--sweeps 1`` cannot take five-field weights."""
    from jitterguard.services.detector.inference import Detector, shipped_weights

    out = tmp_path / "run"
    res = _jg("train", "--out", str(out), "--init", str(shipped_weights("lite")), "--sweeps", "2",
              "--scenarios", "parking-street", "--train-seeds", "0", "--val-seeds", "1", "--frames-per-scenario", "2",
              "--epochs", "1", "--batch-size", "1", "--max-steps-per-epoch", "1", "--threads", "1", "--no-progress")
    assert res.returncode == 0, res.stderr[-2000:]
    model, _, meta = load_weights(out / "weights.pt")
    assert model.config.num_point_features == 5 and meta["source"]["sweeps"] == 2
    assert Detector.load(str(out / "weights.pt"), "lite", threads=1).sweeps == 2
    ev = _jg("eval-detector", "--out", str(tmp_path / "ev"), "--weights", str(out / "weights.pt"),
             "--scenarios", "parking-street", "--seeds", "7", "--frames-per-scenario", "1", "--threads", "1",
             "--no-progress")
    assert ev.returncode == 0, ev.stderr[-2000:]
    assert json.loads(ev.stdout.strip().splitlines()[-1])["samples"] == 1
    assert json.loads((tmp_path / "ev" / "holdout.json").read_text())["scored_on"]["synthetic"]["sweeps"] == 2
    back = _jg("train", "--out", str(tmp_path / "back"), "--init", str(out / "weights.pt"), "--threads", "1",
               "--no-progress")
    assert back.returncode == 2 and "--init" in back.stderr and "5 point fields" in back.stderr


def test_with_time_lag_computes_what_the_single_sweep_model_computes() -> None:
    """The widened network reads a zero-weighted lag: on stacked points its heads equal the four-field network's
    on the same points (the lags dropped), until training moves the new weights."""
    import numpy as np
    import torch

    from jitterguard.bench.detector import bench_scans
    from jitterguard.services.detector.network import with_time_lag

    model, _, _ = load_weights(shipped_weights_path())
    wide = with_time_lag(model).eval()
    pts = bench_scans(1, seed=3)[0][:, :4]
    lagged = np.column_stack([pts, np.random.default_rng(0).uniform(0, 0.5, len(pts))]).astype(np.float32)
    with torch.no_grad():
        a = model([torch.from_numpy(pts)])
        b = wide([torch.from_numpy(lagged)])
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-5)
    assert wide.config.num_point_features == 5
    with pytest.raises(ValueError):
        with_time_lag(wide)


def shipped_weights_path() -> Path:
    from jitterguard.services.detector.inference import shipped_weights

    return Path(shipped_weights("lite"))


TINY_RUN = ["--scenarios", "parking-street", "--train-seeds", "0-1", "--val-seeds", "900", "--frames-per-scenario",
            "2", "--batch-size", "1", "--effects", "none", "--threads", "1", "--no-progress"]


@pytest.mark.slow
def test_resume_refuses_other_settings_in_one_line_and_says_when_it_starts_afresh(tmp_path: Path) -> None:
    out = tmp_path / "run"
    fresh = _jg("train", "--out", str(out), *TINY_RUN, "--epochs", "1", "--resume")
    assert fresh.returncode == 0, fresh.stderr[-2000:]
    assert "no checkpoint" in fresh.stderr  # --resume with nothing to resume from is said, not silent
    ck = (out / "checkpoint.pt").read_bytes()
    for extra, field in ((["--epochs", "2"], "epochs"), (["--epochs", "1", "--rotation", "10"], "rotation_deg"),
                         (["--epochs", "1", "--preset", "paper"], "config.")):
        res = _jg("train", "--out", str(out), *TINY_RUN, *extra, "--resume")
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and "--resume" in lines[0] and field in lines[0], res.stderr
    assert (out / "checkpoint.pt").read_bytes() == ck
    (out / "checkpoint.pt").write_bytes(ck[:500])  # damaged
    res = _jg("train", "--out", str(out), *TINY_RUN, "--epochs", "1", "--resume")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "checkpoint" in res.stderr


@pytest.mark.slow
def test_fit_recalibration_weights_keep_the_training_metadata(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = _jg("train", "--out", str(out), *TINY_RUN, "--epochs", "1", "--fit-recalibration")
    assert res.returncode == 0, res.stderr[-2000:]
    _, rec, meta = load_weights(out / "weights.pt")
    assert rec is not None  # the weights.pt written after the fit (it used to drop what train() recorded)
    # two scans' boxes: a thin fit, said as recalibrate-detector says it (train had said nothing)
    assert "asked, on" in res.stderr and "give a steadier fit" in res.stderr, res.stderr[-2000:]
    assert meta["train_config"]["batch_size"] == 1 and meta["world_size"] == 1 and meta["epochs"] == 1
    assert meta["augment"]["rotation_deg"] == 45.0 and meta["source"]["train_seeds"] == "0-1"


@pytest.mark.slow
def test_a_distilled_fine_tune_says_what_it_was_held_to(tmp_path: Path) -> None:
    """``--distill-from`` trains with the KL term (its loss in the history) and names the teacher, its hash and the
    classes in the weights' metadata."""
    import hashlib

    first, out = tmp_path / "first", tmp_path / "run"
    assert _jg("train", "--out", str(first), *TINY_RUN, "--epochs", "1").returncode == 0
    res = _jg("train", "--out", str(out), *TINY_RUN, "--epochs", "1", "--init", str(first / "weights.pt"),
              "--distill-from", str(first / "weights.pt"), "--distill-classes", "pedestrian,bicycle")
    assert res.returncode == 0, res.stderr[-2000:]
    _, _, meta = load_weights(out / "weights.pt")
    assert meta["distilled"]["classes"] == ["pedestrian", "bicycle"] and meta["distilled"]["weight"] == 1.0
    assert meta["distilled"]["sha256_16"] == hashlib.sha256((first / "weights.pt").read_bytes()).hexdigest()[:16]
    assert list(meta["train_config"]["distill_channels"]) == [4, 3]
    history = json.loads((out / "history.json").read_text())
    assert history[0]["distill"] >= 0.0 and history[0]["loss"] > history[0]["distill"]


def test_too_few_nuscenes_training_frames_are_one_line_and_exit_2(tmp_path: Path) -> None:
    from jitterguard.sim.export import export_scenario
    from jitterguard.sim.world import make_scenario

    root = tmp_path / "root"
    export_scenario(make_scenario("parking-street", 3, duration_s=0.4, rate_hz=10.0), str(root))
    res = _jg("train", "--out", str(tmp_path / "o"), "--nuscenes", str(root), "--holdout-last", "50",
              "--threads", "1", "--no-progress", timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and "--holdout-last" in lines[-1] and "0 training samples" in lines[-1], res.stderr
    assert not any(line.startswith("Traceback") for line in lines)


def test_bootstrap_intervals_report_their_progress(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """eval-detector's bootstrap runs after the detection bar: it has its own bar (one tick per resample)."""
    import numpy as np

    from jitterguard.services.detector.config import Detections3D, Sample
    from jitterguard.services.detector.evaluate import bootstrap_intervals
    from jitterguard.services.detector.train_cli import write_report

    box = np.array([[5.0, 0, -1, 4, 2, 1.5, 0, 0, 0]], np.float32)
    gt = [Sample(np.zeros((1, 4), np.float32), box, np.array([0]), np.array([50])) for _ in range(3)]
    dets = [Detections3D(box, np.array([0.9], np.float32), np.array([0]), np.full((1, 5), -2.0, np.float32))
            for _ in range(3)]
    ticks: list[int] = []
    bootstrap_intervals(dets, gt, resamples=7, progress=ticks.append)
    assert ticks == [1] * 7
    write_report(tmp_path, "x", dets, gt, bootstrap=7, progress=True)
    assert "bootstrap intervals" in capsys.readouterr().err


def test_a_cache_of_another_worlds_scans_is_cast_anew(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A folder's cached scans are reused for the same recipe, but not once the world they were cast in has changed
    (``WORLD_VERSION``): ``eval-detector --out`` reused after an upgrade must not score the old world's scans."""
    import jitterguard.sim.world as world
    from jitterguard.services.detector.train_cli import synthetic_cache

    first = synthetic_cache(tmp_path, ["parking-street"], [7], 1, False)
    again = synthetic_cache(tmp_path, ["parking-street"], [7], 1, False)
    assert len(list(tmp_path.glob("cache-*"))) == 1 and len(first) == len(again) == 1
    assert first.meta["recipe"]["world_version"] == world.WORLD_VERSION
    monkeypatch.setattr(world, "WORLD_VERSION", world.WORLD_VERSION + 1)
    newer = synthetic_cache(tmp_path, ["parking-street"], [7], 1, False)
    assert len(list(tmp_path.glob("cache-*"))) == 2 and newer.meta["recipe"]["world_version"] == world.WORLD_VERSION


def test_a_run_folder_holding_a_checkpoint_is_not_started_over_without_resume(tmp_path: Path) -> None:
    """Forgetting --resume had replaced an interrupted run's checkpoint, history and weights without a word."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"an earlier run's")
    res = _jg("train", "--out", str(out), "--scenarios", "parking-street", "--train-seeds", "0", "--val-seeds", "1",
              "--frames-per-scenario", "1", "--epochs", "1", "--threads", "1", "--no-progress")
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "--resume continues it" in lines[0], res.stderr
    assert (out / "checkpoint.pt").read_bytes() == b"an earlier run's" and sorted(p.name for p in out.iterdir()) == [
        "checkpoint.pt"]


def test_the_seeds_a_weights_file_learnt_are_read_along_its_lineage_and_recipe() -> None:
    from jitterguard.services.detector.inference import shipped_weights
    from jitterguard.services.detector.provenance import trained_seeds

    assert trained_seeds(load_weights(shipped_weights("lite"))[2]) == set(range(60))  # 0-49, 0-19, 20-39, 40-59
    meta = {"source": {"train_seeds": "5-6"}, "command": "jitterguard train --train-seeds 8",
            "init_provenance": {"source": {"train_seeds": "1,3"}}}
    assert trained_seeds(meta) == {1, 3, 5, 6, 8}
    assert trained_seeds({"source": {"train_seeds": "garbled"}}) == set()
