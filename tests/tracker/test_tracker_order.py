"""Late frame or restarted source? The header rules (``jitterguard.stream_order``) and the two consumers that
apply them — the tracker core on ``detections`` and the classifier's frame assembler on ``tracked`` — fed the
same header sequences, so they agree on which frames start a new stream and which are dropped.

The cases are the ones a deployment meets: a sensor driver (or a replay on ``--stamps wall``) restarted, seq
from 0 with time going on; a recording restarted soon after it began, repeating its own first headers; a
recording restarted long after (the old ``rewind_reset_s`` rule); and a relay re-sending old frames between
current ones, which must stay dropped.
"""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.services.classifier.assembly import RESTART_GAP, FrameAssembler
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.core import FrameRejected, TrackerCore
from jitterguard.services.tracker.arrays import DetectionFrame
from jitterguard.stream_order import BehindRun, Verdict, judge
from jitterguard.bench.tracker_sequences import CAR

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
PERIOD = 100 * MS


def stream(n: int, *, seq0: int = 0, t0: int = T0) -> list[tuple[int, int]]:
    """``n`` headers (seq, stamp) of a 10 Hz source."""
    return [(seq0 + i, t0 + i * PERIOD) for i in range(n)]


def det_frame(seq: int, stamp: int, x: float = 10.0) -> DetectionFrame:
    return DetectionFrame(seq=seq, stamp_ns=stamp, ego_x=0.0, ego_y=0.0, ego_yaw=0.0, x=np.array([x]),
                          y=np.array([0.0]), yaw=np.zeros(1), label=np.array([CAR]))


def run_tracker(headers: list[tuple[int, int]], core: TrackerCore | None = None) -> tuple[list[str], TrackerCore]:
    """What the tracker does with each header: next / restarted / rewound, or the drop reason."""
    core = core or TrackerCore()
    out = []
    for seq, stamp in headers:
        try:
            res = core.step(det_frame(seq, stamp))
        except FrameRejected as rej:
            out.append(rej.reason)
            continue
        out.append("rewound" if res.reset else "restarted" if res.source_restarted else "next")
    return out, core


def run_assembler(headers: list[tuple[int, int]]) -> tuple[list[bool], FrameAssembler]:
    """Which closes the classifier's assembler takes (each frame completes at once: no observations)."""
    fa: FrameAssembler = FrameAssembler()
    taken = []
    for seq, stamp in headers:
        taken.append(fa.add_close_item(seq, [], None, now=0.0, stamp_ns=stamp))
        fa.pop_ready(0.0)
    return taken, fa


# ------------------------------------------------------------------------------------------- the header rules


@pytest.mark.parametrize(("seq", "stamp", "want"), [
    (11, T0 + PERIOD, Verdict.NEXT),
    (11, T0, Verdict.NEXT),  # an equal stamp under a higher seq (as before)
    (10, T0, Verdict.DUPLICATE),
    (10, T0 - PERIOD, Verdict.DUPLICATE),
    (0, T0 + PERIOD, Verdict.RESTARTED),  # seq began again, time went on: a restarted driver
    (10, T0 + PERIOD, Verdict.RESTARTED),  # the same seq, but newer: not a duplicate
    (7, T0 - 3 * PERIOD, Verdict.LATE),
    (12, T0 - PERIOD, Verdict.LATE),  # a higher seq from the past
    (0, T0 - 11 * 10**9, Verdict.REWOUND),  # further back than rewind_reset_s
])
def test_judge(seq: int, stamp: int, want: Verdict) -> None:
    assert judge(seq, stamp, 10, T0, rewind_reset_ns=10e9) is want


def test_judge_first_frame_and_disabled_rewind() -> None:
    assert judge(5, T0, None, None) is Verdict.NEXT
    assert judge(0, T0 - 3600 * 10**9, 10, T0, rewind_reset_ns=0) is Verdict.LATE


