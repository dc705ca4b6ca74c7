"""Late frame, jump, or a source that really started over? The header rules (``jitterguard.stream_order``) and the two
consumers that apply them — the tracker core on ``detections`` and the classifier's frame assembler on ``tracked`` —
fed the same header sequences, so they agree on which frames are taken and which are dropped.

The cases are the ones a deployment meets — a sensor driver restarted (seq from 0, time going on), a recording
started over, a long gap — and the ones a buggy upstream or an intruder sends: a stamp an hour ahead or 2^64 - 1, a
seq of 2^62, old frames re-sent between current ones, a replayed capture. One message never changes the state; a
discontinuity is followed once successive frames confirm it.
"""

from __future__ import annotations

import numpy as np
import pytest

from jitterguard.bench.tracker_sequences import CAR
from jitterguard.services.classifier.assembly import FrameAssembler
from jitterguard.services.tracker.arrays import DetectionFrame
from jitterguard.services.tracker.config import default_config
from jitterguard.services.tracker.core import FrameRejected, TrackerCore
from jitterguard.stream_order import StreamGuard, StreamLimits, Verdict

T0 = 1_700_000_000_000_000_000
MS = 1_000_000
PERIOD = 100 * MS
HOUR = 3600 * 10**9


def stream(n: int, *, seq0: int = 0, t0: int = T0) -> list[tuple[int, int]]:
    """``n`` headers (seq, stamp) of a 10 Hz source."""
    return [(seq0 + i, t0 + i * PERIOD) for i in range(n)]


def det_frame(seq: int, stamp: int, x: float = 10.0) -> DetectionFrame:
    return DetectionFrame(seq=seq, stamp_ns=stamp, ego_x=0.0, ego_y=0.0, ego_yaw=0.0, x=np.array([x]),
                          y=np.array([0.0]), yaw=np.zeros(1), label=np.array([CAR]))


def run_tracker(headers: list[tuple[int, int]], core: TrackerCore | None = None) -> tuple[list[str], TrackerCore]:
    """What the tracker does with each header: next / restarted / rewound / jumped, or the drop reason."""
    core = core or TrackerCore()
    out = []
    for seq, stamp in headers:
        try:
            res = core.step(det_frame(seq, stamp))
        except FrameRejected as rej:
            out.append(rej.reason)
            continue
        out.append("rewound" if res.reset else "restarted" if res.source_restarted else "jumped" if res.jumped
                   else "next")
    return out, core


def run_assembler(headers: list[tuple[int, int]]) -> tuple[list[bool], FrameAssembler]:
    """Which closes the classifier's assembler takes (each frame completes at once: no observations). The time
    condition of a confirmation is tested on its own above; here frames alone confirm, as in the tracker core
    driven without a clock."""
    fa: FrameAssembler = FrameAssembler(guard=StreamGuard(StreamLimits(confirm_s=0.0)))
    taken = []
    for k, (seq, stamp) in enumerate(headers):  # arriving at 10 Hz on the receiver's clock
        taken.append(fa.add_close_item(seq, [], None, now=k * 0.1, stamp_ns=stamp))
        fa.pop_ready(k * 0.1)
    return taken, fa


# ------------------------------------------------------------------------------------------- the header rules


