"""Metrics of the offline evaluator: AP, PR ties, operating-point rates, matching, label mapping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitterguard.eval.groundtruth import group_of, is_dynamic, nuscenes_label
from jitterguard.eval.metrics import (
    TrackBootstrap,
    alpha_from_labels,
    group_metrics,
    alpha_sweep,
    attribute_metrics,
    average_precision,
    compute_metrics,
    ghost_metrics,
    matched_metrics,
    planner_metrics,
    pr_curve,
    rate,
    time_to_first_correct,
    weighted_average_precision,
)
from jitterguard.eval.pipeline import Records, match_tracks
from jitterguard.services.classifier.core import DYNAMIC, STATIC, UNDECIDED


def test_ap_of_perfect_score_is_one() -> None:
    pos = np.array([0, 1, 0, 1, 1, 0], bool)
    assert average_precision(pos.astype(float) * 3 + 0.5, pos) == pytest.approx(1.0)


def test_ap_of_reversed_score_is_low() -> None:
    rng = np.random.default_rng(0)
    pos = rng.random(400) < 0.3
    score = np.where(pos, 0.0, 1.0) + 0.01 * rng.random(400)
    ap = average_precision(score, pos)
    assert ap < 0.35  # near the base rate, far from 1
    assert average_precision(-score, pos) == pytest.approx(1.0)


def test_ap_matches_hand_computation() -> None:
    # ranks: P N P N  -> precision at positives 1/1 and 2/3 -> AP = (1 + 2/3) / 2
    assert average_precision([4, 3, 2, 1], [1, 0, 1, 0]) == pytest.approx((1 + 2 / 3) / 2)


def test_tied_scores_get_no_credit_for_order() -> None:
    # a constant score cannot separate anything: AP equals the positive rate whichever way rows are ordered
    assert average_precision([1, 1, 1, 1], [1, 0, 0, 0]) == pytest.approx(0.25)
    assert average_precision([1, 1, 1, 1], [0, 0, 0, 1]) == pytest.approx(0.25)
    p, r, t = pr_curve([2, 1, 1], [1, 0, 1])
    assert t.tolist() == [2, 1] and r.tolist() == [0.5, 1.0]


def test_ap_undefined_without_positives() -> None:
    assert math.isnan(average_precision([0.3, 0.2], [0, 0]))


def test_rate_counts_only_masked_rows() -> None:
    d = np.array([DYNAMIC, STATIC, DYNAMIC, UNDECIDED])
    assert rate(d, [1, 1, 0, 0], DYNAMIC) == 0.5
    assert math.isnan(rate(d, [0, 0, 0, 0], DYNAMIC))


def test_match_tracks_is_optimal_and_gated() -> None:
    gt = np.array([[0.0, 0.0], [1.5, 0.0]])
    # track 0 sits at 1.0: greedy would give it gt 0 (1.0 m) and leave track 1 (at -0.4) only gt 1 (1.9 m)
    tracks = np.array([[1.0, 0.0], [-0.4, 0.0], [50.0, 0.0]])
    m = match_tracks(tracks, gt, 2.0)
    assert m.tolist() == [1, 0, -1]
    assert match_tracks(np.array([[3.0, 0.0]]), gt, 1.0).tolist() == [-1]
    assert match_tracks(np.empty((0, 2)), gt).tolist() == []


@pytest.mark.parametrize(("attr", "moving", "want"), [
    ("vehicle.moving", False, True), ("vehicle.parked", True, False), ("vehicle.stopped", False, False),
    ("pedestrian.moving", False, True), ("pedestrian.standing", True, False),
    ("pedestrian.sitting_lying_down", False, False), ("cycle.without_rider", True, False),
    ("cycle.with_rider", True, True), ("cycle.with_rider", False, False), ("", True, True),
])
def test_attribute_mapping(attr: str, moving: bool, want: bool) -> None:
    assert is_dynamic(attr, moving) is want


def test_groups_and_nuscenes_labels() -> None:
    # vehicles are issue 15's car, truck, bus, trailer; a motorcycle (5) is scored with the cycles
    assert [group_of(x) for x in (1, 2, 3, 4, 5, 6, 7, 0)] == [
        "vehicle"] * 4 + ["bicycle", "bicycle", "pedestrian", None]
    assert nuscenes_label("human.pedestrian.child") == 7
    assert nuscenes_label("vehicle.construction") == 2  # a truck: it had been dropped, a track on it a ghost
    assert nuscenes_label("vehicle.bus.bendy") == 3
    assert nuscenes_label("movable_object.barrier") is None


def _records(**kw: object) -> Records:
    n = len(kw["z"])  # type: ignore[arg-type]
    base = dict(t_s=np.arange(n) * 0.1, seq=np.arange(n), track_id=np.array(["a"] * n), label=np.ones(n, np.int64),
                speed=np.zeros(n), window=np.full(n, 5), state_z=np.full(n, STATIC, np.int8),
                state_v=np.full(n, STATIC, np.int8), gt_instance=np.zeros(n, np.int64),
                gt_dynamic=np.zeros(n, bool), group=np.array(["vehicle"] * n), alpha=np.full(n, 1.96),
                velocity_threshold=1.0, min_window=2)
    base.update({k: np.asarray(v) if isinstance(v, list) else v for k, v in kw.items()})
    return Records(**base)  # type: ignore[arg-type]


def test_time_to_first_correct() -> None:
    rec = _records(z=[0, 0, 0, 0], gt_dynamic=[True] * 4,
                   state_z=np.array([UNDECIDED, STATIC, DYNAMIC, DYNAMIC], np.int8))
    assert time_to_first_correct(rec, rec.state_z).tolist() == pytest.approx([0.2])
    assert math.isnan(time_to_first_correct(rec, rec.state_v)[0])  # never dynamic


def test_time_to_dynamic_counts_from_the_first_moving_row() -> None:
    # one track: its object stands for three rows, then moves; the z-test says dynamic one row after it
    # starts, the threshold three rows after; a second track on a moving object is never called dynamic by the
    # threshold. Static rows called dynamic early must not count as catching the motion.
    moving = [False, False, False, True, True, True, True, True, True]
    rec = _records(z=[0.0] * 9, track_id=["a"] * 7 + ["b"] * 2, gt_instance=[0] * 7 + [1] * 2,
                   gt_dynamic=moving,
                   state_z=np.array([DYNAMIC, STATIC, STATIC, STATIC, DYNAMIC, DYNAMIC, DYNAMIC, DYNAMIC, DYNAMIC],
                                    np.int8),
                   state_v=np.array([STATIC] * 6 + [DYNAMIC] + [STATIC] * 2, np.int8))
    m = compute_metrics(rec, intervals=False)["vehicle"]
    # track a: first moving row at t 0.3, z dynamic at 0.4 (0.1 s), speed at 0.6 (0.3 s); track b: z at once
    assert m["time_to_dynamic_s_median_z"] == pytest.approx(0.05)
    assert m["time_to_dynamic_s_median_speed"] == pytest.approx(0.3)
    assert m["never_dynamic_fraction_z"] == 0.0
    assert m["never_dynamic_fraction_speed"] == 0.5
    # the older figure counts static rows too: track a is first correct when called static at 0.1 s
    assert m["time_to_first_correct_s_median_z"] == pytest.approx(0.05)


def test_group_metrics_and_sweep() -> None:
    dyn = np.array([False, False, True, True])
    rec = _records(z=[0.5, 3.0, 5.0, 1.0], speed=[0.2, 1.5, 4.0, 2.0], gt_dynamic=dyn,
                   state_z=np.array([STATIC, DYNAMIC, DYNAMIC, STATIC], np.int8),
                   state_v=np.array([STATIC, DYNAMIC, DYNAMIC, DYNAMIC], np.int8))
    m = compute_metrics(rec)["vehicle"]
    assert (m["n_static"], m["n_dynamic"]) == (2, 2)
    assert m["false_dynamic_z"] == 0.5 and m["missed_dynamic_z"] == 0.5
    assert m["false_dynamic_speed"] == 0.5 and m["missed_dynamic_speed"] == 0.0
    assert m["ap_speed"] == pytest.approx(1.0)
    assert m["ap_z"] < 1.0
    sw = alpha_sweep(rec, "vehicle", [0.0, 10.0])
    assert sw["false_dynamic"] == [1.0, 0.0] and sw["missed_dynamic"] == [0.0, 1.0]
    a = alpha_from_labels(rec, "vehicle", max_missed=0.0)
    assert a is not None and a < 1.0 and np.mean(rec.z[dyn] <= a) == 0.0


def test_ap_agrees_with_scikit_learn_including_ties() -> None:
    sk = pytest.importorskip("sklearn.metrics")
    rng = np.random.default_rng(1)
    for _ in range(3):
        y = rng.random(300) < 0.3
        s = np.round(rng.random(300) + 0.3 * y, 2)  # rounding makes ties
        assert average_precision(s, y) == pytest.approx(sk.average_precision_score(y, s), abs=1e-12)


def test_ap_is_null_without_static_or_without_dynamic_rows() -> None:
    """A group with only dynamic rows gets AP null, not a free 1.0; its false-dynamic rate is null too."""
    only_dyn = _records(z=[1.0, 2.0], speed=[2.0, 3.0], gt_dynamic=[True, True])
    m = compute_metrics(only_dyn)["vehicle"]
    assert m["ap_z"] is None and m["ap_speed"] is None and m["false_dynamic_z"] is None
    assert m["missed_dynamic_z"] == 1.0 and m["ci90"]["ap_z"] is None and m["ci90"]["false_dynamic_z"] is None
    only_static = _records(z=[1.0, 2.0], speed=[2.0, 3.0])
    m = compute_metrics(only_static)["vehicle"]
    assert m["ap_z"] is None and m["missed_dynamic_z"] is None and m["false_dynamic_z"] == 0.0


def test_ghost_tracks_are_scored_as_static_by_their_own_label() -> None:
    """Rows matched to no object count for the group of the track's label; dynamic there is a false alarm."""
    rec = _records(z=[0, 0, 0, 0, 0], gt_instance=[-1, -1, -1, -1, 3], group=["", "", "", "", "vehicle"],
                   label=[1, 1, 1, 7, 1], state_z=np.array([DYNAMIC, STATIC, STATIC, DYNAMIC, DYNAMIC], np.int8),
                   state_v=np.array([DYNAMIC, DYNAMIC, STATIC, DYNAMIC, DYNAMIC], np.int8),
                   track_group=["vehicle", "vehicle", "vehicle", "pedestrian", "vehicle"],
                   track_id=["g1", "g1", "g2", "p", "real"])
    v = ghost_metrics(rec, "vehicle")
    assert (v["n"], v["n_tracks"]) == (3, 2)
    assert v["false_dynamic_z"] == pytest.approx(1 / 3) and v["false_dynamic_speed"] == pytest.approx(2 / 3)
    p = ghost_metrics(rec, "pedestrian")
    assert p["n"] == 1 and p["false_dynamic_z"] == 1.0
    assert ghost_metrics(rec, "bicycle")["false_dynamic_z"] is None


