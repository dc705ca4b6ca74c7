"""Which real cars does the detector miss, and is it their intensity, how much of them is seen, or their
neighbours? (docs/detector.md, "What stands around a sparse car" and "A row of nose-in cars").

    .venv/bin/python scripts/real_car_misses.py [--weights W] [--nuscenes ../shared/data/nuscenes-scene-0523] [--seeds 1000-1001] [--effects random,vegetation]

For every labelled car within 50 m the detector (run as ``jitterguard eval-detector`` runs it) is asked whether a car
box scoring ≥ 0.3 lies within 2 m of it, on the real scene and on synthetic hold-out scans with the shipped recipe's
effects (``random,vegetation``). Three views of the gap: (a) found by returns and by how much of the car's length or
width its returns span (a partly hidden car shows a slice: is a slice what the network cannot read?); (b) the found
and missed cars with 5–49 returns side by side — range, the box's bottom and the lowest return over the road plane
measured under the scan, the heading's angle to the line of sight, the highest return as a share of the box's
height, the share of cars with a pedestrian detection (≥ 0.3, none within 1 m of a labelled pedestrian) within 3 m
of the car's centre or inside its box (+0.3 m), whether it stands in a row (another vehicle's centre within
3.5 m: side by side in a lot), the best car score within 2 m; (c) found by returns in a row and alone; (d) the
scans' intensities zeroed, halved, doubled, shuffled among the points or all set to their median (does the network
read intensity at all?). Reads the scene's labels — a diagnosis, never a number fitted to the scene. Prints JSON.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable

import numpy as np

from jitterguard.services.detector.augment import filter_range, points_in_boxes
from jitterguard.services.detector.config import CLASS_NAMES, SELF_CROP_M
from jitterguard.services.detector.data import nuscenes_samples, synthetic_samples
from jitterguard.services.detector.ground import ground_plane
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.train_cli import DEFAULT_SCENARIOS

CAR = CLASS_NAMES.index("car")
RETURN_BANDS = ((1, 5), (5, 20), (20, 50), (50, 100_000))
SPAN_BANDS = ((0.0, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 9.0))
PEDESTRIAN = CLASS_NAMES.index("pedestrian")
FIELDS = ("returns", "span", "range_m", "bottom_over_road_m", "lowest_return_over_road_m", "aspect_deg",
          "top_return_of_height", "pedestrian_within_3m", "pedestrian_in_box", "in_a_row", "best_score", "found")
ROW_M = 3.5
"""A car "in a row": another labelled car's, truck's or bus's centre within this distance (side by side in a lot,
two stalls apart at most; bumper to bumper along a kerb is 5 m or more)."""
VEHICLES = [CLASS_NAMES.index(n) for n in ("car", "truck", "bus")]


def car_rows(det: Detector, samples, intensity: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:  # noqa: ANN001
    """One row per labelled car within 50 m with a return (columns: :data:`FIELDS`)."""
    rows = []
    for s in samples:
        boxes = s.boxes[(s.labels == CAR) & (np.hypot(s.boxes[:, 0], s.boxes[:, 1]) < 50.0)] if len(s.boxes) else s.boxes
        if not len(boxes):
            continue
        points = s.points
        if intensity is not None:
            points = points.copy()
            points[:, 3] = intensity(points[:, 3])
        plane = ground_plane(points)
        d = det.detect(points)
        cars = d.labels == CAR
        inside = points_in_boxes(points, boxes)
        walkers = s.boxes[s.labels == PEDESTRIAN]
        peds = d.boxes[(d.labels == PEDESTRIAN) & (d.scores >= 0.3)]
        if len(walkers) and len(peds):  # a labelled pedestrian's own detection is no confusion
            peds = peds[np.hypot(peds[:, None, 0] - walkers[None, :, 0], peds[:, None, 1] - walkers[None, :, 1]).min(1) > 1.0]
        others = s.boxes[np.isin(s.labels, VEHICLES)]
        for j, b in enumerate(boxes):
            q = points[inside[:, j]]
            if not len(q):
                continue
            c, s_ = np.cos(b[6]), np.sin(b[6])
            rel = q[:, :2] - b[:2]
            span = max(np.ptp(rel[:, 0] * c + rel[:, 1] * s_) / b[3], np.ptp(-rel[:, 0] * s_ + rel[:, 1] * c) / b[4])
            road = plane.slope_x * b[0] + plane.slope_y * b[1] - plane.height if plane is not None else np.nan
            near = cars & (np.hypot(d.boxes[:, 0] - b[0], d.boxes[:, 1] - b[1]) < 2.0)
            best = float(np.max(d.scores[near], initial=0.0))
            aspect = abs((b[6] - np.arctan2(b[1], b[0]) + np.pi / 2) % np.pi - np.pi / 2)
            pr = peds[:, :2] - b[:2]
            along, across = pr[:, 0] * c + pr[:, 1] * s_, -pr[:, 0] * s_ + pr[:, 1] * c
            in_box = (np.abs(along) < b[3] / 2 + 0.3) & (np.abs(across) < b[4] / 2 + 0.3)
            gap = np.hypot(others[:, 0] - b[0], others[:, 1] - b[1])
            in_row = bool(((gap > 1e-3) & (gap < ROW_M)).any())
            rows.append((len(q), span, np.hypot(b[0], b[1]), b[2] - b[5] / 2 - road, q[:, 2].min() - road,
                         np.degrees(aspect), (q[:, 2].max() - (b[2] - b[5] / 2)) / b[5],
                         bool((np.hypot(pr[:, 0], pr[:, 1]) < 3.0).any()), bool(in_box.any()), in_row, best,
                         best >= 0.3))
    return np.asarray(rows, dtype=np.float64).reshape(-1, len(FIELDS))


def _share(a: np.ndarray, m: np.ndarray) -> list:
    return [int(m.sum()), round(float(a[m, -1].mean()), 2) if m.any() else None]


def found_by_returns(a: np.ndarray) -> dict:
    return {f"{lo}-{hi - 1}": _share(a, (a[:, 0] >= lo) & (a[:, 0] < hi))[1] for lo, hi in RETURN_BANDS}


def by_returns_and_span(a: np.ndarray) -> dict:
    out = {}
    for lo, hi in RETURN_BANDS:
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        out[f"{lo}-{hi - 1} returns"] = {"cars, found": _share(a, m), **{
            f"span {s0}-{s1}": _share(a, m & (a[:, 1] >= s0) & (a[:, 1] < s1)) for s0, s1 in SPAN_BANDS}}
    return out


def in_a_row_by_returns(a: np.ndarray) -> dict:
    """Found share by returns, for cars in a row (:data:`ROW_M`) and for the rest."""
    row = a[:, FIELDS.index("in_a_row")] == 1
    return {f"{lo}-{hi - 1} returns": {"in a row": _share(a, m & row), "alone": _share(a, m & ~row)}
            for lo, hi in RETURN_BANDS for m in [(a[:, 0] >= lo) & (a[:, 0] < hi)]}


def found_against_missed(a: np.ndarray) -> dict:
    m = (a[:, 0] >= 5) & (a[:, 0] < 50)
    shares = ("pedestrian_within_3m", "pedestrian_in_box", "in_a_row")
    return {name: {"cars": int(k.sum()), **{f: (round(float(a[k, i].mean()), 2) if f in shares else
                                                np.round(np.percentile(a[k, i], [10, 50, 90]), 2).tolist())
                                             for i, f in enumerate(FIELDS[2:-1], start=2)}}
            for name, k in (("found", m & (a[:, -1] == 1)), ("missed", m & (a[:, -1] == 0)))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--seeds", default="1000-1001")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--effects", default="random,vegetation", help="the synthetic scans' effects")
    a = ap.parse_args()
    det = Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M)
    rng = det.config.point_cloud_range
    lo, _, hi = a.seeds.partition("-")
    data = {"real": [filter_range(s, rng) for s in nuscenes_samples(a.nuscenes)],
            "synthetic": [filter_range(s, rng) for s in synthetic_samples(
                DEFAULT_SCENARIOS.split(","), list(range(int(lo), int(hi or lo) + 1)), frames_per_scenario=5,
                effects=a.effects)]}
    shuffle = np.random.default_rng(0)
    variants: dict[str, Callable[[np.ndarray], np.ndarray]] = {
        "zeroed": lambda x: x * 0, "halved": lambda x: x * 0.5, "doubled": lambda x: np.minimum(x * 2, 255),
        "shuffled": shuffle.permutation, "median": lambda x: np.full_like(x, np.median(x))}
    out: dict = {"weights": a.weights or "shipped lite", "synthetic effects": a.effects}
    for name, samples in data.items():
        rows = car_rows(det, samples)
        out[name] = {"by_returns_and_span": by_returns_and_span(rows), "5-49 returns": found_against_missed(rows),
                     "in_a_row": in_a_row_by_returns(rows),
                     "intensity": {"as is": found_by_returns(rows), **{
                         vname: found_by_returns(car_rows(det, samples, fn)) for vname, fn in variants.items()}}}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
