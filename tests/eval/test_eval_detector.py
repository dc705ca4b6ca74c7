"""``jitterguard eval --input detector``: scans as the replay publishes them → detector → tracker → classifier.

Two kinds of detector: a tiny randomly initialised network saved as a weights file (exercises the real load /
inference / conversion path; its detections are meaningless, so no quality is asserted), and an *oracle* that
returns each scan's sensor-frame ground truth in place of the network. The oracle is the only stand-in: it
makes the expected numbers exact (AP 1, ECE = the constant σ it reports), so it can tell whether scans, sensor-
frame boxes, world-frame labels and poses line up — a frame or ordering bug would show as unmatched tracks.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from jitterguard.cli import main
from jitterguard.schemas import decode
from jitterguard.schemas.models import DetectedObjects
from jitterguard.eval.detector_input import (
    LabelledScan,
    detection_metrics,
    detector_frames,
    nuscenes_scans,
    run_detector_pipeline,
    synthetic_scans,
)
from jitterguard.eval.metrics import compute_metrics
from jitterguard.services.detector.config import CLASS_NAMES, LITE, Detections3D
from jitterguard.services.detector.inference import save_weights
from jitterguard.services.detector.network import CenterPointNet
from jitterguard.sim.world import make_scenario
from helpers import NUSC

TINY = LITE.model_copy(update=dict(
    name="tiny", point_cloud_range=(-12.8, -12.8, -3.0, 12.8, 12.8, 3.0), voxel_size=(0.2, 0.2, 6.0),
    pfn_channels=8, backbone_layers=(1, 1, 1), backbone_channels=(8, 16, 16), neck_channels=(8, 8, 8),
    head_channels=8, max_pillars=4000,
))
"""tests/detector/test_model.py's unit-test network: 128×128 pillars, cheap enough for a 10-scan run."""
ORACLE_VAR = 0.01
DET_ARGS = ["eval", "--scenario", "parking-street", "--seed", "2", "--duration", "1", "--input", "detector",
            "--threads", "1"]


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _weights(path: Path, uncertainty: bool = True) -> Path:
    torch.manual_seed(0)
    save_weights(path, CenterPointNet(TINY.model_copy(update={"uncertainty": uncertainty})))
    return path


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _weights(tmp_path_factory.mktemp("w") / "tiny.pt")


def _oracle(scans: list[LabelledScan]) -> Callable[[np.ndarray], Detections3D]:
    """A 'network' that returns the visible ground truth of the scan it is given, σ² = ORACLE_VAR on every
    axis. It is handed the scans' samples in order and checks that the points it receives are that sample's
    (the scan the tracker's detections come from is the scan the metrics score against)."""
    it: Iterator[LabelledScan] = iter(scans)

    def detect(points: np.ndarray) -> Detections3D:
        s = next(it).sample
        np.testing.assert_array_equal(points, s.points[np.isfinite(s.points).all(axis=1)])
        keep = s.num_points >= 1
        n = int(keep.sum())
        return Detections3D(s.boxes[keep], np.full(n, 0.9, np.float32), s.labels[keep],
                            np.full((n, 5), math.log(ORACLE_VAR), np.float32))

    return detect


def _run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    cap = capsys.readouterr()
    return int(exc.value.code or 0), cap.out, cap.err


# ------------------------------------------------------------------------------------------- scan sources


def test_synthetic_scan_is_what_the_replay_publishes() -> None:
    from jitterguard.services.replay.adapter import point_cloud_message
    from jitterguard.services.replay.sources.synthetic import SyntheticSource

    frame = next(iter(SyntheticSource("parking-street", seed=2, duration_s=1.0, rate_hz=10.0).frames(3)))
    sc = make_scenario("parking-street", 2, 1.0, 10.0)
    ours = [ls for ls, _ in zip(synthetic_scans(sc, 2), range(4))][3]
    replay = point_cloud_message(frame, 3, frame.stamp_ns)
    assert ours.scan.fields == replay.fields and ours.scan.num_points == replay.num_points > 1000
    assert ours.scan.data == replay.data
    assert ours.scan.ego_pose == replay.ego_pose and ours.scan.header == replay.header
    assert ours.gt.seq == 3 and ours.sample.token == "synthetic/parking-street/2/3"
    assert (ours.sample.num_points > 0).any() and len(ours.sample.boxes) == len(ours.sample.labels)


# ------------------------------------------------------------------------------------------- oracle runs


