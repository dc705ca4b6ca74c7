"""Track-to-detection association as Autoware's multi_object_tracker gates it, vectorised.

Autoware scores every (track, detection) pair: zero unless the label pair may be assigned
(``can_assign``), the centres are within ``max_dist``, the detection's footprint area is within
``[min_area, max_area]``, the heading difference (mod pi) is within ``max_rad`` and the Mahalanobis distance of
the position is below 3.035 (the 99% gate of a chi-square with 2 dof); otherwise the score is
``(max_dist - dist) / max_dist``. The optimal assignment maximises the total score, and pairs scoring below
``score_threshold`` stay unassigned. Autoware's 2D-IoU gate is not applied: for boxes that already passed the
distance and area gates it rarely changes the outcome and would cost a polygon clip per pair.

Why vectorised and sparse: with 200 tracks and 200 detections a Python double loop is 40,000 iterations per
frame, and even one dense ``N x M`` numpy expression per gate costs milliseconds. Here a sweep over x finds
the pairs within the largest ``max_dist`` (:func:`near_pairs`), every gate runs as an array expression over
just those pairs, and ``scipy.optimize.linear_sum_assignment`` only sees the rows and columns that actually
compete for each other — most pairs are unambiguous and are assigned directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ...geometry import rect_iou
from .config import ConfigTables
from .kalman import wrap_half_pi

F64 = NDArray[np.float64]
IntArr = NDArray[np.intp]
UNKNOWN = 0
"""Autoware's label 0: a box of no known class loses to a classified one it overlaps."""


@dataclass(frozen=True)
class Candidates:
    """The gated pairs of one frame: ``rows[k]`` (track) may take ``cols[k]`` (detection) with ``score[k]``."""

    rows: IntArr
    cols: IntArr
    score: F64
    dist: F64
    mahalanobis: F64

    def subset(self, keep: NDArray[np.bool_]) -> "Candidates":
        """The pairs where ``keep`` is true."""
        return Candidates(self.rows[keep], self.cols[keep], self.score[keep], self.dist[keep], self.mahalanobis[keep])


MAX_PAIRS = 100_000
"""Candidate pairs expanded at once (or ``max_per_row`` per row, if more) before :func:`near_pairs` bounds each row."""


def near_pairs(a: F64, b: F64, r: float, max_per_row: int | None = None) -> tuple[IntArr, IntArr]:
    """All (i, j) with ``|a_i - b_j| <= r`` on both axes (a square, the caller checks the circle); with
    ``max_per_row``, at most that many per ``a_i``, the nearest.

    A sweep over x: ``b`` sorted by x, each ``a_i`` takes the slice within ``r`` by binary search and the
    pairs are expanded with ``repeat``; nothing is ``len(a) x len(b)`` unless every object is within ``r`` of
    every other. That is what keeps 500 objects per frame in budget. Should the slices together exceed
    :data:`MAX_PAIRS` (a crowd of co-located objects no sensor produces), ``max_per_row`` bounds the memory: a
    row whose slice is wider is cut to its nearest, one row at a time.
    """
    e = np.empty(0, dtype=np.intp)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return e, e
    order = np.argsort(b[:, 0], kind="stable")
    bx = b[order, 0]
    pad = r + 1e-9 * (1.0 + r + float(np.abs(bx).max()))  # rounding in a ± r must not lose a boundary pair
    lo = np.searchsorted(bx, a[:, 0] - pad, side="left")
    hi = np.searchsorted(bx, a[:, 0] + pad, side="right")
    counts = hi - lo
    wide = e
    if max_per_row is not None and int(counts.sum()) > max(MAX_PAIRS, max_per_row * a.shape[0]):  # a crowd
        wide = np.flatnonzero(counts > max_per_row)
        counts = np.where(counts > max_per_row, 0, counts)
    total = int(counts.sum())
    i = np.repeat(np.arange(a.shape[0]), counts)
    starts = np.repeat(lo - (np.cumsum(counts) - counts), counts)
    j = order[starts + np.arange(total)]
    keep = (np.abs(a[i, 0] - b[j, 0]) <= r) & (np.abs(a[i, 1] - b[j, 1]) <= r)
    rows, cols = [i[keep]], [j[keep]]
    for k in wide.tolist():  # a crowd: the nearest max_per_row within the square, one row at a time
        cand = order[lo[k]:hi[k]]
        dx, dy = b[cand, 0] - a[k, 0], b[cand, 1] - a[k, 1]
        inside = (np.abs(dx) <= r) & (np.abs(dy) <= r)
        cand, d2 = cand[inside], (dx * dx + dy * dy)[inside]
        if cand.size > max_per_row:
            cand = cand[np.argpartition(d2, max_per_row - 1)[:max_per_row]]
        rows.append(np.full(cand.size, k, dtype=np.intp))
        cols.append(cand)
    return np.concatenate(rows), np.concatenate(cols)


