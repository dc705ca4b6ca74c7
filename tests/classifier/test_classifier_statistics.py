"""The z-test (eq. 1, 2) and the χ² variant against independent computations and their statistical promises.

The paper's statistic: every config here takes the reported variances as they are (``calibration: off``) with
H0 v = 0 (``PAPER``); the calibrated statistic is tested in test_classifier_calibration.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import DYNAMIC, STATIC, UNDECIDED, MotionClassifierCore, Observations
from jitterguard.services.classifier.statistics import chi2_2_threshold, two_sided_p


PAPER = {"calibration": "off", "min_speed_mps": 0.0, "effective_n": "cluster", "alpha_per_class": {}}


def paper(**kw) -> ClassifierConfig:
    return ClassifierConfig(**{**PAPER, **kw})


def _ids(n: int) -> list[str]:
    return [f"{i + 1:032x}" for i in range(n)]


def feed(core: MotionClassifierCore, ids, xs, ys, cxx, cyy, cxy=None, labels=None, speed=None):
    """Feed per-frame columns: xs[t][k] is track k's x at frame t. Returns the last Decisions."""
    n = len(ids)
    dec = None
    for t in range(len(xs)):
        dec = core.update(Observations.from_lists(
            ids, labels if labels is not None else np.ones(n), xs[t], ys[t], cxx[t], np.zeros(n) if cxy is None else cxy[t],
            cyy[t], speed, seq=t))
    return dec


def reference_z(x: np.ndarray, var: np.ndarray, independent: bool, floor: float = 1e-4) -> float:
    """Straight from the paper: older floor(N/2) vs newer ceil(N/2), eq. 2 variances, eq. 1 statistic."""
    n = len(x)
    n1 = n // 2
    a, b = x[:n1], x[n1:]
    v1, v2 = max(var[:n1].mean(), floor), max(var[n1:].mean(), floor)
    k1, k2 = (len(a), len(b)) if independent else (1, 1)
    return abs(a.mean() - b.mean()) / np.sqrt(v1 / k1 + v2 / k2)


@pytest.mark.parametrize("independent", [False, True])
@pytest.mark.parametrize("n_frames", [2, 3, 7, 10, 14])
def test_z_matches_reference(independent, n_frames):
    rng = np.random.default_rng(n_frames)
    window = 10
    core = MotionClassifierCore(paper(window_size=window, effective_n="independent" if independent else "cluster"))
    x = rng.normal(0, 0.3, n_frames) + np.linspace(0, 0.5, n_frames)
    y = rng.normal(0, 0.3, n_frames)
    vx = rng.uniform(0.01, 0.2, n_frames)
    vy = rng.uniform(0.01, 0.2, n_frames)
    dec = feed(core, _ids(1), x[:, None], y[:, None], vx[:, None], vy[:, None])
    w = min(window, n_frames)
    assert dec.window_length[0] == w
    assert dec.z_x[0] == pytest.approx(reference_z(x[-w:], vx[-w:], independent), rel=1e-9)
    assert dec.z_y[0] == pytest.approx(reference_z(y[-w:], vy[-w:], independent), rel=1e-9)
    assert dec.mean_x[0] == pytest.approx(x[-w:].mean())


def test_variance_floor_applies_to_each_half():
    core = MotionClassifierCore(paper(variance_floor=0.01))
    x = np.array([0.0, 0.0, 0.1, 0.1])
    dec = feed(core, _ids(1), x[:, None], np.zeros((4, 1)), np.full((4, 1), 1e-9), np.full((4, 1), 1e-9))
    assert dec.z_x[0] == pytest.approx(0.1 / np.sqrt(0.02))


def test_alpha_threshold_matches_normal_quantile():
    assert float(two_sided_p(1.96)) == pytest.approx(2 * stats.norm.sf(1.96))
    for alpha in (1.28, 1.64, 1.96, 2.58):
        p = 2 * stats.norm.sf(alpha)
        assert float(chi2_2_threshold(alpha)) == pytest.approx(stats.chi2.isf(p, df=2), rel=1e-9)


