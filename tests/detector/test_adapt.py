"""`jitterguard adapt`: label-free normalisation statistics, pseudo-labels, tracked-residual recalibration, and a
tiny real run end to end (labels never read, the scans used named in the weights)."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from jitterguard.services.detector.adapt import (
    UnlabelledScan,
    propagate_static,
    pseudo_samples,
    read_unlabelled,
    recompute_norm_stats,
    tracked_residuals,
)
from jitterguard.services.detector.config import LITE, SELF_CROP_M, Detections3D, Sample
from jitterguard.services.detector.ground import TRAINED_SENSOR_HEIGHT_M, GroundPlane
from jitterguard.services.detector.inference import load_weights
from jitterguard.services.detector.network import CenterPointNet
from jitterguard.services.detector.pillars import voxelize
from jitterguard.services.detector.provenance import adapted_on_scans
from jitterguard.services.detector.targets import build_targets
from jitterguard.sim.export import export_scenario
from jitterguard.sim.world import make_scenario

TINY = LITE.model_copy(update=dict(
    name="tiny", point_cloud_range=(-12.8, -12.8, -3.0, 12.8, 12.8, 3.0), voxel_size=(0.2, 0.2, 6.0),
    pfn_channels=8, backbone_layers=(1, 1, 1), backbone_channels=(8, 16, 16), neck_channels=(8, 8, 8),
    head_channels=8, max_pillars=4000,
))


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _scan(seed: int, n: int = 3000, shift: float = 0.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-12, 12, (n, 2)), rng.normal(-1.0 + shift, 0.5, n),
                            rng.uniform(0, 60, n)]).astype(np.float32)


def test_norm_stats_are_the_real_scans_statistics() -> None:
    torch.manual_seed(0)
    model = CenterPointNet(TINY)
    scans = [_scan(i, shift=2.0) for i in range(3)]
    recompute_norm_stats(model, scans, batch_size=3)  # one batch: running stats = that batch's statistics
    assert not model.training
    pfn = model.pfn
    with torch.no_grad():
        feats = pfn.linear(pfn.point_features(voxelize([torch.from_numpy(s) for s in scans], TINY)))
    torch.testing.assert_close(pfn.norm.running_mean, feats.mean(0), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(pfn.norm.running_var, feats.var(0, unbiased=True), rtol=1e-3, atol=1e-5)
    assert pfn.norm.momentum == 0.1  # restored


def test_pseudo_labels_keep_confident_boxes_with_points_and_train_no_regression() -> None:
    pts = _scan(1)
    box = np.array([[3.0, 2.0, -1.0, 4.0, 2.0, 2.0, 0.0, 0.0, 0.0]], np.float32)
    inside = np.column_stack([np.random.default_rng(2).uniform([1.5, 1.2, -1.8], [4.5, 2.8, -0.2], (50, 3)),
                              np.full(50, 10.0)]).astype(np.float32)
    pts = np.concatenate([pts, inside])
    boxes = np.concatenate([box, box + [[0, -8, 0, 0, 0, 0, 0, 0, 0]], box + [[-30, 0, 0, 0, 0, 0, 0, 0, 0]]])
    det = Detections3D(boxes.astype(np.float32), np.array([0.9, 0.3, 0.95], np.float32), np.array([0, 0, 0]),
                       np.zeros((3, 5), np.float32))
    scan = UnlabelledScan(pts, np.eye(4), "rec", "0.bin", False)
    (s,) = pseudo_samples([scan], [det], thresholds=(0.5, 0.5, 0.5, 0.4, 0.4), min_points=3)
    assert s.pseudo and len(s.boxes) == 1 and s.num_points[0] >= 50  # low score and empty box dropped
    t = build_targets(s, TINY)
    assert t.heatmap.max() == 1.0 and not t.mask.any()  # where, not how precisely
    t2 = build_targets(dataclasses.replace(s, pseudo=False), TINY)
    assert t2.mask.sum() == 1


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    m = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = (x, y)
    return m


def test_static_pseudo_labels_are_carried_to_the_scans_that_missed_them() -> None:
    """A parked car pseudo-labelled in 4 of 7 posed scans (the sensor driving past and turning) is carried into
    the scan where the model missed it while it held 2 returns — at its place in that scan's frame, z through each
    scan's road plane — and not into the one where it held none, nor where another pseudo-label already stands
    there. A car that moves 3 m a scan, a bicycle labelled in only 2 scans and a scan without a pose get nothing."""
    rng = np.random.default_rng(0)
    ground = GroundPlane(2.0, slope_x=0.01)  # the scans' road: 2 m under the sensor, rising 1 cm per metre ahead
    parked_w = np.array([34.0, 6.0, -1.2, 4.5, 1.9, 1.6, 0.4, 0.0, 0.0])  # beyond _scan's clutter (±12 m)
    poses = [_pose(2.0 * k, 0.2 * k, 0.03 * k) for k in range(7)]

    def trained(box_w: np.ndarray, pose: np.ndarray) -> np.ndarray:  # a world box in a scan's trained frame
        b = box_w.copy()
        b[:3] = (box_w[:3] - pose[:3, 3]) @ pose[:3, :3]
        b[6] = box_w[6] - math.atan2(pose[1, 0], pose[0, 0])
        b[2] += (ground.height - TRAINED_SENSOR_HEIGHT_M) - ground.slope_x * b[0]
        return b

    def returns(box: np.ndarray, n: int) -> np.ndarray:  # n returns inside a box of a scan's trained frame
        c, s_ = math.cos(box[6]), math.sin(box[6])
        local = rng.uniform(-0.4, 0.4, (n, 3)) * box[3:6]
        xyz = np.column_stack([box[0] + c * local[:, 0] - s_ * local[:, 1], box[1] + s_ * local[:, 0] + c * local[:, 1],
                               box[2] + local[:, 2]])
        return np.column_stack([xyz, np.full(n, 20.0)]).astype(np.float32)

    labelled = {0, 1, 2, 3}  # the model found the parked car in these scans
    scans, pseudo = [], []
    for k, pose in enumerate(poses):
        parked = trained(parked_w, pose)
        mover = trained(np.array([3.0 * k - 5.0, -4.0, -1.2, 4.5, 1.9, 1.6, 0.0, 0.0, 0.0]), pose)
        bike = trained(np.array([10.0, -8.0, -1.4, 1.8, 0.6, 1.4, 0.0, 0.0, 0.0]), pose)
        n_parked = {4: 2, 5: 0}.get(k, 30)
        pts = np.concatenate([_scan(k), returns(parked, n_parked) if n_parked else np.zeros((0, 4), np.float32),
                              returns(mover, 30), returns(bike, 20)])
        boxes, labels = [mover], [0]
        if k in labelled:
            noisy = parked.copy()
            noisy[:2] += rng.normal(0.0, 0.1, 2)
            boxes.append(noisy)
            labels.append(0)
        if k < 2:
            boxes.append(bike)
            labels.append(3)
        if k == 6:  # a truck pseudo-label already where the car is: nothing carried on top of it
            boxes.append(parked + [0.3, 0, 0, 1, 0, 0, 0, 0, 0])
            labels.append(1)
        b = np.asarray(boxes, np.float32)
        pseudo.append(Sample(pts, b, np.asarray(labels, np.int64), np.full(len(b), 10), f"p/{k}", pseudo=True))
        scans.append(UnlabelledScan(pts, pose, "rec", f"{k}.bin", True))
    # a scan of another recording without a pose, the parked car's returns where scan 4 has them: never touched
    scans.append(UnlabelledScan(scans[4].points, np.eye(4), "other", "x.bin", False))
    pseudo.append(Sample(scans[4].points, np.zeros((0, 9), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64),
                         "p/x", pseudo=True))

    out, added = propagate_static(pseudo, scans, [ground] * len(scans))
    assert added == 1
    for k, (before, after) in enumerate(zip(pseudo, out)):
        if k != 4:
            assert after is before, k
    new = out[4]
    assert len(new.boxes) == len(pseudo[4].boxes) + 1 and new.labels[-1] == 0 and new.num_points[-1] == 2
    want = trained(parked_w, poses[4])
    np.testing.assert_allclose(new.boxes[-1, :3], want[:3], atol=0.15)  # the median of 4 labels 0.1 m apart
    assert abs((new.boxes[-1, 6] - want[6] + math.pi) % (2 * math.pi) - math.pi) < 1e-5
    assert new.pseudo
    # asked for 5 scans, the car pseudo-labelled in 4 is not a static place: nothing is carried
    _, added3 = propagate_static(pseudo, scans, [ground] * len(scans), min_scans=5)
    assert added3 == 0


def test_tracked_residuals_recover_the_per_axis_miscalibration() -> None:
    """Static objects seen from a moving, turning sensor with sensor-axis noise 2σ in x and 1σ in y (σ the
    predicted SD): the fitted variance scales are ≈ 4 and ≈ 1."""
    rng = np.random.default_rng(0)
    objects = rng.uniform(-30, 30, (25, 2))
    sigma = 0.2
    frames = []
    for k in range(12):
        pose = _pose(1.5 * k, 0.3 * k, 0.05 * k)
        rot, t = pose[:2, :2], pose[:2, 3]
        local = (objects - t) @ rot  # world → sensor
        noisy = local + rng.normal(0, 1, local.shape) * [2 * sigma, sigma]
        boxes = np.zeros((len(objects), 9), np.float32)
        boxes[:, :2] = noisy
        lv = np.full((len(objects), 5), math.log(sigma ** 2), np.float32)
        frames.append((Detections3D(boxes, np.full(len(objects), 0.9, np.float32), np.zeros(len(objects), np.int64),
                                    lv), pose))
    tr = tracked_residuals(frames, gate_m=2.0)
    assert tr.num_tracks == 25 and tr.num_detections == 300
    sx, sy = tr.scales
    assert sx == pytest.approx(4.0, rel=0.2) and sy == pytest.approx(1.0, rel=0.2)


def _dataroot(tmp_path: Path) -> Path:
    root = tmp_path / "root"
    export_scenario(make_scenario("parking-street", 3, duration_s=0.4, rate_hz=10.0), str(root))
    (next(root.glob("v1.0-*")) / "sample_annotation.json").unlink()  # no labels at all: adapt must not need them
    return root


def test_unlabelled_scans_read_without_any_annotation_table(tmp_path: Path) -> None:
    root = _dataroot(tmp_path)
    scans = read_unlabelled([str(root)])
    assert len(scans) == 4 and all(s.has_pose and s.points.shape[1] == 4 for s in scans)
    assert scans[0].source.endswith("#parking-street-3") or "#" in scans[0].source
    assert not np.allclose(scans[0].pose, scans[-1].pose)  # the ego moved
    assert all(s.source.split("#")[0] == str(root.resolve()) for s in scans)  # absolute: metadata survives a cd


@pytest.mark.slow
def test_adapt_cli_writes_weights_that_name_their_scans(tmp_path: Path) -> None:
    root = _dataroot(tmp_path)
    out = tmp_path / "adapted"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "adapt", "--weights",
                          str(Path(__file__).resolve().parents[2] / "jitterguard/services/detector/weights/lite.pt"),
                          "--out", str(out), "--scans", str(root), "--rounds", "1", "--epochs", "1",
                          "--scenarios", "parking-street", "--synthetic-seeds", "0", "--frames-per-scenario", "1",
                          "--recalibration-seeds", "60-62", "--threads", "1", "--no-progress"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    report = json.loads(res.stdout.strip().splitlines()[-1])
    assert report["scans"] == 4 and len(report["report"]["rounds"]) == 1
    model, rec, meta = load_weights(out / "weights.pt")
    assert meta["labels_read"] is False and meta["unlabelled_scans"][0]["scans"] == 4
    assert meta["unlabelled_scans"][0]["recording"].startswith(str(root.resolve()))
    # eval-detector can tell that scoring these weights on this dataroot is test-time adaptation
    # (a folder that holds the scans counts too — they are inside what it would score — a sibling does not)
    assert adapted_on_scans(meta, root) and adapted_on_scans(meta, tmp_path) and not adapted_on_scans({}, root)
    assert not adapted_on_scans(meta, tmp_path / "other")
    assert "adapt" in meta["command"] and meta["adapted_from"]["sha256_16"]
    assert meta["adapt"]["self_crop"] == list(SELF_CROP_M)  # the real scans were cropped as the service crops
    assert rec is not None and json.loads((out / "adapt.json").read_text())["labels_read"] is False
    # the variance scales are refitted after adapting, on labelled synthetic scans (ideal and with effects)
    fit_on = meta["recalibration_fit_on"]
    assert fit_on["seeds"] == "60-62" and fit_on["scans"] == 6 and fit_on["effects"].startswith("none+")
    assert report["report"]["recalibration"]["scales"] == rec.to_payload()
    bad = subprocess.run([sys.executable, "-m", "jitterguard.cli", "adapt", "--weights", str(out / "weights.pt"),
                          "--out", str(out), "--scans", str(root), "--threshold", "car=2"], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "--threshold" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "jitterguard.cli", "adapt", "--weights", str(out / "weights.pt"),
                          "--out", str(out), "--scans", str(root), "--recalibration", "labels"], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "--recalibration" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_adapt_refuses_stacked_sweep_weights_in_one_line(tmp_path: Path) -> None:
    """adapt reads single scans; a five-field (stacked-sweep) model would crash on them mid-run, so it is refused
    up front with exit 2 and a line that says what to do instead."""
    from jitterguard.services.detector.inference import save_weights, shipped_weights
    from jitterguard.services.detector.network import with_time_lag

    model, rec, meta = load_weights(shipped_weights("lite"))
    five = tmp_path / "five.pt"
    save_weights(five, with_time_lag(model), recalibration=rec, meta=meta)
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "adapt", "--weights", str(five), "--out",
                          str(tmp_path / "o"), "--scans", str(_dataroot(tmp_path))], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr[-2000:]
    assert "--weights" in res.stderr and "stacked sweeps" in res.stderr and "--sweeps" in res.stderr
    assert not (tmp_path / "o" / "weights.pt").exists()


def test_flipped_pseudo_labelling_is_mirror_equivariant() -> None:
    """``adapt --flips`` labels with the network averaged over each scan's mirror images: a mirrored scan then gets
    exactly the mirrored labels (a single pass of an untrained network does not)."""
    from jitterguard.services.detector.adapt import _detect_all
    from jitterguard.services.detector.decode import decode

    torch.manual_seed(0)
    model = CenterPointNet(TINY).eval()
    with torch.no_grad():
        model.head.heads["heatmap"][-1].bias.fill_(0.0)  # an untrained net that still fires: many peaks to compare
    scan = _scan(5)
    mirror = scan.copy()
    mirror[:, 1] = -mirror[:, 1]

    def rows(d: Detections3D, flip_y: bool) -> np.ndarray:
        b = d.boxes
        r = np.column_stack([b[:, 0], -b[:, 1] if flip_y else b[:, 1], d.scores, d.labels])
        return r[np.lexsort((r[:, 3], r[:, 1].round(3), r[:, 0].round(3)))]

    (a,), (b,) = _detect_all(model, [scan], decode, flips=True), _detect_all(model, [mirror], decode, flips=True)
    assert len(a) > 10 and len(a) == len(b)
    np.testing.assert_allclose(rows(a, False), rows(b, True), atol=1e-4)
    (c,), (d,) = _detect_all(model, [scan], decode), _detect_all(model, [mirror], decode)
    assert len(c) != len(d) or not np.allclose(rows(c, False), rows(d, True), atol=1e-4)


def test_adapt_draws_a_bar_for_each_pass_over_the_real_scans(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                             ) -> None:
    """Reading scans, recomputing the BatchNorm statistics and pseudo-labelling take minutes on a real recording:
    each has a bar when progress is on (as train's steps do), and none when it is off."""
    from jitterguard.services.detector.adapt import AdaptConfig, UnlabelledScan, adapt

    ticks: list[int] = []
    assert len(read_unlabelled([str(_dataroot(tmp_path))], progress=ticks.append)) == len(ticks) == 4
    scans = [UnlabelledScan(_scan(i), np.eye(4), "rec", str(i), True) for i in range(3)]
    cfg = AdaptConfig(rounds=1, epochs=1, batch_size=2, self_crop=None)
    torch.manual_seed(0)
    adapt(CenterPointNet(TINY), scans, [], cfg, tmp_path / "a", progress=False)
    assert capsys.readouterr().err == ""
    torch.manual_seed(0)
    adapt(CenterPointNet(TINY), scans, [], cfg, tmp_path / "b", progress=True)
    err = capsys.readouterr().err
    for desc in ("BatchNorm statistics", "round 1: pseudo-labels", "round 1: BatchNorm statistics",
                 "tracked recalibration"):
        assert f"{desc}: 100%" in err, desc


@pytest.mark.slow
def test_adapted_weights_keep_what_the_source_was_trained_on(tmp_path: Path) -> None:
    """eval-detector knows the scenes that weights were trained on, also after adapting them, and also when the
    dataroot is named through a symlink: it scores none of their frames unless asked (--holdout-last), and then
    says so."""
    from jitterguard.services.detector.inference import save_weights, shipped_weights

    root = tmp_path / "root"
    export_scenario(make_scenario("parking-street", 3, duration_s=0.4, rate_hz=10.0), str(root))  # with labels
    model, rec, meta = load_weights(shipped_weights("lite"))
    source = {"nuscenes": str(root.resolve()), "holdout_last": 2, "sweeps": 1}
    save_weights(tmp_path / "src.pt", model, recalibration=rec,
                 meta={**meta, "source": source, "train_config": {"epochs": 3}, "world_size": 1})
    out = tmp_path / "adapted"
    cli = [sys.executable, "-m", "jitterguard.cli"]
    res = subprocess.run([*cli, "adapt", "--weights", str(tmp_path / "src.pt"), "--out", str(out), "--scans",
                          str(root), "--rounds", "0", "--recalibration", "keep", "--threads", "1", "--no-progress"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    _, _, adapted = load_weights(out / "weights.pt")
    assert adapted["source"] == source and adapted["augment"] == meta["augment"]
    assert adapted["train_config"] == {"epochs": 3} and adapted["adapted_from"]["source"] == source
    # they say they are adapted, not the source's recipe as their own (the shipped note: "synthetic scans only")
    assert adapted["recipe_note"].startswith("adapted by `jitterguard adapt` from src.pt (sha256 ")
    assert "to 4 unlabelled real scans (labels never read): 0 self-training round(s)" in adapted["recipe_note"]
    assert "variance scales kept from the source weights" in adapted["recipe_note"]
    assert adapted["recipe_note"].endswith(f"The source weights' recipe: {meta['recipe_note']}")
    assert adapted["recipe"] == [*meta["recipe"], adapted["command"]]
    link = tmp_path / "link"
    link.symlink_to(root)
    ev_cmd = [*cli, "eval-detector", "--out", str(tmp_path / "ev"), "--weights", str(out / "weights.pt"),
              "--nuscenes", str(link), "--bootstrap", "0", "--threads", "1", "--no-progress"]
    # its only scene trained the network (a held-out tail is still the scene): no cross-scene figure to give
    ev = subprocess.run(ev_cmd, capture_output=True, text=True, timeout=600)
    assert ev.returncode == 2 and "--nuscenes: the weights were trained on the labels of every scene" in ev.stderr
    ev = subprocess.run([*ev_cmd, "--holdout-last", "2"], capture_output=True, text=True, timeout=600)
    assert ev.returncode == 0, ev.stderr[-3000:]
    scored = json.loads((tmp_path / "ev" / "holdout.json").read_text())["scored_on"]
    assert scored["weights_trained_on_it"] is True and scored["holdout_last"] == 2 and scored["key_frames"] == 2
    assert scored["scored_scenes_trained_on"] == scored["scenes"] != [] and "within-scene" in ev.stderr
    assert scored["weights_adapted_on_its_scans"] is True and scored["nuscenes"] == str(root.resolve())
