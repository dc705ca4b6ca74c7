"""Do returns high over a car (tree crowns, facades) spoil its pillars? Car AP with every return higher than H m above
the road dropped before the pillars; and, with ``--shifts``, with the scan moved up or down after the road plane's
fit instead (a plane estimate that far off) (docs/detector.md, "What stands around a sparse car").

    .venv/bin/python scripts/height_crop.py [--weights W] [--nuscenes ../shared/data/nuscenes-scene-0523] [--heights 4,3.5,3,2.5]
    .venv/bin/python scripts/height_crop.py --shifts=-0.2,0.2

A pillar holds every return over its 0.4 m cell whatever its height (the `lite` range reaches ~4.9 m above the road),
so a crown over a parked car changes the car's own pillars' features. The detector is run as ``jitterguard
eval-detector`` runs it (the self-crop, the road plane measured, the variances recalibrated), once as it is and once
per height with the returns above it dropped in the trained frame (the road at its trained depth below the sensor);
reads the scene's labels to score — a diagnosis, never a number fitted to the scene. Prints JSON lines.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

import jitterguard.services.detector.inference as inference
from jitterguard.services.detector.augment import filter_range
from jitterguard.services.detector.config import SELF_CROP_M
from jitterguard.services.detector.data import nuscenes_samples
from jitterguard.services.detector.evaluate import detection_ap
from jitterguard.services.detector.ground import TRAINED_SENSOR_HEIGHT_M


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--nuscenes", default="../shared/data/nuscenes-scene-0523")
    ap.add_argument("--heights", default="4,3.5,3,2.5", help="metres above the road, comma-separated")
    ap.add_argument("--shifts", default=None, help="metres to move the scan up (+) or down after the plane fit, "
                    "comma-separated; instead of --heights")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    crop: list[float | None] = [None]
    shift = [0.0]
    to_trained_frame = inference.to_trained_frame

    def cropped(points: np.ndarray, ground) -> np.ndarray:  # noqa: ANN001 - the detector's GroundPlane
        p = to_trained_frame(points, ground)
        if shift[0]:
            p = p.copy()
            p[:, 2] += shift[0]
        return p if crop[0] is None else p[p[:, 2] < crop[0] - TRAINED_SENSOR_HEIGHT_M]

    inference.to_trained_frame = cropped  # the one step of Detector.detect this diagnosis changes
    det = inference.Detector.load(a.weights, "lite", threads=a.threads, recalibrate=True, self_crop=SELF_CROP_M)
    samples = [filter_range(s, det.config.point_cloud_range) for s in nuscenes_samples(a.nuscenes)]
    what = "shifted_up_m" if a.shifts else "dropped_above_road_m"
    for v in [None, *(float(x) for x in (a.shifts or a.heights).split(","))]:
        if a.shifts:
            shift[0] = v or 0.0
        else:
            crop[0] = v
        classes = detection_ap([det.detect(s.points) for s in samples], samples)["classes"]
        print(json.dumps({what: v, **{c: round(float(classes[c]["mean_ap"]), 3) for c in ("car", "truck", "pedestrian")},
                          "car_found_by_returns": classes["car"]["recall_by_returns"]}), flush=True)


if __name__ == "__main__":
    main()