def gate(
    track_pos: F64,
    track_label: NDArray[np.integer],
    track_yaw: F64,
    track_pos_cov: F64,
    det_pos: F64,
    det_label: NDArray[np.integer],
    det_area: F64,
    det_yaw: F64,
    det_yaw_valid: NDArray[np.bool_],
    det_pos_cov: F64,
    tables: ConfigTables,
    mahalanobis_gate: float,
    use_innovation: bool,
    score_threshold: float,
    gate_min_variance: float = 0.0,
    max_candidates: int | None = None,
) -> Candidates:
    """Apply Autoware's gates to every (track, detection) pair and score the survivors.

    ``*_pos_cov`` are world-frame 2x2 position covariances: the track's predicted one and the detection's
    measurement covariance. With ``use_innovation`` the Mahalanobis distance uses their sum (the innovation
    covariance); without it only the track's, exactly as Autoware does. ``gate_min_variance`` is added to
    the gate covariance's diagonal so an over-confident detector cannot make a track reject its own object.
    ``max_candidates``: at most that many detections per track are scored, the nearest (memory stays bounded
    by the gating, not by the product of the counts, whatever a frame holds).
    """
    n, m = track_pos.shape[0], det_pos.shape[0]
    empty_i = np.empty(0, dtype=np.intp)
    empty_f = np.empty(0)
    if n == 0 or m == 0:
        return Candidates(empty_i, empty_i, empty_f, empty_f, empty_f)

    tl = track_label.astype(np.intp)
    dl = det_label.astype(np.intp)
    r_max = float(tables.max_dist[tables.can_assign].max()) if tables.can_assign.any() else 0.0
    rows, cols = near_pairs(track_pos, det_pos, r_max, max_candidates)
    tlr, dlc = tl[rows], dl[cols]
    ex = det_pos[cols, 0] - track_pos[rows, 0]
    ey = det_pos[cols, 1] - track_pos[rows, 1]
    dist2 = ex * ex + ey * ey
    mdist = tables.max_dist[tlr, dlc]
    ok = tables.can_assign[tlr, dlc] & (dist2 <= mdist * mdist)
    if not ok.all():
        rows, cols, tlr, dlc, ex, ey, dist2, mdist = (
            v[ok] for v in (rows, cols, tlr, dlc, ex, ey, dist2, mdist))
    if rows.size == 0:
        return Candidates(empty_i, empty_i, empty_f, empty_f, empty_f)
    dist = np.sqrt(dist2)

    # area gate: the detection's footprint against the label pair's bounds
    area = det_area[cols]
    keep = (area >= tables.min_area[tlr, dlc]) & (area <= tables.max_area[tlr, dlc])

    # heading gate (front/back not distinguished); a bound above pi disables it, as in Autoware
    max_rad = tables.max_rad[tlr, dlc]
    use_rad = (max_rad < np.pi) & det_yaw_valid[cols]
    dyaw = np.abs(wrap_half_pi(det_yaw[cols] - track_yaw[rows]))
    keep &= ~use_rad | (dyaw <= max_rad)

    # Mahalanobis gate on the 2x2 position covariance (closed-form inverse)
    S = track_pos_cov[rows]
    if use_innovation:
        S = S + det_pos_cov[cols]
    a, b, c = S[:, 0, 0] + gate_min_variance, S[:, 0, 1], S[:, 1, 1] + gate_min_variance
    det = np.maximum(a * c - b * b, 1e-12)
    md2 = (c * ex * ex - 2.0 * b * ex * ey + a * ey * ey) / det
    keep &= md2 < mahalanobis_gate * mahalanobis_gate

    score = (mdist - np.minimum(dist, mdist)) / mdist
    keep &= score >= score_threshold
    return Candidates(rows[keep], cols[keep], score[keep], dist[keep], np.sqrt(np.maximum(md2[keep], 0.0)))


