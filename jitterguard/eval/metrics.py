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
    """Per (track, matched object) pair, seconds from the pair's first row to its first correct decision
    (undecided is not correct); NaN if never correct. The paper wants a quick first decision (min_window 2).
    Timed from the pair's first row, not the track's: after an ID switch the new object's latency had included
    the time the track spent on the old one."""
    out: list[float] = []
    if len(rec) == 0:
        return np.empty(0)
    want = np.where(rec.gt_dynamic, DYNAMIC, STATIC)
    keys = np.char.add(np.char.add(rec.track_id, ":"), rec.gt_instance.astype(str))
    idx = np.flatnonzero(rec.gt_instance >= 0)
    idx = idx[np.argsort(keys[idx], kind="stable")]  # each pair's rows together, in table order (one pass)
    bounds = np.flatnonzero(keys[idx][1:] != keys[idx][:-1]) + 1
    for rows in np.split(idx, bounds) if idx.size else []:
        ok = rows[state[rows] == want[rows]]
        out.append(float(rec.t_s[ok[0]] - rec.t_s[rows[0]]) if len(ok) else math.nan)
    return np.asarray(out, dtype=np.float64)


def scored_rows(rec: Records, group: str, *, full_window: bool = False) -> NDArray[np.bool_]:
    """Rows scored for ``group``: matched, in the group, z-test window long enough to decide (or, with
    ``full_window``, holding ``window_size`` observations)."""
    need = rec.window_size if full_window else rec.min_window
    return (rec.group == group) & (rec.window >= need)


def ghost_rows(rec: Records, group: str) -> NDArray[np.bool_]:
    """Rows of tracks matched to no object whose own label is in ``group``, window long enough to decide."""
    return (rec.gt_instance < 0) & (rec.track_group == group) & (rec.window >= rec.min_window)


def vetoed_rows(rec: Records) -> dict[str, dict[str, int]]:
    """Per report group, the scored rows the jump veto called static although the test rejected — on static objects
    (false alarms it took back), on moving ones (misses it caused) and on ghost tracks: what the veto did to this
    run's rates (``false_dynamic_z`` without it = (false rows + ``static``) / ``n_static``)."""
    out = {}
    for g in REPORT_GROUPS:
        scored = rec.vetoed & scored_rows(rec, g)
        out[g] = {"static": int(np.count_nonzero(scored & ~rec.gt_dynamic)),
                  "moving": int(np.count_nonzero(scored & rec.gt_dynamic)),
                  "ghost": int(np.count_nonzero(rec.vetoed & ghost_rows(rec, g)))}
    return out


def _nan_to_none(x: float) -> float | None:
    return None if (isinstance(x, float) and math.isnan(x)) else round(float(x), 6)


def _clean(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (_nan_to_none(v) if isinstance(v, float) else v) for k, v in d.items()}


BOOTSTRAP_RESAMPLES = 400
"""Resamples of tracks behind every 90 % interval (seeded: the same table gives the same interval)."""


