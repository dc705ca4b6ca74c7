"""Detection AP (hand-computed nuScenes cases), filtering, positional calibration, recalibration, report, plots."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from jitterguard.services.detector.config import CLASS_NAMES, Detections3D, Sample
from jitterguard.services.detector.evaluate import (
    Recalibration,
    apply_recalibration,
    calibration,
    calibration_from_residuals,
    detection_ap,
    devkit_mean_ap,
    evaluation_report,
    fit_recalibration,
    greedy_match,
    matched_residuals,
    score_order,
)
from jitterguard.services.detector.plots import calibration_plot, pr_plot

CAR, TRUCK, BUS, BICYCLE, PED = range(5)


def boxes(xy: list[tuple[float, float]] | np.ndarray) -> np.ndarray:
    a = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out = np.zeros((len(a), 9), np.float32)
    out[:, :2] = a
    out[:, 3:6] = (4.5, 1.9, 1.6)
    return out


def gt(xy, labels, num_points=None, token: str = "") -> Sample:
    lab = np.asarray(labels, np.int64).reshape(-1)
    pts = np.full(len(lab), 50, np.int64) if num_points is None else np.asarray(num_points, np.int64)
    return Sample(np.zeros((0, 4), np.float32), boxes(xy), lab, pts, token)


def det(xy, scores, labels, logvar=None) -> Detections3D:
    lab = np.asarray(labels, np.int64).reshape(-1)
    lv = None if logvar is None else np.asarray(logvar, np.float32).reshape(len(lab), 5)
    return Detections3D(boxes(xy), np.asarray(scores, np.float32).reshape(-1), lab, lv)


def ap_of(result, cls: str = "car", th: str = "2") -> float:
    return result["classes"][cls]["ap"][th]


# ------------------------------------------------------------------ AP by hand


def test_perfect_predictions_score_one() -> None:
    xy = [(5.0, 0.0), (10.0, 3.0), (-20.0, 7.0)]
    r = detection_ap([det(xy, [0.9, 0.8, 0.7], [CAR] * 3)], [gt(xy, [CAR] * 3)])
    car = r["classes"]["car"]
    assert all(v == pytest.approx(1.0) for v in car["ap"].values())
    assert car["mean_ap"] == pytest.approx(1.0) and r["mAP"] == pytest.approx(1.0)
    assert (car["tp"], car["fp"], car["fn"]) == (3, 0, 0)
    # classes without ground truth are undefined, not 0; the devkit would count them as 0
    assert math.isnan(r["classes"]["bus"]["mean_ap"])
    assert devkit_mean_ap(r) == pytest.approx(1.0 / 5)


def test_far_predictions_score_zero() -> None:
    r = detection_ap([det([(5.0 + 4.5, 0.0), (30.0, 30.0)], [0.9, 0.8], [CAR, CAR])], [gt([(5.0, 0.0)], [CAR])])
    assert all(v == 0.0 for v in r["classes"]["car"]["ap"].values())
    assert (r["classes"]["car"]["tp"], r["classes"]["car"]["fp"], r["classes"]["car"]["fn"]) == (0, 2, 1)


def test_known_ordering_by_hand() -> None:
    # scores: FP 0.9, TP 0.8, TP 0.7 over 2 GT → precision [0, 1/2, 2/3] at recall [0, 1/2, 1].
    # Linear interpolation: p(r) = r on [0, .5], p(r) = .5 + (r − .5)/3 on [.5, 1].
    # AP = Σ_{i=11}^{100} max(p(i/100) − .1, 0) / 90 / .9
    #    = [Σ_{i=11}^{50} (i/100 − .1) + Σ_{i=51}^{100} (.4 + (i/100 − .5)/3)] / 81
    #    = [(12.2 − 4) + (20 + (37.75 − 25)/3)] / 81 = 32.45 / 81
    g = gt([(10.0, 0.0), (20.0, 0.0)], [CAR, CAR])
    d = det([(30.0, 0.0), (10.1, 0.0), (20.0, 0.2)], [0.9, 0.8, 0.7], [CAR] * 3)
    r = detection_ap([d], [g])
    assert ap_of(r, th="2") == pytest.approx(32.45 / 81, abs=1e-12)
    assert ap_of(r, th="0.5") == pytest.approx(32.45 / 81, abs=1e-12)
    assert r["classes"]["car"]["precision"]["2"][50] == pytest.approx(0.5)
    assert r["classes"]["car"]["precision"]["2"][100] == pytest.approx(2 / 3)


def test_distance_threshold_is_strict_and_per_threshold() -> None:
    g = gt([(10.0, 0.0)], [CAR])
    r = detection_ap([det([(10.0, 0.75)], [0.5], [CAR])], [g])
    assert r["classes"]["car"]["ap"] == pytest.approx({"0.5": 0.0, "1": 1.0, "2": 1.0, "4": 1.0})
    assert r["classes"]["car"]["mean_ap"] == pytest.approx(0.75)
    r = detection_ap([det([(11.0, 0.0)], [0.5], [CAR])], [g])  # exactly 1 m: not < 1
    assert r["classes"]["car"]["ap"]["1"] == 0.0 and r["classes"]["car"]["ap"]["2"] == pytest.approx(1.0)


def test_greedy_takes_next_nearest_untaken_box() -> None:
    # GT at 0 and 1.5 m; the higher score takes GT0, the lower one (0.2 m from GT0) falls to GT1 at 1.3 m
    g = gt([(10.0, 0.0), (11.5, 0.0)], [CAR, CAR])
    d = det([(10.1, 0.0), (10.2, 0.0)], [0.9, 0.8], [CAR, CAR])
    r = detection_ap([d], [g])
    car = r["classes"]["car"]
    assert car["ap"]["0.5"] < 1.0 and car["ap"]["1"] < 1.0
    assert car["ap"]["2"] == pytest.approx(1.0) and car["ap"]["4"] == pytest.approx(1.0)
    assert (car["tp"], car["fp"]) == (2, 0)
    # reversed scores: the 10.2 m prediction now goes first and takes GT0 (0.2 m), 10.1 m takes GT1 (1.4 m)
    m = greedy_match(np.zeros(2, np.int64), np.array([[10.2, 0.0], [10.1, 0.0]]), np.zeros(2, np.int64),
                     np.array([[10.0, 0.0], [11.5, 0.0]]), [0.5, 2.0])
    assert m.tolist() == [[0, -1], [0, 1]]


def test_matching_is_per_sample_and_per_class() -> None:
    g = [gt([(10.0, 0.0)], [CAR]), gt([(10.0, 0.0)], [PED])]
    d = [det([(10.0, 0.0)], [0.9], [PED]), det([(10.0, 0.0)], [0.9], [CAR])]
    r = detection_ap(d, g)
    assert r["classes"]["car"]["tp"] == 0 and r["classes"]["pedestrian"]["tp"] == 0
    assert r["mAP"] == 0.0


def test_score_ties_break_like_the_devkit() -> None:
    # devkit: sorted((score, index))[::-1] → among equal scores the later index goes first
    assert score_order(np.array([0.5, 0.9, 0.5, 0.5])).tolist() == [1, 3, 2, 0]
    g = gt([(10.0, 0.0)], [CAR])
    d = det([(10.1, 0.0), (10.3, 0.0)], [0.5, 0.5], [CAR, CAR])
    m = matched_residuals([replace_lv(d)], [g])
    assert m.row.tolist() == [1]  # the later one took the box


def replace_lv(d: Detections3D) -> Detections3D:
    return Detections3D(d.boxes, d.scores, d.labels, np.zeros((len(d), 5), np.float32))


# ------------------------------------------------------------------ filters


def test_class_range_filters_ground_truth_and_predictions() -> None:
    # a pedestrian at 45 m is beyond its 40 m range: not a positive, and a prediction there is no FP;
    # a car at 45 m is inside its 50 m range and counts
    g = gt([(10.0, 0.0), (45.0, 0.0), (0.0, 45.0)], [PED, PED, CAR])
    d = det([(10.0, 0.0), (45.0, 0.0), (30.0, 30.0)], [0.5, 0.9, 0.95], [PED, PED, PED])
    r = detection_ap([d], [g])
    ped = r["classes"]["pedestrian"]
    assert ped["num_gt"] == 1 and ped["num_pred"] == 1 and ped["mean_ap"] == pytest.approx(1.0)
    assert r["classes"]["car"]["num_gt"] == 1 and r["classes"]["car"]["mean_ap"] == 0.0
    wide = detection_ap([d], [g], class_range=(50.0,) * 5)
    assert wide["classes"]["pedestrian"]["num_gt"] == 2 and wide["classes"]["pedestrian"]["num_pred"] == 3
    assert wide["classes"]["pedestrian"]["fp"] == 1


def test_min_points_drops_invisible_ground_truth() -> None:
    g = gt([(10.0, 0.0), (20.0, 0.0)], [CAR, CAR], num_points=[12, 0])
    d = det([(10.0, 0.0)], [0.8], [CAR])
    r = detection_ap([d], [g])
    assert r["classes"]["car"]["num_gt"] == 1 and r["classes"]["car"]["mean_ap"] == pytest.approx(1.0)
    r0 = detection_ap([d], [g], min_points=0)
    assert r0["classes"]["car"]["num_gt"] == 2 and r0["classes"]["car"]["mean_ap"] < 0.6
    # a prediction on the dropped box is a false positive, as in nuScenes
    r2 = detection_ap([det([(10.0, 0.0), (20.0, 0.0)], [0.8, 0.9], [CAR, CAR])], [g])
    assert r2["classes"]["car"]["fp"] == 1


def test_mismatched_lengths_and_bad_labels_are_rejected() -> None:
    with pytest.raises(ValueError, match="prediction sets"):
        detection_ap([], [gt([(1.0, 0.0)], [CAR])])
    with pytest.raises(ValueError, match="class index"):
        detection_ap([det([(1.0, 0.0)], [0.5], [7])], [gt([(1.0, 0.0)], [CAR])])


def test_empty_inputs() -> None:
    r = detection_ap([Detections3D.empty()], [gt(np.zeros((0, 2)), [])])
    assert math.isnan(r["mAP"])
    c = calibration([Detections3D.empty()], [gt(np.zeros((0, 2)), [])])
    assert c["num_matched"] == 0 and c["ece"] is not None and math.isnan(c["ece"])
    with pytest.raises(ValueError, match="no true positives"):
        fit_recalibration([Detections3D.empty()], [gt(np.zeros((0, 2)), [])])


# ------------------------------------------------------------------ calibration


def synthetic(rng: np.random.Generator, n_samples: int, sigma_scale: float = 1.0,
              sigma_range: tuple[float, float] = (0.05, 0.3)) -> tuple[list[Detections3D], list[Sample]]:
    """Cars on a 6 m grid (far apart next to the residuals), detected with x/y errors drawn with SD
    ``sigma_scale`` × the predicted SD; predicted SD log-uniform in ``sigma_range``."""
    g = np.arange(-27.0, 28.0, 6.0)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    dets, gts = [], []
    for _ in range(n_samples):
        sig = np.exp(rng.uniform(*np.log(sigma_range), size=(len(grid), 2)))
        xy = grid + rng.normal(size=grid.shape) * sig * sigma_scale
        lv = np.zeros((len(grid), 5))
        lv[:, :2] = np.log(sig ** 2)
        dets.append(det(xy, rng.uniform(0.2, 1.0, len(grid)), [CAR] * len(grid), lv))
        gts.append(gt(grid, [CAR] * len(grid)))
    return dets, gts


def test_calibrated_residuals_have_near_zero_ece() -> None:
    dets, gts = synthetic(np.random.default_rng(0), 200)
    c = calibration(dets, gts)
    assert c["num_matched"] == 200 * 100
    assert c["ece"] < 0.006  # ≈ sampling noise of the RMS in 2000-match bins
    for a in ("x", "y"):
        ax = c["axes"][a]
        assert sum(ax["bins"]["count"]) == 20000 and len(ax["bins"]["count"]) == 10
        assert ax["coverage_1sigma"] == pytest.approx(0.6827, abs=0.01)
        assert ax["coverage_2sigma"] == pytest.approx(0.9545, abs=0.006)
        assert ax["variance_ratio"] == pytest.approx(1.0, abs=0.03)
        assert np.all(np.diff(ax["bins"]["pred_sd"]) > 0)  # equal-count bins ordered by σ


def test_misscaled_residuals_show_large_ece_and_recalibration_fixes_it() -> None:
    rng = np.random.default_rng(1)
    val_d, val_g = synthetic(rng, 100, sigma_scale=2.0)
    test_d, test_g = synthetic(rng, 100, sigma_scale=2.0)
    before = calibration(test_d, test_g)
    # observed SD = 2 σ_pred → ECE ≈ E[σ_pred] ≈ 0.14 m; 68 % of |r| ≤ σ becomes P(|N(0,4)| ≤ 1) = 38 %
    assert before["ece"] > 0.1
    assert before["coverage_1sigma"] == pytest.approx(0.383, abs=0.015)
    rec = fit_recalibration(val_d, val_g)
    assert rec.score_edges == () and len(rec.scales) == 1
    sx, sy = rec.scales[0]
    assert sx == pytest.approx(4.0, rel=0.05) and sy == pytest.approx(4.0, rel=0.05)
    after = calibration([apply_recalibration(d, (sx, sy)) for d in test_d], test_g)
    assert after["ece"] < 0.01 < before["ece"] / 10
    assert after["nll"] < before["nll"]


def test_recalibration_is_per_axis_and_leaves_other_variances() -> None:
    d = det([(1.0, 2.0)], [0.5], [CAR], [[0.1, 0.2, 0.3, 0.4, 0.5]])
    out = apply_recalibration(d, (4.0, 0.25))
    assert out.log_variances is not None and d.log_variances is not None
    assert out.log_variances[0] == pytest.approx([0.1 + math.log(4), 0.2 - math.log(4), 0.3, 0.4, 0.5], abs=1e-6)
    assert d.log_variances[0, 0] == pytest.approx(0.1)  # input untouched
    with pytest.raises(ValueError):
        apply_recalibration(d, (0.0, 1.0))
    with pytest.raises(ValueError):
        apply_recalibration(det([(1.0, 2.0)], [0.5], [CAR]), (1.0, 1.0))


def test_ece_formula_on_a_hand_made_bin() -> None:
    # one bin: σ = 1 for both residuals, residuals ±2 → σ_obs = 2, σ_pred = 1 → ECE = 1
    r = np.array([[2.0, 1.0], [-2.0, -1.0]])
    c = calibration_from_residuals(r, np.zeros((2, 2)), num_bins=1)
    assert c["axes"]["x"]["ece"] == pytest.approx(1.0) and c["axes"]["y"]["ece"] == pytest.approx(0.0)
    assert c["ece"] == pytest.approx(0.5)
    assert c["axes"]["x"]["nll"] == pytest.approx(0.5 * math.log(2 * math.pi) + 2.0)
    assert c["axes"]["y"]["coverage_1sigma"] == 1.0 and c["axes"]["x"]["coverage_2sigma"] == 1.0


def test_uniform_bins_and_residual_matching_sign() -> None:
    d = det([(10.3, -0.2)], [0.9], [CAR], [[0.0] * 5])
    m = matched_residuals([d], [gt([(10.0, 0.0)], [CAR])])
    assert m.residual[0] == pytest.approx([0.3, -0.2], abs=1e-6)  # predicted − ground truth
    dets, gts = synthetic(np.random.default_rng(2), 20)
    c = calibration(dets, gts, binning="uniform", num_bins=5)
    b = c["axes"]["x"]["bins"]
    assert len(b["count"]) == 5 and sum(b["count"]) == 2000
    widths = np.asarray(b["sigma_hi"]) - np.asarray(b["sigma_lo"])
    assert widths.max() < 0.3 / 5 * 1.01  # equal-width bins over [0.05, 0.3]


def test_vanilla_detections_have_no_calibration() -> None:
    d, g = [det([(10.0, 0.0)], [0.9], [CAR])], [gt([(10.0, 0.0)], [CAR])]
    with pytest.raises(ValueError, match="vanilla"):
        calibration(d, g)
    rep = evaluation_report(d, g)
    assert rep["calibration"] is None and rep["summary"]["positional_ece"] is None


# ------------------------------------------------------------------ report and plots


def test_report_is_strict_json_and_plots_render(tmp_path) -> None:
    dets, gts = synthetic(np.random.default_rng(3), 10, sigma_scale=1.5)
    dets[0] = det(np.r_[dets[0].boxes[:, :2], [[3.0, 3.0]]], np.r_[dets[0].scores, 0.95], [CAR] * 101,
                  np.r_[dets[0].log_variances, np.zeros((1, 5))])
    rep = evaluation_report(dets, gts)
    text = json.dumps(rep, allow_nan=False)
    back = json.loads(text)
    assert back["summary"]["car_ap"] == pytest.approx(rep["detection"]["classes"]["car"]["mean_ap"])
    assert back["summary"]["bus_ap"] is None  # no bus ground truth: null, not NaN
    assert back["detection"]["classes"]["car"]["fp"] == 1
    assert "precision" not in back["detection"]["classes"]["car"]
    assert set(back["summary"]) == ({"mAP", "positional_ece", "nll", "coverage_1sigma", "num_matched"}
                                    | {f"{c}_ap" for c in CLASS_NAMES})
    assert back["summary"]["coverage_1sigma"] == pytest.approx(rep["calibration"]["coverage_1sigma"])
    assert back["summary"]["num_matched"] == rep["calibration"]["num_matched"] > 0
    full = evaluation_report(dets, gts, include_curves=True)
    calibration_plot(full["calibration"], tmp_path / "calib.png")
    pr_plot(full["detection"], tmp_path / "pr.png")
    for name in ("calib.png", "pr.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_a_score_binned_recalibration_fixes_an_error_that_grows_as_the_score_falls() -> None:
    """The shape the shipped weights show on real and on sim-to-real scans: confident boxes about right, weak
    ones over-confident. One global scale cannot fix it; scales per score bin can."""
    rng = np.random.default_rng(3)

    def draw(n: int) -> tuple[list[Detections3D], list[Sample]]:
        dets, gts = synthetic(rng, n)
        out = []
        for d, g in zip(dets, gts):
            k = 1.0 + 2.0 * (1.0 - d.scores)  # true SD up to 2.6× the predicted at score 0.2, 1× at 1.0
            xy = g.boxes[:, :2] + (d.boxes[:, :2] - g.boxes[:, :2]) * k[:, None]
            out.append(det(xy, d.scores, [CAR] * len(xy), d.log_variances))
        return out, gts

    val_d, val_g = draw(60)
    test_d, test_g = draw(60)
    one = fit_recalibration(val_d, val_g)
    five = fit_recalibration(val_d, val_g, bins=5)
    assert len(five.scales) == 5 and len(five.score_edges) == 4
    cal = calibration(val_d, val_g)  # the report shows the shape the scales undo
    by_score = cal["by_score"]
    assert len(by_score) == 5 and sum(b["n"] for b in by_score) == cal["num_matched"] > 5900
    ratios = [b["variance_ratio_x"] for b in by_score]
    assert ratios[0] > 3.0 > 1.5 > ratios[-1] and all(a > b for a, b in zip(ratios, ratios[1:]))
    assert np.all(np.diff(np.asarray(five.scales)[:, 0]) < 0)  # the weakest bin gets the largest scale

    def weak_coverage(rec: Recalibration) -> float:  # ±1σ coverage of the boxes scored below 0.4
        d = [apply_recalibration(x, rec) for x in test_d]
        m = matched_residuals(d, test_g)
        score = np.concatenate([x.scores for x in d])[m.sample * 100 + m.row]
        return float(np.mean(np.abs(m.residual[score < 0.4]) <= m.sigma[score < 0.4]))

    assert weak_coverage(one) < 0.6 and weak_coverage(five) == pytest.approx(0.683, abs=0.03)
    assert calibration([apply_recalibration(d, five) for d in test_d], test_g)["nll"] < \
        calibration([apply_recalibration(d, one) for d in test_d], test_g)["nll"]
    # a bin holds at least RECALIBRATION_MIN_PER_BIN matches: few matches, fewer bins
    assert len(fit_recalibration(val_d[:1], val_g[:1], bins=5).scales) == 1  # 100 matches
    with pytest.raises(ValueError, match="bins"):
        fit_recalibration(val_d, val_g, bins=0)


def test_a_recalibration_round_trips_its_payload_and_rejects_bad_ones() -> None:
    rec = Recalibration(((2.0, 3.0), (1.0, 1.5)), (0.5,))
    assert Recalibration.of(rec.to_payload()) == rec
    assert Recalibration.of([2.0, 0.5]) == Recalibration(((2.0, 0.5),))
    assert Recalibration(((2.0, 0.5),)).to_payload() == [2.0, 0.5]  # one bin: the format older readers know
    assert Recalibration.of(None) is None
    np.testing.assert_allclose(rec.factors(np.array([0.1, 0.5, 0.9])), [[2.0, 3.0], [1.0, 1.5], [1.0, 1.5]])
    for bad in (((0.0, 1.0),), ((1.0, 1.0), (1.0, 1.0))):
        with pytest.raises(ValueError):
            Recalibration(bad)
    with pytest.raises(ValueError):
        Recalibration(((1.0, 1.0), (1.0, 1.0), (1.0, 1.0)), (0.6, 0.4))  # edges must increase


def test_recall_by_returns_counts_a_box_found_only_by_a_prediction_above_the_working_score() -> None:
    """Three cars of 3, 30 and 300 returns: the sparse one is found (0.9, plus a duplicate that takes nothing),
    the middle one only by a box below the working score 0.3, the dense one by nothing at all. Empty bins say
    None, not 0."""
    sample = gt([(10.0, 0.0), (20.0, 0.0), (30.0, 0.0)], [CAR] * 3, num_points=[3, 30, 300])
    pred = det([(10.2, 0.0), (10.4, 0.1), (20.1, 0.0)], [0.9, 0.5, 0.2], [CAR] * 3)
    rows = detection_ap([pred], [sample])["classes"]["car"]["recall_by_returns"]
    assert [(r["returns"], r["num_gt"], r["recall"]) for r in rows] == [
        ("1-4", 1, 1.0), ("5-19", 0, None), ("20-49", 1, 0.0), ("50-199", 0, None), ("200+", 1, 0.0)]
    # the same boxes scored above the working point: the middle car is found too
    pred_hi = det([(10.2, 0.0), (10.4, 0.1), (20.1, 0.0)], [0.9, 0.5, 0.4], [CAR] * 3)
    rows = detection_ap([pred_hi], [sample])["classes"]["car"]["recall_by_returns"]
    assert [r["recall"] for r in rows] == [1.0, None, 1.0, None, 0.0]
    assert json.loads(json.dumps(evaluation_report([pred], [sample])))["detection"]["classes"]["car"][
        "recall_by_returns"][1]["recall"] is None


def test_false_positives_are_told_what_they_stand_on() -> None:
    """Car boxes over the working score that match no car are counted by the nearest labelled object within 1 m:
    a second box on a car already taken is a duplicate, one on a truck a confusion, one on a labelled cone (an
    unscored category) that cone, one on nothing labelled nothing; a true positive and a false box under the
    working score are not counted; the resamples of the bootstrap do not explain."""
    sample = Sample(np.zeros((0, 4), np.float32), boxes([(10.0, 0.0), (20.0, 5.0)]), np.array([CAR, TRUCK]),
                    np.array([50, 50]), "s", unscored=(("movable_object.trafficcone", 30.0, -4.0),
                                                      ("movable_object.debris", 12.0, 9.0)))
    pred = det([(10.1, 0.0), (10.6, 0.3), (20.3, 5.2), (30.4, -4.2), (-25.0, 8.0), (12.0, 9.0), (12.2, 9.1)],
               [0.9, 0.8, 0.7, 0.6, 0.5, 0.2, 0.35], [CAR] * 7)
    res = detection_ap([pred], [sample])["classes"]
    assert res["car"]["false_positives_on"] == {"duplicate": 1, "movable_object.debris": 1,
                                                "movable_object.trafficcone": 1, "nothing labelled": 1, "truck": 1}
    assert res["truck"]["false_positives_on"] == {}
    # a pedestrian box on the car is a confusion with the car; 1 m away from everything it stands on nothing
    ped = det([(10.5, 0.5), (13.0, 9.0)], [0.9, 0.9], [PED, PED])
    assert detection_ap([ped], [sample])["classes"]["pedestrian"]["false_positives_on"] == {
        "car": 1, "nothing labelled": 1}
    assert detection_ap([pred], [sample], explain=False)["classes"]["car"]["false_positives_on"] is None
    report = json.loads(json.dumps(evaluation_report([pred], [sample])))
    assert report["detection"]["classes"]["car"]["false_positives_on"]["truck"] == 1


def test_the_pr_figure_names_which_ap_is_which(tmp_path) -> None:
    """The curves are one threshold's (2 m), each class's AP in the JSON and report.md the mean over the four:
    the legend gives both and the title says what its mAP is over (it had given the 2 m AP, 0.986 for cars on a
    run whose report.md said 0.958, under the mean mAP as if both were of 2 m). Drawn as SVG: its text comments
    name every label."""
    dets, gts = synthetic(np.random.default_rng(3), 10, sigma_scale=1.5)
    full = evaluation_report(dets, gts, include_curves=True)["detection"]
    pr_plot(full, tmp_path / "pr.svg")
    text = (tmp_path / "pr.svg").read_text()
    car = full["classes"]["car"]
    assert f"car: AP {car['ap']['2']:.3f} at 2 m, {car['mean_ap']:.3f} over 0.5/1/2/4 m" in text
    assert f"(mAP {full['mAP']:.3f} over 0.5/1/2/4 m)" in text
