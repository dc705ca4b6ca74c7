"""What do the real scene's false pedestrians stand on? The highest-scored pedestrian boxes by the nearest labelled
object of any nuScenes category, and pedestrian AP with the boxes on debris, cones and barriers left out
(docs/detector.md, "Things the size of a person").

    .venv/bin/python scripts/pedestrian_fp.py [--weights W] [--nuscenes ../shared/data/nuscenes-scene-0523]

jitterguard's classes drop every nuScenes category that is no road user (barriers, traffic cones, debris), so a
pedestrian box on a pile of debris counts as a false positive with nothing to say why; nuscenes-devkit reads every
annotation of the scene here. Reads the scene's labels — a diagnosis, never a number fitted to the scene. Prints
JSON lines.
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np
from nuscenes.nuscenes import NuScenes

from jitterguard.services.detector.augment import filter_range
from jitterguard.services.detector.config import CLASS_NAMES, SELF_CROP_M
from jitterguard.services.detector.data import nuscenes_samples
from jitterguard.services.detector.evaluate import detection_ap
from jitterguard.services.detector.inference import Detector

PEDESTRIAN = CLASS_NAMES.index("pedestrian")
ON_M = 1.0
"""A box stands on a labelled object when their centres are this close."""


def labelled_objects(nusc: NuScenes, token: str) -> list[tuple[str, float, float]]:
    """(last part of the category, x, y) of every annotation of a key frame in the detector's sensor frame (x
    forward: nuScenes' LIDAR_TOP turned by −90°)."""
    _, boxes, _ = nusc.get_sample_data(nusc.get("sample", token)["data"]["LIDAR_TOP"])
    return [(b.name.split(".")[-1], float(b.center[1]), float(-b.center[0])) for b in boxes]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    det = Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M)
    nusc = NuScenes(version=a.version, dataroot=a.nuscenes, verbose=False)
    samples = [filter_range(s, det.config.point_cloud_range) for s in nuscenes_samples(a.nuscenes)]
    dets = [det.detect(s.points) for s in samples]
    labels = [labelled_objects(nusc, s.token.rsplit("/", 1)[1]) for s in samples]
    rows = []  # (score, what it stands on) of every pedestrian box within the class's 40 m
    nearest = []  # per scan: (category, distance) of the nearest labelled object of each box
    for d, objs in zip(dets, labels):
        xy = np.array([(x, y) for _, x, y in objs]).reshape(-1, 2)
        dist = np.hypot(d.boxes[:, None, 0] - xy[None, :, 0], d.boxes[:, None, 1] - xy[None, :, 1]) if len(xy) else \
            np.full((len(d), 1), np.inf)
        j = dist.argmin(1)
        near = [(objs[k][0] if dist[i, k] < ON_M else "nothing", float(dist[i, k])) for i, k in enumerate(j)] \
            if len(xy) else [("nothing", np.inf)] * len(d)
        nearest.append(near)
        for i in np.flatnonzero(d.labels == PEDESTRIAN):
            if np.hypot(*d.boxes[i, :2]) <= 40.0:
                rows.append((float(d.scores[i]), near[i][0]))
    rows.sort(key=lambda r: -r[0])
    out: dict = {"weights": a.weights or "shipped lite"}
    for top in (50, 100, 200):
        out[f"top_{top}_pedestrian_boxes_on"] = dict(collections.Counter(w for _, w in rows[:top]).most_common())
    for left_out in ((), ("debris",), ("debris", "trafficcone"), ("debris", "trafficcone", "barrier")):
        kept = [d.subset(~((d.labels == PEDESTRIAN) & np.array([w in left_out for w, _ in near], np.bool_)))
                if len(d) else d for d, near in zip(dets, nearest)]
        classes = detection_ap(kept, samples)["classes"]
        out["pedestrian_ap_without_boxes_on_" + ("+".join(left_out) or "nothing")] = round(
            float(classes["pedestrian"]["mean_ap"]), 3)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
