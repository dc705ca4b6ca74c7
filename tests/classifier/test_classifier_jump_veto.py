"""The jump veto (``jump_veto``): a full window that one jump of the box explains better than steady motion (a line,
or a stand that starts or stops) is not called dynamic — a detector that re-places a parked car's box once is not
a moving car — while a car that moves, steadily, accelerating, starting or stopping in the window, stays dynamic;
and ``jump_ratio`` computes what its docstring says, checked against a direct loop over every split and knot."""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.schemas.models import ClassifierConfig, Label
from jitterguard.services.classifier.core import (DYNAMIC, JUMP_VETO_MIN_VEHICLE, STATIC, MotionClassifierCore,
                                                  Observations)
from jitterguard.services.classifier.statistics import CHANNELS, jump_ratio

SIGMA = 0.05
HZ = 10.0
CAR_ID = f"{1:032x}"


def _sse(design: np.ndarray, xy: np.ndarray) -> float:
    """Residual sum of squares of both axes about their least-squares fit on ``design``'s columns."""
    return float(np.sum((xy - design @ np.linalg.lstsq(design, xy, rcond=None)[0]) ** 2))


def _direct_ratio(t: np.ndarray, xy: np.ndarray) -> float:
    """SSE about the best single step (two or more a side) over SSE about the best of the least-squares line and
    the one-sided hinges (a stand, then motion from the knot on; motion up to the knot, then a stand; two or more
    observations a side) where the step beats the line, by brute force over every split and knot."""
    tc, xyc = t - t.mean(), xy - xy.mean(0)  # epoch stamps and UTM positions would lose the digits compared
    one = np.ones_like(tc)
    motion = [_sse(np.stack([one, tc], 1), xyc)]
    for tj in tc:
        for h, still in ((np.maximum(tc - tj, 0.0), tc <= tj), (np.minimum(tc - tj, 0.0), tc >= tj)):
            if still.sum() >= 2 and (~still).sum() >= 2:
                motion.append(_sse(np.stack([one, h], 1), xyc))
    steps = [sum(float(np.sum((seg - seg.mean(0)) ** 2)) for seg in (xyc[:k], xyc[k:])) for k in range(2, len(t) - 1)]
    # where no step beats the line, the hinges cannot bring the ratio below 1: it is reported against the line
    return min(steps) / (min(motion) if min(steps) < motion[0] else motion[0])


def test_jump_ratio_matches_a_direct_loop_over_every_split() -> None:
    rng = np.random.default_rng(3)
    k, w = 300, 20
    win = rng.normal(0.0, 50.0, (k, w, len(CHANNELS)))  # stale slots hold garbage: it must not count
    count = rng.integers(0, w + 1, k)
    for i in range(k):
        n = int(count[i])
        t = 1.7e9 + np.sort(rng.uniform(0.0, 2.0, n))  # epoch stamps: the centring keeps their precision
        shape = rng.choice(["ramp", "step", "noise", "start"])
        knot = rng.uniform(0.3, 1.7)
        since = t - (t[0] if n else 0.0)  # seconds into the window
        base = {"ramp": np.outer(since, rng.normal(0, 3, 2)),
                "start": np.outer(np.maximum(since - knot, 0.0), rng.normal(0, 3, 2)),
                "step": np.outer(np.arange(n) >= rng.integers(2, max(n - 1, 3)), rng.normal(0, 2, 2)),
                "noise": np.zeros((n, 2))}[shape]
        win[i, w - n:, 0:2] = 4e5 + base + rng.normal(0.0, 0.1, (n, 2))  # far from the origin, as UTM would be
        win[i, w - n:, 5] = t
    got = jump_ratio(win, count, min_count=6)
    for i in range(k):
        n = int(count[i])
        if n < 6:
            assert got[i] == np.inf
        else:
            want = _direct_ratio(win[i, w - n:, 5], win[i, w - n:, 0:2])
            assert got[i] == pytest.approx(want, rel=1e-6)
    assert np.isfinite(got).sum() > 100 and (got < 1).any() and (got > 3).any()


def test_jump_ratio_gives_no_evidence_of_a_jump_on_broken_windows() -> None:
    win = np.zeros((3, 10, len(CHANNELS)))
    win[..., 5] = np.arange(10) * 0.1
    win[0, 4, 0] = np.nan  # a NaN position
    win[1, :, 0] = 2.0  # a window that does not move at all: a line fits it exactly
    win[2, :, 5] = 1.0  # every stamp equal: no line to fit, the step decides nothing
    win[2, 5:, 0] = 1.0
    assert np.all(jump_ratio(win, np.array([10, 10, 10])) == np.inf)


