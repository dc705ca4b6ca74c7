"""Ray-casting throughput: full HDL-32E scans per second on one core (``jitterguard bench sim``).

A scan here is everything a frame costs the LiDAR: composing the objects' part shapes, culling the clutter,
casting all rays (32 × 1085 ≈ 35k for the HDL-32E), noise, dropout and the per-object point counts. The scene is
a scenario frame cut down to its ``objects`` nearest road users (the clutter stays). Scenario generation is
not timed. Several runs; the median is reported together with every run.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import replace
from typing import Any

import numpy as np

from ..sim.lidar import cast_frame, scene_primitives
from ..sim.sensors import SENSORS
from ..sim.world import GroundTruthFrame, make_scenario


def nearest_objects(frame: GroundTruthFrame, n: int) -> GroundTruthFrame:
    """``frame`` with only its ``n`` objects nearest to the sensor."""
    d = np.hypot(frame.centers[:, 0] - frame.ego_x, frame.centers[:, 1] - frame.ego_y)
    keep = np.sort(np.argsort(d, kind="stable")[:n])
    return replace(
        frame, instance_ids=frame.instance_ids[keep], labels=frame.labels[keep], centers=frame.centers[keep],
        sizes=frame.sizes[keep], yaws=frame.yaws[keep], velocities=frame.velocities[keep],
        moving=frame.moving[keep], attributes=tuple(frame.attributes[i] for i in keep),
        visibility=frame.visibility[keep], num_points=frame.num_points[keep])


def bench_raycast(sensor: str = "hdl32e", scenario: str = "parking-street", objects: int = 60, scans: int = 40,
                  repeat: int = 3, seed: int = 0) -> dict[str, Any]:
    """Time ``scans`` ray casts ``repeat`` times; returns figures as a JSON-ready dict."""
    spec = SENSORS[sensor]()
    sc = make_scenario(scenario, seed, duration_s=max(scans / 10.0 + 1.0, 2.0), rate_hz=10.0, gt_radius_m=150.0)
    frames = [nearest_objects(sc.frame(i % sc.num_frames), objects) for i in range(scans)]
    prims = [len(scene_primitives(f, spec)[0]) for f in frames[:5]]
    rates: list[float] = []
    points = 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        points = 0
        for f in frames:
            res, _ = cast_frame(f, spec, seed)
            points += len(res.points)
        rates.append(len(frames) / (time.perf_counter() - t0))
    return {
        "bench": "sim.raycast",
        "sensor": spec.name,
        "rays_per_scan": spec.num_rays,
        "scenario": scenario,
        "objects": int(np.mean([f.num_objects for f in frames])),
        "primitives": int(np.mean(prims)),
        "scans": len(frames),
        "points_per_scan": int(points / len(frames)),
        "scans_per_s": round(statistics.median(rates), 2),
        "runs_scans_per_s": [round(r, 2) for r in rates],
        "rays_per_s": int(statistics.median(rates) * spec.num_rays),
    }
