"""Experiment (docs/results.md, "What the detector's static false alarms are made of"; tuning seeds only): is the
slide of a parked car's detected centre a placement the classifier could undo?

    .venv/bin/python scripts/centre_bias.py --scenario diagonal-lot --seeds 0-3 --input detector --anchors
    .venv/bin/python scripts/centre_bias.py --scenario diagonal-lot --seeds 0-3 --input detector --table-on 0,1

``--anchors``: each static vehicle's detections (matched to its label within 2 m, frame by frame, no tracker) in
windows of 20; the half-mean contrast |d| of the box centre against three points a tracker could follow instead
(Autoware's anchor-point idea): the box corner nearest the sensor, the middle of the face that looks at it, and
the centre placed back from that corner with the window's median length and width (a box whose extent guess
changes moves its centre by half the change). ``--table-on SEEDS``: a table of the mean centre error in the box's
own frame per bearing of the sensor in that frame (24 bins) and range band, fitted on the labels of SEEDS and
subtracted from every vehicle detection of the other seeds before the evaluator's tracker and classifier (one
online calibration, as ``jitterguard eval --runs``); vehicle and pedestrian rates with and without it. Labels
are read by the diagnosis and the table fit only. A record of an experiment, not a feature (not shipped).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import input_arguments, seed_pairs  # noqa: E402
from jitterguard.eval.metrics import ghost_rows, scored_rows  # noqa: E402
from jitterguard.eval.pipeline import concat_records, track_and_classify  # noqa: E402
from jitterguard.geometry import sensor_to_world_xy, world_to_sensor_xy, yaw_from_quaternion, yaws_from_quaternions  # noqa: E402
from jitterguard.schemas import read_detected_objects  # noqa: E402
from jitterguard.schemas.models import ClassifierConfig, Label  # noqa: E402
from jitterguard.schemas.wire import DetectedColumns, write_detected_objects  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC, MotionClassifierCore  # noqa: E402
from jitterguard.services.tracker.config import default_config  # noqa: E402

POSE = "kinematics.pose_with_covariance.pose."
VEHICLES = (Label.CAR, Label.TRUCK, Label.BUS, Label.TRAILER)
BEARING_BINS = 24
RANGE_EDGES = np.array([15.0, 30.0])
WINDOW = 20


def _boxes(cols: DetectedColumns) -> tuple[np.ndarray, ...]:
    """Vehicle mask, sensor-frame x, y, yaw, length, width of every detection of one payload."""
    o = cols.objects
    q = (o[POSE + "orientation.x"], o[POSE + "orientation.y"], o[POSE + "orientation.z"], o[POSE + "orientation.w"])
    return (np.isin(o["classification.0.label"], VEHICLES), o[POSE + "position.x"], o[POSE + "position.y"],
            yaws_from_quaternions(*q), o["shape.dimensions.x"], o["shape.dimensions.y"])


def _to_sensor(cols: DetectedColumns, xy: np.ndarray) -> np.ndarray:
    """World points (N, 2) into the payload's sensor frame."""
    p = cols.ego_pose
    yaw = yaw_from_quaternion(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
    return np.stack(world_to_sensor_xy(xy[:, 0], xy[:, 1], p.position.x, p.position.y, yaw), 1)


def _matches(gt, cols: DetectedColumns, *, static_only: bool) -> list[tuple[str, int, np.ndarray]]:  # noqa: ANN001
    """(instance, detection index, the label's centre in the sensor frame) per labelled vehicle with a vehicle
    detection within 2 m."""
    veh, x, y = _boxes(cols)[:3]
    centres = _to_sensor(cols, np.asarray(gt.centers)[:, :2])
    out = []
    for j in range(gt.num_objects):
        if gt.labels[j] not in VEHICLES or (static_only and gt.moving[j]):
            continue
        dist = np.where(veh, np.hypot(x - centres[j, 0], y - centres[j, 1]), np.inf)
        if dist.size and dist.min() <= 2.0:
            out.append((str(gt.instance_ids[j]), int(dist.argmin()), centres[j]))
    return out


def anchors(pairs: dict) -> None:
    """|d| of the centre against three anchor points (world frame), static vehicles, windows of 20 detections."""
    contrast: dict[str, list[float]] = {"centre": [], "nearest corner": [], "facing side": [], "centre, fixed extent": []}
    for frames in pairs.values():
        seq: dict[str, list[tuple[float, ...]]] = {}
        for gt, payload in frames:
            cols = read_detected_objects(payload)
            _, x, y, yaw, length, width = _boxes(cols)
            p = cols.ego_pose
            ego_yaw = yaw_from_quaternion(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
            wx, wy = sensor_to_world_xy(x, y, p.position.x, p.position.y, ego_yaw)
            for inst, k, _ in _matches(gt, cols, static_only=True):
                seq.setdefault(inst, []).append((wx[k], wy[k], yaw[k] + ego_yaw, length[k], width[k],
                                                 p.position.x, p.position.y))
        for obs in seq.values():
            a = np.array(obs)
            for end in range(WINDOW, len(a) + 1):
                cx, cy, yw, ln, wd, sx, sy = a[end - WINDOW:end].T
                head, side = np.stack([np.cos(yw), np.sin(yw)], 1), np.stack([-np.sin(yw), np.cos(yw)], 1)
                centre = np.stack([cx, cy], 1)
                look = np.stack([sx - cx, sy - cy], 1)  # towards the sensor
                look /= np.maximum(np.linalg.norm(look, axis=1, keepdims=True), 1e-9)
                sh, ss = np.sign((head * look).sum(1))[:, None], np.sign((side * look).sum(1))[:, None]
                corner = centre + 0.5 * ln[:, None] * sh * head + 0.5 * wd[:, None] * ss * side
                ends = np.abs((head * look).sum(1)) > np.abs((side * look).sum(1))
                facing = centre + np.where(ends[:, None], 0.5 * ln[:, None] * sh * head, 0.5 * wd[:, None] * ss * side)
                fixed = corner - 0.5 * np.median(ln) * sh * head - 0.5 * np.median(wd) * ss * side
                half = WINDOW // 2
                for name, p in zip(contrast, (centre, corner, facing, fixed)):
                    contrast[name].append(float(np.linalg.norm(p[half:].mean(0) - p[:half].mean(0))))
    for name, v in contrast.items():
        d = np.array(v)
        print(f"{name:>21}: windows {d.size}, |d| median {np.median(d):.3f} m, 90 % {np.quantile(d, 0.9):.3f}, "
              f"99 % {np.quantile(d, 0.99):.3f}; share over 0.5 m {np.mean(d > 0.5):.4f}, over 0.8 m {np.mean(d > 0.8):.4f}")


def _bearing_cells(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bearing bin of the sensor in each box's own frame, and the range band."""
    bx = np.cos(yaw) * -x + np.sin(yaw) * -y
    by = -np.sin(yaw) * -x + np.cos(yaw) * -y
    b = np.floor((np.arctan2(by, bx) + np.pi) / (2 * np.pi) * BEARING_BINS).astype(int) % BEARING_BINS
    return b, np.searchsorted(RANGE_EDGES, np.hypot(x, y))


def fit_table(pairs: dict, seeds: list[int], prior: float = 30.0) -> np.ndarray:
    """Median centre error (along, across the box) per bearing bin and range band, shrunk to 0 with ``prior``
    pseudo-observations."""
    cells: dict[tuple[int, int], list[tuple[float, float]]] = {}
    for seed in seeds:
        for gt, payload in pairs[seed]:
            cols = read_detected_objects(payload)
            _, x, y, yaw, _, _ = _boxes(cols)
            b, band = _bearing_cells(x, y, yaw)
            for _, k, c in _matches(gt, cols, static_only=False):
                ex, ey = x[k] - c[0], y[k] - c[1]
                along, across = np.cos(yaw[k]) * ex + np.sin(yaw[k]) * ey, -np.sin(yaw[k]) * ex + np.cos(yaw[k]) * ey
                cells.setdefault((int(b[k]), int(band[k])), []).append((along, across))
    table = np.zeros((BEARING_BINS, len(RANGE_EDGES) + 1, 2))
    for (b_, band_), errs in cells.items():
        table[b_, band_] = np.median(errs, 0) * len(errs) / (len(errs) + prior)
    return table


def debiased(frames: list, table: np.ndarray) -> list:
    """The frames with the table's error subtracted from every vehicle detection's centre."""
    out = []
    for gt, payload in frames:
        cols = read_detected_objects(payload)
        cols = dataclasses.replace(cols, objects=np.frombuffer(bytearray(cols.objects.tobytes()), cols.objects.dtype))
        veh, x, y, yaw, _, _ = _boxes(cols)
        b, band = _bearing_cells(x, y, yaw)
        along, across = table[b, band, 0] * veh, table[b, band, 1] * veh
        cols.objects[POSE + "position.x"] = x - (np.cos(yaw) * along - np.sin(yaw) * across)
        cols.objects[POSE + "position.y"] = y - (np.sin(yaw) * along + np.cos(yaw) * across)
        out.append((gt, write_detected_objects(cols)))
    return out


def rates(runs: list) -> str:
    """Vehicle and pedestrian z-test (threshold) rates of the evaluator's pipeline over ``runs`` as one drive."""
    clf = ClassifierConfig()
    drive = MotionClassifierCore.make_online(clf)
    rec = concat_records([track_and_classify(iter(f), clf, default_config(), calibration=drive) for f in runs],
                         [str(i) for i in range(len(runs))])
    out = []
    for group in ("vehicle", "pedestrian"):
        m = scored_rows(rec, group)
        static, moving, ghost = m & ~rec.gt_dynamic, m & rec.gt_dynamic, ghost_rows(rec, group)

        def rate(mask: np.ndarray, dynamic: bool, state: np.ndarray) -> str:
            return f"{np.mean((state[mask] == DYNAMIC) == dynamic):.4f}" if mask.any() else "-"

        out.append(f"{group[0].upper()} false {rate(static, True, rec.state_z)} ({rate(static, True, rec.state_v)}) "
                   f"missed {rate(moving, False, rec.state_z)} ({rate(moving, False, rec.state_v)}) "
                   f"ghost {rate(ghost, True, rec.state_z)}")
    return " | ".join(out) + "   (threshold in brackets)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--anchors", action="store_true")
    ap.add_argument("--table-on", default=None, help="seeds whose labels fit the bias table, e.g. 0,1")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    if args.anchors:
        anchors(pairs)
    if args.table_on:
        fit = [int(s) for s in args.table_on.split(",")]
        table = fit_table(pairs, fit)
        test = [pairs[s] for s in pairs if s not in fit]
        print(f"table fitted on seeds {fit}: |mean error| up to {np.abs(table).max():.3f} m, mean {np.abs(table).mean():.3f} m")
        print("as detected:", rates(test), flush=True)
        print("debiased:   ", rates([debiased(f, table) for f in test]), flush=True)


if __name__ == "__main__":
    main()
