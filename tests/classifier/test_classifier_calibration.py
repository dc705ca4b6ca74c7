"""Variance self-calibration: the block moments, the online estimator, the calibrated statistic, the file.

Every expectation here is computed independently of the code under test (simulated noise with known scale and
correlation, plain numpy formulas), and every random draw is seeded.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from scipy.special import digamma, polygamma

from jitterguard.schemas.models import ClassifierConfig, Label
from classifier.reference_statistics import reference_block_moments
from jitterguard.services.classifier.calibration import (
    GROUPS,
    HUBER_C,
    MAX_BLOCK_SPEED,
    SCALE_BOUNDS,
    TAU_GRID_S,
    NoiseModel,
    OnlineCalibration,
    block_moments,
    expected_moments,
    group_of_labels,
)
from jitterguard.services.classifier.calibration_file import (
    FORMAT,
    CalibrationFileError,
    dump_calibration,
    parse_calibration,
    read_calibration,
    write_calibration,
)
from jitterguard.services.classifier.core import (
    DYNAMIC,
    STATIC,
    LEARN_BLOCKS_PER_FRAME,
    MotionClassifierCore,
    Observations,
    calibration_gauges,
)
from jitterguard.services.classifier.statistics import (
    CHANNELS,
    calibrated_statistics,
    chi2_2_threshold,
    split_halves,
    t2_to_chi2,
    two_sided_p,
)


def ar_noise(rng: np.random.Generator, shape: tuple[int, int], dt: float, m: float, tau: float) -> np.ndarray:
    """Unit-variance noise over the last axis: white share 1 − m, exp(−|Δt|/τ)-correlated share m."""
    n_blk, n = shape
    phi = math.exp(-dt / tau)
    c = rng.standard_normal(n_blk)
    out = np.empty(shape)
    for j in range(n):
        if j:
            c = phi * c + math.sqrt(1 - phi * phi) * rng.standard_normal(n_blk)
        out[:, j] = math.sqrt(1 - m) * rng.standard_normal(n_blk) + math.sqrt(m) * c
    return out


def blocks(rng: np.random.Generator, n_blk: int, k: float, m: float, tau: float, *, sigma: float = 0.2,
           n: int = 10, dt: float = 0.1, speed: float = 0.0) -> tuple[np.ndarray, ...]:
    """Objects 10–50 m from a sensor at the origin, moving at ``speed`` along a random heading, with errors
    of true variance k·σ² (σ reported) along and across the line of sight."""
    t = np.arange(n) * dt + rng.uniform(0, 100, (n_blk, 1))
    rng_m = rng.uniform(10, 50, n_blk)
    bearing = rng.uniform(-np.pi, np.pi, n_blk)
    u = np.stack([np.cos(bearing), np.sin(bearing)], -1)
    v = np.stack([-u[:, 1], u[:, 0]], -1)
    head = rng.uniform(-np.pi, np.pi, n_blk)
    vel = speed * np.stack([np.cos(head), np.sin(head)], -1)
    e_u = ar_noise(rng, (n_blk, n), dt, m, tau) * sigma * math.sqrt(k)
    e_v = ar_noise(rng, (n_blk, n), dt, m, tau) * sigma * math.sqrt(k)
    pos = (rng_m[:, None, None] * u[:, None, :] + vel[:, None, :] * (t - t[:, :1])[..., None]
           + e_u[..., None] * u[:, None, :] + e_v[..., None] * v[:, None, :])
    cov = np.tile([sigma**2, 0.0, sigma**2], (n_blk, n, 1))
    return t, pos, cov, np.zeros((n_blk, n, 2))


def half_contrast_variance(k: float, m: float, tau: float, n: int = 10, dt: float = 0.1) -> float:
    """Var(μ̄_new − μ̄_old) per unit reported variance, straight from the definition."""
    t = np.arange(n) * dt
    R = (1 - m) * np.eye(n) + m * np.exp(-np.abs(t[:, None] - t[None, :]) / tau)
    h = n // 2
    w = np.r_[np.full(h, -1 / h), np.full(n - h, 1 / (n - h))]
    return float(k * w @ R @ w)


def fitted(cal: OnlineCalibration, group: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    model = cal.refit()
    return model.scale[group, :, 1, 0], model.correlation[group], model.tau_s[group]


def feed(cal: OnlineCalibration, data: tuple[np.ndarray, ...], batch: int = 25, group: int = 0) -> None:
    t, pos, cov, sensor = data
    for i in range(0, len(t), batch):
        sl = slice(i, i + batch)
        cal.add(np.full(len(t[sl]), group), block_moments(t[sl], pos[sl], cov[sl], sensor[sl]))


# ------------------------------------------------------------------------------------------- block moments


def test_residuals_do_not_see_constant_velocity() -> None:
    """A straight line in time leaves the residual moments unchanged: moving steadily looks like standing."""
    rng = np.random.default_rng(0)
    t, pos, cov, _ = blocks(rng, 20, 2.0, 0.3, 0.5)
    sensor = np.full(pos.shape, -5000.0)  # far away: the line of sight does not turn while the object moves
    still = block_moments(t, pos, cov, sensor)
    vel = np.array([3.0, -2.0])
    moving = block_moments(t, pos + vel * (t - t[:, :1])[..., None], cov, sensor)
    np.testing.assert_allclose(moving.Y, still.Y, rtol=1e-2, atol=5e-3)


def test_an_object_at_the_sensor_is_calibrated_along_the_line_not_along_its_own_noise() -> None:
    """Isotropic errors of exactly the reported variance, on an object 5 cm from the sensor, give equal scales
    along and across the line of sight. The axes had been taken to each observed position, so at the sensor they
    turned with the error itself and put it all along the line (parked objects at 0 m pulled the near vehicle
    band across the line of sight to 0.66); they are now taken to the fitted line's position."""
    rng = np.random.default_rng(7)
    t, pos, cov, sensor = blocks(rng, 3000, 1.0, 0.0, 0.5)
    near = pos - pos.mean(axis=1, keepdims=True) + np.array([0.05, 0.0])  # the same errors, 5 cm from the sensor
    mom = block_moments(t, near, cov, sensor)
    along, across = (np.einsum("nii->n", mom.Y[:, a]).mean() / np.einsum("nii->n", mom.Ew[:, a]).mean()
                     for a in range(2))
    assert along == pytest.approx(1.0, abs=0.06) and across == pytest.approx(1.0, abs=0.06)
    ref = reference_block_moments(t, near, cov, sensor)[0]
    np.testing.assert_allclose(mom.Y, ref, rtol=1e-9, atol=1e-12)


