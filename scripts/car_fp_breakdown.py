"""Where a detector's real car AP goes: its car boxes by what they lie on, what AP would be without each kind of
false positive, and what the returns under the background boxes look like (docs/detector.md, "Vegetation masses").

    .venv/bin/python scripts/car_fp_breakdown.py [--weights W] [--flips] [--nuscenes ../shared/data/nuscenes-scene-0523]

Runs the detector as ``jitterguard eval-detector`` does (the scans in the vehicle's axes, the self-crop, the
recalibrated variances) and reads the scene's labels — for diagnosis only: what it prints may guide what the
synthetic world should add, never a number fitted to the scene. Car boxes scored ≥ ``--min-score`` are split
into those within 2 m of a labelled car, within 3 m of a truck or bus, and 4 m or more from any labelled object
("background"); the AP lines drop one kind of false positive at a time (an oracle, not a method). Prints JSON.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from jitterguard.services.detector.augment import filter_range
from jitterguard.services.detector.config import CLASS_NAMES, SELF_CROP_M
from jitterguard.services.detector.data import nuscenes_samples
from jitterguard.services.detector.evaluate import detection_ap
from jitterguard.services.detector.inference import Detector

CAR, TRUCK, BUS = (CLASS_NAMES.index(n) for n in ("car", "truck", "bus"))


def _kind(sample, box) -> str:  # noqa: ANN001 - a Sample and one predicted box
    dist = np.hypot(*(sample.boxes[:, :2] - box[:2]).T) if len(sample.boxes) else np.full(1, np.inf)
    labels = sample.labels if len(sample.boxes) else np.full(1, -1)
    if np.any((dist < 2.0) & (labels == CAR)):
        return "car"
    if np.any((dist < 3.0) & np.isin(labels, [TRUCK, BUS])):
        return "truck_or_bus"
    return "background" if not np.any(dist < 4.0) else "near_other"


def _column(sample, box) -> tuple[float, float]:  # noqa: ANN001
    """Highest return above the road in the box's column (1 m larger than the box) and the share of its returns
    within 0.3 m of the road (the road: the 5th percentile of the heights within 15 m of the sensor)."""
    p = sample.points
    road = np.percentile(p[np.hypot(p[:, 0], p[:, 1]) < 15.0, 2], 5)
    c, s = np.cos(box[6]), np.sin(box[6])
    rel = p[:, :2] - box[:2]
    lx, ly = rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c
    z = p[(np.abs(lx) < box[3] / 2 + 0.5) & (np.abs(ly) < box[4] / 2 + 0.5), 2] - road
    return (float(z.max()), float(np.mean(z < 0.3))) if len(z) else (float("nan"), float("nan"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--min-score", type=float, default=0.4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--flips", action="store_true", help="the detector with test-time flips")
    a = ap.parse_args()
    det = Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M, flips=a.flips)
    samples = [filter_range(s, det.config.point_cloud_range) for s in nuscenes_samples(a.nuscenes)]
    dets = [det.detect(s.points) for s in samples]
    kinds: list[list[str]] = [[_kind(s, b) if lab == CAR else "" for b, lab in zip(d.boxes, d.labels)]
                              for s, d in zip(samples, dets)]
    out: dict = {"weights": a.weights or "shipped lite", "flips": a.flips, "scans": len(samples),
                 "min_score": a.min_score}
    counts: dict[str, int] = {}
    columns: dict[str, list[tuple[float, float]]] = {"car": [], "background": []}
    for s, d, ks in zip(samples, dets, kinds):
        for b, sc, k in zip(d.boxes, d.scores, ks):
            if k and sc >= a.min_score:
                counts[k] = counts.get(k, 0) + 1
                if k in columns:
                    columns[k].append(_column(s, b))
    out["car_boxes_by_kind"] = counts
    for k, rows in columns.items():
        arr = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
        out[f"{k}_column"] = {"top_above_road_m_p10_50_90": np.round(np.nanpercentile(arr[:, 0], [10, 50, 90]), 2).tolist(),
                              "share_near_road_p10_50_90": np.round(np.nanpercentile(arr[:, 1], [10, 50, 90]), 2).tolist()}

    def car_ap(drop: str | None) -> float:
        kept = [d.subset(np.array([k != drop for k in ks], dtype=bool)) for d, ks in zip(dets, kinds)]
        return round(float(detection_ap(kept, samples)["classes"]["car"]["mean_ap"]), 3)

    out["car_ap"] = {"as_is": car_ap(None), "without_background": car_ap("background"),
                     "without_truck_or_bus": car_ap("truck_or_bus")}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
