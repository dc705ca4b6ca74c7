"""Autoware's gates, the sparse pair search and the optimal assignment."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from jitterguard.geometry import rect_iou
from jitterguard.services.tracker.association import Candidates, assign, gate, near_pairs, overlapping
from jitterguard.services.tracker.config import default_config

CAR, TRUCK, PED, UNKNOWN = 1, 2, 7, 0
TABLES = default_config().tables()


def _gate(track_xy, track_label, det_xy, det_label, *, det_area=None, track_yaw=None, det_yaw=None,
          track_cov=0.25, det_cov=0.04, use_innovation=True, gate_min_variance=0.0):
    track_xy = np.atleast_2d(np.asarray(track_xy, dtype=float))
    det_xy = np.atleast_2d(np.asarray(det_xy, dtype=float))
    n, m = len(track_xy), len(det_xy)
    return gate(
        track_xy, np.asarray(track_label), np.zeros(n) if track_yaw is None else np.asarray(track_yaw, float),
        np.tile(np.eye(2) * track_cov, (n, 1, 1)),
        det_xy, np.asarray(det_label), np.full(m, 8.0) if det_area is None else np.asarray(det_area, float),
        np.zeros(m) if det_yaw is None else np.asarray(det_yaw, float), np.ones(m, dtype=bool),
        np.tile(np.eye(2) * det_cov, (m, 1, 1)), TABLES, 3.035, use_innovation, 0.01, gate_min_variance,
    )


def test_score_is_autowares_normalised_distance() -> None:
    c = _gate([[0, 0]], [CAR], [[0.5, 0.0]], [CAR])
    assert c.rows.tolist() == [0] and c.cols.tolist() == [0]
    assert c.score[0] == pytest.approx((2.0 - 0.5) / 2.0)  # car-car max_dist is 2 m


def test_can_assign_matrix_keeps_cars_and_pedestrians_apart() -> None:
    assert _gate([[0, 0]], [CAR], [[0.1, 0]], [PED], det_area=[0.36]).rows.size == 0
    assert _gate([[0, 0]], [CAR], [[0.1, 0]], [TRUCK], det_area=[8.0]).rows.size == 1
    assert _gate([[0, 0]], [UNKNOWN], [[0.1, 0]], [CAR]).rows.size == 0


def test_max_distance_depends_on_the_label_pair() -> None:
    # car track, truck detection: 5 m allowed; car-car: 2 m (large covariance so only distance gates)
    assert _gate([[0, 0]], [CAR], [[3.0, 0]], [TRUCK], track_cov=10.0).rows.size == 1
    assert _gate([[0, 0]], [CAR], [[3.0, 0]], [CAR], track_cov=10.0).rows.size == 0


def test_area_gate_rejects_a_pedestrian_sized_car_and_a_bus_sized_car() -> None:
    assert _gate([[0, 0]], [CAR], [[0.1, 0]], [CAR], det_area=[2.0]).rows.size == 0  # < 3.6
    assert _gate([[0, 0]], [CAR], [[0.1, 0]], [CAR], det_area=[20.0]).rows.size == 0  # > 12.1
    assert _gate([[0, 0]], [CAR], [[0.1, 0]], [CAR], det_area=[8.6]).rows.size == 1


def test_heading_gate_ignores_front_back_flips_only() -> None:
    ok_flip = _gate([[0, 0]], [CAR], [[0.1, 0]], [CAR], track_yaw=[0.0], det_yaw=[np.pi - 0.2])
    sideways = _gate([[0, 0]], [CAR], [[0.1, 0]], [CAR], track_yaw=[0.0], det_yaw=[np.pi / 2])
    assert ok_flip.rows.size == 1 and sideways.rows.size == 0
    # pedestrians: max_rad > pi disables the gate
    assert _gate([[0, 0]], [PED], [[0.1, 0]], [PED], det_area=[0.4], det_yaw=[np.pi / 2]).rows.size == 1


def test_mahalanobis_gate_at_3_035_on_track_or_innovation_covariance() -> None:
    # track sigma 0.2 m, detection sigma 0.2 m, 0.75 m away: 3.75 sigma on the track alone, 2.65 on both
    kw = dict(track_cov=0.04, det_cov=0.04)
    assert _gate([[0, 0]], [CAR], [[0.75, 0]], [CAR], use_innovation=False, **kw).rows.size == 0
    assert _gate([[0, 0]], [CAR], [[0.75, 0]], [CAR], use_innovation=True, **kw).rows.size == 1
    # the floor widens an over-confident gate
    tight = dict(track_cov=0.001, det_cov=0.001)
    assert _gate([[0, 0]], [CAR], [[0.3, 0]], [CAR], **tight).rows.size == 0
    assert _gate([[0, 0]], [CAR], [[0.3, 0]], [CAR], gate_min_variance=0.04, **tight).rows.size == 1


def test_assignment_is_optimal_not_greedy() -> None:
    """Greedy would give track 0 its best detection (0) and leave track 1 without any; the optimum serves both."""
    c = Candidates(rows=np.array([0, 0, 1]), cols=np.array([0, 1, 0]), score=np.array([0.9, 0.8, 0.85]),
                   dist=np.zeros(3), mahalanobis=np.zeros(3))
    rows, cols = assign(2, 2, c)
    assert dict(zip(rows.tolist(), cols.tolist())) == {0: 1, 1: 0}


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.integers(1, 6), st.integers(1, 6), st.data())
def test_assignment_matches_brute_force(n: int, m: int, data: st.DataObject) -> None:
    mask = data.draw(arrays(bool, (n, m)))
    scores = data.draw(arrays(float, (n, m), elements=st.floats(0.01, 1.0)))
    rows, cols = np.nonzero(mask)
    c = Candidates(rows=rows, cols=cols, score=scores[rows, cols], dist=np.zeros(rows.size),
                   mahalanobis=np.zeros(rows.size))
    r, k = assign(n, m, c)
    assert len(set(r.tolist())) == r.size and len(set(k.tolist())) == k.size
    assert all(mask[a, b] for a, b in zip(r, k))
    got = float(scores[r, k].sum())
    best = 0.0
    for perm in itertools.permutations(range(max(n, m)), n):
        s = sum(scores[i, j] for i, j in enumerate(perm) if j < m and mask[i, j])
        best = max(best, s)
    assert got == pytest.approx(best)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(arrays(float, st.tuples(st.integers(0, 30), st.just(2)), elements=st.floats(-20, 20)),
       arrays(float, st.tuples(st.integers(0, 30), st.just(2)), elements=st.floats(-20, 20)),
       st.floats(0.1, 10))
def test_near_pairs_finds_exactly_the_pairs_within_the_square(a: np.ndarray, b: np.ndarray, r: float) -> None:
    i, j = near_pairs(a, b, r)
    got = set(zip(i.tolist(), j.tolist()))
    want = {(p, q) for p in range(len(a)) for q in range(len(b))
            if abs(a[p, 0] - b[q, 0]) <= r and abs(a[p, 1] - b[q, 1]) <= r}
    assert got == want


def test_overlapping_tracks_keep_the_one_with_more_hits() -> None:
    pos = np.array([[0.0, 0.0], [0.5, 0.0], [10.0, 0.0], [10.0, 0.9]])
    label = np.array([CAR, CAR, PED, PED])
    width = np.array([1.9, 1.9, 0.6, 0.6])
    hits = np.array([3, 20, 10, 10])
    drop = overlapping(pos, label, width, hits, TABLES.can_assign, 0.75)
    # the two cars 0.5 m apart are one object (keep the 20-hit one); pedestrians 0.9 m apart are two
    assert drop.tolist() == [True, False, False, False]


def test_a_tentative_track_never_removes_a_confirmed_one() -> None:
    """Of two overlapping tracks the one with fewer hits goes, unless it is confirmed and the other is not (a
    recurring clutter return that stays tentative gathers hits); a confirmed one still removes a tentative one,
    and two tentative ones still merge."""
    pos = np.array([[0.0, 0.0], [0.5, 0.0], [10.0, 0.0], [10.5, 0.0], [20.0, 0.0], [20.5, 0.0]])
    label = np.full(6, CAR)
    width = np.full(6, 1.9)
    hits = np.array([50, 10, 10, 50, 50, 10])
    confirmed = np.array([False, True, True, False, False, False])
    drop = overlapping(pos, label, width, hits, TABLES.can_assign, 0.75, confirmed=confirmed)
    assert drop.tolist() == [False, False, False, False, False, True]
    both = overlapping(pos, label, width, hits, TABLES.can_assign, 0.75, confirmed=np.ones(6, dtype=bool))
    assert both.tolist() == [False, True, True, False, False, True]


def test_overlap_needs_compatible_labels() -> None:
    pos = np.array([[0.0, 0.0], [0.2, 0.0]])
    drop = overlapping(pos, np.array([CAR, PED]), np.array([1.9, 0.6]), np.array([5, 1]), TABLES.can_assign, 0.75)
    assert not drop.any()


# ---- bird's-eye IoU and Autoware's IoU rule for overlapped tracks


def _grid_iou(a, b, n: int = 4000) -> float:
    """An independent IoU, integrated over x: each rectangle cuts the vertical line at x in an interval of y,
    exact (two slabs, |along| <= length/2 and |across| <= width/2, each linear in y), so only the midpoint rule
    over ``n`` columns approximates. (Counting grid points had been 4 % off for a box 0.31 m wide, and the
    property's examples depend on what the test run had imported before.)"""
    ext = max(a[2], a[3], b[2], b[3])
    lo, hi = min(a[0], b[0]) - ext, max(a[0], b[0]) + ext
    step = (hi - lo) / n
    px = lo + step * (np.arange(n) + 0.5)

    def interval(r):
        cx, cy, ln, wd, yaw = r
        c, s = math.cos(yaw), math.sin(yaw)
        y0, y1 = np.full(n, -np.inf), np.full(n, np.inf)
        # along = c dx + s dy, across = -s dx + c dy, dy = y - cy: each |k0 + k1 dy| <= half
        for k0, k1, half in ((c * (px - cx), s, ln / 2), (-s * (px - cx), c, wd / 2)):
            if abs(k1) < 1e-12:
                out = np.abs(k0) > half
                y0, y1 = np.where(out, np.inf, y0), np.where(out, -np.inf, y1)
            else:
                e0, e1 = (-half - k0) / k1, (half - k0) / k1
                y0, y1 = np.maximum(y0, np.minimum(e0, e1) + cy), np.minimum(y1, np.maximum(e0, e1) + cy)
        return y0, y1

    (a0, a1), (b0, b1) = interval(a), interval(b)
    la, lb = np.maximum(a1 - a0, 0.0), np.maximum(b1 - b0, 0.0)
    inter = np.maximum(np.minimum(a1, b1) - np.maximum(a0, b0), 0.0)
    union = (la + lb - inter).sum()
    return float(inter.sum() / union) if union > 0 else 0.0


def _iou1(a, b) -> float:
    return float(rect_iou(tuple(np.array([v]) for v in a), tuple(np.array([v]) for v in b))[0])


def test_rect_iou_exact_cases() -> None:
    car = (0.0, 0.0, 4.5, 1.9, 0.3)
    assert _iou1(car, car) == pytest.approx(1.0)
    assert _iou1(car, (10.0, 0.0, 4.5, 1.9, 0.3)) == 0.0
    # the same footprint shifted half a length along its axis: overlap 2.25 x 1.9 of a union of 3 halves
    half = (math.cos(0.3) * 2.25, math.sin(0.3) * 2.25, 4.5, 1.9, 0.3)
    assert _iou1(car, half) == pytest.approx(1.0 / 3.0)
    # a unit square and the same square turned 45°: they share an octagon of area 2(√2 - 1) = 0.828
    inter = 2.0 * (math.sqrt(2.0) - 1.0)
    assert _iou1((0, 0, 1, 1, 0), (0, 0, 1, 1, math.pi / 4)) == pytest.approx(inter / (2.0 - inter))
    # a box flipped by 180° is the same footprint
    assert _iou1(car, (0.0, 0.0, 4.5, 1.9, 0.3 + math.pi)) == pytest.approx(1.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=2, max_size=2), st.floats(0.3, 6), st.floats(0.3, 3), st.floats(-4, 4),
       st.floats(0.3, 6), st.floats(0.3, 3), st.floats(-4, 4))