def test_white_noise_expectation_is_exact() -> None:
    """Σ over blocks of ε̃ε̃ᵀ approaches k·G Gᵀ: the trace of one block's residual sum is k (n − 2) on average."""
    rng = np.random.default_rng(1)
    mom = block_moments(*blocks(rng, 4000, 3.0, 0.0, 0.5))
    tr_y = np.einsum("naii->na", mom.Y).mean()
    tr_w = np.einsum("naii->na", mom.Ew).mean()
    assert tr_w == pytest.approx(8.0, rel=1e-6)  # n − 2 residual degrees of freedom, equal variances
    assert tr_y / tr_w == pytest.approx(3.0, rel=0.03)


@pytest.mark.parametrize(("k", "m", "tau"), [(1.0, 0.0, 0.5), (4.0, 0.0, 0.5), (4.0, 0.5, 0.3),
                                              (0.25, 0.5, 1.0), (1.0, 0.5, 0.2)])
def test_online_fit_recovers_the_half_window_variance(k: float, m: float, tau: float) -> None:
    """What the test needs — the variance of a half-window mean difference — within 30 % from 2000 blocks,
    whatever the scale and the serial correlation (the slow part is only partly visible in a window: the
    parametric model extrapolates it)."""
    rng = np.random.default_rng(2)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(cal, blocks(rng, 2000, k, m, tau))
    ks, ms, ts = fitted(cal)
    for ai in range(2):
        est = half_contrast_variance(ks[ai], ms[ai], ts[ai])
        assert est / half_contrast_variance(k, m, tau) == pytest.approx(1.0, abs=0.3)


def test_white_scale_is_accurate_and_shared_by_every_range_band() -> None:
    rng = np.random.default_rng(3)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(cal, blocks(rng, 2000, 2.5, 0.0, 0.5))
    model = cal.refit()
    # the three range bands of vehicles (established tracks), both axes
    assert np.allclose(model.scale[0, :, :, 0], 2.5, rtol=0.12)


def test_scaling_every_reported_variance_scales_the_estimate() -> None:
    """The invariance the classifier needs: report every variance ×¼ (or ×4) and the learnt scale moves by ×4
    (×¼), so the calibrated variances — and every z — stay where they were."""
    base = None
    for factor in (0.25, 1.0, 4.0):
        rng = np.random.default_rng(4)
        t, pos, cov, sensor = blocks(rng, 1500, 2.0, 0.3, 0.4)
        cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
        feed(cal, (t, pos, cov * factor, sensor))
        model = cal.refit()
        calibrated = model.scale[0, :, :, 0] * factor
        if base is None:
            base = calibrated
        np.testing.assert_allclose(calibrated, base, rtol=0.05)


def test_outlier_blocks_barely_move_the_scale() -> None:
    """Misassociations and ghosts: 5 % of blocks with a metre-sized outlier. Unweighted they would double the
    scale; down-weighted each counts like HUBER_C ordinary blocks at most. (A jump that persists looks like
    motion and the block is not pooled at all: ``test_fast_blocks_are_not_pooled``.)"""
    rng = np.random.default_rng(5)
    t, pos, cov, sensor = blocks(rng, 2000, 1.0, 0.0, 0.5)
    clean = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(clean, (t, pos, cov, sensor))
    bad = pos.copy()
    idx = rng.choice(len(t), 100, replace=False)
    bad[idx, 4] += rng.normal(0, 1.5, (100, 2))  # one frame on a neighbour (a misassociation, a ghost)
    dirty = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(dirty, (t, bad, cov, sensor))
    k_clean, k_dirty = fitted(clean)[0], fitted(dirty)[0]
    assert np.all(k_dirty / k_clean < 1.3)
    assert dirty.counts["blocks_downweighted"] > 50


def test_fast_blocks_are_not_pooled() -> None:
    rng = np.random.default_rng(6)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(cal, blocks(rng, 200, 9.0, 0.0, 0.5, speed=3 * MAX_BLOCK_SPEED))
    assert cal.counts["blocks"] == 0 and cal.counts["blocks_fast"] == 200
    assert np.allclose(cal.refit().scale, 1.0)  # nothing learnt: the prior


def test_a_handful_of_tracks_cannot_swing_a_cell_and_scales_stay_bounded() -> None:
    rng = np.random.default_rng(7)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(cal, blocks(rng, 3, 50.0, 0.0, 0.5), group=1)  # three pedestrian blocks, 50× too noisy
    model = cal.refit()
    assert np.all(model.scale[1, :, :, 0] < 10.0)
    cal2 = OnlineCalibration(prior_blocks=0.0, half_life_s=math.inf)
    feed(cal2, blocks(rng, 500, 1e5, 0.0, 0.5))
    assert cal2.refit().scale.max() <= SCALE_BOUNDS[1]


def test_forgetting_halves_the_evidence_per_half_life_and_time_may_restart() -> None:
    rng = np.random.default_rng(8)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=60.0)
    cal.advance(1000.0)
    feed(cal, blocks(rng, 100, 2.0, 0.0, 0.5))
    before = cal.effective_blocks
    cal.advance(1060.0)
    assert cal.effective_blocks == pytest.approx(before / 2)
    cal.advance(5.0)  # a recording that started over: no forgetting, the clock restarts
    assert cal.effective_blocks == pytest.approx(before / 2)
    cal.advance(65.0)
    assert cal.effective_blocks == pytest.approx(before / 4)


def test_label_groups() -> None:
    labels = [Label.UNKNOWN, Label.CAR, Label.TRUCK, Label.BUS, Label.TRAILER, Label.MOTORCYCLE, Label.BICYCLE,
              Label.PEDESTRIAN, 99]
    names = [GROUPS[g] for g in group_of_labels(np.array(labels))]
    assert names == ["unknown", "vehicle", "vehicle", "vehicle", "vehicle", "cycle", "cycle", "pedestrian",
                     "unknown"]


# ------------------------------------------------------------------------------------------- the statistic