def gate_newborn(
    track_pos: F64,
    track_label: NDArray[np.integer],
    track_yaw: F64,
    track_ctrv: NDArray[np.bool_],
    newborn: IntArr,
    since_birth_s: F64,
    det_pos: F64,
    det_vel: F64,
    det_label: NDArray[np.integer],
    det_area: F64,
    free: IntArr,
    tables: ConfigTables,
    max_candidates: int | None = None,
) -> Candidates:
    """A second gate for tracks born on the previous detection (``newborn`` rows: one hit, so no velocity yet)
    and the detections no track took (``free``), scored like :func:`gate`.

    A newborn is predicted where it was born (zero velocity), so the main gate's ``max_dist`` (2 m car to car,
    Autoware's) is all the way its object may have moved: a car first seen at over 20 m/s at 10 Hz, or 4 m/s on
    nuScenes' 2 Hz key frames, got a new tentative track every frame and was never tracked. Here the reach is
    ``max_dist`` plus the class's ``max_speed`` times the time since birth; a vehicle's (CTRV) displacement must
    lie along its box's heading (across it, within ``max_dist``), a mover's path; and the detection's own
    velocity (its twist: ``free`` holds only detections that report one) must predict the displacement to
    within ``max_dist``. Without that last condition a parked car's noisy young boxes, 2–6 m apart along the
    line of sight, paired up as a "fast" newcomer (tuning seeds, noise model: 78 → 97 static-vehicle rows
    called moving). UNKNOWN detections get no such chance: a blob's class says nothing of how far it moved.
    """
    empty_i = np.empty(0, dtype=np.intp)
    empty_f = np.empty(0)
    dl_all = det_label.astype(np.intp)
    free = free[dl_all[free] != UNKNOWN]
    newborn = newborn[track_label[newborn].astype(np.intp) != UNKNOWN]
    if newborn.size == 0 or free.size == 0:
        return Candidates(empty_i, empty_i, empty_f, empty_f, empty_f)
    tl_n = track_label[newborn].astype(np.intp)
    reach_n = tables.max_dist[tl_n].max(axis=1) + tables.max_speed[tl_n] * since_birth_s[newborn]
    i, j = near_pairs(track_pos[newborn], det_pos[free], float(reach_n.max()), max_candidates)
    rows, cols = newborn[i], free[j]
    tlr, dlc = track_label[rows].astype(np.intp), dl_all[cols]
    ex = det_pos[cols, 0] - track_pos[rows, 0]
    ey = det_pos[cols, 1] - track_pos[rows, 1]
    dist = np.hypot(ex, ey)
    mdist = tables.max_dist[tlr, dlc]
    reach = mdist + tables.max_speed[tlr] * since_birth_s[rows]
    moved = np.hypot(ex - det_vel[cols, 0] * since_birth_s[rows], ey - det_vel[cols, 1] * since_birth_s[rows])
    c, s = np.cos(track_yaw[rows]), np.sin(track_yaw[rows])
    across = np.abs(-s * ex + c * ey)
    area = det_area[cols]
    keep = (tables.can_assign[tlr, dlc] & (dist <= reach) & (area >= tables.min_area[tlr, dlc])
            & (area <= tables.max_area[tlr, dlc]) & (~track_ctrv[rows] | (across <= mdist)) & (moved <= mdist))
    score = (reach - dist) / reach
    keep &= score > 0.0
    return Candidates(rows[keep], cols[keep], score[keep], dist[keep], np.full(int(keep.sum()), np.nan))


