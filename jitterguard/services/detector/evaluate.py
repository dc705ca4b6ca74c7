"""Detector evaluation: nuScenes detection AP and the calibration of the predicted positional variances.

Pure numpy over the detector's two array bundles (:class:`~.config.Detections3D` predictions and
:class:`~.config.Sample` ground truth, both in the sensor frame); ``predictions[i]`` belongs to
``ground_truth[i]``. No I/O: figures are in :mod:`.plots`.

**Detection AP** is nuScenes' ``DetectionEval`` (devkit 1.2, ``eval/detection/algo.py``: ``accumulate`` and
``calc_ap``), re-implemented so that training can score every epoch without a nuScenes dataroot:

* ground truth is kept if its BEV distance from the sensor is ``< class_range[class]`` and it holds
  ``≥ min_points`` LiDAR returns; predictions only pass the range filter. Two departures from the devkit, both
  kept on purpose (a LiDAR-only detector scored in its own frame) and both visible only on real nuScenes data:
  the devkit drops a box only with 0 LiDAR *and* 0 radar points, and it measures range from the ego-pose origin
  (the rear axle), which on nuScenes lies about 1 m behind LIDAR_TOP (scene-0523: 0.99 m), not under it as in
  this project's synthetic exports. On scene-0523 with the shipped weights (docs/detector.md, "Evaluation") the
  devkit's two rules give car AP 0.193 and pedestrian AP 0.172 against these 0.218 and 0.177 (the range origin
  alone: 0.220, 0.175).
* per class, all predictions of all samples are taken in descending score (ties: the later one in
  sample-then-box order first, exactly as the devkit's ``sorted(...)[::-1]``); each takes the nearest
  *untaken* ground-truth box of its class in its sample, and is a true positive iff that BEV centre
  distance is ``< threshold``.
* precision is linearly interpolated (``np.interp``, no monotone envelope) at 101 recall points, zero beyond
  the highest recall reached; ``AP = mean(max(p[i] − 0.1, 0) for i = 11…100) / 0.9`` (min recall 0.1, min
  precision 0.1). A class's AP is the mean over the thresholds 0.5, 1, 2, 4 m; mAP the mean over classes.

One deliberate difference: a class without ground truth gets AP NaN (undefined) and is left out of mAP; the
devkit scores it 0 and averages it in. :func:`devkit_mean_ap` gives the devkit's number when it is wanted.

**Positional calibration** (paper §IV-A, Fig. 3, Table I "ECE"): true positives are matched as above at
``match_distance``; per axis a ∈ {x, y} (sensor frame) the residual is r = x̂ − x_gt and the predicted SD is
σ = sqrt(exp(log σ²)). The matches are binned by predicted σ (equal-count bins by default) and per bin b

    σ_pred,b = sqrt(mean_b σ²)        σ_obs,b = sqrt(mean_b r²)        (variances averaged, then SD)
    ECE_a    = Σ_b (n_b / N) · |σ_obs,b − σ_pred,b|        [metres]
    ECE      = (ECE_x + ECE_y) / 2

σ_obs is the root-mean-square residual, not the sample SD around the bin mean: a biased box is an error the
variance has to cover. Variances are averaged before the square root (the paper bins variances and converts
to SD) so that a calibrated detector, r ~ N(0, σ²), scores ECE → 0 however wide the bins are. Also reported:
the Gaussian NLL ½ log(2πσ²) + r²/(2σ²), the fraction of |r| ≤ σ and ≤ 2σ (0.683 and 0.954 when calibrated)
and the variance ratio mean(r²/σ²) (1 when calibrated).

**Recalibration** (the paper leaves calibration open): one variance scale s²_a per axis minimising the Gaussian
NLL of the matched residuals on a validation split, in closed form s²_a = mean(r_a² / σ_a²);
:func:`apply_recalibration` adds log s²_a to the log-variances. It fixes a global over- or under-estimate,
not a wrongly shaped one (the paper's x over / y under is per-axis, so it is in reach).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ...geometry import nearest_within
from .config import CLASS_NAMES, CLASS_RANGE_M, Detections3D, Sample

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

DIST_THRESHOLDS_M: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)
"""nuScenes' BEV centre-distance thresholds (detection_cvpr_2019)."""
COUNT_THRESHOLD_M = 2.0
"""Threshold of the TP/FP/FN counts (nuScenes' ``dist_th_tp``)."""
MIN_RECALL = 0.1
MIN_PRECISION = 0.1
RECALL_POINTS = 101
AXES = ("x", "y")


def threshold_key(t: float) -> str:
    """Dictionary key of a distance threshold in the result dicts: ``0.5 → "0.5"``, ``2.0 → "2"``."""
    return f"{t:g}"


