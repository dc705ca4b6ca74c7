"""The replay loop without Zenoh: windowing, looping, numbering, re-stamping, error policy, stopping."""

from __future__ import annotations

import threading
from dataclasses import replace

import pytest

from jitterguard.schemas import encode
from jitterguard.services.replay.adapter import message_for
from jitterguard.services.replay.frames import EgoPose, Frame, FrameError, SourceError
from replay.helpers import FakeClock
from jitterguard.services.replay.runner import ReplayPlan, run_replay
from jitterguard.services.replay.sources.base import MemorySource

from .helpers import MS, ExplodingSource, memory, scan


class Sink:
    def __init__(self) -> None:
        self.out: list[tuple[str, int, int]] = []

    def __call__(self, frame: Frame, seq: int, stamp: int) -> None:
        self.out.append((frame.origin, seq, stamp))


def test_plays_every_frame_once_in_order_with_recorded_stamps() -> None:
    sink = Sink()
    stats = run_replay(memory(4), ReplayPlan(rate=None), sink, clock=FakeClock())
    assert [o for o, _, _ in sink.out] == ["mem#0", "mem#1", "mem#2", "mem#3"]
    assert [s for _, s, _ in sink.out] == [0, 1, 2, 3]
    assert [t for _, _, t in sink.out] == [0, 100 * MS, 200 * MS, 300 * MS]
    assert (stats.published, stats.passes, stats.errors, stats.last_seq) == (4, 1, 0, 3)


def test_real_rate_sleeps_the_recorded_spacing_on_the_fake_clock() -> None:
    clock = FakeClock()
    run_replay(memory(3), ReplayPlan(rate=0.5), Sink(), clock=clock)
    assert clock.sleeps == pytest.approx([0.2, 0.2])


def test_loop_keeps_seq_and_stamps_increasing_across_passes() -> None:
    sink = Sink()
    stats = run_replay(memory(3), ReplayPlan(rate=None, loop=True, passes=3), sink, clock=FakeClock())
    seqs = [s for _, s, _ in sink.out]
    stamps = [t for _, _, t in sink.out]
    assert seqs == list(range(9))
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert stamps[3] - stamps[2] == 100 * MS  # the next pass starts one period later
    assert stats.passes == 3


def test_wall_stamps_make_a_restarted_replay_go_on_in_time_where_recorded_stamps_rewind() -> None:
    """Two runs of the same replay, the second started (as supervisord would) 0.5 s after the first ended:
    seq begins again either way; on wall stamps time goes on (a restarted source), on recorded ones it goes back."""
    wall = [1_700_000_000 * 10**9]
    runs = {}
    for stamps in ("recorded", "wall"):
        out = []
        for _ in range(2):
            sink = Sink()
            clock = FakeClock()
            t_start = clock.now()
            run_replay(memory(5), ReplayPlan(rate=1.0, stamps=stamps), sink, clock=clock, wall_ns=lambda: wall[0])
            wall[0] += int((clock.now() - t_start + 0.5) * 1e9)  # the run took its paced time, then a restart
            out.append(sink.out)
        runs[stamps] = out
    for stamps, (first, second) in runs.items():
        assert [s for _, s, _ in second] == [0, 1, 2, 3, 4]
        assert [b[2] - a[2] for a, b in zip(second, second[1:])] == [100 * MS] * 4  # recorded spacing kept
    assert runs["recorded"][1][0][2] < runs["recorded"][0][-1][2]
    assert runs["wall"][1][0][2] > runs["wall"][0][-1][2]
    assert runs["wall"][1][0][2] - runs["wall"][0][-1][2] == pytest.approx(500 * MS, abs=MS)  # the restart gap


def test_start_and_limit_select_a_window_per_pass() -> None:
    sink = Sink()
    run_replay(memory(10), ReplayPlan(rate=None, start=4, limit=3, loop=True, passes=2), sink, clock=FakeClock())
    assert [o for o, _, _ in sink.out] == ["mem#4", "mem#5", "mem#6"] * 2
    assert [s for _, s, _ in sink.out] == list(range(6))


def test_seq_start_offsets_the_numbering() -> None:
    sink = Sink()
    run_replay(memory(2), ReplayPlan(rate=None, seq_start=41), sink, clock=FakeClock())
    assert [s for _, s, _ in sink.out] == [41, 42]