@pytest.mark.parametrize(("seq", "stamp", "want"), [
    (11, T0 + PERIOD, Verdict.NEXT),
    (11, T0, Verdict.DUPLICATE),  # an equal stamp under a higher seq: the same instant, or a clock standing still
    (1010, T0 + 9 * 10**9, Verdict.NEXT),  # within both steps: a sensor back after a short gap
    (10, T0, Verdict.DUPLICATE),
    (10, T0 - PERIOD, Verdict.DUPLICATE),
    (7, T0 - 3 * PERIOD, Verdict.LATE),
    (12, T0 - PERIOD, Verdict.LATE),  # a higher seq from the past
    (0, T0 - HOUR, Verdict.LATE),
    (11, T0 + HOUR, Verdict.JUMP),  # a stamp an hour ahead
    (11, 2**63 - 1, Verdict.JUMP),
    (2**62, T0 + PERIOD, Verdict.JUMP),  # a seq far ahead
    (0, T0 + PERIOD, Verdict.JUMP),  # seq began again, time went on: a restart, not yet confirmed
    (10, T0 + PERIOD, Verdict.JUMP),  # the same seq, newer
])
def test_one_header_is_judged_against_the_newest_frame_taken(seq: int, stamp: int, want: Verdict) -> None:
    g = StreamGuard()
    assert g.admit(10, T0) is Verdict.NEXT  # the first frame is taken as it comes
    g.accept(10, T0)
    assert g.admit(seq, stamp) is want


def test_a_run_confirms_only_with_enough_frames_each_after_the_previous_and_enough_time() -> None:
    g = StreamGuard(StreamLimits(confirm_frames=3, confirm_s=0.5))
    g.accept(100, T0)
    restarted = stream(6, t0=T0 + 50 * PERIOD)  # seq 0.. with time going on
    assert [g.admit(s, t, now_s=k * 0.1) for k, (s, t) in enumerate(restarted)] == [Verdict.JUMP] * 5 + [Verdict.RESTARTED]
    g = StreamGuard(StreamLimits(confirm_frames=3, confirm_s=0.0))
    g.accept(100, T0)
    assert [g.admit(s, t) for s, t in stream(3, t0=T0 - HOUR)] == [Verdict.LATE, Verdict.LATE, Verdict.REWOUND]
    g = StreamGuard(StreamLimits(confirm_frames=3, confirm_s=0.0))
    g.accept(100, T0)
    assert [g.admit(s, t) for s, t in stream(3, seq0=2**62, t0=T0 + PERIOD)] == [Verdict.JUMP, Verdict.JUMP, Verdict.JUMPED]
    g = StreamGuard(StreamLimits(confirm_frames=3, confirm_s=0.0))
    g.accept(100, T0)
    g.admit(0, T0 + HOUR), g.admit(1, T0 + HOUR + PERIOD)
    g.accept(101, T0 + PERIOD)  # the live stream went on in between: the run is history
    assert g.admit(2, T0 + HOUR + 2 * PERIOD) is Verdict.JUMP


def test_a_flood_of_a_replayed_capture_never_outlasts_the_live_stream() -> None:
    """A capture of consecutive frames replayed as fast as it can be sent: every run starts afresh after the next live
    frame, and none lasts ``confirm_s`` on the receiver's clock."""
    g = StreamGuard()
    capture = stream(20, t0=T0)
    taken, now = 0, 0.0
    for k, (seq, stamp) in enumerate(stream(100, seq0=1000, t0=T0 + 60 * 10**9)):
        now = k * 0.05
        if g.admit(seq, stamp, now).accepted:
            g.accept(seq, stamp)
            taken += 1
        for s, t in capture:  # the whole capture between two live frames
            assert not g.admit(s, t, now + 0.001).accepted
    assert taken == 100


# ------------------------------------------------------------------------------------- tracker and classifier


def test_a_restarted_source_is_followed_once_confirmed_and_tracks_carry_on() -> None:
    first = stream(40, t0=T0)
    restarted = stream(10, t0=T0 + 42 * PERIOD)  # seq from 0 again, stamps after the gap
    got, core = run_tracker(first[:1])
    ids = list(core.tracks.ids)
    got, core = run_tracker(first[1:] + restarted, core)
    assert got == ["next"] * 39 + ["jump", "jump", "restarted"] + ["next"] * 7
    assert list(core.tracks.ids) == ids  # the same car, the same track: time went on, nothing to forget
    taken, fa = run_assembler(first + restarted)
    assert taken == [True] * 40 + [False, False] + [True] * 8 and fa.counts["source_restarts"] == 1
    assert "upstream_restarts" not in fa.counts  # time went on: the classifier keeps its windows