# ---------------------------------------------------------------------------------------------------------
# flattening and filtering
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Flat:
    """Boxes of all samples in one table, in sample-then-box order (the devkit's ``EvalBoxes.all`` order)."""

    sample: I64
    row: I64  # index of the box within its sample
    xy: F64
    label: I64
    score: F64
    logvar_xy: F64 | None  # (N, 2) log σ² of x and y, predictions with variances only
    returns: I64 | None = None  # LiDAR returns inside each box, ground truth only

    def subset(self, m: NDArray[np.bool_] | I64) -> "_Flat":
        return _Flat(self.sample[m], self.row[m], self.xy[m], self.label[m], self.score[m],
                     None if self.logvar_xy is None else self.logvar_xy[m],
                     None if self.returns is None else self.returns[m])


def _index(counts: list[int]) -> tuple[I64, I64]:
    """(sample, row) of every box when sample i holds counts[i] boxes."""
    sample = np.repeat(np.arange(len(counts), dtype=np.int64), counts)
    starts = np.cumsum([0] + counts[:-1]) if counts else np.zeros(0, np.int64)
    return sample, np.arange(len(sample), dtype=np.int64) - np.repeat(np.asarray(starts, np.int64), counts)


def _in_range(xy: F64, label: I64, class_range: Sequence[float]) -> NDArray[np.bool_]:
    rng = np.asarray(class_range, dtype=np.float64)
    if len(label) and (label.min() < 0 or label.max() >= len(rng)):
        raise ValueError(f"class index out of range [0, {len(rng)}): {int(label.min())}…{int(label.max())}")
    return np.hypot(xy[:, 0], xy[:, 1]) < rng[label] if len(label) else np.zeros(0, bool)


def _flatten_gt(ground_truth: Sequence[Sample], class_range: Sequence[float], min_points: int) -> _Flat:
    sample, row = _index([len(s.labels) for s in ground_truth])
    xy = np.concatenate([np.asarray(s.boxes, np.float64).reshape(-1, 9)[:, :2] for s in ground_truth]) \
        if ground_truth else np.zeros((0, 2))
    label = np.concatenate([np.asarray(s.labels, np.int64) for s in ground_truth]) if ground_truth \
        else np.zeros(0, np.int64)
    pts = np.concatenate([np.asarray(s.num_points, np.int64) for s in ground_truth]) if ground_truth \
        else np.zeros(0, np.int64)
    flat = _Flat(sample, row, xy, label, np.full(len(label), -1.0), None, pts)
    return flat.subset(_in_range(xy, label, class_range) & (pts >= min_points))


def _flatten_pred(predictions: Sequence[Detections3D], class_range: Sequence[float], *,
                  need_variance: bool = False) -> _Flat:
    sample, row = _index([len(d) for d in predictions])
    if predictions:
        xy = np.concatenate([np.asarray(d.boxes, np.float64).reshape(-1, 9)[:, :2] for d in predictions])
        label = np.concatenate([np.asarray(d.labels, np.int64) for d in predictions])
        score = np.concatenate([np.asarray(d.scores, np.float64) for d in predictions])
    else:
        xy, label, score = np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0)
    logvar = None
    if need_variance:
        if any(d.log_variances is None for d in predictions):
            raise ValueError("calibration needs predicted variances: these detections come from a vanilla model")
        logvar = np.concatenate([np.asarray(d.log_variances, np.float64).reshape(-1, 5)[:, :2]
                                 for d in predictions]) if predictions else np.zeros((0, 2))
    flat = _Flat(sample, row, xy, label, score, logvar)
    return flat.subset(_in_range(xy, label, class_range))


def _check_pairs(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample]) -> None:
    if len(predictions) != len(ground_truth):
        raise ValueError(f"{len(predictions)} prediction sets for {len(ground_truth)} samples")


# ---------------------------------------------------------------------------------------------------------
# matching and AP
# ---------------------------------------------------------------------------------------------------------


def score_order(scores: NDArray[np.floating]) -> I64:
    """Indices in descending score; among equal scores the later index first (the devkit sorts
    ``(score, index)`` pairs ascending and reverses the list)."""
    s = np.asarray(scores, dtype=np.float64)
    return np.lexsort((np.arange(len(s)), s))[::-1].astype(np.int64)