def _windows(rng, n_trk, model, k, m, tau, *, sigma=0.2, n=10, dt=0.1, speed=0.0):
    """Full windows of vehicles (channels of statistics.CHANNELS) whose errors follow (k, m, τ)."""
    t, pos, cov, sensor = blocks(rng, n_trk, k, m, tau, sigma=sigma, n=n, dt=dt, speed=speed)
    ordinal = np.tile(np.arange(n) + 100.0, (n_trk, 1))  # established tracks
    return np.concatenate([pos, cov, t[..., None], sensor, ordinal[..., None]], axis=-1)


def _stats(win, model, effective_n="measured", min_speed=0.0):
    from jitterguard.services.classifier.statistics import split_halves as halves

    n_trk, n = win.shape[:2]
    masks = halves(np.zeros(n_trk, dtype=np.int64), np.full(n_trk, n), n)
    return calibrated_statistics(win, masks, np.zeros(n_trk, dtype=np.int64), model, variance_floor=1e-6,
                                 effective_n=effective_n, min_speed=min_speed)


def _model(k: float, m: float, tau: float, track_dof: float = 1000.0) -> NoiseModel:
    base = NoiseModel.prior()
    g = len(GROUPS)
    return NoiseModel(base.band_edges_m, np.full(base.scale.shape, k), np.full((g, 2), m), np.full((g, 2), tau),
                      base.blocks, 0.1, np.full(g, track_dof))


def test_measured_mode_fires_at_the_nominal_rate_under_correlated_noise() -> None:
    """With the true scale and correlation, each axis' z of a parked car is |N(0, 1)|: P(z_x > 1.96) ≈ 5 %,
    where counting observations as independent fires far more often and the paper's clusters far less."""
    rng = np.random.default_rng(9)
    k, m, tau = 3.0, 0.5, 0.4
    win = _windows(rng, 6000, None, k, m, tau)
    model = _model(k, m, tau)
    z = _stats(win, model).z_x
    se = math.sqrt(0.05 * 0.95 / len(z))
    assert abs((z > 1.96).mean() - 0.05) < 4 * se
    assert (_stats(win, model, "independent").z_x > 1.96).mean() > 0.08
    assert (_stats(win, model, "cluster").z_x > 1.96).mean() < 0.01


def test_measured_variance_stays_positive_with_strong_correlation_and_cross_terms() -> None:
    """The denominator is a covariance: never negative, whatever m and the reported cross term."""
    rng = np.random.default_rng(10)
    win = _windows(rng, 500, None, 1.0, 0.0, 0.5)
    win[..., 3] = rng.uniform(-0.039, 0.039, win.shape[:2])  # |cxy| up to almost sqrt(cxx·cyy)
    stats = _stats(win, _model(1.0, 0.99, 3.0))
    assert np.all(np.isfinite(stats.z_x)) and np.all(stats.z_x < 1e3)
    assert np.all(np.isfinite(stats.chi2)) and np.all(stats.chi2 >= 0)


def test_min_speed_is_the_null_hypothesis_speed() -> None:
    """A box drifting at 8 cm/s with 5 mm noise is 'moving' against H0 v = 0 and static against |v| ≤ 0.1 m/s;
    a car at 2 m/s is dynamic against either."""
    rng = np.random.default_rng(12)
    drift = _windows(rng, 50, None, 1.0, 0.0, 0.5, sigma=0.005, speed=0.08)
    model = _model(1.0, 0.0, 0.5)
    z0 = _stats(drift, model)
    assert np.maximum(z0.z_x, z0.z_y).min() > 3
    z01 = _stats(drift, model, min_speed=0.1)
    assert np.all(np.maximum(z01.z_x, z01.z_y) == 0.0)
    moving = _windows(rng, 50, None, 1.0, 0.0, 0.5, sigma=0.05, speed=2.0)
    zm = _stats(moving, model, min_speed=0.1)
    assert np.all(np.maximum(zm.z_x, zm.z_y) > 5)


def test_a_track_noisier_than_its_class_learns_its_own_scale() -> None:
    """Windows 4× noisier than the class calibration says: with a finite ν₀ their own residuals raise the
    denominator, so far fewer of them are false alarms than with every track taken like its class."""
    rng = np.random.default_rng(13)
    win = _windows(rng, 3000, None, 4.0, 0.0, 0.5)
    like_class = _stats(win, _model(1.0, 0.0, 0.5, track_dof=1000.0))
    own = _stats(win, _model(1.0, 0.0, 0.5, track_dof=4.0))
    fd = lambda s: (np.maximum(s.z_x, s.z_y) > 2.58).mean()  # noqa: E731
    assert fd(like_class) > 0.2
    assert fd(own) < fd(like_class) / 2


def test_a_cold_start_tests_with_the_uncertainty_of_its_prior() -> None:
    """Before any block the calibration knows only its prior k = 1: parked cars whose variances are reported
    4× too small (the shipped detector on real scans) fire far less often than if k = 1 were taken as known,
    and as blocks arrive the class scale's degrees of freedom grow until the test is the known-scale one."""
    from dataclasses import replace

    from jitterguard.services.classifier.calibration import BLOCK_DOF, PRIOR_SCALE_DOF

    rng = np.random.default_rng(21)
    cal = OnlineCalibration(window=10)
    cold = cal.current
    assert cold.scale_dof == PRIOR_SCALE_DOF and np.allclose(cold.scale, 1.0)
    known = replace(cold, scale_dof=math.inf)  # the same scales, taken as given (a calibration file)
    g = np.zeros(3, dtype=np.int64)
    assert np.allclose(known.test_dof(g), cold.track_dof[g])
    assert np.allclose(cold.test_dof(g), 1.0 / (1.0 / cold.track_dof[g] + 1.0 / PRIOR_SCALE_DOF))
    win = _windows(rng, 3000, None, 4.0, 0.0, 0.5, n=2)  # two observations: no residuals of its own yet
    fd = lambda model: (np.maximum(_stats(win, model).z_x, _stats(win, model).z_y) > 2.58).mean()  # noqa: E731
    assert fd(known) > 0.3
    assert fd(cold) < fd(known) / 2
    feed(cal, blocks(rng, 40, 1.0, 0.0, 0.5))  # k = 1: no block is down-weighted as an outlier
    warm = cal.refit()
    assert warm.scale_dof == pytest.approx(PRIOR_SCALE_DOF + BLOCK_DOF * 40, rel=0.03)
    feed(cal, blocks(rng, 2000, 1.0, 0.0, 0.5))
    assert np.allclose(cal.refit().test_dof(g), cal.current.track_dof[g], rtol=0.1)


# ------------------------------------------------------------------------------------------- the core