def test_behind_run_needs_consecutive_frames_each_after_the_previous() -> None:
    run = BehindRun(3)
    assert [run.behind(s, t) for s, t in stream(3)] == [False, False, True]
    run = BehindRun(3)
    assert not run.behind(0, T0) and not run.behind(1, T0 + PERIOD)
    assert not run.behind(0, T0)  # went back within the run: starts again
    assert not run.behind(1, T0 + PERIOD) and run.behind(2, T0 + 2 * PERIOD)
    run = BehindRun(3)
    run.behind(0, T0), run.behind(1, T0 + PERIOD)
    run.clear()  # something newer was accepted in between
    assert not run.behind(2, T0 + 2 * PERIOD)
    assert not any(BehindRun(0).behind(s, t) for s, t in stream(10))


# ------------------------------------------------------------------------------------- tracker and classifier


def test_a_source_restarted_with_time_going_on_is_followed_at_once_and_tracks_carry_on() -> None:
    first = stream(40, t0=T0)
    restarted = stream(10, t0=T0 + 42 * PERIOD)  # seq from 0 again, stamps after the gap
    got, core = run_tracker(first[:1])
    ids = list(core.tracks.ids)
    got, core = run_tracker(first[1:] + restarted, core)
    assert got == ["next"] * 39 + ["restarted"] + ["next"] * 9
    assert list(core.tracks.ids) == ids  # the same car, the same track: time went on, nothing to forget
    taken, fa = run_assembler(first + restarted)
    assert all(taken) and fa.counts["upstream_restarts"] == 1


@pytest.mark.parametrize("age", [5, 15, 60])
def test_a_young_recording_restarted_is_taken_after_three_frames(age: int) -> None:
    """A replay killed ``age`` frames after it began starts again with its own first headers, stamps back by
    less than rewind_reset_s: frame for frame a re-send of old frames. Three in a row settle it."""
    first, again = stream(age), stream(10)
    got, core = run_tracker(first + again)
    assert got[age:] == ["out_of_order", "out_of_order", "rewound"] + ["next"] * 7
    assert len(core.tracks) == 1 and core.last_seq == 9
    taken, fa = run_assembler(first + again)
    far = age - 1 > RESTART_GAP  # the assembler's older rule: a seq that far back is a restart at once
    assert taken[age:] == [True] * 10 if far else [False, False, True] + [True] * 7
    assert fa.counts["upstream_restarts"] == 1 and fa.counts.get("duplicate_or_late_frames", 0) == (0 if far else 2)


def test_the_assembler_follows_the_tracker_after_it_reset_on_a_rewind() -> None:
    """What reaches the classifier after a young rewind: the tracker's frames from the third one on."""
    first = stream(15)
    got, _ = run_tracker(first + first[:10])
    published = [h for h, what in zip(first + first[:10], got) if what in ("next", "restarted", "rewound")]
    taken, fa = run_assembler(published)
    assert taken[15:] == [False, False, True] + [True] * 5
    assert fa.counts["upstream_restarts"] == 1


def test_a_recording_restarted_long_after_resets_at_once() -> None:
    first = stream(150)  # 15 s: further than rewind_reset_s (10 s)
    got, core = run_tracker(first + first[:3])
    assert got[150:] == ["rewound", "next", "next"]


def test_old_frames_re_sent_between_current_ones_stay_dropped() -> None:
    """The hostile relay: after each current frame, now and then the frame from ten back (or a duplicate)."""
    rng = np.random.default_rng(3)
    headers = []
    frames = stream(200)
    for i, h in enumerate(frames):
        headers.append(h)
        r = rng.random()
        if r < 0.3 and i >= 10:
            headers.append(frames[i - 10])
        elif r < 0.4:
            headers.append(h)
    got, core = run_tracker(headers)
    assert "rewound" not in got and "restarted" not in got
    assert got.count("next") == 200 and core.last_seq == 199
    assert got.count("out_of_order") + got.count("duplicate") == len(headers) - 200
    taken, fa = run_assembler(headers)
    assert sum(taken) == 200 and "upstream_restarts" not in fa.counts


def test_a_short_rewind_without_confirmation_waits_for_the_stamps_to_pass() -> None:
    first = stream(15)
    core = TrackerCore(default_config(rewind_confirm_frames=0))
    got, _ = run_tracker(first + stream(20), core)
    assert got[15:] == ["out_of_order"] * 14 + ["duplicate", "next", "next", "next", "next", "next"]  # as before