@pytest.mark.parametrize("age", [5, 15, 150])
def test_a_recording_started_over_is_taken_after_three_frames(age: int) -> None:
    """A replay killed ``age`` frames after it began starts again with its own first headers: frame for frame a
    re-send of old frames. Three in a row, each after the previous, settle it."""
    first, again = stream(age), stream(10)
    got, core = run_tracker(first + again)
    assert got[age:] == ["out_of_order", "out_of_order", "rewound"] + ["next"] * 7
    assert len(core.tracks) == 1 and core.last_seq == 9
    taken, fa = run_assembler(first + again)
    assert taken[age:] == [False, False] + [True] * 8
    assert fa.counts["upstream_restarts"] == 1 and fa.counts["duplicate_or_late_frames"] == 2


def test_the_assembler_follows_the_tracker_after_it_reset_on_a_rewind() -> None:
    """What reaches the classifier after a rewind: the tracker's frames from the third one on."""
    first = stream(15)
    got, _ = run_tracker(first + first[:10])
    published = [h for h, what in zip(first + first[:10], got) if what in ("next", "restarted", "rewound")]
    taken, fa = run_assembler(published)
    assert taken[15:] == [False, False, True] + [True] * 5
    assert fa.counts["upstream_restarts"] == 1


@pytest.mark.parametrize("bad", [(40, T0 + HOUR), (40, 2**63 - 1), (2**62, T0 + 40 * PERIOD), (0, T0 + 40 * PERIOD)])
def test_one_bad_header_changes_nothing_and_is_counted(bad: tuple[int, int]) -> None:
    """A stamp an hour ahead (or the largest int64), a seq of 2^62, a lone seq 0: dropped, no track lost, and the
    next normal frame is taken as if it had not been there."""
    frames = stream(40)
    got, core = run_tracker(frames)
    ids = list(core.tracks.ids)
    got, core = run_tracker([bad, *stream(5, seq0=40, t0=T0 + 40 * PERIOD)], core)
    assert got == ["jump"] + ["next"] * 5 and list(core.tracks.ids) == ids and core.last_seq == 44
    taken, fa = run_assembler([*frames, bad, *stream(5, seq0=40, t0=T0 + 40 * PERIOD)])
    assert taken == [True] * 40 + [False] + [True] * 5 and fa.counts["held_jumps"] == 1
    assert "upstream_restarts" not in fa.counts


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


def test_a_long_gap_within_the_stamp_step_is_just_the_next_frame() -> None:
    core = TrackerCore(default_config(stream=StreamLimits(max_stamp_step_s=30.0)))
    got, core = run_tracker(stream(5) + stream(3, seq0=5, t0=T0 + 25 * 10**9), core)
    assert got == ["next"] * 8


def test_frames_of_a_clock_that_stands_still_are_duplicates_and_the_table_stays_bounded() -> None:
    """A driver that stamps every scan alike (0, or a lost time sync) under new seqs: taken, such frames aged no
    track (dt 0), so clutter's tentative tracks never expired — 3,600 tracks after 300 frames of 20 returns."""
    rng = np.random.default_rng(0)
    core = TrackerCore()
    dropped = 0
    for k in range(300):
        xy = rng.uniform(0, 100, size=(20, 2))
        f = DetectionFrame(seq=k, stamp_ns=T0, ego_x=0.0, ego_y=0.0, ego_yaw=0.0, x=xy[:, 0], y=xy[:, 1],
                           yaw=np.zeros(20), label=np.zeros(20, np.int8), length=np.ones(20), width=np.ones(20))
        try:
            core.step(f)
        except FrameRejected as exc:
            assert exc.reason == "duplicate"
            dropped += 1
    assert dropped == 299 and len(core.tracks) <= 20