def test_chi2_statistic_matches_direct_matrix_computation():
    rng = np.random.default_rng(3)
    core = MotionClassifierCore(paper(mode="chi2", effective_n="independent"))
    n = 8
    x, y = rng.normal(0, 0.2, n), rng.normal(0, 0.2, n)
    cxx, cyy = rng.uniform(0.02, 0.05, n), rng.uniform(0.02, 0.05, n)
    cxy = rng.uniform(-0.01, 0.01, n)
    dec = feed(core, _ids(1), x[:, None], y[:, None], cxx[:, None], cyy[:, None], cxy[:, None])
    h = n // 2
    d = np.array([x[h:].mean() - x[:h].mean(), y[h:].mean() - y[:h].mean()])
    s1 = np.array([[cxx[:h].mean(), cxy[:h].mean()], [cxy[:h].mean(), cyy[:h].mean()]]) / h
    s2 = np.array([[cxx[h:].mean(), cxy[h:].mean()], [cxy[h:].mean(), cyy[h:].mean()]]) / (n - h)
    assert dec.chi2[0] == pytest.approx(d @ np.linalg.solve(s1 + s2, d), rel=1e-9)


def _static_noise_rates(mode: str, n_tracks=4000, frames=10, seed=11):
    """Parked objects whose detections are drawn from exactly the covariance they report."""
    rng = np.random.default_rng(seed)
    core = MotionClassifierCore(paper(mode=mode, effective_n="independent"), capacity=n_tracks)
    sx = rng.uniform(0.05, 0.4, n_tracks)
    sy = rng.uniform(0.05, 0.4, n_tracks)
    xs = rng.normal(0, 1, (frames, n_tracks)) * sx + rng.uniform(-50, 50, n_tracks)
    ys = rng.normal(0, 1, (frames, n_tracks)) * sy
    dec = feed(core, _ids(n_tracks), xs, ys, np.tile(sx**2, (frames, 1)), np.tile(sy**2, (frames, 1)))
    return dec


def test_nominal_false_alarm_rate_in_independent_mode():
    """Under H0 each axis' z is |N(0,1)|: P(z_x > 1.96) = 5%; the χ² decision fires at exactly 5%;
    max(z_x, z_y) fires at 1 − 0.95² ≈ 9.75% — why the χ² variant exists."""
    dec = _static_noise_rates("z_test")
    n = len(dec.z_x)
    se = np.sqrt(0.05 * 0.95 / n)
    assert abs((dec.z_x > 1.96).mean() - 0.05) < 4 * se
    assert abs((dec.z_y > 1.96).mean() - 0.05) < 4 * se
    both = 1 - 0.95**2
    assert abs((dec.state == DYNAMIC).mean() - both) < 4 * np.sqrt(both * (1 - both) / n)
    chi = _static_noise_rates("chi2")
    assert abs((chi.state == DYNAMIC).mean() - 0.05) < 4 * se


