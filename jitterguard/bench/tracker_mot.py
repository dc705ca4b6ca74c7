"""Run the tracker core over a synthetic sequence and score it with motmetrics (MOTA, IDF1, ID switches).

Ground truth is every object within sensor range (occluded and missed ones included: a tracker is expected to
coast through them); a hypothesis is every confirmed track the core reports for the frame. A match needs the
centres within ``max_dist`` metres (2 m, nuScenes' tracking threshold).
"""

from __future__ import annotations

from dataclasses import dataclass

import motmetrics as mm  # the eval extra; this module is imported only by the tracker-mot bench and tests
import numpy as np

from ..services.tracker.config import TrackerConfig, default_config
from ..services.tracker.core import TrackerCore
from .tracker_sequences import Sequence, make_sequence

METRICS = ["mota", "idf1", "num_switches", "num_false_positives", "num_misses", "num_objects", "motp",
           "num_unique_objects", "mostly_tracked"]


@dataclass
class MotResult:
    mota: float
    idf1: float
    id_switches: int
    false_positives: int
    misses: int
    gt: int
    motp: float
    unique_objects: int
    mostly_tracked: int

    def as_dict(self) -> dict[str, float]:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def evaluate(seq: Sequence, config: TrackerConfig | None = None, max_dist: float = 2.0) -> MotResult:
    core = TrackerCore(config)
    acc = mm.MOTAccumulator(auto_id=True)
    numeric: dict[str, int] = {}  # motmetrics wants numeric hypothesis IDs
    for f in seq.frames:
        res = core.step(f.detections)
        hyp = np.stack([res.tracks.x, res.tracks.y], axis=1) if len(res.tracks) else np.zeros((0, 2))
        d = mm.distances.norm2squared_matrix(f.gt_xy, hyp, max_d2=max_dist * max_dist)
        acc.update(list(f.gt_ids), [numeric.setdefault(t, len(numeric)) for t in res.tracks.ids], d)
    s = mm.metrics.create().compute(acc, metrics=METRICS, name="seq").iloc[0]
    return MotResult(
        mota=float(s["mota"]), idf1=float(s["idf1"]), id_switches=int(s["num_switches"]),
        false_positives=int(s["num_false_positives"]), misses=int(s["num_misses"]), gt=int(s["num_objects"]),
        motp=float(np.sqrt(s["motp"])) if np.isfinite(s["motp"]) else float("nan"),
        unique_objects=int(s["num_unique_objects"]), mostly_tracked=int(s["mostly_tracked"]),
    )


def mot_summary(seeds: list[int], frames: int = 150, measurement_covariance: str = "detector") -> dict:
    """MOTA, IDF1 and ID switches per seeded sequence and over all of them (``jitterguard bench tracker-mot``)."""
    cfg = default_config(measurement_covariance=measurement_covariance)
    per_seed = {f"seed_{s}": evaluate(make_sequence(s, n_frames=frames), cfg).as_dict() for s in seeds}
    rows = list(per_seed.values())
    summary = {
        "mota_mean": round(sum(r["mota"] for r in rows) / len(rows), 4),
        "idf1_mean": round(sum(r["idf1"] for r in rows) / len(rows), 4),
        "mota_min": min(r["mota"] for r in rows),
        "idf1_min": min(r["idf1"] for r in rows),
        "id_switches_total": sum(r["id_switches"] for r in rows),
        "frames_per_seed": frames,
        "measurement_covariance": measurement_covariance,
    }
    return {"summary": summary, **per_seed}
