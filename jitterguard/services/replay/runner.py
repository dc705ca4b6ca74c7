"""The replay loop, without Zenoh: window (``--start``/``--limit``), loop, re-stamp, pace, number, emit.

Kept apart from the publisher so that every rule here — seq strictly increasing across loops, stamps
re-stamped monotonically, skip-and-count versus stop on a corrupt frame, stop requests honoured mid-sleep —
is tested with a fake clock and a list as the sink.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Literal

from .frames import DEFAULT_PERIOD_NS, MAX_SCAN_BYTES, Frame, FrameError, Item, pose_refusal, scan_refusal
from .pacing import Clock, Pacer, RealClock, Restamper
from .sources.base import Source, past_end

OnError = Literal["skip", "stop"]
Stamps = Literal["recorded", "wall"]
Emit = Callable[[Frame, int, int], None]
"""``emit(frame, seq, stamp_ns)``: publish one frame under the given header seq and (re-stamped) stamp."""


@dataclass(frozen=True)
class ReplayPlan:
    """What to replay and how fast. ``rate=None`` is ``--rate max``."""

    rate: float | None = 1.0
    loop: bool = False
    passes: int | None = None
    """With ``loop``: stop after this many passes (None: until stopped)."""
    start: int = 0
    limit: int | None = None
    on_error: OnError = "skip"
    seq_start: int = 0
    max_lag_s: float = 0.5
    stamps: Stamps = "recorded"
    """``recorded``: the recording's stamps (shifted forward across loop passes); ``wall``: the first frame is
    stamped with the wall clock and the rest keep the recorded spacing after it (see :class:`Restamper`).

    Looping, seq keeps counting and stamps keep going on across passes, on either kind of stamps: every frame
    follows the one before (:mod:`jitterguard.stream_order`). The jump back to the start of the recording is a
    discontinuity of the world (objects and ego teleport) that the tracker's gates absorb: a parked object stands
    where it stood and keeps its track and window, a mover far from where it started gets a new track. (Until 3
    Dec 2026 a wall-stamped pass began seq again as a restarted source; a pass shorter than the confirmation of
    a restart — 3 frames and 0.3 s at the consumer — was then dropped by the tracker and the classifier, pass after
    pass, forever.)"""
    max_scan_bytes: int = MAX_SCAN_BYTES
    """A scan whose ``points`` payload is larger is an unreadable frame (:func:`~.frames.scan_refusal`): the
    detector refuses it unread."""

    def __post_init__(self) -> None:
        if self.start < 0:
            raise ValueError(f"--start must be >= 0, got {self.start}")
        if self.limit is not None and self.limit < 1:
            raise ValueError(f"--limit must be >= 1, got {self.limit}")
        if self.passes is not None and self.passes < 1:
            raise ValueError(f"passes must be >= 1, got {self.passes}")
        if self.on_error not in ("skip", "stop"):
            raise ValueError(f"--on-error must be 'skip' or 'stop', got {self.on_error!r}")
        if self.stamps not in ("recorded", "wall"):
            raise ValueError(f"--stamps must be 'recorded' or 'wall', got {self.stamps!r}")


@dataclass
class ReplayStats:
    """What a replay did; ``stopped_by`` is set when ``on_error='stop'`` ended it on a bad frame."""

    published: int = 0
    errors: int = 0
    passes: int = 0
    late: int = 0
    reordered: int = 0
    """Recorded stamps not after the previous one, published 1 ns after it."""
    stepped_back: int = 0
    """Times the recording's clock stepped back more than a frame period (the timeline went on as a new pass)."""
    last_seq: int = -1
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    interrupted: bool = False
    stopped_by: FrameError | None = None
    error_origins: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return {
            "published": self.published,
            "errors": self.errors,
            "passes": self.passes,
            "late": self.late,
            "reordered": self.reordered,
            "stepped_back": self.stepped_back,
            "last_seq": self.last_seq,
            "interrupted": self.interrupted,
            "stopped_by": str(self.stopped_by) if self.stopped_by else None,
        }


