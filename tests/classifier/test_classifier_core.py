"""Window bookkeeping of the classifier core: eviction, resizing, presets, the baseline, world-frame covariance.

These tests pin the paper's statistic (``PAPER``: reported variances as they are, H0 v = 0) so their expected
z values are the paper's equations; the calibrated statistic has its own tests (test_classifier_calibration.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from jitterguard.geometry import rotate_cov2
from jitterguard.schemas.models import ClassifierConfig, Label
from jitterguard.services.classifier.config import PRESETS
from jitterguard.services.classifier.core import (
    DYNAMIC, STATIC, UNDECIDED, MotionClassifierCore, Observations, stride_for_interval, window_for_interval)

AUTHORS_ALPHA = {"car": 2.58, "truck": 2.58, "bus": 2.58, "trailer": 1.64, "motorcycle": 1.96, "bicycle": 1.64,
                 "pedestrian": 1.28, "unknown": 1.96}
"""The authors' deployed per-class alpha as DESIGN.md lists them (spelled out: the preset file must hold these)."""


def obs(ids, x, y=None, label=Label.CAR, var=0.01, speed=None, seq=0, stamp_ns=0):
    n = len(ids)
    return Observations.from_lists(ids, np.full(n, int(label)), x, np.zeros(n) if y is None else y,
                                   np.full(n, var), np.zeros(n), np.full(n, var), speed, seq=seq, stamp_ns=stamp_ns)


A, B, C, D = (f"{i:032x}" for i in (10, 11, 12, 13))
PAPER = {"calibration": "off", "min_speed_mps": 0.0, "alpha_per_class": {}}


def paper(**kw) -> ClassifierConfig:
    """The paper's statistic with the given fields."""
    return ClassifierConfig(**{**PAPER, "effective_n": "cluster", **kw})


def test_split_uses_floor_older_and_ceil_newer():
    core = MotionClassifierCore(paper(effective_n="independent", variance_floor=1e-9))
    xs = [0.0, 0.0, 1.0]  # N=3: older = [0], newer = [0, 1] -> diff 0.5
    for x in xs:
        dec = core.update(obs([A], [x], var=1.0))
    assert dec.z_x[0] == pytest.approx(0.5 / np.sqrt(1.0 / 1 + 1.0 / 2))


def test_sliding_window_forgets_old_observations():
    core = MotionClassifierCore(paper(window_size=4))
    for t in range(4):
        core.update(obs([A], [t * 2.0]))  # moving
    assert core.last_decisions().state[0] == DYNAMIC
    for _ in range(4):
        dec = core.update(obs([A], [100.0]))  # stopped: the moving part slides out
    assert dec.state[0] == STATIC
    assert dec.mean_x[0] == pytest.approx(100.0)
    assert dec.window_length[0] == 4


def test_eviction_of_tracks_no_longer_reported():
    core = MotionClassifierCore(ClassifierConfig(), capacity=8)
    core.update(obs([A, B, C], [0.0, 1.0, 2.0]))
    assert core.retain(np.array([A, C], dtype="S32")) == 1
    assert sorted(core.track_ids()) == [A, C]
    dec = core.update(obs([B], [1.0]))  # B comes back: a fresh window
    assert dec.window_length[0] == 1 and dec.state[0] == UNDECIDED
    assert core.last_decisions(np.array([b"f" * 32])).window_length[0] == 0


def test_capacity_grows_and_rows_are_reused():
    core = MotionClassifierCore(ClassifierConfig(), capacity=8)
    ids = [f"{i:032x}" for i in range(100)]
    core.update(obs(ids, np.arange(100.0)))
    assert len(core.track_ids()) == 100
    core.retain(np.array(ids[:10], dtype="S32"))
    core.update(obs([f"{i:032x}" for i in range(1000, 1050)], np.zeros(50)))
    assert len(core.track_ids()) == 60
    for _ in range(3):
        dec = core.update(obs(ids[:10], np.arange(10.0)))
    assert (dec.window_length == 4).all()