def greedy_match(pred_sample: I64, pred_xy: F64, gt_sample: I64, gt_xy: F64,
                 thresholds: Sequence[float]) -> I64:
    """nuScenes' greedy centre-distance matching of one class, for several thresholds in one pass.

    Predictions must come in priority order (see :func:`score_order`). Each takes the nearest ground-truth box
    of its sample that is still untaken *at that threshold* (first one on an exact tie) and matches it iff the
    BEV distance is ``< threshold``. Returns ``(T, K)`` ground-truth row per prediction, −1 where unmatched.

    Samples are independent, so the work is split per sample; within a sample only predictions with some
    ground truth closer than the largest threshold enter the sequential loop (the rest are false positives at
    every threshold and take nothing).
    """
    ths = np.asarray(thresholds, dtype=np.float64)
    T, K = len(ths), len(pred_sample)
    out = np.full((T, K), -1, dtype=np.int64)
    if K == 0 or len(gt_sample) == 0:
        return out
    gt_order = np.argsort(gt_sample, kind="stable")
    samples = np.unique(pred_sample)
    starts = np.searchsorted(gt_sample[gt_order], samples, side="left")
    ends = np.searchsorted(gt_sample[gt_order], samples, side="right")
    pred_order = np.argsort(pred_sample, kind="stable")  # keeps the priority order within each sample
    p_starts = np.searchsorted(pred_sample[pred_order], samples, side="left")
    p_ends = np.searchsorted(pred_sample[pred_order], samples, side="right")
    t_idx = np.arange(T)
    max_th = ths.max() if T else 0.0
    for s0, s1, q0, q1 in zip(starts, ends, p_starts, p_ends):
        if s0 == s1:
            continue
        g_rows = gt_order[s0:s1]
        p_rows = pred_order[q0:q1]
        d = np.hypot(pred_xy[p_rows, None, 0] - gt_xy[None, g_rows, 0], pred_xy[p_rows, None, 1] - gt_xy[None, g_rows, 1])
        taken = np.zeros((T, len(g_rows)), dtype=bool)
        for i in np.flatnonzero(d.min(axis=1) < max_th):
            masked = np.where(taken, np.inf, d[i][None, :])
            j = masked.argmin(axis=1)
            ok = masked[t_idx, j] < ths
            taken[t_idx[ok], j[ok]] = True
            out[t_idx[ok], p_rows[i]] = g_rows[j[ok]]
    return out


def interpolated_precision(is_tp: NDArray[np.bool_], num_gt: int) -> F64:
    """Precision at the 101 recall points 0, 0.01, …, 1 from the TP flags of predictions in score order;
    all zeros when nothing matched (the devkit's ``no_predictions``)."""
    tp_flags = np.asarray(is_tp, dtype=bool)
    if num_gt == 0 or not tp_flags.any():
        return np.zeros(RECALL_POINTS)
    tp = np.cumsum(tp_flags).astype(np.float64)
    fp = np.cumsum(~tp_flags).astype(np.float64)
    prec = tp / (tp + fp)
    rec = tp / float(num_gt)
    return np.interp(np.linspace(0.0, 1.0, RECALL_POINTS), rec, prec, right=0.0)


def ap_from_precision(precision: F64, min_recall: float = MIN_RECALL, min_precision: float = MIN_PRECISION) -> float:
    """nuScenes' ``calc_ap``: mean precision above ``min_precision`` over the recall points above
    ``min_recall``, normalised to [0, 1]."""
    if not (0.0 <= min_precision < 1.0 and 0.0 <= min_recall <= 1.0):
        raise ValueError("need 0 <= min_precision < 1 and 0 <= min_recall <= 1")
    p = np.asarray(precision, dtype=np.float64)[round(100 * min_recall) + 1:] - min_precision
    return float(np.mean(np.maximum(p, 0.0))) / (1.0 - min_precision)


