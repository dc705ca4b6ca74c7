"""Pacing and re-stamping: pure logic, driven by an injectable clock so tests run on a fake one.

Replay publishes frame *i* at ``anchor_wall + (stamp_i - anchor_stamp) / rate``: the recording's own
spacing, sped up or slowed down by ``--rate``. ``--rate max`` never sleeps; the publisher's BLOCK
congestion control then makes it go exactly as fast as the consumer keeps up, with nothing dropped.

When replay falls behind (a slow disk, a blocked publisher) by more than ``max_lag_s`` it re-anchors on the
late frame instead of bursting to catch up, because a burst would hand downstream services a rate the
recording never had; each re-anchor is counted as ``late``.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections.abc import Callable
from typing import Protocol

from .frames import DEFAULT_PERIOD_NS


MIN_RATE = 1e-3
"""The slowest ``--rate``: a thousandth of real time (a 10 Hz recording at a frame every 100 s). 1e-300 had been
taken and never sent a second frame."""


def parse_rate(text: str) -> float | None:
    """``--rate``: a finite factor on the recorded rate of at least :data:`MIN_RATE`, written ``2`` or ``2x``, or
    ``max`` (returned as ``None``)."""
    t = text.strip().lower()
    if t in ("max", "inf", "unlimited"):
        return None
    try:
        value = float(t[:-1] if t.endswith("x") else t)  # one x: "2xx" had been read as 2
    except ValueError:
        raise ValueError(f"--rate must be a positive number (e.g. 1, 0.5, 2x) or 'max', got {text!r}") from None
    if not math.isfinite(value) or value < MIN_RATE:
        raise ValueError(f"--rate must be a number >= {MIN_RATE:g} (e.g. 1, 0.5, 2x) or 'max', got {text!r}")
    return value


class Clock(Protocol):
    """Time source for pacing. ``sleep`` returns False when interrupted by a stop request."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> bool: ...


class RealClock:
    """Monotonic wall clock whose sleep wakes at once when ``stop`` is set (Ctrl-C, service close)."""

    def __init__(self, stop: threading.Event | None = None) -> None:
        self._stop = stop or threading.Event()

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> bool:
        if seconds <= 0:
            return not self._stop.is_set()
        # a rate of 1e-12 asks for longer than any timer can wait (it had raised OverflowError after one frame)
        return not self._stop.wait(min(seconds, threading.TIMEOUT_MAX))


class Pacer:
    """Decides how long to wait before publishing a frame with a given (re-stamped) stamp."""

    def __init__(self, rate: float | None, clock: Clock, max_lag_s: float = 0.5) -> None:
        if rate is not None and not (rate > 0 and math.isfinite(rate)):
            raise ValueError(f"rate must be positive and finite, got {rate!r}")
        self.rate = rate
        self.clock = clock
        self.max_lag_s = max_lag_s
        self.late = 0
        self._anchor: tuple[float, int] | None = None

    def target(self, stamp_ns: int) -> float:
        """Wall time (clock seconds) at which ``stamp_ns`` is due; anchors on the first stamp seen."""
        if self._anchor is None:
            self._anchor = (self.clock.now(), stamp_ns)
        wall0, stamp0 = self._anchor
        assert self.rate is not None
        return wall0 + (stamp_ns - stamp0) / 1e9 / self.rate

    def anchor(self, stamp_ns: int) -> None:
        """Pace from now on as if ``stamp_ns`` were due now (the stamps were moved: :meth:`Restamper.catch_up`)."""
        self._anchor = (self.clock.now(), stamp_ns)

    def wait(self, stamp_ns: int) -> bool:
        """Sleep until ``stamp_ns`` is due. Returns False if the sleep was interrupted by a stop."""
        if self.rate is None:
            return True
        delay = self.target(stamp_ns) - self.clock.now()
        if delay > 0:
            return self.clock.sleep(delay)
        if -delay > self.max_lag_s:
            self.late += 1
            self._anchor = (self.clock.now(), stamp_ns)
        return True


class Restamper:
    """Maps recorded stamps to published ones: strictly increasing, continuous across ``--loop`` passes.

    Within a pass a stamp keeps its recorded value (shifted by the pass offset) unless it would not exceed the
    previous one (out-of-order bag stamps), in which case it becomes previous + 1 ns. A new pass starts one
    typical frame period (the median recorded spacing) after the last published stamp, so looping a 20 s
    recording yields one uninterrupted, monotonic timeline. A recorded stamp more than one such period behind the
    previous one is the recording's clock stepping back (a times.txt or bag whose clock was reset), not a reordered
    frame: the timeline goes on from there as a new pass does, the recording's spacing kept (the rest of the
    recording had been stamped 1 ns apart, and so published in one burst).

    With ``origin`` (``--stamps wall``: ``time.time_ns``) the timeline starts at ``origin()``, read when the
    first frame is stamped, instead of at the recorded stamp; the recorded spacing is kept. Published in real
    time, the stamps then follow the wall clock like a live sensor's, so a replay that is restarted goes on
    forward in time (a restarted source) instead of rewinding to the recording's first stamp.
    """

    def __init__(self, default_period_ns: int = DEFAULT_PERIOD_NS, origin: Callable[[], int] | None = None) -> None:
        self._origin = origin
        self._offset = 0
        self._last_in: int | None = None
        self._last_out: int | None = None
        self._diffs: list[int] = []
        self._new_pass = False
        self._default_period = default_period_ns
        self.reordered = 0
        """Stamps not after the previous one (out-of-order bag stamps), published 1 ns after it instead."""
        self.stepped_back = 0
        """Times the recording's clock stepped back by more than a period: the timeline went on as a new pass."""

    @property
    def period_ns(self) -> int:
        return int(statistics.median(self._diffs)) if self._diffs else self._default_period

    def begin_pass(self) -> None:
        """Call before the first frame of every pass after the first."""
        self._new_pass = True
        self._last_in = None

    def __call__(self, stamp_ns: int) -> int:
        if self._last_in is not None and stamp_ns > self._last_in and len(self._diffs) < 1000:
            self._diffs.append(stamp_ns - self._last_in)
        if self._last_out is None and self._origin is not None:
            self._offset = int(self._origin()) - stamp_ns
        if self._last_in is not None and self._last_in - stamp_ns > self.period_ns:  # the clock stepped back
            self._new_pass = True
            self.stepped_back += 1
        if self._new_pass and self._last_out is not None:
            self._offset = self._last_out + self.period_ns - stamp_ns
            self._new_pass = False
        out = stamp_ns + self._offset
        if self._last_out is not None and out <= self._last_out:
            out = self._last_out + 1
            self.reordered += 1
        out = max(out, 0)
        self._last_in = stamp_ns
        self._last_out = out
        return out

    def catch_up(self, lag_ns: int) -> int:
        """Move the timeline ``lag_ns`` forward (``--stamps wall`` after a stall the pacer gave up on: the stamps
        follow the wall clock again instead of lagging it by every stall so far) and return the last stamp so
        moved."""
        if lag_ns > 0 and self._last_out is not None:
            self._offset += lag_ns
            self._last_out += lag_ns
        return self._last_out if self._last_out is not None else 0
