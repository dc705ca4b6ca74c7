"""What do the real scene's false pedestrians stand on? The highest-scored pedestrian boxes by the nearest labelled
object of any nuScenes category, and pedestrian AP with the boxes on debris, cones and barriers left out
(docs/detector.md, "Things the size of a person").

    .venv/bin/python scripts/pedestrian_fp.py [--weights W] [--nuscenes ../shared/data/nuscenes-scene-0523]

jitterguard's classes leave out every nuScenes category that is no road user (barriers, traffic cones, debris), so
a pedestrian box on a pile of debris is a false positive with nothing to say why; the loader keeps those objects as
``Sample.unscored``, and ``eval-detector``'s ``false_positives_on`` counts what every false positive stands on. This
script ranks the boxes: the highest-scored ones, true and false, and the AP they would give without those on each
kind. Reads the scene's labels — a diagnosis, never a number fitted to the scene. Prints JSON lines.
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np

from jitterguard.geometry import nearest_within
from jitterguard.services.detector.augment import filter_range
from jitterguard.services.detector.config import CLASS_NAMES, SELF_CROP_M, Sample
from jitterguard.services.detector.data import nuscenes_samples
from jitterguard.services.detector.evaluate import detection_ap
from jitterguard.services.detector.inference import Detector

PEDESTRIAN = CLASS_NAMES.index("pedestrian")


def labelled_objects(s: Sample) -> list[tuple[str, float, float]]:
    """(class or nuScenes category, x, y) of every labelled object of a scan, scored or not."""
    return [(CLASS_NAMES[int(k)], float(b[0]), float(b[1])) for b, k in zip(s.boxes, s.labels)] + list(s.unscored)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    det = Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M)
    samples = [filter_range(s, det.config.point_cloud_range) for s in nuscenes_samples(a.nuscenes)]
    dets = [det.detect(s.points) for s in samples]
    labels = [labelled_objects(s) for s in samples]
    rows = []  # (score, what it stands on) of every pedestrian box within the class's 40 m
    nearest = []  # per scan: what each box stands on (the nearest labelled object within STANDS_ON_M)
    for d, objs in zip(dets, labels):
        near = [objs[j][0] if j >= 0 else "nothing"
                for j in nearest_within(d.boxes[:, :2], [o[1:] for o in objs]).tolist()]
        nearest.append(near)
        for i in np.flatnonzero(d.labels == PEDESTRIAN):
            if np.hypot(*d.boxes[i, :2]) <= 40.0:
                rows.append((float(d.scores[i]), near[i]))
    rows.sort(key=lambda r: -r[0])
    out: dict = {"weights": a.weights or "shipped lite"}
    for top in (50, 100, 200):
        out[f"top_{top}_pedestrian_boxes_on"] = dict(collections.Counter(w for _, w in rows[:top]).most_common())
    for kinds in ((), ("debris",), ("debris", "trafficcone"), ("debris", "trafficcone", "barrier")):
        left_out = tuple(f"movable_object.{k}" for k in kinds)
        kept = [d.subset(~((d.labels == PEDESTRIAN) & np.array([w in left_out for w in near], np.bool_)))
                if len(d) else d for d, near in zip(dets, nearest)]
        classes = detection_ap(kept, samples)["classes"]
        out["pedestrian_ap_without_boxes_on_" + ("+".join(kinds) or "nothing")] = round(
            float(classes["pedestrian"]["mean_ap"]), 3)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