def _obs(ids, x, y, t_s, sensor=(0.0, 0.0), var=0.01, label=Label.CAR):
    n = len(ids)
    return Observations.from_lists(ids, np.full(n, int(label)), x, y, np.full(n, var), np.zeros(n),
                                   np.full(n, var), stamp_ns=int(round(t_s * 1e9)), sensor_x=sensor[0],
                                   sensor_y=sensor[1])


def test_core_learns_online_and_keeps_what_it_learnt_across_reset() -> None:
    """Parked cars reported 3× too confident in σ (9× in variance): after a few seconds the online calibration
    says so, the false alarms of the uncalibrated test are gone, and a tracker restart keeps the scales."""
    rng = np.random.default_rng(14)
    ids = [f"{i + 1:032x}" for i in range(60)]
    base = rng.uniform(-40, 40, (60, 2))
    cfg = ClassifierConfig(window_size=10)  # windows turn over every 10 frames: the last one fills at frame 150
    core = MotionClassifierCore(cfg)
    off = MotionClassifierCore(ClassifierConfig(calibration="off", window_size=10))
    fired_on = fired_off = 0
    for f in range(150):
        p = base + rng.normal(0, 0.3, (60, 2))  # true σ 0.3, reported 0.1
        o = _obs(ids, p[:, 0], p[:, 1], f * 0.1)
        d_on, d_off = core.update(o), off.update(o)
        if f >= 100:
            fired_on += int((d_on.state == DYNAMIC).sum())
            fired_off += int((d_off.state == DYNAMIC).sum())
    before = core.calibration_state()["counts"]["blocks"]
    core.learn()  # what the service does once a frame's objects are out (ClassifierAdapter.settle)
    state = core.calibration_state()
    # windows that filled in the last frame, pooled only now (a frame's budget at most: LEARN_BLOCKS_PER_FRAME)
    assert before < state["counts"]["blocks"] <= before + LEARN_BLOCKS_PER_FRAME
    assert state["mode"] == "online" and state["counts"]["blocks"] >= 60 * 14
    scale = state["groups"]["vehicle"]["along"]["scale"]["20-40"]
    assert scale == pytest.approx(9.0, rel=0.25)
    assert fired_on < 0.05 * 50 * 60 < fired_off
    core.reset()
    assert core.calibration_state()["groups"]["vehicle"]["along"]["scale"]["20-40"] == pytest.approx(scale)
    gauges = calibration_gauges(core.calibration_state())
    assert gauges["calibration.vehicle.along.scale.20-40"] == pytest.approx(scale)
    assert "calibration.vehicle.across.variance_factor" in gauges


def test_a_decision_is_not_delayed_by_learning_and_learning_misses_nothing() -> None:
    """update() decides with the model as the previous frames left it and only queues the windows that
    filled; learn() pools them. Driving the core with learn() after every frame (the service) or never (a
    caller that only updates: update() learns first) pools the same blocks and ends with the same model."""
    rng = np.random.default_rng(3)
    ids = [f"{i + 1:032x}" for i in range(40)]
    base = rng.uniform(-40, 40, (40, 2))
    frames = [_obs(ids, *(base + rng.normal(0, 0.3, (40, 2))).T, f * 0.1) for f in range(60)]
    settled, lazy = MotionClassifierCore(ClassifierConfig()), MotionClassifierCore(ClassifierConfig())
    for o in frames:
        model_before = settled.noise_model()
        blocks_before = settled.online_calibration.counts["blocks"]
        a, b = settled.update(o), lazy.update(o)
        assert settled.noise_model() is model_before  # no pooling or fitting on the decision's path
        assert settled.online_calibration.counts["blocks"] == blocks_before
        np.testing.assert_allclose(a.z_x, b.z_x, rtol=1e-12)  # the same test, to rounding
        settled.learn()
    lazy.learn()
    assert settled.online_calibration.counts == lazy.online_calibration.counts
    assert settled.online_calibration.counts["blocks"] > 0
    np.testing.assert_allclose(settled.noise_model().scale, lazy.noise_model().scale, rtol=1e-12)


def test_file_mode_needs_scales_and_uses_them() -> None:
    with pytest.raises(ValueError, match="file"):
        MotionClassifierCore(ClassifierConfig(calibration="file", calibration_file="x.yaml"))
    model = _model(9.0, 0.0, 0.5)
    core = MotionClassifierCore(ClassifierConfig(calibration="file", calibration_file="x.yaml"),
                                calibration_model=model)
    assert core.noise_model() is model
    assert core.calibration_state()["groups"]["vehicle"]["along"]["scale"]["0-20"] == 9.0
    assert core.calibration_state()["scale_dof"] is None  # a file's scales are taken as given
    assert "calibration.scale_dof" not in calibration_gauges(core.calibration_state())
    cold = MotionClassifierCore(ClassifierConfig())  # online, nothing learnt: the operator sees how little it knows
    assert cold.calibration_state()["scale_dof"] == 2.0
    assert calibration_gauges(cold.calibration_state())["calibration.scale_dof"] == 2.0


def test_the_evidence_shown_is_that_behind_the_scales_in_force() -> None:
    """A classifier that learnt online and was then switched to a file's scales, or off, had gone on showing the
    idle estimator's effective blocks in /v1/state and the heartbeat, as if the scales in force rested on them."""
    rng = np.random.default_rng(41)
    ids = [f"{i + 1:032x}" for i in range(30)]
    base = rng.uniform(-30, 30, (30, 2))
    core = MotionClassifierCore(ClassifierConfig(window_size=10))
    for f in range(120):
        p = base + rng.normal(0, 0.1, (30, 2))
        core.update(_obs(ids, p[:, 0], p[:, 1], f * 0.1))
        core.learn()
    learnt = core.online_calibration.effective_blocks
    assert learnt > 100 and core.calibration_state()["effective_blocks"] == pytest.approx(learnt, abs=1e-3)
    model = _model(9.0, 0.0, 0.5)
    model.blocks[:] = 0.0
    model.blocks[0, :, 1, 0] = 7.0  # the file's evidence: 7 blocks of vehicles at 20-40 m, both axes
    core.configure(ClassifierConfig(window_size=10, calibration="file", calibration_file="x.yaml"),
                   calibration_model=model)
    state = core.calibration_state()
    assert state["effective_blocks"] == 7.0 and calibration_gauges(state)["calibration.effective_blocks"] == 7.0
    core.configure(ClassifierConfig(window_size=10, calibration="off"))
    assert core.calibration_state()["effective_blocks"] == 0.0
    core.configure(ClassifierConfig(window_size=10))  # online again: what it had learnt
    assert core.calibration_state()["effective_blocks"] == pytest.approx(learnt, abs=1e-3)


