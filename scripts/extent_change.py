"""Diagnosis (tuning seeds only; labels read to pick the rows): do the z-test's false alarms on static vehicles
come with a change of the detected box's extent between the window's halves — an occlusion change that moves a
box centre placed from the faces the sensor sees?

For every static-vehicle row with a full window the tracker's associated detections of the window's frames give
the half-mean contrast of the box's length and width (|Δl|, |Δw|, m) and of its position along and across the
box's own heading; printed as medians for the rows the z-test calls moving and for the rest, and the share of each
with |Δl| or |Δw| over 0.5 m.

    .venv/bin/python scripts/extent_change.py --scenario mixed --seeds 0-3 --input detector --cache DIR
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import classifier_config, classify_seeds, input_arguments, seed_pairs  # noqa: E402
from jitterguard.eval.metrics import scored_rows  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC  # noqa: E402
from jitterguard.services.tracker import core as tracker_core  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    args = ap.parse_args()
    pairs = seed_pairs(args)
    history: dict = defaultdict(list)  # (run, track id) -> [(seq, length, width, x, y, yaw)]
    run = {"i": 0}
    step = tracker_core.TrackerCore.step

    def hooked(self, frame):  # noqa: ANN001, ANN202
        result = step(self, frame)
        ids = result.tracks.ids
        length = frame.length if frame.length is not None else np.full(len(frame), np.nan)
        width = frame.width if frame.width is not None else np.full(len(frame), np.nan)
        d = result.detections
        for t, k in zip(result.obs_track.tolist(), result.obs_det.tolist()):
            history[(run["i"], ids[t])].append((frame.seq, length[k], width[k], d.x[k], d.y[k], d.yaw[k]))
        return result

    tracker_core.TrackerCore.step = hooked
    try:
        recs = classify_seeds(pairs, classifier_config(args), on_run=lambda i: run.update(i=i))
    finally:
        tracker_core.TrackerCore.step = step
    out: dict[bool, list] = {True: [], False: []}
    for i, rec in enumerate(recs):
        static = scored_rows(rec, "vehicle") & ~rec.gt_dynamic & (rec.window >= rec.window_size)
        for k in np.flatnonzero(static).tolist():
            h = [r for r in history[(i, str(rec.track_id[k]))] if r[0] <= int(rec.seq[k])][-int(rec.window[k]):]
            if len(h) < 4:
                continue
            a = np.array(h, dtype=np.float64)
            n_new = (len(a) + 1) // 2
            old, new = a[:-n_new], a[-n_new:]
            dl, dw = new[:, 1].mean() - old[:, 1].mean(), new[:, 2].mean() - old[:, 2].mean()
            yaw = a[-1, 5]
            dx, dy = new[:, 3].mean() - old[:, 3].mean(), new[:, 4].mean() - old[:, 4].mean()
            along, across = dx * np.cos(yaw) + dy * np.sin(yaw), -dx * np.sin(yaw) + dy * np.cos(yaw)
            out[bool(rec.state_z[k] == DYNAMIC)].append((abs(dl), abs(dw), abs(along), abs(across)))
    for fired, rows in ((True, out[True]), (False, out[False])):
        a = np.array(rows).reshape(-1, 4)
        if not len(a):
            continue
        med = np.median(a, axis=0)
        print(f"static vehicle rows called {'moving' if fired else 'static'}: {len(a)}; median |Δl| {med[0]:.3f} m, "
              f"|Δw| {med[1]:.3f} m, |Δ along| {med[2]:.3f} m, |Δ across| {med[3]:.3f} m; share |Δl| or |Δw| > 0.5 m "
              f"{np.mean((a[:, 0] > 0.5) | (a[:, 1] > 0.5)):.3f}; corr(|Δl|, |Δ along|) "
              f"{np.corrcoef(a[:, 0], a[:, 2])[0, 1]:.2f}")


if __name__ == "__main__":
    main()