def test_skip_counts_bad_frames_names_them_and_goes_on() -> None:
    sink = Sink()
    seen: list[FrameError] = []
    stats = run_replay(memory(5, errors=(1, 3)), ReplayPlan(rate=None), sink, clock=FakeClock(), on_error=seen.append)
    assert [o for o, _, _ in sink.out] == ["mem#0", "mem#2", "mem#4"]
    assert [s for _, s, _ in sink.out] == [0, 1, 2]  # no gaps for skipped frames
    assert stats.errors == 2 and stats.error_origins == ["bad1.bin", "bad3.bin"]
    assert [str(e) for e in seen] == ["bad1.bin: corrupt", "bad3.bin: corrupt"]
    assert stats.stopped_by is None


def test_stop_policy_ends_at_the_first_bad_frame() -> None:
    sink = Sink()
    stats = run_replay(memory(5, errors=(2,)), ReplayPlan(rate=None, on_error="stop"), sink, clock=FakeClock())
    assert [o for o, _, _ in sink.out] == ["mem#0", "mem#1"]
    assert stats.stopped_by is not None and stats.stopped_by.origin == "bad2.bin"


def test_looping_a_recording_with_no_readable_frame_terminates() -> None:
    stats = run_replay(memory(3, errors=(0, 1, 2)), ReplayPlan(rate=None, loop=True), Sink(), clock=FakeClock())
    assert stats.published == 0 and stats.errors == 3 and stats.passes == 1


def test_start_past_the_end_is_a_source_error() -> None:
    with pytest.raises(SourceError, match="--start 7 is past the end"):
        run_replay(memory(3), ReplayPlan(rate=None, start=7), Sink(), clock=FakeClock())


def test_a_reader_that_raises_becomes_one_error_naming_the_source() -> None:
    sink = Sink()
    seen: list[FrameError] = []
    stats = run_replay(ExplodingSource(), ReplayPlan(rate=None), sink, clock=FakeClock(), on_error=seen.append)
    assert len(sink.out) == 2
    assert stats.errors == 1 and seen[0].origin == "exploding" and "disk went away" in seen[0].reason


def test_stop_event_ends_a_looping_replay() -> None:
    stop = threading.Event()
    sink = Sink()

    def emit(frame: Frame, seq: int, stamp: int) -> None:
        sink(frame, seq, stamp)
        if seq == 6:
            stop.set()

    stats = run_replay(memory(3), ReplayPlan(rate=None, loop=True), emit, clock=FakeClock(), stop=stop)
    assert stats.interrupted and stats.published == 7


