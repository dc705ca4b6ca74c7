"""Training data for the detector: synthetic scans with ground truth, a disk cache, and (re-exported) the
nuScenes loader and the augmentations.

Everything here speaks :class:`~jitterguard.services.detector.config.Sample` — points (P, 4) and boxes (N, 9)
in the *sensor* frame — so the training loop does not care where a scan came from.

Synthetic path: :func:`synthetic_samples` generates scenarios with :func:`jitterguard.sim.world.make_scenario`,
ray-casts frames spread over each scenario with :func:`jitterguard.sim.lidar.cast_frame` and converts the
world-frame ground truth into sensor-frame boxes (:func:`frame_to_sensor_boxes`, pure). Ray-casting costs
≈ 15–20 ms a scan, so a training run that sees the same scans every epoch writes them once with
:func:`build_cache` and reads them back with :class:`CachedSamples` (one uncompressed ``.npz`` per sample:
random access for a shuffled epoch costs one small file read, no torch needed).
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ...geometry import quaternion_from_yaw
from ...sim.effects import ScanEffects, draw_effects, parse_components
from ...sim.lidar import ScanResult, cast_frame
from ...sim.sensors import LidarSpec, hdl32e
from ...sim.world import GroundTruthFrame, Scenario, make_scenario
from .augment import (  # noqa: F401  (re-exported: one import site for the training code)
    flip_x,
    flip_y,
    global_rotate,
    global_scale,
    random_augment,
    filter_range,
    drop_empty,
    points_in_boxes,
    GTDatabase,
    build_gt_database,
    gt_sample,
)
from .config import AUTOWARE_TO_CLASS, BOX_DIM, LazySamples, Sample
from .sweeps import EarlierSweep, pose_matrices, relative_transform, stack_sweeps
from .data_nuscenes import (  # noqa: F401  (re-exported)
    NUSCENES_TO_CLASS,
    NuScenesKeyframes,
    official_split,
    iter_nuscenes_samples,
    nuscenes_class,
    nuscenes_samples,
    scene_of,
    split_holdout,
)

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

CACHE_INDEX = "index.json"
CACHE_FORMAT = 1


# ------------------------------------------------------------------------------------------ synthetic


def frame_to_sensor_boxes(frame: GroundTruthFrame, mount_height_m: float) -> tuple[F32, I64]:
    """All of ``frame``'s objects as sensor-frame boxes (N, 9) and class indices (N,), −1 where the Autoware
    label is not a detector class. Rows stay aligned with the frame (and so with ``ScanResult.owner``).

    The sensor sits at the ego pose, ``mount_height_m`` above the ground (world z = 0); centres are rotated and
    translated into the sensor frame, z becomes relative to the sensor, yaw relative to the ego's heading, and
    velocities are rotated but not made ego-relative (nuScenes' convention: a parked car has zero velocity
    whatever the ego does)."""
    n = frame.num_objects
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    dx = frame.centers[:, 0] - frame.ego_x
    dy = frame.centers[:, 1] - frame.ego_y
    vx, vy = frame.velocities[:, 0], frame.velocities[:, 1]
    boxes = np.empty((n, BOX_DIM), np.float64)
    boxes[:, 0] = c * dx + s * dy
    boxes[:, 1] = -s * dx + c * dy
    boxes[:, 2] = frame.centers[:, 2] - mount_height_m
    boxes[:, 3:6] = frame.sizes
    boxes[:, 6] = _wrap(frame.yaws - frame.ego_yaw)
    boxes[:, 7] = c * vx + s * vy
    boxes[:, 8] = -s * vx + c * vy
    labels = np.array([AUTOWARE_TO_CLASS.get(int(lab), -1) for lab in frame.labels], np.int64)
    return boxes.astype(np.float32), labels


def sample_from_scan(frame: GroundTruthFrame, scan: ScanResult, mount_height_m: float, token: str = "") -> Sample:
    """One :class:`Sample` from a frame and its scan: detector classes only (unmapped labels dropped), point
    counts from the ray-cast, boxes raised onto the scan's ground where its effects lifted them."""
    boxes, labels = frame_to_sensor_boxes(frame, mount_height_m)
    if scan.object_lift is not None and len(boxes):
        boxes[:, 2] += scan.object_lift.astype(np.float32)
    keep = labels >= 0
    return Sample(
        points=np.ascontiguousarray(scan.points, np.float32),
        boxes=np.ascontiguousarray(boxes[keep]),
        labels=labels[keep],
        num_points=np.asarray(scan.num_points, np.int64)[keep],
        token=token,
    )


MAX_STACK_SPAN_S = 0.5
"""The oldest sweep of a synthetic stack is at most this much older than the newest (CenterPoint: 0.5 s)."""


def spread_indices(num_frames: int, k: int) -> list[int]:
    """``k`` frame indices evenly spread over ``[0, num_frames)`` (all of them if ``k >= num_frames``), so that
    consecutive samples of a scenario are not near-duplicates of each other."""
    if k <= 0 or num_frames <= 0:
        return []
    if k >= num_frames:
        return list(range(num_frames))
    return sorted({int(round(v)) for v in np.linspace(0, num_frames - 1, k)})


