"""Scores of the motion classifier against ground truth: pure functions over a :class:`Records` table.

What is scored (paper §IV-B, Table II): per evaluation group, every (frame, track) row that is matched to a
ground-truth object and whose z-test window is long enough to decide (``window ≥ min_window``) — the same
rows for both rules, so the velocity threshold is not credited for deciding on a track's first frame.
"Dynamic" is the positive class. AP uses the raw score (z, or the tracker's speed) and is threshold-free;
the false-/missed-dynamic rates are at the configured operating point (alpha per class; velocity threshold).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..services.classifier.core import DYNAMIC, STATIC
from .pipeline import Records

REPORT_GROUPS = ("vehicle", "pedestrian", "bicycle")


def pr_curve(scores: ArrayLike, positive: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                                NDArray[np.float64]]:
    """Precision, recall and the threshold at each distinct score (highest first); ties form one point,
    so a score that cannot separate two samples gets no credit for their order."""
    s = np.asarray(scores, dtype=np.float64)
    p = np.asarray(positive, dtype=bool)
    if s.shape != p.shape:
        raise ValueError("scores and positive must have the same shape")
    order = np.argsort(-s, kind="stable")
    s, p = s[order], p[order]
    tp = np.cumsum(p)
    fp = np.cumsum(~p)
    last = np.r_[np.flatnonzero(np.diff(s) != 0), len(s) - 1] if len(s) else np.empty(0, np.int64)
    tp, fp = tp[last], fp[last]
    n_pos = max(int(p.sum()), 1)
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / n_pos
    return precision, recall, s[last]


def average_precision(scores: ArrayLike, positive: ArrayLike) -> float:
    """AP = Σ (Rₙ − Rₙ₋₁) Pₙ over distinct thresholds (scikit-learn's definition, no interpolation);
    NaN when there is no positive sample (AP is undefined then, not 0)."""
    p = np.asarray(positive, dtype=bool)
    if not p.any():
        return math.nan
    precision, recall, _ = pr_curve(scores, p)
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def rate(decisions: ArrayLike, mask: ArrayLike, state: int) -> float:
    """Fraction of the rows in ``mask`` decided ``state`` (NaN for an empty mask)."""
    d = np.asarray(decisions)
    m = np.asarray(mask, dtype=bool)
    return float(np.mean(d[m] == state)) if m.any() else math.nan


def time_to_first_correct(rec: Records, state: NDArray[np.int8]) -> NDArray[np.float64]:
    """Per (track, matched object) pair, seconds from the track's first row to its first correct decision
    (undecided is not correct); NaN if never correct. The paper wants a quick first decision (min_window 2)."""
    out: list[float] = []
    if len(rec) == 0:
        return np.empty(0)
    first_seen: dict[str, float] = {}
    for tid, t in zip(rec.track_id.tolist(), rec.t_s.tolist()):
        first_seen.setdefault(tid, t)
    want = np.where(rec.gt_dynamic, DYNAMIC, STATIC)
    keys = np.char.add(np.char.add(rec.track_id, ":"), rec.gt_instance.astype(str))
    matched = rec.gt_instance >= 0
    for key in np.unique(keys[matched]):
        rows = np.flatnonzero(keys == key)
        ok = rows[state[rows] == want[rows]]
        tid = str(rec.track_id[rows[0]])
        out.append(float(rec.t_s[ok[0]] - first_seen[tid]) if len(ok) else math.nan)
    return np.asarray(out, dtype=np.float64)


def scored_rows(rec: Records, group: str) -> NDArray[np.bool_]:
    """Rows scored for ``group``: matched, in the group, z-test window long enough to decide."""
    return (rec.group == group) & (rec.window >= rec.min_window)


def _nan_to_none(x: float) -> float | None:
    return None if (isinstance(x, float) and math.isnan(x)) else round(float(x), 6)


def group_metrics(rec: Records, group: str) -> dict[str, Any]:
    """One group's AP (z and speed as scores), operating-point error rates, counts and decision latency."""
    m = scored_rows(rec, group)
    dyn = rec.gt_dynamic[m]
    z, sp = rec.z[m], rec.speed[m]
    sz, sv = rec.state_z[m], rec.state_v[m]
    sub = rec.subset(rec.group == group)
    ttz = time_to_first_correct(sub, sub.state_z)
    ttv = time_to_first_correct(sub, sub.state_v)

    def med(a: NDArray[np.float64]) -> float:
        a = a[np.isfinite(a)]
        return float(np.median(a)) if len(a) else math.nan

    out = {
        "n_static": int((~dyn).sum()),
        "n_dynamic": int(dyn.sum()),
        "n_tracks": int(len(np.unique(sub.track_id))),
        "ap_z": average_precision(z, dyn),
        "ap_speed": average_precision(sp, dyn),
        "false_dynamic_z": rate(sz, ~dyn, DYNAMIC),
        "false_dynamic_speed": rate(sv, ~dyn, DYNAMIC),
        "missed_dynamic_z": rate(sz, dyn, STATIC),
        "missed_dynamic_speed": rate(sv, dyn, STATIC),
        "time_to_first_correct_s_median_z": med(ttz),
        "time_to_first_correct_s_median_speed": med(ttv),
        "never_correct_fraction_z": float(np.mean(~np.isfinite(ttz))) if len(ttz) else math.nan,
        "never_correct_fraction_speed": float(np.mean(~np.isfinite(ttv))) if len(ttv) else math.nan,
    }
    return {k: (_nan_to_none(v) if isinstance(v, float) else v) for k, v in out.items()}


def compute_metrics(rec: Records) -> dict[str, Any]:
    """The ``motion`` block of metrics.json: ``{group: group_metrics}`` for vehicle, pedestrian, bicycle."""
    return {g: group_metrics(rec, g) for g in REPORT_GROUPS}


def alpha_sweep(rec: Records, group: str, alphas: ArrayLike) -> dict[str, list[float]]:
    """False-/missed-dynamic rate of ``z > alpha`` for one alpha applied to every class (scored rows)."""
    m = scored_rows(rec, group)
    dyn, z = rec.gt_dynamic[m], rec.z[m]
    a = np.asarray(alphas, dtype=np.float64)
    fd = [float(np.mean(z[~dyn] > x)) if (~dyn).any() else math.nan for x in a]
    md = [float(np.mean(z[dyn] <= x)) if dyn.any() else math.nan for x in a]
    return {"alpha": a.tolist(), "false_dynamic": fd, "missed_dynamic": md}


def alpha_from_labels(rec: Records, group: str, max_missed: float = 0.05) -> float | None:
    """The smallest-false-dynamic alpha whose missed-dynamic rate stays ≤ ``max_missed`` on labelled rows:
    the paper could not tune alpha for lack of labels (§IV-B); with labels, this is the tuning rule."""
    m = scored_rows(rec, group)
    dyn, z = rec.gt_dynamic[m], rec.z[m]
    if not dyn.any():
        return None
    zd = np.sort(z[dyn])
    k = int(math.floor(max_missed * len(zd)))
    # missed = fraction of dynamic z ≤ alpha; the largest alpha with ≤ k misses sits just below zd[k]
    return float(np.nextafter(zd[k], -np.inf)) if k < len(zd) else float(zd[-1])