def test_resizing_the_window_keeps_newest_in_order():
    core = MotionClassifierCore(paper(window_size=10, effective_n="independent", variance_floor=1e-9))
    for x in [0, 0, 0, 0, 0, 0, 0, 1, 1, 1]:
        core.update(obs([A], [float(x)], var=1.0))
    core.configure(paper(window_size=4, effective_n="independent", variance_floor=1e-9))
    d = core.last_decisions()
    assert d.window_length[0] == 4
    dec = core.update(obs([A], [1.0], var=1.0))  # window now [1, 1, 1, 1]
    assert dec.z_x[0] == pytest.approx(0.0)
    core.configure(paper(window_size=6, effective_n="independent", variance_floor=1e-9))
    dec = core.update(obs([A], [3.0], var=1.0))  # [1,1,1,1,3] -> older [1,1], newer [1,1,3]
    assert dec.window_length[0] == 5
    assert dec.z_x[0] == pytest.approx((5 / 3 - 1) / np.sqrt(1 / 2 + 1 / 3))


def _frames(core: MotionClassifierCore, n: int, interval_s: float, start: int = 0, ids=(A,)) -> None:
    """``n`` frames of static tracks ``ids``, ``interval_s`` apart, seq counting frames."""
    for k in range(start, start + n):
        core.update(obs(list(ids), np.zeros(len(ids)), seq=k, stamp_ns=int(round(k * interval_s * 1e9))))


@pytest.mark.parametrize(("hz", "window"), [(20.0, 20), (10.0, 20), (5.0, 10), (8.0, 16), (2.0, 10), (0.5, 10)])
def test_a_slower_stream_gets_the_same_span_in_fewer_observations(hz, window):
    core = MotionClassifierCore(ClassifierConfig())  # window_size 20 at the reference 10 Hz
    _frames(core, 60, 1.0 / hz)
    assert core.window == window
    assert core.last_decisions().window_length[0] == window  # the track's window holds that many, and no more
    assert core.calibration_state()["window"] == window


@pytest.mark.parametrize(("hz", "stride", "window"), [(10.0, 1, 20), (12.0, 1, 20), (15.0, 1, 20), (17.0, 2, 17),
                                                       (20.0, 2, 20), (30.0, 3, 20), (40.0, 4, 20), (100.0, 10, 20)])
def test_a_faster_stream_keeps_the_span_by_taking_every_kth_frame(hz, stride, window):
    core = MotionClassifierCore(ClassifierConfig())  # window_size 20 at the reference 10 Hz: 2 s
    _frames(core, 40 * stride + 5, 1.0 / hz)
    assert (core.stride, core.window) == (stride, window)
    assert core.last_decisions().window_length[0] == window
    newest_first = core._table.ordered(np.array([core._id_rows[0]]), window)[0, :, 5]  # the window's stamps
    np.testing.assert_allclose(np.diff(newest_first), stride / hz, rtol=1e-6)  # evenly every k-th frame


def test_the_stride_holds_at_a_rounding_edge_and_is_off_without_a_reference():
    cfg = ClassifierConfig()
    assert stride_for_interval(cfg, 1 / 14.0) == 1 and stride_for_interval(cfg, 1 / 16.5) == 2
    assert stride_for_interval(cfg, 1 / 15.5, current=1) == 1  # within 0.6 of the stride in force: kept
    assert stride_for_interval(cfg, 1 / 14.5, current=2) == 2
    assert stride_for_interval(cfg, 1 / 13.0, current=2) == 1
    for interval in (None, 0.0, -1.0, math.nan):
        assert stride_for_interval(cfg, interval) == 1 and stride_for_interval(cfg, interval, current=3) == 3
    assert stride_for_interval(cfg, 5e-324) == 100  # a nonsense rate is bounded
    assert stride_for_interval(ClassifierConfig(window_reference_hz=None), 0.01) == 1
    core = MotionClassifierCore(ClassifierConfig(window_reference_hz=None))
    _frames(core, 30, 0.05)
    assert core.stride == 1 and core.last_decisions().window_length[0] == 20  # every frame, as before


