"""Why the z-test misses moving objects in young windows: each factor of the calibrated statistic switched off in
turn, on the same rows, on the synthetic tuning seeds (docs/results.md, "Why the z-test misses young windows").

    .venv/bin/python scripts/z_factors.py [--scenario mixed] [--seeds 0-3] [--noise jittery]

Runs the evaluator's pipeline (the live tracker and classifier cores, the honest noise model) over the seeds as
one drive, exactly like ``jitterguard eval --runs``, and for every row the z-test core decides also computes the
statistic without the per-track scale prior (normal instead of Student-t), with the paper's H0 (v = 0), with the
reported variances (no calibration scales, no prior) and with independent observations (no serial
correlation). Prints, per class group and window length: the rate at which each variant calls moving rows
dynamic and static rows dynamic, the median displacement of the half-window means and the calibrated standard
deviation it is tested against; then each variant's missed rate at equal false-dynamic rates (its ROC), and
what a lower α on young windows alone would buy. For diagnosis on tuning seeds only (never the test seeds
2000–2009). Prints tables; no files.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from jitterguard.eval.pipeline import NOISE_PRESETS, run_pipeline
from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier import core as core_module
from jitterguard.services.classifier.calibration import group_of_labels
from jitterguard.services.classifier.statistics import calibrated_statistics, split_halves
from jitterguard.sim.world import make_scenario

VARIANTS = ("default", "no_track_prior", "h0_v0", "reported_var", "independent")
WINDOW_BINS = ((2, 3), (3, 4), (4, 6), (6, 10), (10, 11))


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


class _Recorder:
    """Wraps ``MotionClassifierCore._decide`` of the z-test core: per decided row, max(z_x, z_y) of every
    variant, the half-mean displacement and its calibrated σ (per axis, averaged), keyed by (part, track, seq)."""

    def __init__(self) -> None:
        self.rows: dict[tuple[int, str, int], dict[str, float]] = {}
        self.part = 0
        self._orig = core_module.MotionClassifierCore._decide
        recorder = self

        def decide(core, rows, ids, speed, stamp_ns, seq):  # noqa: ANN001, ANN202 - the wrapped method
            out = recorder._orig(core, rows, ids, speed, stamp_ns, seq)
            if core.config.mode == "z_test":
                recorder.record(core, rows, ids, seq, out)
            return out

        core_module.MotionClassifierCore._decide = decide

    def record(self, core, rows, ids, seq, out) -> None:  # noqa: ANN001
        cfg, t = core.config, core._table
        count = t.count[rows]
        masks = split_halves(np.zeros(len(rows), dtype=np.int64), count, t.window)
        win = t.ordered(rows, t.window)
        groups = group_of_labels(t.label[rows])
        model = core.noise_model()
        kw = dict(variance_floor=cfg.variance_floor, effective_n=cfg.effective_n, min_speed=cfg.min_speed_mps)
        raw = calibrated_statistics(win, masks, groups, model, track_scale_prior=False, **{**kw, "min_speed": 0.0})
        stats = {
            "default": out,
            "no_track_prior": calibrated_statistics(win, masks, groups, model, track_scale_prior=False, **kw),
            "h0_v0": calibrated_statistics(win, masks, groups, model, track_scale_prior=True,
                                           **{**kw, "min_speed": 0.0}),
            "reported_var": calibrated_statistics(win, masks, groups, replace(model, scale=np.ones_like(model.scale)),
                                                  track_scale_prior=False, **kw),
            "independent": calibrated_statistics(win, masks, groups, model, track_scale_prior=False,
                                                 **{**kw, "effective_n": "independent"}),
        }
        w = masks.new / np.maximum(masks.n_new, 1)[:, None] - masks.old / np.maximum(masks.n_old, 1)[:, None]
        dx, dy = (w * win[..., 0]).sum(1), (w * win[..., 1]).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            sd = 0.5 * (np.abs(dx) / raw.z_x + np.abs(dy) / raw.z_y)  # σ of the contrast, from z = |Δ| / σ
        for i, tid in enumerate(ids.tolist()):
            rec = {k: float(max(s.z_x[i], s.z_y[i])) for k, s in stats.items()}
            rec.update(d=float(np.hypot(dx[i], dy[i])), sd=float(sd[i]), n=float(count[i]))
            self.rows[(self.part, tid.decode(), int(seq))] = rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="mixed")
    ap.add_argument("--seeds", default="0-3")
    ap.add_argument("--noise", default="jittery")
    args = ap.parse_args()
    cfg = ClassifierConfig()
    drive = core_module.MotionClassifierCore.make_online(cfg)
    rec = _Recorder()
    table: dict[str, list] = {k: [] for k in ("group", "dyn", "alpha", *VARIANTS, "d", "sd", "n")}
    for part, seed in enumerate(_seeds(args.seeds)):
        rec.part = part
        r = run_pipeline(make_scenario(args.scenario, seed, 15.0, 10.0), NOISE_PRESETS[args.noise](), seed, cfg,
                         calibration=drive)
        for i in np.flatnonzero((r.gt_instance >= 0) & (r.window >= 2)).tolist():
            row = rec.rows.get((part, str(r.track_id[i]), int(r.seq[i])))
            if row is None:
                continue
            table["group"].append(str(r.group[i]))
            table["dyn"].append(bool(r.gt_dynamic[i]))
            table["alpha"].append(float(r.alpha[i]))
            for k in (*VARIANTS, "d", "sd", "n"):
                table[k].append(row[k])
    a = {k: np.asarray(v) for k, v in table.items()}
    for group in ("vehicle", "pedestrian"):
        g = a["group"] == group
        print(f"{group}: share of rows called dynamic (moving: caught; static: false alarms), by window length")
        print("   n       rows  " + "  ".join(f"{v:>15}" for v in VARIANTS) + "   |Δμ| med   σ med")
        for lo, hi in WINDOW_BINS:
            for dyn in (True, False):
                m = g & (a["dyn"] == dyn) & (a["n"] >= lo) & (a["n"] < hi)
                if not m.any():
                    continue
                fire = [f"{(a[v][m] > a['alpha'][m]).mean():15.3f}" for v in VARIANTS]
                label = f"{lo}" if hi == lo + 1 else f"{lo}-{hi - 1}"
                print(f"   {label:<5} {'moving' if dyn else 'static'} {m.sum():5d} " + "  ".join(fire)
                      + f"   {np.median(a['d'][m]):7.3f} {np.nanmedian(a['sd'][m]):7.3f}")
        dyn, st = g & a["dyn"], g & ~a["dyn"]
        print(f"{group}: missed-dynamic rate of each variant at equal false-dynamic rates (one threshold swept)")
        fds = (0.02, 0.03, 0.04, 0.056) if group == "vehicle" else (0.15, 0.2, 0.25, 0.3)
        for v in VARIANTS:
            cells = [f"{(a[v][dyn] <= np.quantile(a[v][st], 1 - f)).mean():.3f} @ {f:.3f}" for f in fds]
            print(f"   {v:>15}: " + "   ".join(cells))
        base = float(np.median(a["alpha"][g]))
        print(f"{group}: a lower α for windows shorter than n (α {base:g} otherwise): false / missed dynamic")
        for factor in (1.0, 0.8, 0.65, 0.5, 0.4):
            cells = []
            for cut in (4, 6, 10):
                alpha = np.where(a["n"] < cut, factor * a["alpha"], a["alpha"])
                fire = a["default"] > alpha
                cells.append(f"n<{cut}: {fire[st].mean():.3f} / {(~fire[dyn]).mean():.3f}")
            print(f"   α × {factor:.2f} ({factor * base:.2f})   " + "   ".join(cells))


if __name__ == "__main__":
    main()