def test_calibration_config_validates() -> None:
    with pytest.raises(ValueError, match="calibration_file"):
        ClassifierConfig(calibration="file")
    # band edges are a set of distances: any order, repeats dropped (JSON Schema cannot say "increasing", so
    # the HTTP API must accept what its schema admits)
    assert ClassifierConfig(calibration_range_bands_m=[40.0, 20.0, 40.0]).calibration_range_bands_m == [20.0, 40.0]
    with pytest.raises(ValueError):
        ClassifierConfig(calibration_range_bands_m=[0.0])
    with pytest.raises(ValueError):
        ClassifierConfig(effective_n="sometimes")


# ------------------------------------------------------------------------------------------- the file


def test_calibration_file_round_trip_read_back_independently(tmp_path: Path) -> None:
    rng = np.random.default_rng(15)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(cal, blocks(rng, 300, 2.0, 0.3, 0.4))
    model = cal.refit()
    path = tmp_path / "cal.yaml"
    write_calibration(path, model, window=10, source={"recording": "synthetic"})
    raw = yaml.safe_load(path.read_text())  # an independent reader: plain YAML
    assert raw["format"] == FORMAT and raw["source"]["recording"] == "synthetic"
    assert raw["groups"]["vehicle"]["along"]["scale"]["20-40"] == pytest.approx(model.scale[0, 0, 1, 0], rel=1e-5)
    back = read_calibration(path)
    np.testing.assert_allclose(back.scale, model.scale, rtol=1e-5)
    np.testing.assert_allclose(back.correlation, model.correlation, rtol=1e-5)
    np.testing.assert_allclose(back.track_dof, model.track_dof, rtol=1e-3)


def test_range_bands_that_print_alike_keep_names_of_their_own(tmp_path: Path) -> None:
    """Edges 20, 20.000001 and 20.000002 m had named two bands "20-20": the state, the heartbeat and the file held
    one of their scales, and the file read back gave the other band the prior's 1."""
    edges = [20.0, 20.000001, 20.000002]
    cfg = ClassifierConfig(calibration_range_bands_m=edges)
    state = MotionClassifierCore(cfg).calibration_state()
    assert len(state["groups"]["vehicle"]["along"]["scale"]) == 4
    assert len([k for k in calibration_gauges(state) if k.startswith("calibration.vehicle.along.scale.")]) == 4
    prior = NoiseModel.prior(edges)
    scale = prior.scale.copy()
    scale[:, :, :, 0] = np.array([0.5, 2.0, 3.0, 4.0])  # a scale of its own per band
    model = NoiseModel(prior.band_edges_m, scale, prior.correlation, prior.tau_s, prior.blocks)
    write_calibration(tmp_path / "c.yaml", model, window=10)
    np.testing.assert_array_equal(read_calibration(tmp_path / "c.yaml").scale, scale)
    assert MotionClassifierCore(ClassifierConfig()).calibration_state()["range_bands_m"] == [20.0, 40.0]
    assert list(NoiseModel.prior().to_mapping()["groups"]["vehicle"]["along"]["scale"]) == ["0-20", "20-40", "40-inf"]


def test_a_written_file_cut_short_or_edited_is_refused_by_its_digest(tmp_path: Path) -> None:
    """Cut short at a whole entry a written file is still valid YAML whose missing groups keep the prior: it had
    loaded without a word. Its digest catches that; a hand edit loads once the digest line is deleted."""
    rng = np.random.default_rng(16)
    cal = OnlineCalibration(prior_blocks=20.0, half_life_s=math.inf)
    feed(cal, blocks(rng, 300, 2.0, 0.3, 0.4))
    model = cal.refit()
    text = dump_calibration(model, window=10, source={"recording": "synthetic"})
    lines = text.splitlines(keepends=True)
    assert lines[1].startswith("digest: sha256:")
    np.testing.assert_allclose(parse_calibration(text).scale, model.scale, rtol=1e-5)
    cut = "".join(lines[: next(i for i, ln in enumerate(lines) if ln.startswith("  pedestrian:"))])
    assert yaml.safe_load(cut)["groups"]["vehicle"]  # valid YAML, a whole entry short
    with pytest.raises(CalibrationFileError, match="digest does not match"):
        parse_calibration(cut)
    edited = text.replace("window: 10", "window: 12")
    with pytest.raises(CalibrationFileError, match="digest does not match"):
        parse_calibration(edited)
    undigested = "".join(ln for ln in edited.splitlines(keepends=True) if not ln.startswith("digest:"))
    assert parse_calibration(undigested).scale.shape == model.scale.shape
    with pytest.raises(CalibrationFileError, match="digest does not match"):
        parse_calibration(text.replace("digest: sha256:", "digest: 12"))


@pytest.mark.parametrize(("text", "needle"), [
    ("not: [yaml", "not YAML"),
    ("format: other/1\n", "format"),
    ("format: jitterguard-calibration/2\n", "of another version"),
    (f"format: {FORMAT}\ngroups: {{vehicle: {{along: {{scale: {{0-20: -1}}}}}}}}\n", "groups.vehicle.along.scale.0-20"),
    (f"format: {FORMAT}\ngroups: {{lorry: {{}}}}\n", "groups.lorry"),
    (f"format: {FORMAT}\ngroups: {{vehicle: {{along: {{correlation: .nan}}}}}}\n", "correlation"),
    # a misspelt key had left its scales at the prior of 1 without a word; blocks that are no mapping had raised
    # an AttributeError past the config write's handler
    (f"format: {FORMAT}\ngroups: {{vehicle: {{along: {{scales: {{0-20: 2}}}}}}}}\n", "groups.vehicle.along.scales"),
    (f"format: {FORMAT}\nrange_band_m: [10]\n", "range_band_m"),
    (f"format: {FORMAT}\ngroups: {{vehicle: {{along: {{blocks: 12}}}}}}\n", "groups.vehicle.along.blocks"),
    # a file cut short leaves a key empty; a tampered window or variance factor had been taken without a look
    (f"format: {FORMAT}\ngroups:\n  vehicle:\n    along:\n      blocks:\n", "groups.vehicle.along.blocks"),
    (f"format: {FORMAT}\nwindow: '10'\n", "window"),
    (f"format: {FORMAT}\nwindow: 100000\n", "window"),
    (f"format: {FORMAT}\ngroups: {{vehicle: {{along: {{variance_factor: 0}}}}}}\n", "groups.vehicle.along.variance_factor"),
])
def test_bad_calibration_files_name_the_entry(text: str, needle: str) -> None:
    with pytest.raises(CalibrationFileError, match=needle.replace(".", r"\.")):
        parse_calibration(text)


