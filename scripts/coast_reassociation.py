"""Would a coasting track taking the detection its gate refused give fewer re-born tracks and fewer young windows?
(docs/tracker.md, "Tracks per object"; measured 5 Dec 2026 and not adopted.)

    .venv/bin/python scripts/coast_reassociation.py --factors 0,1.5,2 --scenario mixed --seeds 0-3 \
        [--input gt-noise|detector] [--cache DIR]

A prototype hooked into the live tracker core for the run (nothing in the package changes): after the main
assignment and the newborns' second detections, each confirmed track that took no detection this frame may take
one that no track took, through Autoware's gates with the Mahalanobis gate widened ``factor`` times (0: the
tracker as shipped), before the rest start new tracks. Prints, per factor, the confirmed tracks and the z-test's
and the threshold's rates as ``jitterguard eval`` scores them. For diagnosis on tuning seeds.
"""

from __future__ import annotations

import argparse

import numpy as np

from ghost_breakdown import classifier_config, classify_seeds, input_arguments, rates_line, seed_pairs
from jitterguard.eval.metrics import ghost_rows, scored_rows
from jitterguard.eval.pipeline import concat_records
from jitterguard.services.classifier.core import DYNAMIC
from jitterguard.services.tracker import core as tracker_core
from jitterguard.services.tracker.association import assign, gate
from jitterguard.services.tracker.config import load_config

SHIPPED = tracker_core.TrackerCore._second_detections


def with_coasting(factor: float):  # type: ignore[no-untyped-def]
    """The tracker's second-chance step, followed by the coasting tracks' wider gate."""

    def second(self, f, det, stamp, rows, cols, stale, usable):  # type: ignore[no-untyped-def]
        rows, cols = SHIPPED(self, f, det, stamp, rows, cols, stale, usable)
        tr, cfg, tb = self.tracks, self.config, self.tables
        taken = np.zeros(len(tr), dtype=bool)
        taken[rows] = True
        coast = np.flatnonzero(tr.confirmed & ~taken & ~stale)
        free_mask = usable.copy()
        free_mask[cols] = False
        free = np.flatnonzero(free_mask)
        if factor <= 0 or coast.size == 0 or free.size == 0:
            return rows, cols
        pos = np.stack([det.x, det.y], axis=1)
        cand = gate(tr.x[coast, :2], tr.label[coast], tr.x[coast, 2], tr.P[coast, :2, :2], pos[free], f.label[free],
                    f.area[free], det.yaw[free], (f.orientation > 0)[free], det.R[free, :2, :2], tb,
                    cfg.mahalanobis_gate * factor, cfg.mahalanobis_covariance == "innovation", cfg.score_threshold,
                    cfg.gate_min_variance, cfg.max_candidates)
        r2, c2 = assign(coast.size, free.size, cand)
        return np.concatenate([rows, coast[r2]]), np.concatenate([cols, free[c2]])

    return second


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap, default_input="gt-noise")
    ap.add_argument("--factors", default="0,1.5,2", help="Mahalanobis gate factors of coasting tracks (0: as shipped)")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    for factor in (float(x) for x in args.factors.split(",")):
        tracker_core.TrackerCore._second_detections = with_coasting(factor)
        rec = concat_records(classify_seeds(pairs, classifier_config(args), load_config(None)),
                             [str(s) for s in pairs])
        print(f"factor {factor:g}: confirmed tracks {len(np.unique(rec.track_id))}; z-test {rates_line(rec)}")
        for group in ("vehicle", "pedestrian"):
            m = scored_rows(rec, group)
            print(f"   threshold {group}: false {np.mean(rec.state_v[m & ~rec.gt_dynamic] == DYNAMIC):.4f} missed "
                  f"{np.mean(rec.state_v[m & rec.gt_dynamic] != DYNAMIC):.4f} ghost "
                  f"{np.mean(rec.state_v[ghost_rows(rec, group)] == DYNAMIC):.4f}")
    tracker_core.TrackerCore._second_detections = SHIPPED


if __name__ == "__main__":
    main()
