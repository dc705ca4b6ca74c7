"""Per-frame cost of the classifier core on a 20 Hz stream, three windows back to back frame by frame (same
machine load): the default (20 observations of every second frame: 2 s), every frame with 20 (1 s: what a 20 Hz
stream got before the stride) and every frame with 40 (2 s the expensive way). Prints JSON: median / mean / p99 ms
per frame and the CPU per second of stream. Usage: OMP_NUM_THREADS=1 python scripts/ab_fast_stream.py [TRACKS ...]"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from jitterguard.bench.classifier import _Scene
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import MotionClassifierCore

RATE_HZ = 20.0


def main(sizes: list[int], frames: int = 200) -> dict:
    variants = {"stride_w20": ClassifierConfig(), "every_w20": ClassifierConfig(window_reference_hz=None),
                "every_w40": ClassifierConfig(window_size=40, window_reference_hz=None)}
    out: dict = {"rate_hz": RATE_HZ}
    for n in sizes:
        scene = _Scene(n, seed=0)
        cores = {k: MotionClassifierCore(c, capacity=n) for k, c in variants.items()}
        warm = 120  # 6 s: every window full, the calibration learning
        times: dict[str, list[float]] = {k: [] for k in cores}
        for k in range(warm + frames):
            obs = scene.frame(k)
            obs = type(obs)(**{**obs.__dict__, "stamp_ns": 1_700_000_000_000_000_000 + round(k * 1e9 / RATE_HZ)})
            for name, core in cores.items():
                t0 = time.perf_counter()
                core.update(obs)
                core.learn()
                if k >= warm:
                    times[name].append((time.perf_counter() - t0) * 1e3)
        row = {}
        for name, ts in times.items():
            a = np.asarray(ts)
            row[name] = {"median_ms": round(float(np.median(a)), 2), "mean_ms": round(float(a.mean()), 2),
                         "p99_ms": round(float(np.percentile(a, 99)), 2),
                         "cpu_share_at_20hz": round(float(a.mean()) * RATE_HZ / 1e3, 3),
                         "stride": cores[name].stride, "window": cores[name].window}
        out[f"tracks_{n}"] = row
    return out


if __name__ == "__main__":
    print(json.dumps(main([int(a) for a in sys.argv[1:]] or [200, 1000])))
