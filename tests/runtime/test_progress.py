"""ProgressMonitor: health as progress, from the times the caller passes (no clock)."""

from __future__ import annotations

from jitterguard.runtime.progress import FAILING, OK, STALLED, ProgressMonitor, ProgressPolicy

POLICY = ProgressPolicy(stall_s=5.0, failing_frames=3)


def test_no_input_is_not_a_fault() -> None:
    m = ProgressMonitor(POLICY)
    assert m.assess(0.0).state == OK and m.assess(1e6).state == OK


def test_input_answered_in_time_is_ok_and_waiting_input_becomes_a_stall() -> None:
    m = ProgressMonitor(POLICY)
    m.input(10.0)
    m.input(11.0)  # a second input does not move the start of the wait
    assert m.assess(14.9).state == OK
    h = m.assess(15.0)
    assert h.state == STALLED and "5.0 s" in h.reason and h.unhealthy_for_s == 0.0
    assert m.assess(22.0).unhealthy_for_s == 7.0  # the unhealthy clock runs from the first unhealthy verdict
    m.output(22.5)
    assert m.assess(23.0).state == OK
    m.input(30.0)
    h = m.assess(35.0)
    assert h.state == STALLED and h.unhealthy_for_s == 0.0  # a new episode starts afresh


def test_failures_in_a_row_are_failing_until_one_frame_goes_through() -> None:
    m = ProgressMonitor(POLICY)
    for t in (1.0, 2.0):
        m.input(t)
        m.failure(t, "MemoryError: 74.5 GiB")
    assert m.assess(2.5).state == OK  # two in a row: not yet
    m.failure(3.0, "MemoryError: 74.5 GiB")
    h = m.assess(3.0)
    assert h.state == FAILING and "last 3 frames" in h.reason and "MemoryError" in h.reason
    m.output(4.0)
    assert m.assess(4.0).state == OK
    m.failure(5.0, "x")
    m.failure(6.0, "x")
    assert m.assess(6.0).state == OK  # the count restarted at the output


def test_one_failed_frame_then_silence_is_no_stall() -> None:
    """The frame was dealt with (it raised); nothing waits after it. It had read as `stalled` 5 s later, and under
    the watchdog the service exited 70 for one bad frame."""
    m = ProgressMonitor()
    m.input(0.0)
    m.failure(0.01, "ValueError: bad frame")
    assert m.assess(16.0).state == "ok"
    for k in range(5):  # five in a row is still failing
        m.input(20.0 + k)
        m.failure(20.0 + k, "ValueError: bad frame")
    assert m.assess(30.0).state == "failing"