def test_a_restarted_fast_stream_keeps_its_stride():
    """A 20 Hz recording that starts over (stamps go back) is measured afresh, but keeps taking every second frame
    meanwhile: its windows do not take the first frames of the new start at twice the rate."""
    core = MotionClassifierCore(ClassifierConfig())
    _frames(core, 10, 0.05)
    assert core.stride == 2
    core.update(obs([A], [0.0], seq=0, stamp_ns=0))  # the recording starts over
    assert core.frame_interval_s is None and core.stride == 2
    taken = core.last_decisions().window_length[0]
    _frames(core, 4, 0.05, start=1)  # stamps 0.05 … 0.2 s: every second frame taken
    assert core.stride == 2 and core.last_decisions().window_length[0] == taken + 2


def test_a_fast_stream_is_tested_as_the_reference_rate_stream_of_its_kth_frames():
    """At 20 Hz the statistic on a frame that took its observation equals, to rounding, the one a 10 Hz stream
    of the same observations gives; a frame in between repeats it, while the hold runs on every frame."""
    rng = np.random.default_rng(11)
    ids = [f"{i:032x}" for i in range(12)]
    xs = rng.normal(0.0, 0.3, (81, 12)) + np.linspace(0.0, 4.0, 81)[:, None] * (np.arange(12) % 3 == 0)
    cfg = ClassifierConfig(calibration="off", dynamic_hold_s_per_class={"car": 0.15})
    fast, slow = MotionClassifierCore(cfg), MotionClassifierCore(cfg)
    called_on_odd = 0  # movers called dynamic on a frame whose window took nothing (the hold's clock ran on)
    for k in range(81):
        d_fast = fast.update(obs(ids, xs[k], seq=k, stamp_ns=k * 50_000_000, var=0.01))
        if k % 2:
            called_on_odd += int(((d_fast.state == DYNAMIC) & (before.state != DYNAMIC)).sum())
        if k % 2 == 0:
            d_slow = slow.update(obs(ids, xs[k], seq=k // 2, stamp_ns=k * 50_000_000, var=0.01))
            np.testing.assert_allclose(d_fast.z_x, d_slow.z_x, rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(d_fast.window_length, d_slow.window_length)
            before = d_fast
        else:
            np.testing.assert_array_equal(d_fast.z_x, before.z_x)  # the window took nothing: same statistic
            np.testing.assert_array_equal(d_fast.window_length, before.window_length)
    assert fast.stride == 2 and slow.stride == 1 and fast.window == slow.window == 20
    assert (d_fast.state == DYNAMIC).sum() >= 3  # the movers are caught
    assert called_on_odd >= 3  # 0.15 s after the first rejection: an odd frame of the fast stream
    assert (fast.last_decisions().state == slow.last_decisions().state).all()


def test_the_window_follows_the_configured_size_and_floor():
    for cfg, window in ((ClassifierConfig(window_size=10), 10), (ClassifierConfig(window_size=6), 6),
                        (ClassifierConfig(window_size=40), 10), (ClassifierConfig(window_reference_hz=None), 20),
                        (ClassifierConfig(window_size=30, min_window=14), 14),
                        (ClassifierConfig(window_size=40, window_reference_hz=2.0), 40)):
        core = MotionClassifierCore(cfg)
        _frames(core, 12, 0.5)  # 2 Hz
        assert core.window == window, cfg


def test_the_rate_is_per_frame_of_seq_and_robust_to_gaps_and_restarts():
    core = MotionClassifierCore(ClassifierConfig())
    for k in (0, 3, 6, 9, 12):  # a 10 Hz stream whose tracks are seen every third frame only
        core.update(obs([A], [0.0], seq=k, stamp_ns=k * 100_000_000))
    assert core.frame_interval_s == pytest.approx(0.1)
    assert core.window == 20
    _frames(core, 20, 0.1, start=13)
    core.update(obs([A], [0.0], seq=40, stamp_ns=60 * 10**9))  # one long pause does not move the median
    assert core.window == 20
    core.update(obs([A], [0.0], seq=0, stamp_ns=0))  # the recording starts over: its rate is measured afresh
    assert core.frame_interval_s is None
    _frames(core, 5, 0.5, start=1)
    assert core.window == 10


@pytest.mark.parametrize("pattern", ["jitter", "alternating", "pairs"])
def test_a_jittered_stream_keeps_its_window(pattern):
    """A 10 Hz driver whose stamps jitter by ±30 ms, alternate 50 / 150 ms or come in pairs 2 ms apart: the window
    stays at 20 observations. The median of successive intervals had swung it between 10 and 20 frame to frame,
    and every shrink dropped each track's oldest observations."""
    rng = np.random.default_rng(3)
    core = MotionClassifierCore(ClassifierConfig())
    windows = set()
    for k in range(300):
        t = {"jitter": k * 0.1 + rng.uniform(-0.03, 0.03), "alternating": k * 0.1 + (0.05 if k % 2 else 0.0),
             "pairs": (k // 2) * 0.2 + (k % 2) * 0.002}[pattern]
        d = core.update(obs([A], [0.0], seq=k, stamp_ns=int(round(t * 1e9))))
        if k >= 30:
            windows.add((core.window, core.stride, int(d.window_length[0])))
    assert windows == {(20, 1, 20)}


@pytest.mark.parametrize(("interval_s", "window"), [(1e-300, 20), (5e-324, 20), (1e300, 10), (math.inf, 10),
                                                     (math.nan, 20), (-1.0, 20)])
def test_extreme_intervals_give_a_window_in_bounds(interval_s, window):
    for ref in (0.1, 10.0, 1000.0):
        assert window_for_interval(ClassifierConfig(window_reference_hz=ref), interval_s) == window


def test_equal_stamps_keep_the_configured_window():
    core = MotionClassifierCore(ClassifierConfig())
    _frames(core, 25, 0.0)
    assert core.frame_interval_s is None and core.window == 20
    assert core.last_decisions().window_length[0] == 20


def test_a_config_write_resizes_at_the_measured_rate():
    core = MotionClassifierCore(ClassifierConfig())
    _frames(core, 12, 0.5)
    assert core.window == 10
    core.configure(ClassifierConfig(window_reference_hz=None))
    assert core.window == 20 and core.last_decisions().window_length[0] == 10  # kept, fills up to 20
    core.configure(ClassifierConfig(window_size=40))
    assert core.window == 10


def test_a_slow_streams_calibration_learns_blocks_of_its_window():
    """The online calibration of a 2 Hz stream is the one a fixed window of 10 gives: same blocks, same prior."""
    rng = np.random.default_rng(7)
    ids = [f"{i:032x}" for i in range(30)]
    xs = rng.normal(0.0, 0.3, (60, 30))
    cores = [MotionClassifierCore(ClassifierConfig()),
             MotionClassifierCore(ClassifierConfig(window_size=10, window_reference_hz=None))]
    for core in cores:
        for k in range(60):
            core.update(obs(ids, xs[k], seq=k, stamp_ns=k * 500_000_000, var=0.01))
            core.learn()
    a, b = (c.online_calibration for c in cores)
    assert a.window == b.window == 10
    assert a.counts["blocks"] == b.counts["blocks"] > 0
    np.testing.assert_allclose(a.current.scale, b.current.scale, rtol=1e-12)
    last = [c.last_decisions(np.array(ids, dtype="S32")) for c in cores]
    np.testing.assert_allclose(last[0].z_x, last[1].z_x, rtol=1e-12)


def test_per_class_alpha_and_authors_preset():
    assert PRESETS["authors"] == {"alpha_default": 1.96, "alpha_per_class": AUTHORS_ALPHA}
    assert ClassifierConfig().alpha_per_class == AUTHORS_ALPHA  # also the default
    cfg = paper(**PRESETS["authors"])
    core = MotionClassifierCore(cfg)
    ped, car = f"{1:032x}", f"{2:032x}"
    # both have z = 2.0: above the pedestrian's 1.28, below the car's 2.58
    for x in (0.0, 2.0 * np.sqrt(2 * 0.01)):
        core.update(Observations.from_lists([ped, car], [int(Label.PEDESTRIAN), int(Label.CAR)], [x, x], [0, 0],
                                            [0.01, 0.01], [0, 0], [0.01, 0.01]))
    d = core.last_decisions(np.array([ped, car], dtype="S32"))
    np.testing.assert_allclose(d.z_x, [2.0, 2.0])
    assert list(d.alpha) == [AUTHORS_ALPHA["pedestrian"], AUTHORS_ALPHA["car"]]
    assert list(d.state) == [DYNAMIC, STATIC]


def test_velocity_threshold_baseline_uses_tracker_speed_only():
    core = MotionClassifierCore(ClassifierConfig(mode="velocity_threshold", velocity_threshold=1.0))
    dec = core.update(obs([A, B], [0.0, 0.0], speed=[0.5, 3.0]))
    assert list(dec.state) == [STATIC, DYNAMIC]  # decides from the first observation
    dec = core.update(obs([A, B], [50.0, 0.0], speed=[0.5, 3.0]))  # position jumps do not matter
    assert list(dec.state) == [STATIC, DYNAMIC]


def test_baseline_thresholds_are_autowares_per_class():
    """Vehicles and motorcycles above 1.0 m/s, pedestrians (and bicycles, unknown) above 0.28 m/s, as Autoware's
    static_obstacle_avoidance.param.yaml (a motorcycle had been held to 0.28 m/s)."""
    core = MotionClassifierCore(ClassifierConfig(mode="velocity_threshold"))
    ids = [A, B, C, D]
    labels = [int(Label.CAR), int(Label.PEDESTRIAN), int(Label.UNKNOWN), int(Label.MOTORCYCLE)]
    dec = core.update(Observations.from_lists(ids, labels, [0] * 4, [0] * 4, [0.01] * 4, [0] * 4, [0.01] * 4,
                                              speed=[0.5, 0.5, 0.2, 0.5]))
    assert list(dec.state) == [STATIC, DYNAMIC, STATIC, STATIC]
    assert list(dec.threshold) == [1.0, 0.28, 0.28, 1.0]


def test_baseline_sustain_times_hold_the_speed_before_dynamic():
    """With Autoware's sustain times a car must stay above 1 m/s for 2 s; dropping below restarts the clock."""
    core = MotionClassifierCore(ClassifierConfig(mode="velocity_threshold", **PRESETS["autoware-sustain"]))
    states = []
    for k, v in enumerate([2.0] * 15 + [0.5] + [2.0] * 25):  # 10 Hz
        dec = core.update(obs([A], [0.0], speed=[v], stamp_ns=k * 100_000_000))
        states.append(int(dec.state[0]))
    assert states[:15] == [STATIC] * 15  # 1.4 s above: not yet
    assert states[15] == STATIC  # dropped below
    assert states[16:36] == [STATIC] * 20 and states[36] == DYNAMIC  # 2.0 s after the drop



def _states(config: ClassifierConfig, xs: np.ndarray, labels: list[int]) -> np.ndarray:
    """States of tracks A and B (one per label) fed the same x positions at 10 Hz, frame by frame."""
    core = MotionClassifierCore(config)
    out = []
    for k, x in enumerate(xs):
        dec = core.update(Observations.from_lists([A, B], labels, [x, x], [0.0, 0.0], [0.01] * 2, [0.0] * 2,
                                                  [0.01] * 2, [0.0, 0.0], stamp_ns=k * 100_000_000))
        out.append(dec.state.copy())
    return np.array(out)


def test_dynamic_hold_delays_every_run_of_rejections_by_its_length():
    """With a hold of 0.3 s at 10 Hz a track is dynamic exactly where the test has rejected H0 on this decision
    and the three before it; runs of rejections shorter than that never make it dynamic, and a run that ends
    restarts the clock. Only the classes given a hold wait (pedestrian here), the car's decisions are as without."""
    rng = np.random.default_rng(7)
    # walks off, stops, moves in bursts, then stands with jitter larger than it reports: runs of rejections of
    # many lengths
    steps = np.concatenate([np.zeros(10), np.full(12, 0.15), np.zeros(14), np.tile([0.4, 0.4] + [0.0] * 6, 4),
                            np.zeros(60)])
    noise = np.r_[np.full(68, 0.03), np.full(60, 0.25)]
    xs = np.cumsum(steps) + rng.normal(0.0, 1.0, steps.size) * noise
    labels = [int(Label.CAR), int(Label.PEDESTRIAN)]
    # the paper's window of 10: this trajectory's runs of rejections then come in both kinds (checked below)
    at_once = _states(ClassifierConfig(window_size=10), xs, labels)
    held = _states(ClassifierConfig(window_size=10, dynamic_hold_s_per_class={"pedestrian": 0.3}), xs, labels)
    assert np.array_equal(held[:, 0], at_once[:, 0])  # the car: no hold
    rej = at_once[:, 1] == DYNAMIC
    want = np.array([k >= 3 and rej[k - 3:k + 1].all() for k in range(len(rej))])
    assert np.array_equal(held[:, 1] == DYNAMIC, want)
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, rej.astype(int), 0])))[::2]  # lengths of the runs of rejections
    assert want.any() and (runs < 4).any() and (runs >= 4).any()  # the trajectory exercises both kinds of run
    assert (held[:, 1] == UNDECIDED).sum() == (at_once[:, 1] == UNDECIDED).sum()  # the hold decides, as soon


def test_a_mode_switch_restarts_the_hold():
    """A track held 0.3 s whose test rejected before a switch to the speed rule and back is not dynamic at once:
    the clock restarts with the test that now decides."""
    cfg = ClassifierConfig(dynamic_hold_s_per_class={"car": 0.3})
    core = MotionClassifierCore(cfg)
    stamps = iter(range(0, 10**10, 100_000_000))

    def step(x: float) -> int:
        return int(core.update(obs([A], [x], speed=[5.0], stamp_ns=next(stamps))).state[0])

    states = [step(0.5 * k) for k in range(6)]  # moving 5 m/s: rejects from the 2nd observation
    assert states[-1] == DYNAMIC
    core.configure(cfg.model_copy(update={"mode": "velocity_threshold"}))
    assert step(3.0) == DYNAMIC  # the speed rule
    core.configure(cfg)
    after = [step(3.0 + 0.5 * k) for k in range(1, 5)]
    assert after[:3] == [STATIC] * 3 and after[3] == DYNAMIC  # held 0.3 s again

def test_hold_preset_holds_every_class():
    cfg = ClassifierConfig.model_validate({**ClassifierConfig().model_dump(), **PRESETS["hold"]})
    assert {cfg.hold_for(int(lb)) for lb in Label} == {0.3}
    assert cfg.window_size == 10
    assert ClassifierConfig().hold_for(int(Label.CAR)) == 0.0  # off by default: the paper decides at once
    with pytest.raises(ValueError, match="unknown class name"):
        ClassifierConfig(dynamic_hold_s_per_class={"lorry": 1.0})
    with pytest.raises(ValueError) as err:  # a flood of made-up names is named in a line, not megabytes
        ClassifierConfig(alpha_per_class={f"k{i:06d}": 1.0 for i in range(300_000)})
    assert len(str(err.value)) < 2000 and "and 299995 more" in str(err.value)

def test_world_frame_rotation_of_covariance_matters():
    """A car parked along the world x-axis seen by a sensor rotated 90°: the detector is precise along
    its beam (sensor x) and loose across it. Rotated correctly, the loose axis is world x and the jitter
    there is explained; copying the sensor diagonal declares it moving."""
    rng = np.random.default_rng(0)
    ego_yaw = np.pi / 2
    sl, sa = 0.05, 0.5  # sensor-frame sigmas (along beam, across beam)
    cxx, cxy, cyy = rotate_cov2(sl**2, 0.0, sa**2, ego_yaw)
    assert cxx == pytest.approx(sa**2) and cyy == pytest.approx(sl**2)
    xs = np.concatenate([rng.normal(0, sa, 5) - 0.4, rng.normal(0, sa, 5) + 0.4])  # jitter along world x
    right = MotionClassifierCore(paper())
    wrong = MotionClassifierCore(paper())
    for x in xs:
        d_right = right.update(Observations.from_lists([A], [1], [x], [0.0], [cxx], [cxy], [cyy]))
        d_wrong = wrong.update(Observations.from_lists([A], [1], [x], [0.0], [sl**2], [0.0], [sa**2]))
    assert d_right.state[0] == STATIC
    assert d_wrong.state[0] == DYNAMIC


def test_duplicate_ids_in_one_frame_rejected():
    core = MotionClassifierCore()
    with pytest.raises(ValueError, match="unique"):
        core.update(obs([A, A], [0.0, 1.0]))