def detection_ap(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample], *,
                 thresholds: Sequence[float] = DIST_THRESHOLDS_M,
                 class_range: Sequence[float] = CLASS_RANGE_M, min_points: int = 1,
                 class_names: Sequence[str] = CLASS_NAMES, count_threshold: float = COUNT_THRESHOLD_M,
                 min_recall: float = MIN_RECALL, min_precision: float = MIN_PRECISION,
                 explain: bool = True) -> dict[str, Any]:
    """nuScenes detection AP per class and threshold, per-class mean over thresholds, and mAP (module doc).

    Returns ``{"thresholds_m", "count_threshold_m", "recall" (the 101 points), "mAP", "classes": {name:
    {"num_gt", "num_pred", "ap": {threshold_key: AP}, "mean_ap", "tp", "fp", "fn", "recall_by_returns",
    "false_positives_on", "precision": {threshold_key: 101 floats}}}}``. TP/FP/FN count every prediction that passes
    the range filter, at ``count_threshold``; ``false_positives_on`` explains those scoring ≥ :data:`RECALL_SCORE`
    (None when not ``explain``: the bootstrap's resamples need only the APs). NaN marks an AP that is undefined because the class has no ground truth.
    """
    _check_pairs(predictions, ground_truth)
    ths = [float(t) for t in thresholds]
    if not ths or min(ths) <= 0:
        raise ValueError("thresholds must be positive and non-empty")
    match_ths = ths + ([float(count_threshold)] if float(count_threshold) not in ths else [])
    ci = match_ths.index(float(count_threshold))
    if len(class_range) != len(class_names):
        raise ValueError("class_range and class_names differ in length")
    gt = _flatten_gt(ground_truth, class_range, min_points)
    pr = _flatten_pred(predictions, class_range)
    classes: dict[str, Any] = {}
    for c, name in enumerate(class_names):
        g = gt.subset(gt.label == c)
        p = pr.subset(pr.label == c)
        p = p.subset(score_order(p.score))
        match = greedy_match(p.sample, p.xy, g.sample, g.xy, match_ths) >= 0
        npos = len(g.label)
        precision = {threshold_key(t): interpolated_precision(match[k], npos) for k, t in enumerate(ths)}
        ap = {k: (ap_from_precision(v, min_recall, min_precision) if npos else math.nan)
              for k, v in precision.items()}
        n_tp = int(match[ci].sum())
        rows = greedy_match(p.sample, p.xy, g.sample, g.xy, [float(count_threshold)])[0]
        classes[name] = {
            "num_gt": npos, "num_pred": len(p.label),
            "ap": ap, "mean_ap": float(np.mean(list(ap.values()))) if npos else math.nan,
            "tp": n_tp, "fp": len(p.label) - n_tp, "fn": npos - n_tp,
            "recall_by_returns": recall_by_returns(rows[p.score >= RECALL_SCORE], g.returns),
            "false_positives_on": false_positives_on(p.sample[(rows < 0) & (p.score >= RECALL_SCORE)],
                                                     p.xy[(rows < 0) & (p.score >= RECALL_SCORE)], c,
                                                     ground_truth, class_names) if explain else None,
            "precision": {k: v.tolist() for k, v in precision.items()},
        }
    means = [v["mean_ap"] for v in classes.values() if v["num_gt"]]
    return {
        "thresholds_m": ths, "count_threshold_m": float(count_threshold),
        "recall": np.linspace(0.0, 1.0, RECALL_POINTS).tolist(),
        "mAP": float(np.mean(means)) if means else math.nan,
        "classes": classes,
    }


RETURN_BINS: tuple[int, ...] = (1, 5, 20, 50, 200)
"""Lower edges of the bins of LiDAR returns per ground-truth box for :func:`recall_by_returns` (the last bin
open): a real scan's cars are mostly sparse (on nuScenes scene-0523 59 % of the visible cars within 50 m carry
fewer than 20 returns), so where recall is lost says more than one recall figure."""
RECALL_SCORE = 0.3
"""Detection score from which :func:`recall_by_returns` counts a box found (a working point, not the AP's sweep)."""


def recall_by_returns(matched_rows: I64, returns: I64 | None, edges: Sequence[int] = RETURN_BINS) -> list[dict[str, Any]]:
    """Per bin of returns per ground-truth box: how many boxes, and the share found — matched by a prediction
    scoring ≥ :data:`RECALL_SCORE` within the count threshold, in the AP's own greedy order (so a box is found
    iff it is a true positive of the predictions above that score). ``matched_rows``: the ground-truth rows
    those predictions took (−1: none); recall is None for an empty bin."""
    if returns is None:
        return []
    found = np.zeros(len(returns), dtype=bool)
    found[matched_rows[matched_rows >= 0]] = True
    out: list[dict[str, Any]] = []
    for k, lo in enumerate(edges):
        hi = edges[k + 1] if k + 1 < len(edges) else None
        m = (returns >= lo) & ((returns < hi) if hi is not None else True)
        n = int(m.sum())
        out.append({"returns": f"{lo}-{hi - 1}" if hi is not None else f"{lo}+", "num_gt": n,
                    "recall": float(found[m].mean()) if n else None})
    return out