def test_cluster_mode_is_more_conservative_than_independent():
    rng = np.random.default_rng(5)
    xs = rng.normal(0, 0.1, (10, 50)) + np.linspace(0, 0.3, 10)[:, None]
    v = np.full((10, 50), 0.01)
    z = {}
    for mode in ("cluster", "independent"):
        core = MotionClassifierCore(paper(effective_n=mode))
        z[mode] = feed(core, _ids(50), xs, np.zeros((10, 50)), v, v).z_x
    # equal halves of 5 and equal variances: sqrt(v/5 + v/5) vs sqrt(v + v) -> ratio sqrt(5)
    np.testing.assert_allclose(z["independent"], z["cluster"] * np.sqrt(5.0), rtol=1e-9)
    assert (z["independent"] > z["cluster"]).all()


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    shift=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
    mode=st.sampled_from(["z_test", "chi2"]),
)
def test_translation_and_arrival_order_invariance(seed, shift, mode):
    rng = np.random.default_rng(seed)
    n, frames = 12, 10
    ids = _ids(n)
    xs = rng.normal(0, 0.3, (frames, n)) + rng.uniform(0, 1, n) * np.arange(frames)[:, None] * 0.2
    ys = rng.normal(0, 0.3, (frames, n))
    cxx = rng.uniform(0.01, 0.1, (frames, n))
    cyy = rng.uniform(0.01, 0.1, (frames, n))
    cxy = rng.uniform(-0.005, 0.005, (frames, n))
    cfg = paper(mode=mode)
    base = feed(MotionClassifierCore(cfg), ids, xs, ys, cxx, cyy, cxy)
    moved = feed(MotionClassifierCore(cfg), ids, xs + shift[0], ys + shift[1], cxx, cyy, cxy)
    np.testing.assert_allclose(moved.z_x, base.z_x, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(moved.chi2, base.chi2, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(moved.state, base.state)
    # arrival order: a different permutation every frame
    core = MotionClassifierCore(cfg)
    for t in range(frames):
        p = rng.permutation(n)
        dec = core.update(Observations.from_lists([ids[i] for i in p], np.ones(n), xs[t, p], ys[t, p], cxx[t, p],
                                                  cxy[t, p], cyy[t, p], seq=t))
    inv = np.argsort(p)
    np.testing.assert_allclose(dec.z_x[inv], base.z_x, rtol=1e-12)
    np.testing.assert_array_equal(dec.state[inv], base.state)


def test_chi2_is_rotation_invariant_max_z_is_not():
    rng = np.random.default_rng(9)
    n, frames = 200, 10
    xs = rng.normal(0, 0.2, (frames, n)) + np.arange(frames)[:, None] * 0.05
    ys = rng.normal(0, 0.1, (frames, n))
    cxx, cyy, cxy = np.full((frames, n), 0.04), np.full((frames, n), 0.01), np.zeros((frames, n))
    th = 0.7
    c, s = np.cos(th), np.sin(th)
    rx, ry = c * xs - s * ys, s * xs + c * ys
    from jitterguard.geometry import rotate_cov2

    rcxx, rcxy, rcyy = rotate_cov2(cxx, cxy, cyy, th)
    out = {}
    for mode in ("z_test", "chi2"):
        a = feed(MotionClassifierCore(paper(mode=mode)), _ids(n), xs, ys, cxx, cyy, cxy)
        b = feed(MotionClassifierCore(paper(mode=mode)), _ids(n), rx, ry, rcxx, rcyy, rcxy)
        out[mode] = (a, b)
    np.testing.assert_allclose(out["chi2"][1].chi2, out["chi2"][0].chi2, rtol=1e-9)
    za = np.maximum(out["z_test"][0].z_x, out["z_test"][0].z_y)
    zb = np.maximum(out["z_test"][1].z_x, out["z_test"][1].z_y)
    assert np.abs(za - zb).max() > 0.1


def test_undecided_until_min_window():
    core = MotionClassifierCore(paper(min_window=4))
    ids = _ids(1)
    states = []
    for t in range(5):
        states.append(int(core.update(Observations.from_lists(ids, [1], [t * 5.0], [0], [0.01], [0], [0.01])).state[0]))
    assert states == [UNDECIDED, UNDECIDED, UNDECIDED, DYNAMIC, DYNAMIC]
    assert STATIC not in states


def test_statistics_stay_finite_and_dynamic_at_the_float_limit() -> None:
    """Positions ~1e300 apart (a broken upstream) used to give chi2 = inf (and NaN from inf - inf), which the
    state feed's own reader rejects until the track ages out: the statistics saturate instead."""
    from jitterguard.services.classifier.statistics import split_halves, window_statistics

    big = 1e300
    w = np.zeros((3, 4, 5))
    w[:, :, 2] = w[:, :, 4] = 0.01  # cxx, cyy
    w[0, 2:, 0] = big                # x jumps by 1e300: chi2 overflows
    w[1, 2:, 0] = w[1, 2:, 1] = big  # both axes, with a correlated covariance: inf - inf
    w[1, :, 3] = 0.005
    w[2, :2, 0], w[2, 2:, 0] = -1.7e308, 1.7e308  # the difference itself overflows
    masks = split_halves(np.zeros(3, dtype=np.int64), np.full(3, 4, dtype=np.int64), 4)  # slots 2, 3 newer
    for independent in (False, True):
        st = window_statistics(w, masks, variance_floor=1e-4, independent=independent)
        for arr in (st.z_x, st.z_y, st.chi2, st.mean_x, st.mean_y):
            assert np.isfinite(arr).all(), arr
        assert (st.chi2 > 1e6).all() and (np.maximum(st.z_x, st.z_y) > 1e6).all()
        assert st.mean_x[0] == pytest.approx(big / 2) and st.mean_x[2] == pytest.approx(0.0, abs=1e300)


def test_a_window_inside_the_speed_bound_has_z_zero_not_negative_zero() -> None:
    """−ndtri(½) is −0.0: a window whose contrast lies inside H0's speed bound had gone on the wire as z = −0.0
    (every viewer's label read "z=-0.00")."""
    from jitterguard.services.classifier.statistics import _saturate, t_to_z

    z = _saturate(t_to_z(np.array([0.0, -0.0, 1.5]), np.array([5.0, 5.0, 5.0])))
    assert not np.signbit(z).any() and z[0] == 0.0 and z[2] > 0


def test_the_chi2_threshold_keeps_its_meaning_up_to_the_largest_alpha_the_config_takes():
    """α may be up to 100; p = P(|Z| > α) underflows past α ≈ 37.5, and clipped to 1e-300 it had held the χ²₂
    threshold at 1381.6 from there on (α 50 fired at a χ² of 1400, a z of 37). The threshold is bracketed by the
    normal tail's Mills-ratio bounds φ(α)/α · (1 − 1/α²) < Φ(−α) < φ(α)/α, and it grows with α."""
    alphas = np.array([20.0, 30.0, 37.0, 37.6, 38.0, 40.0, 50.0, 75.0, 100.0])
    got = chi2_2_threshold(alphas)
    log_phi = -0.5 * alphas**2 - 0.5 * np.log(2 * np.pi)
    upper = -2.0 * (np.log(2.0) + log_phi - np.log(alphas) + np.log1p(-1.0 / alphas**2))  # p at its lower bound
    lower = -2.0 * (np.log(2.0) + log_phi - np.log(alphas))
    assert ((got > lower) & (got < upper)).all(), (got, lower, upper)
    assert (np.diff(got) > 0).all()
    # through the core: a window whose χ² is 2000 (an equivalent z of 44) is no motion at α 50
    core = MotionClassifierCore(paper(mode="chi2", alpha_default=50.0, window_size=2))
    d = float(np.sqrt(2000.0 * 2 * 0.01))  # cluster: χ² = d² / (σ₁² + σ₂²)
    dec = feed(core, _ids(1), np.array([[0.0], [d]]), np.zeros((2, 1)), np.full((2, 1), 0.01), np.full((2, 1), 0.01))
    assert dec.chi2[0] == pytest.approx(2000.0) and dec.state[0] == STATIC
    assert dec.threshold[0] == pytest.approx(got[6])


def test_t_to_z_keeps_its_meaning_where_the_tail_probability_underflows():
    """The calibrated statistic's t becomes a z with the same tail probability. Where that probability underflows
    (z beyond 37) the z had stuck at 37.04 and then jumped to |t| itself (ν 1000, t 100: z 100 where it is 49):
    for an α the config allows (up to 100) a window was called moving or static against its own evidence. Checked
    against the tail integrated numerically in the log domain and the normal tail inverted by root finding."""
    from classifier.reference_statistics import normal_score_of_log_tail, t_log_tail

    from jitterguard.services.classifier.statistics import t_to_z

    for nu in (2.0, 5.0, 12.0, 50.0, 300.0, 1000.0):
        ts = np.geomspace(5.0, 1e6, 60)
        z = t_to_z(ts, np.full(ts.shape, nu))
        assert (np.diff(z) > 0).all(), nu  # the evidence grows, the z with it: no plateau, no jump
        for t, zi in zip(ts[::7], z[::7]):
            assert zi == pytest.approx(normal_score_of_log_tail(t_log_tail(float(t), nu)), rel=1e-8), (nu, t)
    assert float(t_to_z(np.array([100.0]), np.array([1000.0]))[0]) == pytest.approx(48.958, abs=1e-3)
    assert float(t_to_z(np.array([np.inf]), np.array([12.0]))[0]) == np.inf


def test_a_window_that_did_not_move_has_chi2_zero_however_small_the_variance_floor():
    """variance_floor may be any positive number; below ~1e-154 the determinant of the half-means' covariance had
    underflowed to 0, and a window of identical positions with reported variances of 0 got χ² = 0 / 0, saturated to
    the largest float: called dynamic in the chi2 mode. A window that did move keeps z² = χ² on one axis."""
    for independent in (False, True):
        kw = dict(mode="chi2", variance_floor=1e-300, window_size=4, effective_n="independent" if independent
                  else "cluster")
        still = feed(MotionClassifierCore(paper(**kw)), _ids(1), np.full((4, 1), 3.0), np.zeros((4, 1)),
                     np.zeros((4, 1)), np.zeros((4, 1)))
        assert still.chi2[0] == 0.0 and still.state[0] == STATIC
        moved = feed(MotionClassifierCore(paper(**kw)), _ids(1), np.array([[0.0], [0.0], [1e-3], [1e-3]]),
                     np.zeros((4, 1)), np.zeros((4, 1)), np.zeros((4, 1)))
        assert moved.chi2[0] == pytest.approx(moved.z_x[0] ** 2, rel=1e-12) and moved.state[0] == DYNAMIC
