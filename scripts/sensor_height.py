"""Experiment (docs/detector.md, "The sensor's height"): what a wrong height of the scans' frame costs the shipped
detector, and what measuring it in every scan (``sensor_height_m: auto``) gives back.

    .venv/bin/python scripts/sensor_height.py real [--lift 0,0.3,-0.3,1.84,-0.11]
    .venv/bin/python scripts/sensor_height.py synthetic [--runs 1.84:none,1.84:random+vegetation,1.5:random,2.3:random]
    .venv/bin/python scripts/sensor_height.py estimates

``real``: every key frame of ../shared/data/nuscenes-scene-0523 lifted by each Δz (its boxes lowered by Δz before
scoring), scored with the height declared 1.84 m (the detector before 4 Dec 2026) and with ``auto``; the labels
are read by the scorer only. ``synthetic``: synthetic hold-out scans (seeds 1000–1004, four scenarios × 10 frames)
ray-cast from another mount (M:EFFECTS, effects '+'-joined for a comma), both ways. ``estimates``: the estimate
against the known mount on synthetic effect scans (seeds 1000–1002) and on the real recordings. Prints lines; no
files.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
from pathlib import Path

import numpy as np

from jitterguard.services.detector.data import nuscenes_samples, synthetic_samples
from jitterguard.services.detector.evaluate import evaluation_report
from jitterguard.services.detector.ground import ground_height, shift_z
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.train_cli import _Prepared
from jitterguard.sim.sensors import hdl32e

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SCENARIOS = ["parking-street", "diagonal-lot", "intersection", "mixed"]


def _summary(dets: list, items: list) -> str:  # noqa: ANN001
    rep = evaluation_report(dets, items)["summary"]
    return f"car {rep['car_ap']:.3f} pedestrian {rep['pedestrian_ap']:.3f} mAP {rep['mAP']:.3f} cov {rep['coverage_1sigma']:.2f}"


def _detectors(threads: int) -> dict[str, Detector]:
    return {"declared 1.84": Detector.load(threads=threads, sensor_height_m=1.84), "auto": Detector.load(threads=threads)}


def real(lifts: list[float], threads: int) -> None:
    dets = _detectors(threads)
    every = nuscenes_samples(DATA / "nuscenes-scene-0523")
    items = [_Prepared(every, dets["auto"].config.point_cloud_range)[i] for i in range(len(every))]
    for dz in lifts:
        for name, det in dets.items():
            out = []
            for s in items:
                d = det.detect(shift_z(s.points, dz))
                if len(d):
                    boxes = d.boxes.copy()
                    boxes[:, 2] -= dz
                    d = dataclasses.replace(d, boxes=boxes)
                out.append(d)
            print(f"lifted {dz:+.2f} m, {name}: {_summary(out, items)}", flush=True)


def synthetic(runs: list[str], threads: int) -> None:
    dets = _detectors(threads)
    for run in runs:
        mount, effects = run.split(":")
        spec = dataclasses.replace(hdl32e(), mount_height_m=float(mount))
        s = list(synthetic_samples(SCENARIOS, range(1000, 1005), frames_per_scenario=10, sensor=spec,
                                   effects=effects.replace("+", ",")))
        items = [_Prepared(s, dets["auto"].config.point_cloud_range)[i] for i in range(len(s))]
        est = np.array([ground_height(it.points) for it in items], dtype=float)
        for name, det in dets.items():
            print(f"mount {mount} m, {effects}, {name}: {_summary([det.detect(it.points) for it in items], items)}"
                  f" (estimate 5/50/95 %: {np.round(np.nanpercentile(est, [5, 50, 95]), 2)})", flush=True)


def estimates() -> None:
    for mount, effects in ((1.84, "random,vegetation"), (1.5, "random"), (2.3, "random")):
        spec = dataclasses.replace(hdl32e(), mount_height_m=mount)
        est = np.array([ground_height(s.points) for s in synthetic_samples(
            SCENARIOS, range(1000, 1003), frames_per_scenario=5, sensor=spec, effects=effects)], dtype=float)
        print(f"synthetic mount {mount} m, {effects}: error 5/25/50/75/95 % "
              f"{np.round(np.nanpercentile(est - mount, [5, 25, 50, 75, 95]), 3)}")
    est = np.array([ground_height(s.points) for s in nuscenes_samples(DATA / "nuscenes-scene-0523")], dtype=float)
    print(f"scene-0523 (mount 1.84 m): min/median/max {np.round([est.min(), np.median(est), est.max()], 3)}")
    for f in sorted(glob.glob(str(DATA / "kitti-velodyne-6" / "*.bin"))):
        print(f"{Path(f).name} (mount 1.73 m): {ground_height(np.fromfile(f, np.float32).reshape(-1, 4)):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["real", "synthetic", "estimates"])
    ap.add_argument("--lift", default="0,-0.11,-0.3,0.3,1.84")
    ap.add_argument("--runs", default="1.84:none,1.84:random+vegetation,1.5:random,2.3:random")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if args.what == "real":
        real([float(x) for x in args.lift.split(",")], args.threads)
    elif args.what == "synthetic":
        synthetic(args.runs.split(","), args.threads)
    else:
        estimates()


if __name__ == "__main__":
    main()