def false_positives_on(sample: I64, xy: F64, label: int, ground_truth: Sequence[Sample],
                       class_names: Sequence[str] = CLASS_NAMES) -> dict[str, int]:
    """What the false positives of class ``label`` (their scans ``sample`` and BEV centres ``xy``) stand on: the
    nearest labelled object within :data:`~jitterguard.geometry.STANDS_ON_M` — ``"duplicate"`` (an object of the
    same class, taken by a better box or not scored: out of range, no returns), another class's name (a confusion),
    an unscored category (:attr:`~.config.Sample.unscored`: nuScenes' barriers, cones, debris) — or ``"nothing
    labelled"`` (clutter, vegetation, walls; or an object too far out of range to be scored). Counts, the commonest
    first.

    Why: AP says how many boxes are wrong, not why; on nuScenes scene-0523 a fifth of the 100 highest-scored false
    pedestrians stood on four piles of debris (docs/detector.md, "Things the size of a person")."""
    counts: dict[str, int] = {}
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    for s in np.unique(sample).tolist():
        gt = ground_truth[s]
        names = [("duplicate" if int(k) == label else class_names[int(k)]) for k in gt.labels]
        names += [u[0] for u in gt.unscored]
        objects = np.concatenate([np.asarray(gt.boxes[:, :2], np.float64).reshape(-1, 2),
                                  np.array([u[1:] for u in gt.unscored], np.float64).reshape(-1, 2)])
        for j in nearest_within(xy[sample == s], objects).tolist():
            what = names[j] if j >= 0 else "nothing labelled"
            counts[what] = counts.get(what, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def devkit_mean_ap(ap_result: dict[str, Any]) -> float:
    """mAP as the devkit reports it over these classes: a class without ground truth counts as AP 0."""
    vals = [0.0 if v["num_gt"] == 0 else v["mean_ap"] for v in ap_result["classes"].values()]
    return float(np.mean(vals)) if vals else math.nan


# ---------------------------------------------------------------------------------------------------------
# positional calibration
# ---------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MatchedResiduals:
    """True positives' residuals ``r`` (N, 2) = predicted − ground-truth x, y (sensor frame), predicted
    log-variances (N, 2) of x, y, class indices (N,), and the predictions' indices: (sample, row)."""

    residual: F64
    log_variance: F64
    label: I64
    sample: I64
    row: I64

    def __len__(self) -> int:
        return len(self.label)

    @property
    def sigma(self) -> F64:
        return np.sqrt(np.exp(self.log_variance))


def matched_residuals(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample], *,
                      match_distance: float = COUNT_THRESHOLD_M, class_range: Sequence[float] = CLASS_RANGE_M,
                      min_points: int = 1) -> MatchedResiduals:
    """The true positives of the AP matching at ``match_distance`` (same filters, same greedy order), with
    their residuals and predicted variances."""
    _check_pairs(predictions, ground_truth)
    gt = _flatten_gt(ground_truth, class_range, min_points)
    pr = _flatten_pred(predictions, class_range, need_variance=True)
    res, lv, lab, smp, rw = [], [], [], [], []
    for c in range(len(class_range)):
        gsel = np.flatnonzero(gt.label == c)
        psel = np.flatnonzero(pr.label == c)
        psel = psel[score_order(pr.score[psel])]
        m = greedy_match(pr.sample[psel], pr.xy[psel], gt.sample[gsel], gt.xy[gsel], [match_distance])[0]
        ok = m >= 0
        pi, gi = psel[ok], gsel[m[ok]]
        res.append(pr.xy[pi] - gt.xy[gi])
        assert pr.logvar_xy is not None
        lv.append(pr.logvar_xy[pi])
        lab.append(np.full(len(pi), c, np.int64))
        smp.append(pr.sample[pi])
        rw.append(pr.row[pi])
    if not res:
        z2, z = np.zeros((0, 2)), np.zeros(0, np.int64)
        return MatchedResiduals(z2, z2, z, z, z)
    return MatchedResiduals(np.concatenate(res), np.concatenate(lv), np.concatenate(lab), np.concatenate(smp),
                            np.concatenate(rw))


def calibration_bins(sigma: F64, residual: F64, num_bins: int = 10,
                     binning: Literal["quantile", "uniform"] = "quantile") -> dict[str, list[float]]:
    """Bins of one axis over predicted σ: count, σ range, σ_pred = sqrt(mean σ²), σ_obs = sqrt(mean r²).

    ``quantile``: equal-count bins (sorted by σ, split into ``num_bins`` nearly equal runs), so every bin's
    σ_obs rests on the same number of residuals. ``uniform``: equal-width bins over [min σ, max σ], as in
    most calibration plots (empty bins are dropped)."""
    s = np.asarray(sigma, dtype=np.float64)
    r = np.asarray(residual, dtype=np.float64)
    if num_bins < 1:
        raise ValueError("num_bins must be at least 1")
    if binning == "quantile":
        order = np.argsort(s, kind="stable")
        groups = [g for g in np.array_split(order, min(num_bins, len(s))) if len(g)] if len(s) else []
    elif binning == "uniform":
        if len(s):
            edges = np.linspace(s.min(), s.max(), num_bins + 1)
            idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, num_bins - 1)
            groups = [np.flatnonzero(idx == b) for b in range(num_bins)]
            groups = [g for g in groups if len(g)]
        else:
            groups = []
    else:
        raise ValueError(f"unknown binning {binning!r}")
    return {
        "count": [int(len(g)) for g in groups],
        "sigma_lo": [float(s[g].min()) for g in groups],
        "sigma_hi": [float(s[g].max()) for g in groups],
        "pred_sd": [float(np.sqrt(np.mean(s[g] ** 2))) for g in groups],
        "obs_sd": [float(np.sqrt(np.mean(r[g] ** 2))) for g in groups],
    }