def test_rect_iou_matches_a_grid_count(c, la, wa, ya, lb, wb, yb) -> None:
    a, b = (0.0, 0.0, la, wa, ya), (c[0], c[1], lb, wb, yb)
    assert _iou1(a, b) == pytest.approx(_grid_iou(a, b), abs=0.005)


def test_a_second_box_off_a_cars_centre_is_one_object_by_iou() -> None:
    """Two car tracks 2 m apart along their axis: the centre rule (0.75 x width = 1.4 m) misses them, their
    footprints overlap with IoU 0.38 > 0.1, so the one with fewer hits goes; 2.5 m sideways they do not touch."""
    pos = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.5]])
    label = np.array([CAR, CAR, CAR])
    width, length = np.full(3, 1.9), np.full(3, 4.5)
    hits = np.array([30, 4, 4])
    assert not overlapping(pos, label, width, hits, TABLES.can_assign, 0.75).any()  # the centre rule alone
    drop = overlapping(pos, label, width, hits, TABLES.can_assign, 0.75, yaw=np.zeros(3), length=length,
                       min_iou=0.1, min_iou_unknown=0.001)
    assert drop.tolist() == [False, True, False]


def test_iou_rule_crosses_labels_drops_unknown_first_and_can_be_switched_off() -> None:
    pos = np.array([[0.0, 0.0], [2.0, 0.0]])
    width, length, yaw = np.full(2, 1.9), np.full(2, 4.5), np.zeros(2)
    kw = dict(yaw=yaw, length=length, min_iou=0.1, min_iou_unknown=0.001)
    # one footprint, two classes the can-assign matrix keeps apart: the IoU rule still applies (fewer hits go)
    drop = overlapping(pos, np.array([CAR, PED]), width, np.array([30, 2]), TABLES.can_assign, 0.75, **kw)
    assert drop.tolist() == [False, True]
    # an UNKNOWN box goes whatever its hits, and at the UNKNOWN bound (IoU 0.001): 4.4 m apart the boxes touch
    far = np.array([[0.0, 0.0], [4.4, 0.0]])
    drop = overlapping(far, np.array([UNKNOWN, TRUCK]), width, np.array([30, 2]), TABLES.can_assign, 0.75, **kw)
    assert drop.tolist() == [True, False]
    drop = overlapping(far, np.array([CAR, TRUCK]), width, np.array([30, 2]), TABLES.can_assign, 0.75, **kw)
    assert not drop.any()  # IoU 0.01 < 0.1 between two classified boxes
    # min_iou 0 switches the rule off
    drop = overlapping(pos, np.array([CAR, CAR]), width, np.array([30, 2]), TABLES.can_assign, 0.75,
                       yaw=yaw, length=length, min_iou=0.0, min_iou_unknown=0.0)
    assert not drop.any()