def _drive(core: MotionClassifierCore, centres: np.ndarray, rng: np.random.Generator,
           label: Label = Label.CAR) -> list[int]:
    """One frame per row of ``centres`` (the detected centre before jitter), a stopped sensor; the states."""
    states = []
    for j, p in enumerate(centres):
        seen = p + rng.normal(0.0, SIGMA, 2)
        dec = core.update(Observations.from_lists(
            [CAR_ID], [int(label)], [seen[0]], [seen[1]], np.full(1, SIGMA**2), np.zeros(1), np.full(1, SIGMA**2),
            stamp_ns=int(j / HZ * 1e9), seq=j, sensor_x=0.0, sensor_y=-10.0))
        states.append(int(dec.state[0]))
    return states


def _config(veto: bool) -> ClassifierConfig:
    return ClassifierConfig(calibration="off", effective_n="independent", jump_veto=veto)


def test_a_parked_box_replaced_once_is_static_with_the_veto_and_moving_without() -> None:
    frames = 30
    centres = np.zeros((frames, 2))
    centres[15:, 0] = 0.8  # the detector re-places the box 0.8 m along the car at frame 15
    without = _drive(MotionClassifierCore(_config(False)), centres, np.random.default_rng(0))
    veto = _drive(MotionClassifierCore(_config(True)), centres, np.random.default_rng(0))
    assert DYNAMIC in without[19:]  # the jump is 16σ of the jitter: the half-means differ
    assert all(s == STATIC for s in veto[19:])  # every full window holds the step


@pytest.mark.parametrize("accel", [0.0, 2.0], ids=["steady 3 m/s", "accelerating at 2 m/s² from 1 m/s"])
def test_a_moving_car_stays_dynamic_with_the_veto(accel: float) -> None:
    frames = 30
    t = np.arange(frames) / HZ
    centres = np.stack([1.0 * t + (3.0 - 1.0) * t * (accel == 0) + 0.5 * accel * t**2, np.zeros(frames)], 1)
    states = _drive(MotionClassifierCore(_config(True)), centres, np.random.default_rng(1))
    assert all(s == DYNAMIC for s in states[19:])


@pytest.mark.parametrize("starts", [True, False], ids=["starts", "stops"])
def test_a_car_that_starts_or_stops_in_the_window_stays_dynamic_with_the_veto(starts: bool) -> None:
    """A stand that turns into motion (or motion into a stand) half way through the window: one step fits it better
    than one straight line, so a veto that weighed the step against the line alone would call it static; the
    one-sided hinges keep it a mover."""
    frames = 40
    t = np.arange(frames) / HZ
    knot = 2.0 if starts else 1.6  # the frame where the car starts, or stops
    x = 3.0 * np.maximum(t - knot, 0.0) if starts else 3.0 * np.minimum(t, knot)
    states = _drive(MotionClassifierCore(_config(True)), np.stack([x, np.zeros(frames)], 1), np.random.default_rng(2))
    without = _drive(MotionClassifierCore(_config(False)), np.stack([x, np.zeros(frames)], 1), np.random.default_rng(2))
    moving = slice(25, 30) if starts else slice(17, 25)  # full windows that hold both the stand and the motion
    assert all(s == DYNAMIC for s in without[moving])
    assert states[moving] == without[moving]


def test_a_young_vehicle_window_is_vetoed_a_young_pedestrian_window_is_not() -> None:
    """The box re-placed at the track's fifth frame: from JUMP_VETO_MIN_VEHICLE observations on, a car's window is
    examined (a detector re-places a car's box most often as it comes out of occlusion, when the track is young);
    a pedestrian's only once its window is full — until then the test alone decides."""
    frames = 12  # windows of up to 12 observations: never full (20)
    centres = np.zeros((frames, 2))
    centres[4:, 0] = 0.8
    car = _drive(MotionClassifierCore(_config(True)), centres, np.random.default_rng(5), Label.CAR)
    walker = _drive(MotionClassifierCore(_config(True)), centres, np.random.default_rng(5), Label.PEDESTRIAN)
    bare = _drive(MotionClassifierCore(_config(False)), centres, np.random.default_rng(5), Label.CAR)
    bare_walker = _drive(MotionClassifierCore(_config(False)), centres, np.random.default_rng(5), Label.PEDESTRIAN)
    assert JUMP_VETO_MIN_VEHICLE <= 6 and DYNAMIC in bare[6:]  # the test alone calls the jump moving
    assert all(s == STATIC for s in car[6:])
    assert DYNAMIC in bare_walker[6:] and walker == bare_walker  # the same draws: no veto before a full window