def test_missing_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError) as exc:
        read_calibration(tmp_path / "nope.yaml")
    assert "\n" not in str(exc.value) and "nope.yaml" in str(exc.value)


def test_a_file_that_is_no_calibration_is_refused_without_quoting_it(tmp_path: Path) -> None:
    """A config write may name any path on the classifier's host: the refusal says where the file stopped being a
    calibration file, never what it holds."""
    secret = tmp_path / "my.cnf"
    secret.write_text("[client]\npassword\t= s3cr3tPW\n")
    other = tmp_path / "other.yaml"
    other.write_text("format: s3cr3tPW\n")
    for path in (secret, other):
        with pytest.raises(CalibrationFileError) as exc:
            read_calibration(path)
        assert "s3cr3tPW" not in str(exc.value) and str(path) in str(exc.value)
    with pytest.raises(CalibrationFileError, match="line 2, column"):
        read_calibration(secret)


def test_a_fifo_or_device_is_refused_without_being_read(tmp_path: Path) -> None:
    """A FIFO nobody writes to would block the config queryable on open; /dev/zero would be read without end."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero")):
        with pytest.raises(CalibrationFileError, match="not a regular file"):
            read_calibration(path)
    with pytest.raises(CalibrationFileError, match=f"^{tmp_path}: a folder, not a calibration file$"):
        read_calibration(tmp_path)  # had been "Is a directory: 3", the descriptor's number


@pytest.mark.parametrize("path", ["/proc/self/status", "/proc/version", "/proc/self/cmdline",
                                  "/sys/kernel/mm/transparent_hugepage/enabled"])
def test_a_kernel_file_is_refused_the_same_way_whatever_it_holds(path: str, tmp_path: Path) -> None:
    """/proc and /sys files stat as regular: they were read, and the refusal told their YAML's line and column —
    a description of the file to whoever may write the config. Reached through a link too."""
    link = tmp_path / "cal.yaml"
    link.symlink_to(path)
    for p in (Path(path), link):
        with pytest.raises(CalibrationFileError) as exc:
            read_calibration(p)
        assert str(exc.value) == f"{p}: a kernel file, not a calibration file"


def test_an_empty_file_is_refused_unread(tmp_path: Path) -> None:
    empty = tmp_path / "empty.yaml"
    empty.touch()
    with pytest.raises(CalibrationFileError, match="empty, not a calibration file"):
        read_calibration(empty)


@pytest.mark.parametrize("path", ["cal\x00.yaml", "cal\udbf1.yaml"])
def test_a_path_no_file_system_holds_is_refused_and_the_message_encodes(path: str) -> None:
    """A NUL byte or a lone surrogate (a config write can carry either) is a clean refusal whose message the
    classifier can put on the wire (UTF-8, printable), not an internal error."""
    with pytest.raises(CalibrationFileError) as exc:
        read_calibration(path)
    msg = str(exc.value)
    assert msg.encode("utf-8") and msg.isprintable() and "cannot read" in msg


def test_static_decisions_use_the_calibrated_scales() -> None:
    """The same jittering window is dynamic with the detector's variances and static with the file's ×9 (the test's
    statistic alone: the jump veto, which looks at a window's shape, would keep most of these static either way)."""
    rng = np.random.default_rng(16)
    ids = [f"{i + 1:032x}" for i in range(200)]
    base = rng.uniform(10, 30, (200, 2))
    plain = MotionClassifierCore(ClassifierConfig(calibration="off", alpha_per_class={}, jump_veto=False))
    cal = MotionClassifierCore(ClassifierConfig(calibration="file", calibration_file="f", alpha_per_class={},
                                                jump_veto=False),
                               calibration_model=_model(9.0, 0.0, 0.5, track_dof=1000.0))
    for f in range(10):
        p = base + rng.normal(0, 0.3, (200, 2))
        o = _obs(ids, p[:, 0], p[:, 1], 100 + f * 0.1)
        dp, dc = plain.update(o), cal.update(o)
    assert (dp.state == DYNAMIC).mean() > 0.3
    assert (dc.state == DYNAMIC).mean() < 0.15
    assert (dc.state == STATIC).mean() > 0.85


def test_factored_moments_and_their_pooling_match_the_dense_products() -> None:
    """The compiled pooling's block moments are the dense r rᵀ, G Gᵀ and G Φ Gᵀ of the first implementation to
    rounding — for evenly spaced, gappy, unsorted and long-spanning blocks — and pooling them gives the
    Huber-weighted dense sums per (group, band, age) cell, shorter blocks in the leading rows and columns, and the
    track-heterogeneity sums from each block's dense covariance at its group's τ."""
    rng = np.random.default_rng(33)
    t, pos, cov, sensor = blocks(rng, 60, 2.0, 0.4, 0.5, n=20)
    t = t + np.where(rng.random(t.shape) < 0.1, 0.1, 0.0).cumsum(axis=1)  # missed frames: gaps
    t[:5] = t[:5] * 40.0  # blocks spanning minutes
    t[5:8] = t[5:8, ::-1]  # stamps out of order
    pos[:, :, 0] += rng.uniform(-60.0, 60.0, (60, 1))  # every range band
    ref = reference_block_moments(t, pos, cov, sensor)
    mom = block_moments(t, pos, cov, sensor)
    for got, want, name in zip((mom.Y, mom.Ew, mom.Et), ref, ("Y", "Ew", "Et")):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max(), err_msg=name)
    t2, pos2, cov2, sensor2 = blocks(rng, 15, 2.0, 0.4, 0.5, n=7)
    groups, young = rng.integers(0, len(GROUPS), 60), rng.random(60) < 0.4
    groups2, young2 = rng.integers(0, len(GROUPS), 15), rng.random(15) < 0.4
    cal = OnlineCalibration(window=20)
    cal.advance(100.0)
    want = {name: np.zeros_like(getattr(cal, name)) for name in ("_Y", "_Ew", "_Et", "_n", "_het")}
    for (tt, pp, cc, ss), g, y in (((t, pos, cov, sensor), groups, young), ((t2, pos2, cov2, sensor2), groups2, young2)):
        model = cal.model()
        Yd, Ewd, Etd = reference_block_moments(tt, pp, cc, ss)
        m = block_moments(tt, pp, cc, ss)
        band = model.bands(m.range_m)
        k = model.scale[g, :, band, y.astype(np.int64)]
        pred = expected_moments(np.einsum("naii->na", Ewd)[..., None], np.einsum("natii->nat", Etd)[..., None, :],
                                k, model.correlation[g], model.tau_s[g])[..., 0]
        w = np.minimum(1.0, HUBER_C / (np.einsum("naii->na", Yd) / pred)) * (m.speed <= MAX_BLOCK_SPEED)[:, None]
        n = tt.shape[1]
        for b in range(len(tt)):
            for a in range(2):
                cell = (g[b], a, band[b], int(y[b]))
                for name, dense in (("_Y", Yd), ("_Ew", Ewd)):
                    want[name][cell].reshape(20, 20)[:n, :n] += w[b, a] * dense[b, a]
                want["_Et"][cell].reshape(20, 20, -1)[:n, :n] += w[b, a] * np.moveaxis(Etd[b, a], 0, -1)
                want["_n"][cell] += w[b, a]
        # the track heterogeneity: each slow block's Satterthwaite dof from its dense covariance Q at the group's τ
        slow = m.speed <= MAX_BLOCK_SPEED
        lt = np.log(TAU_GRID_S)  # the group's τ between two grid points, linear in log τ
        x = np.clip(np.log(model.tau_s[g]), lt[0], lt[-1])
        i = np.clip(np.searchsorted(lt, x) - 1, 0, len(lt) - 2)
        f = ((x - lt[i]) / (lt[i + 1] - lt[i]))[..., None, None]
        nb = np.arange(len(tt))[:, None]
        Bt = (1 - f) * Etd[nb, np.arange(2), i] + f * Etd[nb, np.arange(2), i + 1]
        mm = model.correlation[g][..., None, None]
        Q = k[..., None, None] * ((1 - mm) * Ewd + mm * Bt)
        trace, trace2 = np.einsum("naii->n", Q), (Q * Q).sum((1, 2, 3))
        S0 = np.einsum("naii->n", Yd)
        nu = trace ** 2 / trace2
        y_b = np.log(S0 / trace) - (digamma(nu / 2) - np.log(nu / 2))
        wt = w.min(axis=1)
        for col, val in enumerate((wt * y_b, wt * y_b ** 2, wt * polygamma(1, nu / 2), wt)):
            want["_het"][:, col] += np.bincount(g[slow], weights=val[slow], minlength=len(GROUPS))
        cal.add(g, m, y)
    for name, value in want.items():
        np.testing.assert_allclose(getattr(cal, name), value, rtol=1e-9, atol=1e-9, err_msg=name)