def ece_from_bins(bins: dict[str, list[float]]) -> float:
    """Σ_b (n_b / N) |σ_obs,b − σ_pred,b| in metres; NaN without data."""
    n = np.asarray(bins["count"], dtype=np.float64)
    if n.sum() == 0:
        return math.nan
    return float(np.sum(n / n.sum() * np.abs(np.asarray(bins["obs_sd"]) - np.asarray(bins["pred_sd"]))))


def calibration_from_residuals(residual: F64, log_variance: F64, *, num_bins: int = 10,
                               binning: Literal["quantile", "uniform"] = "quantile") -> dict[str, Any]:
    """Calibration statistics of residuals ``(N, 2)`` against predicted log-variances ``(N, 2)`` (x, y).

    Returns ``{"num_matched", "ece", "nll", "coverage_1sigma", "coverage_2sigma", "axes": {"x" | "y":
    {"ece", "nll", "coverage_1sigma", "coverage_2sigma", "variance_ratio", "rms_residual", "rms_sigma",
    "bins": calibration_bins(...)}}}``; top-level values are means over the two axes. Formula: module doc."""
    r = np.asarray(residual, dtype=np.float64).reshape(-1, 2)
    lv = np.asarray(log_variance, dtype=np.float64).reshape(-1, 2)
    if r.shape != lv.shape:
        raise ValueError("residual and log_variance must both be (N, 2)")
    var = np.exp(lv)
    sig = np.sqrt(var)
    n = len(r)
    axes: dict[str, Any] = {}
    for a, name in enumerate(AXES):
        bins = calibration_bins(sig[:, a], r[:, a], num_bins, binning)
        z2 = r[:, a] ** 2 / var[:, a]
        axes[name] = {
            "ece": ece_from_bins(bins),
            "nll": float(np.mean(0.5 * (math.log(2 * math.pi) + lv[:, a] + z2))) if n else math.nan,
            "coverage_1sigma": float(np.mean(z2 <= 1.0)) if n else math.nan,
            "coverage_2sigma": float(np.mean(z2 <= 4.0)) if n else math.nan,
            "variance_ratio": float(np.mean(z2)) if n else math.nan,
            "rms_residual": float(np.sqrt(np.mean(r[:, a] ** 2))) if n else math.nan,
            "rms_sigma": float(np.sqrt(np.mean(var[:, a]))) if n else math.nan,
            "bins": bins,
        }
    out: dict[str, Any] = {"num_matched": int(n), "binning": binning}
    for key in ("ece", "nll", "coverage_1sigma", "coverage_2sigma"):
        out[key] = float(np.mean([axes[a][key] for a in AXES])) if n else math.nan
    out["axes"] = axes
    return out


def calibration(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample], *,
                match_distance: float = COUNT_THRESHOLD_M, num_bins: int = 10,
                binning: Literal["quantile", "uniform"] = "quantile",
                class_range: Sequence[float] = CLASS_RANGE_M, min_points: int = 1) -> dict[str, Any]:
    """Positional calibration of the detector's x/y variances over its true positives (module doc for the
    ECE formula); see :func:`calibration_from_residuals` for the keys, plus ``by_score``
    (:func:`calibration_by_score`). Raises ValueError for detections without variances."""
    m = matched_residuals(predictions, ground_truth, match_distance=match_distance, class_range=class_range,
                          min_points=min_points)
    out = calibration_from_residuals(m.residual, m.log_variance, num_bins=num_bins, binning=binning)
    out["match_distance_m"] = float(match_distance)
    out["by_score"] = calibration_by_score(matched_scores(predictions, m), m)
    return out


def matched_scores(predictions: Sequence[Detections3D], m: MatchedResiduals) -> F64:
    """The detection scores of the true positives ``m`` (in its order)."""
    flat = [np.asarray(d.scores, np.float64) for d in predictions]
    offset = np.cumsum([0] + [len(f) for f in flat])
    return np.concatenate(flat)[offset[m.sample] + m.row] if len(m) else np.zeros(0)


def calibration_by_score(score: F64, m: MatchedResiduals, num_bins: int = 5) -> list[dict[str, float]]:
    """Per equal-count bin of the true positives' scores: the score range, matches, variance ratio
    mean(r²/σ²) per axis (1 when calibrated) and the ±1σ coverage of both axes (0.683). A detector whose
    variances are off by a score-dependent factor shows it here, where the σ-binned ECE averages it away."""
    if len(m) < num_bins:
        return []
    z2 = m.residual ** 2 / np.exp(m.log_variance)
    order = np.argsort(score, kind="stable")
    out = []
    for part in np.array_split(order, num_bins):
        out.append({"score_min": float(score[part].min()), "score_max": float(score[part].max()),
                    "n": int(len(part)), "variance_ratio_x": float(z2[part, 0].mean()),
                    "variance_ratio_y": float(z2[part, 1].mean()), "coverage_1sigma": float(np.mean(z2[part] <= 1.0))})
    return out


