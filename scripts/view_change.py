"""Experiment (docs/results.md, "What the detector's static false alarms are made of"; tuning seeds only): do the
z-test's false alarms on static vehicles follow the change of the sensor's view of the object, and what would a
view-change term in the test buy?

    .venv/bin/python scripts/view_change.py --scenario diagonal-lot --seeds 0-3 --input detector --diagnose
    .venv/bin/python scripts/view_change.py --scenario diagonal-lot --seeds 0-3 --input detector --s 0,0.5,1,2

``--diagnose``: for static vehicle rows (matched, window ≥ 10) the half-mean contrast d of the positions and Δū,
the same contrast of the unit line-of-sight vectors; medians of |d|, |Δū| and cos(d, Δū) for the rows the
z-test calls dynamic and for the rest. ``--s``: the test with s² Δū Δūᵀ added to the contrast's covariance for
vehicles (a box centre that shifts by about s metres per unit change of the view direction: the classifier's
``view_slide_m_per_class``); vehicle and pedestrian false / missed / ghost rates per s on the same tracks."""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import classifier_config, classify_seeds, input_arguments, rates_line, seed_pairs  # noqa: E402
from jitterguard.eval.metrics import scored_rows  # noqa: E402
from jitterguard.eval.pipeline import concat_records  # noqa: E402
from jitterguard.services.classifier import core as core_mod  # noqa: E402
from jitterguard.services.classifier.calibration import vehicle_class_names  # noqa: E402
from jitterguard.services.classifier.core import DYNAMIC  # noqa: E402
from jitterguard.services.classifier.statistics import split_halves  # noqa: E402

def _run(args: argparse.Namespace, pairs: dict, slide: float = 0.0, on_run: Callable[[int], None] | None = None) -> list:
    """The evaluator's tracker and classifier over each seed's cached detections as one drive; the classifier's
    view term for vehicles at ``slide`` m (0: none)."""
    slides = dict.fromkeys(vehicle_class_names(), slide) if slide else {}
    return classify_seeds(pairs, classifier_config(args, view_slide_m_per_class=slides), on_run=on_run)


def _contrasts(args: argparse.Namespace, pairs: dict) -> None:
    """Record each decided window's contrasts of position and of the line of sight, join them to the scored rows."""
    log: dict[tuple[int, int, str], tuple[float, float, float, float]] = {}
    run = {"i": 0}
    statistic = core_mod.MotionClassifierCore._statistics

    def hooked(self, rows):  # noqa: ANN001, ANN202
        if self._config.mode == "z_test":
            t = self._table
            win = t.ordered(rows, t.window)
            m = split_halves(np.zeros(len(rows), dtype=np.int64), t.count[rows], t.window)
            w = m.new / np.maximum(m.n_new, 1)[:, None] - m.old / np.maximum(m.n_old, 1)[:, None]
            ux, uy = win[..., 0] - win[..., 6], win[..., 1] - win[..., 7]
            r = np.maximum(np.hypot(ux, uy), 1e-6)
            cols = [(w * win[..., 0]).sum(1), (w * win[..., 1]).sum(1), (w * ux / r).sum(1), (w * uy / r).sum(1)]
            ids = dict(zip(self._id_rows.tolist(), self._ids.tolist()))
            for j, row in enumerate(rows.tolist()):
                log[(run["i"], int(self._clock[1]), ids[row].decode())] = tuple(float(c[j]) for c in cols)
        return statistic(self, rows)

    core_mod.MotionClassifierCore._statistics = hooked
    try:
        recs = _run(args, pairs, on_run=lambda i: run.update(i=i))
    finally:
        core_mod.MotionClassifierCore._statistics = statistic
    d, du, fired = [], [], []
    for i, rec in enumerate(recs):
        static = scored_rows(rec, "vehicle") & ~rec.gt_dynamic & (rec.window >= 10)
        for k in np.flatnonzero(static).tolist():
            v = log.get((i, int(rec.seq[k]), str(rec.track_id[k])))
            if v is not None:
                d.append(v[:2])
                du.append(v[2:])
                fired.append(rec.state_z[k] == DYNAMIC)
    d, du, fired = np.array(d), np.array(du), np.array(fired)
    nd, ndu = np.hypot(*d.T), np.hypot(*du.T)
    cos = np.sum(d * du, 1) / np.maximum(nd * ndu, 1e-12)
    for name, m in (("called dynamic", fired), ("called static", ~fired)):
        print(f"static vehicle rows {name}: {m.sum()}, |d| median {np.median(nd[m]):.3f} m, |Δū| median "
              f"{np.median(ndu[m]):.3f}, cos(d, Δū) median {np.median(cos[m]):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--s", default="0,0.5,1,2")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    if args.diagnose:
        _contrasts(args, pairs)
        return
    for text in args.s.split(","):
        rec = concat_records(_run(args, pairs, float(text)), [str(s) for s in pairs])
        print(f"s {text:>4} | {rates_line(rec)}", flush=True)


if __name__ == "__main__":
    main()
