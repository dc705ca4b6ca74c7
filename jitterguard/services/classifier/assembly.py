"""Frame assembly: pair the tracker's per-track observations with the message that closes their frame.

Zenoh gives no ordering between two subscribers, so ``tracks/{id}`` samples of frame *s* may arrive after
the ``tracked`` message that closes *s*. The closing message lists the IDs it expects; a frame is complete
when all of them are in, or when the straggler timeout has passed since its close arrived (then the missing
ones are counted). Which closes are taken at all — duplicates, late frames, jumps, a restarted tracker — is the
:class:`~jitterguard.stream_order.StreamGuard`'s call. Pure: the caller passes the clock.

The assembler only looks at a frame's seq and track IDs; what it stores per observation and per close is the
caller's business (``*_item`` methods): the adapter stores the few numbers the core needs per observation and
the ``tracked`` columns.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from ...stream_order import StreamGuard, Verdict

RESTART_GAP = 20
"""A closing seq this far below the last one means the tracker restarted (its seq began again)."""

O = TypeVar("O")  # noqa: E741  what is stored per observation
C = TypeVar("C")  # what is stored per close


@dataclass
class CompleteFrame(Generic[O, C]):
    seq: int
    tracked: C
    observations: list[O]  # in the order of the close's list (the tracker's), whatever order they arrived in
    received_at: float  # when the closing message arrived (for latency)
    missing: int  # expected observations that never came


@dataclass
class FrameAssembler(Generic[O, C]):
    straggler_timeout_s: float = 0.05
    max_pending_frames: int = 64
    max_frame_observations: int = 1000
    """Observations kept per frame (the adapter passes ``limits.max_objects``: no frame has more objects, so no more
    observed tracks). Beyond it a new track ID is dropped, counted ``excess_observations``: the frames were bounded
    in number only, and a flood of made-up track IDs under a few seqs no close ever comes for grew without end
    (~0.5 kB each)."""
    last_done: int = -1
    last_done_stamp: int | None = None
    counts: dict[str, int] = field(default_factory=dict)
    _obs: dict[int, dict[str, O]] = field(default_factory=dict)
    _closes: dict[int, tuple[C, float, tuple[str, ...], int]] = field(default_factory=dict)  # IDs in the close's order
    _waiting: dict[int, set[str]] = field(default_factory=dict)  # per closed seq: expected IDs not yet in
    guard: StreamGuard = field(default_factory=StreamGuard)  # over the closes: which frames to take

    def is_late(self, seq: int, stamp_ns: int | None = None) -> bool:
        """An observation for a frame already processed: it would be dropped, so it need not be validated.

        Lets a service that fell behind skip validating stragglers it cannot use (a seq far below the last
        one is an upstream restart, not late; so is one stamped after the last frame decided — a source whose seq
        began again while time went on, whose observations had been dropped as late until the restart was
        confirmed).
        """
        if stamp_ns is not None and self.last_done_stamp is not None and stamp_ns > self.last_done_stamp:
            return False
        return seq <= self.last_done and self.last_done - seq <= RESTART_GAP

    def count(self, name: str, n: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + n

    def add_observation_item(self, seq: int, track_id: str, item: O, stamp_ns: int | None = None) -> None:
        """Register what the caller keeps of the observation of ``track_id`` in frame ``seq`` (stamped
        ``stamp_ns``)."""
        if self.is_late(seq, stamp_ns):
            self.count("late_observations")
            return
        bucket = self._obs.setdefault(seq, {})
        if track_id in bucket:  # a frame has one observation per track: the first stands (a re-sent copy or a
            self.count("duplicate_observations")  # forgery after it must not rewrite the window)
            return
        if len(bucket) >= self.max_frame_observations:
            self.count("excess_observations")
            return
        bucket[track_id] = item
        waiting = self._waiting.get(seq)
        if waiting is not None:
            waiting.discard(track_id)
        if len(self._obs) > self.max_pending_frames:  # closes that never come must not grow memory
            victim = self._eviction_victim()
            lost = self._obs.pop(victim)
            self.count("orphaned_observations", len(lost))
            if victim in self._closes:  # only when every open frame is closed: counted missing when it is decided
                self._waiting[victim].update(set(lost) & set(self._closes[victim][2]))

    def _eviction_victim(self) -> int:
        """The frame whose observations go when too many frames are open: one whose close has not come, the seq
        farthest from the last close taken (ties: the later; no close yet: the first begun). Only when every open
        frame is closed (a worker far behind) does the first begun go, its observations then counted missing when
        it is decided (a closed frame's lost observations had been counted nowhere).

        A publisher allowed one track's key can open a frame per seq it makes up, one observation each. The first
        begun had gone: 65 made-up future seqs a frame evicted every real frame's observations before its close,
        and frames were decided with none of them and none counted missing (0 ``motion`` in 40 frames, health
        ``ok``). The frames the tracker is closing now lie next to its last close; made-up ones can crowd them
        only by lying nearer, and near ones are the seqs real frames will use anyway (one observation each)."""
        open_ = [s for s in self._obs if s not in self._closes]
        if not open_:
            return next(iter(self._obs))
        ref = self.guard.last_seq
        if ref is None:
            return open_[0]
        return max(open_, key=lambda s: (abs(s - ref), s))

    def admit(self, seq: int, stamp_ns: int, now: float | None = None) -> Verdict:
        """Judge a frame-closing header (:mod:`jitterguard.stream_order`) before its payload is read; a dropped
        one is counted (``duplicate_or_late_frames``, or ``held_jumps`` for a jump not yet confirmed)."""
        verdict = self.guard.admit(seq, stamp_ns, now)
        if verdict is Verdict.JUMP:
            self.count("held_jumps")
        elif not verdict.accepted:
            self.count("duplicate_or_late_frames")
        return verdict

    def add_close_item(self, seq: int, expected_ids: Iterable[str], item: C, now: float, stamp_ns: int,
                       verdict: Verdict | None = None) -> bool:
        """Register a frame-closing message; returns False (and counts) when it is dropped. ``verdict``: what
        :meth:`admit` already said of its header. A confirmed rewind of the upstream (time going back) resets the
        frames in flight and the caller learns it through ``counts['upstream_restarts']`` (its windows go too); a
        confirmed restart (seq back, time going on: a restarted driver or detector under a tracker that keeps its
        tracks) resets the frames in flight only, counted ``source_restarts``; a confirmed jump ahead is counted
        ``jumps`` and followed."""
        if verdict is None:
            verdict = self.admit(seq, stamp_ns, now)
        if not verdict.accepted:
            return False
        if verdict in (Verdict.RESTARTED, Verdict.REWOUND):
            self.count("upstream_restarts" if verdict is Verdict.REWOUND else "source_restarts")
            self.last_done = -1
            self._obs = {s: b for s, b in self._obs.items() if s <= seq + RESTART_GAP}
            self._closes.clear()
            self._waiting.clear()
        elif verdict is Verdict.JUMPED:
            self.count("jumps")
        self.guard.accept(seq, stamp_ns)
        expected = tuple(dict.fromkeys(expected_ids))  # the close's order, each ID once
        self._closes[seq] = (item, now, expected, stamp_ns)
        got = self._obs.get(seq, {})
        self._waiting[seq] = {i for i in expected if i not in got}
        return True

    def pop_ready(self, now: float, *, give_up: bool = True) -> list[CompleteFrame[O, C]]:
        """Frames that are complete or timed out, in seq order; older pending frames are flushed first.

        ``give_up=False``: release complete frames only. For a caller that has not yet read everything that
        arrived (its own backlog may hold the stragglers), so a frame is not given up on for its lateness.
        """
        out: list[CompleteFrame[O, C]] = []
        for seq in sorted(self._closes):
            item, t0, wanted, stamp = self._closes[seq]
            missing = len(self._waiting[seq])
            if missing and (not give_up or now - t0 < self.straggler_timeout_s):
                break  # keep order: later frames wait behind this one
            del self._closes[seq]
            del self._waiting[seq]
            bucket = self._obs.pop(seq, {})
            # in the tracker's order, not the order Zenoh delivered them: new tracks get their rows, and filled
            # windows their turn in the calibration's learning, as in any other run of the same frames (offline too)
            observations = [bucket[i] for i in wanted if i in bucket]
            if len(observations) != len(bucket):
                self.count("unexpected_observations", len(bucket) - len(observations))
            for stale in [s for s in self._obs if s < seq]:
                self.count("orphaned_observations", len(self._obs.pop(stale)))
            if missing:
                self.count("missing_observations", missing)
            self.last_done, self.last_done_stamp = seq, stamp
            out.append(CompleteFrame(seq, item, observations, t0, missing))
        return out

    @property
    def pending(self) -> int:
        return len(self._closes)