def test_oracle_detector_gives_exact_metrics_and_tracks_on_the_ground_truth() -> None:
    sc = make_scenario("parking-street", 1, 3.0, 10.0)
    scans = list(synthetic_scans(sc, 1))
    frames = list(detector_frames(scans, _oracle(scans)))
    # what the tracker receives: the service's conversion, sensor frame, the variances as covariances
    msg = decode(DetectedObjects, frames[5].detections)
    assert msg.header == scans[5].scan.header and msg.ego_pose == scans[5].scan.ego_pose
    assert len(msg.objects) == int((scans[5].sample.num_points >= 1).sum()) > 5
    assert all(o.kinematics.has_position_covariance for o in msg.objects)
    assert msg.objects[0].kinematics.pose_with_covariance.covariance[0] == pytest.approx(ORACLE_VAR, rel=1e-5)

    rec, preds, samples = run_detector_pipeline(iter(frames))
    assert len(preds) == len(samples) == len(sc)
    block, report = detection_metrics(preds, samples)
    assert block["map"] == pytest.approx(1.0)
    for name in CLASS_NAMES:
        assert block[name]["ap"] == (pytest.approx(1.0) if block[name]["num_gt"] else None), name
        assert block[name]["fp"] == 0
    assert block["car"]["num_gt"] > 100
    assert block["ece_pos"] == pytest.approx(math.sqrt(ORACLE_VAR), rel=1e-4)  # residual 0, predicted σ 0.1
    assert report["detection"]["classes"]["car"]["precision"]["2"][:10] == pytest.approx([1.0] * 10)
    # the tracker puts its tracks onto the world-frame ground truth, and motion is plain to see
    assert (rec.gt_instance >= 0).mean() > 0.95
    motion = compute_metrics(rec)["vehicle"]
    assert motion["n_dynamic"] > 0 and motion["n_static"] > 0
    assert motion["ap_z"] > 0.9


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_oracle_on_nuscenes_scans_labels_and_poses_line_up() -> None:
    from jitterguard.eval.groundtruth import load_nuscenes_frames

    _, gt = load_nuscenes_frames(NUSC)
    scans = nuscenes_scans(NUSC, None, gt)
    assert len(scans) == len(gt) >= 30
    assert scans[0].scan.fields == ["x", "y", "z", "intensity", "ring"]
    rec, preds, samples = run_detector_pipeline(detector_frames(scans, _oracle(scans)))
    block, _ = detection_metrics(preds, samples)
    assert block["map"] == pytest.approx(1.0) and block["car"]["num_gt"] > 100
    # sensor-frame boxes (detector loader) → LIDAR_TOP pose → tracker world frame ≈ the evaluator's world GT
    assert (rec.gt_instance >= 0).mean() > 0.9


@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_detections_equal_the_detector_evaluations_own_on_nuscenes(tiny_weights: Path) -> None:
    """The replay-message path (five columns, picked by name) gives the detector exactly the points its own
    evaluation (``eval-detector``, via ``nuscenes_samples``) feeds it, hence the same boxes and the same AP."""
    from jitterguard.eval.groundtruth import load_nuscenes_frames
    from jitterguard.services.detector.adapter import finite_detections
    from jitterguard.services.detector.evaluate import evaluation_report
    from jitterguard.services.detector.inference import Detector

    det = Detector.load(tiny_weights, threads=1)
    _, gt = load_nuscenes_frames(NUSC)
    scans = nuscenes_scans(NUSC, None, gt)[:12]
    ours = [f.predictions for f in detector_frames(scans, det.detect)]
    direct = [finite_detections(det.detect(ls.sample.points))[0] for ls in scans]
    assert sum(len(d) for d in ours) > 0
    for a, b in zip(ours, direct):
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.log_variances, b.log_variances)
    samples = [ls.sample for ls in scans]
    assert detection_metrics(ours, samples)[0]["map"] == evaluation_report(direct, samples)["summary"]["mAP"]


# ------------------------------------------------------------------------------------------- the CLI


GROUP_KEYS = ("ap_z", "ap_speed", "false_dynamic_z", "missed_dynamic_z", "n_static", "n_dynamic")


def _check_detection_block(det: dict, has_variances: bool) -> None:
    assert det["num_samples"] > 0
    for name in CLASS_NAMES:
        c = det[name]
        assert c["ap"] is None if c["num_gt"] == 0 else 0.0 <= c["ap"] <= 1.0, name
    assert det["map"] is None or 0.0 <= det["map"] <= 1.0
    if has_variances:
        assert det["ece_pos"] is None or det["ece_pos"] >= 0.0
    else:
        assert det["ece_pos"] is None and det["num_matched"] is None