@pytest.mark.parametrize(
    "kwargs,match",
    [({"start": -1}, "--start"), ({"limit": 0}, "--limit"), ({"on_error": "ignore"}, "--on-error"), ({"passes": 0}, "passes")],
)
def test_plan_rejects_bad_values(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ReplayPlan(**kwargs)


def test_a_wall_stamped_loop_keeps_counting_and_every_frame_is_taken_downstream() -> None:
    """A pass of 3 frames, looped: seq and stamps go on, so the consumers' stream guard takes every frame. Each pass
    had begun seq again as a restarted source, which a pass shorter than a restart's confirmation (3 frames, 0.3 s)
    never got: the tracker and the classifier dropped every frame after the first pass."""
    from jitterguard.stream_order import StreamGuard

    sink = Sink()
    run_replay(memory(3), ReplayPlan(rate=None, loop=True, passes=5, stamps="wall"), sink, clock=FakeClock(),
               wall_ns=lambda: 1_700_000_000 * 10**9)
    assert [s for _, s, _ in sink.out] == list(range(15))
    stamps = [t for _, _, t in sink.out]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    guard, taken = StreamGuard(), 0
    for k, (_, s, t) in enumerate(sink.out):
        if guard.admit(s, t, now_s=k * 0.1).accepted:
            guard.accept(s, t)
            taken += 1
    assert taken == 15


def test_a_wall_stamped_loop_of_one_frame_keeps_counting() -> None:
    sink = Sink()
    run_replay(memory(1), ReplayPlan(rate=None, loop=True, passes=4, stamps="wall"), sink, clock=FakeClock(),
               wall_ns=lambda: 1_700_000_000 * 10**9)
    assert [s for _, s, _ in sink.out] == [0, 1, 2, 3]


class StallingSink(Sink):
    """A sink that stalls the clock for ``seconds`` once it has taken frame ``at_seq`` (a slow consumer)."""

    def __init__(self, clock: FakeClock, at_seq: int = 2, seconds: float = 2.0) -> None:
        super().__init__()
        self.clock, self.at_seq, self.seconds = clock, at_seq, seconds

    def __call__(self, frame: Frame, seq: int, stamp: int) -> None:
        super().__call__(frame, seq, stamp)
        if seq == self.at_seq:
            self.clock.advance(self.seconds)


def test_wall_stamps_follow_the_wall_clock_again_after_a_stall() -> None:
    """A 2 s stall at the third frame (a slow consumer, a paused process): the pacer gives up on catching up, and
    the stamps now catch up with the wall clock too — they had lagged it by every stall so far, so that a later
    restart jumped ahead by the sum (past 10 s, a jump rather than a restarted source downstream)."""
    clock = FakeClock()
    wall0 = 1_700_000_000 * 10**9
    wall = lambda: wall0 + int(round((clock.now() - 1000.0) * 1e9))  # noqa: E731

    sink = StallingSink(clock)
    run_replay(memory(8), ReplayPlan(rate=1.0, stamps="wall"), sink, clock=clock, wall_ns=wall)
    stamps = [t for _, _, t in sink.out]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    # every frame after the stall is stamped within one frame period of the wall clock at its publication
    assert abs(stamps[-1] - wall()) < 150 * MS
    assert stamps[3] - stamps[2] > 1900 * MS  # the stall shows in the stamps as it did on the wall


def test_a_stall_is_reported_as_it_happens() -> None:
    """The replay service counted `late` only once the replay returned; a looping replay (the stack's) never
    returns, so its heartbeats never showed a stall."""
    clock = FakeClock()
    seen_at: list[int] = []

    sink = StallingSink(clock)
    run_replay(memory(6), ReplayPlan(rate=1.0), sink, clock=clock, on_late=lambda: seen_at.append(len(sink.out)))
    assert seen_at == [3]  # during the run, at the frame after the stall


@pytest.mark.parametrize("on_error", ["skip", "stop"])
def test_a_frame_whose_ego_pose_no_reader_takes_is_an_unreadable_frame_not_the_end_of_the_replay(on_error) -> None:
    """A NaN odometry sample (or a PCD's VIEWPOINT) in the middle of a recording had ended the whole replay at that
    frame with a multi-line validation error, exit 1; a pose beyond the wire's limits went out for every consumer to
    refuse. Each is an unreadable frame now, skipped and counted (or the stop of ``--on-error stop``)."""
    bad_poses = [EgoPose(x=float("nan")), EgoPose(qw=float("inf")), EgoPose(y=1e30), EgoPose(qw=0.0)]
    frames = [scan(0)] + [replace(scan(1 + k), pose=pose) for k, pose in enumerate(bad_poses)] + [scan(5)]
    published: list[str] = []

    def emit(frame: Frame, seq: int, stamp: int) -> None:  # what the publisher does before its put
        encode(message_for(frame, seq, stamp))
        published.append(frame.origin)

    errors: list[FrameError] = []
    stats = run_replay(MemorySource(frames), ReplayPlan(rate=None, on_error=on_error), emit, clock=FakeClock(),
                       on_error=errors.append)
    if on_error == "stop":
        assert published == ["mem#0"] and stats.stopped_by is not None and stats.errors == 1
        return
    assert published == ["mem#0", "mem#5"]
    assert stats.errors == 4 and [e.origin for e in errors] == ["mem#1", "mem#2", "mem#3", "mem#4"]
    assert all("\n" not in str(e) and "ego" in str(e) for e in errors), errors


@pytest.mark.parametrize("suffix", [".bin", ".pcd"])
def test_one_scan_looped_goes_out_at_its_hz_not_at_10_hz(tmp_path, suffix: str) -> None:
    """``jitterguard replay one.bin --loop --hz 2``: a pass of one frame has no spacing of its own to measure, and
    the re-stamper had fallen back on 10 Hz whatever ``--hz`` said (stamps and sleeps 0.1 s apart)."""
    import numpy as np

    from jitterguard.services.replay.sources import SourceOptions, open_source

    path = tmp_path / f"one{suffix}"
    if suffix == ".bin":
        np.zeros((4, 4), dtype="<f4").tofile(path)
    else:
        path.write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2 3\n")
    clock = FakeClock()
    sink = Sink()
    with open_source(str(path), SourceOptions(rate_hz=2.0, period_ns=500 * MS)) as src:
        run_replay(src, ReplayPlan(rate=1.0, loop=True, passes=4), sink, clock=clock)
    assert [stamp for _, _, stamp in sink.out] == [0, 500 * MS, 1000 * MS, 1500 * MS]
    assert [seq for _, seq, _ in sink.out] == [0, 1, 2, 3]
    assert clock.sleeps == pytest.approx([0.5, 0.5, 0.5])


def test_a_scan_over_the_detectors_cap_is_refused_and_counted_as_the_unreadable_ones_are() -> None:
    """A scan whose ``points`` payload is over the detector's ``max_scan_bytes`` (64 MiB; from a bag or PCD of a
    dense sensor) had been published without a word, and the detector refused every one of them, unread. The replay
    holds each scan to that cap before it goes out: one line naming the scan and its size, skipped and counted like
    an unreadable frame (a recording none of whose frames fits is refused, as one none of whose frames reads)."""
    import numpy as np

    from jitterguard.services.replay.frames import scan_refusal

    big = replace(scan(1), points=np.zeros((300, 4), np.float32))  # 4,800 bytes of points
    frames = [scan(0), big, scan(2)]
    payload = len(encode(message_for(big, 0, big.stamp_ns)))
    assert scan_refusal(big, payload) is None and scan_refusal(big, payload - 1) is not None  # the payload, exact
    sink = Sink()
    errors: list[FrameError] = []
    stats = run_replay(MemorySource(frames), ReplayPlan(rate=None, max_scan_bytes=4096), sink, clock=FakeClock(),
                       on_error=errors.append)
    assert [o for o, _, _ in sink.out] == ["mem#0", "mem#2"] and stats.errors == 1
    [err] = errors
    assert err.origin == "mem#1" and "over" in err.reason and "max_scan_bytes" in err.reason, err


class StopsAfterSleeps(FakeClock):
    """A fake clock whose ``n``-th sleep is cut short by a stop (as Ctrl-C ends a real clock's wait)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def sleep(self, seconds: float) -> bool:
        super().sleep(seconds)
        return len(self.sleeps) < self.n


@pytest.mark.parametrize("frames,sleeps,want", [(1, 1, (1, 1)), (1, 3, (3, 3)), (3, 4, (4, 2))])
def test_a_looping_replay_stopped_counts_only_the_passes_that_published(frames: int, sleeps: int,
                                                                        want: tuple[int, int]) -> None:
    """A pass stopped while it waited for its first frame published nothing: a looped one-frame recording stopped
    after one frame had reported "1 frame(s) in 2 pass(es)". A pass stopped midway still counts (it published)."""
    stats = run_replay(memory(frames), ReplayPlan(rate=1.0, loop=True), Sink(), clock=StopsAfterSleeps(sleeps))
    assert stats.interrupted and (stats.published, stats.passes) == want


def test_stamps_the_timeline_could_not_keep_are_counted_as_they_happen_and_in_the_stats() -> None:
    """Out-of-order stamps (published 1 ns after the previous) and a clock stepping back had been fixed up in
    silence: a bag replayed with its stamps rewritten gave no sign of it."""
    frames = [scan(i, stamp_ns=stamp) for i, stamp in enumerate((0, 100 * MS, 50 * MS, 200 * MS, 10 * MS, 110 * MS))]
    seen: list[str] = []
    stats = run_replay(MemorySource(frames), ReplayPlan(rate=None), Sink(), clock=FakeClock(), on_restamped=seen.append)
    assert seen == ["stamps_reordered", "stamps_stepped_back"]
    assert (stats.reordered, stats.stepped_back) == (1, 1) and stats.as_dict()["reordered"] == 1