def _window(source: Source, start: int, limit: int | None) -> Iterator[Item]:
    """One pass over ``source``: at most ``limit`` positions from ``start``; a reader crash becomes an error item.

    A source is meant to yield :class:`FrameError` for bad frames; if its generator raises anyway (an I/O
    error it did not foresee), the pass ends with one error item naming the source instead of a traceback.
    """
    it = source.frames(start)
    n = 0
    while limit is None or n < limit:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as exc:  # a reader bug or an unforeseen I/O error: report, do not crash
            yield FrameError(source.info.name, f"reading failed after frame {start + n}: {type(exc).__name__}: {exc}")
            return
        n += 1
        yield item


def run_replay(
    source: Source,
    plan: ReplayPlan,
    emit: Emit,
    *,
    clock: Clock | None = None,
    stop: threading.Event | None = None,
    on_error: Callable[[FrameError], None] | None = None,
    on_published: Callable[[Frame, int], None] | None = None,
    wall_ns: Callable[[], int] = time.time_ns,
    on_late: Callable[[], None] | None = None,
    on_restamped: Callable[[str], None] | None = None,
) -> ReplayStats:
    """Replay ``source`` through ``emit`` according to ``plan`` and return what happened.

    ``wall_ns`` is the wall clock that ``plan.stamps == 'wall'`` starts the timeline at (injectable for tests);
    ``on_late`` is called at each stall the pacer gave up catching up on (as it happens: a looping replay never
    returns its stats); ``on_restamped`` with ``stamps_reordered`` or ``stamps_stepped_back`` at each recorded stamp
    the timeline could not keep (:class:`~.pacing.Restamper`), which had been fixed up without a word.
    Raises :class:`SourceError` if ``--start`` lies past the end of the recording (nothing to replay).
    """
    stop = stop or threading.Event()
    clock = clock or RealClock(stop)
    pacer = Pacer(plan.rate, clock, plan.max_lag_s)
    # a pass of one frame has no spacing to measure: the source's own (--hz) paces it, not 10 Hz whatever --hz said
    restamp = Restamper(source.info.period_ns or DEFAULT_PERIOD_NS, origin=wall_ns if plan.stamps == "wall" else None)
    stats = ReplayStats()
    seq = plan.seq_start
    good = 0
    while not stop.is_set():
        if stats.passes:
            restamp.begin_pass()
        positions = good = 0
        for item in _window(source, plan.start, plan.limit):
            positions += 1
            if stop.is_set():
                stats.interrupted = True
                break
            if not isinstance(item, FrameError):
                item = pose_refusal(item) or scan_refusal(item, plan.max_scan_bytes) or item
            if isinstance(item, FrameError):
                stats.errors += 1
                if len(stats.error_origins) < 100:
                    stats.error_origins.append(item.origin)
                if on_error:
                    on_error(item)
                if plan.on_error == "stop":
                    stats.stopped_by = item
                    stats.passes += 1
                    stats.late = pacer.late
                    stats.reordered, stats.stepped_back = restamp.reordered, restamp.stepped_back
                    return stats
                continue
            fixes = (restamp.reordered, restamp.stepped_back)
            stamp = restamp(item.stamp_ns)
            if on_restamped is not None and (restamp.reordered, restamp.stepped_back) != fixes:
                on_restamped("stamps_reordered" if restamp.reordered != fixes[0] else "stamps_stepped_back")
            late_before = pacer.late
            if not pacer.wait(stamp):
                stats.interrupted = True
                break
            if pacer.late != late_before:
                if on_late is not None:
                    on_late()
                if plan.stamps == "wall":  # a stall: the stamps go back to the wall clock
                    stamp = restamp.catch_up(wall_ns() - stamp)
                    pacer.anchor(stamp)
            emit(item, seq, stamp)
            good += 1
            stats.published += 1
            stats.last_seq = seq
            if stats.first_stamp_ns is None:
                stats.first_stamp_ns = stamp
            stats.last_stamp_ns = stamp
            if on_published:
                on_published(item, seq)
            seq += 1
        if not (stats.interrupted and good == 0):  # a pass stopped before its first frame was none: a looped
            stats.passes += 1                     # one-frame recording had said "1 frame(s) in 2 pass(es)"
        if stats.interrupted:
            break
        if positions == 0 and stats.passes == 1:
            raise past_end(plan.start, source.info)
        if not plan.loop or good == 0:  # a loop over a recording with no readable frame would spin forever
            break
        if plan.passes is not None and stats.passes >= plan.passes:
            break
    else:
        stats.interrupted = True
    stats.late = pacer.late
    stats.reordered, stats.stepped_back = restamp.reordered, restamp.stepped_back
    return stats