def test_cli_detector_run_writes_detection_metrics_and_is_deterministic(
        tmp_path: Path, tiny_weights: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out1, out2 = tmp_path / "a", tmp_path / "b"
    code, stdout, err = _run_cli([*DET_ARGS, "--weights", str(tiny_weights), "--out", str(out1), "--json"], capsys)
    assert code == 0, err
    m = json.loads((out1 / "metrics.json").read_text())
    assert json.loads(stdout) == m
    assert m["run"]["input"] == "detector" and m["run"]["noise"] is None and m["run"]["frames"] == 10
    assert m["run"]["detector"]["preset"] == "tiny" and not m["run"]["detector"]["random_init"]
    assert "sha256" in m["run"]["detector"]["weights"]
    assert m["run"]["detector"]["sensor_height_m"] == "auto" and m["run"]["detector"]["sensor_tilt"] == "auto"
    _check_detection_block(m["detection"], has_variances=True)
    assert m["detection"]["car"]["num_gt"] > 0 and m["detection"]["car"]["num_pred"] > 0
    for g in ("vehicle", "pedestrian"):
        for k in GROUP_KEYS:
            assert k in m["motion"][g], (g, k)
    for name in ("report.md", "speed_vs_z.png", "pr_curves.png", "alpha_sweep.png", "detection_calibration.png",
                 "detection_pr.png"):
        assert (out1 / name).stat().st_size > 0, name
    report = (out1 / "report.md").read_text()
    assert "## Detector" in report and "| car |" in report and "detection_calibration.png" in report

    code, _, _ = _run_cli([*DET_ARGS, "--weights", str(tiny_weights), "--out", str(out2)], capsys)
    assert code == 0
    assert (out2 / "metrics.json").read_text() == (out1 / "metrics.json").read_text()


def test_cli_vanilla_model_has_no_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    w = _weights(tmp_path / "vanilla.pt", uncertainty=False)
    code, stdout, err = _run_cli([*DET_ARGS, "--duration", "0.5", "--weights", str(w), "--out",
                                  str(tmp_path / "o"), "--json"], capsys)
    assert code == 0, err
    m = json.loads(stdout)
    _check_detection_block(m["detection"], has_variances=False)
    assert m["run"]["detector"]["figures"] == ["detection_pr.png"]
    assert not (tmp_path / "o" / "detection_calibration.png").exists()


NEED_DETECTOR = ("--weights, --threads, --no-self-crop, --detector-flips, --sensor-height and --sensor-tilt need"
                 " --input detector")


@pytest.mark.parametrize("argv, needle", [
    (["--input", "detector", "--weights", "/nonexistent/w.pt"], "--weights: file not found"),
    (["--input", "detector", "--weights", "GARBAGE"], "--weights:"),
    (["--input", "detector", "--noise", "clean"], "--noise applies to --input gt-noise"),
    (["--input", "gt-noise", "--weights", "x.pt"], NEED_DETECTOR),
    (["--input", "gt-noise", "--threads", "2"], NEED_DETECTOR),
    (["--input", "gt-noise", "--no-self-crop"], NEED_DETECTOR),
    (["--input", "gt-noise", "--detector-flips"], NEED_DETECTOR),
    (["--input", "gt-noise", "--sensor-height", "0"], NEED_DETECTOR),
    (["--input", "detector", "--sensor-height", "184"], "--sensor-height: expected 'auto' or a height in metres"),
    (["--input", "gt-noise", "--sensor-tilt", "level"], NEED_DETECTOR),
    (["--input", "detector", "--sensor-tilt", "pitched"], "--sensor-tilt: expected 'auto' or 'level', got 'pitched'"),
    (["--input", "detector", "--nuscenes", "/nonexistent", "--runs", "2"], "--runs"),
])
def test_cli_bad_detector_input_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                   argv: list[str], needle: str) -> None:
    if "GARBAGE" in argv:
        garbage = tmp_path / "garbage.pt"
        garbage.write_bytes(b"not a torch file\n" * 10)
        argv = [str(garbage) if a == "GARBAGE" else a for a in argv]
    code, _, err = _run_cli(["eval", "--out", str(tmp_path / "x"), *argv], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and needle in err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_cli_detector_on_the_nuscenes_scene(tmp_path: Path, tiny_weights: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    code, stdout, err = _run_cli(["eval", "--nuscenes", str(NUSC), "--input", "detector", "--threads", "1",
                                  "--weights", str(tiny_weights), "--out", str(tmp_path / "nu"), "--json"], capsys)
    assert code == 0, err
    m = json.loads(stdout)
    assert m["run"]["frames"] == m["detection"]["num_samples"] >= 30
    _check_detection_block(m["detection"], has_variances=True)
    assert m["detection"]["car"]["num_gt"] > 100 and m["detection"]["pedestrian"]["num_gt"] > 0
    assert (tmp_path / "nu" / "detection_calibration.png").stat().st_size > 0


# ------------------------------------------------------------------------- what the weights have seen


def _stub_detector(meta: dict) -> object:
    from types import SimpleNamespace

    return SimpleNamespace(meta=meta, config=SimpleNamespace(name="tiny", uncertainty=True, score_threshold=0.1),
                           self_crop=None, flips=False, score_threshold=None, sensor_height_m=None, sensor_tilt=True)


def test_run_info_says_when_the_weights_saw_the_scored_dataroot(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Weights trained on a nuScenes dataroot (``source.nuscenes``) or adapted on its scans (``unlabelled_scans``)
    and scored there by ``eval --input detector``: metrics.json's ``run.detector`` and report.md say so, and a
    warning goes to stderr. The scalar-only meta had dropped both records, so such a run looked like an unseen
    scene (eval-detector checked; eval did not)."""
    from jitterguard.eval.cli import detector_run_info, warn_seen, weights_saw_scored_data
    from jitterguard.eval.report import _input_desc
    from jitterguard.services.detector import data_nuscenes

    root = tmp_path / "nuscenes"
    root.mkdir()
    (tmp_path / "link").symlink_to(root)
    other = tmp_path / "other"
    other.mkdir()
    trained = {"source": {"nuscenes": str(root.resolve()), "split": None, "holdout_last": 10}, "epochs": 3}
    adapted = {"source": {"scenarios": ["mixed"], "train_seeds": "0-9"},
               "unlabelled_scans": [{"recording": f"{root.resolve()}#scene-0523", "scans": 40}]}

    seen = weights_saw_scored_data(trained, tmp_path / "link", ["scene-0523"])  # the held-out tail is the scene
    info = detector_run_info(_stub_detector(trained), "w.pt (sha256 0)", seen)
    assert info["weights_trained_on_this_dataroot"] is True and info["weights_adapted_on_its_scans"] is False
    assert info["trained_on"] == trained["source"] and info["meta"] == {"epochs": 3}
    assert info["sensor_height_m"] == "auto" and info["sensor_tilt"] == "auto"  # measured in every scan (the defaults)
    assert "trained on this dataroot" in _input_desc({"detector": info})
    warn_seen(info, root)
    assert "trained on" in capsys.readouterr().err

    info = detector_run_info(_stub_detector(adapted), "w.pt (sha256 0)", weights_saw_scored_data(adapted, root, ["scene-0523"]))
    assert info["weights_trained_on_this_dataroot"] is False and info["weights_adapted_on_its_scans"] is True
    assert "adapted on its unlabelled scans" in _input_desc({"detector": info})
    warn_seen(info, root)
    assert "adapted on" in capsys.readouterr().err

    for meta in (trained, adapted):  # another dataroot: neither
        s = weights_saw_scored_data(meta, other, ["scene-0523"])
        assert not s["weights_trained_on_this_dataroot"] and not s["weights_adapted_on_its_scans"]
        warn_seen(s, other)
    assert capsys.readouterr().err == ""
    synthetic = detector_run_info(_stub_detector(trained), "w.pt (sha256 0)")  # a synthetic run: not defined
    assert synthetic["weights_trained_on_this_dataroot"] is None and synthetic["weights_adapted_on_its_scans"] is None
    assert "trained on this dataroot" not in _input_desc({"detector": synthetic})

    # trained with an official split: the scored scene counts as seen when the split or the validation split holds it
    splits = {"train": ["scene-0001", "scene-0523"], "val": ["scene-0002"]}
    monkeypatch.setattr(data_nuscenes, "official_split", lambda name: splits[name])
    by_split = {"source": {"nuscenes": str(root.resolve()), "split": "train", "val_split": "val", "holdout_last": None}}
    assert weights_saw_scored_data(by_split, root, ["scene-0523"])["weights_trained_on_this_dataroot"] is True
    assert weights_saw_scored_data(by_split, root, ["scene-0002"])["weights_trained_on_this_dataroot"] is True
    assert weights_saw_scored_data(by_split, root, ["scene-0003"])["weights_trained_on_this_dataroot"] is False


@pytest.mark.slow
@pytest.mark.skipif(not NUSC.is_dir(), reason="../shared/data/nuscenes-scene-0523 absent")
def test_cli_flags_weights_trained_on_the_scored_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The whole command: weights whose metadata says they trained on the scene's dataroot."""
    torch.manual_seed(0)
    w = tmp_path / "seen.pt"
    save_weights(w, CenterPointNet(TINY), meta={"source": {"nuscenes": str(NUSC.resolve()), "holdout_last": 10}})
    code, stdout, err = _run_cli(["eval", "--nuscenes", str(NUSC), "--input", "detector", "--threads", "1",
                                  "--weights", str(w), "--out", str(tmp_path / "nu"), "--json"], capsys)
    assert code == 0, err
    assert "trained on" in err
    det = json.loads(stdout)["run"]["detector"]
    assert det["weights_trained_on_this_dataroot"] is True and det["weights_adapted_on_its_scans"] is False
    assert "trained on this dataroot" in (tmp_path / "nu" / "report.md").read_text()