def test_matched_compares_at_equal_false_alarms() -> None:
    """Speed rule: 1 of 4 static rows above its threshold (FD 0.25). The z-test at that FD (its 2nd-highest
    static z sets the cut) misses the dynamic rows at or below it."""
    z = [0.1, 0.2, 0.3, 5.0, 0.25, 4.0, 6.0]
    speed = [0.1, 0.2, 2.0, 0.3, 0.5, 3.0, 3.0]
    dyn = [False, False, False, False, True, True, True]
    rec = _records(z=z, speed=speed, gt_dynamic=dyn,
                   state_z=np.where(np.array(z) > 1.96, DYNAMIC, STATIC).astype(np.int8),
                   state_v=np.where(np.array(speed) > 1.0, DYNAMIC, STATIC).astype(np.int8))
    m = matched_metrics(rec, "vehicle")
    assert m["false_dynamic_speed"] == 0.25 and m["false_dynamic_z"] == 0.25
    # z cut at the 2nd-highest static z (0.3): dynamic z 0.25 is missed, 4 and 6 caught
    assert m["missed_dynamic_z_at_speed_false_dynamic"] == pytest.approx(1 / 3)
    # speed cut (normalised by 1 m/s) at the 2nd-highest static speed (0.3): 0.5, 3, 3 all caught
    assert m["missed_dynamic_speed_at_z_false_dynamic"] == 0.0


