"""Track-ID survival: how many confirmed track IDs live on for a second while their object stays in view.

Why this figure: the classifier's z-test needs a window of observations under one track ID, and a planner or
an operator following an ID (``/v1/state``) loses it when the tracker drops the track on a missed detection and
starts a new one. MOTA/IDF1 average that away; this asks the question directly:

    of every (frame t, confirmed track matched to ground-truth object o) where o stays in view from t to
    t + horizon, in what fraction is the same track ID still reported (confirmed) at t + horizon?

"In view" means what a detector could see: the object is of a class the detector detects, within that class's
evaluation range of the sensor (nuScenes' 50 m / 40 m) and hit by at least ``min_points`` LiDAR returns, in
every frame of the interval. ``same_object`` additionally needs the ID to still be matched to o at the end
(an ID that survived by jumping to a neighbour is an ID switch, not survival).

Also counted: tentative (unconfirmed) tracks reaching the output must be zero by construction, and is checked;
tracks born per frame and confirmed tracks per frame describe the churn.

:func:`survival` is pure (frames in, figures out); ``jitterguard bench track-survival``
(:mod:`jitterguard.bench.survival`) runs the shipped detector on ray-cast scans of a synthetic scenario, as the live stack
does, and prints JSON.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..schemas import encode, read_detected_objects
from ..schemas.models import DetectedObjects
from ..services.detector.config import AUTOWARE_TO_CLASS, CLASS_RANGE_M
from ..services.tracker.config import TrackerConfig, default_config
from ..services.tracker.adapter import detection_frame
from ..services.tracker.core import FrameRejected, TrackerCore
from ..sim.world import GroundTruthFrame
from .pipeline import MATCH_DISTANCE_M, match_tracks

DEFAULT_MIN_POINTS = 5
"""LiDAR returns an object needs to count as in view (a box with fewer is rarely detectable at all)."""


@dataclass
class _FrameRecord:
    stamp_ns: int
    reported: set[str]
    match: dict[str, int]  # confirmed track ID -> ground-truth instance (matched ones only)
    in_view: set[int]  # ground-truth instances a detector could see


def in_view(gt: GroundTruthFrame, min_points: int) -> set[int]:
    """Instances of ``gt`` the detector could see: a detector class, within its range, ≥ ``min_points`` returns."""
    out: set[int] = set()
    for k in range(gt.num_objects):
        cls = AUTOWARE_TO_CLASS.get(int(gt.labels[k]))
        if cls is None or int(gt.num_points[k]) < min_points:
            continue
        dist = math.hypot(float(gt.centers[k, 0]) - gt.ego_x, float(gt.centers[k, 1]) - gt.ego_y)
        if dist <= CLASS_RANGE_M[cls]:
            out.add(int(gt.instance_ids[k]))
    return out


@dataclass
class SurvivalRun:
    """What one sequence gave: per confirmed track, its trials and how many it survived; and the churn counts."""

    per_track: dict[str, list[int]] = field(default_factory=dict)  # track ID -> [trials, alive, same object]
    counts: dict[str, int] = field(default_factory=dict)
    horizon_s: float = 1.0
    min_points: int = DEFAULT_MIN_POINTS


BOOTSTRAP_REPS = 1000


def _rate_ci(trials: np.ndarray, hits: np.ndarray, rng: np.random.Generator) -> list[float] | None:
    """95 % interval of sum(hits)/sum(trials) by resampling whole tracks (a track's trials, one per frame, are
    far from independent: a binomial interval over them would be several times too narrow)."""
    n = trials.size
    if n == 0 or trials.sum() == 0:
        return None
    idx = rng.integers(0, n, size=(BOOTSTRAP_REPS, n))
    t = trials[idx].sum(axis=1)
    rates = hits[idx].sum(axis=1) / np.maximum(t, 1)
    lo, hi = np.percentile(rates[t > 0], [2.5, 97.5])
    return [round(float(lo), 4), round(float(hi), 4)]


def score(runs: list[SurvivalRun], seed: int = 0) -> dict[str, Any]:
    """Survival over one or more runs (pooled), with track-resampled 95 % intervals (seeded)."""
    rows = np.array([v for r in runs for v in r.per_track.values()], dtype=np.int64).reshape(-1, 3)
    trials, alive, same = (rows[:, k] for k in range(3))
    n = int(trials.sum())
    c: dict[str, int] = {}
    for r in runs:
        for k, v in r.counts.items():
            c[k] = c.get(k, 0) + v
    rng = np.random.default_rng(seed)

    def ratio(a: int, b: int, nd: int = 4) -> float | None:
        return round(a / b, nd) if b else None

    return {
        "survival": ratio(int(alive.sum()), n),
        "survival_ci95": _rate_ci(trials, alive, rng),
        "survival_same_object": ratio(int(same.sum()), n),
        "survival_same_object_ci95": _rate_ci(trials, same, rng),
        "trials": n,
        "tracks": int((trials > 0).sum()),
        "coverage": ratio(c.get("covered", 0), c.get("seen", 0)),
        "all_confirmed_survival": ratio(c.get("any_alive", 0), c.get("any", 0)),
        "unmatched_confirmed_fraction": ratio(c.get("ghosts", 0), c.get("any", 0)),
        "frames": c.get("frames", 0),
        "tracks_born_per_frame": ratio(c.get("born", 0), c.get("frames", 0), 2),
        "confirmed_per_frame": ratio(c.get("confirmed", 0), c.get("frames", 0), 2),
        "tentative_published": c.get("tentative_published", 0),
        "horizon_s": runs[0].horizon_s if runs else None,
        "min_points": runs[0].min_points if runs else None,
    }


def survival_run(frames: Iterable[tuple[GroundTruthFrame, DetectedObjects | bytes]], tracker: TrackerConfig | None = None, *,
                 horizon_s: float = 1.0, min_points: int = DEFAULT_MIN_POINTS,
                 match_distance_m: float = MATCH_DISTANCE_M) -> SurvivalRun:
    """Run the tracker core over (ground truth, detections) pairs and collect the survival trials (module
    docstring). The detections (a ``DetectedObjects`` model, or its wire payload as the detector service
    publishes it) go through the wire and the tracker service's own read and conversion
    (:func:`~jitterguard.schemas.read_detected_objects`, ``detection_frame``); track IDs are deterministic so a
    run repeats."""
    counter = iter(range(1, 1 << 62))
    core = TrackerCore(tracker or default_config(), lambda: f"{next(counter):032x}")
    recs: list[_FrameRecord] = []
    c = dict.fromkeys(("frames", "born", "confirmed", "tentative_published", "seen", "covered", "any", "any_alive",
                       "ghosts"), 0)
    for gt, msg in frames:
        frame = detection_frame(read_detected_objects(msg if isinstance(msg, bytes) else encode(msg)))
        try:
            res = core.step(frame)
        except FrameRejected:
            continue
        c["frames"] += 1
        c["born"] += len(res.born)
        snap = res.tracks
        ids = list(snap.ids)
        confirmed = set(core.tracks.ids[i] for i in np.flatnonzero(core.tracks.confirmed))
        c["tentative_published"] += sum(1 for t in ids if t not in confirmed)
        c["confirmed"] += len(ids)
        xy = np.stack([np.asarray(snap.x), np.asarray(snap.y)], axis=1) if ids else np.zeros((0, 2))
        gi = match_tracks(xy, gt.centers[:, :2], match_distance_m) if gt.num_objects else np.full(len(ids), -1)
        match = {tid: int(gt.instance_ids[g]) for tid, g in zip(ids, gi.tolist()) if g >= 0}
        visible = in_view(gt, min_points)
        c["seen"] += len(visible)
        c["covered"] += len(visible & set(match.values()))
        recs.append(_FrameRecord(int(gt.stamp_ns), set(ids), match, visible))

    run = SurvivalRun(counts=c, horizon_s=horizon_s, min_points=min_points)
    horizon_ns = int(round(horizon_s * 1e9))
    stamps = np.array([r.stamp_ns for r in recs], dtype=np.int64)
    for i, r in enumerate(recs):
        j = int(np.searchsorted(stamps, r.stamp_ns + horizon_ns, side="left"))
        if j >= len(recs):
            break
        window, end = recs[i + 1 : j + 1], recs[j]
        c["any"] += len(r.reported)
        c["any_alive"] += len(r.reported & end.reported)
        c["ghosts"] += len(r.reported) - len(r.match)
        for tid, inst in r.match.items():
            if inst not in r.in_view or any(inst not in w.in_view for w in window):
                continue
            row = run.per_track.setdefault(tid, [0, 0, 0])
            row[0] += 1
            if tid in end.reported:
                row[1] += 1
                row[2] += int(end.match.get(tid) == inst)
    return run


def survival(frames: Iterable[tuple[GroundTruthFrame, DetectedObjects | bytes]], tracker: TrackerConfig | None = None, *,
             horizon_s: float = 1.0, min_points: int = DEFAULT_MIN_POINTS,
             match_distance_m: float = MATCH_DISTANCE_M) -> dict[str, Any]:
    """:func:`score` of one :func:`survival_run`."""
    return score([survival_run(frames, tracker, horizon_s=horizon_s, min_points=min_points,
                               match_distance_m=match_distance_m)])
