"""The classifier core fed what a broken upstream or clock produces (the wire refuses most of it; the offline
evaluator and tools drive the core directly): observations that must not enter a window, classes it does not
know, time going back, and the online calibration at the extreme of its config."""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.schemas.models import ClassifierConfig, Label
from jitterguard.services.classifier.calibration import GROUPS, OnlineCalibration, block_moments
from jitterguard.services.classifier.core import DYNAMIC, STATIC, UNDECIDED, MotionClassifierCore, Observations

T0 = 1_700_000_000_000_000_000
A, B = "a" * 32, "b" * 32
SIGMA = 0.1


def obs(seq: int, x, y, *, t: float | None = None, label=Label.CAR, cxx=SIGMA**2, cxy=0.0, cyy=SIGMA**2,
        ids=(A, B)) -> Observations:
    n = len(ids)
    col = lambda v: np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()  # noqa: E731
    t = seq * 0.1 if t is None else t
    return Observations.from_lists(list(ids), np.broadcast_to(int(label), (n,)), col(x), col(y), col(cxx), col(cxy),
                                   col(cyy), stamp_ns=T0 + int(round(t * 1e9)), seq=seq)


def parked(rng: np.random.Generator, n: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Two parked cars 15 and 25 m ahead, detected with the σ they report."""
    return 15.0 + 10.0 * np.arange(n) + rng.normal(0, SIGMA, n), 3.0 + rng.normal(0, SIGMA, n)


@pytest.mark.parametrize("bad", [
    dict(x=np.nan), dict(y=np.inf), dict(cxx=np.nan), dict(cxy=np.inf), dict(cyy=-0.01), dict(cxx=1e300),
    dict(cxy=0.5),  # |cxy| > sqrt(cxx·cyy): not a covariance
], ids=lambda d: ",".join(f"{k}={v}" for k, v in d.items()))
def test_a_broken_observation_stays_out_of_the_window(bad: dict) -> None:
    # taken, a NaN position had gone out as the static position (the window's mean) for a whole window, and a
    # NaN, negative or overflowing variance had saturated z: the parked car was called dynamic
    rng = np.random.default_rng(0)
    core = MotionClassifierCore(ClassifierConfig(jump_veto=False))
    for s in range(30):
        x, y = parked(rng)
        kw = dict(x=x, y=y, cxx=np.full(2, SIGMA**2), cxy=np.zeros(2), cyy=np.full(2, SIGMA**2))
        if s in (12, 25):  # track A's observation is broken in two frames
            for k, v in bad.items():
                kw[k][0] = v
        dec = core.update(obs(s, **kw))
        for name in ("z_x", "z_y", "chi2", "mean_x", "mean_y"):
            assert np.isfinite(getattr(dec, name)).all(), (s, name)
        assert s < 2 or dec.state.tolist() == [STATIC, STATIC], s
        assert dec.z_x.max() < 100.0 and dec.z_y.max() < 100.0, s
    # the broken frames were not counted: A's window holds the other observations, B's every one
    assert core.last_decisions().window_length.tolist() == [20, 20]
    assert core._table.seen[core._lookup(np.array([A, B], dtype="S32"))[0]].tolist() == [28, 30]


def test_a_track_whose_every_observation_is_broken_stays_undecided() -> None:
    core = MotionClassifierCore()
    for s in range(25):
        dec = core.update(obs(s, np.nan, 3.0))
        assert dec.state.tolist() == [UNDECIDED, UNDECIDED]
        assert np.isfinite(dec.mean_x).all()
    assert core.online_calibration.counts["blocks"] == 0


def test_a_class_the_classifier_does_not_know_is_unknown() -> None:
    # a label past the last had been clipped to PEDESTRIAN (alpha 1.28, the most sensitive), not read as UNKNOWN
    core = MotionClassifierCore()
    unknown = ClassifierConfig().alpha_for(int(Label.UNKNOWN))
    assert unknown != ClassifierConfig().alpha_for(int(Label.PEDESTRIAN))
    for label in (9, 200, -1):
        dec = core.update(obs(0, [1.0, 2.0], [0.0, 0.0], label=label))
        assert dec.alpha.tolist() == [unknown, unknown]


def test_time_going_back_does_not_hold_a_mover_static() -> None:
    # the hold's clock had started in the future: every rejection was held back until the stamps caught up, and a car
    # moving at 1 m/s all along was called static (zero twist) for the 100 s time had gone back — even with no hold
    rng = np.random.default_rng(1)
    core = MotionClassifierCore()
    stamps = [100.0 + 0.1 * i for i in range(30)] + [0.1 * i for i in range(30)]  # no reset in between
    states = []
    for s, t in enumerate(stamps):
        x, y = parked(rng)
        dec = core.update(obs(s, x + 1.0 * t, y, t=t))
        states.append(dec.state.tolist())
    assert all(st == [DYNAMIC, DYNAMIC] for st in states[25:]), states[25:]


def test_a_cell_with_neither_blocks_nor_prior_takes_the_level_above() -> None:
    # calibration_prior_blocks = 0 (the config allows it): the fit of an empty cell had come out k = 0, clipped to
    # 0.01 — every class, band and age nobody had measured yet was tested with σ taken 10× too large
    rng = np.random.default_rng(2)
    cal = OnlineCalibration(prior_blocks=0.0, window=10)
    n_blk, n, k_true = 200, 10, 4.0
    t = np.arange(n) * 0.1 + rng.uniform(0, 100, (n_blk, 1))
    pos = np.stack([rng.uniform(10, 18, n_blk), np.zeros(n_blk)], -1)[:, None, :] \
        + rng.normal(0, SIGMA * np.sqrt(k_true), (n_blk, n, 2))  # all within 20 m: the first band only
    cov = np.tile([SIGMA**2, 0.0, SIGMA**2], (n_blk, n, 1))
    cal.add(np.full(n_blk, GROUPS.index("vehicle")), block_moments(t, pos, cov, np.zeros((n_blk, n, 2))))
    scale = cal.refit().scale
    vehicle, pedestrian = GROUPS.index("vehicle"), GROUPS.index("pedestrian")
    assert scale[vehicle, :, 0, 0] == pytest.approx(k_true, rel=0.25)  # measured
    assert scale[vehicle, :, 1:, 0] == pytest.approx(np.broadcast_to(scale[vehicle, :, :1, 0], (2, 2)), rel=0.25)
    assert (scale[pedestrian] > 1.0).all()  # the all-classes level (k_true shrunk a little towards 1), not 0.01
