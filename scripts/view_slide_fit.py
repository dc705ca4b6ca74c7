"""Experiment (docs/classifier.md, "Can s be learnt from the tracks?"; tuning seeds only): is the view term's
slide s a variance the tracks would estimate without labels?

For every window the classifier decides with a full window, the kernel's ``contrast`` output: the displacement d of
the half means (before H0's speed shrinks it), its covariance C = λ V before the view term, and Δū. If the slide
were a Gaussian component, static windows would be d ~ N(0, C + s² Δū Δūᵀ). Printed per run:

* how well C describes the static windows (labels read for the diagnosis): dᵀC⁻¹d (χ²₂: mean 2, median 1.39, 1 %
  beyond 9.21), and per band of a = ΔūᵀC⁻¹Δū the whitened contrast along C⁻¹Δū, q²/a (χ²₁: mean 1 at s = 0,
  1 + s²a with the slide);
* s by maximum likelihood on the windows labelled static (the oracle), and label-free: a two-component mixture
  fitted by EM over every full window of the group — static N(0, C + s² Δū Δūᵀ), moving N(0, C + σ_m² I).

    .venv/bin/python scripts/view_slide_fit.py --scenario diagonal-lot --seeds 0-3 --input detector --cache DIR
    .venv/bin/python scripts/view_slide_fit.py --scenario mixed --seeds 0-3 --input gt-noise --group pedestrian
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ghost_breakdown import classify_seeds, input_arguments, seed_pairs  # noqa: E402
from jitterguard.eval.metrics import ghost_rows, scored_rows  # noqa: E402
from jitterguard.schemas.models import ClassifierConfig  # noqa: E402
from jitterguard.services.classifier import core as core_mod  # noqa: E402
from jitterguard.services.classifier.calibration import vehicle_class_names  # noqa: E402
from jitterguard.services.classifier.core import MotionClassifierCore  # noqa: E402

GRID = np.linspace(0.0, 6.0, 121)  # s [m] searched
STATIC, MOVING, GHOST = 0, 1, 2


def collect(pairs: dict, slide: float, group: str, effective_n: str | None = None) -> np.ndarray:
    """(N, 8): the kernel's 7 contrast rows of every full window of ``group`` the evaluator scores or counts as a
    ghost, and its kind (static, moving, ghost). The classifier runs as ``jitterguard eval`` runs it, with the
    vehicles' view term at ``slide``; ``effective_n`` (None: the classifier's) computes the contrast's covariance
    under another mode on the same windows, the decisions unchanged."""
    log: dict = {}
    run = {"i": 0}
    original, statistic = core_mod.calibrated_statistics, MotionClassifierCore._statistics
    last: dict = {}

    def hooked(windows, masks, groups, model, **kw):  # noqa: ANN001, ANN202, ANN003
        c = np.zeros((7, len(groups)))
        if effective_n is None:
            out = original(windows, masks, groups, model, contrast=c, **kw)
        else:
            out = original(windows, masks, groups, model, **kw)
            original(windows, masks, groups, model, contrast=c, **{**kw, "effective_n": effective_n})
        last["c"], last["n"] = c, masks.n_old + masks.n_new
        return out

    def stats(self, rows):  # noqa: ANN001, ANN202
        last.clear()
        out = statistic(self, rows)
        if last:
            ids = dict(zip(self._id_rows.tolist(), self._ids.tolist()))
            for j, row in enumerate(rows.tolist()):
                log[(run["i"], int(self._clock[1]), ids[row].decode())] = (last["c"][:, j].copy(), last["n"][j])
        return out

    core_mod.calibrated_statistics, MotionClassifierCore._statistics = hooked, stats
    clf = ClassifierConfig(view_slide_m_per_class=dict.fromkeys(vehicle_class_names(), slide) if slide else {})
    try:  # the windows' contrasts do not depend on the decisions (nor on the jump veto)
        recs = classify_seeds(pairs, clf, on_run=lambda i: run.update(i=i))
    finally:
        core_mod.calibrated_statistics, MotionClassifierCore._statistics = original, statistic
    rows = []
    for i, rec in enumerate(recs):
        scored, ghost = scored_rows(rec, group), ghost_rows(rec, group)
        for k in np.flatnonzero(scored | ghost).tolist():
            v = log.get((i, int(rec.seq[k]), str(rec.track_id[k])))
            if v is not None and v[1] >= rec.window_size:
                rows.append((*v[0], GHOST if ghost[k] else MOVING if rec.gt_dynamic[k] else STATIC))
    return np.array(rows).reshape(-1, 8)


def whitened(a: np.ndarray) -> tuple[np.ndarray, ...]:
    """dᵀC⁻¹d, a = ΔūᵀC⁻¹Δū, q = ΔūᵀC⁻¹d and log det C per window."""
    dx, dy, cxx, cxy, cyy, ux, uy = a[:, :7].T
    det = np.maximum(cxx * cyy - cxy * cxy, 1e-300)

    def quad(x0, x1, y0, y1):  # noqa: ANN001, ANN202
        return (cyy * x0 * y0 - cxy * (x0 * y1 + x1 * y0) + cxx * x1 * y1) / det

    return quad(dx, dy, dx, dy), quad(ux, uy, ux, uy), quad(ux, uy, dx, dy), np.log(det)


def fit(a: np.ndarray, mixture: bool, iters: int = 40) -> dict:
    """s by maximum likelihood (on a grid): over static windows alone, or in the two-component mixture by EM."""
    q0, aa, q, ld = whitened(a)
    dx, dy, cxx, cyy = a[:, 0], a[:, 1], a[:, 2], a[:, 4]
    one = 1.0 + GRID[:, None] ** 2 * aa  # det(C + s² Δū Δūᵀ) = det C (1 + s² a); Sherman–Morrison for the quadratic
    ll_grid = -np.log(2 * np.pi) - 0.5 * ld - 0.5 * np.log(one) - 0.5 * (q0 - GRID[:, None] ** 2 * q * q / one)
    s_idx, pi, sm2 = 0, 0.8, 4.0
    resp = np.ones(len(q0))
    for _ in range(iters if mixture else 1):
        if mixture:
            vx, vy = cxx + sm2, cyy + sm2
            l1 = -np.log(2 * np.pi) - 0.5 * np.log(vx * vy) - 0.5 * (dx * dx / vx + dy * dy / vy)
            top = np.maximum(ll_grid[s_idx], l1)
            w0, w1 = pi * np.exp(ll_grid[s_idx] - top), (1 - pi) * np.exp(l1 - top)
            resp = w0 / (w0 + w1)
            pi = float(np.clip(resp.mean(), 0.01, 0.99))
            sm2 = float(max(np.sum((1 - resp) * (dx * dx + dy * dy)) / max(2 * np.sum(1 - resp), 1e-9), 0.01))
        s_idx = int(np.argmax(ll_grid @ resp))
    out = {"s_m": round(float(GRID[s_idx]), 2), "n": len(q0)}
    if mixture:
        out.update(static_share=round(pi, 3), moving_sigma_m=round(float(np.sqrt(sm2)), 2))
    return out


def diagnose(a: np.ndarray) -> None:
    q0, aa, q, _ = whitened(a[a[:, 7] == STATIC])
    if not len(q0):
        print("no static windows")
        return
    print(f"static windows {len(q0)}: dᵀC⁻¹d mean {q0.mean():.2f}, median {np.median(q0):.2f}, "
          f"share > 9.21 {np.mean(q0 > 9.21):.4f}")
    along = q * q / np.maximum(aa, 1e-300)
    edges = np.quantile(aa, [0, 0.5, 0.8, 0.95, 1])
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (aa >= lo) & (aa <= hi)
        print(f"  a in [{lo:.3g}, {hi:.3g}]: {m.sum()} windows, q²/a mean {along[m].mean():.2f}, "
              f"share > 6.63 {np.mean(along[m] > 6.63):.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_arguments(ap)
    ap.add_argument("--slide", type=float, default=0.0, help="the vehicles' view term while the windows are collected")
    ap.add_argument("--group", default="vehicle", choices=("vehicle", "pedestrian"))
    ap.add_argument("--effective-n", default=None, choices=("measured", "independent", "cluster"),
                    help="the covariance C under this mode (the decisions keep the classifier's)")
    args = ap.parse_args()
    pairs = seed_pairs(args)
    a = collect(pairs, args.slide, args.group, args.effective_n)
    print("full windows", {k: int((a[:, 7] == v).sum()) for k, v in (("static", STATIC), ("moving", MOVING),
                                                                      ("ghost", GHOST))})
    diagnose(a)
    if (a[:, 7] == STATIC).any():
        print("s, oracle (labelled static windows):", fit(a[a[:, 7] == STATIC], mixture=False))
    print("s, label-free (mixture over every full window):", fit(a, mixture=True))


if __name__ == "__main__":
    main()