def assign(n_tracks: int, n_dets: int, cand: Candidates) -> tuple[IntArr, IntArr]:
    """Maximum-total-score one-to-one assignment over the gated pairs; returns (track rows, detection cols).

    A pair that is the only candidate of both its track and its detection is assigned directly (the optimum
    cannot do otherwise); the rest — tracks and detections that compete — go to ``linear_sum_assignment`` on
    the dense sub-matrix they span, where a zero means "not allowed" and is dropped from the answer.
    """
    if cand.rows.size == 0:
        e = np.empty(0, dtype=np.intp)
        return e, e
    row_deg = np.bincount(cand.rows, minlength=n_tracks)
    col_deg = np.bincount(cand.cols, minlength=n_dets)
    simple = (row_deg[cand.rows] == 1) & (col_deg[cand.cols] == 1)
    out_r = [cand.rows[simple]]
    out_c = [cand.cols[simple]]
    hard = ~simple
    if hard.any():
        for hr, hc, hs in _components(cand.rows[hard], cand.cols[hard], cand.score[hard]):
            ur, ir = np.unique(hr, return_inverse=True)
            uc, ic = np.unique(hc, return_inverse=True)
            if ur.size * uc.size > MAX_DENSE_CELLS:  # a crowd too big for an optimal solve in bounded memory
                r_, c_ = _greedy(hr, hc, hs)
                out_r.append(r_)
                out_c.append(c_)
                continue
            mat = np.zeros((ur.size, uc.size))
            mat[ir, ic] = hs
            r, c = linear_sum_assignment(mat, maximize=True)
            good = mat[r, c] > 0.0
            out_r.append(ur[r[good]])
            out_c.append(uc[c[good]])
    rows = np.concatenate(out_r)
    cols = np.concatenate(out_c)
    order = np.argsort(rows, kind="stable")
    return rows[order], cols[order]


MAX_DENSE_CELLS = 250_000
"""The largest (tracks x detections) block solved optimally at once (2 MB); a bigger block of competing pairs is
split into its connected components, and one still bigger (a crowd no sensor produces) assigned greedily."""


def _components(rows: IntArr, cols: IntArr, score: F64) -> list[tuple[IntArr, IntArr, F64]]:
    """The competing pairs as one block when it is small enough, else one block per connected component."""
    n_r, n_c = int(rows.max()) + 1, int(cols.max()) + 1
    if np.unique(rows).size * np.unique(cols).size <= MAX_DENSE_CELLS:
        return [(rows, cols, score)]
    graph = coo_matrix((np.ones(rows.size), (rows, n_r + cols)), shape=(n_r + n_c, n_r + n_c))
    _, label = connected_components(graph, directed=False)
    comp = label[rows]
    order = np.argsort(comp, kind="stable")
    bounds = np.flatnonzero(np.diff(comp[order])) + 1
    return [(rows[k], cols[k], score[k]) for k in np.split(order, bounds)]


def _greedy(rows: IntArr, cols: IntArr, score: F64) -> tuple[IntArr, IntArr]:
    """Pairs taken best score first, each track and detection once (positive scores only)."""
    taken_r: set[int] = set()
    taken_c: set[int] = set()
    out_r, out_c = [], []
    for k in np.argsort(-score, kind="stable").tolist():
        r, c = int(rows[k]), int(cols[k])
        if score[k] > 0.0 and r not in taken_r and c not in taken_c:
            taken_r.add(r)
            taken_c.add(c)
            out_r.append(r)
            out_c.append(c)
    return np.asarray(out_r, dtype=np.intp), np.asarray(out_c, dtype=np.intp)


