"""How a sparse car's few returns look, real against synthetic (docs/detector.md, "Clear glass"): per band of
returns inside the box (1–4, 5–19, 20–49; cars within 50 m), the median range, the number of beams that hit the car
(rings, from each return's elevation at HDL-32E's 1.33° spacing), how much of the box's length and width the
returns span, and where they sit in the box's height (0 its bottom, 1 its top: lowest, highest, median return).

    .venv/bin/python scripts/sparse_cars.py --effects random,vegetation --effects random,vegetation,clear-glass

The real figures read scene-0523's labelled car boxes (a diagnosis of the sim-to-real gap, as ``jitterguard
domain-gap`` does); synthetic scans: hold-out seeds 1000–1001, 5 frames per scenario. Prints JSON.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from jitterguard.services.detector.augment import points_in_boxes
from jitterguard.services.detector.config import CLASS_NAMES, Sample
from jitterguard.services.detector.data import nuscenes_samples, synthetic_samples
from jitterguard.services.detector.train_cli import DEFAULT_SCENARIOS

CAR = CLASS_NAMES.index("car")
BANDS = ((1, 5), (5, 20), (20, 50))
RING_DEG = 1.33


def sparse_car_shapes(samples: list[Sample]) -> dict:
    rows = []
    for s in samples:
        p = s.points[np.linalg.norm(s.points[:, :3], axis=1) >= 1.0]
        boxes = s.boxes[s.labels == CAR]
        boxes = boxes[np.hypot(boxes[:, 0], boxes[:, 1]) < 50.0] if len(boxes) else boxes
        if not len(boxes):
            continue
        inside = points_in_boxes(p, boxes)
        for j, b in enumerate(boxes):
            q = p[inside[:, j]]
            if not 1 <= len(q) < BANDS[-1][1]:
                continue
            c, sn = np.cos(b[6]), np.sin(b[6])
            rel = q[:, :2] - b[:2]
            lx, ly = rel[:, 0] * c + rel[:, 1] * sn, -rel[:, 0] * sn + rel[:, 1] * c
            el = np.degrees(np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1])))
            zrel = (q[:, 2] - (b[2] - b[5] / 2)) / b[5]
            rows.append((len(q), np.hypot(b[0], b[1]), len(np.unique(np.round(el / RING_DEG))), np.ptp(lx) / b[3],
                         np.ptp(ly) / b[4], zrel.min(), zrel.max(), np.median(zrel)))
    a = np.array(rows).reshape(-1, 8)
    out = {}
    for lo, hi in BANDS:
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        med = [round(float(np.median(a[m, k])), 2) if m.any() else None for k in range(1, 8)]
        out[f"{lo}-{hi - 1} returns"] = dict(zip(("cars", "range_m", "rings", "length_spanned", "width_spanned",
                                                  "lowest", "highest", "median_height"), [int(m.sum()), *med]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--effects", action="append", default=None, help="synthetic scans' effects, one set per flag")
    ap.add_argument("--seeds", default="1000-1001")
    a = ap.parse_args()
    lo, _, hi = a.seeds.partition("-")
    seeds = list(range(int(lo), int(hi or lo) + 1))
    out = {"real": sparse_car_shapes(nuscenes_samples(a.nuscenes))}
    for e in a.effects or ["random,vegetation"]:
        out[f"synthetic {e}"] = sparse_car_shapes(list(synthetic_samples(DEFAULT_SCENARIOS.split(","), seeds,
                                                                         frames_per_scenario=5, effects=e)))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
