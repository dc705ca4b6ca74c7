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
(:mod:`.survival_cli`) runs the shipped detector on ray-cast scans of a synthetic scenario, as the live stack
does, and prints JSON.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..schemas.models import DetectedObjects
from ..services.detector.config import AUTOWARE_TO_CLASS, CLASS_RANGE_M
from ..services.tracker.config import TrackerConfig, default_config
from ..services.tracker.convert import frame_from_message
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


def wilson(k: int, n: int, z: float = 1.96) -> list[float] | None:
    """95 % Wilson score interval of k successes in n trials (None when n = 0)."""
    if n == 0:
        return None
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return [round(c - h, 4), round(c + h, 4)]


def survival(frames: Iterable[tuple[GroundTruthFrame, DetectedObjects]], tracker: TrackerConfig | None = None, *,
             horizon_s: float = 1.0, min_points: int = DEFAULT_MIN_POINTS,
             match_distance_m: float = MATCH_DISTANCE_M) -> dict[str, Any]:
    """Run the tracker core over (ground truth, detections) pairs and score track-ID survival (module docstring).

    The detections go through the tracker service's own conversion (``frame_from_message``); track IDs are
    deterministic so a run repeats.
    """
    counter = iter(range(1, 1 << 62))
    core = TrackerCore(tracker or default_config(), lambda: f"{next(counter):032x}")
    recs: list[_FrameRecord] = []
    born = frames_n = confirmed_total = tentative_published = seen = covered = 0
    for gt, msg in frames:
        frame = frame_from_message(msg)
        try:
            res = core.step(frame)
        except FrameRejected:
            continue
        frames_n += 1
        born += len(res.born)
        snap = res.tracks
        ids = list(snap.ids)
        confirmed = set(core.tracks.ids[i] for i in np.flatnonzero(core.tracks.confirmed))
        tentative_published += sum(1 for t in ids if t not in confirmed)
        confirmed_total += len(ids)
        xy = np.stack([np.asarray(snap.x), np.asarray(snap.y)], axis=1) if ids else np.zeros((0, 2))
        gi = match_tracks(xy, gt.centers[:, :2], match_distance_m) if gt.num_objects else np.full(len(ids), -1)
        match = {tid: int(gt.instance_ids[g]) for tid, g in zip(ids, gi.tolist()) if g >= 0}
        visible = in_view(gt, min_points)
        seen += len(visible)
        covered += len(visible & set(match.values()))
        recs.append(_FrameRecord(int(gt.stamp_ns), set(ids), match, visible))

    horizon_ns = int(round(horizon_s * 1e9))
    stamps = np.array([r.stamp_ns for r in recs], dtype=np.int64)
    trials = alive = same = any_n = any_alive = ghosts = 0
    for i, r in enumerate(recs):
        j = int(np.searchsorted(stamps, r.stamp_ns + horizon_ns, side="left"))
        if j >= len(recs):
            break
        window = recs[i + 1 : j + 1]
        any_n += len(r.reported)
        any_alive += len(r.reported & recs[j].reported)
        ghosts += len(r.reported) - len(r.match)
        for tid, inst in r.match.items():
            if inst not in r.in_view or any(inst not in w.in_view for w in window):
                continue
            trials += 1
            end = recs[j]
            if tid in end.reported:
                alive += 1
                if end.match.get(tid) == inst:
                    same += 1
    return {
        "survival": round(alive / trials, 4) if trials else None,
        "survival_ci95": wilson(alive, trials),
        "survival_same_object": round(same / trials, 4) if trials else None,
        "survival_same_object_ci95": wilson(same, trials),
        "trials": trials,
        "coverage": round(covered / seen, 4) if seen else None,
        "all_confirmed_survival": round(any_alive / any_n, 4) if any_n else None,
        "unmatched_confirmed_fraction": round(ghosts / any_n, 4) if any_n else None,
        "frames": frames_n,
        "tracks_born_per_frame": round(born / frames_n, 2) if frames_n else None,
        "confirmed_per_frame": round(confirmed_total / frames_n, 2) if frames_n else None,
        "tentative_published": tentative_published,
        "horizon_s": horizon_s,
        "min_points": min_points,
    }
