"""Does a person inside a car's footprint cost pedestrian AP? Detection AP with and without dropping every
pedestrian or cyclist box whose centre lies inside a higher-scored vehicle box's footprint (shrunk by a margin)
(docs/detector.md, "Things the size of a person").

    .venv/bin/python scripts/cross_class.py [--weights W] [--seeds 1100-1102] [--margins 0,0.3,0.6]
    .venv/bin/python scripts/cross_class.py --weights W --nuscenes ../shared/data/nuscenes-scene-0523

Circle NMS runs per class, so nothing stops the network from reporting a pedestrian where it reports a car: two
objects on one patch of ground, which the world never holds. The detector is run as ``jitterguard eval-detector``
runs it (the self-crop, the road plane measured, the variances recalibrated); each variant only drops boxes from
the same detections. Synthetic scans by default (design seeds, every effect and vegetation); ``--nuscenes`` reads
that scene's labels to score — a look at the scene, to be disclosed. Prints JSON lines.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from jitterguard.services.detector.augment import filter_range
from jitterguard.services.detector.config import CLASS_NAMES, SELF_CROP_M, Detections3D
from jitterguard.services.detector.data import nuscenes_samples, synthetic_samples
from jitterguard.services.detector.evaluate import detection_ap
from jitterguard.services.detector.inference import Detector

VEHICLES = tuple(CLASS_NAMES.index(c) for c in ("car", "truck", "bus"))
PEOPLE = tuple(CLASS_NAMES.index(c) for c in ("pedestrian", "bicycle"))


def inside_a_vehicle(d: Detections3D, margin: float) -> np.ndarray:
    """Mask of person boxes whose centre lies inside a higher-scored vehicle box's footprint shrunk by ``margin``."""
    drop = np.zeros(len(d), np.bool_)
    veh = np.flatnonzero(np.isin(d.labels, VEHICLES))
    ppl = np.flatnonzero(np.isin(d.labels, PEOPLE))
    if not len(veh) or not len(ppl):
        return drop
    vb = d.boxes[veh]
    rel = d.boxes[ppl, None, :2] - vb[None, :, :2]  # (P, V, 2)
    c, s = np.cos(vb[:, 6]), np.sin(vb[:, 6])
    along = rel[..., 0] * c + rel[..., 1] * s
    across = -rel[..., 0] * s + rel[..., 1] * c
    inside = (np.abs(along) <= vb[:, 3] / 2 - margin) & (np.abs(across) <= vb[:, 4] / 2 - margin)
    higher = d.scores[veh][None, :] > d.scores[ppl][:, None]
    drop[ppl] = (inside & higher).any(1)
    return drop


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default=None, help="score on this scene instead of synthetic scans (a look)")
    ap.add_argument("--seeds", default="1100-1102")
    ap.add_argument("--scenarios", default="mixed,diagonal-lot,parking-street,perpendicular-lot")
    ap.add_argument("--effects", default="random,vegetation")
    ap.add_argument("--margins", default="0,0.3,0.6", help="metres the footprint is shrunk by, comma-separated")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    det = Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M)
    rng = det.config.point_cloud_range
    if a.nuscenes:
        samples = [filter_range(s, rng) for s in nuscenes_samples(a.nuscenes)]
    else:
        lo, _, hi = a.seeds.partition("-")
        samples = [filter_range(s, rng) for s in synthetic_samples(
            a.scenarios.split(","), list(range(int(lo), int(hi or lo) + 1)), frames_per_scenario=5,
            effects=a.effects)]
    dets = [det.detect(s.points) for s in samples]
    for m in [None, *(float(x) for x in a.margins.split(","))]:
        masks = [np.zeros(len(d), np.bool_) if m is None else inside_a_vehicle(d, m) for d in dets]
        kept = [d.subset(~k) for d, k in zip(dets, masks)]
        classes = detection_ap(kept, samples)["classes"]
        print(json.dumps({"margin_m": m, "dropped": int(sum(k.sum() for k in masks)),
                          **{c: round(float(classes[c]["mean_ap"]), 3) for c in ("car", "pedestrian", "bicycle")
                             if c in classes}}), flush=True)


if __name__ == "__main__":
    main()
