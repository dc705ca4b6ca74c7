"""The online calibration learns a bounded number of filled windows per frame: a frame in which every track's window
fills at once (all of a scene's tracks born together) spreads its pooling over the next frames instead of
stalling one, and loses none of them."""

from __future__ import annotations

import numpy as np

from jitterguard.schemas.models import ClassifierConfig
from jitterguard.services.classifier.core import LEARN_BLOCKS_PER_FRAME, MotionClassifierCore, Observations

W = 10


def _frame(n: int, k: int, rng: np.random.Generator, ids: np.ndarray | None = None) -> Observations:
    """``n`` parked cars seen every frame at 10 Hz with 0.1 m of jitter (slow blocks: all of them pool)."""
    ids = np.array([f"{i:032x}" for i in range(n)], dtype="S32") if ids is None else ids
    base = np.stack([np.arange(len(ids)) * 6.0 % 60.0 + 5.0, np.arange(len(ids)) // 10 * 5.0], axis=1)
    pos = base + rng.normal(0.0, 0.1, (len(ids), 2))
    return Observations(track_ids=ids, labels=np.ones(len(ids), dtype=np.int64), x=pos[:, 0], y=pos[:, 1],
                        cxx=np.full(len(ids), 0.01), cxy=np.zeros(len(ids)), cyy=np.full(len(ids), 0.01),
                        speed=np.zeros(len(ids)), stamp_ns=1_700_000_000_000_000_000 + k * 100_000_000, seq=k)


def _core() -> MotionClassifierCore:
    return MotionClassifierCore(ClassifierConfig(window_size=W, window_reference_hz=None), capacity=8)


def test_windows_that_fill_together_are_pooled_over_several_frames_and_all_of_them() -> None:
    n = 3 * LEARN_BLOCKS_PER_FRAME + 5
    rng = np.random.default_rng(0)
    core = _core()
    pooled = []
    for k in range(2 * W):
        core.update(_frame(n, k, rng))
        core.learn()  # the service's settle, after objects
        pooled.append(core.online_calibration.counts["blocks"])
    steps = np.diff([0, *pooled])
    assert steps.max() <= LEARN_BLOCKS_PER_FRAME  # never the whole burst in one frame
    assert (steps[: W - 1] == 0).all()
    assert (steps[W - 1: W + 2] == LEARN_BLOCKS_PER_FRAME).all()  # the burst spread over the next frames
    assert pooled[W + 2] == n  # none lost: every track's first full window pooled once
    # each window pooled restarts its count, so the next ones fill in W-frame steps after: the burst stays spread
    assert steps[2 * W - 1] == LEARN_BLOCKS_PER_FRAME and pooled[-1] == n + LEARN_BLOCKS_PER_FRAME


def test_a_frame_pools_once_even_when_update_and_settle_both_ask() -> None:
    """update() learns first when no settle ran since the last frame; after a settle it must not pool a second
    batch on the latency path."""
    n = 2 * LEARN_BLOCKS_PER_FRAME
    rng = np.random.default_rng(1)
    core = _core()
    for k in range(W):
        core.update(_frame(n, k, rng))
    core.learn()
    assert core.online_calibration.counts["blocks"] == LEARN_BLOCKS_PER_FRAME
    core.update(_frame(n, W, rng))  # a frame came: its learn() at the start pools nothing new (settle ran)
    assert core.online_calibration.counts["blocks"] == LEARN_BLOCKS_PER_FRAME
    core.learn()
    assert core.online_calibration.counts["blocks"] == n


def test_a_track_that_ends_while_its_window_waits_is_pooled_once_on_eviction() -> None:
    n = 2 * LEARN_BLOCKS_PER_FRAME
    rng = np.random.default_rng(2)
    core = _core()
    ids = np.array([f"{i:032x}" for i in range(n)], dtype="S32")
    for k in range(W):
        core.update(_frame(n, k, rng, ids))
    core.learn()  # half the burst pooled, half waiting
    assert core.online_calibration.counts["blocks"] == LEARN_BLOCKS_PER_FRAME
    core.retain(ids[: LEARN_BLOCKS_PER_FRAME // 2])  # most tracks end, waiting ones among them
    # every ended waiting window pooled whole on eviction; nothing waits twice or is pooled twice
    assert core.online_calibration.counts["blocks"] == n
    for k in range(W, W + 3):
        core.update(_frame(n, k, rng, ids[: LEARN_BLOCKS_PER_FRAME // 2]))
        core.learn()
    assert core.online_calibration.counts["blocks"] == n