def test_attributes_split_the_rates() -> None:
    rec = _records(z=[0, 0, 0, 0], gt_dynamic=[False, False, True, True],
                   gt_attribute=["vehicle.parked", "vehicle.parked", "vehicle.moving", "vehicle.moving"],
                   state_z=np.array([DYNAMIC, STATIC, STATIC, DYNAMIC], np.int8),
                   state_v=np.array([STATIC, STATIC, DYNAMIC, DYNAMIC], np.int8))
    a = attribute_metrics(rec)
    assert set(a) == {"vehicle.parked", "vehicle.moving"}
    assert a["vehicle.parked"]["false_dynamic_z"] == 0.5 and a["vehicle.parked"]["missed_dynamic_z"] is None
    assert a["vehicle.moving"]["missed_dynamic_z"] == 0.5 and a["vehicle.moving"]["missed_dynamic_speed"] == 0.0
    assert set(planner_metrics(rec)) == {"ghost", "matched", "by_attribute", "full_window"}


def test_bootstrap_intervals_resample_whole_tracks() -> None:
    """Two tracks, one always wrong, one always right: every resample's rate is 0, ½ or 1 (rows of a track
    move together), and the 90 % interval spans from 0 to 1; a single track's rate gets none — its resamples all
    repeat it, and a point interval [0.6, 0.6] (as before 6 Dec) claimed a certainty one track cannot give."""
    n = 40
    rec = _records(z=np.zeros(n), track_id=np.array(["a"] * 20 + ["b"] * 20),
                   state_z=np.array([DYNAMIC] * 20 + [STATIC] * 20, np.int8))
    boot = TrackBootstrap(rec.track_id, resamples=400, seed=1)
    hit = rec.state_z == DYNAMIC
    lo, hi = boot.rate(np.ones(n, bool), hit)
    assert (lo, hi) == (0.0, 1.0)
    one = TrackBootstrap(np.array(["a"] * 5))
    assert one.rate(np.ones(5, bool), np.array([True, False, True, False, True])) is None