def overlapping(
    pos: F64,
    label: NDArray[np.integer],
    width: F64,
    hits: NDArray[np.integer],
    can_assign: NDArray[np.bool_],
    factor: float,
    max_per_row: int | None = None,
    *,
    yaw: F64 | None = None,
    length: F64 | None = None,
    min_iou: float = 0.0,
    min_iou_unknown: float = 0.0,
    confirmed: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """Rows to delete because another track describes the same object (Autoware's overlapped-tracker removal).

    Two tracks overlap when (a) their labels may share a detection and their centres are closer than
    ``factor`` times the narrower box's width, or (b) their bird's-eye boxes (``yaw``, ``length``, ``width``)
    overlap with an IoU above ``min_iou`` — ``min_iou_unknown`` where either is UNKNOWN — whatever their labels,
    as Autoware's ``removeOverlappedTracker`` tests it. Of such a pair the UNKNOWN one goes if only one is, else
    the one with fewer hits (the younger on a tie) — but a tentative track (``confirmed`` false) never removes a
    confirmed one, as in Autoware (a track that is not confident removes nothing): a low-scored clutter return
    that recurs in one place stays tentative and gathers hits, and a confirmed car driving past it had been
    deleted, its ID gone and the car unpublished until a new track of it was confirmed. Without (a) a detection that once missed its track's gate
    starts a twin that then steals every other detection, and both live on, alternating, as duplicate confirmed
    tracks; without (b) a second box the detector puts on one long or partly seen vehicle, a metre or two off
    its centre, becomes a confirmed track of its own that hops between such boxes — a ghost that appears to
    move. The price of (b): where such a second box was tracked first, it is the real box's newborn track that
    goes, and the object is published through the overlapping, off-centre track until that one dies.
    """
    n = pos.shape[0]
    drop = np.zeros(n, dtype=bool)
    use_iou = yaw is not None and length is not None and (min_iou > 0.0 or min_iou_unknown > 0.0)
    if n < 2 or (factor <= 0.0 and not use_iou):
        return drop
    r = factor * float(width.max())
    if use_iou:
        assert length is not None
        r = max(r, float(np.hypot(length, width).max()))  # boxes whose centres are farther apart cannot touch
    i, j = near_pairs(pos, pos, r, max_per_row)
    up = i < j
    i, j = i[up], j[up]
    d2 = (pos[i, 0] - pos[j, 0]) ** 2 + (pos[i, 1] - pos[j, 1]) ** 2
    lim = factor * np.minimum(width[i], width[j])
    tl = label.astype(np.intp)
    close = (d2 < lim * lim) & can_assign[tl[i], tl[j]]
    unknown_i, unknown_j = tl[i] == UNKNOWN, tl[j] == UNKNOWN
    by_iou = np.zeros_like(close)
    if use_iou:
        assert yaw is not None and length is not None
        thr = np.where(unknown_i | unknown_j, min_iou_unknown, min_iou)
        half_diag = 0.5 * np.hypot(length, width)
        reach = half_diag[i] + half_diag[j]
        test = np.flatnonzero((thr > 0.0) & ~close & (d2 < reach * reach))  # only pairs that can touch
        iou = rect_iou((pos[i[test], 0], pos[i[test], 1], length[i[test]], width[i[test]], yaw[i[test]]),
                       (pos[j[test], 0], pos[j[test], 1], length[j[test]], width[j[test]], yaw[j[test]]))
        by_iou[test] = iou > thr[test]
    pair = close | by_iou
    i, j = i[pair], j[pair]
    unknown_i, unknown_j = unknown_i[pair], unknown_j[pair]
    if i.size == 0:
        return drop
    # rows are in birth order, so j (> i) is the younger: it goes unless it has strictly more hits
    loser = np.where(hits[j] > hits[i], i, j)
    loser = np.where(unknown_i & ~unknown_j, i, np.where(unknown_j & ~unknown_i, j, loser))
    if confirmed is not None:
        winner = np.where(loser == i, j, i)
        loser = loser[~(confirmed[loser] & ~confirmed[winner])]
    drop[loser] = True
    return drop
