"""Is a sparse car lost to its own few returns or to what stands around it? A counterfactual on scans (docs/detector.md,
"What a sparse car needs").

    .venv/bin/python scripts/sparse_context.py [--weights W] [--effects random,vegetation] [--seeds 1000-1001]

For every labelled car within 50 m carrying 1–19 returns, the detector (run as ``jitterguard eval-detector`` runs it:
the self-crop, the road plane measured, the variances recalibrated) is asked three times: on the scan as it is; on
the scan with every return above the road within ``--radius`` m of the car taken away but the car's own
(``cleared``); and on the road alone with the car's own returns (``alone``: every other object, shrub, wall and
pole of the scan gone); and, to tell which surroundings, with only the other labelled objects' returns within the
radius taken away (``cleared_objects``), or only the returns there that lie in no labelled box — vegetation, walls,
poles, kerbside clutter (``cleared_background``), and for the cars found only then, where those returns lie
(nearer the sensor than the car, beyond it, within 3 m of its line of sight; their heights). A car counts as found
when a car box scoring ≥ 0.3 lies within 2 m of it. The same is done on synthetic hold-out scans with the
sim-to-real effects, whose sparse cars the network finds far more often: if clearing the surroundings recovers the
real sparse cars and not the synthetic ones, the surroundings are what the synthetic world lacks; if neither
recovers them, the car's own returns are. Reads scene-0523's labels — a
diagnosis, never a number fitted to the scene. Prints JSON.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from jitterguard.services.detector.augment import filter_range, points_in_boxes
from jitterguard.services.detector.config import CLASS_NAMES, SELF_CROP_M
from jitterguard.services.detector.data import nuscenes_samples, synthetic_samples
from jitterguard.services.detector.ground import ground_plane
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.train_cli import DEFAULT_SCENARIOS

CAR = CLASS_NAMES.index("car")
ROAD_BAND_M = 0.25
"""A return this close to the fitted road plane (or below it) is road, kept in every variant."""
BANDS = ((1, 5), (5, 20))


def _found(det, xy: np.ndarray) -> bool:  # noqa: ANN001 - Detections3D
    m = (det.labels == CAR) & (det.scores >= 0.3)
    return bool(m.any() and np.min(np.hypot(*(det.boxes[m, :2] - xy).T)) < 2.0)


def sparse_car_recall(det: Detector, samples, radius: float) -> dict:  # noqa: ANN001 - Samples
    rows, where = [], []
    for s in samples:
        boxes = s.boxes[s.labels == CAR] if len(s.boxes) else s.boxes
        if not len(boxes):
            continue
        boxes = boxes[np.hypot(boxes[:, 0], boxes[:, 1]) < 50.0]
        p = s.points
        plane = ground_plane(p)
        if plane is None or not len(boxes):
            continue
        above = p[:, 2] - (plane.slope_x * p[:, 0] + plane.slope_y * p[:, 1] - plane.height) > ROAD_BAND_M
        grown = boxes.copy()
        grown[:, 3:6] += 0.4  # the car's own returns, with a margin for the label's own error
        inside = points_in_boxes(p, grown)
        own_counts = points_in_boxes(p, boxes).sum(axis=0)
        all_grown = s.boxes.copy()
        all_grown[:, 3:6] += 0.4
        in_any = points_in_boxes(p, all_grown).any(axis=1)  # on some labelled object (this car included)
        full = det.detect(p)
        for j, b in enumerate(boxes):
            n = int(own_counts[j])
            if not 1 <= n < BANDS[-1][1]:
                continue
            own = inside[:, j]
            near = np.hypot(p[:, 0] - b[0], p[:, 1] - b[1]) < radius
            around = above & near & ~own
            variants = (p[~around], p[~above | own], p[~(around & in_any)], p[~(around & ~in_any)])
            rows.append((n, _found(full, b[:2]), *(_found(det.detect(v), b[:2]) for v in variants)))
            if not rows[-1][1] and rows[-1][5]:  # found once the unlabelled returns around it are gone: where are they
                q, hq = p[around & ~in_any], (p[:, 2] - (plane.slope_x * p[:, 0] + plane.slope_y * p[:, 1]
                                                         - plane.height))[around & ~in_any]
                rc, rq = np.hypot(*b[:2]), np.hypot(q[:, 0], q[:, 1])
                off = np.abs((np.arctan2(q[:, 1], q[:, 0]) - np.arctan2(b[1], b[0]) + np.pi) % (2 * np.pi) - np.pi) * rc
                where.append((len(q), np.mean(rq < rc - 1.0), np.mean(rq > rc + 1.0), np.mean(off < 3.0),
                              *np.percentile(hq, [10, 50, 90])))
    a = np.array(rows, dtype=np.float64).reshape(-1, 6)
    out = {}
    for lo, hi in BANDS:
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        out[f"{lo}-{hi - 1} returns"] = {"cars": int(m.sum()), **{
            k: round(float(a[m, i].mean()), 3) if m.any() else None
            for i, k in enumerate(("found_as_is", "found_cleared", "found_alone", "found_cleared_objects",
                                   "found_cleared_background"), start=1)}}
    w = np.array(where, dtype=np.float64).reshape(-1, 7)
    out["found_once_unlabelled_cleared"] = {"cars": len(w), **({
        k: round(float(np.median(w[:, i])), 2) for i, k in enumerate(
            ("returns_cleared", "share_nearer_than_the_car", "share_beyond_it", "share_within_3m_of_its_line_of_sight",
             "height_p10", "height_p50", "height_p90"))} if len(w) else {})}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--effects", default="random,vegetation", help="the synthetic control scans' effects")
    ap.add_argument("--seeds", default="1000-1001")
    ap.add_argument("--radius", type=float, default=6.0, help="cleared around the car, m")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    det = Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M)
    rng = det.config.point_cloud_range
    lo, _, hi = a.seeds.partition("-")
    seeds = list(range(int(lo), int(hi or lo) + 1))
    real = [filter_range(s, rng) for s in nuscenes_samples(a.nuscenes)]
    synthetic = [filter_range(s, rng) for s in synthetic_samples(DEFAULT_SCENARIOS.split(","), seeds,
                                                                  frames_per_scenario=5, effects=a.effects)]
    print(json.dumps({"weights": a.weights or "shipped lite", "radius_m": a.radius,
                      "real": sparse_car_recall(det, real, a.radius),
                      f"synthetic {a.effects}": sparse_car_recall(det, synthetic, a.radius)}, indent=1))


if __name__ == "__main__":
    main()