def synthetic_samples(
    scenarios: Sequence[str],
    seeds: Sequence[int],
    *,
    frames_per_scenario: int,
    duration_s: float = 20.0,
    sensor: LidarSpec | None = None,
    scan_seed: int = 0,
    rate_hz: float = 10.0,
    effects: str = "none",
    workers: int = 0,
    sweeps: int = 1,
) -> Iterator[Sample]:
    """Labelled synthetic scans: for every (scenario, seed), ``frames_per_scenario`` frames spread evenly over a
    ``duration_s`` scenario, ray-cast with ``sensor`` (HDL-32E, nuScenes' LIDAR_TOP, by default).

    ``effects``: ``"none"`` casts the ideal scan; ``"random"`` draws each scan's
    :class:`~jitterguard.sim.effects.ScanEffects` (uneven ground, glass, dropout, noise, the ego's roof, mixed
    pixels, street clutter, open scenery, measured intensity) with :func:`~jitterguard.sim.effects.draw_effects`
    — the domain randomisation the shipped weights train with; a comma list picks components
    (:func:`~jitterguard.sim.effects.parse_components`, e.g. ``"ground,glass"`` or ``"random,no-intensity"``).

    ``workers`` > 0 ray-casts the (scenario, seed) pairs in that many processes: a scan with effects costs
    ≈ 0.1 s of one core, so a GPU machine's cores cast a large training set in a minute instead of a quarter
    of an hour. The samples and their order are the same for any ``workers`` (each pair is seeded on its own).

    ``sweeps`` > 1 stacks each scan with ``sweeps − 1`` earlier sweeps, as CenterPoint's nuScenes input and the
    live detector service do (:mod:`.sweeps`: points (P, 5) with the time lag in seconds, earlier sweeps moved into
    the newest's sensor frame). The scenario then runs at the sensor's spin rate (HDL-32E: 20 Hz) and each sample
    draws how many spins lie between its sweeps (1 up to what keeps the stack within 0.5 s), so one model learns
    the 20 Hz stacks of a live sensor and the 2 Hz key-frame stacks of a keyframes-only recording alike; the
    sweeps of a sample share its effects, anchored in the world (``cast_frame(anchor=…)``), and a stack near the
    scenario's start holds the sweeps there are. Boxes are the newest sweep's.

    Deterministic: the same arguments give the same samples (the scan's noise and effects are seeded by
    ``scan_seed``, the scenario, its seed and the frame). Tokens are ``synthetic/{scenario}/{seed}/{seq}``.
    Yields ``len(scenarios) * len(seeds) * frames_per_scenario`` samples (fewer if a scenario has fewer
    frames), scenario-major."""
    components = parse_components(effects)
    spec = sensor or hdl32e()
    if sweeps < 1:
        raise ValueError("sweeps must be >= 1")
    jobs = [(name, int(seed), frames_per_scenario, duration_s, spec, scan_seed, rate_hz, components, int(sweeps))
            for name in scenarios for seed in seeds]
    if workers <= 0 or len(jobs) <= 1:
        for job in jobs:
            yield from _cast_scenario(job)
        return
    import multiprocessing

    # spawn, not fork: the caller may hold torch threads or a CUDA context, which a forked child must not inherit
    with multiprocessing.get_context("spawn").Pool(min(workers, len(jobs))) as pool:
        for batch in pool.imap(_cast_scenario_list, jobs):
            yield from batch


_CastJob = tuple[str, int, int, float, LidarSpec, int, float, tuple[str, ...], int]


def _cast_scenario(job: _CastJob) -> Iterator[Sample]:
    """The labelled scans of one (scenario, seed): the unit of work of :func:`synthetic_samples`."""
    name, seed, frames_per_scenario, duration_s, spec, scan_seed, rate_hz, components, sweeps = job
    sc = make_scenario(name, seed, duration_s, spec.rate_hz if sweeps > 1 else rate_hz)
    for i in spread_indices(len(sc), frames_per_scenario):
        fx = None
        if components:
            key = int.from_bytes(name.encode(), "little") % (2**31)
            fx = draw_effects(np.random.default_rng([scan_seed, key, seed, i]), components)
        if sweeps > 1:
            yield _stacked_sample(sc, i, spec, scan_seed, fx, sweeps,
                                  np.random.default_rng([scan_seed, seed, i, sweeps]), f"synthetic/{name}/{seed}")
            continue
        scan, frame = cast_frame(sc.frame(i), spec, scan_seed, effects=fx)
        yield sample_from_scan(frame, scan, spec.mount_height_m, f"synthetic/{name}/{seed}/{frame.seq}")


