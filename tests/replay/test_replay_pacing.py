"""Pacing and re-stamping on a fake clock: recorded spacing, --rate scaling, max, re-anchoring, loops."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jitterguard.services.replay.pacing import Pacer, Restamper, parse_rate
from replay.helpers import FakeClock

MS = 1_000_000


@pytest.mark.parametrize("text,expected", [("1", 1.0), ("0.5", 0.5), ("2x", 2.0), ("MAX", None), (" max ", None),
                                           ("0.001", 0.001)])
def test_parse_rate_accepts_factors_and_max(text: str, expected: float | None) -> None:
    assert parse_rate(text) == expected


@pytest.mark.parametrize("text", ["0", "-1", "fast", "nan", "inf1", "", "1e999",
                                  "2xx",  # had been read as 2
                                  "1e-300", "0.0009"])  # taken, and the second frame never came
def test_parse_rate_rejects_nonsense_with_the_flag_name(text: str) -> None:
    with pytest.raises(ValueError, match="--rate"):
        parse_rate(text)


def test_pacer_reproduces_recorded_spacing_at_rate_one() -> None:
    clock = FakeClock()
    pacer = Pacer(1.0, clock)
    for stamp in (0, 100 * MS, 250 * MS, 300 * MS):
        assert pacer.wait(stamp)
    assert clock.sleeps == pytest.approx([0.1, 0.15, 0.05])


def test_pacer_rate_two_halves_every_wait() -> None:
    clock = FakeClock()
    pacer = Pacer(2.0, clock)
    for stamp in (0, 100 * MS, 200 * MS):
        pacer.wait(stamp)
    assert clock.sleeps == pytest.approx([0.05, 0.05])


def test_pacer_max_never_sleeps() -> None:
    clock = FakeClock()
    pacer = Pacer(None, clock)
    for stamp in range(0, 10**10, 10**9):
        assert pacer.wait(stamp)
    assert clock.sleeps == []


def test_pacer_counts_processing_time_against_the_wait() -> None:
    clock = FakeClock()
    pacer = Pacer(1.0, clock)
    pacer.wait(0)
    clock.advance(0.03)  # publishing took 30 ms
    pacer.wait(100 * MS)
    assert clock.sleeps == pytest.approx([0.07])


def test_pacer_reanchors_instead_of_bursting_when_far_behind() -> None:
    clock = FakeClock()
    pacer = Pacer(1.0, clock, max_lag_s=0.5)
    pacer.wait(0)
    clock.advance(2.0)  # stalled for 2 s
    pacer.wait(100 * MS)  # 1.9 s late: re-anchor, no sleep
    assert pacer.late == 1
    pacer.wait(200 * MS)  # back on the recorded spacing from the new anchor
    assert clock.sleeps == pytest.approx([0.1])


def test_pacer_small_lag_is_caught_up_without_reanchoring() -> None:
    clock = FakeClock()
    pacer = Pacer(1.0, clock, max_lag_s=0.5)
    pacer.wait(0)
    clock.advance(0.15)
    pacer.wait(100 * MS)
    pacer.wait(200 * MS)
    assert pacer.late == 0
    assert clock.sleeps == pytest.approx([0.05])


def test_restamper_keeps_recorded_stamps_in_the_first_pass() -> None:
    r = Restamper()
    assert [r(s) for s in (5 * MS, 105 * MS, 205 * MS)] == [5 * MS, 105 * MS, 205 * MS]


def test_restamper_continues_the_timeline_across_loops() -> None:
    r = Restamper()
    first = [r(s) for s in (1000 * MS, 1100 * MS, 1200 * MS)]
    r.begin_pass()
    second = [r(s) for s in (1000 * MS, 1100 * MS, 1200 * MS)]
    assert first == [1000 * MS, 1100 * MS, 1200 * MS]
    assert second == [1300 * MS, 1400 * MS, 1500 * MS]  # one median period after the last stamp


def test_restamper_on_wall_time_starts_at_the_origin_read_at_the_first_frame_and_keeps_the_spacing() -> None:
    reads: list[int] = []

    def wall() -> int:
        reads.append(1)
        return 1_700_000_000 * 10**9

    r = Restamper(origin=wall)
    assert not reads  # read when the first frame is stamped, not before (the replay may wait for subscribers)
    first = [r(s) for s in (5 * MS, 105 * MS, 255 * MS)]
    r.begin_pass()
    second = [r(s) for s in (5 * MS, 105 * MS)]
    t0 = 1_700_000_000 * 10**9
    assert first == [t0, t0 + 100 * MS, t0 + 250 * MS]
    assert second == [t0 + 375 * MS, t0 + 475 * MS]  # loops go on from there, one median period later
    assert len(reads) == 1


def test_restamper_forces_out_of_order_stamps_forward() -> None:
    r = Restamper()
    out = [r(s) for s in (100, 300, 200, 200, 400)]
    assert out == [100, 300, 301, 302, 400]
    assert (r.reordered, r.stepped_back) == (2, 0)  # counted: they had been moved without a word



def test_a_recording_whose_clock_steps_back_goes_on_at_its_own_spacing_not_1_ns_apart() -> None:
    """times.txt (or a bag) whose clock was reset an hour back after three frames: the frames after the step had
    been stamped 1 ns apart — published in one burst, a tracker's velocities divided by a nanosecond. The step is a
    discontinuity of the recording's clock: the timeline goes on one period later, the recorded spacing kept."""
    hour = 3600 * 10**9
    r = Restamper()
    out = [r(s) for s in (hour, hour + 100 * MS, hour + 200 * MS, 300 * MS, 400 * MS, 500 * MS)]
    assert out == [hour + k * 100 * MS for k in range(6)]
    assert (r.reordered, r.stepped_back) == (0, 1)
    r.begin_pass()  # a loop's new pass is no step of the recording's clock
    r(hour)
    assert r.stepped_back == 1

@settings(max_examples=200, deadline=None)
@given(
    passes=st.lists(st.lists(st.integers(min_value=0, max_value=10**12), min_size=1, max_size=20), min_size=1, max_size=5)
)
def test_restamper_output_is_strictly_increasing_whatever_the_input(passes: list[list[int]]) -> None:
    r = Restamper()
    out: list[int] = []
    for i, stamps in enumerate(passes):
        if i:
            r.begin_pass()
        out.extend(r(s) for s in stamps)
    assert all(b > a for a, b in zip(out, out[1:]))
    assert all(s >= 0 for s in out)
