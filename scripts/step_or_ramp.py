"""Diagnosis (tuning seeds only; labels read to pick the rows): is a static object's window that the z-test calls
moving shaped like a jump — the detector re-placing the box once — rather than a ramp, as a mover's is?

For every decided row with a full window: the sum of squared residuals of the window's positions about the best
constant-velocity line (per axis) and about the best single step (each side of one split its own mean, the split
shared by both axes); R = SSE_step / SSE_line (< 1: a jump explains the window better than motion does). Printed
per kind of row: static called moving (false alarms), static called static, moving called moving (hits), moving
called static (misses), ghosts called moving — the share with R < 1 and R's median.

    .venv/bin/python scripts/step_or_ramp.py --scenario mixed --seeds 0-3 --input detector --cache DIR
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import classifier_config, classify_seeds, input_arguments, seed_pairs  # noqa: E402
from jitterguard.eval.metrics import ghost_rows, scored_rows  # noqa: E402
from jitterguard.services.classifier import core as core_mod  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC, MotionClassifierCore  # noqa: E402


def step_line_ratio(t: np.ndarray, xy: np.ndarray) -> float:
    """SSE about the best single step over SSE about the least-squares line (both axes pooled)."""
    n = len(t)
    tc = t - t.mean()
    b = (tc @ (xy - xy.mean(0))) / max(float(tc @ tc), 1e-12)
    sse_line = float(((xy - xy.mean(0) - np.outer(tc, b)) ** 2).sum())
    csum, csq = np.cumsum(xy, 0), np.cumsum((xy ** 2).sum(1))
    best = np.inf
    for k in range(2, n - 1):  # at least two observations on each side
        left = csq[k - 1] - (csum[k - 1] ** 2).sum() / k
        rs, rq = csum[-1] - csum[k - 1], csq[-1] - csq[k - 1]
        right = rq - (rs ** 2).sum() / (n - k)
        best = min(best, float(left + right))
    return best / max(sse_line, 1e-12)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--group", default="vehicle", choices=("vehicle", "pedestrian"))
    args = ap.parse_args()
    pairs = seed_pairs(args)
    log: dict = {}
    run = {"i": 0}
    statistic = MotionClassifierCore._statistics

    def hooked(self, rows):  # noqa: ANN001, ANN202
        t = self._table
        win = t.ordered(rows, t.window)
        count = t.count[rows]
        ids = dict(zip(self._id_rows.tolist(), self._ids.tolist()))
        for j, row in enumerate(rows.tolist()):
            n = int(count[j])
            if n >= 6:
                w = win[j, -n:]
                log[(run["i"], int(self._clock[1]), ids[row].decode())] = step_line_ratio(w[:, 5], w[:, :2])
        return statistic(self, rows)

    core_mod.MotionClassifierCore._statistics = hooked
    try:
        recs = classify_seeds(pairs, classifier_config(args), on_run=lambda i: run.update(i=i))
    finally:
        core_mod.MotionClassifierCore._statistics = statistic
    kinds: dict[str, list[float]] = {k: [] for k in ("static called moving", "static called static",
                                                     "moving called moving", "moving called static",
                                                     "ghost called moving", "ghost called static")}
    for i, rec in enumerate(recs):
        scored, ghost = scored_rows(rec, args.group), ghost_rows(rec, args.group)
        full = rec.window >= rec.window_size
        for k in np.flatnonzero((scored | ghost) & full).tolist():
            r = log.get((i, int(rec.seq[k]), str(rec.track_id[k])))
            if r is None:
                continue
            fired = rec.state_z[k] == DYNAMIC
            what = "ghost" if ghost[k] else "moving" if rec.gt_dynamic[k] else "static"
            kinds[f"{what} called {'moving' if fired else 'static'}"].append(r)
    for name, v in kinds.items():
        if v:
            a = np.array(v)
            print(f"{name:22s} {len(a):6d} rows: share R < 1 {np.mean(a < 1):.3f}, R < 0.7 {np.mean(a < 0.7):.3f}, "
                  f"median R {np.median(a):.2f}")


if __name__ == "__main__":
    main()