RECALIBRATION_MIN_PER_BIN = 200
"""Fewest true positives per score bin of a fitted recalibration: the mean of r²/σ² over n matches has a
relative standard error of about sqrt(2/n) (10 % at 200); with fewer matches the fit uses fewer bins."""


@dataclass(frozen=True)
class Recalibration:
    """Per-axis variance scales s²_a per detection-score bin: a box scored s gets σ²_a · s²_a[b(s)], with
    b(s) the number of ``score_edges`` ≤ s. One bin (no edges) is the classic global per-axis scale.

    Why by score: a detector's variance error is not one factor. On synthetic scans with sim-to-real effects the
    shipped weights' variances are about right for their most confident boxes and 2× too small (in variance)
    for the least confident ones — the same shape they show on real scans (docs/detector.md, "Shipped
    weights") — so one global scale leaves the weak boxes over-confident and the strong ones under-confident."""

    scales: tuple[tuple[float, float], ...]
    score_edges: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        s = np.asarray(self.scales, dtype=np.float64)
        e = np.asarray(self.score_edges, dtype=np.float64)
        if s.ndim != 2 or s.shape[1] != 2 or len(s) < 1 or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError(f"scales must be rows of two positive finite numbers, got {self.scales!r}")
        if len(e) != len(s) - 1 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
            raise ValueError(f"score_edges must be {len(s) - 1} increasing finite numbers, got {self.score_edges!r}")

    @classmethod
    def of(cls, value: "Recalibration | Sequence[float] | dict[str, Any] | None") -> "Recalibration | None":
        """From a weights file's or an ONNX manifest's entry: None, ``[s2_x, s2_y]`` (one bin, the format
        before score bins) or ``{"scales": [[s2_x, s2_y], …], "score_edges": […]}``."""
        if value is None or isinstance(value, Recalibration):
            return value
        if isinstance(value, dict):
            return cls(tuple((float(a), float(b)) for a, b in value["scales"]),
                       tuple(float(e) for e in value.get("score_edges") or ()))
        a, b = value
        return cls(((float(a), float(b)),))

    def to_payload(self) -> list[float] | dict[str, Any]:
        """The entry :meth:`of` reads back; one bin stays the plain ``[s2_x, s2_y]`` older readers know."""
        if len(self.scales) == 1:
            return [float(self.scales[0][0]), float(self.scales[0][1])]
        return {"scales": [[float(a), float(b)] for a, b in self.scales], "score_edges": list(self.score_edges)}

    def factors(self, scores: NDArray[np.floating]) -> F64:
        """(N, 2) variance scales for detections with these scores."""
        s = np.asarray(self.scales, dtype=np.float64)
        return s[np.searchsorted(np.asarray(self.score_edges), np.asarray(scores, dtype=np.float64), side="right")]


