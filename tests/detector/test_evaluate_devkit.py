"""Cross-check of :func:`detection_ap` against nuscenes-devkit's own ``DetectionEval`` on an exported scene.

A short synthetic scenario is exported as a nuScenes dataroot; predictions are made from its ground truth
(jittered by 0.05–3 m so every threshold matters, some dropped, some duplicated, some relabelled, false
positives up to 60 m so the range filter bites, scores rounded to 0.05 so ties are common), written as a
devkit submission in the global frame and scored by ``DetectionEval`` on a custom split (``splits.json``).
Our AP, from the same boxes in the sensor frame, must agree per class and threshold, down to the 101-point
precision curves.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from jitterguard.geometry import sensor_to_world_xy, world_to_sensor_xy
from jitterguard.services.detector.config import CLASS_NAMES, Detections3D, Sample
from jitterguard.services.detector.evaluate import DIST_THRESHOLDS_M, detection_ap, threshold_key
from jitterguard.sim import make_scenario
from jitterguard.sim.export import export_scenario, quaternion_wxyz
from helpers import iter_scans
from jitterguard.sim.world import SENSOR_HEIGHT_M, GroundTruthFrame

nuscenes = pytest.importorskip("nuscenes.nuscenes")
from nuscenes.eval.common.config import config_factory  # noqa: E402
from nuscenes.eval.detection.evaluate import DetectionEval  # noqa: E402
from nuscenes.eval.detection.utils import category_to_detection_name  # noqa: E402

SPLIT = "jg_crosscheck"


def sample_from_frame(frame: GroundTruthFrame, categories: dict[int, str]) -> Sample:
    """Sensor-frame ground truth of the devkit's five classes (motorcycles and trailers are classes of their
    own in nuScenes, so they are left out here rather than folded in as the detector does)."""
    names = [category_to_detection_name(categories[int(i)]) for i in frame.instance_ids]
    keep = np.array([n in CLASS_NAMES for n in names], dtype=bool)
    x, y = world_to_sensor_xy(frame.centers[keep, 0], frame.centers[keep, 1], frame.ego_x, frame.ego_y,
                              frame.ego_yaw)
    b = np.zeros((int(keep.sum()), 9), np.float32)
    b[:, 0], b[:, 1] = x, y
    b[:, 2] = frame.centers[keep, 2] - SENSOR_HEIGHT_M
    b[:, 3:6] = frame.sizes[keep]
    b[:, 6] = frame.yaws[keep] - frame.ego_yaw
    labels = np.array([CLASS_NAMES.index(n) for n, k in zip(names, keep) if k], np.int64)
    return Sample(np.zeros((0, 4), np.float32), b, labels, frame.num_points[keep].astype(np.int64))


def predict(s: Sample, rng: np.random.Generator) -> Detections3D:
    """Detections from ground truth with errors of every size, misses, duplicates, confusions and clutter."""
    n = len(s.labels)
    keep = rng.random(n) > 0.15
    err = rng.choice([0.05, 0.3, 0.7, 1.5, 3.0], size=n)[:, None] * rng.normal(size=(n, 2)) / math.sqrt(2)
    b = s.boxes.copy()
    b[:, :2] += err
    labels = np.where(rng.random(n) < 0.05, rng.integers(0, 5, n), s.labels)
    score = np.clip(1.0 - np.hypot(err[:, 0], err[:, 1]) / 4 + rng.normal(0, 0.2, n), 0.05, 1.0)
    dup = keep & (rng.random(n) < 0.1)
    b_dup = s.boxes[dup].copy()
    b_dup[:, :2] += rng.normal(0, 0.3, (int(dup.sum()), 2))
    n_fp = int(rng.poisson(8))
    r, phi = 60 * np.sqrt(rng.random(n_fp)), rng.uniform(-np.pi, np.pi, n_fp)
    b_fp = np.zeros((n_fp, 9), np.float32)
    b_fp[:, 0], b_fp[:, 1], b_fp[:, 3:6] = r * np.cos(phi), r * np.sin(phi), (4.0, 1.8, 1.5)
    boxes = np.concatenate([b[keep], b_dup, b_fp]).astype(np.float32)
    scores = np.concatenate([score[keep], rng.uniform(0.05, 0.6, len(b_dup)), rng.uniform(0.05, 0.9, n_fp)])
    scores = (np.round(scores * 20) / 20).astype(np.float32)  # many exact ties: the order rule must match
    labs = np.concatenate([labels[keep], s.labels[dup], rng.integers(0, 5, n_fp)]).astype(np.int64)
    perm = rng.permutation(len(labs))
    return Detections3D(boxes[perm], scores[perm], labs[perm], None)


def submission_boxes(d: Detections3D, frame: GroundTruthFrame, sample_token: str) -> list[dict[str, object]]:
    x, y = sensor_to_world_xy(d.boxes[:, 0], d.boxes[:, 1], frame.ego_x, frame.ego_y, frame.ego_yaw)
    out = []
    for k in range(len(d)):
        b = d.boxes[k]
        out.append({
            "sample_token": sample_token,
            "translation": [float(x[k]), float(y[k]), float(b[2]) + SENSOR_HEIGHT_M],
            "size": [float(b[4]), float(b[3]), float(b[5])],  # nuScenes: width, length, height
            "rotation": quaternion_wxyz(float(b[6]) + frame.ego_yaw),
            "velocity": [0.0, 0.0],
            "detection_name": CLASS_NAMES[int(d.labels[k])],
            "detection_score": float(d.scores[k]),
            "attribute_name": "",
        })
    return out


@pytest.fixture(scope="module")
def crosscheck(tmp_path_factory: pytest.TempPathFactory):
    sc = make_scenario("parking-street", 4, duration_s=4.0, rate_hz=2.0)  # all five classes in range
    root = str(tmp_path_factory.mktemp("nusc"))
    export_scenario(sc, root, seed=1)  # zero-point boxes are annotated: the devkit's point filter must bite
    frames = [f for f, _ in iter_scans(sc, seed=1)]  # the same casts, for num_points in our samples
    nusc = nuscenes.NuScenes(version="v1.0-mini", dataroot=root, verbose=False)
    with open(os.path.join(root, "v1.0-mini", "splits.json"), "w") as fh:
        json.dump({SPLIT: [nusc.scene[0]["name"]]}, fh)
    tokens, tok = [], nusc.scene[0]["first_sample_token"]
    while tok:
        tokens.append(tok)
        tok = nusc.get("sample", tok)["next"]
    assert len(tokens) == len(frames) == 8
    rng = np.random.default_rng(7)
    samples = [sample_from_frame(f, sc.categories) for f in frames]
    preds = [predict(s, rng) for s in samples]
    results = {t: submission_boxes(d, f, t) for t, d, f in zip(tokens, preds, frames)}
    sub = os.path.join(root, "results.json")
    with open(sub, "w") as fh:
        json.dump({"meta": {"use_lidar": True, "use_camera": False, "use_radar": False, "use_map": False,
                            "use_external": False}, "results": results}, fh)
    ev = DetectionEval(nusc, config_factory("detection_cvpr_2019"), sub, SPLIT,
                       output_dir=os.path.join(root, "eval"), verbose=False)
    metrics, md_list = ev.evaluate()
    ours = detection_ap(preds, samples)
    return ev, metrics, md_list, ours, samples


def test_ap_matches_devkit_per_class_and_threshold(crosscheck) -> None:
    ev, metrics, md_list, ours, samples = crosscheck
    compared = 0
    for name in CLASS_NAMES:
        c = ours["classes"][name]
        n_dev = sum(b.detection_name == name for b in ev.gt_boxes.all)
        assert c["num_gt"] == n_dev, name  # same range and point filters
        assert c["num_pred"] == sum(b.detection_name == name for b in ev.pred_boxes.all), name
        for th in DIST_THRESHOLDS_M:
            dev = metrics.get_label_ap(name, th)
            if n_dev == 0:
                assert dev == 0.0 and math.isnan(c["ap"][threshold_key(th)])  # the documented difference
                continue
            assert c["ap"][threshold_key(th)] == pytest.approx(dev, abs=1e-9), (name, th)
            np.testing.assert_allclose(c["precision"][threshold_key(th)], md_list[(name, th)].precision,
                                       atol=1e-9, err_msg=f"{name} @ {th} m")
            compared += 1
    # the check is only worth something if the scene exercises it
    assert compared == 5 * 4
    car = ours["classes"]["car"]["ap"]
    assert 0.05 < car["0.5"] < car["1"] < car["2"] < car["4"] < 0.99
    assert ours["classes"]["pedestrian"]["num_gt"] > 20
    unfiltered = sum(int((s.num_points == 0).sum()) for s in samples)
    assert unfiltered > 0  # zero-point boxes were present and dropped by both