class TrackBootstrap:
    """90 % percentile intervals over tracks: resampling whole tracks (with replacement) keeps the rows of one
    track together, since they are strongly dependent (one parked car gives hundreds of near-identical rows). A
    rate of exactly 0 or 1, which every resample repeats, gets the exact binomial interval over its tracks instead;
    any other rate of a single track has none (None: resampling one track says nothing of how far its rate may be).

    ``weights[b, i]`` is how often row i's track is drawn in resample b; a rate is Σ w·num / Σ w·den, an AP is
    the weighted AP (:func:`weighted_average_precision`)."""

    def __init__(self, track_ids: NDArray[np.str_], resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> None:
        self.uniq, self.inverse = np.unique(track_ids, return_inverse=True)
        rng = np.random.default_rng(seed)
        n = len(self.uniq)
        draws = rng.integers(0, max(n, 1), size=(resamples, n)) if n else np.zeros((resamples, 0), np.int64)
        self.track_weights = np.stack([np.bincount(d, minlength=n) for d in draws]).astype(np.float64) \
            if n else np.zeros((resamples, 0))

    def rows(self, mask: NDArray[np.bool_]) -> NDArray[np.float64]:
        """(resamples, rows in mask) weights."""
        return self.track_weights[:, self.inverse[mask]]

    def rate(self, mask: NDArray[np.bool_], hit: NDArray[np.bool_]) -> list[float] | None:
        """Interval of mean(hit[mask]); None where the mask is empty, or one track's rate is neither 0 nor 1."""
        if not mask.any():
            return None
        h = hit[mask]
        if not h.any() or h.all():
            # every resample gives the same 0 (or 1): the bootstrap says nothing of how far the rate may be from it
            # (0 of 55 rows had read [0, 0]); the exact Clopper–Pearson 90 % interval does, with the tracks as the
            # trials (conservative: the rows of one track move together)
            edge = round(0.05 ** (1.0 / len(np.unique(self.inverse[mask]))), 6)
            return [0.0, round(1.0 - edge, 6)] if not h.any() else [edge, 1.0]
        if len(np.unique(self.inverse[mask])) < 2:
            return None  # one track: every resample repeats its rate, and a point interval would claim certainty
        w = self.rows(mask)
        den = w.sum(axis=1)
        num = (w * hit[mask]).sum(axis=1)
        r = num[den > 0] / den[den > 0]
        return _interval(r)

    def ap(self, mask: NDArray[np.bool_], score: NDArray[np.float64], positive: NDArray[np.bool_]) -> list[float] | None:
        """Interval of the AP of ``score`` for ``positive`` on the rows in ``mask`` (None if undefined). Where every
        resample gives the same AP (a few tracks, perfectly ranked), the bootstrap says nothing of how far it may be:
        an AP of 1 gets the exact lower bound with the tracks as trials, as a rate of 1 does (``[1, 1]`` from 3
        tracks had claimed certainty), any other such AP none."""
        if not mask.any() or positive[mask].all() or not positive[mask].any():
            return None
        w = self.rows(mask)
        s, p = score[mask], positive[mask]
        vals = np.asarray([v for v in (weighted_average_precision(s, p, wb) for wb in w) if not math.isnan(v)])
        if len(vals) == 0:
            return None
        if vals.min() == vals.max():
            tracks = len(np.unique(self.inverse[mask]))
            return [round(0.05 ** (1.0 / tracks), 6), 1.0] if vals[0] == 1.0 else None
        return _interval(vals)


def _interval(values: NDArray[np.float64]) -> list[float] | None:
    if len(values) == 0:
        return None
    lo, hi = np.percentile(values, [5.0, 95.0])
    return [round(float(lo), 6), round(float(hi), 6)]


def weighted_average_precision(scores: ArrayLike, positive: ArrayLike, weights: ArrayLike) -> float:
    """:func:`average_precision` with row weights (a bootstrap resample); NaN without weighted positives or
    without weighted negatives (a resample of dynamic rows only has no AP, as the point estimate has none: it
    had counted as 1.0 and lifted intervals' upper ends to 1)."""
    s = np.asarray(scores, dtype=np.float64)
    p = np.asarray(positive, dtype=bool)
    w = np.asarray(weights, dtype=np.float64)
    order = np.argsort(-s, kind="stable")
    s, p, w = s[order], p[order], w[order]
    tp = np.cumsum(w * p)
    fp = np.cumsum(w * ~p)
    n_pos = tp[-1] if len(tp) else 0.0
    if n_pos <= 0 or (fp[-1] if len(fp) else 0.0) <= 0:
        return math.nan
    last = np.r_[np.flatnonzero(np.diff(s) != 0), len(s) - 1]
    tp, fp = tp[last], fp[last]
    precision = tp / np.maximum(tp + fp, 1e-300)
    recall = tp / n_pos
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def _defined(x: float, ok: bool) -> float:
    return x if ok else math.nan


def group_metrics(rec: Records, group: str, boot: TrackBootstrap | None = None, *,
                  full_window: bool = False) -> dict[str, Any]:
    """One group's AP (z and speed as scores), operating-point error rates, counts, decision latency and (with
    ``boot``) their 90 % intervals over tracks. An AP needs both static and dynamic rows (else null, not 1.0);
    a false-dynamic rate needs static rows, a missed-dynamic rate dynamic ones."""
    m = scored_rows(rec, group, full_window=full_window)
    dyn = rec.gt_dynamic[m]
    z, sp = rec.z[m], rec.speed[m]
    sz, sv = rec.state_z[m], rec.state_v[m]
    both = bool(dyn.any() and (~dyn).any())
    sub = rec.subset(rec.group == group)
    ttz = time_to_first_correct(sub, sub.state_z)
    ttv = time_to_first_correct(sub, sub.state_v)
    # the latency a planner feels: from a track's first row on a moving object to its first dynamic decision
    moving = rec.subset((rec.group == group) & rec.gt_dynamic)
    tdz = time_to_first_correct(moving, moving.state_z)
    tdv = time_to_first_correct(moving, moving.state_v)

    def med(a: NDArray[np.float64]) -> float:
        a = a[np.isfinite(a)]
        return float(np.median(a)) if len(a) else math.nan

    out: dict[str, Any] = {
        "n_static": int((~dyn).sum()),
        "n_dynamic": int(dyn.sum()),
        "n_tracks": int(len(np.unique(rec.track_id[m]))),
        "ap_z": _defined(average_precision(z, dyn), both),
        "ap_speed": _defined(average_precision(sp, dyn), both),
        "false_dynamic_z": rate(sz, ~dyn, DYNAMIC),
        "false_dynamic_speed": rate(sv, ~dyn, DYNAMIC),
        "missed_dynamic_z": rate(sz, dyn, STATIC),
        "missed_dynamic_speed": rate(sv, dyn, STATIC),
    }
    if not full_window:
        latency = {
            "time_to_first_correct_s_median_z": med(ttz),
            "time_to_first_correct_s_median_speed": med(ttv),
            "never_correct_fraction_z": float(np.mean(~np.isfinite(ttz))) if len(ttz) else math.nan,
            "never_correct_fraction_speed": float(np.mean(~np.isfinite(ttv))) if len(ttv) else math.nan,
            "time_to_dynamic_s_median_z": med(tdz),
            "time_to_dynamic_s_median_speed": med(tdv),
            "never_dynamic_fraction_z": float(np.mean(~np.isfinite(tdz))) if len(tdz) else math.nan,
            "never_dynamic_fraction_speed": float(np.mean(~np.isfinite(tdv))) if len(tdv) else math.nan,
        }
        # none of the group's rows decided: no latency to report (a run too short had read "never correct" 1.0 for
        # the z-test and 0 s for the speed rule, from rows no rate scores)
        out.update(latency if m.any() else dict.fromkeys(latency, math.nan))
    out = _clean(out)
    if boot is not None:
        static_m, dyn_m = m & ~rec.gt_dynamic, m & rec.gt_dynamic
        out["ci90"] = {
            "ap_z": boot.ap(m, rec.z, rec.gt_dynamic) if both else None,
            "ap_speed": boot.ap(m, rec.speed, rec.gt_dynamic) if both else None,
            "false_dynamic_z": boot.rate(static_m, rec.state_z == DYNAMIC),
            "false_dynamic_speed": boot.rate(static_m, rec.state_v == DYNAMIC),
            "missed_dynamic_z": boot.rate(dyn_m, rec.state_z == STATIC),
            "missed_dynamic_speed": boot.rate(dyn_m, rec.state_v == STATIC),
        }
    return out


def ghost_metrics(rec: Records, group: str, boot: TrackBootstrap | None = None) -> dict[str, Any]:
    """Tracks matched to no object (``ghost_rows``), scored as static truth: a ghost with a velocity is what
    makes a planner brake for nothing. ``on``: the same by what the ghosts stand on (``Records.ghost_on``: a
    labelled object that is no road user — a ghost pedestrian on a nuScenes pile of debris is a real obstacle —
    or nothing labelled), the commonest first."""
    m = ghost_rows(rec, group)
    out: dict[str, Any] = _clean({
        "n": int(m.sum()),
        "n_tracks": int(len(np.unique(rec.track_id[m]))),
        "false_dynamic_z": rate(rec.state_z, m, DYNAMIC),
        "false_dynamic_speed": rate(rec.state_v, m, DYNAMIC),
    })
    if boot is not None:
        out["ci90"] = {"false_dynamic_z": boot.rate(m, rec.state_z == DYNAMIC),
                       "false_dynamic_speed": boot.rate(m, rec.state_v == DYNAMIC)}
    out["on"] = {}
    kinds, counts = np.unique(rec.ghost_on[m], return_counts=True)  # by name, then the commonest first
    for what in kinds[np.argsort(-counts, kind="stable")].tolist():
        on = m & (rec.ghost_on == what)
        out["on"][what] = _clean({"n": int(on.sum()), "n_tracks": int(len(np.unique(rec.track_id[on]))),
                                  "false_dynamic_z": rate(rec.state_z, on, DYNAMIC),
                                  "false_dynamic_speed": rate(rec.state_v, on, DYNAMIC)})
        if boot is not None:  # a handful of tracks on a cone: the interval says how little that is
            out["on"][what]["ci90"] = {"false_dynamic_z": boot.rate(on, rec.state_z == DYNAMIC),
                                       "false_dynamic_speed": boot.rate(on, rec.state_v == DYNAMIC)}
    return out


def _missed_at_fd(score: NDArray[np.float64], dyn: NDArray[np.bool_], fd_target: float) -> float:
    """Missed-dynamic rate of ``score > t`` for the lowest t whose false-dynamic rate is ≤ ``fd_target``."""
    if not dyn.any() or dyn.all() or math.isnan(fd_target):
        return math.nan
    st = np.sort(score[~dyn])[::-1]  # static scores, highest first
    k = int(math.floor(fd_target * len(st) + 1e-9))  # this many static rows may score above t
    t = st[k] if k < len(st) else -math.inf
    return float(np.mean(score[dyn] <= t))


def matched_metrics(rec: Records, group: str) -> dict[str, Any]:
    """Each rule's missed-dynamic rate at the other rule's false-dynamic rate: the speed rule's normalised
    score speed / class threshold and the z-test's z / class alpha are each swept over one factor, so both
    keep their per-class structure. Answers "at equal false alarms, who misses less?"."""
    m = scored_rows(rec, group)
    dyn = rec.gt_dynamic[m]
    zs = rec.z[m] / np.maximum(rec.alpha[m], 1e-9)
    vs = rec.speed[m] / np.maximum(rec.speed_threshold[m], 1e-9)
    fd_v = rate(rec.state_v[m], ~dyn, DYNAMIC)
    fd_z = rate(rec.state_z[m], ~dyn, DYNAMIC)
    return _clean({
        "false_dynamic_speed": fd_v,
        "missed_dynamic_z_at_speed_false_dynamic": _missed_at_fd(zs, dyn, fd_v),
        "missed_dynamic_speed": rate(rec.state_v[m], dyn, STATIC),
        "false_dynamic_z": fd_z,
        "missed_dynamic_speed_at_z_false_dynamic": _missed_at_fd(vs, dyn, fd_z),
        "missed_dynamic_z": rate(rec.state_z[m], dyn, STATIC),
    })


def attribute_metrics(rec: Records, boot: TrackBootstrap | None = None) -> dict[str, Any]:
    """Per ground-truth attribute (``vehicle.parked``, ``pedestrian.moving``, …) of the scored rows: false
    dynamic for static attributes, missed dynamic for moving ones (the other pair null), and row counts."""
    out: dict[str, Any] = {}
    decided = (rec.gt_instance >= 0) & (rec.group != "") & (rec.window >= rec.min_window)
    for attr in sorted(set(rec.gt_attribute[decided].tolist()) - {""}):
        m = decided & (rec.gt_attribute == attr)
        dyn = rec.gt_dynamic[m]
        st_m, dy_m = m & ~rec.gt_dynamic, m & rec.gt_dynamic
        block: dict[str, Any] = _clean({
            "n": int(m.sum()), "n_tracks": int(len(np.unique(rec.track_id[m]))),
            "false_dynamic_z": rate(rec.state_z[m], ~dyn, DYNAMIC),
            "false_dynamic_speed": rate(rec.state_v[m], ~dyn, DYNAMIC),
            "missed_dynamic_z": rate(rec.state_z[m], dyn, STATIC),
            "missed_dynamic_speed": rate(rec.state_v[m], dyn, STATIC),
        })
        if boot is not None:
            block["ci90"] = {"false_dynamic_z": boot.rate(st_m, rec.state_z == DYNAMIC),
                             "false_dynamic_speed": boot.rate(st_m, rec.state_v == DYNAMIC),
                             "missed_dynamic_z": boot.rate(dy_m, rec.state_z == STATIC),
                             "missed_dynamic_speed": boot.rate(dy_m, rec.state_v == STATIC)}
        out[attr] = block
    return out


def compute_metrics(rec: Records, *, intervals: bool = True) -> dict[str, Any]:
    """The ``motion`` block of metrics.json: ``{group: group_metrics}`` for vehicle, pedestrian, bicycle, each
    with 90 % intervals over tracks unless ``intervals`` is false."""
    boot = TrackBootstrap(rec.track_id) if intervals else None
    return {g: group_metrics(rec, g, boot) for g in REPORT_GROUPS}


def planner_metrics(rec: Records, *, intervals: bool = True) -> dict[str, Any]:
    """What a planner sees beyond ``motion``: ``ghost.{group}``, ``matched.{group}``, ``by_attribute`` and
    ``full_window.{group}`` (the rates on rows whose window has filled)."""
    boot = TrackBootstrap(rec.track_id) if intervals else None
    return {
        "ghost": {g: ghost_metrics(rec, g, boot) for g in ("vehicle", "pedestrian", "bicycle")},
        "matched": {g: matched_metrics(rec, g) for g in REPORT_GROUPS},
        "by_attribute": attribute_metrics(rec, boot),
        "full_window": {g: group_metrics(rec, g, boot, full_window=True) for g in REPORT_GROUPS},
    }


RUN_KEYS = ("n_static", "n_dynamic", "false_dynamic_z", "false_dynamic_speed", "missed_dynamic_z",
            "missed_dynamic_speed")


def run_metrics(rec: Records, tags: list[str]) -> dict[str, Any]:
    """``by_run.{tag}``: each pooled run's (seed's or scene's) vehicle and pedestrian rates and counts and its
    ghost rates, without intervals (one run is a handful of tracks: the pooled figures carry the intervals).
    Rows belong to the run whose ``tag/`` prefixes their track ID (:func:`~.pipeline.concat_records`); what one
    place does to a pooled rate shows here."""
    out: dict[str, Any] = {}
    for tag in tags:
        sub = rec.subset(np.char.startswith(rec.track_id.astype(str), f"{tag}/"))
        entry: dict[str, Any] = {}
        for g in ("vehicle", "pedestrian"):
            m = group_metrics(sub, g)
            entry[g] = {k: m.get(k) for k in RUN_KEYS}
            gh = ghost_metrics(sub, g)
            entry[g].update({"ghost_n": gh["n"], "ghost_false_dynamic_z": gh.get("false_dynamic_z"),
                             "ghost_false_dynamic_speed": gh.get("false_dynamic_speed")})
        out[tag] = entry
    return out


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
    # missed = fraction of dynamic z ≤ alpha; the largest alpha with ≤ k misses sits just below zd[k]; none if
    # that is not above 0 (more than k moving rows at z 0, e.g. vetoed): no alpha > 0 keeps the misses that low
    if k >= len(zd):
        return float(zd[-1])
    return float(np.nextafter(zd[k], -np.inf)) if zd[k] > 0 else None
