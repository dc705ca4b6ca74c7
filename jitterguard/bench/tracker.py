"""``jitterguard bench tracker``: the core's per-frame update time at 50 / 200 / 500 objects.

What is timed is exactly :meth:`TrackerCore.step` — sensor-to-world transform, prediction, gating, assignment,
update, lifecycle and the output snapshot — on pre-built frames after a warm-up in which every object's track
has been confirmed (so the steady state is measured, not births). Serialisation and Zenoh are not included:
they are the adapter's cost, not the tracker's. The process is pinned to one CPU while it runs, where the OS
allows, because the target is "one core".

The scene: objects on a jittered 8 m grid (so gating is as busy as in dense traffic but no two objects
overlap), 70 % cars moving at up to 12 m/s, 20 % pedestrians, the rest cyclists and unknowns; 5 % misses and
two false positives per frame; detection noise 0.1-0.3 m with matching reported covariance.
"""

from __future__ import annotations

import math
import os
import statistics
import time
from contextlib import contextmanager
from collections.abc import Iterator

import numpy as np

from ..services.tracker.config import TrackerConfig, default_config
from ..services.tracker.core import TrackerCore
from ..services.tracker.arrays import DetectionFrame

SIZES = (50, 200, 500)
DIMS = {1: (4.5, 1.9, 1.6), 7: (0.6, 0.6, 1.7), 6: (1.8, 0.6, 1.6), 0: (1.0, 1.0, 1.0)}


def scene_frames(n_objects: int, n_frames: int, seed: int = 0, dt: float = 0.1) -> list[DetectionFrame]:
    """Seeded detection frames of ``n_objects`` moving objects (sensor at the world origin, ego static)."""
    rng = np.random.default_rng(seed)
    side = int(math.ceil(math.sqrt(n_objects)))
    cells = rng.permutation(side * side)[:n_objects]
    spacing = 8.0
    x0 = (cells % side - side / 2) * spacing + rng.uniform(-1, 1, n_objects)
    y0 = (cells // side - side / 2) * spacing + rng.uniform(-1, 1, n_objects)
    kind = rng.choice([1, 7, 6, 0], size=n_objects, p=[0.7, 0.2, 0.05, 0.05])
    heading = rng.uniform(-math.pi, math.pi, n_objects)
    speed = np.where(kind == 1, rng.uniform(0.0, 12.0, n_objects), rng.uniform(0.0, 1.5, n_objects))
    speed = np.where(rng.random(n_objects) < 0.3, 0.0, speed)  # some parked / standing
    dims = np.array([DIMS[int(k)] for k in kind])
    frames = []
    for k in range(n_frames):
        t = k * dt
        x = x0 + speed * np.cos(heading) * t
        y = y0 + speed * np.sin(heading) * t
        seen = rng.random(n_objects) > 0.05
        sig = 0.1 + 0.2 * rng.random(n_objects)
        xs = x[seen] + rng.normal(0, 1, seen.sum()) * sig[seen]
        ys = y[seen] + rng.normal(0, 1, seen.sum()) * sig[seen]
        n_fp = 2
        span = side * spacing / 2
        xs = np.concatenate([xs, rng.uniform(-span, span, n_fp)])
        ys = np.concatenate([ys, rng.uniform(-span, span, n_fp)])
        lbl = np.concatenate([kind[seen], np.full(n_fp, 7)])
        var = np.concatenate([sig[seen] ** 2, np.full(n_fp, 0.04)])
        d = np.concatenate([dims[seen], np.tile(DIMS[7], (n_fp, 1))])
        yaw = np.concatenate([heading[seen] + rng.normal(0, 0.05, seen.sum()), rng.uniform(-3, 3, n_fp)])
        m = xs.size
        frames.append(DetectionFrame(
            seq=k, stamp_ns=1_000_000_000 + int(round(t * 1e9)), ego_x=0.0, ego_y=0.0, ego_yaw=0.0,
            x=xs, y=ys, yaw=yaw, label=lbl, length=d[:, 0], width=d[:, 1], height=d[:, 2],
            cov_xx=var, cov_xy=np.zeros(m), cov_yy=var, var_yaw=np.full(m, 0.0025), has_cov=np.ones(m, dtype=bool),
        ))
    return frames


@contextmanager
def _one_cpu(pin: bool) -> Iterator[None]:
    """Pin this process to one CPU for the duration (Linux), restoring the previous affinity afterwards."""
    if not pin or not hasattr(os, "sched_getaffinity"):
        yield
        return
    before = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(before)})
    except OSError:
        yield
        return
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def bench_size(n_objects: int, frames: int = 60, warmup: int = 20, seed: int = 0,
               config: TrackerConfig | None = None) -> dict[str, float]:
    """Median / p90 / max milliseconds of one ``step`` at ``n_objects`` after ``warmup`` frames."""
    data = scene_frames(n_objects, warmup + frames, seed)
    core = TrackerCore(config or default_config())
    for f in data[:warmup]:
        core.step(f)
    times = []
    n_tracks = []
    for f in data[warmup:]:
        t0 = time.perf_counter()
        res = core.step(f)
        times.append((time.perf_counter() - t0) * 1e3)
        n_tracks.append(len(res.tracks))
    times.sort()
    return {
        "median_ms": round(statistics.median(times), 4),
        "p90_ms": round(times[int(0.9 * (len(times) - 1))], 4),
        "max_ms": round(times[-1], 4),
        "frames": frames,
        "confirmed_tracks": int(statistics.median(n_tracks)),
    }


def run(sizes: tuple[int, ...] = SIZES, frames: int = 60, warmup: int = 20, seed: int = 0,
        pin: bool = True) -> dict[str, dict[str, float]]:
    """The benchmark's JSON document: ``{"objects_50": {"median_ms": ...}, ...}``."""
    out: dict[str, dict[str, float]] = {}
    with _one_cpu(pin):
        for n in sizes:
            out[f"objects_{n}"] = bench_size(n, frames=frames, warmup=warmup, seed=seed)
    return out