def _stacked_sample(sc: Scenario, i: int, spec: LidarSpec, scan_seed: int, fx: ScanEffects | None, sweeps: int,
                    rng: np.random.Generator, token: str) -> Sample:
    """Frame ``i`` of ``sc`` (at the spin rate) stacked with ``sweeps − 1`` earlier frames, a drawn number of
    spins apart (see :func:`synthetic_samples`)."""
    period = 1.0 / spec.rate_hz
    widest = max(1, int(math.floor((MAX_STACK_SPAN_S + 1e-9) / (period * (sweeps - 1)))))
    step = int(rng.integers(1, widest + 1))
    key = sc.frame(i)
    anchor = (float(key.ego_x), float(key.ego_y), float(key.ego_yaw))
    scan, frame = cast_frame(key, spec, scan_seed, effects=fx, anchor=anchor)
    sample = sample_from_scan(frame, scan, spec.mount_height_m, f"{token}/{frame.seq}")
    r_key, t_key = _sensor_pose(key, spec)
    earlier = []
    for k in range(1, sweeps):
        j = i - k * step
        if j < 0:
            break
        fj = sc.frame(j)
        sj, _ = cast_frame(fj, spec, scan_seed, effects=fx, anchor=anchor)
        r, t = relative_transform(r_key, t_key, *_sensor_pose(fj, spec))
        earlier.append(EarlierSweep(np.ascontiguousarray(sj.points, np.float32), r, t, (key.stamp_ns - fj.stamp_ns) * 1e-9))
    return Sample(points=stack_sweeps(sample.points, earlier), boxes=sample.boxes, labels=sample.labels,
                  num_points=sample.num_points, token=sample.token)


def _sensor_pose(frame: GroundTruthFrame, spec: LidarSpec) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The sensor's world pose of a synthetic frame (mount height above the nominal ground; level)."""
    return pose_matrices((frame.ego_x, frame.ego_y, spec.mount_height_m), quaternion_from_yaw(float(frame.ego_yaw)))


def _cast_scenario_list(job: _CastJob) -> list[Sample]:
    return list(_cast_scenario(job))


def _wrap(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


# ------------------------------------------------------------------------------------------ disk cache


def _progress(it: Iterable[Sample], total: int | None, desc: str, enabled: bool) -> Iterable[Sample]:
    if not enabled:
        return it
    from tqdm import tqdm  # type: ignore[import-untyped]  # only when a bar is asked for

    return tqdm(it, total=total, desc=desc, unit="scan", file=sys.stderr)


def build_cache(out_dir: str | os.PathLike[str], samples: Iterable[Sample], *, total: int | None = None,
                progress: bool = True, meta: dict[str, object] | None = None) -> int:
    """Write ``samples`` to ``out_dir`` (one uncompressed ``NNNNNN.npz`` per sample) and an ``index.json``
    naming them; returns the number written. ``total`` sizes the progress bar (stderr); ``meta`` is stored in
    the index (e.g. the scenarios and seeds, to tell caches apart).

    The index is written last, so a cache interrupted mid-way has none and :class:`CachedSamples` refuses it
    rather than silently training on a partial set. Uncompressed because the float scans barely compress and
    decompression would cost more than the read."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    idx_path = out / CACHE_INDEX
    if idx_path.exists():
        idx_path.unlink()
    entries: list[dict[str, object]] = []
    for k, s in enumerate(_progress(samples, total, f"cache {out.name}", progress)):
        name = f"{k:06d}.npz"
        with (out / name).open("wb") as fh:
            np.savez(fh, points=np.asarray(s.points, np.float32), boxes=np.asarray(s.boxes, np.float32),
                     labels=np.asarray(s.labels, np.int64), num_points=np.asarray(s.num_points, np.int64))
        entries.append({"file": name, "token": s.token, "num_points": int(len(s.points)),
                        "num_boxes": int(len(s.boxes))})
    index = {"format": CACHE_FORMAT, "count": len(entries), "meta": meta or {}, "samples": entries}
    tmp = out / (CACHE_INDEX + ".tmp")
    tmp.write_text(json.dumps(index, indent=0))
    tmp.replace(idx_path)
    return len(entries)


class CachedSamples(LazySamples):
    """A cache written by :func:`build_cache`, as a lazy random-access sequence of :class:`Sample` (each item is
    read from disk when asked for; nothing is kept in memory but the index). Torch-free, so a DataLoader's
    workers can each hold one."""

    def __init__(self, out_dir: str | os.PathLike[str]) -> None:
        self.root = Path(out_dir)
        idx_path = self.root / CACHE_INDEX
        if not idx_path.is_file():
            raise FileNotFoundError(f"{self.root}: no sample cache here ({CACHE_INDEX} missing; build it first)")
        index = json.loads(idx_path.read_text())
        if index.get("format") != CACHE_FORMAT:
            raise ValueError(f"{idx_path}: cache format {index.get('format')!r}, expected {CACHE_FORMAT}")
        self.meta: dict[str, object] = index.get("meta", {})
        self._entries: list[dict[str, object]] = index["samples"]

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def tokens(self) -> list[str]:
        return [str(e["token"]) for e in self._entries]

    def _sample(self, i: int) -> Sample:
        e = self._entries[i]
        with np.load(self.root / str(e["file"])) as z:
            return Sample(points=z["points"], boxes=z["boxes"], labels=z["labels"], num_points=z["num_points"],
                          token=str(e["token"]))
