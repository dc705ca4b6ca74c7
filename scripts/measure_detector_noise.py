"""Measure the shipped detector's positional error model per line-of-sight axis (prints JSON).

    .venv/bin/python scripts/measure_detector_noise.py --synthetic mixed,diagonal-lot,parking-street \
        --seeds 1000-1002 [--nuscenes ../shared/data/nuscenes-scene-0523] [--weights FILE] [--threads 1]

Runs the detector exactly as ``jitterguard eval --input detector`` does (same scans, same service steps),
matches every detection to the nearest ground-truth object within 2 m (optimal one-to-one per frame) and
summarises the errors with :func:`jitterguard.eval.detector_noise.summarize`: bias and scatter of the
reported σ, variance ratio, coverage and the serial correlation of the normalised error of static objects.
These figures set the honest presets of ``jitterguard.sim.detection_model`` (docs/calibration.md).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment  # type: ignore[import-untyped]

from jitterguard.eval.cli import load_detector
from jitterguard.eval.detector_input import detect_scan, nuscenes_scans, synthetic_scans
from jitterguard.eval.detector_noise import MatchedErrors, summarize
from jitterguard.eval.groundtruth import is_dynamic, load_nuscenes_frames
from jitterguard.sim.world import make_scenario


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b) + 1)) if b else [int(x) for x in text.split(",")]


def collect(scans, detect, frame_offset: int, instance_offset: int) -> dict[str, list]:
    cols: dict[str, list] = {k: [] for k in MatchedErrors.__dataclass_fields__}
    for k, ls in enumerate(scans):
        gt = ls.gt
        det = detect_scan(detect, ls.scan)
        if len(det) == 0 or gt.num_objects == 0 or det.log_variances is None:
            continue
        c, s = math.cos(gt.ego_yaw), math.sin(gt.ego_yaw)
        dx, dy = gt.centers[:, 0] - gt.ego_x, gt.centers[:, 1] - gt.ego_y
        gx, gy = c * dx + s * dy, -s * dx + c * dy
        px, py = det.boxes[:, 0].astype(float), det.boxes[:, 1].astype(float)
        d = np.hypot(px[:, None] - gx[None, :], py[:, None] - gy[None, :])
        cost = np.where(d <= 2.0, d, 1e6)
        rows, cols_ = linear_sum_assignment(cost)
        ok = cost[rows, cols_] < 1e6
        rows, cols_ = rows[ok], cols_[ok]
        var = np.exp(det.log_variances[rows, :2].astype(float))
        cols["instance"].append(gt.instance_ids[cols_] + instance_offset)
        cols["frame"].append(np.full(len(rows), k + frame_offset))
        cols["static"].append(np.array([not is_dynamic(gt.attributes[j], bool(gt.moving[j])) for j in cols_.tolist()]))
        cols["gx"].append(gx[cols_])
        cols["gy"].append(gy[cols_])
        cols["rx"].append(px[rows] - gx[cols_])
        cols["ry"].append(py[rows] - gy[cols_])
        cols["cxx"].append(var[:, 0])
        cols["cxy"].append(np.zeros(len(rows)))
        cols["cyy"].append(var[:, 1])
    return cols


def to_matched(parts: list[dict[str, list]]) -> MatchedErrors:
    merged = {k: np.concatenate([np.concatenate(p[k]) for p in parts if p[k]]) for k in MatchedErrors.__dataclass_fields__}
    return MatchedErrors(**merged)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synthetic", default="mixed,diagonal-lot,parking-street")
    ap.add_argument("--seeds", default="1000-1002")
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--nuscenes", type=Path, default=None)
    ap.add_argument("--weights", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    det, desc = load_detector(args.weights, args.threads)
    out: dict[str, object] = {"weights": desc}
    parts = []
    for i, name in enumerate(x for x in args.synthetic.split(",") if x):
        for seed in _seeds(args.seeds):
            sc = make_scenario(name, seed, args.duration, 10.0)
            parts.append(collect(synthetic_scans(sc, seed), det.detect, 100000 * len(parts), 10 ** 7 * len(parts)))
            print(f"{name} seed {seed}: {sum(len(x) for x in parts[-1]['rx'])} matches", file=sys.stderr)
    if parts:
        out["synthetic"] = summarize(to_matched(parts))
    if args.nuscenes is not None:
        _, frames = load_nuscenes_frames(args.nuscenes)
        out["nuscenes"] = summarize(to_matched([collect(nuscenes_scans(args.nuscenes, None, frames), det.detect, 0, 0)]))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