def fit_recalibration(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample], *, bins: int = 1,
                      match_distance: float = COUNT_THRESHOLD_M, class_range: Sequence[float] = CLASS_RANGE_M,
                      min_points: int = 1) -> Recalibration:
    """Per-axis variance scales minimising the Gaussian NLL of the matched residuals when every σ² is multiplied
    by s²: d/ds² Σ [½ log(s²σ²) + r²/(2 s²σ²)] = 0 ⇒ s² = mean(r² / σ²), per score bin. ``bins`` equal-count
    bins of the true positives' scores (fewer when a bin would hold under :data:`RECALIBRATION_MIN_PER_BIN`
    matches). Fit on a validation split, never on the data it is judged on. Raises ValueError when nothing
    matches."""
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    m = matched_residuals(predictions, ground_truth, match_distance=match_distance, class_range=class_range,
                          min_points=min_points)
    if len(m) == 0:
        raise ValueError("no true positives to fit a recalibration on")
    score = matched_scores(predictions, m)
    k = int(max(1, min(bins, len(m) // RECALIBRATION_MIN_PER_BIN)))
    edges = np.unique(np.quantile(score, np.linspace(0.0, 1.0, k + 1)[1:-1])) if k > 1 else np.zeros(0)
    b = np.searchsorted(edges, score, side="right")
    ratio = m.residual ** 2 / np.exp(m.log_variance)
    # a residual of exactly zero everywhere would give s² = 0 (log −inf): keep the scale usable
    s2 = [np.maximum(ratio[b == i].mean(axis=0), np.finfo(np.float64).tiny) for i in range(len(edges) + 1)]
    return Recalibration(tuple((float(a), float(c)) for a, c in s2), tuple(float(e) for e in edges))


def apply_recalibration(dets: Detections3D, recalibration: Recalibration | tuple[float, float]) -> Detections3D:
    """``dets`` with σ²_x, σ²_y multiplied by the scales of their score bins (log s² added to the
    log-variances; velocity and yaw variances untouched); a pair (s2_x, s2_y) is one global bin. The result is
    not clamped to the model's log-variance floor: the floor is a training device, the scaled value is the
    calibrated estimate."""
    if dets.log_variances is None:
        raise ValueError("these detections have no variances to recalibrate")
    rec = Recalibration.of(recalibration)
    assert rec is not None
    lv = np.array(dets.log_variances, dtype=np.float32, copy=True)
    lv[:, :2] += np.log(rec.factors(dets.scores)).astype(np.float32)
    return replace(dets, log_variances=lv)


# ---------------------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------------------


def _finite(obj: Any) -> Any:
    """JSON-ready copy: numpy scalars to Python, NaN/inf to None (strict JSON has no NaN)."""
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def evaluation_report(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample], *,
                      thresholds: Sequence[float] = DIST_THRESHOLDS_M, class_range: Sequence[float] = CLASS_RANGE_M,
                      min_points: int = 1, match_distance: float = COUNT_THRESHOLD_M, num_bins: int = 10,
                      include_curves: bool = False) -> dict[str, Any]:
    """AP and (for models with variances) positional calibration in one JSON-serialisable dict.

    ``{"num_samples", "summary": {"mAP", "<class>_ap", ..., "positional_ece", "nll"}, "detection":
    detection_ap(...) , "calibration": calibration(...) or None}``. PR curves are dropped unless
    ``include_curves`` (they are 5 × 4 × 101 numbers, too many for a per-epoch log). NaN becomes null.
    """
    ap = detection_ap(predictions, ground_truth, thresholds=thresholds, class_range=class_range,
                      min_points=min_points)
    if not include_curves:
        ap = {k: v for k, v in ap.items() if k != "recall"}
        ap["classes"] = {c: {k: v for k, v in d.items() if k != "precision"} for c, d in ap["classes"].items()}
    has_var = bool(predictions) and all(d.log_variances is not None for d in predictions)
    cal = calibration(predictions, ground_truth, match_distance=match_distance, num_bins=num_bins,
                      class_range=class_range, min_points=min_points) if has_var else None
    summary: dict[str, Any] = {"mAP": ap["mAP"]}
    summary.update({f"{c}_ap": d["mean_ap"] for c, d in ap["classes"].items()})
    summary["positional_ece"] = cal["ece"] if cal else None
    summary["nll"] = cal["nll"] if cal else None
    summary["coverage_1sigma"] = cal["coverage_1sigma"] if cal else None
    summary["num_matched"] = cal["num_matched"] if cal else None
    return _finite({"num_samples": len(ground_truth), "summary": summary, "detection": ap, "calibration": cal})


def bootstrap_intervals(predictions: Sequence[Detections3D], ground_truth: Sequence[Sample], *, resamples: int = 1000,
                        level: float = 0.9, seed: int = 0, class_range: Sequence[float] = CLASS_RANGE_M,
                        min_points: int = 1, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Percentile intervals of each class's mean AP and of the ±1σ coverage over ``resamples`` bootstrap
    resamples of the *frames* (frames, not boxes, are the independent units: boxes of one frame share its
    scan). ``{"level", "resamples", "<class>_ap": [lo, hi] | None, "coverage_1sigma": [lo, hi] | None}``;
    None where the statistic is undefined in too many resamples (a class with no ground truth). ``progress`` is
    called with 1 after each resample (the resamples can take minutes: a caller's progress bar)."""
    _check_pairs(predictions, ground_truth)
    n = len(ground_truth)
    out: dict[str, Any] = {"level": level, "resamples": resamples}
    if n == 0 or resamples <= 0:
        return out
    rng = np.random.default_rng(seed)
    has_var = all(d.log_variances is not None for d in predictions)
    aps: dict[str, list[float]] = {c: [] for c in CLASS_NAMES}
    cov: list[float] = []
    for _ in range(resamples):
        idx = rng.integers(0, n, n)
        p = [predictions[i] for i in idx]
        g = [ground_truth[i] for i in idx]
        res = detection_ap(p, g, class_range=class_range, min_points=min_points, explain=False)
        for c, d in res["classes"].items():
            aps[c].append(d["mean_ap"])
        if has_var:
            m = matched_residuals(p, g, class_range=class_range, min_points=min_points)
            if len(m):
                cov.append(float(np.mean(m.residual ** 2 / np.exp(m.log_variance) <= 1.0)))
        if progress is not None:
            progress(1)
    lo, hi = (1 - level) / 2 * 100, (1 + level) / 2 * 100

    def interval(vals: list[float]) -> list[float] | None:
        v = np.asarray([x for x in vals if math.isfinite(x)])
        if len(v) < 0.9 * resamples:
            return None
        return [float(np.percentile(v, lo)), float(np.percentile(v, hi))]

    for c, vals in aps.items():
        out[f"{c}_ap"] = interval(vals)
    out["coverage_1sigma"] = interval(cov) if has_var else None
    return out