def test_garbage_blocks_neither_raise_nor_poison_the_sums() -> None:
    """Whatever a broken upstream sends — NaN or infinite stamps, positions and covariances, stamps far beyond any
    clock, zero, negative or absurd covariances, repeated stamps, stamps out of order — the pooling raises
    nothing, every block is counted once (pooled, fast or invalid), the sums stay finite and the fitted scales
    stay in their bounds; the sound blocks of the batch are still learnt."""
    rng = np.random.default_rng(5)
    for trial in range(20):
        t, pos, cov, sensor = blocks(rng, 30, 2.0, 0.4, 0.5)
        n_bad = 20
        rows = rng.choice(30, n_bad, replace=False)
        for r in rows:
            j = rng.integers(0, t.shape[1])
            kind = rng.integers(0, 9)
            if kind == 0:
                t[r, j] = np.nan
            elif kind == 1:
                pos[r, j, rng.integers(0, 2)] = rng.choice([np.nan, np.inf, -np.inf])
            elif kind == 2:
                cov[r, j, rng.integers(0, 3)] = rng.choice([np.nan, np.inf])
            elif kind == 3:
                t[r] = rng.choice([1e200, -1e160, 1e20])
            elif kind == 4:
                cov[r] = rng.choice([0.0, -1.0, 1e120, 1e-300])
            elif kind == 5:
                t[r] = t[r, 0]  # one stamp repeated: no line in time
            elif kind == 6:
                t[r] = rng.permutation(t[r])  # out of order
            elif kind == 7:
                pos[r] += 1e160
            else:
                sensor[r, j] = np.nan
        groups, young = rng.integers(0, len(GROUPS), 30), rng.random(30) < 0.3
        cal = OnlineCalibration()
        cal.advance(100.0 + trial)
        cal.add(groups, block_moments(t, pos, cov, sensor), young)
        c = cal.counts
        assert c["blocks"] + c["blocks_fast"] + c["blocks_invalid"] == 30, (trial, c)
        assert c["blocks"] >= 10  # the 10 untouched blocks at least (still, so slow) are pooled
        for name in ("_Y", "_Ew", "_Et", "_n", "_het"):
            assert np.isfinite(getattr(cal, name)).all(), (trial, name)
        model = cal.refit()
        assert np.isfinite(model.scale).all() and (model.scale >= SCALE_BOUNDS[0]).all()
        assert (model.scale <= SCALE_BOUNDS[1]).all() and np.isfinite(model.track_dof).all()


