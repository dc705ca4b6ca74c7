"""Telling a late frame from a restarted source, from its header alone (``seq``, ``stamp``). Pure, no I/O.

Every consumer of a frame stream (the tracker on ``detections``, the classifier on ``tracked``) must drop
duplicates and frames that arrive late, yet follow a source that started over. Within one stream both ``seq``
and ``stamp`` increase, so a frame's header, compared with the newest frame accepted, says which case it is:

* ``NEXT``: seq and stamp went on (an equal stamp under a higher seq too).
* ``DUPLICATE``: the same seq, not newer.
* ``RESTARTED``: seq went back (or stood) while the stamp went *forward*: a source whose seq began again
  while time went on — a restarted sensor driver, or a replay stamping on the wall clock. A late frame
  can never be newer than the frame that followed it, so this needs no confirmation: accept it at once.
* ``REWOUND``: the stamp went back by more than the rewind threshold (a recording that started over), or
  :class:`BehindRun` saw the stream persist behind us (see below). Time went back: reset and accept.
* ``LATE``: anything else behind the newest frame (reordered or re-sent): drop and count.

A restarted *recording* is the ambiguous case: it starts again at seq 0 with the very stamps it had the first
time, so its first frame is bit for bit a late re-send of the old stream's first frame. What tells them apart is
persistence: a re-sent frame is a one-off between current frames, a restarted source keeps publishing behind
us and nothing newer comes. :class:`BehindRun` counts such frames in a row, each newer than the one before;
``confirm_frames`` of them (3 by default, 0.3 s at 10 Hz) confirm the rewind.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

DEFAULT_CONFIRM_FRAMES = 3
"""Frames in a row behind the stream (each after the previous) that prove the source went back in time."""


class Verdict(str, Enum):
    """What a frame is relative to the newest frame accepted (see the module docstring)."""

    NEXT = "next"
    DUPLICATE = "duplicate"
    LATE = "late"
    RESTARTED = "restarted"
    REWOUND = "rewound"

    @property
    def accepted(self) -> bool:
        return self in (Verdict.NEXT, Verdict.RESTARTED, Verdict.REWOUND)


def judge(seq: int, stamp_ns: int, last_seq: int | None, last_stamp_ns: int | None,
          rewind_reset_ns: float = 0.0) -> Verdict:
    """Classify a frame by its header against the newest accepted one (``None``: nothing accepted yet).

    ``rewind_reset_ns`` > 0: a stamp this much older than the newest means the source rewound (0 disables).
    Never returns ``REWOUND`` for a short step back: that takes :class:`BehindRun`'s confirmation.
    """
    if last_seq is None or last_stamp_ns is None:
        return Verdict.NEXT
    if stamp_ns > last_stamp_ns:
        return Verdict.NEXT if seq > last_seq else Verdict.RESTARTED
    if seq == last_seq:
        return Verdict.DUPLICATE
    if rewind_reset_ns > 0 and last_stamp_ns - stamp_ns > rewind_reset_ns:
        return Verdict.REWOUND
    if stamp_ns == last_stamp_ns and seq > last_seq:
        return Verdict.NEXT
    return Verdict.LATE


@dataclass
class BehindRun:
    """Frames that arrived behind the stream, one after another: after ``confirm_frames`` of them, each after
    the previous in both seq and stamp and with nothing accepted in between, the source itself went back.

    ``confirm_frames`` 0 disables the rule (a short rewind then waits until the stamps pass the old ones).
    """

    confirm_frames: int = DEFAULT_CONFIRM_FRAMES
    length: int = 0
    _seq: int = 0
    _stamp_ns: int = 0

    def behind(self, seq: int, stamp_ns: int) -> bool:
        """Note one frame judged ``LATE``; True when it completes a run (the run then starts afresh)."""
        if self.confirm_frames <= 0:
            return False
        if self.length and seq > self._seq and stamp_ns > self._stamp_ns:
            self.length += 1
        else:
            self.length = 1
        self._seq, self._stamp_ns = seq, stamp_ns
        if self.length >= self.confirm_frames:
            self.length = 0
            return True
        return False

    def clear(self) -> None:
        """A frame was accepted: whatever was behind it was late after all."""
        self.length = 0
