"""Which frames of a stream to take, from their headers alone (``seq``, ``stamp``). Pure: the caller passes the clock.

Every consumer of a frame stream (the tracker on ``detections``, the classifier on ``tracked``) must drop
duplicates and frames that arrive late, follow a source that started over or went quiet for a while, and never let
one message change its state: a stamp an hour ahead, a seq of 2^62 or a replayed capture is what a buggy upstream or
an intruder sends. A frame *follows* the newest one taken when its seq is higher by at most ``max_seq_step`` and its
stamp is not older and newer by at most ``max_stamp_step_s``. Then it is:

* ``NEXT``: it follows; take it.
* ``DUPLICATE``: the same seq, not newer, or the same stamp as the newest taken under any seq (a scan of the same
  instant: sent twice, or a driver whose clock stands still — taken, such frames had left every tentative track
  unexpired, and the tracker's table grew without bound); drop it.
* anything else is a *discontinuity*, held back: ``LATE`` (behind the stream: a re-send, a replay) or ``JUMP``
  (ahead beyond the steps, or seq back with time going on) — dropped and counted, unless it confirms a run.

A run is a series of held frames each following the previous one, with nothing taken in between. A real
discontinuity keeps going — a restarted driver, a recording started over, a sensor back after a long gap — while
the old stream has stopped; a forged or replayed frame is a one-off between current ones, and a flood of them
still never outlasts the live stream's next frame. So ``confirm_frames`` frames in a run spanning at least
``confirm_s`` on the receiver's clock confirm it, and the frame that does is taken as:

* ``REWOUND`` (its stamp is behind the stream: the state is reset), ``RESTARTED`` (seq back, time going on: the
  state carries on) or ``JUMPED`` (ahead: the state carries on, and ages by the gap).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from pydantic import BaseModel, ConfigDict, Field


class StreamLimits(BaseModel):
    """How far a frame may step from the last one taken, and what confirms a discontinuity."""

    # strict: `true` or "5" is no count (a config file's `limits:` / `stream:` had read them as 1 and 5)
    model_config = ConfigDict(extra="forbid", strict=True)

    max_stamp_step_s: float = Field(
        10.0, gt=0.0, le=86400.0, description="a stamp further ahead than this is a jump, taken only once confirmed")
    max_seq_step: int = Field(1000, ge=1, description="a seq further ahead than this is a jump, taken only once confirmed")
    confirm_frames: int = Field(3, ge=1, le=100, description="held frames in a run, each following the previous,"
                                " that confirm a discontinuity (a restart, a rewind, a jump)")
    confirm_s: float = Field(0.3, ge=0.0, le=60.0, description="how long (receiver's clock) such a run must last,"
                             " with nothing from the old stream in between")


class Verdict(str, Enum):
    """What a frame is relative to the stream (see the module docstring)."""

    NEXT = "next"
    DUPLICATE = "duplicate"
    LATE = "out_of_order"
    JUMP = "jump"
    RESTARTED = "restarted"
    REWOUND = "rewound"
    JUMPED = "jumped"

    @property
    def accepted(self) -> bool:
        return self not in (Verdict.DUPLICATE, Verdict.LATE, Verdict.JUMP)


@dataclass
class StreamGuard:
    """The newest frame taken and the run of held frames behind or ahead of it. :meth:`admit` judges a header;
    the caller :meth:`accept` s a frame once it has processed it (a frame whose body is invalid is not taken)."""

    limits: StreamLimits = field(default_factory=StreamLimits)
    last_seq: int | None = None
    last_stamp_ns: int | None = None
    _run: tuple[int, int] | None = None  # the last held frame of the run
    _run_len: int = 0
    _run_since: float | None = None

    def follows(self, seq: int, stamp_ns: int, after_seq: int, after_stamp_ns: int) -> bool:
        step_ns = self.limits.max_stamp_step_s * 1e9
        return after_seq < seq <= after_seq + self.limits.max_seq_step and 0 < stamp_ns - after_stamp_ns <= step_ns

    def admit(self, seq: int, stamp_ns: int, now_s: float | None = None) -> Verdict:
        """Judge one header; a held frame extends (or starts) the run. ``now_s`` None: no time condition."""
        if self.last_seq is None or self.last_stamp_ns is None:
            return Verdict.NEXT
        if self.follows(seq, stamp_ns, self.last_seq, self.last_stamp_ns):
            return Verdict.NEXT
        if (seq == self.last_seq and stamp_ns <= self.last_stamp_ns) or stamp_ns == self.last_stamp_ns:
            return Verdict.DUPLICATE
        if self._run is not None and self.follows(seq, stamp_ns, *self._run):
            self._run_len += 1
        else:
            self._run_len, self._run_since = 1, now_s
        self._run = (seq, stamp_ns)
        lasted = now_s is None or self._run_since is None or now_s - self._run_since >= self.limits.confirm_s
        if self._run_len >= self.limits.confirm_frames and lasted:
            if stamp_ns < self.last_stamp_ns:
                return Verdict.REWOUND
            return Verdict.RESTARTED if seq <= self.last_seq else Verdict.JUMPED
        return Verdict.LATE if stamp_ns <= self.last_stamp_ns else Verdict.JUMP

    def accept(self, seq: int, stamp_ns: int) -> None:
        """The frame was taken: it is the stream's newest, and whatever was held is history."""
        self.last_seq, self.last_stamp_ns = seq, stamp_ns
        self._run, self._run_len, self._run_since = None, 0, None

    def reset(self) -> None:
        """Forget the stream (the next frame is taken as the first)."""
        self.last_seq = self.last_stamp_ns = None
        self._run, self._run_len, self._run_since = None, 0, None