def test_fast_and_broken_blocks_are_counted_not_pooled() -> None:
    """Blocks faster than MAX_BLOCK_SPEED are counted and add nothing (the compiled pooling skips their work) and
    broken ones (positions near the float limit) are counted invalid: a mix pools exactly — bit for bit, sums,
    heterogeneity and model — what its slow, sound blocks pool alone."""
    rng = np.random.default_rng(21)
    t, pos, cov, sensor = (np.concatenate(parts) for parts in zip(
        blocks(rng, 40, 2.0, 0.4, 0.5), blocks(rng, 40, 2.0, 0.4, 0.5, speed=6.0),
        blocks(rng, 10, 2.0, 0.4, 0.5, speed=0.6)))
    pos[:3, 5:] += 1e300  # a broken upstream: counted invalid, whatever its speed
    groups = rng.integers(0, len(GROUPS), len(t))
    young = rng.random(len(t)) < 0.3
    mixed = OnlineCalibration()
    mixed.advance(100.0)
    mom = block_moments(t, pos, cov, sensor)
    mixed.add(groups, mom, young)
    sel = np.flatnonzero(mom.finite() & (mom.speed <= MAX_BLOCK_SPEED))
    assert 40 <= sel.size < 50  # the slow blocks but the broken ones (the 0.6 m/s ones pool too)
    alone = OnlineCalibration()
    alone.advance(100.0)
    alone.add(groups[sel], block_moments(t[sel], pos[sel], cov[sel], sensor[sel]), young[sel])
    assert mixed.counts["blocks_fast"] >= 40 and mixed.counts["blocks_invalid"] == 3
    assert mixed.counts["blocks"] == alone.counts["blocks"] == sel.size
    assert alone.counts["blocks_fast"] == alone.counts["blocks_invalid"] == 0
    for name in ("_Y", "_Ew", "_Et", "_n", "_het"):
        np.testing.assert_array_equal(getattr(mixed, name), getattr(alone, name), err_msg=name)
    assert np.abs(mixed._Et).sum() > 0  # something was pooled
    np.testing.assert_array_equal(mixed.refit().scale, alone.refit().scale)


# ------------------------------------------------------------------------------------------- the chi2 mode


def test_t2_to_chi2_is_the_chi2_with_the_same_tail_as_f() -> None:
    """T²/2 ~ F(2, ν): the conversion gives the χ²₂ value of the same upper-tail probability (scipy's F and χ²
    computed independently), and T² itself for ν = ∞."""
    from scipy import stats

    for nu in (2.0, 5.0, 30.0, 300.0):
        t2 = np.array([0.1, 1.0, 5.0, 20.0, 80.0])
        want = stats.chi2.isf(stats.f.sf(t2 / 2, 2, nu), 2)
        np.testing.assert_allclose(t2_to_chi2(t2, np.full(5, nu)), want, rtol=1e-8)
    np.testing.assert_array_equal(t2_to_chi2(np.array([3.0, 7.0]), np.array([np.inf, np.inf])), [3.0, 7.0])


def test_chi2_mode_fires_at_the_rate_of_the_z_test_even_at_a_cold_start() -> None:
    """Static windows drawn exactly from their reported covariance, the calibrated statistic with each window's own
    scale: χ² against the χ²₂ quantile of α fires no more often than α promises, whether the calibration is warm
    (scales known) or cold (scale_dof 2, heavy tails) — as the z's do. Before T² was converted from the
    F distribution of an estimated scale, it fired at 1.7× the nominal rate at a cold start (0.017 at α 2.58)."""
    from dataclasses import replace as dc_replace

    rng = np.random.default_rng(8)
    K, W, sig = 20000, 10, 0.2
    win = np.zeros((K, W, len(CHANNELS)))
    win[..., 0] = 30.0 + rng.normal(0, sig, (K, W))
    win[..., 1] = rng.normal(0, sig, (K, W))
    win[..., 2] = win[..., 4] = sig ** 2
    win[..., 5] = np.arange(W) * 0.1
    win[..., 8] = 100  # established observations
    masks = split_halves(np.zeros(K, np.int64), np.full(K, W), W)
    warm = dc_replace(NoiseModel.prior(), correlation=np.zeros((len(GROUPS), 2)))  # the noise drawn is white
    for model in (warm, dc_replace(warm, scale_dof=2.0)):
        st = calibrated_statistics(win, masks, np.zeros(K, np.int64), model, variance_floor=1e-4,
                                   effective_n="measured", track_scale_prior=True)
        for alpha in (1.96, 2.58):
            p = float(two_sided_p(alpha))
            rate = float((st.chi2 > chi2_2_threshold(alpha)).mean())
            assert p / 3 < rate < p + 4 * np.sqrt(p * (1 - p) / K), (model.scale_dof, alpha, rate)


@pytest.mark.parametrize("window", [2, 3, 4])
def test_windows_too_short_to_pool_keep_the_prior(window: int) -> None:
    """Blocks shorter than five observations are never pooled; with a window of 2–4 the fit had drawn its own
    prior's rank-deficient pseudo-blocks and came out at k 0.57–1.57: the scales stay the prior's 1."""
    cal = OnlineCalibration(window=window)
    cal.advance(0.0)
    cal.advance(1.0)
    model = cal.refit()
    np.testing.assert_allclose(model.scale, 1.0)
    np.testing.assert_allclose(model.correlation, NoiseModel.prior().correlation)


@pytest.mark.parametrize("text,needle", [
    ("format: jitterguard-calibration/1\nframe_interval_s: " + "9" * 400 + "\n", "a number too large for a float"),
    ("format: jitterguard-calibration/1\ngroups: {vehicle: {track_dof: " + "9" * 5000 + "}}\n", "a number too long"),
    ("[" * 20000 + "]" * 20000 + "\n", "nested too deep"),
    ("format: jitterguard-calibration/1\nwhen: 2024-02-30\n", "a value YAML cannot convert"),  # not "too long"
])
def test_well_formed_but_hostile_yaml_is_refused_in_one_line(text: str, needle: str) -> None:
    """A 400-digit number, one past Python's 4300-digit conversion limit and 20 000 nested lists had escaped as
    OverflowError, ValueError and RecursionError: tracebacks from `classifier --calibration-file` and `eval`, and a
    502 "internal error" from a config write naming the file (a 422 is promised)."""
    with pytest.raises(CalibrationFileError, match=needle):
        parse_calibration(text)


@pytest.mark.parametrize("edit,needle", [
    (lambda m: m.update(range_bands_m=[True]), "range_bands_m"),  # had read as a 1 m band
    (lambda m: m.update(range_bands_m=[float(i) for i in range(1, 10)]), "at most 8"),  # the config's own bound
    (lambda m: m.update(range_bands_m=[20.0, 5000.0]), "(0, 1000]"),
    (lambda m: m["groups"]["vehicle"]["along"]["blocks"].update({"0-2O": 3.0}), "blocks: expected a mapping over"),
], ids=["bool-edge", "nine-edges", "far-edge", "misspelt-band-under-blocks"])
def test_a_calibration_mapping_outside_the_configs_bounds_is_refused(edit, needle: str) -> None:
    data = NoiseModel.prior([20.0, 40.0]).to_mapping()
    edit(data)
    with pytest.raises(ValueError, match=re.escape(needle)):
        NoiseModel.from_mapping(data)
