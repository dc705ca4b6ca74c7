"""Experiment (docs/detector.md, "The sensor's height" and "The sensor's tilt"): what a wrong height or a tilt of
the scans' frame costs the shipped detector, and what measuring them in every scan (``sensor_height_m: auto``,
``sensor_tilt: auto``) gives back.

    .venv/bin/python scripts/sensor_height.py real [--lift 0,0.3,-0.3,1.84,-0.11]
    .venv/bin/python scripts/sensor_height.py synthetic [--runs 1.84:none,1.84:random+vegetation,1.5:random,2.3:random]
    .venv/bin/python scripts/sensor_height.py estimates
    .venv/bin/python scripts/sensor_height.py tilt [--on real|none|random+vegetation] [--seeds 1000-1004]
        [--turns 0:0,1:0,2:0,-2:0,0:2]

``real``: every key frame of ../shared/data/nuscenes-scene-0523 lifted by each Δz (its boxes lowered by Δz before
scoring), scored with the height declared 1.84 m (the detector before 4 Dec 2026) and with ``auto``; the labels
are read by the scorer only. ``synthetic``: synthetic hold-out scans (seeds 1000–1004, four scenarios × 10 frames)
ray-cast from another mount (M:EFFECTS, effects '+'-joined for a comma), both ways. ``estimates``: the estimate
against the known mount on synthetic effect scans (seeds 1000–1002) and on the real recordings. ``tilt``: every scan
seen from a frame pitched and rolled by each PITCH:ROLL (degrees, a rigid turn about the sensor; the boxes turned
back before scoring), scored with the frame taken as level (``sensor_tilt: level``, the detector before 5 Dec 2026)
and with the tilt measured, with the road plane's measured slope (5/50/95 %) of the unturned scans. Prints lines;
no files.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
from pathlib import Path

import numpy as np

from jitterguard.services.detector.data import nuscenes_samples, synthetic_samples
from jitterguard.services.detector.evaluate import evaluation_report
from jitterguard.services.detector.ground import ground_height, ground_plane
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.train_cli import _Prepared
from jitterguard.sim.sensors import hdl32e

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SCENARIOS = ["parking-street", "diagonal-lot", "intersection", "mixed"]


def _summary(dets: list, items: list) -> str:  # noqa: ANN001
    rep = evaluation_report(dets, items)["summary"]
    return f"car {rep['car_ap']:.3f} pedestrian {rep['pedestrian_ap']:.3f} mAP {rep['mAP']:.3f} cov {rep['coverage_1sigma']:.2f}"


def _lift(points: np.ndarray, dz: float) -> np.ndarray:
    out = points.copy()
    out[:, 2] += np.float32(dz)
    return out


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
                d = det.detect(_lift(s.points, dz))
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


def _turn(pitch_deg: float, roll_deg: float) -> np.ndarray:
    """The rigid turn of a frame pitched (about y) and rolled (about x) by the angles."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    return ry @ rx


def tilt(on: str, seeds: range, turns: list[tuple[float, float]], threads: int) -> None:
    dets = {"level": Detector.load(threads=threads, sensor_tilt=False), "auto": Detector.load(threads=threads)}
    pcr = dets["auto"].config.point_cloud_range
    if on == "real":
        every = nuscenes_samples(DATA / "nuscenes-scene-0523")
    else:
        every = list(synthetic_samples(SCENARIOS, seeds, frames_per_scenario=10, effects=on.replace("+", ",")))
    items = [_Prepared(every, pcr)[i] for i in range(len(every))]
    planes = [ground_plane(it.points) for it in items]
    slopes = np.array([p.slope_deg for p in planes if p is not None])
    print(f"{on}: road slope along x / y, degrees 5/50/95 %: {np.round(np.percentile(slopes[:, 0], [5, 50, 95]), 2)}"
          f" / {np.round(np.percentile(slopes[:, 1], [5, 50, 95]), 2)}", flush=True)
    for pitch, roll in turns:
        turn = _turn(pitch, roll)
        for name, det in dets.items():
            out = []
            for it in items:
                pts = it.points.copy()
                pts[:, :3] = (it.points[:, :3].astype(np.float64) @ turn.T).astype(np.float32)
                d = det.detect(pts)
                if len(d):
                    boxes = d.boxes.copy()
                    boxes[:, :3] = boxes[:, :3] @ turn  # back into the unturned frame (row vectors: the inverse)
                    d = dataclasses.replace(d, boxes=boxes)
                out.append(d)
            print(f"{on}, frame pitched {pitch:+g}° rolled {roll:+g}°, tilt {name}: {_summary(out, items)}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["real", "synthetic", "estimates", "tilt"])
    ap.add_argument("--lift", default="0,-0.11,-0.3,0.3,1.84")
    ap.add_argument("--runs", default="1.84:none,1.84:random+vegetation,1.5:random,2.3:random")
    ap.add_argument("--on", default="real", help="tilt: real, or synthetic effects ('+'-joined; none: ideal)")
    ap.add_argument("--seeds", default="1000-1004", help="tilt on synthetic scans: seeds LO-HI")
    ap.add_argument("--turns", default="0:0,1:0,2:0,-2:0,0:2", help="tilt: PITCH:ROLL in degrees, comma-separated")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if args.what == "real":
        real([float(x) for x in args.lift.split(",")], args.threads)
    elif args.what == "synthetic":
        synthetic(args.runs.split(","), args.threads)
    elif args.what == "tilt":
        lo, hi = (int(v) for v in args.seeds.split("-"))
        turns = [(float(a), float(b)) for a, b in (t.split(":") for t in args.turns.split(","))]
        tilt(args.on, range(lo, hi + 1), turns, args.threads)
    else:
        estimates()


if __name__ == "__main__":
    main()