def test_a_rate_of_zero_or_one_gets_the_exact_interval_over_its_tracks() -> None:
    """0 of 55 rows on 13 tracks: every resample is 0, and [0, 0] had said the rate is surely 0; the exact
    (Clopper–Pearson) 90 % interval counting tracks bounds it below 1 − 0.05^(1/13) ≈ 0.206 instead."""
    ids = np.array([f"t{i % 13}" for i in range(55)])
    boot = TrackBootstrap(ids, resamples=400, seed=1)
    mask = np.ones(55, bool)
    assert boot.rate(mask, np.zeros(55, bool)) == [0.0, round(1 - 0.05 ** (1 / 13), 6)]
    assert boot.rate(mask, np.ones(55, bool)) == [round(0.05 ** (1 / 13), 6), 1.0]
    part = ids == "t0"  # a group of one track: the widest interval, 90 % of the way
    assert boot.rate(part, np.zeros(55, bool)) == [0.0, 0.95]


def test_weighted_ap_matches_repeated_rows() -> None:
    rng = np.random.default_rng(2)
    s, y = rng.random(50), rng.random(50) < 0.4
    w = rng.integers(0, 4, 50)
    rep_s, rep_y = np.repeat(s, w), np.repeat(y, w)
    assert weighted_average_precision(s, y, w) == pytest.approx(average_precision(rep_s, rep_y), abs=1e-12)


def test_a_bootstrap_resample_without_a_static_row_has_no_ap() -> None:
    """One static track (z 5) and one moving (z 1): AP 0.5, and a resample holding only the moving track has no
    AP — it had counted as 1.0 and lifted the interval's upper end to 1."""
    from jitterguard.eval.metrics import weighted_average_precision

    z = np.array([5.0] * 5 + [1.0] * 5)
    dyn = np.array([False] * 5 + [True] * 5)
    assert weighted_average_precision(z, dyn, np.ones(10)) == pytest.approx(0.5)
    assert math.isnan(weighted_average_precision(z, dyn, np.r_[np.zeros(5), np.ones(5)]))
    m = group_metrics(_records(z=z, gt_dynamic=dyn, track_id=np.array(["s"] * 5 + ["d"] * 5)), "vehicle",
                      TrackBootstrap(np.array(["s"] * 5 + ["d"] * 5)))
    # every resample with an AP gives 0.5: no interval (a point [0.5, 0.5] had claimed a certainty two tracks lack)
    assert m["ap_z"] == pytest.approx(0.5) and m["ci90"]["ap_z"] is None


def test_a_perfect_ap_from_a_few_tracks_gets_the_exact_lower_bound_not_a_point() -> None:
    """Three tracks ranked perfectly: every resample's AP is 1, and [1.0, 1.0] had claimed certainty; the bound
    with the tracks as trials (as for a rate of 1) is 0.05^(1/3) ≈ 0.368."""
    z = np.array([0.0] * 5 + [5.0] * 5 + [6.0] * 5)
    dyn = np.array([False] * 5 + [True] * 10)
    ids = np.array(["s"] * 5 + ["d1"] * 5 + ["d2"] * 5)
    m = group_metrics(_records(z=z, gt_dynamic=dyn, track_id=ids), "vehicle", TrackBootstrap(ids))
    assert m["ap_z"] == pytest.approx(1.0) and m["ci90"]["ap_z"] == [round(0.05 ** (1 / 3), 6), 1.0]


def test_latency_is_timed_from_the_pairs_first_row_after_an_id_switch() -> None:
    """Track t follows moving object 1 for 1 s, never called dynamic, then switches to moving object 2 and is
    called dynamic at once: the pair (t, 2) took 0 s, not the track's 1 s."""
    n = 20
    state = np.full(n, STATIC, np.int8)
    state[10:] = DYNAMIC
    rec = _records(z=np.zeros(n), gt_dynamic=np.ones(n, bool), gt_instance=np.r_[np.ones(10), np.full(10, 2)]
                   .astype(np.int64), state_z=state)
    got = time_to_first_correct(rec, rec.state_z)
    assert math.isnan(got[0]) and got[1] == 0.0


def test_alpha_from_labels_is_none_where_no_positive_alpha_keeps_the_misses_down() -> None:
    """Three of 20 moving rows at z 0 (vetoed): no alpha > 0 misses at most 5 % — it had returned -5e-324."""
    z = np.r_[np.zeros(3), np.linspace(1, 10, 17)]
    assert alpha_from_labels(_records(z=z, gt_dynamic=np.ones(20, bool)), "vehicle") is None
